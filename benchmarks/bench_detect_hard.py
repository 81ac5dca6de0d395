"""The default chessboard detector on hard frames: time and accuracy per condition, against SB.

``python benchmarks/bench_detect_hard.py [--views N] [--seed S] [--only NAME ...] [--real]``

Renders (seeded) 1280 x 720 frames of a 22 x 15 chessboard (330 corners) near fronto-parallel
through a pinhole camera with barrel distortion, under one hard condition at a time: strong
Gaussian blur or defocus, motion blur (elliptical PSF), JPEG quality 40-60, read noise 4-8 DN,
vignetting with a lighting gradient, low contrast (40 DN between dark print and paper), the
board small (20 % of the frame) or filling and leaving the frame, views tilted 50-60 deg, and
all of these at once. ``model`` (the default method) and ``sb`` run on the same frames, one
thread. Printed per condition: seconds per frame of each, their ratio, RMS corner error
against the renderer's truth (corners both methods found, so the two RMS compare the same
corners), and the fraction of ``model``'s corners flagged as fallback.

``--real`` first times both methods on the real photos in ``tests/data/opencv-samples`` (13
frames, 640 x 480, 9 x 6 corners; best of 3 runs per frame): seconds per frame and per corner.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.camera import CameraModel, Sensor  # noqa: E402
from zoomcalib.detect import detect_image  # noqa: E402
from zoomcalib.render.image import (  # noqa: E402
    Optics,
    camera_mapping,
    project_points,
    psf_sigma_px,
    render_coverage,
)
from zoomcalib.targets import parse_pattern  # noqa: E402

PATTERN = "chessboard:22x15:20"
SENSOR = Sensor(1280, 720, 0.003)
FX = 1100.0


@dataclass(frozen=True)
class Condition:
    """One hard frame condition.

    ``fill`` is the board's height over the frame's height (the board with its border squares
    is 1.44 times as wide as high); ``tilt_deg`` the range of the tilt about a random in-plane
    axis; ``gradient`` the fractional fall of the illumination across the frame (left to right,
    linear); ``contrast_dn`` the swing between dark print and paper, DN; ``jpeg`` the quality
    (None: none); ``noise_dn`` the read noise sd, DN; ``shift`` the board's offset from the
    frame centre as a fraction of the frame (moves part of a large board out of the frame).
    """

    name: str
    optics: Optics = field(default_factory=lambda: Optics(blur_px=0.7))
    noise_dn: float = 2.0
    jpeg: int | None = None
    vignetting: float = 0.0
    gradient: float = 0.0
    contrast_dn: float = 196.0
    fill: float = 0.85
    tilt_deg: tuple[float, float] = (0.0, 10.0)
    shift: float = 0.0


CONDITIONS = (
    Condition("reference"),
    Condition("blur 1.5 px", Optics(blur_px=1.5)),
    Condition("blur 3 px", Optics(blur_px=3.0)),
    # defocus blur sigma 2.5 px (0.072 mm / (4 N) / pitch) with 10 % of the light in glare
    Condition("defocus 2.5 px + glare", Optics(blur_px=0.7, defocus_mm=0.072, psf="halo",
                                               halo_fraction=0.1, halo_sigma_px=8.0)),
    Condition("motion 3 px", Optics(blur_px=3.0, psf="elliptical", ellipse_ratio=0.25,
                                    ellipse_angle_deg=20.0)),
    Condition("jpeg 40", jpeg=40),
    Condition("noise 8 DN", noise_dn=8.0),
    Condition("vignetting+gradient", vignetting=0.6, gradient=0.5),
    Condition("contrast 40 DN", contrast_dn=40.0),
    Condition("board 20 %", fill=0.5),
    Condition("board fills, cut", fill=1.15, shift=0.06),
    Condition("tilt 50-60 deg", tilt_deg=(50.0, 60.0), fill=0.7),
    Condition("all hard", Optics(blur_px=2.0), noise_dn=6.0, jpeg=50, vignetting=0.4,
              gradient=0.4, contrast_dn=40.0),
)


def _pose(cond: Condition, rng: np.random.Generator, target) -> tuple[np.ndarray, np.ndarray]:
    """A pose (R, t) with the board's height ``cond.fill`` of the frame's, tilted by a random
    angle of ``cond.tilt_deg`` about a random in-plane axis, turned by up to 5 deg in plane."""
    ext = target.extent_mm
    centre = np.array([0.5 * (ext[0] + ext[2]), 0.5 * (ext[1] + ext[3]), 0.0])
    board_h = np.ptp(target.object_points[:, 1]) + 2 * (target.object_points[1, 0]
                                                      - target.object_points[0, 0])
    tilt = np.deg2rad(rng.uniform(*cond.tilt_deg))
    axis = rng.uniform(0, 2 * np.pi)
    R = cv2.Rodrigues(np.array([np.cos(axis), np.sin(axis), 0.0]) * tilt)[0]
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(rng.uniform(-5, 5))]))[0] @ R
    distance = FX * board_h / (cond.fill * SENSOR.height_px)
    direction = rng.uniform(0, 2 * np.pi)
    offset = cond.shift * distance * SENSOR.width_px / FX * np.array(
        [np.cos(direction), np.sin(direction)])
    t = np.array([offset[0], offset[1], distance]) - R @ centre
    return R, t


def render_frame(cond: Condition, seed: int, target):
    """One seeded frame of ``cond``: (8-bit image, true corners (330, 2) px, visible (330,))."""
    rng = np.random.default_rng(seed)
    cam = CameraModel(FX, FX, 652.0, 347.0, np.array([-0.1, 0.05, 0.0, 0.0, 0.0]), SENSOR)
    mapping = camera_mapping(cam)
    for _ in range(100):  # a pose that keeps the board in the frame unless it is meant to leave
        R, t = _pose(cond, rng, target)
        truth = project_points(target.object_points, mapping, R, t)
        visible = ((truth[:, 0] > 8) & (truth[:, 0] < SENSOR.width_px - 9)
                   & (truth[:, 1] > 8) & (truth[:, 1] < SENSOR.height_px - 9))
        # every pixel's ray must meet the board's plane well in front (no horizon in view)
        rays = np.column_stack([cam.unproject_normalized(np.array(
            [[0, 0], [SENSOR.width_px - 1, 0], [0, SENSOR.height_px - 1],
             [SENSOR.width_px - 1, SENSOR.height_px - 1]], float)), np.ones(4)])
        reach = (R[:, 2] @ t) / (rays @ R[:, 2])
        if np.all((reach > 0) & (reach < 20 * t[2])) and (cond.shift > 0 or np.all(visible)):
            break
    sigma = psf_sigma_px(cond.optics, SENSOR.pixel_pitch_mm)
    reflectance = render_coverage(target, mapping, R, t, SENSOR, sigma, optics=cond.optics)
    # illumination: vignetting (1 - v r^2, r = 1 at the frame's corner) times a linear fall
    # from left to right; the dark print and the paper are 40 DN and 40 + contrast DN where lit
    v, u = np.mgrid[0:SENSOR.height_px, 0:SENSOR.width_px].astype(float)
    cu, cv_ = (SENSOR.width_px - 1) / 2, (SENSOR.height_px - 1) / 2
    r2 = ((u - cu) ** 2 + (v - cv_) ** 2) / (cu**2 + cv_**2)
    light = (1 - cond.vignetting * r2) * (1 - cond.gradient * u / (SENSOR.width_px - 1))
    light /= light.max()
    dark = 20.0 if cond.contrast_dn >= 150 else 100.0
    signal = (dark + cond.contrast_dn * reflectance) * light
    signal += rng.normal(0.0, cond.noise_dn, signal.shape)
    image = np.clip(np.round(signal), 0, 255).astype(np.uint8)
    if cond.jpeg:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, cond.jpeg])
        image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return image, truth, visible


def _timed(image: np.ndarray, target, method: str):
    t0 = time.perf_counter()
    det = detect_image(image, target, method)
    return det, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=2, help="frames per condition")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", default=None, help="condition names to run")
    ap.add_argument("--real", action="store_true", help="also time the real photos")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    target = parse_pattern(PATTERN)
    print(f"# {args.views} frames per condition, 1280x720, {PATTERN}, seed {args.seed}; "
          f"one thread")
    print(f"# machine: {platform.machine()}, {__import__('os').cpu_count()} cores, Python "
          f"{platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}")
    print("# RMS: px against the renderer's truth, over the corners model kept (not fallback) "
          "in frames both methods found; fallback: model's corners flagged")
    print(f"{'condition':24s} {'found m/sb':>10s} {'model s':>8s} {'sb s':>7s} {'m/sb':>6s} "
          f"{'model RMS':>10s} {'sb RMS':>8s} {'fallback':>9s}")
    if args.real:
        _time_real_photos()
    worst = 0.0
    for k, cond in enumerate(CONDITIONS):
        if args.only and cond.name not in args.only:
            continue
        t_m, t_s, e_m, e_s, n_fb, n_pts = [], [], [], [], 0, 0
        found_m = found_s = 0
        for i in range(args.views):
            image, truth, _ = render_frame(cond, args.seed * 10_000 + k * 100 + i, target)
            dm, tm = _timed(image, target, "model")
            ds, ts = _timed(image, target, "sb")
            t_m.append(tm)
            t_s.append(ts)
            found_m += dm.ok
            found_s += ds.ok
            if dm.ok:
                n_fb += dm.n_fallback
                n_pts += len(dm.ids)
            if dm.ok and ds.ok:
                keep = ~dm.fallback
                sb_at = dict(zip(ds.ids.tolist(), ds.points, strict=True))
                both = np.array([j in sb_at for j in dm.ids]) & keep
                e_m.append(np.linalg.norm(dm.points[both] - truth[dm.ids[both]], axis=1))
                e_s.append(np.linalg.norm(np.array([sb_at[j] for j in dm.ids[both]])
                                          - truth[dm.ids[both]], axis=1))
        rms_m = _rms(e_m)
        rms_s = _rms(e_s)
        worst = max(worst, max(t_m))
        fb = f"{n_fb / n_pts:9.3f}" if n_pts else f"{'-':>9s}"
        print(f"{cond.name:24s} {found_m:4d}/{found_s:<5d} {np.mean(t_m):8.3f} {np.mean(t_s):7.3f} "
              f"{np.mean(t_m) / np.mean(t_s):6.2f} {rms_m:10.4f} {rms_s:8.4f} {fb}", flush=True)
    print(f"# slowest model frame: {worst:.3f} s")


def _time_real_photos() -> None:
    """Seconds per frame and ms per corner of ``model`` and ``sb`` on the OpenCV sample photos."""
    files = sorted((ROOT / "tests" / "data" / "opencv-samples").glob("left*.jpg"))
    target = parse_pattern("chessboard:9x6:25")
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    for method in ("model", "sb"):
        times, corners, fallback = [], 0, 0
        for image in images:
            runs = [_timed(image, target, method) for _ in range(3)]
            times.append(min(t for _, t in runs))
            det = runs[0][0]
            corners += len(det.ids)
            fallback += det.n_fallback if det.ok else 0
        print(f"# real photos, {method:5s}: {len(images)} frames 640x480, {np.mean(times):.3f} s "
              f"per frame (max {np.max(times):.3f}), {1e3 * np.sum(times) / corners:.2f} ms per "
              f"corner, {corners} corners, {fallback} fallback", flush=True)


def _rms(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.array([np.nan])
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


if __name__ == "__main__":
    main()
