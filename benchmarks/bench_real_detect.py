"""The corner detectors on a real camera's frames: time per frame, fallbacks, fit residual.

``python benchmarks/bench_real_detect.py FOLDER [--pattern chessboard:22x15:25] [--frames 6]
[--steps zoom_1x ...] [--calibrate]``

``FOLDER`` holds zoom-step subfolders of images (e.g. the ``calibration_images`` folder of the
public set ``e-cagan/camera-calibration``: frames of a PTZ camera's H.264 stream, sharpened in
the camera; it has no licence and is read where it lies). For the first ``--frames`` images of
every step, each detector runs in this one process on the same decoded image, so the times are
CPU seconds on one core and the ratios compare the detectors in the same run:

- ``model``, the default (OpenCV finds the corners, :func:`~zoomcalib.detect.refine.refine_corners`
  places them), with its fallbacks (corners whose fit failed and kept OpenCV's position);
- ``sb``, ``findChessboardCornersSB`` with ``CALIB_CB_ACCURACY`` (the peer);
- ``classic``, ``findChessboardCorners`` and ``cornerSubPix``.

The refiner's residual (RMS of the window pixels about its fitted model, grey levels, median
over corners) says how far the model is from the frames; on rendered frames of the same board
it is near the noise, 2-3 DN (``benchmarks/bench_detect_flags.py`` renders).

With ``--calibrate`` each step is also calibrated with plain OpenCV
(:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_robust`, five distortion terms)
on each detector's corners (a fallback corner left out): if the detectors' RMS and
intrinsics agree, the step's reprojection residual is not the detector's doing. ``--frames
0`` takes every frame; ``--steps`` chooses the steps.
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

from zoomcalib.calibrate.opencv_backend import (  # noqa: E402
    calibrate_opencv_robust,
    observations_from_detections,
)
from zoomcalib.detect import detect_image  # noqa: E402
from zoomcalib.detect.opencv import image_files  # noqa: E402
from zoomcalib.detect.refine import refine_corners  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

METHODS = ("model", "sb", "classic")


def _cpu(fn, *args, **kwargs):
    t = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--steps", nargs="+", default=None)
    ap.add_argument("--calibrate", action="store_true")
    args = ap.parse_args()
    target = parse_pattern(args.pattern)
    steps = sorted((p for p in args.folder.iterdir() if p.is_dir()
                    and (not args.steps or p.name in args.steps)),
                   key=lambda p: (len(p.name), p.name))
    calibrations = []
    print(f"machine: {platform.processor() or platform.machine()}, one process; "
          f"{args.frames} frames per step")
    print(f"{'step':>9} " + " ".join(f"{m + ' s':>9}" for m in METHODS)
          + f" {'model/sb':>8} {'fallback':>9} {'resid DN':>8} {'blur px':>7}")
    total = {m: 0.0 for m in METHODS}
    counts = {"frames": 0, "corners": 0, "fallback": 0}
    residuals = []
    for step in steps:
        files = image_files(step)[:args.frames or None]
        times = {m: [] for m in METHODS}
        detections = {m: [] for m in METHODS}
        fallback = corners = 0
        resid, blur = [], []
        for f in files:
            grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if grey is None:
                continue
            found = {}
            for m in METHODS:
                found[m], dt = _cpu(detect_image, grey, target, m, name=f.name)
                times[m].append(dt)
                if found[m].ok:
                    detections[m].append(found[m])
            det = found["model"]
            if not det.ok:
                continue
            corners += len(det.points)
            fallback += det.n_fallback
            fit = refine_corners(grey.astype(float), det.points, sigma="shared",
                                 window=5, max_window=12)
            resid.append(np.median(fit.rms[fit.converged]))
            blur.append(float(np.median(fit.sigma)))
        if not resid:
            print(f"{step.name:>9} no frame detected")
            continue
        mean = {m: float(np.mean(t)) for m, t in times.items()}
        for m in METHODS:
            total[m] += float(np.sum(times[m]))
        counts["frames"] += len(times["model"])
        counts["corners"] += corners
        counts["fallback"] += fallback
        residuals += resid
        print(f"{step.name:>9} " + " ".join(f"{mean[m]:9.3f}" for m in METHODS)
              + f" {mean['model'] / mean['sb']:8.2f} {100 * fallback / corners:8.2f}% "
              f"{np.median(resid):8.1f} {np.median(blur):7.2f}")
        if args.calibrate:
            calibrations += [_calibrated(step.name, m, detections[m], target) for m in METHODS]
    n = max(counts["frames"], 1)
    print(f"{'all':>9} " + " ".join(f"{total[m] / n:9.3f}" for m in METHODS)
          + f" {total['model'] / total['sb']:8.2f} "
          f"{100 * counts['fallback'] / max(counts['corners'], 1):8.2f}% "
          f"{np.median(residuals):8.1f}")
    if calibrations:
        print("plain OpenCV per step on each detector's corners (5 terms):")
        print("\n".join(calibrations))


def _calibrated(step: str, method: str, detections: list, target) -> str:
    """One line: the step calibrated with plain OpenCV on ``method``'s detections."""
    try:
        obs = observations_from_detections(detections, target, detections[0].image_size)
        r = calibrate_opencv_robust(obs)
    except (ValueError, RuntimeError, IndexError) as exc:
        return f"{step:>9} {method:>8}: not calibrated ({exc})"
    return (f"{step:>9} {method:>8}: {obs.n_views} views, RMS {r.rms_px:.3f} px, "
            f"fx {r.fx:.1f} ± {r.sd['fx']:.1f}, cx {r.cx:.1f} ± {r.sd['cx']:.1f}, "
            f"cy {r.cy:.1f} ± {r.sd['cy']:.1f}")


if __name__ == "__main__":
    main()
