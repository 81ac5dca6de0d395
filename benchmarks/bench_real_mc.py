"""How wide should a real sweep's sigmas be? A Monte Carlo of synthetic sweeps that imitate it.

``python benchmarks/bench_real_mc.py FOLDER --out DIR [--pattern chessboard:22x15:25]
[--draws 10] [--seed 0] [--errors resampled|imitated|views] [--in-plane-mm 0.3]
[--board-shape print] [--draws-board-shape points] [--verbose]``

``FOLDER`` and ``--out`` as for ``bench_real_ptz.py`` (the real PTZ set of
``e-cagan/camera-calibration``, read where it lies; detections cached in ``DIR/detections``).

1. The default ``calibrate`` run on the real set gives, per step, the zoom-wide intrinsics,
   their sigmas, every view's pose, each capture session's board (modes, point heights and,
   where kept, the print's in-plane shape) and each step's residual sd per coordinate.
2. Each draw builds a sweep with the same steps, views and visible corners, projected by
   ``cv2.projectPoints`` with the step's measured camera and poses, and errors from one of these
   generators:

   - ``resampled`` (default): the real run's own residuals, view by view, each view's whole
     residual field multiplied by a random sign (a wild bootstrap clustered by view, Cameron,
     Gelbach & Miller 2008). The projection is of the run's estimated board (modes, point
     heights, the print's shape). Whatever the real views carry (a camera that moved, a board
     that flexed between frames, the compression, a rolling shutter) is in the draws with its
     structure within each view, without a model of it; an error the real board shares across views
     is made a per-view one by the signs. The residuals are those of a fit, a little smaller
     than the errors (by the parameters each view's corners determine: 6 pose and a share
     of the intrinsics and heights, of about 600 coordinates).
   - ``views``: no projection: each step's real views themselves, drawn with replacement (a
     bootstrap over views, the pairs bootstrap clustered by view). Whatever differs from view
     to view, the errors within each view and the views' poses alike, is in the spread; the
     "truth" the z are taken against is the real run's estimate. With ``n`` views per step
     its spread is smaller than the estimator's by about ``sqrt((n - 1) / n)``.
   - ``imitated``: a model of the causes. Every session's board is the nominal board plus
     the measured smooth shape, fresh ripples (three plane waves of 3-6 cycles across the
     board, random direction and phase, of the measured point heights' RMS) and in-plane
     errors of ``--in-plane-mm`` RMS per point (a printed board's; the adjustment's print
     shape is smooth, so it has no such term); white corner noise brings each step's
     residual to its measured sd (the in-plane errors' share taken out in quadrature). It has
     no error that differs between views beyond the noise: the real views' scatter is not in
     it.
3. Each draw is calibrated zoom-wide as the default does (the same sessions and settings), or
   with the board model ``--draws-board-shape``: what that model makes of a board like the
   real run's.

Per step it prints the real run's sigma of fx, cx, cy, the spread (sd) of the draws'
estimates, their ratio (issue goal: at most 1.5), and the draws' RMS z against their truth
with their own sigmas (honest sigmas: near 1); ``--verbose`` also prints every draw's errors
of cx, cy with their sigmas, and p1 and the distortion terms, true and estimated, per step.
The data have no licence: nothing of them is
kept in this repository.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from bench_real_ptz import real_set_parser  # noqa: E402

from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.zoomwide import (  # noqa: E402
    BOARD_SHAPES,
    board_options,
    calibrate_zoom_wide,
)

COMPARED = ("fx", "cx", "cy")


def ripple(board: np.ndarray, rms_mm: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) heights mm: three plane waves of 3-6 cycles across the board, ``rms_mm`` RMS."""
    xy = board[:, :2] - board[:, :2].mean(axis=0)
    xy = xy / (np.ptp(board[:, :2], axis=0) / 2)
    angle, cycles, phase = (rng.uniform(0, np.pi, 3), rng.uniform(3, 6, 3),
                            rng.uniform(0, 2 * np.pi, 3))
    h = sum(np.sin(np.pi * c * (np.cos(a) * xy[:, 0] + np.sin(a) * xy[:, 1]) + p)
            for a, c, p in zip(angle, cycles, phase, strict=True))
    return rms_mm * h / np.sqrt(np.mean(h**2))


def draw_sweep(run, zw, in_plane_mm: float, rng: np.random.Generator
               ) -> tuple[dict[str, Observations], dict[str, dict]]:
    """One synthetic sweep imitating the real one (module docstring) and its truth."""
    nominal = next(iter(run.observations.values())).object_points.astype(float)
    heights = zw.board_heights
    boards = {}
    for k, session in enumerate(zw.board_sessions):
        board = nominal.copy()
        step = next(s for s, r in zw.results.items() if r.info["board_session"] == session)
        smooth = zw.results[step].object_points[:, 2] - (0 if heights is None else heights[k])
        rms = 0.0 if heights is None else float(np.sqrt(np.mean(heights[k] ** 2)))
        board[:, 2] = smooth + ripple(nominal, rms, rng)
        board[:, :2] += rng.normal(0, in_plane_mm / np.sqrt(2), (len(board), 2))
        boards[session] = board
    sweep, truth = {}, {}
    for step, r in zw.results.items():
        obs = run.observations[step]
        board = boards[r.info["board_session"]]
        views = []
        for v, (ids, _) in enumerate(obs.views):
            p = cv2.projectPoints(board[ids], r.rvecs[v], r.tvecs[v], r.K, r.dist)[0]
            flat = board[ids].copy()
            flat[:, :2] = nominal[ids, :2]
            q = cv2.projectPoints(flat, r.rvecs[v], r.tvecs[v], r.K, r.dist)[0]
            views.append((ids, p.reshape(-1, 2), q.reshape(-1, 2)))
        in_plane = np.sqrt(np.mean(np.concatenate([p - q for _, p, q in views]) ** 2))
        white = np.sqrt(max(r.info["noise_sigma_px"] ** 2 - in_plane**2, 0.0))
        sweep[step] = Observations(nominal, [(ids, p + rng.normal(0, white, p.shape))
                                             for ids, p, _ in views], obs.image_size,
                                   list(obs.names))
        truth[step] = {"fx": r.fx, "cx": r.cx, "cy": r.cy, "white_px": white, "board": board,
                       "in_plane_px": in_plane}
    return sweep, truth


def resample_sweep(run, zw, rng: np.random.Generator
                   ) -> tuple[dict[str, Observations], dict[str, dict]]:
    """One sweep of the real run's own residuals, each view's with a random sign (module
    docstring, ``resampled``), and its truth."""
    nominal = next(iter(run.observations.values())).object_points.astype(float)
    sweep, truth = {}, {}
    for step, r in zw.results.items():
        obs = run.observations[step]
        views = []
        for v, (ids, pts) in enumerate(obs.views):
            p = cv2.projectPoints(r.object_points[ids].astype(float), r.rvecs[v], r.tvecs[v],
                                  r.K, r.dist)[0].reshape(-1, 2)
            views.append((ids, p + rng.choice((-1.0, 1.0)) * (pts - p)))
        sweep[step] = Observations(nominal, views, obs.image_size, list(obs.names))
        truth[step] = {"fx": r.fx, "cx": r.cx, "cy": r.cy}
    return sweep, truth


def resample_views(run, zw, rng: np.random.Generator
                   ) -> tuple[dict[str, Observations], dict[str, dict]]:
    """One sweep of each step's real views drawn with replacement (module docstring,
    ``views``), and the real run's estimates as the centre the draws scatter about."""
    sweep, truth = {}, {}
    for step, r in zw.results.items():
        obs = run.observations[step]
        pick = rng.integers(0, obs.n_views, obs.n_views)
        sweep[step] = Observations(obs.object_points, [obs.views[i] for i in pick],
                                   obs.image_size, [f"{obs.names[i]}#{k}"
                                                    for k, i in enumerate(pick)])
        truth[step] = {"fx": r.fx, "cx": r.cx, "cy": r.cy}
    return sweep, truth


def main() -> None:
    ap = real_set_parser(__doc__)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--errors", default="resampled", choices=("resampled", "imitated", "views"))
    ap.add_argument("--in-plane-mm", type=float, default=0.3,
                    help="in-plane board errors of the imitated errors, mm RMS")
    ap.add_argument("--board-shape", default="print", choices=BOARD_SHAPES,
                    help="the real run's board model, whose board the draws carry (default "
                         "print, as calibrate)")
    ap.add_argument("--draws-board-shape", default=None, choices=BOARD_SHAPES,
                    help="the board model that calibrates the draws (default: --board-shape); "
                         "another one measures what that model does to a board like the real "
                         "run's")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    t = time.perf_counter()
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=lambda m: None, report=False, board_shape=args.board_shape)
    zw = run.zoom_wide
    print(f"real run: {time.perf_counter() - t:.0f} s; sessions {zw.board_sessions}")
    sessions = {s: r.info["board_session"] for s, r in zw.results.items()}
    rng = np.random.default_rng(args.seed)
    draws_shape = args.draws_board_shape or args.board_shape
    estimates = {s: [] for s in zw.results}
    z = {s: [] for s in zw.results}
    for d in range(args.draws):
        t = time.perf_counter()
        if args.errors == "resampled":
            sweep, truth = resample_sweep(run, zw, rng)
        elif args.errors == "views":
            sweep, truth = resample_views(run, zw, rng)
        else:
            sweep, truth = draw_sweep(run, zw, args.in_plane_mm, rng)
        if d == 0 and args.errors == "imitated":
            print("white noise px per step: " + ", ".join(
                f"{s} {tr['white_px']:.2f} (in-plane {tr['in_plane_px']:.2f})"
                for s, tr in truth.items()))
        adjusted = calibrate_zoom_wide(sweep, sessions=sessions, workers=2,
                                       **board_options(draws_shape))
        got = adjusted.results
        if args.verbose:
            for s, r in got.items():
                print(f"    {s}: cx {r.cx - truth[s]['cx']:+.1f} ± {r.sd['cx']:.1f}, cy "
                      f"{r.cy - truth[s]['cy']:+.1f} ± {r.sd['cy']:.1f}; p1 true "
                      f"{zw.results[s].dist[2]:+.4f} got {r.dist[2]:+.4f}; terms true "
                      f"{','.join(zw.terms[s])} got {','.join(adjusted.terms[s])}")
        for s, r in got.items():
            estimates[s].append([getattr(r, q) for q in COMPARED])
            z[s].append([(getattr(r, q) - truth[s][q]) / r.sd[q] for q in COMPARED])
        print(f"  draw {d}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"{args.draws} draws, errors {args.errors}, board shape {args.board_shape}, the "
          f"draws calibrated with {draws_shape}"
          + (f", in-plane {args.in_plane_mm} mm" if args.errors == "imitated" else ""))
    print(f"{'step':>9} " + " ".join(f"{'sd_' + q:>8} {'mc':>7} {'ratio':>5} {'rms z':>5}"
                                     for q in COMPARED))
    ratios = []
    for s, r in zw.results.items():
        est, zs = np.array(estimates[s]), np.array(z[s])
        cells = []
        for i, q in enumerate(COMPARED):
            mc = est[:, i].std(ddof=1)
            ratios.append(r.sd[q] / mc)
            cells.append(f"{r.sd[q]:8.2f} {mc:7.2f} {r.sd[q] / mc:5.2f} "
                         f"{np.sqrt(np.mean(zs[:, i] ** 2)):5.2f}")
        print(f"{s:>9} " + " ".join(cells))
    allz = np.concatenate([np.array(v) for v in z.values()])
    print(f"ratio real sigma / MC sd: median {np.median(ratios):.2f}, largest "
          f"{max(ratios):.2f}, above 1.5: {sum(x > 1.5 for x in ratios)} of {len(ratios)}; "
          f"draws' pooled RMS z {np.sqrt(np.mean(allz**2)):.2f}, beyond 3: "
          f"{int((np.abs(allz) > 3).sum())} of {allz.size}")


if __name__ == "__main__":
    main()
