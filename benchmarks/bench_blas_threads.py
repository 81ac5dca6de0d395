"""The zoom-wide adjustment with BLAS on one thread per process, against two (its peer).

``python benchmarks/bench_blas_threads.py FOLDER [--out DIR] [--pattern chessboard:22x15:25]
[--board-shape print] [--repeats 1]``

``FOLDER`` is a zoom set (step subfolders), e.g. the real PTZ set's ``calibration_images``
(``bench_real_ptz.py``; nothing of it is kept here) or ``data/synthetic/example``. Its
detections are made, or reused from ``OUT/detections``, by ``calibrate_folder``; then
:func:`~zoomcalib.calibrate.zoomwide.calibrate_zoom_wide` runs twice on them, with two worker
processes for the per-step OpenCV fits:

- **one thread** (the default since this benchmark): the adjustment and its pool's workers run
  BLAS on one thread (:func:`zoomcalib.pool.one_blas_thread`, the pool's initializer);
- **two threads** (the peer, as before): BLAS as the machine sets it up (OpenBLAS: one thread
  per core, in the main process and in each worker).

It prints each run's wall time, the time of the adjustment's Schur steps (the products of a
few hundred columns where the threads cost most), the ratio, and the largest difference
between the two runs' fx, cx, cy in sigmas (the threads change only the order of sums).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from threadpoolctl import threadpool_info, threadpool_limits  # noqa: E402

import zoomcalib.calibrate.solver as solver  # noqa: E402
import zoomcalib.calibrate.zoomwide as zoomwide  # noqa: E402
import zoomcalib.pool as pool  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.stepfolders import capture_date  # noqa: E402


def _timed_schur():
    """Wrap the Schur step to sum its time; returns the list the wrapper adds to."""
    spent = [0.0]
    original = solver.schur_step

    def timed(*args):
        t = time.perf_counter()
        out = original(*args)
        spent[0] += time.perf_counter() - t
        return out

    solver.schur_step = timed
    return spent, original


def _run(obs, sessions, kwargs: dict, threads: int):
    """One adjustment; ``threads`` 1 as shipped, 2 as the machine sets BLAS up."""
    spent, original = _timed_schur()
    default_init = pool.ignore_interrupt
    if threads == 1:
        adjust = zoomwide.calibrate_zoom_wide
    else:  # the undecorated adjustment, workers without the one-thread limit
        adjust = zoomwide.calibrate_zoom_wide.__wrapped__
        pool.ignore_interrupt = _interrupt_only
    try:
        with threadpool_limits(threads, user_api="blas"):
            t = time.perf_counter()
            result = adjust(obs, sessions=sessions, workers=2, **kwargs)
            wall = time.perf_counter() - t
    finally:
        solver.schur_step = original
        pool.ignore_interrupt = default_init
    return result, wall, spent[0]


def _interrupt_only() -> None:
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench-blas-threads"))
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    ap.add_argument("--board-shape", default="print", choices=zoomwide.BOARD_SHAPES)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    blas = [(i["internal_api"], i["num_threads"]) for i in threadpool_info()
            if i["user_api"] == "blas"]
    print(f"BLAS libraries and their threads as set up: {blas}")
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=lambda m: None, report=False, zoom_wide=False)
    obs = dict(run.observations)
    # each step's capture day, as calibrate takes it from the image names (None: one session)
    sessions = {s: capture_date(list(o.names))[0] for s, o in obs.items()}
    sessions = None if None in sessions.values() else sessions
    kwargs = zoomwide.board_options(args.board_shape)
    rows = {1: [], 2: []}
    results = {}
    for _ in range(args.repeats):
        for threads in (2, 1):
            results[threads], wall, schur = _run(obs, sessions, kwargs, threads)
            rows[threads].append((wall, schur))
            print(f"BLAS threads {threads}: {wall:.1f} s wall, Schur steps {schur:.1f} s")
    one, two = (np.median(np.array(rows[k]), axis=0) for k in (1, 2))
    worst = max(abs(getattr(results[1].results[s], q) - getattr(results[2].results[s], q))
                / results[1].results[s].sd[q]
                for s in results[1].results for q in ("fx", "cx", "cy"))
    print(f"{len(obs)} steps, {sum(o.n_views for o in obs.values())} views, board "
          f"{args.board_shape}: one thread {one[0]:.1f} s (Schur {one[1]:.1f} s), two "
          f"{two[0]:.1f} s (Schur {two[1]:.1f} s): ratio {two[0] / one[0]:.2f} "
          f"(Schur {two[1] / max(one[1], 1e-9):.1f}); largest fx, cx, cy difference "
          f"{worst:.2g} sigma")


if __name__ == "__main__":
    main()
