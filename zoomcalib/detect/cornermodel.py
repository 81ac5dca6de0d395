"""The image of a chessboard corner (an X-junction) and of a dark dot near it, under a point
spread function and integrated over the pixels, with its analytic Jacobian: the model that
:mod:`zoomcalib.detect.refine` fits and :mod:`zoomcalib.detect.crlb` bounds.

The model, its formulas and its pixel rule: :mod:`zoomcalib.detect.refine`'s module docstring
("Image model"). Here: the X-junction's value and Jacobian for a Gaussian PSF (isotropic or
anisotropic, a covariance per corner) and for a camera's unsharp mask (:class:`SharpenedPSF`),
the blurred ellipse's, and :func:`xjunction_image` and :func:`dot_image`, which render either
on a pixel grid. Pixels follow OpenCV's convention (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.special import ndtr

from ..imaging import (
    _phi,
    _sheppard,
    pixel_nodes,
)

__all__ = ["SharpenedPSF", "xjunction_image", "dot_image"]


_RHO_MAX = 0.98  # |cos| of the smallest edge angle handled (~11.5 deg between edges)


PixelModel = Literal["quadrature", "gaussian"]


def _window_grid(window: int) -> np.ndarray:
    """(M, 2) pixel offsets ``(dx, dy)`` of a ``(2 window + 1)^2`` window, row-major."""
    r = np.arange(-window, window + 1, dtype=float)
    gx, gy = np.meshgrid(r, r)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _extract(image: np.ndarray, centres: np.ndarray, window: int):
    """Patches around integer pixel centres; out-of-image pixels get weight 0.

    Returns
    -------
    data : (K, M) float64, weights : (K, M) float64 (0 or 1), origin : (K, 2) int (x, y).
    """
    origin = np.rint(centres).astype(np.int64)
    grid = _window_grid(window).astype(np.int64)
    xs = origin[:, None, 0] + grid[None, :, 0]
    ys = origin[:, None, 1] + grid[None, :, 1]
    h, w = image.shape
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    data = image[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)].astype(np.float64)
    return data, inside.astype(np.float64), origin


# ----------------------------------------------------------------------------------------------
# X-junction model: value and analytic Jacobian
# ----------------------------------------------------------------------------------------------

# Parameter vector per corner (local window coordinates):
#   0 cx, 1 cy   corner position, px
#   2 alpha1, 3 alpha2   edge direction angles, rad
#   4 a, 5 b     contrast and offset (intensity units)
#   6 log(sigma) PSF blur (only when fitted)
_XJ_NP = 7


def _blur_variances(blur: np.ndarray, n1: np.ndarray, n2: np.ndarray):
    """Variances of ``n_1 . z``, ``n_2 . z`` and their covariance for ``z ~ N(0, S)``.

    ``blur`` is (K,) isotropic sd (``S = sigma^2 I``) or (K, 3) entries ``(S_xx, S_xy, S_yy)``;
    ``n1, n2`` are (K, 2) unit normals. Returns ``v_i = n_i^T S n_i`` and ``c = n_1^T S n_2``.
    """
    if blur.ndim == 1:
        var = blur * blur
        return var, var.copy(), var * np.einsum("kd,kd->k", n1, n2)
    sxx, sxy, syy = blur[:, 0], blur[:, 1], blur[:, 2]

    def quad(a, b):
        return sxx * a[:, 0] * b[:, 0] + sxy * (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0]) \
            + syy * a[:, 1] * b[:, 1]

    return quad(n1, n1), quad(n2, n2), quad(n1, n2)


def _apply_cov(blur: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``S v`` per corner for ``v`` (K, 2); ``blur`` as in :func:`_blur_variances`."""
    if blur.ndim == 1:
        return (blur * blur)[:, None] * v
    return np.column_stack([blur[:, 0] * v[:, 0] + blur[:, 1] * v[:, 1],
                            blur[:, 1] * v[:, 0] + blur[:, 2] * v[:, 1]])


def _pixel_rule(pixel_model: PixelModel, n_sub: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Node offsets from the pixel centre (S, 2) px, their weights (S,) and the variance the
    model adds to the PSF (px^2) of a pixel model: the ``n_sub x n_sub`` Gauss-Legendre rule,
    or the pixel centre alone with the box's variance 1/12 (module docstring)."""
    if pixel_model == "quadrature":
        off, wts = pixel_nodes(n_sub)
        return off, wts, 0.0
    if pixel_model == "gaussian":
        return np.zeros((1, 2)), np.ones(1), 1.0 / 12.0
    raise ValueError(f"pixel_model must be 'quadrature' or 'gaussian', got {pixel_model!r}")


@dataclass(frozen=True)
class _XjEdges:
    """The two edges of K X-junctions under their PSF, each (K,) unless said: the sines and
    cosines of the edge angles, the unit normals ``n1``, ``n2`` (K, 2), the PSF with the pixel
    model's variance ``eff`` (sd, px, (K,); or covariance entries (K, 3), px^2), the variances
    ``v1``, ``v2`` of ``n_i . z`` (px^2) and their sds ``sd1``, ``sd2`` (px), the correlation
    ``rho_raw``, ``rho`` clipped to ``_RHO_MAX`` and ``srho = sqrt(1 - rho^2)``."""

    sin1: np.ndarray
    cos1: np.ndarray
    sin2: np.ndarray
    cos2: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    eff: np.ndarray
    v1: np.ndarray
    v2: np.ndarray
    sd1: np.ndarray
    sd2: np.ndarray
    rho_raw: np.ndarray
    rho: np.ndarray
    srho: np.ndarray

    @classmethod
    def of(cls, alpha1: np.ndarray, alpha2: np.ndarray, eff: np.ndarray) -> _XjEdges:
        """The edges at direction angles ``alpha1``, ``alpha2`` (rad) under ``eff``."""
        s1, c1, s2, c2 = np.sin(alpha1), np.cos(alpha1), np.sin(alpha2), np.cos(alpha2)
        n1, n2 = np.column_stack([-s1, c1]), np.column_stack([-s2, c2])
        v1, v2, c12 = _blur_variances(eff, n1, n2)
        with np.errstate(invalid="ignore"):  # trial steps with an indefinite S are rejected later
            sd1, sd2 = np.sqrt(v1), np.sqrt(v2)
        rho_raw = c12 / (sd1 * sd2)
        rho = np.clip(rho_raw, -_RHO_MAX, _RHO_MAX)
        return cls(s1, c1, s2, c2, n1, n2, eff, v1, v2, sd1, sd2, rho_raw, rho,
                   np.sqrt(1.0 - rho * rho))


@dataclass(frozen=True)
class _XjNodes:
    """The quadrature nodes of every pixel relative to each corner, (K, M, S): offsets ``dx``,
    ``dy`` (px) and the edges' normalised distances ``h = u_1 / sd_1``, ``k = u_2 / sd_2``;
    and the node ``weights`` (S,)."""

    dx: np.ndarray
    dy: np.ndarray
    h: np.ndarray
    k: np.ndarray
    weights: np.ndarray


def _xj_eval(
    p: np.ndarray,
    sigma: np.ndarray,
    xy: np.ndarray,
    pixel_model: PixelModel,
    n_sub: int,
    jacobian: bool = True,
):
    """Pixel-integrated X-junction model and its Jacobian.

    Parameters
    ----------
    p : (K, 6) ndarray
        ``(cx, cy, alpha1, alpha2, a, b)`` in the coordinates of ``xy``.
    sigma : (K,) or (K, 3) ndarray
        Isotropic Gaussian PSF standard deviation, px; or the covariance ``S`` of an
        anisotropic Gaussian PSF as ``(S_xx, S_xy, S_yy)``, px^2.
    xy : (M, 2) ndarray
        Pixel centres.

    Returns
    -------
    f : (K, M) ndarray
        ``b + a * P``.
    jac : (K, M, 7) or (K, M, 9) ndarray
        ``df / d(cx, cy, alpha1, alpha2, a, b, log sigma)``; with a covariance, the last three
        columns are ``df / d(S_xx, S_xy, S_yy)`` instead (px^-2).

    Notes
    -----
    The PSF blurs edge ``i`` by a 1-D Gaussian of variance ``v_i = n_i^T S n_i`` (``S = sigma^2
    I`` when isotropic; plus ``I / 12`` for the Gaussian pixel model), so ``h = u_1 /
    sqrt(v_1)``, ``k = u_2 / sqrt(v_2)`` and ``rho = n_1^T S n_2 / sqrt(v_1 v_2)``. With ``g =
    Phi(h) + Phi(k) - 2 Phi_2(h, k; rho)`` at each quadrature node, ``s = sqrt(1 - rho^2)``, and
    the standard identities ``d Phi_2 / dh = phi(h) Phi((k - rho h) / s)`` and ``d Phi_2 / d rho
    = phi_2(h, k; rho)`` (Plackett):

        dg/dh = phi(h) (1 - 2 Phi((k - rho h) / s)),   dg/dk likewise,
        dg/drho = -2 exp(-(h^2 - 2 rho h k + k^2) / (2 s^2)) / (2 pi s),

    and ``du_i/dc = -n_i``, ``dn_i/dalpha_i = -t_i`` (``t_i = (cos alpha_i, sin alpha_i)``), so
    ``du_i/dalpha_i = -t_i . (x - c)``, ``dv_i/dalpha_i = -2 t_i^T S n_i``, ``d(n_1^T S
    n_2)/dalpha_1 = -t_1^T S n_2``; ``dh/dv_1 = -h / (2 v_1)``, ``drho = d(n_1^T S n_2) /
    sqrt(v_1 v_2) - rho (dv_1 / v_1 + dv_2 / v_2) / 2``. The pixel value and its derivatives
    are the node sums weighted by :func:`pixel_nodes`.
    """
    off, wts, box = _pixel_rule(pixel_model, n_sub)
    sigma = np.asarray(sigma, dtype=float)
    aniso = sigma.ndim == 2
    eff = sigma + np.array([box, 0.0, box]) if aniso else np.sqrt(sigma**2 + box)
    cx, cy, a1, a2, a, b = (p[:, i] for i in range(6))
    edges = _XjEdges.of(a1, a2, eff)
    # node coordinates relative to the corner: (K, M, S)
    dx = (xy[None, :, 0, None] + off[None, None, :, 0]) - cx[:, None, None]
    dy = (xy[None, :, 1, None] + off[None, None, :, 1]) - cy[:, None, None]
    e = (slice(None), None, None)
    u1 = -edges.sin1[e] * dx + edges.cos1[e] * dy
    u2 = -edges.sin2[e] * dx + edges.cos2[e] * dy
    h, k = u1 / edges.sd1[e], u2 / edges.sd2[e]
    nh, nk = ndtr(h), ndtr(k)
    g = nh + nk - 2.0 * (nh * nk + _sheppard_by_rho(h, k, edges.rho[e]))
    pix = g @ wts  # (K, M)
    f = b[:, None] + a[:, None] * pix
    if not jacobian:
        return f, None
    return f, _xj_jacobian(edges, _XjNodes(dx, dy, h, k, wts), a, pix, sigma)


def _xj_jacobian(edges: _XjEdges, nodes: _XjNodes, a: np.ndarray, pix: np.ndarray,
                 sigma: np.ndarray) -> np.ndarray:
    """The Jacobian of :func:`_xj_eval` (formulas in its Notes) from its ``edges``, ``nodes``,
    contrasts ``a`` (K,), blurred pattern ``pix`` (K, M) and PSF ``sigma`` (as given there)."""
    s1, c1, s2, c2 = edges.sin1, edges.cos1, edges.sin2, edges.cos2
    n1, n2, eff, v1, v2 = edges.n1, edges.n2, edges.eff, edges.v1, edges.v2
    sd1, sd2, rho_raw = edges.sd1, edges.sd2, edges.rho_raw
    dx, dy, h, k, wts = nodes.dx, nodes.dy, nodes.h, nodes.k, nodes.weights
    aniso = sigma.ndim == 2
    e = (slice(None), None, None)
    r_, sr = edges.rho[e], edges.srho[e]
    ph, pk = _phi(h), _phi(k)
    gh = ph * (1.0 - 2.0 * ndtr((k - r_ * h) / sr))
    gk = pk * (1.0 - 2.0 * ndtr((h - r_ * k) / sr))
    grho = -2.0 * np.exp(-(h * h - 2.0 * r_ * h * k + k * k) / (2.0 * sr * sr)) / (
        2.0 * np.pi * sr
    )
    t1v, t2v = np.column_stack([c1, s1]), np.column_stack([c2, s2])
    t1 = c1[e] * dx + s1[e] * dy  # along-edge coordinates; d u_i / d alpha_i = -t_i
    t2 = c2[e] * dx + s2[e] * dy
    Sn1, Sn2 = _apply_cov(eff, n1), _apply_cov(eff, n2)
    t1Sn1 = np.einsum("kd,kd->k", t1v, Sn1)  # 0 when isotropic
    t2Sn2 = np.einsum("kd,kd->k", t2v, Sn2)
    sd12 = sd1 * sd2
    drho_a1 = -np.einsum("kd,kd->k", t1v, Sn2) / sd12 + rho_raw * t1Sn1 / v1
    drho_a2 = -np.einsum("kd,kd->k", t2v, Sn1) / sd12 + rho_raw * t2Sn2 / v2
    ghh, gkk = (gh * h) @ wts, (gk * k) @ wts  # (K, M)
    gr = grho @ wts
    n_blur = 3 if aniso else 1
    jac = np.empty(pix.shape + (6 + n_blur,))
    av = a[:, None]
    inv1, inv2 = (1.0 / sd1)[e], (1.0 / sd2)[e]
    jac[..., 0] = av * ((gh * (s1[e] * inv1) + gk * (s2[e] * inv2)) @ wts)
    jac[..., 1] = av * ((gh * (-c1[e] * inv1) + gk * (-c2[e] * inv2)) @ wts)
    jac[..., 2] = av * ((-gh * t1 * inv1) @ wts + ghh * (t1Sn1 / v1)[:, None]
                        + gr * drho_a1[:, None])
    jac[..., 3] = av * ((-gk * t2 * inv2) @ wts + gkk * (t2Sn2 / v2)[:, None]
                        + gr * drho_a2[:, None])
    jac[..., 4] = pix
    jac[..., 5] = 1.0
    if not aniso:
        # S = sigma^2 I (+ I/12): dv_i / dlog sigma = 2 sigma^2, rho does not depend on sigma
        jac[..., 6] = av * (-(ghh + gkk)) * (sigma**2 / eff**2)[:, None]
        return jac
    for j, (dv1, dv2, dc) in enumerate(_cov_entry_derivatives(n1, n2)):
        drho = dc / sd12 - 0.5 * rho_raw * (dv1 / v1 + dv2 / v2)
        jac[..., 6 + j] = av * (-0.5 * ghh * (dv1 / v1)[:, None] - 0.5 * gkk * (dv2 / v2)[:, None]
                                + gr * drho[:, None])
    return jac


@dataclass(frozen=True)
class SharpenedPSF:
    """A Gaussian blur followed by a camera's unsharp mask, as one point spread function.

    ``PSF = (1 + amount) G_sigma - amount G_wide``, ``wide = sqrt(sigma^2 + radius^2)``: the
    frame blurred by ``G_sigma`` (px), then sharpened as ``I' = (1 + amount) I - amount
    (G_radius * I)``. The blurred X-junction is linear in its PSF, so the model is the same
    combination of two Gaussian X-junctions (:func:`_xj_eval_sharpened`). Its negative lobe
    makes the overshoot on both sides of an edge that the cameras of video streams add and
    no Gaussian blur makes.

    Examples
    --------
    >>> round(SharpenedPSF(0.6, 0.8, 0.8).wide, 3)
    1.0
    """

    sigma: float
    amount: float
    radius: float

    @property
    def wide(self) -> float:
        """The wide Gaussian's sd, ``sqrt(sigma^2 + radius^2)``, px."""
        return float(np.hypot(self.sigma, self.radius))


# A fixed blur: an isotropic sd (px), covariance entries (S_xx, S_xy, S_yy) (px^2) or a
# sharpened PSF
Blur = float | np.ndarray | SharpenedPSF


def _xj_eval_sharpened(
    p: np.ndarray,
    sigma: np.ndarray,
    amount: np.ndarray,
    radius: np.ndarray,
    xy: np.ndarray,
    pixel_model: PixelModel,
    n_sub: int,
    jacobian: bool = True,
):
    """The X-junction under a :class:`SharpenedPSF`, and its Jacobian.

    ``f = (1 + A) f_sigma - A f_wide`` with ``f_s`` the Gaussian X-junction of
    :func:`_xj_eval` at blur ``s`` and ``wide = sqrt(sigma^2 + radius^2)`` (``b`` and ``a``
    enter both alike, so the combination keeps them). ``sigma, amount, radius`` are (K,).
    The wide term is integrated over the pixel by the Gaussian pixel model when every
    ``wide`` is at least ``_GAUSSIAN_PIXEL_SIGMA``, where that model is as exact as the
    quadrature (module docstring).
    The Jacobian's columns are ``df / d(cx, cy, alpha1, alpha2, a, b, log sigma, A, log
    radius)``, with ``d log wide / d log sigma = sigma^2 / wide^2`` and ``d log wide /
    d log radius = radius^2 / wide^2``.
    """
    wide = np.hypot(sigma, radius)
    f1, j1 = _xj_eval(p, sigma, xy, pixel_model, n_sub, jacobian)
    if np.all(wide >= _GAUSSIAN_PIXEL_SIGMA):  # where the Gaussian pixel model is as exact
        f2, j2 = _xj_eval(p, wide, xy, "gaussian", 1, jacobian)
    else:
        f2, j2 = _xj_eval(p, wide, xy, pixel_model, n_sub, jacobian)
    A = amount[:, None]
    f = (1.0 + A) * f1 - A * f2
    if not jacobian:
        return f, None
    jac = np.empty(f.shape + (9,))
    jac[..., :6] = (1.0 + A)[..., None] * j1[..., :6] - A[..., None] * j2[..., :6]
    w2 = wide * wide
    jac[..., 6] = (1.0 + A) * j1[..., 6] - A * j2[..., 6] * (sigma * sigma / w2)[:, None]
    jac[..., 7] = f1 - f2
    jac[..., 8] = -A * j2[..., 6] * (radius * radius / w2)[:, None]
    return f, jac


def _cov_entry_derivatives(n1: np.ndarray, n2: np.ndarray):
    """Derivatives of ``(v_1, v_2, n_1^T S n_2)`` by ``S_xx``, ``S_xy`` and ``S_yy``."""
    return (
        (n1[:, 0] ** 2, n2[:, 0] ** 2, n1[:, 0] * n2[:, 0]),
        (2 * n1[:, 0] * n1[:, 1], 2 * n2[:, 0] * n2[:, 1],
         n1[:, 0] * n2[:, 1] + n1[:, 1] * n2[:, 0]),
        (n1[:, 1] ** 2, n2[:, 1] ** 2, n1[:, 1] * n2[:, 1]),
    )


def _sheppard_by_rho(h: np.ndarray, k: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """:func:`~zoomcalib.imaging._sheppard` with the quadrature order chosen per corner (the
    first axis), so one corner with nearly parallel edges does not raise every corner's cost."""
    counts = _rho_node_counts(np.abs(rho.reshape(len(rho), -1)[:, 0]))
    if np.all(counts == counts[0]):
        return _sheppard(h, k, rho, int(counts[0]))
    out = np.empty(np.broadcast_shapes(h.shape, k.shape))
    for n in np.unique(counts):
        sel = counts == n
        out[sel] = _sheppard(h[sel], k[sel], rho[sel], int(n))
    return out


def xjunction_image(
    xy: np.ndarray,
    corner: np.ndarray,
    angles: np.ndarray,
    sigma: float | np.ndarray,
    contrast: float | np.ndarray = 1.0,
    offset: float | np.ndarray = 0.0,
    *,
    pixel_model: PixelModel = "quadrature",
    n_sub: int = 4,
) -> np.ndarray:
    """Render the pixel-integrated blurred X-junction model at pixel centres.

    ``I = offset + contrast * (Phi(h) + Phi(k) - 2 Phi_2(h, k; cos(alpha_1 - alpha_2)))``,
    averaged over each pixel (module docstring). The value is ``offset + contrast`` in the two
    opposite sectors where ``u_1 u_2 < 0`` and ``offset`` in the other two.

    Parameters
    ----------
    xy : (M, 2) ndarray
        Pixel centres ``(x, y)``, px, OpenCV convention.
    corner : (K, 2) or (2,) ndarray
        Corner positions, px.
    angles : (K, 2) or (2,) ndarray
        Edge direction angles ``(alpha_1, alpha_2)``, rad (from +x towards +y).
    sigma, contrast, offset : float or (K,) ndarray
        Gaussian PSF sd (px), contrast ``a`` and offset ``b``.
    pixel_model : {'quadrature', 'gaussian'}
        Pixel integration by Gauss-Legendre nodes, or by the variance-matched Gaussian.
    n_sub : int
        Nodes per axis for ``'quadrature'``.

    Returns
    -------
    (K, M) or (M,) ndarray

    Examples
    --------
    >>> v = xjunction_image(np.array([[0.0, 0.0], [5.0, -5.0], [5.0, 5.0]]), [0.0, 0.0],
    ...                     [0.0, np.pi / 2], 0.7)
    >>> np.round(v, 6).tolist()  # one half at the corner; 0 where u1 u2 > 0, 1 where u1 u2 < 0
    [0.5, 0.0, 1.0]
    """
    corner = np.asarray(corner, dtype=float)
    single = corner.ndim == 1
    corner = corner.reshape(-1, 2)
    n = corner.shape[0]
    ang = np.broadcast_to(np.asarray(angles, dtype=float), (n, 2))
    p = np.column_stack(
        [corner, ang, np.broadcast_to(contrast, (n,)), np.broadcast_to(offset, (n,))]
    ).astype(float)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
    f, _ = _xj_eval(p, sig, np.asarray(xy, float).reshape(-1, 2), pixel_model, n_sub, False)
    return f[0] if single else f


# ----------------------------------------------------------------------------------------------
# Dot (ellipse) model: value and analytic Jacobian
# ----------------------------------------------------------------------------------------------

# Parameter vector: 0 cx, 1 cy, 2 q11, 3 q12, 4 q22 (Q scaled: Q = qtilde / R0^2), 5 a, 6 b,
# 7 log(sigma).
_DOT_NP = 8


def _dot_eval(
    p: np.ndarray,
    sigma: np.ndarray,
    scale: np.ndarray,
    xy: np.ndarray,
    n_sub: int,
    jacobian: bool = True,
):
    """Pixel-integrated blurred-ellipse model and its Jacobian.

    Parameters
    ----------
    p : (K, 7) ndarray
        ``(cx, cy, q11, q12, q22, a, b)`` with ``Q = [[q11, q12], [q12, q22]] / scale^2``.
    sigma, scale : (K,) ndarray
    xy : (M, 2) ndarray

    Returns
    -------
    f : (K, M), jac : (K, M, 8) with the last column ``d f / d log sigma``.
    """
    off, wts = pixel_nodes(n_sub)
    cx, cy, q11, q12, q22, a, b = (p[:, i] for i in range(7))
    e = (slice(None), None, None)
    inv2 = 1.0 / scale[e] ** 2
    Q11, Q12, Q22 = q11[e] * inv2, q12[e] * inv2, q22[e] * inv2
    det = Q11 * Q22 - Q12 * Q12
    dx = (xy[None, :, 0, None] + off[None, None, :, 0]) - cx[:, None, None]
    dy = (xy[None, :, 1, None] + off[None, None, :, 1]) - cy[:, None, None]
    w1 = Q11 * dx + Q12 * dy
    w2 = Q12 * dx + Q22 * dy
    r2 = dx * w1 + dy * w2
    # A node exactly at the centre (r = G = 0; e.g. an odd n_sub and a centre on a pixel
    # centre): r / G has no limit there (a cone apex); use the circle value sqrt(2 / tr Q) and
    # drop its (measure-zero, ~0) derivative contribution.
    apex = r2 < 1e-16
    r = np.sqrt(np.where(apex, 1.0, r2))
    G = np.where(apex, 1.0, np.sqrt(w1 * w1 + w2 * w2))
    with np.errstate(invalid="ignore"):  # trial steps with an indefinite Q are rejected later
        ratio = np.where(apex, np.sqrt(2.0 / (Q11 + Q22)), r / G)
    d = np.where(apex, -ratio, (r - 1.0) * ratio)
    kappa = det * ratio**3  # boundary curvature at c + (x - c) / r
    s_ = sigma[e]
    z = d / s_ + 0.5 * s_ * kappa
    pix = ndtr(z) @ wts
    f = b[:, None] + a[:, None] * pix
    if not jacobian:
        return f, None
    fz = np.where(apex, 0.0, _phi(z))
    cr = (2.0 * r - 1.0) / G  # dd/dr (holding G)
    cg = -d / G  # dd/dG (holding r)
    hk = 1.5 * s_ * kappa  # (sigma / 2) * kappa * 3: d(sigma kappa / 2) = hk (dr / r - dG / G)
    zr = cr / s_ + hk / r  # dz/dr
    zg = cg / s_ - hk / G  # dz/dG
    # derivatives of r and G w.r.t. the node offset (dx, dy): dr = w / r, dG = Q w / G
    drx, dry = w1 / r, w2 / r
    dgx, dgy = (Q11 * w1 + Q12 * w2) / G, (Q12 * w1 + Q22 * w2) / G
    # w.r.t. Q entries (then chain to qtilde = Q * scale^2); d det = (Q22, -2 Q12, Q11)
    dr11, dr12, dr22 = dx * dx / (2.0 * r), dx * dy / r, dy * dy / (2.0 * r)
    dg11, dg12, dg22 = w1 * dx / G, (w1 * dy + w2 * dx) / G, w2 * dy / G
    zdet = 0.5 * s_ * kappa / det
    av = a[:, None]
    jac = np.empty(f.shape + (_DOT_NP,))
    jac[..., 0] = -av * ((fz * (zr * drx + zg * dgx)) @ wts)
    jac[..., 1] = -av * ((fz * (zr * dry + zg * dgy)) @ wts)
    jac[..., 2] = av * ((fz * (zr * dr11 + zg * dg11 + zdet * Q22) * inv2) @ wts)
    jac[..., 3] = av * ((fz * (zr * dr12 + zg * dg12 - 2.0 * zdet * Q12) * inv2) @ wts)
    jac[..., 4] = av * ((fz * (zr * dr22 + zg * dg22 + zdet * Q11) * inv2) @ wts)
    jac[..., 5] = pix
    jac[..., 6] = 1.0
    jac[..., 7] = av * ((fz * (0.5 * s_ * kappa - d / s_)) @ wts)
    return f, jac


def _dot_params(axes, angle, scale):
    """Scaled shape entries ``qtilde`` (K, 3) from semi-axes (K, 2) and angle (K,)."""
    ca, sa = np.cos(angle), np.sin(angle)
    l1, l2 = 1.0 / axes[:, 0] ** 2, 1.0 / axes[:, 1] ** 2
    q11 = l1 * ca * ca + l2 * sa * sa
    q12 = (l1 - l2) * ca * sa
    q22 = l1 * sa * sa + l2 * ca * ca
    return np.column_stack([q11, q12, q22]) * (scale**2)[:, None]


def _dot_shape(q: np.ndarray, scale: np.ndarray):
    """Semi-axes (K, 2) (major, minor) and major-axis angle (K,) from scaled ``qtilde``."""
    q11, q12, q22 = (q[:, i] / scale**2 for i in range(3))
    tr, det = q11 + q22, q11 * q22 - q12 * q12
    disc = np.sqrt(np.maximum(0.25 * (q11 - q22) ** 2 + q12 * q12, 0.0))
    lmin, lmax = 0.5 * tr - disc, 0.5 * tr + disc
    with np.errstate(invalid="ignore", divide="ignore"):
        axes = np.column_stack([1.0 / np.sqrt(lmin), 1.0 / np.sqrt(lmax)])
    # the major axis is the eigenvector of the smaller eigenvalue
    angle = 0.5 * np.arctan2(-2.0 * q12, q22 - q11)
    angle = np.mod(angle, np.pi)
    axes[det <= 0] = np.nan
    return axes, angle


def dot_image(
    xy: np.ndarray,
    centre: np.ndarray,
    axes: np.ndarray,
    angle: float | np.ndarray,
    sigma: float | np.ndarray,
    contrast: float | np.ndarray = 1.0,
    offset: float | np.ndarray = 0.0,
    *,
    n_sub: int = 3,
) -> np.ndarray:
    """Render the pixel-integrated blurred ellipse model at pixel centres.

    ``I = offset + contrast * Phi(d / sigma)``, ``d`` the approximate signed distance to the
    ellipse boundary (negative inside), averaged over each pixel (module docstring). With a
    positive contrast the dot is dark (``offset``) on a bright (``offset + contrast``) ground.

    Parameters
    ----------
    xy : (M, 2) ndarray
        Pixel centres, px.
    centre : (K, 2) or (2,) ndarray
        Ellipse centres, px.
    axes : (K, 2) or (2,) ndarray
        Semi-axes ``(A, B)``, px; ``A`` lies along ``angle``.
    angle : float or (K,) ndarray
        Direction of the ``A`` axis, rad from +x towards +y.
    sigma, contrast, offset : float or (K,) ndarray
    n_sub : int
        Gauss-Legendre nodes per axis and pixel.

    Returns
    -------
    (K, M) or (M,) ndarray

    Examples
    --------
    >>> v = dot_image(np.array([[0.0, 0.0], [20.0, 0.0]]), [0.0, 0.0], [5.0, 5.0], 0.0, 0.7)
    >>> np.round(v, 6).tolist()
    [0.0, 1.0]
    """
    centre = np.asarray(centre, dtype=float)
    single = centre.ndim == 1
    centre = centre.reshape(-1, 2)
    n = centre.shape[0]
    axes = np.broadcast_to(np.asarray(axes, dtype=float), (n, 2))
    scale = np.ones(n)
    q = _dot_params(axes, np.broadcast_to(angle, (n,)), scale)
    p = np.column_stack(
        [centre, q, np.broadcast_to(contrast, (n,)), np.broadcast_to(offset, (n,))]
    ).astype(float)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n,)).copy()
    f, _ = _dot_eval(p, sig, scale, np.asarray(xy, float).reshape(-1, 2), n_sub, False)
    return f[0] if single else f


_GAUSSIAN_PIXEL_SIGMA = 1.0  # px; a fixed or shared blur from which the cheap model is final


def _rho_node_counts(rho_abs: np.ndarray) -> np.ndarray:
    """Gauss-Legendre order of Sheppard's integral per corner (as ``imaging._n_rho_nodes``)."""
    return np.where(rho_abs <= 0.75, 6, np.where(rho_abs <= 0.9, 10, 16))
