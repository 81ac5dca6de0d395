"""The principal point's zoom model chosen by held-out steps against the second-difference prior,
on many seeded projection sweeps with hidden paths.

``python benchmarks/bench_zoom_model.py [--seeds 10] [--views 6] [--models angle2,prior2,select]
[--paths quadratic,traced-static,traced]``

Each sweep comes from ``sweep_observations`` of ``tests/test_zoomwide.py`` (OpenCV's projection
of a board bent by sine waves, Gaussian detection noise of 0.012 px, 7 steps, fx 2300-23000 px);
its principal-point path is either the ray-traced zoom lens (``traced``, 40 px span, with and
without the cam-track run-out, drawn from the seed) or a quadratic in log fx (``quadratic``).
The adjustments (``pp_model`` ``angle2``, ``prior2`` and ``select``, every distortion term
free) run on the same detections. Printed per path: how often ``select`` chose each model, and
per adjustment the largest ``|error| / sigma`` of cx and cy over the steps and seeds, the number
of sweeps with a step beyond 3 and 4 sigmas, the RMS of ``error / sigma`` over all steps and at
the two longest (1.0 = honest sigmas), and the median over seeds of the long-end sigma (cx, cy).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout
sys.path.insert(0, str(ROOT / "tests"))

from test_zoomwide import sweep_observations  # noqa: E402

from zoomcalib.calibrate.zoomwide import calibrate_zoom_wide  # noqa: E402
from zoomcalib.render.pp_path import traced_path  # noqa: E402

FX = (2300.0, 23000.0)


def _path(kind: str, seed: int):
    def traced(u, runout):
        return np.array([640.0, 360.0]) + traced_path(u / u[-1], FX, 40.0, seed, runout)[0]

    def quadratic(u):
        t = u / u[-1]
        return np.column_stack([640 + 80 * t - 60 * t**2, 360 - 40 * t + 60 * t**2])

    return {"traced": lambda u: traced(u, 1.0), "traced-static": lambda u: traced(u, 0.0),
            "quadratic": quadratic}[kind]


def _z(zw, truth) -> np.ndarray:
    """(steps, 2) errors of cx, cy against the truth in reported sigmas."""
    return np.array([[(getattr(zw.results[s], q) - t[q]) / zw.results[s].sd[q]
                      for q in ("cx", "cy")] for s, t in truth.items()])


def _one_path(kind: str, seeds: int, views: int, models: list[str]) -> None:
    chosen, worst, beyond, sd_last = Counter(), {}, {}, {m: [] for m in models}
    z_all = {m: [] for m in models}
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        obs, truth, _ = sweep_observations(rng, views=views, noise=0.012, pp=_path(kind, seed))
        fits = {m: calibrate_zoom_wide(obs, select=False, pp_model=m) for m in models}
        if "select" in fits:
            chosen.update(f"{q} {fits['select'].zoom_models[q]['model']}" for q in ("cx", "cy"))
        last = list(obs)[-1]
        for m, zw in fits.items():
            z_all[m].append(_z(zw, truth))
            z = float(np.max(np.abs(z_all[m][-1])))
            worst[m] = max(worst.get(m, 0.0), z)
            beyond.setdefault(m, [0, 0])
            beyond[m][0] += z > 3
            beyond[m][1] += z > 4
            sd_last[m].append([zw.results[last].sd[q] for q in ("cx", "cy")])
    print(f"{kind}:" + (f" select chose {dict(sorted(chosen.items()))}" if chosen else ""))
    for m in models:
        sd = np.median(sd_last[m], axis=0)
        z = np.array(z_all[m])
        print(f"  {m:>6s}: worst |z| {worst[m]:.1f}; sweeps with a step beyond 3 sigma "
              f"{beyond[m][0]}/{seeds}, beyond 4 sigma {beyond[m][1]}/{seeds}; RMS z "
              f"{np.sqrt(np.mean(z ** 2)):.2f}, at the two longest steps "
              f"{np.sqrt(np.mean(z[:, -2:] ** 2)):.2f}; long-end sigma, median: "
              f"cx {sd[0]:.2f}, cy {sd[1]:.2f} px")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--models", default="angle2,prior2,select",
                    help="pp_model values to compare, comma-separated")
    ap.add_argument("--paths", default="quadratic,traced-static,traced",
                    help="principal-point paths, comma-separated")
    args = ap.parse_args()
    models = args.models.split(",")
    print(f"# {args.seeds} seeds, 7 steps x {args.views} views, noise 0.012 px")
    for kind in args.paths.split(","):
        _one_path(kind, args.seeds, args.views, models)


if __name__ == "__main__":
    main()
