"""The image model shared by the renderer and the detectors: blurred, pixel-integrated edges.

A straight edge blurred by an isotropic Gaussian PSF of sd ``sigma`` is ``Phi(u / sigma)``, with
``u`` the signed distance to the edge; the quadrant beyond two straight edges with unit normals
``n_1, n_2`` is ``Phi_2(u_1 / sigma, u_2 / sigma; n_1 . n_2)``, the bivariate normal CDF (exact,
for any angle between the edges). Integration over a square pixel uses a Gauss-Legendre product
rule (:func:`pixel_nodes`, :func:`auto_n_sub`).

References
----------
W. F. Sheppard, Phil. Trans. R. Soc. A 192 (1899) 101-167; A. Genz, Statistics and Computing 14
(2004) 251-260.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import ndtr

__all__ = ["bivariate_normal_cdf", "pixel_nodes", "auto_n_sub"]

_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


def _phi(x: np.ndarray) -> np.ndarray:
    """Standard normal density."""
    return _INV_SQRT_2PI * np.exp(-0.5 * x * x)


@lru_cache(maxsize=32)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights of the ``n``-point Gauss-Legendre rule on [-1, 1] (cached, read-only:
    the model evaluations ask for the same few rules thousands of times per image)."""
    t, w = np.polynomial.legendre.leggauss(n)
    t.flags.writeable = False
    w.flags.writeable = False
    return t, w


def _n_rho_nodes(rho_abs_max: float) -> int:
    # Gauss-Legendre order for Sheppard's integral by |rho|; its error against Owen's T is
    # measured by ``python benchmarks/bench_refine.py --model-accuracy`` (docs/model.md).
    if rho_abs_max <= 0.75:
        return 6
    if rho_abs_max <= 0.9:
        return 10
    return 16


def bivariate_normal_cdf(
    h: np.ndarray, k: np.ndarray, rho: np.ndarray, n_nodes: int | None = None
) -> np.ndarray:
    """Bivariate standard normal CDF ``Phi_2(h, k; rho) = P(X <= h, Y <= k)``, vectorised.

    Uses Sheppard's formula (from Plackett's identity ``d Phi_2 / d rho = phi_2``)::

        Phi_2(h, k; rho) = Phi(h) Phi(k)
            + 1/(2 pi) * int_0^{asin rho} exp(-(h^2 - 2 h k sin t + k^2) / (2 cos^2 t)) dt

    integrated by an ``n_nodes``-point Gauss-Legendre rule. The integrand is smooth for
    ``|rho| < 1``; the default order grows with ``max |rho|``. Its error against Owen's T
    function is measured by ``python benchmarks/bench_refine.py --model-accuracy``; results in
    ``docs/model.md`` ("Accuracy of the image model").

    Parameters
    ----------
    h, k : (...) array_like
        Upper limits (broadcast together with ``rho``).
    rho : (...) array_like
        Correlation, ``|rho| < 1``.
    n_nodes : int, optional
        Quadrature order; chosen from ``max |rho|`` when omitted.

    Returns
    -------
    (...) ndarray

    References
    ----------
    Sheppard (1899); Genz (2004) -- see the module docstring.

    Examples
    --------
    >>> round(float(bivariate_normal_cdf(0.0, 0.0, 0.5)), 12)  # 1/4 + asin(rho) / (2 pi)
    0.333333333333
    """
    h, k, rho = (np.asarray(v, dtype=float) for v in (h, k, rho))
    return ndtr(h) * ndtr(k) + _sheppard(h, k, rho, n_nodes)


def _sheppard(h: np.ndarray, k: np.ndarray, rho: np.ndarray, n_nodes: int | None) -> np.ndarray:
    """``Phi_2(h, k; rho) - Phi(h) Phi(k)`` by Gauss-Legendre quadrature of Sheppard's integral.

    The nodes depend on ``rho`` only, so they are computed at ``rho``'s (small) shape and
    broadcast against ``h`` and ``k``: with ``t_q`` the nodes on ``[0, asin rho]``,
    ``sum_q w_q exp((h^2 + k^2) (-1 / (2 cos^2 t_q)) + h k (sin t_q / cos^2 t_q))``.
    """
    if n_nodes is None:
        n_nodes = _n_rho_nodes(float(np.max(np.abs(rho), initial=0.0)))
    t, w = _gauss_legendre(int(n_nodes))
    half = 0.5 * np.arcsin(rho)
    s = np.sin(half[..., None] * (t + 1.0))
    c2 = 1.0 - s * s
    quad = (h * h + k * k)[..., None]
    cross = (h * k)[..., None]
    integrand = np.exp(quad * (-0.5 / c2) + cross * (s / c2))
    return half / (2.0 * np.pi) * (integrand @ w)


def pixel_nodes(n_sub: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre product rule over one pixel.

    Parameters
    ----------
    n_sub : int
        Nodes per axis.

    Returns
    -------
    offsets : (n_sub**2, 2) ndarray
        Node offsets ``(dx, dy)`` from the pixel centre, px, inside ``(-1/2, 1/2)^2``.
    weights : (n_sub**2,) ndarray
        Weights summing to 1, so ``sum(w * f(centre + offsets))`` is the pixel mean of ``f``.

    Examples
    --------
    >>> off, w = pixel_nodes(2)
    >>> off.shape, float(w.sum())
    ((4, 2), 1.0)
    """
    t, w = _gauss_legendre(int(n_sub))
    t, w = 0.5 * t, 0.5 * w
    gx, gy = np.meshgrid(t, t)
    return np.stack([gx.ravel(), gy.ravel()], axis=1), np.outer(w, w).ravel()


def auto_n_sub(sigma: float) -> int:
    """Gauss-Legendre nodes per pixel axis that integrate the blurred pattern over a pixel to
    about 1e-4 of the contrast or better, for PSF sd ``sigma`` px.

    The thresholds come from the largest error of the X-junction over a window (contrast 1)
    against a 16-node rule, per ``sigma`` and ``n_sub``, measured by ``python
    benchmarks/bench_refine.py --model-accuracy``; results in ``docs/model.md`` ("Accuracy of the
    image model").

    Examples
    --------
    >>> auto_n_sub(0.7), auto_n_sub(0.4), auto_n_sub(0.1)
    (3, 4, 6)
    """
    if sigma >= 0.55:
        return 3
    if sigma >= 0.35:
        return 4
    if sigma >= 0.25:
        return 5
    return 6
