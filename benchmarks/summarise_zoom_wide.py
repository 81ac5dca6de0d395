"""One line per rendered sweep from the printed output of ``bench_zoom_wide.py``.

``python benchmarks/summarise_zoom_wide.py OUT.txt [OUT.txt ...]``

Per file (the output of one ``bench_zoom_wide.py`` run, saved with ``> OUT.txt``): per-step
OpenCV's RMS z of cx and cy against the truth over the steps and its largest |z|; the zoom-wide
adjustment's largest |z| (cx, cy), largest |fx error| in % and largest cx, cy sigma in px; and
the long-end ratio (per-step OpenCV's principal-point sigma over zoom-wide's, cx/cy) at the two
longest steps.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def summarise(text: str) -> str:
    errors: dict[str, list[list[float]]] = {"opencv": [], "zoom-wide": []}
    ratios: dict[str, tuple[float, float]] = {}
    for line in text.splitlines():
        cols = line.split()
        if len(cols) == 10 and cols[0].startswith("fx_") and cols[1] in errors:
            errors[cols[1]].append([float(c) for c in cols[2:]])
        elif len(cols) == 6 and cols[0].startswith("fx_") and cols[1] == "zoom-wide":
            ratios[cols[0]] = (float(cols[2]), float(cols[3]))
    if not errors["opencv"] or len(ratios) < 2:
        raise SystemExit("no error table or long-end table in the output")
    opencv, zoom_wide = np.array(errors["opencv"]), np.array(errors["zoom-wide"])
    z_cv, z_zw = opencv[:, [4, 7]], zoom_wide[:, [4, 7]]       # z cx, z cy
    rms = np.sqrt(np.mean(z_cv**2, axis=0))
    long_end = "   ".join(f"{step} {cx:.2f}/{cy:.2f}" for step, (cx, cy) in ratios.items())
    return (f"opencv RMS z {rms[0]:.2f}/{rms[1]:.2f} max {np.abs(z_cv).max():.1f} | zoom-wide "
            f"max |z| {np.abs(z_zw).max():.1f} |dfx| {np.abs(zoom_wide[:, 0]).max():.2f} % "
            f"sd max {zoom_wide[:, [3, 6]].max():.2f} px | ratio {long_end}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outputs", nargs="+", type=Path)
    for path in ap.parse_args().outputs:
        print(f"{path.stem:>10s}  {summarise(path.read_text())}")


if __name__ == "__main__":
    main()
