"""OpenCV's reported 1-sigmas against the scatter over repeated noise draws, long and short end.

``python benchmarks/bench_opencv_sd.py [--fx 23000] [--k1 14.4] [--tilt 3] [--draws 25]``

One set of 10 views of the 22 x 15 board (1280 x 720, tilted at most ``--tilt`` degrees: the
poses of :func:`zoomcalib.render.sweep.sweep_poses`) through radial distortion ``k1`` (14.4:
the Zoom-Nikkor 80-400's pincushion at 400 mm in lensfun), the true image points from the
renderer's camera model (not OpenCV's projection); ``--draws`` times fresh Gaussian noise of
0.01 px, each calibrated by per-step OpenCV as ``zoomcalib calibrate --per-step`` runs it
(:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_robust`, five terms, multi-start
within 15 degrees of fronto-parallel).

Printed for fx, cx, cy: the standard deviation over the draws (what an honest 1-sigma
predicts), the median of OpenCV's own 1-sigma, the median of the reported one (the full
inverse where OpenCV's was truncated, ``info['sd_check']``), and how many draws ended more than
5 % from the true fx.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.opencv_backend import calibrate_opencv_robust  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.camera import CameraModel  # noqa: E402
from zoomcalib.render.image import camera_mapping, project_points  # noqa: E402
from zoomcalib.render.sweep import SWEEP_SENSOR, sweep_poses  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

NAMES = ("fx", "cx", "cy")


def true_views(fx: float, k1: float, tilt_deg: float, seed: int):
    """The board's object points and its true image points (10 views, px)."""
    target = parse_pattern("chessboard:22x15:20")
    cam = CameraModel(fx, fx, 652.0, 334.0, np.array([k1, 0, 0, 0, 0]), SWEEP_SENSOR)
    poses = sweep_poses(target, cam, 10, tilt_deg, np.random.default_rng(seed))
    return target.object_points, [project_points(target.object_points, camera_mapping(cam), R, t)
                                  for R, t in poses]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fx", type=float, default=23000.0)
    ap.add_argument("--k1", type=float, default=14.4)
    ap.add_argument("--tilt", type=float, default=3.0, help="largest view tilt, degrees")
    ap.add_argument("--draws", type=int, default=25)
    ap.add_argument("--noise", type=float, default=0.01, help="px per coordinate")
    ap.add_argument("--seed", type=int, default=2, help="seed of the poses")
    a = ap.parse_args()
    points, clean = true_views(a.fx, a.k1, a.tilt, a.seed)
    rows, flagged = [], 0
    for d in range(a.draws):
        rng = np.random.default_rng(100 + d)
        views = [(np.arange(len(uv)), uv + rng.normal(0, a.noise, uv.shape)) for uv in clean]
        res = calibrate_opencv_robust(
            Observations(points, views, (1280, 720), [f"v{i}" for i in range(10)]),
            fronto_parallel_deg=15.0)
        check = res.info.get("sd_check")
        own = check["opencv_sd"] if check else res.sd
        flagged += check is not None
        rows.append([res.fx, res.cx, res.cy, *(own[n] for n in NAMES), *(res.sd[n] for n in NAMES)])
    rows = np.array(rows)
    print(f"# fx {a.fx:g} px, k1 {a.k1:g}, tilt <= {a.tilt:g} deg, {a.draws} draws of "
          f"{a.noise:g} px; OpenCV's sd replaced by the full inverse's in {flagged} draws")
    print(f"{'':>4s} {'spread':>9s} {'OpenCV sd':>10s} {'reported':>9s} {'spread/rep':>10s}")
    for i, name in enumerate(NAMES):
        spread = rows[:, i].std(ddof=1)
        own, reported = np.median(rows[:, 3 + i]), np.median(rows[:, 6 + i])
        print(f"{name:>4s} {spread:9.3f} {own:10.4f} {reported:9.3f} {spread / reported:10.2f}")
    off = np.abs(rows[:, 0] / a.fx - 1) > 0.05
    print(f"# fx more than 5 % off in {int(off.sum())} of {a.draws} draws"
          + (f": {', '.join(f'{v:.0f}' for v in rows[off, 0])}" if off.any() else ""))


if __name__ == "__main__":
    main()
