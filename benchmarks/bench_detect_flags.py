"""Chessboard detectors and OpenCV flags against rendered truth: which is the most accurate?

``python benchmarks/bench_detect_flags.py [--views N] [--seed S] [--jpeg Q]``

Renders 1280 x 720 views of a 22 x 15 chessboard (330 corners, 20 mm squares) through a pinhole
camera with barrel distortion (fx 1100 px, k1 -0.1), tilts up to 25 deg, with the analytic
renderer (exact edge coverage, Gaussian PSF of 0.7 px before pixel integration), read noise
2 DN, 8 bits, optionally JPEG-compressed. Each detector runs on the same images; printed: RMS and
largest corner error against the renderer's truth, the ratio of the RMS to the Cramér-Rao bound
of the same corners (the bound of the refiner's image model with the blur known), and the time
per image on one worker (read the ratios: machines are shared).

Rows: ``findChessboardCornersSB`` with each flag combination, ``classic``
(findChessboardCorners + cornerSubPix) and ``model`` (the model fit of
:mod:`zoomcalib.detect.refine`).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.camera import CameraModel, Sensor  # noqa: E402
from zoomcalib.detect import detect_image  # noqa: E402
from zoomcalib.detect.report import chessboard_crlb  # noqa: E402
from zoomcalib.render.image import Optics, Radiometry, camera_mapping, render_image  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

PATTERN = "chessboard:22x15:20"
SB_FLAGS = {
    "SB (no flags)": 0,
    "SB ACCURACY": cv2.CALIB_CB_ACCURACY,
    "SB NORMALIZE_IMAGE": cv2.CALIB_CB_NORMALIZE_IMAGE,
    "SB ACCURACY|NORMALIZE_IMAGE": cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE,
    "SB ACCURACY|EXHAUSTIVE": cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE,
    "SB ACCURACY|LARGER": cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER,
}


def render_views(n_views: int, seed: int, jpeg: int | None):
    """Images and true corners of ``n_views`` random views (see the module docstring)."""
    rng = np.random.default_rng(seed)
    sensor = Sensor(1280, 720, 0.003)
    fx = 1100.0
    cam = CameraModel(fx, fx, 652.0, 347.0, np.array([-0.1, 0.05, 0.0, 0.0, 0.0]), sensor)
    target = parse_pattern(PATTERN)
    centre = target.object_points.mean(axis=0)
    radiometry = Radiometry(noise_sd=2.0 / 255.0)
    views = []
    for i in range(n_views):
        angles = np.deg2rad([rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(-8, 8)])
        R = cv2.Rodrigues(angles)[0]
        distance = fx * 18 * 20 / 720 * rng.uniform(1.12, 1.3)  # the board fills the height
        t = np.array([rng.uniform(-20, 20), rng.uniform(-10, 10), distance]) - R @ centre
        view = render_image(target, camera_mapping(cam), R, t, sensor, Optics(blur_px=0.7),
                            radiometry, rng=seed * 1000 + i)
        image = view.image
        if jpeg:
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg])
            image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        views.append((image, view.points_px, view.sigma_px))
    return target, radiometry, views


def sb_corners(image: np.ndarray, target, flags: int):
    """findChessboardCornersSB with ``flags``, in the board's order, or None."""
    from zoomcalib.detect.opencv import _normalise_order

    ok, corners = cv2.findChessboardCornersSB(image, tuple(target.pattern_size), flags=flags)
    if not ok:
        return None
    return _normalise_order(np.asarray(corners, float).reshape(-1, 2), target, image)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jpeg", type=int, default=None, help="JPEG quality (default: none)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    target, rm, views = render_views(args.views, args.seed, args.jpeg)
    bound = np.concatenate([chessboard_crlb(pts, target.pattern_size, s, rm.noise_sd,
                                            rm.white - rm.black, 1 / 255) for _, pts, s in views])
    crlb = float(np.sqrt(np.mean(bound**2)))
    runs = {name: (lambda img, f=f: sb_corners(img, target, f)) for name, f in SB_FLAGS.items()}
    for method in ("classic", "model"):
        runs[method] = lambda img, m=method: _points(detect_image(img, target, m))
    print(f"# {args.views} views 1280x720, {PATTERN}, blur 0.7 px, noise 2 DN, "
          f"jpeg {args.jpeg or 'none'}, seed {args.seed}")
    print(f"# machine: {platform.machine()} {platform.python_version()}, "
          f"numpy {np.__version__}, OpenCV {cv2.__version__}; one thread")
    print(f"{'detector':30s} {'found':>6s} {'RMS px':>8s} {'max px':>8s} {'RMS/CRLB':>9s} "
          f"{'s/image':>8s}")
    for name, run in runs.items():
        errors, times, found = [], [], 0
        for image, truth, _ in views:
            t0 = time.perf_counter()
            pts = run(image)
            times.append(time.perf_counter() - t0)
            if pts is not None:
                found += 1
                errors.append(np.linalg.norm(pts - truth, axis=1))
        e = np.concatenate(errors) if errors else np.array([np.nan])
        rms = float(np.sqrt(np.mean(e**2)))
        print(f"{name:30s} {found:3d}/{len(views):<2d} {rms:8.4f} {e.max():8.3f} "
              f"{rms / crlb:9.2f} {np.mean(times):8.3f}")
    print(f"{'Cramer-Rao bound':30s} {'':6s} {crlb:8.4f}")


def _points(det):
    return det.points if det.ok and len(det.points) == len(det.ids) else None


if __name__ == "__main__":
    main()
