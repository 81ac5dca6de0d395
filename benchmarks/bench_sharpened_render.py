"""The corner detectors on rendered frames sharpened and compressed as a PTZ camera's are.

``python benchmarks/bench_sharpened_render.py [--views 16] [--seeds 2] [--out DIR]
[--noise-dn 2]``

Each seed renders (:func:`zoomcalib.render.sweep.render_zoom_sweep`) one step of a 22 x 15-corner
chessboard (25 mm squares, fx 1500 px, 1280 x 720, tilts up to 40 degrees, ``--noise-dn``
of read noise (2 DN; the real PTZ frames' flat squares carry 6-10,
``docs/notes/performance-real-detector.md``),
0.8 px Gaussian blur) three times from the same seed, so the poses and the noise are the same:
``plain`` (PNG), ``sharpened`` (the camera's unsharp mask, 0.8 at 1.2 px, as
``render-sweep --sharpen 0.8,1.2``) and ``stream`` (sharpened, then JPEG at quality 85). Every
detector runs on every frame in this one process (CPU seconds on one core): ``model`` (the
default), ``sb`` (``findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``, the peer) and
``classic``. Per variant and detector: the RMS distance of the corners from the rendered truth
(px, both axes), CPU s per frame, the default's fallbacks and its fit residual (grey levels,
median over corners), split as ``bench_real_detect.py`` splits it (edge and flat pixels, the
edge pixels' mean by side), and the sharpened PSF the default fitted (median amount and
radius over the frames that chose it; ``sharp``: their share). The sharpened frames carry
the plain frames' information (an unsharp mask is invertible but for clipping and
rounding), so the default's error on them against its error on the plain ones (at the
Cramer-Rao bound, ``docs/notes/performance-real-detector.md``) is how far the sharpening costs it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.detect import detect_image  # noqa: E402
from zoomcalib.detect.refine import refine_corners  # noqa: E402
from zoomcalib.render.image import Radiometry  # noqa: E402
from zoomcalib.render.sweep import CaptureEffects, render_zoom_sweep  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_real_detect import residual_split  # noqa: E402, I001

PATTERN = "chessboard:22x15:25"
METHODS = ("model", "sb", "classic")
VARIANTS = {"plain": (None, None), "sharpened": ((0.8, 1.2), None),
            "stream": ((0.8, 1.2), 85)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("bench-sharpened"))
    ap.add_argument("--noise-dn", type=float, default=2.0)
    args = ap.parse_args()
    target = parse_pattern(PATTERN)
    stats = {(v, m): {"err": [], "cpu": [], "fallback": 0, "corners": 0, "resid": [],
                      "split": [], "psf": []}
             for v in VARIANTS for m in METHODS}
    for seed in range(args.seeds):
        for variant, (sharpen, quality) in VARIANTS.items():
            folder = args.out / f"seed{seed}_{variant}"
            truth = render_zoom_sweep(folder, fx_range=(1500.0, 1500.0), steps=1,
                                      views=args.views, size=(1280, 720), pattern=PATTERN,
                                      jpeg_quality=quality, seed=seed,
                                      effects=CaptureEffects(sharpen),
                                      radiometry=Radiometry(noise_sd=args.noise_dn / 255.0))
            for view in truth["steps"][0]["views"]:
                grey = cv2.imread(str(folder / view["file"]), cv2.IMREAD_GRAYSCALE)
                true = np.array(view["points_px"])
                for m in METHODS:
                    t = time.process_time()
                    det = detect_image(grey, target, m, name=view["file"])
                    s = stats[variant, m]
                    s["cpu"].append(time.process_time() - t)
                    if not det.ok:
                        continue
                    ok = np.ones(len(det.points), bool)
                    if m == "model" and det.fallback is not None:
                        ok = ~np.asarray(det.fallback, bool)
                    if m == "model":
                        s["fallback"] += int((~ok).sum())
                        fit = refine_corners(grey.astype(float), det.points, sigma="shared",
                                             window=5, max_window=12)
                        s["resid"].append(float(np.median(fit.rms[fit.converged])))
                        s["split"].append(residual_split(grey, fit))
                        psf = fit.sharpening
                        s["psf"].append((np.nan, np.nan) if psf is None
                                        else (psf.amount, psf.radius))
                    s["corners"] += len(det.points)
                    d = det.points[ok] - true[det.ids[ok]]
                    s["err"].append(d)
    print(f"{args.seeds} seeds x {args.views} views, fx 1500 px, 1280 x 720, {PATTERN}, "
          f"{args.noise_dn:g} DN read noise")
    print(f"{'variant':>10} {'detector':>8} {'RMS err px':>10} {'CPU s/frame':>11} "
          f"{'fallback':>8} {'resid DN':>8} {'edge':>5} {'flat':>5} {'edge mean':>9} "
          f"{'sharp':>5} {'amount':>6} {'radius':>6}")
    summary = {}
    for (variant, m), s in stats.items():
        err = np.concatenate(s["err"]) if s["err"] else np.zeros((0, 2))
        rms = float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")
        summary[f"{variant}/{m}"] = rms
        fallback = (f"{100 * s['fallback'] / max(s['corners'], 1):7.2f}%" if m == "model"
                    else f"{'':>8}")
        resid = f"{np.median(s['resid']):8.1f}" if s["resid"] else f"{'':>8}"
        if s["split"]:
            split = np.median(s["split"], axis=0)
            psf = np.array(s["psf"])
            chose = np.isfinite(psf[:, 0])
            fitted = np.median(psf[chose], axis=0) if chose.any() else (np.nan, np.nan)
            resid += (f" {split[0]:5.1f} {split[1]:5.1f} {split[2]:9.1f} {chose.mean():5.2f} "
                      f"{fitted[0]:6.2f} {fitted[1]:6.2f}")
        print(f"{variant:>10} {m:>8} {rms:10.4f} {np.mean(s['cpu']):11.3f} {fallback} {resid}")
    print("default's error, sharpened / plain: "
          f"{summary['sharpened/model'] / summary['plain/model']:.2f}; stream / plain: "
          f"{summary['stream/model'] / summary['plain/model']:.2f}; default / SB on the "
          f"stream: {summary['stream/model'] / summary['stream/sb']:.2f}")
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
