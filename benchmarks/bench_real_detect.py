"""The corner detectors on a real camera's frames: time per frame, fallbacks, fit residual.

``python benchmarks/bench_real_detect.py FOLDER [--pattern chessboard:22x15:25] [--frames 6]``

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
    args = ap.parse_args()
    target = parse_pattern(args.pattern)
    steps = sorted((p for p in args.folder.iterdir() if p.is_dir()),
                   key=lambda p: (len(p.name), p.name))
    print(f"machine: {platform.processor() or platform.machine()}, one process; "
          f"{args.frames} frames per step")
    print(f"{'step':>9} " + " ".join(f"{m + ' s':>9}" for m in METHODS)
          + f" {'model/sb':>8} {'fallback':>9} {'resid DN':>8} {'blur px':>7}")
    total = {m: 0.0 for m in METHODS}
    counts = {"frames": 0, "corners": 0, "fallback": 0}
    residuals = []
    for step in steps:
        files = image_files(step)[:args.frames]
        times = {m: [] for m in METHODS}
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
    n = max(counts["frames"], 1)
    print(f"{'all':>9} " + " ".join(f"{total[m] / n:9.3f}" for m in METHODS)
          + f" {total['model'] / total['sb']:8.2f} "
          f"{100 * counts['fallback'] / max(counts['corners'], 1):8.2f}% "
          f"{np.median(residuals):8.1f}")


if __name__ == "__main__":
    main()
