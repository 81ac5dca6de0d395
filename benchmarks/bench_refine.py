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

``--model-accuracy`` prints instead the accuracy of the image model itself (no noise, no timing):
the Gauss-Legendre order of Sheppard's integral against Owen's T function (scipy), the pixel
quadrature and the variance-matched Gaussian pixel model against a 16-node rule, the product of
two erf edges against the exact blur, and the noise-free corner and dot errors of
``refine_corners`` and ``refine_dots`` on images of the independent brute-force renderer
(``--corners`` corners or dots per row). ``--crlb`` prints the Cramér-Rao bound of
``corner_crlb`` at the reference setting and around it.
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

from scipy.special import erf, ndtr, owens_t  # noqa: E402
from test_refine import (  # noqa: E402  (the independent renderer)
    _dot_mosaic,
    corner_mosaic,
    render_corner,
)

from zoomcalib.detect.crlb import corner_crlb  # noqa: E402
from zoomcalib.detect.refine import (  # noqa: E402
    bivariate_normal_cdf,
    refine_corners,
    refine_dots,
    xjunction_image,
)

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


# ---------------------------------------------------------------------------------------------
# --model-accuracy: the image model against exact references, no noise
# ---------------------------------------------------------------------------------------------
WINDOW_XY = np.stack(np.meshgrid(np.arange(-5, 6), np.arange(-5, 6)), -1).reshape(-1, 2) * 1.0


def bvn_cdf_owen(h, k, rho):
    """Phi_2(h, k; rho) from Owen's T function (h, k nonzero): an independent reference."""
    s = np.sqrt(1.0 - rho * rho)
    beta = np.where(h * k < 0, 0.5, 0.0)
    return (0.5 * ndtr(h) + 0.5 * ndtr(k) - owens_t(h, (k - rho * h) / (h * s))
            - owens_t(k, (h - rho * k) / (k * s)) - beta)


def print_sheppard_orders(rng):
    """Largest error of Sheppard's integral per Gauss-Legendre order and |rho| range."""
    h, k = rng.uniform(-4.0, 4.0, (2, 20000))
    print("Sheppard's integral against Owen's T (scipy), 20000 random (h, k) in [-4, 4]^2:")
    print(f"{'nodes':>6s} {'|rho| <=':>9s} {'max error':>10s}")
    for nodes, rho_max in ((6, 0.75), (10, 0.9), (16, 0.98)):
        rho = rng.uniform(-rho_max, rho_max, h.size)
        err = np.abs(bivariate_normal_cdf(h, k, rho, nodes) - bvn_cdf_owen(h, k, rho))
        print(f"{nodes:6d} {rho_max:9.2f} {err.max():10.1e}")


def window_corners(rng, n):
    """n X-junctions within the central pixel of an 11 x 11 window, edges 35-145 deg apart."""
    corners = rng.uniform(-0.5, 0.5, (n, 2))
    a1 = rng.uniform(0.0, np.pi, n)
    a2 = a1 + np.deg2rad(rng.uniform(35.0, 145.0, n))
    return corners, np.column_stack([a1, a2])


def print_pixel_models(rng, n=200):
    """Intensity error (contrast 1) of the pixel integration against a 16-node rule."""
    corners, angles = window_corners(rng, n)
    orders = (3, 4, 5, 6)
    print(f"\nPixel integration, max intensity error over {n} X-junctions in 11 x 11 windows "
          "(contrast 1), against a 16-node rule:")
    print(f"{'sigma':>6s} " + " ".join(f"{'n_sub=' + str(o):>9s}" for o in orders)
          + f" {'gaussian max':>13s} {'gaussian RMS':>13s}")
    for sigma in (0.25, 0.3, 0.4, 0.55, 0.7, 1.0):
        ref = xjunction_image(WINDOW_XY, corners, angles, sigma, n_sub=16)
        errs = [np.abs(xjunction_image(WINDOW_XY, corners, angles, sigma, n_sub=o) - ref).max()
                for o in orders]
        gauss = xjunction_image(WINDOW_XY, corners, angles, sigma, pixel_model="gaussian") - ref
        print(f"{sigma:6.2f} " + " ".join(f"{e:9.1e}" for e in errs)
              + f" {np.abs(gauss).max():13.1e} {np.sqrt(np.mean(gauss**2)):13.1e}")


def print_erf_product(sigma=SIGMA):
    """Largest departure of the product of two erf edges from the exact blurred X-junction."""
    print(f"\nProduct of two erf edges against the exact blur, corner at the centre of an 11 x 11 "
          f"window, sigma {sigma} px, contrast 1:")
    print(f"{'angle between edges':>20s} {'max error':>10s}")
    s_eff = np.sqrt(sigma**2 + 1.0 / 12.0)
    for deg in (90.0, 70.0, 55.0):
        angles = np.array([0.3, 0.3 + np.deg2rad(deg)])
        exact = xjunction_image(WINDOW_XY, [0.0, 0.0], angles, sigma, n_sub=8)
        normals = np.column_stack([-np.sin(angles), np.cos(angles)])
        u = WINDOW_XY @ normals.T / (np.sqrt(2.0) * s_eff)
        naive = 0.5 * (1.0 - erf(u[:, 0]) * erf(u[:, 1]))
        print(f"{deg:16.0f} deg {np.abs(naive - exact).max():10.3f}")


def max_corner_error(img, truth, init, **kw):
    res = refine_corners(img, init, **kw)
    return float(np.hypot(*(res.points - truth).T).max())


def print_corner_errors(rng, n):
    """Noise-free corner position errors of refine_corners on brute-force rendered images."""
    fits = {"quadrature (auto n_sub)": {}, "quadrature n_sub=3": {"n_sub": 3},
            "gaussian pixel model": {"pixel_model": "gaussian"}}
    print(f"\nNoise-free corners ({n} per row, brute-force renderer, edges 35-145 deg apart, "
          "blur fitted per corner), max position error, px:")
    print(f"{'sigma':>6s} " + " ".join(f"{name:>24s}" for name in fits))
    for sigma in (0.3, 0.5, 0.7, 1.0, 1.6):
        img, truth, init, _, _ = corner_mosaic(rng, n, noise=0.0, sigma=sigma, min_angle=35.0)
        errs = [max_corner_error(img, truth, init, **kw) for kw in fits.values()]
        print(f"{sigma:6.2f} " + " ".join(f"{e:24.1e}" for e in errs))


def print_dot_errors(rng, n, sigma=0.8):
    """Noise-free centre and semi-axis errors of refine_dots on brute-force rendered ellipses."""
    print(f"\nNoise-free dots ({n} per row, brute-force renderer, sigma {sigma} px, aspect "
          "0.6-1, blur fitted), px:")
    print(f"{'semi-major':>10s} {'min semi-minor':>15s} {'max centre error':>17s} "
          f"{'max axis error':>15s}")
    for radius in (5.5, 4.0, 3.0):
        img, truth, axes, _, _ = _dot_mosaic(rng, n, noise=0.0, sigma=sigma, radius=radius)
        init = truth + rng.uniform(-0.5, 0.5, truth.shape)
        res = refine_dots(img, init, radius)
        centre = np.hypot(*(res.centres - truth).T).max()
        axis = np.abs(res.axes - axes).max()
        print(f"{radius - 1:4.1f}-{radius + 1:<5.1f} {axes[:, 1].min():15.2f} {centre:17.1e} "
              f"{axis:15.3f}")


def model_accuracy(n, seed):
    rng = np.random.default_rng(seed)
    print(f"# image model accuracy, seed {seed}")
    print_sheppard_orders(rng)
    print_pixel_models(rng)
    print_erf_product()
    print_corner_errors(rng, n)
    print_dot_errors(rng, n)


def print_crlb():
    """corner_crlb's radial bound at the reference setting and one change at a time."""
    ref = {"sigma_psf": 0.7, "noise_sd": 2.0 / 255.0, "contrast": 1.0,
           "angles": [0.0, np.pi / 2], "window": 5, "quant_step": 1.0 / 255.0}
    rows = {
        "reference (8-bit)": {},
        "no quantisation term": {"quant_step": 0.0},
        "edges at 45 deg to the grid": {"angles": [np.pi / 4, 3 * np.pi / 4]},
        "corner half a pixel off-centre": {"offset": [0.5, 0.5]},
        "contrast 0.8": {"contrast": 0.8},
        "blur 1.0 px": {"sigma_psf": 1.0},
        "blur 1.1 px": {"sigma_psf": 1.1},
        "7 x 7 window": {"window": 3},
        "blur fitted": {"fit_sigma": True},
    }
    print("# corner_crlb: noise 2/255, contrast 1, blur 0.7 px, 11 x 11 window, square corner, "
          "8-bit quantisation; one change per row")
    print(f"{'setting':32s} {'radial px':>10s}")
    for name, change in rows.items():
        print(f"{name:32s} {float(corner_crlb(**{**ref, **change}).radial_rms):10.4f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model-accuracy", action="store_true",
                    help="print the image model's noise-free accuracy instead of the comparison")
    ap.add_argument("--corners", type=int, default=24,
                    help="corners (and dots) per row of --model-accuracy")
    ap.add_argument("--crlb", action="store_true",
                    help="print the corner Cramer-Rao bound around the reference setting")
    args = ap.parse_args(argv)
    if args.crlb:
        print_crlb()
        return
    if args.model_accuracy:
        model_accuracy(args.corners, args.seed)
        return
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
