"""Zoom-wide calibration against per-step OpenCV on a rendered zoom sweep, and the honesty of
its sigmas by Monte Carlo.

``python benchmarks/bench_zoom_wide.py [--steps 7] [--views 10] [--psf airy] [--wave 0.3]
[--jpeg 85] [--pp-path bow|traced] [--pp-span 40] [--pp-runout 1] [--lens NAME]
[--dist-centre DX DY] [--model angle2] [--compare prior2] [--oracle] [--centred] [--mc 20]
[--mc-model angle2] [--workers 2] [--seed 0] [--tested-only] [--out DIR]``

1. Renders a sweep with :func:`zoomcalib.render.sweep.render_zoom_sweep` (1280 x 720, 22 x 15
   board, fx 2300 to 23000 px, a board bent by ``--wave`` mm, the chosen PSF, JPEG, the
   principal point on the ``--pp-path``, distortion fading towards the long end or a real
   lens's with ``--lens``) unless ``DIR/images/truth.json`` exists.
2. Runs the calibrate job with its defaults (model detector, per-step OpenCV beside the zoom-wide
   adjustment) and the principal point's zoom model ``--model``, and the zoom-wide adjustment
   again with ``--compare``. Prints, per step and backend, the error against the rendered
   truth: fx in %, cx and cy in px and in reported sigmas, and the sigmas; the zoom models and
   their ``tau`` beside the rendered path's own roughness in the same units; and at the two
   longest steps the per-step OpenCV principal-point sigma over the zoom-wide one (cx, cy, and
   as a point: the root of the sum of the two variances) for both. ``--oracle`` adds a third
   adjustment whose prior strength is the rendered path's own roughness (what the best estimate
   of ``tau`` could give); ``--centred`` one with p1, p2 held at zero where the held-out views
   did not choose them (the distortion taken to be centred on the principal point).
3. Monte Carlo: the true image points of every detected corner (``truth.json``) plus Gaussian
   noise of the detector's measured RMS error per coordinate, ``--mc`` draws, each adjusted
   zoom-wide (``--workers`` processes; each draw has its own child seed, so the draws do not
   depend on the number of workers); printed per step: the spread of fx, cx, cy over the draws,
   with the 95 % interval that the number of draws leaves on it, and their RMS error against
   the truth, each divided by the mean reported sigma; then how many ratios lie outside
   0.75-1.25, how many of their intervals lie wholly outside it, and how many chance alone
   would put outside (with 40 draws 2.6 % of the ratios, with 100 draws 0.04 %, if every sigma
   were right). Where the prior carries a step,
   its sigma also covers how far this one path lies from what the prior expects, which the
   draws do not redraw: the spread can then be below 1, and the RMS error with it where the
   path is smoother than the prior expects.

``--tested-only``: a sigma takes its view-scatter factor only where a test fired (the rule before
:data:`~zoomcalib.calibrate.scatter.SCALE_UNTESTED` became the default), in the calibrate job
and the Monte Carlo.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
from scipy.stats import chi2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate import scatter  # noqa: E402
from zoomcalib.calibrate.opencv_backend import calibrate_opencv  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.zoommodel import prior_operator  # noqa: E402
from zoomcalib.calibrate.zoomwide import (  # noqa: E402
    DISTORTION_SETS,
    ZOOM_MODELS,
    _distortion_flags,
    calibrate_zoom_wide,
)
from zoomcalib.render.sweep import render_zoom_sweep  # noqa: E402
from zoomcalib.study.lensfun import sweep_distortion  # noqa: E402

PATTERN = "chessboard:22x15:20"


def _render(images: Path, args) -> dict:
    if not (images / "truth.json").exists():
        lens = {} if args.lens is None else sweep_distortion(
            args.lens, np.geomspace(2300.0, 23000.0, args.steps), (1280, 720))
        render_zoom_sweep(images, steps=args.steps, views=args.views, pattern=PATTERN,
                          board_surface=args.wave or None, psf=args.psf,
                          jpeg_quality=args.jpeg, seed=args.seed, supersample=2,
                          pp_path=args.pp_path, pp_span_px=args.pp_span,
                          pp_runout=args.pp_runout, dist_centre_px=args.dist_centre, **lens)
    return json.loads((images / "truth.json").read_text())


def _truth_points(truth: dict) -> dict[str, dict[str, np.ndarray]]:
    return {s["step"]: {Path(v["file"]).name: np.asarray(v["points_px"]) for v in s["views"]}
            for s in truth["steps"]}


def _errors_table(run, truth: dict) -> None:
    print(f"# zoom-wide: the calibrate job (--model {run.model}); {run.compare}: the "
          "adjustment compared with it")
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


def _per_step_opencv(run, step: str):
    """The calibrate job's per-step OpenCV result (k1 k2 p1 p2 k3), or, where it failed (OpenCV
    cannot give a sigma for k3 at the long end), OpenCV with k1 k2 p1 p2."""
    res = run.results.get(step, {})
    if "opencv" in res:
        return res["opencv"], "opencv"
    flags = _distortion_flags(DISTORTION_SETS["k1k2p"])
    return calibrate_opencv(run.observations[step], flags=flags), "opencv without k3"


def _long_end_table(run, truth: dict) -> None:
    """Per-step OpenCV principal-point sigma over the zoom-wide one at the two longest steps."""
    print("# long end: per-step OpenCV sigma / zoom-wide sigma")
    print(f"{'step':>9s} {'model':>9s} {'cx':>6s} {'cy':>6s} {'point':>6s}  per-step")
    for st in truth["steps"][-2:]:
        cv, label = _per_step_opencv(run, st["step"])
        for backend in run.adjustments:
            zw = run.results[st["step"]][backend]
            point = np.hypot(cv.sd["cx"], cv.sd["cy"]) / np.hypot(zw.sd["cx"], zw.sd["cy"])
            print(f"{st['step']:>9s} {backend:>9s} {cv.sd['cx'] / zw.sd['cx']:6.2f} "
                  f"{cv.sd['cy'] / zw.sd['cy']:6.2f} {point:6.2f}  {label}")


def _truth_roughness(truth: dict, steps: list[str], model: str, order: int = 2
                     ) -> dict[str, float]:
    """The rendered path's own RMS difference of cx and cy under the prior of ``model`` over
    ``steps``: radians per u^order for ``angle2``, else px per u^order."""
    sts = [st for st in truth["steps"] if st["step"] in steps]
    fx = np.array([np.asarray(st["K"])[0, 0] for st in sts])
    R = prior_operator(np.log(fx), order, 1.0 / fx if model == "angle2" else None)
    return {q: float(np.sqrt(np.mean((R @ [np.asarray(st["K"])[row, 2] for st in sts]) ** 2)))
            for q, row in (("cx", 0), ("cy", 1))}


def _models_table(run, truth: dict) -> None:
    """Each adjustment's zoom model of cx and cy, its ``tau`` (and the 90 % interval of its
    posterior), and the rendered path's own RMS difference under the same prior (px per u^2,
    or micro-radians per u^2 for ``angle2``); for ``select``, the held-out log predictive
    density of each candidate."""
    print("# zoom models of the principal point: tau against the rendered path's roughness")
    print(f"{'adjustment':>10s} {'param':>5s} {'model':>6s} {'tau':>9s} {'truth':>9s} units"
          "  90% interval")
    for label, zw in run.adjustments.items():
        for q in ("cx", "cy"):
            m = zw.zoom_models[q]
            angular = m["model"] == "angle2"
            scale = 1e6 if angular else 1.0
            rough = _truth_roughness(truth, list(zw.results), m["model"], m["order"])[q]
            interval = " ".join(f"{v * scale:.3g}" for v in m.get("tau_interval_90", []))
            scores = " ".join(f"{k} {v:.1f}" if v is not None else f"{k} -"
                              for k, v in (m["held_out_log_density"] or {}).items())
            print(f"{label:>10s} {q:>5s} {m['model']:>6s} {(m['tau'] or np.inf) * scale:9.3g} "
                  f"{rough * scale:9.3g} {'urad' if angular else 'px'}/u^{m['order']}  "
                  f"{interval or m['tau_kind']} {scores}")
    print(f"# tau from: {run.zoom_wide.tau_source}")


def _detection_error(run, points: dict) -> float:
    """RMS per coordinate of the detections against the truth, px."""
    sq, n = 0.0, 0
    for step, obs in run.observations.items():
        for name, (ids, pts) in zip(obs.names, obs.views, strict=True):
            d = pts - points[step][name][ids]
            sq, n = sq + float(np.sum(d * d)), n + d.size
    return float(np.sqrt(sq / n))


def _one_draw(observations: dict, points: dict, noise: float, seed: np.random.SeedSequence,
              model: str, untested: bool = True) -> dict[str, np.ndarray]:
    """One draw: the true image points plus Gaussian noise, adjusted zoom-wide; per step
    ``[[fx, cx, cy], [sd fx, sd cx, sd cy]]``."""
    scatter.SCALE_UNTESTED = untested          # in the worker process
    rng = np.random.default_rng(seed)
    obs = {}
    for step, o in observations.items():
        views = [(ids, points[step][name][ids] + rng.normal(0, noise, (len(ids), 2)))
                 for name, (ids, _) in zip(o.names, o.views, strict=True)]
        obs[step] = Observations(o.object_points, views, o.image_size, o.names)
    zw = calibrate_zoom_wide(obs, pp_model=model)
    return {step: np.array([[r.fx, r.cx, r.cy], [r.sd["fx"], r.sd["cx"], r.sd["cy"]]])
            for step, r in zw.results.items()}


def spread_interval(ratio: np.ndarray, draws: int, level: float = 0.95) -> np.ndarray:
    """The ``level`` interval of the true spread / sigma behind a ratio measured from ``draws``
    Gaussian draws: ``(n-1) s^2 / sigma^2`` is chi-square with ``n-1`` degrees of freedom, so
    the true ratio lies in ``ratio sqrt((n-1) / q)`` for ``q`` the chi-square's upper and lower
    quantiles. Shape: ``ratio.shape + (2,)``."""
    dof = draws - 1
    q = chi2.ppf([(1 + level) / 2, (1 - level) / 2], dof)
    return np.asarray(ratio)[..., None] * np.sqrt(dof / q)


def _monte_carlo(run, points: dict, truth: dict, noise: float, draws: int, seed: int,
                 model: str, workers: int) -> None:
    """Spread and RMS error over ``draws`` noise draws, each divided by the mean reported sigma,
    the spread with its 95 % interval (what ``draws`` draws can tell). The spread leaves out
    what the prior's sigma covers besides the noise: how far this one path lies from what the
    prior expects, the same in every draw; the RMS error against the truth includes it."""
    seeds = np.random.SeedSequence(seed).spawn(draws)
    job = partial(_one_draw, run.observations, points, noise, model=model,
                  untested=scatter.SCALE_UNTESTED)
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(job, seeds))
    K = {st["step"]: np.asarray(st["K"]) for st in truth["steps"]}
    print(f"# Monte Carlo ({model}): {draws} draws, noise {noise:.4f} px per coordinate; "
          "spread / mean reported sigma [95 % interval], then RMS error against the truth / "
          "mean sigma")
    print(f"{'step':>9s} {'fx':>17s} {'cx':>17s} {'cy':>17s}   {'fx':>6s} {'cx':>6s} {'cy':>6s}")
    ratios, intervals = [], []
    for step in run.observations:
        v = np.array([o[step][0] for o in out])
        sd = np.mean([o[step][1] for o in out], axis=0)
        true = [K[step][0, 0], K[step][0, 2], K[step][1, 2]]
        spread = np.std(v, axis=0, ddof=1) / sd
        band = spread_interval(spread, draws)
        rms = np.sqrt(np.mean((v - true) ** 2, axis=0)) / sd
        ratios.append(spread)
        intervals.append(band)
        print(f"{step:>9s} " + " ".join(f"{x:5.2f} [{a:4.2f} {b:4.2f}]"
                                        for x, (a, b) in zip(spread, band, strict=True))
              + "   " + " ".join(f"{x:6.2f}" for x in rms))
    ratios, intervals = np.array(ratios), np.array(intervals)
    outside = (ratios < 0.75) | (ratios > 1.25)
    surely = (intervals[..., 1] < 0.75) | (intervals[..., 0] > 1.25)
    print(f"# spread / sigma outside 0.75-1.25: {int(outside.sum())} of {outside.size} ratios; "
          f"95 % interval wholly outside: {int(surely.sum())}; chance alone puts "
          f"{_expected_outside(draws) * outside.size:.1f} outside; RMS of the ratios fx/cx/cy "
          + "/".join(f"{x:.2f}" for x in np.sqrt(np.mean(ratios ** 2, axis=0))))


def _expected_outside(draws: int) -> float:
    """Probability that a ratio whose truth is 1 is measured outside 0.75-1.25 from ``draws``
    Gaussian draws."""
    dof = draws - 1
    return float(chi2.cdf(0.75 ** 2 * dof, dof) + chi2.sf(1.25 ** 2 * dof, dof))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=7)
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--psf", default="airy", choices=["gaussian", "airy", "halo", "elliptical"])
    ap.add_argument("--wave", type=float, default=0.3, help="board wave amplitude, mm")
    ap.add_argument("--jpeg", type=int, default=85, help="JPEG quality (0: PNG)")
    ap.add_argument("--pp-path", default="bow", choices=["bow", "traced"])
    ap.add_argument("--pp-span", type=float, default=40.0, help="traced path's span, px")
    ap.add_argument("--pp-runout", type=float, default=1.0, help="traced path's run-out scale")
    ap.add_argument("--dist-centre", type=float, nargs=2, default=(0.0, 0.0),
                    metavar=("DX", "DY"), help="distortion centre relative to the principal "
                                               "point, px (render-sweep --dist-centre)")
    ap.add_argument("--lens", help="a lensfun lens's distortion (render-sweep --lens); default: "
                                   "a barrel fading towards the long end")
    ap.add_argument("--mc", type=int, default=20, help="Monte Carlo draws (0: none)")
    ap.add_argument("--model", default="angle2", choices=ZOOM_MODELS,
                    help="pp_model of the calibrate job")
    ap.add_argument("--compare", default="prior2", choices=ZOOM_MODELS,
                    help="pp_model of the adjustment compared with it")
    ap.add_argument("--mc-model", default="angle2", choices=ZOOM_MODELS,
                    help="pp_model of the Monte Carlo's adjustments")
    ap.add_argument("--oracle", action="store_true",
                    help="also adjust with tau at the rendered path's own roughness (--model)")
    ap.add_argument("--centred", action="store_true",
                    help="also adjust with the distortion centred on the principal point "
                         "(calibrate_zoom_wide(decentring=False))")
    ap.add_argument("--tested-only", action="store_true",
                    help="a sigma takes its view-scatter factor only where a test fired "
                         "(scatter.SCALE_UNTESTED off)")
    ap.add_argument("--workers", type=int, default=2, help="processes for the Monte Carlo")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="bench-zoom-wide")
    args = ap.parse_args()
    args.jpeg = args.jpeg or None
    scatter.SCALE_UNTESTED = not args.tested_only
    out = Path(args.out)
    print(f"# sweep: {args.steps} steps x {args.views} views, 1280x720, {PATTERN}, psf {args.psf}, "
          f"wave {args.wave} mm, jpeg {args.jpeg or 'none'}, seed {args.seed}, pp path "
          f"{args.pp_path}" + (f" (span {args.pp_span} px, run-out x {args.pp_runout})"
                               if args.pp_path == "traced" else ""))
    print(f"# machine: {platform.machine()}, Python {platform.python_version()}")
    t0 = time.perf_counter()
    truth = _render(out / "images", args)
    print(f"# distortion: {truth.get('distortion')}")
    t1 = time.perf_counter()
    run = calibrate_folder(out / "images", PATTERN, out / "calibration", ("opencv",),
                           workers=2, log=lambda m: None, pp_model=args.model)
    t2 = time.perf_counter()
    print(f"# render {t1 - t0:.1f} s (0 when reused); calibrate (2 workers) {t2 - t1:.1f} s")
    run.model, run.compare = args.model, args.compare
    run.other = calibrate_zoom_wide(run.observations, pp_model=args.compare)
    run.adjustments = {"zoom-wide": run.zoom_wide, args.compare: run.other}
    if args.oracle:  # the prior at the rendered path's own roughness
        given = _truth_roughness(truth, list(run.zoom_wide.results), args.model)
        run.adjustments["oracle"] = calibrate_zoom_wide(run.observations, pp_model=args.model,
                                                        prior_strength=given)
    if args.centred:
        run.adjustments["centred"] = calibrate_zoom_wide(run.observations, pp_model=args.model,
                                                         decentring=False)
    for label, zw in list(run.adjustments.items())[1:]:
        for step, r in zw.results.items():
            run.results[step][label] = r
    _errors_table(run, truth)
    _models_table(run, truth)
    _long_end_table(run, truth)
    points = _truth_points(truth)
    noise = _detection_error(run, points)
    print(f"# detection error against the truth: {noise:.4f} px RMS per coordinate")
    if args.mc:
        _monte_carlo(run, points, truth, noise, args.mc, args.seed + 1, args.mc_model,
                     args.workers)


if __name__ == "__main__":
    main()
