"""A real PTZ camera's zoom sweep, calibrated as a user would, and its halves.

``python benchmarks/bench_real_ptz.py FOLDER [--out DIR] [--pattern chessboard:22x15:25]
[--splits 5] [--seed 0] [--one-session] [--free-aspect] [--board-degree 4]
[--board-shape print] [--own-session STEP ...]``

``FOLDER`` is an image folder of zoom-step subfolders, e.g. the ``calibration_images`` folder
of the public set ``e-cagan/camera-calibration`` (10 steps ``zoom_1x`` .. ``zoom_10x`` of a
PTZ camera, 1280 x 720 frames of its H.264 stream, a paper chessboard of 22 x 15 inner corners
taped to a wall, four capture days). The set has no licence: nothing of it is kept in this
repository; this script reads it where it lies and writes to ``--out`` (default
``bench-real-ptz`` in the current folder).

1. **The default run.** ``calibrate_folder`` as ``zoomcalib calibrate FOLDER --pattern ...``
   runs it (detections cached in ``OUT/detections``, so a rerun times the calibration alone),
   timed, beside plain per-step OpenCV on the same detections in the same run (the peer), and
   OpenCV's own detection (``classic``, two processes) plus that calibration. It
   prints the 10-step table: zoom-wide fx, fy / fx, cx, cy with their sigmas, the RMS, the
   status and its reasons.
2. **Halves.** ``--splits`` splits of every step's views (the even and odd groups of views of
   nearly one pose, then random splits of the groups, :func:`random_halves`), each half
   calibrated zoom-wide with the full run's sessions; per step and split
   ``z_q = (q_a - q_b) / sqrt(sd_a^2 + sd_b^2)`` for fx, cx, cy. Honest sigmas give ``|z|``
   within 3 and a pooled RMS near 1 (the bar: 0.6-1.4). The steps' statuses in the halves
   are counted too.

``--one-session`` calibrates with one board shape for all steps, ``--free-aspect`` with a
``fy`` per step: the settings before they became the default. ``--board-degree N`` gives the
zoom-wide board modes up to degree ``N`` (the default run's 4; a paper board taped to a wall
ripples beyond it, ``bench_real_board.py``), for the table and the halves; ``--board-shape``
as calibrate's: ``print`` (the default) with the print's in-plane shape where its test says
it pays, ``points`` without it (the default before), ``modes`` without the height of every
board point and session (``board_points=False``, the default before that).
``--own-session STEP ...`` gives those steps a board of their own (as a ``session`` column
of ``steps.csv`` would).
``--halves-steps S ...``
calibrates the halves of those steps alone (the splits drawn as for all steps, so split ``k``
is the same as in a run over all steps): what the long end's own frames determine without the
short end to anchor it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.checks import random_halves  # noqa: E402
from zoomcalib.calibrate.opencv_backend import calibrate_opencv_robust  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.status import sensor_aspect, step_status  # noqa: E402
from zoomcalib.calibrate.zoomwide import (  # noqa: E402
    BOARD_SHAPES,
    board_options,
    calibrate_zoom_wide,
)
from zoomcalib.detect import detect_folder  # noqa: E402

COMPARED = ("fx", "cx", "cy")


def _table(results: dict, run) -> None:
    """The zoom-wide rows with their statuses (the own per-step OpenCV as the reference)."""
    aspect = sensor_aspect(results)
    print(f"{'step':>9} {'fx':>14} {'fy/fx':>7} {'cx':>13} {'cy':>13} {'rms':>6}  status")
    for step, r in results.items():
        st = step_status(r, run.observations[step].image_size, aspect,
                         run.results[step].get("opencv"))
        print(f"{step:>9} {r.fx:8.1f}±{r.sd['fx']:5.1f} {r.fy / r.fx:7.4f} "
              f"{r.cx:7.1f}±{r.sd['cx']:5.1f} {r.cy:7.1f}±{r.sd['cy']:5.1f} {r.rms_px:6.3f}  "
              f"{st.summary()}")


def _opencv_detection(folder: Path, pattern: str) -> float:
    """Seconds OpenCV's own chessboard detection (findChessboardCorners and cornerSubPix,
    method ``classic``) takes on every step's images in two processes (the detection peer)."""
    t = time.perf_counter()
    for step in sorted(p for p in folder.iterdir() if p.is_dir()):
        detect_folder(step, pattern, "classic", workers=2)
    return time.perf_counter() - t


def _per_step_opencv(run) -> float:
    """Seconds plain per-step OpenCV takes on the run's detections (the peer)."""
    t = time.perf_counter()
    for obs in run.observations.values():
        try:
            calibrate_opencv_robust(obs)
        except (ValueError, RuntimeError):
            pass
    return time.perf_counter() - t


def _half_row(r) -> dict:
    """What a half's step row holds for a look afterwards (``--halves-json``)."""
    info = r.info
    return {"fx": r.fx, "cx": r.cx, "cy": r.cy, "sd": {q: r.sd[q] for q in COMPARED},
            "dist": np.asarray(r.dist).tolist(), "rms_px": r.rms_px, "n_views": len(r.rvecs),
            "view_scatter": (info.get("view_scatter") or {}).get("factor"),
            "sd_noise_model": {q: (info.get("sd_noise_model") or {}).get(q) for q in COMPARED},
            "terms": (info.get("distortion_choice") or {}).get("terms"),
            "basin": info.get("basin"), "prior_share": info.get("prior_share")}


def _halves(run, sessions, splits: int, seed: int, kwargs: dict,
            only: list[str] | None = None, dump: Path | None = None) -> None:
    rng = np.random.default_rng(seed)
    rows: list[dict] = []
    pairs = {s: random_halves(o, splits, rng) for s, o in run.observations.items()}
    pairs = {s: p for s, p in pairs.items() if not only or s in only}
    z = {s: [] for s in pairs}
    statuses = {"ok": 0, "imprecise": 0, "unusable": 0}
    for k in range(splits):
        halves = []
        for side in (0, 1):
            obs = {s: p[k][side] for s, p in pairs.items()}
            t = time.perf_counter()
            res = calibrate_zoom_wide(obs, sessions=sessions, **kwargs).results
            aspect = sensor_aspect(res)
            for s, r in res.items():
                statuses[step_status(r, r_size(run, s), aspect).status] += 1
            if only:
                print(f"  split {k} half {'ab'[side]}: " + ", ".join(
                    f"{s} cy {r.cy:.0f}±{r.sd['cy']:.0f}" for s, r in res.items()))
            halves.append(res)
            rows += [{"split": k, "half": "ab"[side], "step": s, **_half_row(r)}
                     for s, r in res.items()]
            if dump is not None:
                dump.write_text(json.dumps(rows, indent=1, default=str))
            print(f"  split {k} half {'ab'[side]}: {time.perf_counter() - t:.0f} s", flush=True)
        a, b = halves
        for s in pairs:
            if s in a and s in b:
                z[s].append([(getattr(a[s], q) - getattr(b[s], q))
                             / np.hypot(a[s].sd[q], b[s].sd[q]) for q in COMPARED])
    print(f"halves ({splits} splits; z = difference / combined sigma):")
    print(f"{'step':>9} " + " ".join(f"{'max|z_' + q + '|':>10} {'rms':>5}" for q in COMPARED))
    every = []
    for s, rows in z.items():
        arr = np.array(rows)
        every.append(arr)
        print(f"{s:>9} " + " ".join(f"{np.abs(arr[:, i]).max():10.2f} "
                                    f"{np.sqrt(np.mean(arr[:, i] ** 2)):5.2f}"
                                    for i in range(len(COMPARED))))
    allz = np.concatenate(every)
    print("pooled RMS z " + ", ".join(f"{q} {np.sqrt(np.mean(allz[:, i] ** 2)):.2f}"
                                      for i, q in enumerate(COMPARED))
          + f"; all {np.sqrt(np.mean(allz ** 2)):.2f}; largest |z| {np.abs(allz).max():.2f}; "
          f"beyond 3: {int((np.abs(allz) > 3).sum())} of {allz.size}")
    print("halves' statuses: " + ", ".join(f"{k} {v}" for k, v in statuses.items()))


def r_size(run, step: str) -> tuple[int, int]:
    return run.observations[step].image_size


def real_set_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every benchmark of the real PTZ set takes: its image ``folder``, ``--out``
    (detections cached in ``OUT/detections``), ``--pattern`` and ``--seed``."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench-real-ptz"))
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    ap.add_argument("--seed", type=int, default=0)
    return ap


def main() -> None:
    ap = real_set_parser(__doc__)
    ap.add_argument("--splits", type=int, default=5)
    ap.add_argument("--one-session", action="store_true")
    ap.add_argument("--free-aspect", action="store_true")
    ap.add_argument("--board-degree", type=int, default=4,
                    help="highest degree of the zoom-wide board modes (default 4, as calibrate)")
    ap.add_argument("--board-shape", default="print", choices=BOARD_SHAPES,
                    help="the zoom-wide board (calibrate's --board-shape; default print, as "
                         "calibrate)")
    ap.add_argument("--own-session", nargs="+", default=(),
                    help="give these steps a board session of their own")
    ap.add_argument("--halves-steps", nargs="+", default=None,
                    help="calibrate the halves of these steps alone")
    ap.add_argument("--halves-json", type=Path, default=None,
                    help="write every half's step rows (estimates, sigmas, terms, view-scatter "
                         "factors, basin) to this file")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    t = time.perf_counter()
    messages: list[str] = []
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=messages.append, report=False)
    wall = time.perf_counter() - t
    peer = _per_step_opencv(run)
    detection_peer = _opencv_detection(args.folder, args.pattern)
    for m in messages:
        if "session" in m or "unusable" in m:
            print(m)
    print(f"default run: {wall:.0f} s wall ({sum(run.reused.values())} images' detections "
          f"reused from {args.out / 'detections'}; "
          f"{sum(len(o.names) for o in run.observations.values())} views); plain per-step "
          f"OpenCV on the same detections {peer:.1f} s (ratio {wall / peer:.1f}); OpenCV's "
          f"detection (classic, 2 processes) and per-step calibration {detection_peer + peer:.0f}"
          f" s (ratio {wall / (detection_peer + peer):.1f})")
    sessions = {s: r["zoom-wide"].info.get("board_session", "")
                for s, r in run.results.items() if "zoom-wide" in r}
    kwargs = {"shared_aspect": not args.free_aspect, "workers": 2,
              "board_degree": args.board_degree, **board_options(args.board_shape)}
    zw = run.zoom_wide
    for step in args.own_session:
        sessions[step] = f"{sessions.get(step, '')} {step}"
    if (args.one_session or args.free_aspect or args.board_degree != 4
            or args.board_shape != "print" or args.own_session):
        sessions = None if args.one_session else sessions
        t = time.perf_counter()
        zw = calibrate_zoom_wide(run.observations, sessions=sessions, **kwargs)
        print(f"zoom-wide with {'one board shape' if args.one_session else 'sessions'}, "
              f"{'fy per step' if args.free_aspect else 'one aspect ratio'}, board modes to "
              f"degree {args.board_degree}, board {args.board_shape}: "
              f"{time.perf_counter() - t:.0f} s")
    if zw is None:
        print("no zoom-wide adjustment")
        return
    print(f"aspect fy/fx {zw.aspect:.5f} ± {zw.aspect_sd:.5f}; board sessions "
          f"{zw.board_sessions}")
    if zw.print_test is not None:
        pt = zw.print_test
        print(f"print shape: Wald {pt.wald:.0f} on {pt.dof} (threshold {pt.threshold:.1f}): "
              f"{'kept' if pt.kept else 'exact'}; largest mode {pt.largest_mm:+.3f} ± "
              f"{pt.largest_sd_mm:.3f} mm")
    if zw.print_modes is not None:
        print("print modes mm (x, then y; degree 2: y^2, xy, x^2, ...): "
              + "; ".join(" ".join(f"{v:+.2f}±{e:.2f}" for v, e in zip(m, sd, strict=True))
                          for m, sd in zip(zw.print_modes, zw.print_modes_sd, strict=True)))
    _table(zw.results, run)
    if zw is run.zoom_wide:
        for step, st in run.status.items():
            if st.advice:
                print(f"advice {step}: {st.advice['text']}")
    if args.splits:
        _halves(run, sessions, args.splits, args.seed, kwargs, args.halves_steps,
                args.halves_json)


if __name__ == "__main__":
    main()
