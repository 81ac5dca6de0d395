"""How much of a tilted sensor's keystone a calibration takes into its principal point, over
the zoom range of ``laikin-10x``, and how well the linear response predicts it.

For each of 8 lens states (0-1) the axis-tilt set's views (10 views of a 9x6 board at 640 x 480,
12.9 um pixels, the poses :func:`zoomcalib.render.dataset.generate_poses` draws) are projected
through the exact lens on a sensor tilted by ``--tilt`` mrad, without noise, and calibrated
with OpenCV under three flag sets (default 5 terms; k3 fixed; k3 fixed and no tangential
terms). Printed per state and flag set: the calibrated principal point's move against the
untilted lens (px), the move :func:`zoomcalib.calibrate.opencv_backend.keystone_response`
predicts from the solution (``fx theta - diag(f) A eps``), and the absorption ``A`` (diagonal).
Last, the cost: one OpenCV calibration of 30 seeded views of a 22x15 board at 1280 x 720
(0.02 px noise), which includes the response, against the response alone (mean of 3).

``python benchmarks/keystone_absorption.py [--tilt 0.9,-0.4]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.opencv_backend import calibrate_opencv, keystone_response  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.camera import Sensor  # noqa: E402
from zoomcalib.optics.lens_camera import exact_mapping, tilted_sensor  # noqa: E402
from zoomcalib.optics.misalignment import Misalignment  # noqa: E402
from zoomcalib.optics.prescription import load_prescription  # noqa: E402
from zoomcalib.render.dataset import generate_poses, scaled_target_for_view  # noqa: E402
from zoomcalib.render.image import project_points  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

FLAG_SETS = {"5 terms": 0, "k3 fixed": cv2.CALIB_FIX_K3,
             "no p1 p2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST}
SENSOR = Sensor(640, 480, 0.0129)


def _observations(mapping, target, poses) -> Observations:
    pts = target.object_points
    return Observations(pts, [(np.arange(len(pts)), project_points(pts, mapping, R, t))
                              for R, t in poses], (SENSOR.width_px, SENSOR.height_px))


def set_views(mapping, z: float):
    """The axis-tilt set's board (scaled for ``mapping``'s focal length) and 10 poses seen
    through ``mapping``, seeded by the lens state ``z``."""
    target = scaled_target_for_view(parse_pattern("chessboard:9x6:25"), mapping.camera.fy,
                                    SENSOR, 2000.0, 0.6)
    return target, generate_poses(target, mapping, SENSOR, 10, 2000.0,
                                  np.random.default_rng(int(z * 100) + 1))


def _row(lens, z: float, theta: np.ndarray) -> str:
    still = Misalignment(np.zeros((len(lens.groups), 2)), np.zeros((len(lens.groups), 2)))
    aligned = exact_mapping(lens, z, still, SENSOR)
    tilted = tilted_sensor(aligned, lens, z, theta)
    target, poses = set_views(tilted, z)
    f_mm = aligned.camera.fx * SENSOR.pixel_pitch_mm
    out = f"{z:5.2f} {f_mm:6.1f} {f_mm / tilted.exit_pupil_mm:5.2f} |"
    for flags in FLAG_SETS.values():
        plain = calibrate_or_none(_observations(aligned, target, poses), flags)
        moved = calibrate_or_none(_observations(tilted, target, poses), flags)
        if plain is None or moved is None:
            out += f" {'(OpenCV: no sigma)':>38s} |"
            continue
        f = np.array([moved.fx, moved.fy])
        A = keystone_response([target.object_points] * len(poses), moved.K, moved.dist,
                              moved.rvecs, moved.tvecs, flags, 5)["absorption"]
        eps = theta * f * SENSOR.pixel_pitch_mm / tilted.exit_pupil_mm
        predicted = f * theta - f * (A @ eps)
        got = np.array([moved.cx - plain.cx, moved.cy - plain.cy])
        out += (f" {got[0]:6.2f} {got[1]:6.2f} {predicted[0]:6.2f} {predicted[1]:6.2f} "
                f"{A[0, 0]:5.2f} {A[1, 1]:5.2f} |")
    return out


def calibrate_or_none(obs: Observations, flags: int):
    """OpenCV's calibration, None when it refuses the result (no valid 1-sigma)."""
    try:
        return calibrate_opencv(obs, flags=flags)
    except RuntimeError:
        return None


def _cost() -> str:
    obj = parse_pattern("chessboard:22x15:20").object_points.astype(float)
    obj -= obj.mean(axis=0)
    rng = np.random.default_rng(0)
    K = np.array([[2300.0, 0, 640], [0, 2300.0, 360], [0, 0, 1]])
    views = []
    for _ in range(30):
        rvec = rng.normal(size=3)
        rvec *= np.deg2rad(25) / np.linalg.norm(rvec)
        uv = cv2.projectPoints(obj, rvec, np.array([0, 0, 1100.0]), K,
                               np.array([-0.1, 0, 0, 0, 0]))[0].reshape(-1, 2)
        views.append((np.arange(len(obj)), uv + rng.normal(0, 0.02, uv.shape)))
    t0 = time.perf_counter()
    res = calibrate_opencv(Observations(obj, views, (1280, 720)))
    t1 = time.perf_counter()
    for _ in range(3):
        keystone_response([obj] * 30, res.K, res.dist, res.rvecs, res.tvecs)
    t2 = time.perf_counter()
    return (f"cost, 30 views x 330 corners: calibrate_opencv {t1 - t0:.3f} s (response "
            f"included), keystone_response {(t2 - t1) / 3:.3f} s")


def milli_pair(text: str) -> np.ndarray:
    """``"X,Y"`` in milli-units (mrad, um) -> (2,) in units (rad, mm); an argparse type."""
    try:
        pair = np.array([float(v) for v in text.split(",")])
    except ValueError:
        pair = np.zeros(0)
    if pair.shape != (2,):
        raise argparse.ArgumentTypeError(f"expected two numbers X,Y, got {text!r}")
    return 1e-3 * pair


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tilt", type=milli_pair, default="0.9,-0.4", help="TX,TY mrad")
    theta = ap.parse_args().tilt
    lens = load_prescription("laikin-10x")
    head = " | ".join(f"{name:^38s}" for name in FLAG_SETS)
    print(f"{'z':>5s} {'f mm':>6s} {'f/L':>5s} | {head} |")
    print(f"{'':19s}|" + " moved cx, cy | predicted cx, cy |  A_xx  A_yy |" * len(FLAG_SETS))
    for z in np.linspace(0.0, 1.0, 8):
        print(_row(lens, float(z), theta))
    print(_cost())


if __name__ == "__main__":
    main()
