"""The corner detectors on a real camera's frames: time per frame, fallbacks, fit residual.

``python benchmarks/bench_real_detect.py FOLDER [--pattern chessboard:22x15:25] [--frames 6]
[--steps zoom_1x ...] [--calibrate] [--at-cap]``

``FOLDER`` holds zoom-step subfolders of images (e.g. the ``calibration_images`` folder of the
public set ``e-cagan/camera-calibration``: frames of a PTZ camera's H.264 stream, sharpened in
the camera; it has no licence and is read where it lies). For the first ``--frames`` images of
every step, each detector runs in this one process on the same decoded image, so the times are
CPU seconds on one core and the ratios compare the detectors in the same run:

- ``model``, the default (OpenCV finds the corners, :func:`~zoomcalib.detect.refine.refine_corners`
  places them), with its fallbacks (corners whose fit failed and kept OpenCV's position) and
  its time on the frames where it found the board (``found s``: a frame without a whole board
  costs the OpenCV searches that fail, SB's the longest);
- ``sb``, ``findChessboardCornersSB`` with ``CALIB_CB_ACCURACY`` (the peer);
- ``classic``, ``findChessboardCorners`` and ``cornerSubPix``.

The refiner's residual (RMS of the window pixels about its fitted model, grey levels, median
over corners) says how far the model is from the frames; on rendered frames of the same board
it is near the noise, 2-3 DN (``benchmarks/bench_detect_flags.py`` renders). It is split by
where the pixels lie (:func:`residual_split`): ``edge`` within 1 px of either edge, ``flat``
beyond 2.5 px of both (the squares' insides: noise, print, stains, compression), and the mean
residual of the edge pixels by their side (``edge mean``: a profile the model misses shows
there; edges that wander from pixel to pixel do not). ``sharp`` is the share of frames the
refiner fitted with a sharpened PSF (:class:`~zoomcalib.detect.cornermodel.SharpenedPSF`) and
``gain`` the sampled corners' median residual under their own sharpened PSFs over that under
their Gaussian blurs (``RefineResult.sharpening_gain``; 1: no better).

With ``--calibrate`` each step is also calibrated with plain OpenCV
(:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_robust`, five distortion terms)
on each detector's corners (a fallback corner left out): if the detectors' RMS and
intrinsics agree, the step's reprojection residual is not the detector's doing. ``--frames
0`` takes every frame; ``--steps`` chooses the steps.

With ``--at-cap`` the refiner's corners that converged only after using 30 iterations or more
(most of them at their cap, by the undamped step's test of
:func:`~zoomcalib.detect.refine._stationary_at_cap`) are compared with the same fit run with
400 iterations: their distance over their position sd (the root mean square of the two axes'
sds), median and largest.
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
from zoomcalib.detect.refine import (  # noqa: E402
    RefineResult,
    _extract,
    _window_grid,
    refine_corners,
    xjunction_image,
)
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
    ap.add_argument("--at-cap", action="store_true")
    args = ap.parse_args()
    target = parse_pattern(args.pattern)
    steps = sorted((p for p in args.folder.iterdir() if p.is_dir()
                    and (not args.steps or p.name in args.steps)),
                   key=lambda p: (len(p.name), p.name))
    calibrations = []
    print(f"machine: {platform.processor() or platform.machine()}, one process; "
          f"{args.frames} frames per step")
    print(f"{'step':>9} " + " ".join(f"{m + ' s':>9}" for m in METHODS)
          + f" {'model/sb':>8} {'found s':>8} {'fallback':>9} {'resid DN':>8} {'blur px':>7}"
          f" {'edge':>5} {'flat':>5} {'edge mean':>9} {'sharp':>5} {'gain':>5}")
    total = {m: 0.0 for m in METHODS}
    found_times: list[float] = []
    counts = {"frames": 0, "corners": 0, "fallback": 0}
    residuals, at_cap = [], []
    for step in steps:
        files = image_files(step)[:args.frames or None]
        times = {m: [] for m in METHODS}
        found_time = []
        detections = {m: [] for m in METHODS}
        fallback = corners = 0
        resid, blur, split, sharp, gain = [], [], [], [], []
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
            found_time.append(times["model"][-1])
            corners += len(det.points)
            fallback += det.n_fallback
            fit = refine_corners(grey.astype(float), det.points, sigma="shared",
                                 window=5, max_window=12)
            if args.at_cap:
                at_cap += _at_cap(grey, det.points, fit)
            resid.append(np.median(fit.rms[fit.converged]))
            blur.append(float(np.median(fit.sigma)))
            split.append(residual_split(grey, fit))
            sharp.append(fit.sharpening is not None)
            gain.append(fit.sharpening_gain)
        if not resid:
            print(f"{step.name:>9} no frame detected")
            continue
        mean = {m: float(np.mean(t)) for m, t in times.items()}
        for m in METHODS:
            total[m] += float(np.sum(times[m]))
        counts["frames"] += len(times["model"])
        found_times += found_time
        counts["corners"] += corners
        counts["fallback"] += fallback
        residuals += resid
        print(f"{step.name:>9} " + " ".join(f"{mean[m]:9.3f}" for m in METHODS)
              + f" {mean['model'] / mean['sb']:8.2f} {np.mean(found_time):8.3f} "
              f"{100 * fallback / corners:8.2f}% "
              f"{np.median(resid):8.1f} {np.median(blur):7.2f} "
              + " ".join(f"{v:5.1f}" for v in np.median(split, axis=0)[:2])
              + f" {np.median(split, axis=0)[2]:9.1f} {np.mean(sharp):5.2f} "
              f"{np.nanmedian(gain) if np.any(np.isfinite(gain)) else np.nan:5.2f}")
        if args.calibrate:
            calibrations += [_calibrated(step.name, m, detections[m], target) for m in METHODS]
    n = max(counts["frames"], 1)
    print(f"{'all':>9} " + " ".join(f"{total[m] / n:9.3f}" for m in METHODS)
          + f" {total['model'] / total['sb']:8.2f} {np.mean(found_times):8.3f} "
          f"{100 * counts['fallback'] / max(counts['corners'], 1):8.2f}% "
          f"{np.median(residuals):8.1f}")
    if args.at_cap:
        moved = np.asarray(at_cap)
        print(f"converged after 30 or more iterations: {len(moved)} corners; distance to the "
              f"fit with 400 iterations over their sd: median "
              f"{np.median(moved) if len(moved) else np.nan:.3f}, largest "
              f"{moved.max() if len(moved) else np.nan:.3f}")
    if calibrations:
        print("plain OpenCV per step on each detector's corners (5 terms):")
        print("\n".join(calibrations))


def _at_cap(grey: np.ndarray, points: np.ndarray, fit: RefineResult) -> list[float]:
    """Per corner of ``fit`` (the default refinement of ``points``) that converged after 30 or
    more iterations and also converges with 400: its distance to that fit over its position
    sd, ``sqrt(tr(cov) / 2)``."""
    long = refine_corners(grey.astype(float), points, sigma="shared", window=5, max_window=12,
                          max_iter=400)
    late = fit.converged & (fit.n_iter >= 30) & long.converged
    sd = np.sqrt(np.trace(long.cov[late], axis1=1, axis2=2) / 2)
    return list(np.linalg.norm(fit.points[late] - long.points[late], axis=1) / sd)


def residual_split(grey: np.ndarray, fit: RefineResult, window: int = 5
                   ) -> tuple[float, float, float]:
    """RMS residual (DN) of the converged corners' window pixels about their fitted model:
    within 1 px of either edge, beyond 2.5 px of both; and the RMS over the two sides of an
    edge of the edge pixels' mean residual (DN) on that side."""
    ok = fit.converged
    data, wts, origin = _extract(grey.astype(float), fit.points[ok], window)
    xy = _window_grid(window)
    local = fit.points[ok] - origin
    args = dict(angles=fit.angles[ok], contrast=fit.contrast[ok], offset=fit.offset[ok])
    psf = fit.sharpening
    if psf is None:
        model = xjunction_image(xy, local, sigma=fit.sigma[ok], **args)
    else:
        model = ((1 + psf.amount) * xjunction_image(xy, local, sigma=psf.sigma, **args)
                 - psf.amount * xjunction_image(xy, local, sigma=psf.wide, **args))
    resid = np.where(wts > 0, data - model, np.nan)
    dist = []
    for a in fit.angles[ok].T:
        n = np.column_stack([-np.sin(a), np.cos(a)])
        dist.append((xy[None, :, 0] - local[:, :1]) * n[:, :1]
                    + (xy[None, :, 1] - local[:, 1:]) * n[:, 1:])
    near = np.minimum(np.abs(dist[0]), np.abs(dist[1]))
    level = (model - fit.offset[ok, None]) / fit.contrast[ok, None]
    edge = near < 1.0
    sides = [np.nanmean(resid[edge & (level > 0.5)]), np.nanmean(resid[edge & (level <= 0.5)])]

    def rms(mask):
        return float(np.sqrt(np.nanmean(resid[mask] ** 2)))

    return rms(edge), rms(near > 2.5), float(np.sqrt(np.mean(np.square(sides))))


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
