"""Time of writing ``report.html`` for a synthetic zoom set:
``python benchmarks/bench_report.py [--steps 10] [--views 12] [--repeat 3]``.

The set (:func:`zoomcalib.calibrate.synthetic.sweep_detections`, seed 0) is calibrated per step
with OpenCV, with the two-halves check (so every step has both maps), outside the timed part;
the timed part is :func:`zoomcalib.calibrate.report.write_report` (figures, uncertainty maps,
HTML), after one untimed run that imports matplotlib. Prints the best wall and CPU time of
``--repeat`` runs: the machines are shared, and CPU time is the steadier of the two.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from zoomcalib.calibrate.report import write_report  # noqa: E402
from zoomcalib.calibrate.synthetic import calibrated_run, sweep_detections  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sweep = sweep_detections(np.random.default_rng(0), steps=args.steps, views=args.views)
    run = calibrated_run(sweep, "opencv", cross_validate=True)
    with tempfile.TemporaryDirectory() as out:
        write_report(run, out)
        walls, cpus = [], []
        for _ in range(args.repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            path = write_report(run, out)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
        size = path.stat().st_size
    print(f"report.html of {args.steps} steps x {args.views} views ({size / 1e6:.1f} MB): "
          f"best of {args.repeat}: wall {min(walls):.2f} s, CPU {min(cpus):.2f} s")


if __name__ == "__main__":
    main()
