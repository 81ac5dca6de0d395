"""A calibrated rendered sweep against its truth, per step and backend.

``python benchmarks/sweep_vs_truth.py OUT SWEEP``

``OUT``: a folder ``zoomcalib calibrate`` wrote (``calibration.json``); ``SWEEP``: the folder
``zoomcalib render-sweep`` wrote (``truth.json``). Prints per step and backend the errors of fx
(% and in reported sigmas), cx and cy (px and in reported sigmas), and per backend the largest
|z| and the RMS z over the steps.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(out: Path, sweep: Path) -> None:
    steps = json.loads((out / "calibration.json").read_text())["steps"]
    truth = {st["step"]: np.asarray(st["K"], float)
             for st in json.loads((sweep / "truth.json").read_text())["steps"]}
    z: dict[str, list] = {}
    print(f"{'step':>9s} {'backend':>9s} {'dfx %':>7s} {'z fx':>6s} {'dcx':>7s} {'z cx':>6s}"
          f" {'dcy':>7s} {'z cy':>6s}")
    for step, fits in steps.items():
        K_true = truth[step]
        for backend, fit in fits.items():
            K, sd = np.asarray(fit["K"], float), fit["sd"]
            err = {"fx": K[0, 0] - K_true[0, 0], "cx": K[0, 2] - K_true[0, 2],
                   "cy": K[1, 2] - K_true[1, 2]}
            zq = [err[q] / sd[q] for q in ("fx", "cx", "cy")]
            z.setdefault(backend, []).append(zq)
            print(f"{step:>9s} {backend:>9s} {100 * err['fx'] / K_true[0, 0]:+7.3f} "
                  f"{zq[0]:+6.1f} {err['cx']:+7.2f} {zq[1]:+6.1f} {err['cy']:+7.2f} {zq[2]:+6.1f}")
    for backend, values in z.items():
        a = np.abs(values)
        print(f"{backend}: max |z| fx {a[:, 0].max():.1f} cx {a[:, 1].max():.1f} cy "
              f"{a[:, 2].max():.1f}; RMS z fx {np.sqrt(np.mean(a[:, 0]**2)):.2f} cx "
              f"{np.sqrt(np.mean(a[:, 1]**2)):.2f} cy {np.sqrt(np.mean(a[:, 2]**2)):.2f}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__.splitlines()[2].strip("`"))
    main(Path(sys.argv[1]), Path(sys.argv[2]))
