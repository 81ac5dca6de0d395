"""Corner refinement: accuracy against ground truth and the Cramér-Rao bound, and speed against
OpenCV's ``cv2.cornerSubPix``: ``python benchmarks/bench_refine.py [--images N] [--seed S]``.

Each synthetic image is 1280 x 960, 8-bit, with a 10 x 8 chessboard-corner grid (squares of
about 60 px) seen under a random mild perspective, so the two edges at each corner have the
directions a homography gives them (not orthogonal). Within a 60 px square the neighbourhood of
a corner is exactly an X-junction, so each corner's 17 x 17 px neighbourhood is painted by the
independent brute-force renderer of ``tests/test_refine.py`` (32 x 32 sub-samples per pixel,
Gaussian blur sigma = 0.7 px on the fine grid, then pixel averaging), black 0.05 and white 0.95
on a 0..1 scale, plus Gaussian noise of sd 2/255, then rounded to 8 bits. Both refiners start
from the same initial corners (truth + uniform +-0.7 px) and use the same 11 x 11 window.

Printed: RMS radial error and mean error (bias) over all corners for ``refine_corners`` (default
and the fast ``pixel_model='gaussian'``) and ``cv2.cornerSubPix``, the Cramér-Rao bound for the
same corners (``corner_crlb``, with 8-bit quantisation as q^2/12 noise), and the time per image
(best of 3) with its ratio to cornerSubPix: these machines are shared and noisy, read the ratio.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout
sys.path.insert(0, str(ROOT / "tests"))

from test_refine import render_corner  # noqa: E402  (the independent renderer)

from zoomcalib.detect.crlb import corner_crlb  # noqa: E402
from zoomcalib.detect.refine import refine_corners  # noqa: E402

W, H = 1280, 960
COLS, ROWS, SQUARE = 10, 8, 60.0
SIGMA, NOISE, BLACK, WHITE = 0.7, 2.0 / 255.0, 0.05, 0.95
PATCH = 17


def random_homography(rng):
    """Board (mm-free square units) -> pixels: the grid centred, tilted up to ~25 deg."""
    board = np.array([[0, 0], [COLS + 1, 0], [COLS + 1, ROWS + 1], [0, ROWS + 1]], float) - 0.5
    board *= SQUARE
    board -= board.mean(axis=0)
    jitter = rng.uniform(-60, 60, (4, 2))  # corner displacements = perspective
    img_pts = board + jitter + (W / 2, H / 2) + rng.uniform(-60, 60, 2)
    return cv2.getPerspectiveTransform(board.astype(np.float32), img_pts.astype(np.float32))


def apply_h(h, pts):
    p = np.column_stack([pts, np.ones(len(pts))]) @ h.T
    return p[:, :2] / p[:, 2:]


def synth_image(rng):
    hmat = random_homography(rng)
    i, j = np.meshgrid(np.arange(1, COLS + 1), np.arange(1, ROWS + 1))
    board = (np.column_stack([i.ravel(), j.ravel()]) - 0.5) * SQUARE
    board -= np.array([COLS + 1, ROWS + 1]) * SQUARE / 2 - SQUARE / 2
    truth = apply_h(hmat, board)
    # edge directions: images of the board's x and y directions at each corner
    ex = apply_h(hmat, board + (1.0, 0.0)) - truth
    ey = apply_h(hmat, board + (0.0, 1.0)) - truth
    angles = np.column_stack([np.arctan2(ex[:, 1], ex[:, 0]), np.arctan2(ey[:, 1], ey[:, 0])])
    img = np.full((H, W), 0.5 * (BLACK + WHITE))
    parity = (i.ravel() + j.ravel()) % 2
    for k, (c, ang) in enumerate(zip(truth, angles, strict=True)):
        x0, y0 = int(np.rint(c[0])) - PATCH // 2, int(np.rint(c[1])) - PATCH // 2
        patch = render_corner(c - (x0, y0), ang, SIGMA, PATCH)
        if parity[k]:
            patch = 1.0 - patch
        img[y0 : y0 + PATCH, x0 : x0 + PATCH] = BLACK + (WHITE - BLACK) * patch
    img += rng.normal(0.0, NOISE, img.shape)
    img8 = np.clip(np.rint(255.0 * img), 0, 255).astype(np.uint8)
    init = truth + rng.uniform(-0.7, 0.7, truth.shape)
    return img8, truth, init, angles


def best_of(fn, args, repeat=3):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t)
    return min(times), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    methods = {
        "refine_corners": lambda img, init: refine_corners(img, init).points,
        "refine_corners (gaussian)": lambda img, init: refine_corners(
            img, init, pixel_model="gaussian"
        ).points,
        "cv2.cornerSubPix 11x11": lambda img, init: cv2.cornerSubPix(
            img, init.astype(np.float32).reshape(-1, 1, 2), (5, 5), (-1, -1), criteria
        ).reshape(-1, 2),
    }
    errs = {m: [] for m in methods}
    times = {m: [] for m in methods}
    bound_var = []
    for _ in range(args.images):
        img8, truth, init, angles = synth_image(rng)
        for name, fn in methods.items():
            t, pts = best_of(fn, (img8, init.copy()))
            errs[name].append(pts - truth)
            times[name].append(t)
        b = corner_crlb(SIGMA, NOISE * 255, (WHITE - BLACK) * 255, angles, 5,
                        offset=truth - np.rint(init), quant_step=1.0)
        bound_var.append(b.radial_rms**2)
    crlb = float(np.sqrt(np.mean(np.concatenate(bound_var))))
    peer = np.median(times["cv2.cornerSubPix 11x11"])
    n = COLS * ROWS
    print(f"# corner refinement: {args.images} images {W}x{H}, {n} corners each, 8-bit, "
          f"noise {NOISE * 255:.0f}/255, blur {SIGMA} px, contrast {WHITE - BLACK:.2f}, "
          f"window 11x11, seed {args.seed}")
    print(f"# machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}")
    hdr = (f"{'method':28s} {'RMS px':>9s} {'bias x':>9s} {'bias y':>9s} {'RMS/CRLB':>9s} "
           f"{'ms/image':>9s} {'time ratio':>10s}")
    print(hdr)
    print("-" * len(hdr))
    for name in methods:
        e = np.concatenate(errs[name])
        rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        bias = e.mean(axis=0)
        t = float(np.median(times[name]))
        print(f"{name:28s} {rms:9.5f} {bias[0]:+9.5f} {bias[1]:+9.5f} {rms / crlb:9.2f} "
              f"{1e3 * t:9.2f} {t / peer:10.1f}")
    print(f"{'Cramer-Rao bound':28s} {crlb:9.5f} {'':9s} {'':9s} {1.0:9.2f}")


if __name__ == "__main__":
    main()
