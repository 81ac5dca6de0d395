"""Zoom-wide calibration against per-step OpenCV on a rendered zoom sweep, and the honesty of
its sigmas by Monte Carlo.

``python benchmarks/bench_zoom_wide.py [--steps 7] [--views 10] [--psf airy] [--wave 0.3]
[--jpeg 85] [--mc 20] [--seed 0] [--out DIR]``

1. Renders a sweep with :func:`zoomcalib.render.sweep.render_zoom_sweep` (1280 x 720, 22 x 15
   board, fx 2300 to 23000 px, a board bent by ``--wave`` mm, the chosen PSF, JPEG) unless
   ``DIR/images/truth.json`` exists.
2. Runs the calibrate job with its defaults (model detector, per-step OpenCV beside the zoom-wide
   adjustment) and prints, per step and backend, the error against the rendered truth: fx in %,
   cx and cy in px and in reported sigmas, and the sigmas.
3. Monte Carlo: the true image points of every detected corner (``truth.json``) plus Gaussian
   noise of the detector's measured RMS error per coordinate, ``--mc`` draws, each adjusted
   zoom-wide; printed per step: the spread of fx, cx, cy over the draws divided by the mean
   reported sigma (1.0 = honest sigmas).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.zoomwide import (  # noqa: E402
    calibrate_zoom_wide,
    prior_strength,
    second_difference,
)
from zoomcalib.render.sweep import render_zoom_sweep  # noqa: E402

PATTERN = "chessboard:22x15:20"


def _render(images: Path, args) -> dict:
    if not (images / "truth.json").exists():
        render_zoom_sweep(images, steps=args.steps, views=args.views, pattern=PATTERN,
                          board_surface=args.wave or None, psf=args.psf,
                          jpeg_quality=args.jpeg, seed=args.seed, supersample=2)
    return json.loads((images / "truth.json").read_text())


def _truth_points(truth: dict) -> dict[str, dict[str, np.ndarray]]:
    return {s["step"]: {Path(v["file"]).name: np.asarray(v["points_px"]) for v in s["views"]}
            for s in truth["steps"]}


def _errors_table(run, truth: dict) -> None:
    print(f"{'step':>9s} {'backend':>9s} {'dfx %':>8s} {'sd fx %':>8s} {'dcx':>7s} {'sd cx':>6s} "
          f"{'z cx':>5s} {'dcy':>7s} {'sd cy':>6s} {'z cy':>5s}")
    for st in truth["steps"]:
        K = np.asarray(st["K"])
        for backend, r in run.results.get(st["step"], {}).items():
            dcx, dcy = r.cx - K[0, 2], r.cy - K[1, 2]
            print(f"{st['step']:>9s} {backend:>9s} {100 * (r.fx / K[0, 0] - 1):+8.3f} "
                  f"{100 * r.sd['fx'] / K[0, 0]:8.3f} {dcx:+7.2f} {r.sd['cx']:6.2f} "
                  f"{dcx / r.sd['cx']:+5.1f} {dcy:+7.2f} {r.sd['cy']:6.2f} "
                  f"{dcy / r.sd['cy']:+5.1f}")


def _prior_table(run, truth: dict) -> None:
    """The smoothness prior's ``tau`` as the adjustment estimated it, as per-step OpenCV values
    would give it, and the rendered path's own RMS second difference in ``u = log fx``."""
    steps = [st for st in truth["steps"] if "opencv" in run.results.get(st["step"], {})]
    u = np.log([np.asarray(st["K"])[0, 0] for st in steps])
    D = second_difference(u)
    print(f"# smoothness prior (px per u^2), from: {run.zoom_wide.tau_source}")
    print(f"{'param':>6s} {'zoom-wide':>10s} {'opencv':>10s} {'truth':>10s}")
    for q, row in (("cx", 0), ("cy", 1)):
        cv = [run.results[st["step"]]["opencv"] for st in steps]
        tau_cv, _ = prior_strength(np.array([getattr(r, q) for r in cv]),
                                   np.array([r.sd[q] for r in cv]), u)
        path = np.array([np.asarray(st["K"])[row, 2] for st in steps])
        print(f"{q:>6s} {run.zoom_wide.tau[q]:10.2f} {tau_cv:10.2f} "
              f"{np.sqrt(np.mean((D @ path) ** 2)):10.2f}")


def _detection_error(run, points: dict) -> float:
    """RMS per coordinate of the detections against the truth, px."""
    sq, n = 0.0, 0
    for step, obs in run.observations.items():
        for name, (ids, pts) in zip(obs.names, obs.views, strict=True):
            d = pts - points[step][name][ids]
            sq, n = sq + float(np.sum(d * d)), n + d.size
    return float(np.sqrt(sq / n))


def _monte_carlo(run, points: dict, noise: float, draws: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    values = {s: [] for s in run.observations}
    sds = {s: [] for s in run.observations}
    for _ in range(draws):
        obs = {}
        for step, o in run.observations.items():
            views = [(ids, points[step][name][ids] + rng.normal(0, noise, (len(ids), 2)))
                     for name, (ids, _) in zip(o.names, o.views, strict=True)]
            obs[step] = Observations(o.object_points, views, o.image_size, o.names)
        zw = calibrate_zoom_wide(obs)
        for step, r in zw.results.items():
            values[step].append([r.fx, r.cx, r.cy])
            sds[step].append([r.sd["fx"], r.sd["cx"], r.sd["cy"]])
    print(f"# Monte Carlo: {draws} draws, noise {noise:.4f} px per coordinate; "
          "spread / mean reported sigma")
    print(f"{'step':>9s} {'fx':>6s} {'cx':>6s} {'cy':>6s}")
    for step in values:
        ratio = np.std(values[step], axis=0, ddof=1) / np.mean(sds[step], axis=0)
        print(f"{step:>9s} " + " ".join(f"{v:6.2f}" for v in ratio))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=7)
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--psf", default="airy", choices=["gaussian", "airy", "halo", "elliptical"])
    ap.add_argument("--wave", type=float, default=0.3, help="board wave amplitude, mm")
    ap.add_argument("--jpeg", type=int, default=85, help="JPEG quality (0: PNG)")
    ap.add_argument("--mc", type=int, default=20, help="Monte Carlo draws (0: none)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench-zoom-wide")
    args = ap.parse_args()
    args.jpeg = args.jpeg or None
    out = Path(args.out)
    print(f"# sweep: {args.steps} steps x {args.views} views, 1280x720, {PATTERN}, psf {args.psf}, "
          f"wave {args.wave} mm, jpeg {args.jpeg or 'none'}, seed {args.seed}")
    print(f"# machine: {platform.machine()}, Python {platform.python_version()}")
    t0 = time.perf_counter()
    truth = _render(out / "images", args)
    t1 = time.perf_counter()
    run = calibrate_folder(out / "images", PATTERN, out / "calibration", ("opencv",),
                           workers=2, log=lambda m: None)
    t2 = time.perf_counter()
    print(f"# render {t1 - t0:.1f} s (0 when reused); calibrate (2 workers) {t2 - t1:.1f} s")
    _errors_table(run, truth)
    _prior_table(run, truth)
    points = _truth_points(truth)
    noise = _detection_error(run, points)
    print(f"# detection error against the truth: {noise:.4f} px RMS per coordinate")
    if args.mc:
        _monte_carlo(run, points, noise, args.mc, args.seed + 1)


if __name__ == "__main__":
    main()
