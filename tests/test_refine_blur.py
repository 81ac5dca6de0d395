"""The default detector (``model``) under motion blur, against OpenCV's SB detector.

The frames come from a brute-force renderer written here, sharing no code with the model in
``zoomcalib.detect.refine`` nor with ``zoomcalib.render``: a chessboard rotated and shifted by
seeded amounts is sampled on a grid of SS x SS sub-samples per pixel (each sub-sample holds the
exact area fraction of its little square on either side of the nearest grid line of each
family), convolved on that fine grid with a motion-blur kernel -- a uniform line segment (the
path of a steadily moving camera; not a Gaussian) convolved with a small lens Gaussian -- then
averaged down to pixels, with seeded Gaussian read noise and 8-bit rounding. The code under test
sees only the 8-bit frame and the pattern; the truth (the grid crossings) stays here.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from zoomcalib.detect import detect_image
from zoomcalib.detect.refine import refine_corners

SS = 8  # sub-samples per pixel axis
PITCH = 30.0  # square side, px
COLS, ROWS = 7, 5  # inner corners
LENS = 0.5  # sd of the lens Gaussian, px
DARK, LIGHT, NOISE = 30.0, 220.0, 2.0  # DN


def _soft_side(u: np.ndarray, normal: np.ndarray, h: float) -> np.ndarray:
    """Fraction of an h x h square centred at signed distance u from a line with unit normal
    ``normal`` lying on the positive side, mapped to [-1, 1]: the CDF at u of the sum of two
    uniforms of widths h|n_x| and h|n_y| (the square projected on the normal)."""
    lo = max(min(abs(normal[0]), abs(normal[1])) * h, 1e-6 * h)
    hi = max(abs(normal[0]), abs(normal[1])) * h
    s, d = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def ramp(t):
        return 0.5 * np.maximum(t, 0.0) ** 2

    frac = (ramp(u + s) - ramp(u + d) - ramp(u - d) + ramp(u - s)) / (lo * hi)
    return 2.0 * np.clip(frac, 0.0, 1.0) - 1.0


def _motion_kernel(length: float, angle: float) -> np.ndarray:
    """Uniform segment of ``length`` px at ``angle`` (rad, from +x towards +y) convolved with the
    lens Gaussian, sampled on the fine grid (rows along y), summing to 1."""
    half = int(np.ceil((0.5 * length + 4.0 * LENS) * SS)) + 1
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    t = np.linspace(-0.5, 0.5, 400) * length * SS
    x, y = half + t * np.cos(angle), half + t * np.sin(angle)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                      (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), w)  # bilinear splat of the segment's samples
    kernel = cv2.GaussianBlur(kernel, (0, 0), LENS * SS, borderType=cv2.BORDER_CONSTANT)
    return kernel / kernel.sum()


def render_board(rng: np.random.Generator, kernel: np.ndarray):
    """A rotated, shifted chessboard blurred by ``kernel``: (uint8 frame, truth (N, 2) px in
    the pattern's row-major order)."""
    rot = rng.uniform(-0.3, 0.3)
    c, s = np.cos(rot), np.sin(rot)
    width, height = int(PITCH * (COLS + 3)) + 40, int(PITCH * (ROWS + 3)) + 40
    centre = np.array([width, height]) / 2.0 + rng.uniform(-0.5, 0.5, 2)
    # board coordinates (in squares) of a point p: B = R^T (p - centre) / PITCH + offset
    offset = np.array([(COLS + 1) / 2.0, (ROWS + 1) / 2.0])
    xs = (np.arange(width * SS) + 0.5) / SS - 0.5
    ys = (np.arange(height * SS) + 0.5) / SS - 0.5
    px, py = xs[None, :] - centre[0], ys[:, None] - centre[1]
    bx = (c * px + s * py) / PITCH + offset[0]
    by = (-s * px + c * py) / PITCH + offset[1]
    # signed distance (px) to the nearest line of each family, positive on the odd-cell side
    sign = np.ones_like(bx)
    for b, normal in ((bx, (c, s)), (by, (-s, c))):
        u = (b - np.round(b)) * PITCH * np.where(np.round(b) % 2 == 0, 1.0, -1.0)
        sign = sign * _soft_side(u, normal, 1.0 / SS)
    inside = (bx > 0) & (bx < COLS + 1) & (by > 0) & (by < ROWS + 1)
    dark = np.where(inside, 0.5 * (1.0 + sign), 0.0)  # 1 on dark squares, 0 on white
    fine = LIGHT - (LIGHT - DARK) * dark
    fine = cv2.filter2D(fine, -1, kernel, borderType=cv2.BORDER_REPLICATE)
    image = fine.reshape(height, SS, width, SS).mean(axis=(1, 3))
    image += rng.normal(0.0, NOISE, image.shape)
    grid = np.stack(np.meshgrid(np.arange(1, COLS + 1), np.arange(1, ROWS + 1)), -1).reshape(-1, 2)
    b = (grid - offset) * PITCH
    truth = centre + np.column_stack([c * b[:, 0] - s * b[:, 1], s * b[:, 0] + c * b[:, 1]])
    return np.clip(np.round(image), 0, 255).astype(np.uint8), truth


def _errors(image: np.ndarray, truth: np.ndarray, method: str) -> np.ndarray:
    """Distance (px) of each detected corner to the nearest true corner; the detector must
    find the board and keep every corner of it (no fallback)."""
    det = detect_image(image, f"chessboard:{COLS}x{ROWS}:25", method)
    assert det.ok, det.error
    assert det.n_fallback == 0
    d = np.linalg.norm(det.points[:, None, :] - truth[None, :, :], axis=2)
    assert len(det.points) == len(truth)
    return d.min(axis=1)


def _rms(e: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean(np.concatenate(e) ** 2)))


@pytest.mark.parametrize("length", [4.0, 8.0])
def test_model_beats_sb_under_motion_blur(rng, length):
    """Four boards, 35 corners each, motion blur along a seeded random direction. The model's
    error is noise-limited (~0.008 px at this noise); SB's is ~0.03 px. With 140 corners the RMS
    of either is known to ~6 % (chi^2, 280 dof), so ``model <= SB`` holds by many standard
    errors unless the model misses the blur: at 8 px the isotropic 11 x 11 fit does (~0.04 px),
    at 4 px it still passes."""
    e_model, e_sb = [], []
    for _ in range(4):
        kernel = _motion_kernel(length, rng.uniform(0.0, np.pi))
        image, truth = render_board(rng, kernel)
        e_model.append(_errors(image, truth, "model"))
        e_sb.append(_errors(image, truth, "sb"))
    assert _rms(e_model) <= _rms(e_sb)


def test_anisotropy_not_chosen_for_an_isotropic_blur(rng):
    """A round blur (defocus: a uniform disc of radius 1.5 px with the lens Gaussian, not a
    Gaussian): the shared fit stays isotropic, so the corners come out exactly as with the
    isotropic model alone."""
    half = int(np.ceil((1.5 + 4.0 * LENS) * SS)) + 1
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1] / SS
    kernel = cv2.GaussianBlur((xx**2 + yy**2 <= 1.5**2).astype(float), (0, 0), LENS * SS)
    image, truth = render_board(rng, kernel / kernel.sum())
    det = detect_image(image, f"chessboard:{COLS}x{ROWS}:25", "sb")
    new = refine_corners(image, det.points, sigma="shared", max_window=12)
    iso = refine_corners(image, det.points, sigma="shared", max_window=12, anisotropic=False)
    cov = new.psf_cov[0]
    assert cov[0, 1] == 0.0 and cov[0, 0] == cov[1, 1]
    np.testing.assert_array_equal(new.points, iso.points)


def test_motion_blur_estimated_as_an_anisotropic_psf(rng):
    """The shared PSF is found anisotropic, with its major axis along the motion. The kernel's
    second moments are ``L^2 / 12 + lens^2`` along the segment and ``lens^2`` across it (sd
    ratio 2.5 at L = 4 px); a Gaussian fitted to the edges' ramps need not match those moments,
    so only the direction (within 0.1 rad: a median of 48 corners' own fits) and a sd ratio of
    at least 1.5 are required."""
    length, angle = 4.0, rng.uniform(0.0, np.pi)
    image, truth = render_board(rng, _motion_kernel(length, angle))
    det = detect_image(image, f"chessboard:{COLS}x{ROWS}:25", "sb")
    res = refine_corners(image, det.points, sigma="shared", max_window=12)
    w, v = np.linalg.eigh(res.psf_cov[0])
    assert np.sqrt(w[1] / w[0]) >= 1.5
    direction = np.arctan2(v[1, 1], v[0, 1])
    assert abs(np.sin(direction - angle)) < 0.1
    assert np.all(res.converged)
