"""OpenCV's own start against the multi-start on long-end zoom steps: where each solve ends.

``python benchmarks/bench_long_end_start.py [--seeds 12] [--k1 14.4] [--fx 23000]``

Per seed: 10 views at fx ``--fx`` px, 1280 x 720, tilted at most 3 degrees (the long end of
:func:`zoomcalib.render.sweep.sweep_poses`), through radial distortion ``k1`` (default 14.4: the
Zoom-Nikkor 80-400 at 400 mm in lensfun, 1.5 % of the half-diagonal at the corner), the
22 x 15 board's true image points (the renderer's camera model, not OpenCV's projection) plus
0.01 px of Gaussian noise. Printed per seed and term set (k1; none): the focal length and RMS
of :func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv` from OpenCV's own start and of
:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_multistart`, with their times;
then how many own starts ended more than 5 % from the true fx, and the time ratio.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.opencv_backend import (  # noqa: E402
    calibrate_opencv,
    calibrate_opencv_multistart,
)
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.stepfits import _distortion_flags  # noqa: E402
from zoomcalib.camera import CameraModel  # noqa: E402
from zoomcalib.render.image import camera_mapping, project_points  # noqa: E402
from zoomcalib.render.sweep import SWEEP_SENSOR, sweep_poses  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402


def long_end_views(seed: int, fx: float, k1: float) -> Observations:
    target = parse_pattern("chessboard:22x15:20")
    cam = CameraModel(fx, fx, 652.0, 334.0, np.array([k1, 0, 0, 0, 0]), SWEEP_SENSOR)
    rng = np.random.default_rng(seed)
    views = []
    for R, t in sweep_poses(target, cam, 10, 3.0, rng):
        uv = project_points(target.object_points, camera_mapping(cam), R, t)
        views.append((np.arange(len(uv)), uv + rng.normal(0, 0.01, uv.shape)))
    return Observations(target.object_points, views, (1280, 720), [f"v{i}" for i in range(10)])


def _timed(fn, *args, **kwargs):
    t = time.perf_counter()
    try:
        result = fn(*args, **kwargs)
    except (ValueError, RuntimeError) as exc:
        return None, time.perf_counter() - t, str(exc)[:40]
    return result, time.perf_counter() - t, ""


def _show(result) -> str:
    return f"{result.fx:9.0f} {result.rms_px:8.4f}" if result else f"{'failed':>9s} {'':>8s}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--k1", type=float, default=14.4)
    ap.add_argument("--fx", type=float, default=23000.0)
    args = ap.parse_args()
    print(f"# fx {args.fx:g} px, k1 {args.k1:g}, 10 views tilted <= 3 deg, 0.01 px noise")
    print(f"{'seed':>4s} {'terms':>5s} {'own fx':>9s} {'own rms':>8s} {'multi fx':>9s} "
          f"{'multi rms':>9s}  own s  multi s")
    wrong = {"k1": 0, "none": 0}
    own_time = multi_time = 0.0
    for seed in range(args.seeds):
        obs = long_end_views(seed, args.fx, args.k1)
        for label, terms in (("k1", ("k1",)), ("none", ())):
            flags = _distortion_flags(terms)
            own, t_own, err = _timed(calibrate_opencv, obs, flags=flags)
            multi, t_multi, _ = _timed(calibrate_opencv_multistart, obs, flags=flags)
            own_time, multi_time = own_time + t_own, multi_time + t_multi
            wrong[label] += own is None or abs(own.fx / args.fx - 1) > 0.05
            print(f"{seed:4d} {label:>5s} {_show(own)} {_show(multi)} {t_own:6.2f} {t_multi:7.2f}"
                  + (f"  ({err})" if err else ""))
    print(f"# own start more than 5 % off the true fx: k1 {wrong['k1']} of {args.seeds}, none "
          f"{wrong['none']} of {args.seeds}; multi-start / own start time: "
          f"{multi_time / own_time:.1f}")


if __name__ == "__main__":
    main()
