"""Cramér-Rao lower bounds for the position of a chessboard corner and of a dot centre.

The image model is the one the refiner fits (:mod:`zoomcalib.detect.refine`): the ideal pattern
blurred by a Gaussian PSF of sd ``sigma`` px, integrated over 1 x 1 px pixels, scaled
``I = b + a P``, plus independent Gaussian noise of sd ``noise_sd`` per pixel (same units as
``a``). With ``J`` the ``(M, P)`` Jacobian of the ``M`` window pixels with respect to all ``P``
model parameters ``theta`` (position, edge angles or ellipse shape, ``a``, ``b`` and, optionally,
``log sigma``), the Fisher information and the bound are

    F = J^T J / noise_sd^2,        Cov(theta_hat) >= F^-1,

and the bound on the position is the 2 x 2 position block of the *full* inverse, so the unknown
nuisance parameters (angles, contrast, offset, blur) cost what they cost. ``radial_rms =
sqrt(trace)`` is the bound on the RMS of the 2-D position error.

Quantisation to integer grey levels with step ``q`` is, for noise wider than about ``q / 2``,
well approximated by extra uniform noise of variance ``q^2 / 12``; ``quant_step`` adds it.

For a symmetric window the X-junction position decouples from every nuisance parameter (the
blurred X-junction is point-symmetric about the corner, so ``dI/dc`` is odd and every other
derivative even), and the bound depends little on the subpixel position of the corner in its
window. It scales exactly as ``noise_sd / |a|``.

References
----------
.. [1] H. Cramér, *Mathematical Methods of Statistics*, Princeton (1946); C. R. Rao, "Information
   and the accuracy attainable in the estimation of statistical parameters", Bull. Calcutta Math.
   Soc. 37 (1945) 81-91.
.. [2] S. M. Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*, Prentice
   Hall (1993), ch. 3 (Gaussian-noise Fisher information ``J^T J / sigma^2``).
.. [3] B. Widrow, I. Kollár, *Quantization Noise*, Cambridge (2008) (the ``q^2 / 12`` model).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from zoomcalib.detect.cornermodel import _dot_eval, _dot_params, _window_grid, _xj_eval

__all__ = ["Bound", "corner_crlb", "dot_crlb"]


class Bound(NamedTuple):
    """A Cramér-Rao bound on a 2-D position.

    Attributes
    ----------
    cov : (..., 2, 2) ndarray
        Lower bound on the covariance of any unbiased position estimate, px^2.
    radial_rms : (...) ndarray
        ``sqrt(trace(cov))``, px: the bound on the RMS of the 2-D (radial) error.
    """

    cov: np.ndarray
    radial_rms: np.ndarray


def _bound(jac: np.ndarray, var: np.ndarray, shape: tuple[int, ...]) -> Bound:
    fisher = np.einsum("kmp,kmq->kpq", jac, jac) / var[:, None, None]
    cov = np.linalg.inv(fisher)[:, :2, :2]
    cov = cov.reshape(shape + (2, 2))
    return Bound(cov, np.sqrt(np.trace(cov, axis1=-2, axis2=-1)))


def _noise_var(noise_sd, quant_step, n):
    sd = np.broadcast_to(np.asarray(noise_sd, dtype=float), (n,))
    if np.any(sd < 0) or quant_step < 0:
        raise ValueError("noise_sd and quant_step must be non-negative")
    var = sd**2 + quant_step**2 / 12.0
    if np.any(var <= 0):
        raise ValueError("the noise variance must be positive")
    return var


def _flat_common(shape, offset, sigma_psf, contrast, noise_sd, quant_step):
    """Broadcast the parameters shared by both bounds to ``shape`` and flatten them."""
    n = int(np.prod(shape))
    off = np.broadcast_to(np.asarray(offset, dtype=float), shape + (2,)).reshape(n, 2)
    sig = np.broadcast_to(np.asarray(sigma_psf, dtype=float), shape).reshape(n).copy()
    a = np.broadcast_to(np.asarray(contrast, dtype=float), shape).reshape(n)
    if np.any(sig <= 0):
        raise ValueError("sigma_psf must be positive")
    var = _noise_var(np.broadcast_to(noise_sd, shape).reshape(n), quant_step, n)
    return off, sig, a, var


def corner_crlb(
    sigma_psf: float | np.ndarray,
    noise_sd: float | np.ndarray,
    contrast: float | np.ndarray,
    angles: np.ndarray,
    window: int = 5,
    *,
    offset: np.ndarray = (0.0, 0.0),
    fit_sigma: bool = True,
    quant_step: float = 0.0,
    n_sub: int = 4,
) -> Bound:
    """Cramér-Rao bound on the position of an X-junction (chessboard corner).

    ``F = J^T J / s^2`` over the ``(2 window + 1)^2`` pixels, ``J = dI/d(c_x, c_y, alpha_1,
    alpha_2, a, b[, log sigma])`` of the pixel-integrated blurred X-junction
    (:func:`zoomcalib.detect.cornermodel.xjunction_image`),
    ``s^2 = noise_sd^2 + quant_step^2 / 12``; the bound is ``(F^-1)[:2, :2]``. All arguments
    broadcast against the leading shape of ``angles``.

    Parameters
    ----------
    sigma_psf : float or (...) ndarray
        Gaussian PSF sd, px (before pixel integration).
    noise_sd : float or (...) ndarray
        Additive Gaussian noise sd per pixel, intensity units.
    contrast : float or (...) ndarray
        Intensity step ``a`` between dark and bright squares, same units.
    angles : (..., 2) ndarray
        Edge direction angles ``(alpha_1, alpha_2)``, rad.
    window : int
        Half-size of the window, px (5 -> 11 x 11 pixels).
    offset : (..., 2) array_like
        Corner position relative to the centre of the window's central pixel, px.
    fit_sigma : bool
        Count the blur as an unknown (as :func:`~zoomcalib.detect.refine.refine_corners` does
        with ``sigma=None``).
    quant_step : float
        Quantisation step, intensity units (1/255 for 8-bit on a 0..1 scale), added as
        ``quant_step^2 / 12`` variance.
    n_sub : int
        Gauss-Legendre nodes per pixel axis for the pixel integration.

    Returns
    -------
    Bound
        ``cov`` (..., 2, 2) px^2 and ``radial_rms`` (...) px.

    Notes
    -----
    The bound at the reference setting (noise 2/255 on a 0..1 scale, contrast 1, blur 0.7 px,
    11 x 11 window, 8-bit) and its change with the quantisation term, the edge directions, the
    corner's sub-pixel position, the contrast, the blur and the window are printed by
    ``python benchmarks/bench_refine.py --crlb``; results in ``docs/model.md`` ("Detection").
    A fixed or fitted blur gives the same bound on the position (point symmetry).

    Examples
    --------
    The reference setting: noise 2/255, contrast 1, blur 0.7 px, 11 x 11 window, square corner:

    >>> b = corner_crlb(0.7, 2 / 255, 1.0, [0.0, np.pi / 2], window=5)
    >>> round(float(b.radial_rms), 4)
    0.0059
    """
    ang = np.asarray(angles, dtype=float)
    if ang.shape[-1:] != (2,):
        raise ValueError(f"angles must have shape (..., 2), got {ang.shape}")
    shape = np.broadcast_shapes(
        ang.shape[:-1], np.shape(sigma_psf), np.shape(noise_sd), np.shape(contrast),
        np.shape(offset)[:-1],
    )
    n = int(np.prod(shape))
    ang = np.broadcast_to(ang, shape + (2,)).reshape(n, 2)
    off, sig, a, var = _flat_common(shape, offset, sigma_psf, contrast, noise_sd, quant_step)
    p = np.column_stack([off, ang, a, np.zeros(n)])
    _, jac = _xj_eval(p, sig, _window_grid(window), "quadrature", n_sub)
    if not fit_sigma:
        jac = jac[..., :6]
    return _bound(jac, var, shape)


def dot_crlb(
    sigma_psf: float | np.ndarray,
    noise_sd: float | np.ndarray,
    contrast: float | np.ndarray,
    axes: np.ndarray,
    angle: float | np.ndarray = 0.0,
    window: int | None = None,
    *,
    offset: np.ndarray = (0.0, 0.0),
    fit_sigma: bool = True,
    quant_step: float = 0.0,
    n_sub: int = 3,
) -> Bound:
    """Cramér-Rao bound on the centre of a blurred dark ellipse (a dot).

    ``F = J^T J / s^2`` with ``J = dI/d(c_x, c_y, Q_11, Q_12, Q_22, a, b[, log sigma])`` of the
    pixel-integrated blurred-ellipse model (:func:`zoomcalib.detect.cornermodel.dot_image`) over the
    square window; the bound is ``(F^-1)[:2, :2]``. The bound is for the *ellipse* centre, the
    quantity :func:`~zoomcalib.detect.refine.refine_dots` estimates.

    Parameters
    ----------
    sigma_psf, noise_sd, contrast : float or (...) ndarray
        As in :func:`corner_crlb`.
    axes : (..., 2) ndarray
        Semi-axes, px.
    angle : float or (...) ndarray
        Direction of the first axis, rad.
    window : int, optional
        Window half-size, px; default as :func:`~zoomcalib.detect.refine.refine_dots`:
        ``ceil(1.5 max(axes) + 3 sigma + 2)`` (with sigma = 1 px).
    offset : (..., 2) array_like
        Centre relative to the window's central pixel, px.
    fit_sigma, quant_step, n_sub
        As in :func:`corner_crlb`.

    Returns
    -------
    Bound

    Examples
    --------
    A circle of radius 8 px sees far more edge than an 11 x 11 corner window:

    >>> b = dot_crlb(0.7, 2 / 255, 1.0, [8.0, 8.0])
    >>> bool(b.radial_rms < corner_crlb(0.7, 2 / 255, 1.0, [0.0, np.pi / 2]).radial_rms)
    True
    """
    ax = np.asarray(axes, dtype=float)
    if ax.shape[-1:] != (2,):
        raise ValueError(f"axes must have shape (..., 2), got {ax.shape}")
    shape = np.broadcast_shapes(
        ax.shape[:-1], np.shape(angle), np.shape(sigma_psf), np.shape(noise_sd),
        np.shape(contrast), np.shape(offset)[:-1],
    )
    n = int(np.prod(shape))
    ax = np.broadcast_to(ax, shape + (2,)).reshape(n, 2)
    if np.any(ax <= 0):
        raise ValueError("axes must be positive")
    ang = np.broadcast_to(np.asarray(angle, dtype=float), shape).reshape(n)
    off, sig, a, var = _flat_common(shape, offset, sigma_psf, contrast, noise_sd, quant_step)
    if window is None:
        window = int(np.ceil(1.5 * ax.max() + 3.0 + 2.0))
    scale = np.ones(n)
    p = np.column_stack([off, _dot_params(ax, ang, scale), a, np.zeros(n)])
    _, jac = _dot_eval(p, sig, scale, _window_grid(window), n_sub)
    if not fit_sigma:
        jac = jac[..., :7]
    return _bound(jac, var, shape)
