"""Model-based subpixel refinement of chessboard X-junctions and of dark dots (ellipses).

Image model
-----------
Near a target feature the camera image is modelled as

    I(x) = b + a * P_s(x),   P_s = (pattern * G_sigma * Box_1)(x),

the ideal sharp pattern ``pattern`` (values in [0, 1]) blurred by an isotropic Gaussian point
spread function ``G_sigma`` (standard deviation ``sigma`` px), then integrated over the square
1 x 1 px pixel (``Box_1``), then scaled by a contrast ``a`` and an offset ``b``, plus noise.
Pixels follow OpenCV's convention: the centre of the top-left pixel is (0, 0), x to the right,
y down; pixel (row i, column j) covers ``[j - 1/2, j + 1/2] x [i - 1/2, i + 1/2]``.

*X-junction (chessboard corner).* Two straight edges cross at the corner ``c``. Edge ``i`` has
direction angle ``alpha_i`` (radians from the +x axis towards +y, i.e. clockwise on screen) and
unit normal ``n_i = (-sin alpha_i, cos alpha_i)``; ``u_i = n_i . (x - c)`` is the signed distance
to edge ``i``. The sharp pattern ``0.5 (1 - sign(u_1) sign(u_2))`` is 1 where the point lies on
opposite sides of the two edges. The Gaussian blur of this pattern is, exactly,

    P_sigma(x) = Phi(h) + Phi(k) - 2 Phi_2(h, k; rho),   h = u_1 / sigma,  k = u_2 / sigma,
    rho = n_1 . n_2 = cos(alpha_1 - alpha_2),

where ``Phi`` is the standard normal CDF and ``Phi_2`` the bivariate standard normal CDF with
correlation ``rho``: the blurred product of two signs is ``E[sign(u_1 + n_1.z) sign(u_2 +
n_2.z)]`` for ``z ~ N(0, sigma^2 I)``; ``(n_1.z, n_2.z)`` is bivariate normal with correlation
``n_1 . n_2``, so the expectation is ``4 Phi_2(h, k; rho) - 2 Phi(h) - 2 Phi(k) + 1``. The
familiar product of two ``erf`` edges is the special case ``rho = 0`` (orthogonal edges) and is
wrong near the corner for the non-orthogonal edges that perspective produces, the more so the
further the edges are from orthogonal. ``Phi_2`` is evaluated from Sheppard's
integral (see :func:`bivariate_normal_cdf`) by Gauss-Legendre quadrature, with more nodes as
``|rho|`` grows, up to ``|rho| <= 0.98`` (edges at least 11.5 deg apart; ``rho`` is clipped
there). The blur is thus exact up to the quadrature's round-off level, not an approximation.

*Anisotropic blur.* Under motion blur or astigmatism the PSF is modelled as a Gaussian of
covariance ``S`` (2 x 2, px^2). Then ``(n_1.z, n_2.z)`` for ``z ~ N(0, S)`` is bivariate normal
with variances ``v_i = n_i^T S n_i`` and covariance ``n_1^T S n_2``, so the same expression holds
with ``h = u_1 / sqrt(v_1)``, ``k = u_2 / sqrt(v_2)`` and ``rho = n_1^T S n_2 / sqrt(v_1 v_2)``:
each edge is blurred by its own 1-D Gaussian, and the isotropic case is ``S = sigma^2 I``.

*Sharpened frames.* Cameras that stream video sharpen their frames, ``I' = (1 + A) I - A
(G_r * I)`` (an unsharp mask of amount ``A`` and radius ``r`` px), which makes edges
overshoot on both sides; no Gaussian PSF does. The blurred pattern is linear in the PSF, so
the sharpened image is ``(1 + A) P_sigma - A P_wide`` with ``wide = sqrt(sigma^2 + r^2)``: two
evaluations of the model above (:class:`SharpenedPSF`). Its narrow Gaussian carries the
position; the wide one is integrated over the pixel by the Gaussian pixel model below (it is
wider than a pixel).

*Pixel integration.* By default the blurred pattern is integrated over each pixel by an
``n_sub x n_sub`` Gauss-Legendre product rule (``pixel_model='quadrature'``, ``n_sub`` from
:func:`auto_n_sub`: 3 nodes per axis at sigma = 0.7 px), which keeps the intensity error far
below the noise. Fitted to noise-free images from an independent brute-force renderer (32 x 32
sub-samples per pixel, blur on the fine grid, then pixel averaging; ``tests/test_refine.py``) the
corner position error is negligible against the noise-limited error for sigma = 0.3 .. 1.6 px.

The cheaper ``pixel_model='gaussian'`` replaces the box by a Gaussian of the same variance, i.e.
one Gaussian of variance ``sigma^2 + 1/12`` per axis (``S + I / 12``) sampled at the pixel
centre. The box is not
a Gaussian (its projection on an edge normal is uniform for an axis-aligned edge and triangular at
45 deg), so its intensity error grows quickly as the blur falls below a pixel. Both PSFs are
point-symmetric, which keeps the corner position error smaller than that suggests (the fitted
sigma absorbs part of the mismatch). The refiner uses this model to get close, then finishes with
a few quadrature iterations; from a blur of 1 px on (a fixed or shared sigma; for a covariance,
the sd ``sqrt(n_i^T S n_i)`` across each of the corner's edges) the difference has fallen to the
level of the quadrature's own, so the fit ends on this model. A corner whose own position sd is
at least 20 times this model's bias at its blur (:func:`gaussian_pixel_bias`; a model that does
not describe the frame exactly, a dim corner) ends on it too: the polish could not move it by
anything that matters against that sd.

The errors of each of these approximations (quadrature orders, pixel models, the ``erf``
product, noise-free corners and dots) are measured by ``python benchmarks/bench_refine.py
--model-accuracy``; results in ``docs/model.md`` ("Accuracy of the image model").

*Dot.* A dark ellipse ``(x - c)^T Q (x - c) <= 1`` (``Q`` symmetric positive definite, semi-axes
``1 / sqrt(eig Q)``) on a bright background, modelled as a locally straight blurred edge,
``P = Phi(d / sigma + sigma kappa / 2)``, where ``d = (r - 1) r / |Q (x - c)|`` with
``r = sqrt((x - c)^T Q (x - c))`` approximates the signed distance to the boundary (exact for
circles and on the axes of an ellipse) and ``kappa = det(Q) r^3 / |Q (x - c)|^3`` is the
boundary's curvature at ``c + (x - c) / r``. The curvature term is the first-order effect of
blurring a curved edge: the half-intensity contour of a blurred disc of radius ``R`` lies
``sigma^2 / (2 R)`` inside it, so without the term the fitted axes would come out short by
about that much. The model error is point-symmetric about the centre, so the fitted centre is
unbiased either way. Valid for dots a few sigma across; the noise-free centre and axis errors
against dot size are measured by the same benchmark.

Shared blur
-----------
With ``sigma='shared'`` (:func:`refine_corners`) and ``sharpened``, when the sampled corners'
Gaussian fits miss the image by more than 1.5 % of the contrast (``_SHARPEN_MIN_MISFIT``; renders
at 2 DN noise: 1.0 %), they are also fitted with their own :class:`SharpenedPSF`, a Gaussian blur
followed by an unsharp mask (``(1 + amount) G_sigma - amount G_wide``), the in-camera sharpening
of video streams. When at least half of those fits converge, the median amount is above 0.05 and
their median residual RMS is at most 0.85 times the Gaussian fits' (``_SHARPEN_GAIN``), every
corner is fitted with the median PSF (``sharpening`` says which; each evaluation costs two
Gaussian ones). On unsharp-masked renders it recovers the mask and brings the residual down to
the noise (``tests/test_refine.py``); on a real stream's frames the sharpened fits do not
converge and do not fit better (``sharpening_gain`` about 1;
``docs/notes/performance-real-detector.md``), and the choice below applies.

Otherwise, when the sampled corners' fits put the blur below 0.5 px (``_STEEP_EDGE_BLUR``) and
their residual RMS exceeds 3 % (``_STEEP_EDGE_MISFIT``) of their contrast (median over the
sample), the edges are steeper than any Gaussian blur with pixel integration makes: a camera
sharpened them, and the blur the fit finds is no blur but the model's way of steepening them. The
fit then fixes the blur at 0.5 px, where the cheap pixel model ends the fit (its bias there is a
few hundredths of such corners' sd), and says so in ``steep_edges``; a collapsed blur would need
a finer pixel rule, more iterations and leave more corners unconverged, for positions no closer
to the truth on sharpened renders (``tests/test_refine.py``). A render with a genuinely small
blur fits to its noise and keeps its blur.

With ``sigma='shared'`` the blur may come out anisotropic: a Gaussian PSF of covariance ``S``
(Image model), fixed for every corner, chosen only when up to 48 corners' own fits of ``S`` find
an anisotropy beyond its noise (chi^2 test of the median of ``((S_xx - S_yy) / 2, S_xy)`` at
p = 0.001) and a major over minor sd of at least 1.25; an isotropic blur keeps the isotropic
model. With ``max_window`` the window then grows to ``ceil(3 sigma_major) + 2`` px (at most
``max_window``), so that it holds the blurred edges.

References
----------
.. [1] W. F. Sheppard, "On the application of the theory of error to cases of normal distribution
   and normal correlation", Phil. Trans. R. Soc. A 192 (1899) 101-167.
.. [2] A. Genz, "Numerical computation of rectangular bivariate and trivariate normal and t
   probabilities", Statistics and Computing 14 (2004) 251-260.
.. [3] K. Levenberg (1944); D. W. Marquardt, "An algorithm for least-squares estimation of
   nonlinear parameters", J. SIAM 11 (1963) 431-441.
.. [4] D. Chen, G. Zhang, "A new sub-pixel detector for X-corners in camera calibration targets",
   WSCG 2005; and A. Geiger et al., "Automatic camera and range sensor calibration using a single
   shot", ICRA 2012 (model-fitting corner refinement).
.. [5] J. Heikkila, "Moment and curvature preserving technique for accurate ellipse boundary
   detection", ICPR 1998; J. Mallon, P. F. Whelan, "Which pattern? Biasing aspects of planar
   calibration patterns and detection methods", Pattern Recognit. Lett. 28 (2007) 921-930
   (the ellipse centre is not the projected circle centre).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from ..imaging import (  # noqa: F401 (re-exported)
    _phi,
    _sheppard,
    auto_n_sub,
    bivariate_normal_cdf,
    pixel_nodes,
)
from .cornermodel import (
    _GAUSSIAN_PIXEL_SIGMA,
    Blur,
    PixelModel,
    SharpenedPSF,
    _blur_variances,
    _dot_eval,
    _dot_params,
    _dot_shape,
    _extract,
    _window_grid,
    _xj_eval,
    _xj_eval_sharpened,
    dot_image,
    xjunction_image,
)

__all__ = [
    "RefineOptions",
    "RefineResult",
    "DotResult",
    "refine_corners",
    "refine_dots",
    "bivariate_normal_cdf",
    "xjunction_image",
    "dot_image",
    "pixel_nodes",
    "auto_n_sub",
]


def _as_image(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be a 2-D grey-level array, got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise ValueError(f"image must be an integer or float array, got dtype {img.dtype}")
    return img


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    pts = pts.reshape(-1, 2) if pts.size else np.zeros((0, 2))
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name} contains non-finite values")
    return pts


# ----------------------------------------------------------------------------------------------
# Batched Levenberg-Marquardt
# ----------------------------------------------------------------------------------------------
@dataclass
class _LMOut:
    p: np.ndarray
    jac: np.ndarray
    resid: np.ndarray
    cost: np.ndarray
    converged: np.ndarray
    n_iter: np.ndarray


def _batched_lm(
    fun: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    p0: np.ndarray,
    data: np.ndarray,
    weights: np.ndarray,
    *,
    max_iter: int | np.ndarray,
    tol: float,
    rel_tol: float = 0.0,
    valid: Callable[[np.ndarray], np.ndarray] | None = None,
    judged_at_cap: int | None = None,
    crawl_iter: int = 0,
) -> _LMOut:
    """Levenberg-Marquardt on K independent least-squares problems at once.

    Minimises ``sum_m w_km (d_km - f_m(p_k))^2`` for every ``k``. Each iteration solves, per
    problem, ``(J^T W J + lambda diag(J^T W J)) delta = J^T W (d - f)`` (Marquardt's scaling),
    accepts the step if the cost does not increase (``lambda /= 3``), else rejects it
    (``lambda *= 8``). A problem has converged when, while ``lambda <= 0.01``, every parameter's
    step is below ``tol`` px of position equivalent or below ``rel_tol`` of its conditional
    standard deviation ``s / sqrt(A_jj)`` (``s^2 = cost / (M - P)``), whichever is larger::

        |delta_j| sqrt(A_jj) < max(tol max(sqrt(A_00), sqrt(A_11)), rel_tol s)

    (and the position, the first two parameters, by less than ``tol`` unless the second term
    applies); that last step is taken without re-evaluating the model. ``rel_tol`` ends fits
    whose residual is large (a model that does not describe the image exactly) where further
    steps cannot move the result by anything that matters against its own uncertainty; with
    it, a problem that used its iterations is converged where its undamped step from there
    passes that test for its first ``judged_at_cap`` parameters (None: all;
    :func:`_stationary_at_cap`), and one whose step is within :data:`_CRAWL_SD` of its sd gets
    up to ``crawl_iter`` more iterations, in runs of :data:`_CRAWL_RUN` each judged so. A
    problem whose
    ``lambda`` exceeds 1e10 has stalled (not converged).

    Parameters
    ----------
    fun : callable ``(p (k, P), idx (k,)) -> (f (k, M), jac (k, M, P))``
    p0 : (K, P) ndarray
    data, weights : (K, M) ndarray
    max_iter : int or (K,) int ndarray
        Iterations allowed, one cap for all problems or one per problem.

    Returns
    -------
    _LMOut
    """
    p = p0.copy()
    n_all = np.arange(p.shape[0])
    f, jac = fun(p, n_all)
    resid = data - f
    cost = np.einsum("km,km->k", weights, resid * resid)
    lam = np.full(p.shape[0], 1e-3)
    active = np.isfinite(cost)
    stalled = np.zeros(p.shape[0], dtype=bool)
    converged = np.zeros(p.shape[0], dtype=bool)
    n_iter = np.zeros(p.shape[0], dtype=int)
    budget = np.broadcast_to(np.asarray(max_iter, dtype=int), (p.shape[0],)).copy()
    granted = np.zeros(p.shape[0], dtype=int)  # iterations added for crawling
    while True:
        active &= n_iter < budget
        idx = np.flatnonzero(active)
        if idx.size == 0:
            if rel_tol <= 0:
                break
            at_cap = ~converged & ~stalled & np.isfinite(cost) & (n_iter >= budget)
            crawling = _stationary_at_cap(p, jac, resid, cost, weights, converged, at_cap,
                                          rel_tol, judged_at_cap) & (granted < crawl_iter)
            if not crawling.any():
                break
            # close to its minimum, but crawling there: on, and judged again, in short runs
            more = np.minimum(_CRAWL_RUN, crawl_iter - granted[crawling])
            budget[crawling] += more
            granted[crawling] += more
            active |= crawling
            continue
        step, tiny = _damped_step(jac[idx], weights[idx], resid[idx], cost[idx], lam[idx],
                                  tol, rel_tol)
        n_iter[idx] += 1
        done = idx[tiny]
        p[done] += step[tiny]
        converged[done] = True
        active[done] = False
        idx, step = idx[~tiny], step[~tiny]
        if idx.size == 0:
            continue
        pt = p[idx] + step
        ft, jt = fun(pt, idx)
        rt = data[idx] - ft
        ct = np.einsum("km,km->k", weights[idx], rt * rt)
        ok = np.isfinite(ct) & (ct <= cost[idx] * (1.0 + 1e-12) + 1e-300)
        if valid is not None:
            ok &= valid(pt)
        acc = idx[ok]
        p[acc], f[acc], jac[acc], resid[acc], cost[acc] = pt[ok], ft[ok], jt[ok], rt[ok], ct[ok]
        lam[acc] = np.maximum(lam[acc] / 3.0, 1e-9)
        lam[idx[~ok]] *= 8.0
        stalled[idx[lam[idx] > 1e10]] = True
        active &= ~stalled
    return _LMOut(p, jac, resid, cost, converged, n_iter)


def _damped_step(jac: np.ndarray, weights: np.ndarray, resid: np.ndarray, cost: np.ndarray,
                 lam: np.ndarray, tol: float, rel_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """One Marquardt step per problem, and whether it is small enough to end the problem.

    ``jac`` (k, M, P), ``weights``, ``resid`` (k, M), ``cost``, ``lam`` (k,). Returns the step
    (k, P) solving ``(A + lambda diag(A)) delta = J^T W r`` and ``tiny`` (k,): every parameter's
    step passes :func:`_batched_lm`'s stopping test while ``lambda <= 0.01`` (a near
    Gauss-Newton step, not one shrunk by damping), so it is taken without re-evaluating.
    """
    n_par = jac.shape[2]
    jw = jac * weights[:, :, None]
    normal = np.einsum("kmp,kmq->kpq", jw, jac)
    grad = np.einsum("kmp,km->kp", jw, resid)
    diag = np.diagonal(normal, axis1=1, axis2=2)
    damp = lam[:, None] * (diag + 1e-9 * diag.max(axis=1, keepdims=True) + 1e-300)
    damped = normal + damp[:, :, None] * np.eye(n_par)
    try:
        step = np.linalg.solve(damped, grad[..., None])[..., 0]
    except np.linalg.LinAlgError:
        step = np.einsum("kpq,kq->kp", np.linalg.pinv(damped), grad)  # a singular problem
    scale = np.sqrt(np.maximum(diag, 1e-300))  # parameter scale for the stopping test
    # |delta_j| sqrt(A_jj) / s is the step in units of the parameter's conditional sd
    dof = np.maximum(weights.sum(axis=1) - n_par, 1.0)
    small = np.abs(step) * scale < rel_tol * np.sqrt(cost / dof)[:, None]
    small[:, :2] |= np.abs(step[:, :2]) < tol
    small[:, 2:] |= np.abs(step[:, 2:]) * scale[:, 2:] < \
        tol * np.max(scale[:, :2], axis=1, keepdims=True)
    return step, np.all(small, axis=1) & (lam <= 1e-2)


def _stationary_at_cap(p: np.ndarray, jac: np.ndarray, resid: np.ndarray, cost: np.ndarray,
                       weights: np.ndarray, converged: np.ndarray, at_cap: np.ndarray,
                       rel_tol: float, judged: int | None = None) -> np.ndarray:
    """Problems that used their iterations while still taking steps (``at_cap``): converged
    after all, in place, where the undamped Gauss-Newton step from where they stopped moves
    each of the first ``judged`` parameters (None: all) by less than ``rel_tol`` of its
    conditional sd, ``|delta_j| sqrt(A_jj) < rel_tol s``; that step is taken. A model that
    misses the image (a sharpened, compressed frame) crawls there under damping: its last
    steps cannot move the corner by anything that matters against its own sd. A fit whose
    result includes its blur judges every parameter: a blur still running to its bound (steep
    edges) keeps it unconverged. Returns the problems left whose step is within
    :data:`_CRAWL_SD` of their sd: close to their minimum, crawling there."""
    crawling = np.zeros(len(p), dtype=bool)
    idx = np.flatnonzero(at_cap)
    if idx.size == 0:
        return crawling
    n_par = p.shape[1]
    jw = jac[idx] * weights[idx, :, None]
    A = np.einsum("kmp,kmq->kpq", jw, jac[idx])
    g = np.einsum("kmp,km->kp", jw, resid[idx])
    solvable = np.linalg.cond(A) < 1e14
    idx, A, g = idx[solvable], A[solvable], g[solvable]
    if idx.size == 0:
        return crawling
    step = np.linalg.solve(A, g[..., None])[..., 0]
    scale = np.sqrt(np.maximum(np.diagonal(A, axis1=1, axis2=2), 1e-300))
    dof = np.maximum(weights[idx].sum(axis=1) - n_par, 1.0)
    in_sd = ((np.abs(step) * scale)[:, :judged]
             / np.sqrt(cost[idx] / dof)[:, None]).max(axis=1)
    small = in_sd < rel_tol
    p[idx[small]] += step[small]
    converged[idx[small]] = True
    crawling[idx[~small & (in_sd < _CRAWL_SD)]] = True
    return crawling


def _covariance(out: _LMOut, weights: np.ndarray, n_par: int) -> tuple[np.ndarray, np.ndarray]:
    """Residual-variance-scaled inverse normal matrix, position block, and residual RMS.

    ``s^2 = sum w r^2 / (n - P)``, ``cov = s^2 (J^T W J)^-1[:2, :2]``.
    """
    n = weights.sum(axis=1)
    jw = out.jac * weights[:, :, None]
    A = np.einsum("kmp,kmq->kpq", jw, out.jac)
    s2 = out.cost / np.maximum(n - n_par, 1.0)
    cov = np.full((A.shape[0], 2, 2), np.nan)
    ok = np.all(np.isfinite(A.reshape(A.shape[0], -1)), axis=1)
    ok[ok] = np.linalg.cond(A[ok]) < 1e14
    if np.any(ok):
        cov[ok] = np.linalg.inv(A[ok])[:, :2, :2] * s2[ok, None, None]
    return cov, np.sqrt(out.cost / np.maximum(n, 1.0))


# ----------------------------------------------------------------------------------------------
# Corner refinement
# ----------------------------------------------------------------------------------------------
@dataclass
class RefineResult:
    """Result of :func:`refine_corners`.

    Attributes
    ----------
    points : (K, 2) ndarray
        Refined corner positions, px, OpenCV convention (centre of the top-left pixel = (0, 0)).
        Corners that did not converge keep the fitted value; check ``converged``.
    cov : (K, 2, 2) ndarray
        1-sigma covariance of ``points`` from the fit, px^2: the residual-variance-scaled inverse
        normal matrix (all parameters), position block. NaN where singular.
    converged : (K,) bool
        The fit converged, stayed inside its window and found a real junction.
    rms : (K,) ndarray
        Residual RMS per corner, intensity units of the input image.
    angles : (K, 2) ndarray
        Edge direction angles in [0, pi), rad (from +x towards +y).
    contrast : (K,) ndarray
        ``a``, signed: the model is ``b + a`` in the two opposite sectors where
        ``u_1 u_2 < 0`` (``u_i = n_i . (x - c)``, ``n_i = (-sin alpha_i, cos alpha_i)``) and ``b``
        in the other two (see :func:`xjunction_image`).
    offset : (K,) ndarray
        ``b``.
    sigma : (K,) ndarray
        Gaussian PSF sd, px (fitted or the fixed value); for an anisotropic PSF the root mean
        square of its two principal sds, ``sqrt(tr(psf_cov) / 2)``.
    n_iter : (K,) ndarray
        Levenberg-Marquardt iterations.
    psf_cov : (K, 2, 2) ndarray
        Covariance of the Gaussian PSF, px^2, rows and columns in (x, y) order: ``sigma^2 I``
        for an isotropic blur. ``sigma`` is ``sqrt(tr(psf_cov) / 2)``.
    steep_edges : bool
        With ``sigma='shared'``: the corners' own fits put the blur below
        ``_STEEP_EDGE_BLUR`` while missing the image by more than ``_STEEP_EDGE_MISFIT`` of
        their contrast, the signature of edges steeper than any Gaussian blur makes (a camera
        that sharpens), and the sharpened PSF did not fit them better; the blur was then fixed
        at ``_STEEP_EDGE_BLUR`` (see :func:`refine_corners`).
    sharpening : SharpenedPSF or None
        With ``sigma='shared'``: the sharpened PSF every corner was fitted with, when the
        sampled corners chose it (:func:`refine_corners`); ``sigma`` is then its narrow
        Gaussian's sd.
    sharpening_gain : float
        The sampled corners' median residual RMS under their own sharpened PSFs over that
        under their own Gaussian blurs (below 1: the sharpened PSF fits better); NaN when not
        tried (``sigma`` not ``'shared'``, ``sharpened=False``, fewer than 8 corners, or the
        Gaussian fits within ``_SHARPEN_MIN_MISFIT`` of the contrast).
    """

    points: np.ndarray
    cov: np.ndarray
    converged: np.ndarray
    rms: np.ndarray
    angles: np.ndarray
    contrast: np.ndarray
    offset: np.ndarray
    sigma: np.ndarray
    n_iter: np.ndarray
    psf_cov: np.ndarray
    steep_edges: bool = False
    sharpening: SharpenedPSF | None = None
    sharpening_gain: float = float("nan")

    @classmethod
    def unrefined(cls, points: np.ndarray) -> RefineResult:
        """The result before any fit: ``points`` (K, 2) as given, every fitted value NaN (or
        0 iterations) and none converged."""
        K = points.shape[0]
        return cls(
            points=points.copy(), cov=np.full((K, 2, 2), np.nan), converged=np.zeros(K, bool),
            rms=np.full(K, np.nan), angles=np.full((K, 2), np.nan),
            contrast=np.full(K, np.nan), offset=np.full(K, np.nan), sigma=np.full(K, np.nan),
            n_iter=np.zeros(K, int), psf_cov=np.full((K, 2, 2), np.nan),
        )


def _initial_angles(data: np.ndarray, window: int, local: np.ndarray) -> np.ndarray:
    """Two dominant edge directions per patch from a gradient-orientation histogram.

    The gradient of an X-junction patch points along the edge normals. The orientations
    ``theta_m = atan2(g_y, g_x) mod pi`` are histogrammed in 3 deg bins weighted by
    ``|grad I_m|^2``, the histogram is smoothed circularly (binomial kernel, sd ~4 deg); its
    highest bin gives one normal, the highest bin at least 25 deg away the other. Pixels within
    1.5 px of the initial corner are left out (their gradients mix both edges).

    Parameters
    ----------
    data : (K, M) ndarray
        Window pixels, row-major.
    window : int
    local : (K, 2) ndarray
        Initial corner in window coordinates.

    Returns
    -------
    (K, 2) ndarray
        Edge direction angles (normal + pi/2), rad.
    """
    n = 2 * window + 1
    n_bins = 60
    img = data.reshape(-1, n, n)
    gy, gx = np.gradient(img, axis=(1, 2))
    grid = _window_grid(window)
    rr = np.hypot(grid[None, :, 0] - local[:, None, 0], grid[None, :, 1] - local[:, None, 1])
    wgt = (gx * gx + gy * gy).reshape(len(img), -1) * (rr > 1.5)
    theta = np.mod(np.arctan2(gy, gx).reshape(len(img), -1), np.pi)
    b = np.minimum((theta * (n_bins / np.pi)).astype(np.int64), n_bins - 1)
    b += n_bins * np.arange(len(img))[:, None]
    hist = np.bincount(b.ravel(), wgt.ravel(), minlength=n_bins * len(img)).reshape(-1, n_bins)
    for _ in range(3):  # (1, 2, 1)^3 / 64: circular binomial smoothing
        hist = 0.5 * hist + 0.25 * (np.roll(hist, 1, axis=1) + np.roll(hist, -1, axis=1))
    centres = (np.arange(n_bins) + 0.5) * (np.pi / n_bins)
    j1 = np.argmax(hist, axis=1)
    sep = np.abs(np.angle(np.exp(2j * (centres[None, :] - centres[j1][:, None])))) / 2.0
    j2 = np.argmax(np.where(sep > np.deg2rad(25.0), hist, -np.inf), axis=1)
    return np.column_stack([centres[j1], centres[j2]]) + 0.5 * np.pi


def _linear_ab(pix: np.ndarray, data: np.ndarray, weights: np.ndarray):
    """Weighted least-squares ``a, b`` of ``data ~ b + a * pix``, per row."""
    sw = weights.sum(1)
    mx = (weights * pix).sum(1) / sw
    my = (weights * data).sum(1) / sw
    vx = (weights * (pix - mx[:, None]) ** 2).sum(1)
    cxy = (weights * (pix - mx[:, None]) * (data - my[:, None])).sum(1)
    a = cxy / np.maximum(vx, 1e-300)
    return a, my - a * mx


def _normalise_xj(p: np.ndarray) -> np.ndarray:
    """Map edge angles into [0, pi); flipping one edge by pi complements the pattern."""
    p = p.copy()
    for i in (2, 3):
        flip = np.floor(p[:, i] / np.pi).astype(int) % 2 == 1
        p[:, i] = np.mod(p[:, i], np.pi)
        # complement: b + a g -> (b + a) - a (1 - g)
        p[flip, 5] += p[flip, 4]
        p[flip, 4] *= -1.0
    return p


@dataclass(frozen=True)
class RefineOptions:
    """How :func:`refine_corners` fits, beside its window and blur.

    Attributes
    ----------
    pixel_model : {'quadrature', 'gaussian'}
        Pixel integration model for the final iterations.
    n_sub : int, optional
        Gauss-Legendre nodes per pixel axis for ``'quadrature'``; by default
        :func:`auto_n_sub` of the smallest blur in the batch (3 at sigma = 0.7 px).
    max_iter : int
        Levenberg-Marquardt iterations per stage.
    tol : float
        Position step (px) below which a fit has converged.
    chunk : int
        Corners per vectorised batch (bounds memory: about ``chunk * M * n_sub^2 * 16``
        doubles per temporary array, ``M = (2 window + 1)^2``).
    max_window : int, optional
        Largest half-size the window may grow to with a fixed or shared blur,
        ``ceil(3 sigma_major) + 2``; None keeps ``window``. Neighbouring corners must lie
        outside it.
    anisotropic : bool
        With ``sigma='shared'``, allow the anisotropic PSF; False keeps the isotropic one.
    sharpened : bool
        With ``sigma='shared'``, allow the sharpened PSF; False keeps the Gaussian one.
    """

    pixel_model: PixelModel = "quadrature"
    n_sub: int | None = None
    max_iter: int = 30
    tol: float = 1e-5
    chunk: int = 256
    max_window: int | None = None
    anisotropic: bool = True
    sharpened: bool = True


def refine_corners(image: np.ndarray, corners: np.ndarray, window: int = 5,
                   sigma: float | Literal["shared"] | None = None,
                   options: RefineOptions | None = None, **fields) -> RefineResult:
    """Model-based subpixel refinement of chessboard X-junctions.

    For each initial corner (within ~1 px of the truth) the pixels of the ``(2 window + 1)^2``
    window centred on the nearest pixel are fitted by least squares with the pixel-integrated
    blurred X-junction (module docstring)::

        I(x) = b + a (Phi(h) + Phi(k) - 2 Phi_2(h, k; cos(alpha_1 - alpha_2))),
        h = n_1 . (x - c) / sigma,  k = n_2 . (x - c) / sigma,  n_i = (-sin alpha_i, cos alpha_i),

    over ``theta = (c_x, c_y, alpha_1, alpha_2, a, b[, log sigma])`` with batched
    Levenberg-Marquardt and analytic Jacobians (all corners at once, in chunks of
    ``options.chunk``). Edge angles start from the gradient-orientation histogram of the patch,
    ``a, b`` by linear least squares; the first iterations use the variance-matched Gaussian
    pixel model, the last ones (at most 8 for a corner that model did not converge) the
    requested ``options.pixel_model``, except for a fixed or shared ``sigma`` of 1 px or more,
    where the Gaussian pixel model is as exact (module docstring) and the fit ends on it. The
    covariance is ``s^2 (J^T J)^-1`` (position block) with ``s^2 = RSS / (n - P)``.

    With ``sigma='shared'`` the blur every corner is fitted with is chosen from a sample of
    corners' own fits: a Gaussian, a sharpened PSF, a steep-edge blur or an anisotropic
    Gaussian (module docstring, section Shared blur).

    Parameters
    ----------
    image : (H, W) ndarray
        Grey-level image, uint8 / uint16 / float (processed as float64).
    corners : (K, 2) ndarray
        Initial corners ``(x, y)``, px, OpenCV convention.
    window : int
        Half-size of the fitting window, px (5 -> 11 x 11 pixels).
    sigma : float, 'shared' or None
        Gaussian PSF sd, px. A float fixes it; None fits it per corner; 'shared' fits it on up to
        64 corners spread over the list, takes the median over converged ones and fits every
        corner with that value fixed (a two-stage estimate of one common blur), or with the
        shared anisotropic covariance when the data ask for it (see above).
    options : RefineOptions, optional
        Pixel model, iterations, batches and the window's growth (default: its defaults);
        ``fields``, keywords named as its fields, replace them (``max_window=12``).

    Returns
    -------
    RefineResult

    Raises
    ------
    ValueError
        If ``image`` is not 2-D, or ``corners`` has non-finite values.

    References
    ----------
    Sheppard (1899), Marquardt (1963), Chen & Zhang (2005), Geiger et al. (2012) -- see the
    module docstring.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:40, 0:40]
    >>> img = xjunction_image(np.column_stack([xx.ravel(), yy.ravel()]), [20.3, 19.6],
    ...                       [0.2, 1.9], 0.8).reshape(40, 40)
    >>> res = refine_corners(img, [[20.0, 20.0]])
    >>> np.round(res.points, 4).tolist(), bool(res.converged[0])
    ([[20.3, 19.6]], True)
    """
    opts = replace(options or RefineOptions(), **fields)
    img = _as_image(image)
    pts = _as_points(corners, "corners")
    _check_refine_arguments(window, sigma, opts.pixel_model)
    max_window = window if opts.max_window is None else max(int(opts.max_window), window)
    K, chunk = pts.shape[0], opts.chunk
    out = RefineResult.unrefined(pts)
    chunks = [_CornerChunk.start(img, pts[s:s + chunk], window, slice(s, min(s + chunk, K)))
              for s in range(0, K, chunk)]
    blur: Blur | None = sigma
    if sigma == "shared":
        blur = _choose_shared_blur(img, chunks, out, window, max_window, opts.max_iter,
                                   opts.tol if opts.pixel_model == "gaussian" else 1e-3,
                                   opts.anisotropic, opts.sharpened)
    if blur is not None:
        grown = _blur_window(blur, window, max_window)
        for c in chunks:
            c.regrow(img, grown)
            c.fix_blur(blur)
    for whole in chunks:
        _fit_chunk(whole, blur, out, opts.pixel_model, opts.n_sub, opts.max_iter, opts.tol)
    return out


def _check_refine_arguments(window: int, sigma, pixel_model: str) -> None:
    """ValueError for a window below 2 px, an unknown ``sigma`` string or pixel model."""
    if window < 2:
        raise ValueError(f"window must be >= 2, got {window}")
    if isinstance(sigma, str) and sigma != "shared":
        raise ValueError(f"sigma must be a float, 'shared' or None, got {sigma!r}")
    if pixel_model not in ("quadrature", "gaussian"):
        raise ValueError(f"pixel_model must be 'quadrature' or 'gaussian', got {pixel_model!r}")


def _choose_shared_blur(img: np.ndarray, chunks: list[_CornerChunk], out: RefineResult,
                        window: int, max_window: int, max_iter: int, tol: float,
                        anisotropic: bool, sharpened: bool) -> Blur:
    """The blur every corner is fitted with under ``sigma='shared'`` (:func:`_shared_blur`),
    or the steep-edge blur where the sampled corners' Gaussian blur collapses while missing
    the image (:func:`refine_corners`); records ``sharpening``, ``sharpening_gain`` and
    ``steep_edges`` in ``out``."""
    blur, misfit, out.sharpening_gain = _shared_blur(img, chunks, window, max_window,
                                                     max_iter, tol, anisotropic, sharpened)
    if isinstance(blur, SharpenedPSF):
        out.sharpening = blur
    elif np.ndim(blur) == 0 and blur < _STEEP_EDGE_BLUR and misfit > _STEEP_EDGE_MISFIT:
        blur, out.steep_edges = _STEEP_EDGE_BLUR, True
    return blur


def _fit_chunk(whole: _CornerChunk, blur: Blur | None, out: RefineResult,
               pixel_model: PixelModel, n_sub: int | None, max_iter: int, tol: float) -> None:
    """Fit one batch of corners at ``blur`` and store them in ``out`` (the stages of
    :func:`refine_corners`): from a blur of ``_GAUSSIAN_PIXEL_SIGMA`` across both edges on,
    the variance-matched Gaussian pixel model is as good as the quadrature on noise-free
    corners (module docstring) and such corners are fitted on it alone; the others on it,
    then polished with the quadrature unless their own sd dwarfs its bias."""
    gaussian_only = pixel_model == "gaussian"
    cheap = np.full(len(whole.p), gaussian_only)
    if blur is not None and not gaussian_only:
        cheap = whole.edge_sd(blur) >= _GAUSSIAN_PIXEL_SIGMA
    fine = whole.subset(~cheap)
    if len(fine.p):
        # The cheap model brings every corner close (its iterations cost a fraction of a
        # quadrature one), so the quadrature stage only polishes
        # (docs/notes/performance-real-detector.md). A
        # corner it brought close converges in a few of these iterations; one it did not
        # rarely does at all, and must not cost max_iter quadrature ones.
        fine.fit(blur, "gaussian", 1, max_iter, 1e-3)
        # A corner whose position sd dwarfs the Gaussian pixel model's bias (a poor fit on
        # a real, sharpened frame; a dim corner) ends here: polishing cannot move it by
        # anything that matters against its own sd.
        done = fine.gaussian_is_final(blur) if pixel_model == "quadrature" else \
            np.zeros(len(fine.p), bool)
        final = fine.subset(done)
        if len(final.p):
            final.store(out, blur)
        fine = fine.subset(~done)
    if len(fine.p):
        budget = np.where(fine.lm.converged, max_iter, min(max_iter, _POLISH_ITER))
        fine.fit(blur, "quadrature", n_sub or auto_n_sub(fine.smallest_sigma(blur)),
                 budget, tol)
        fine.store(out, blur)
    coarse = whole.subset(cheap)
    if len(coarse.p):
        coarse.fit(blur, "gaussian", 1, max_iter, tol)
        coarse.store(out, blur)


_POLISH_ITER = 8  # iteration cap of the final (quadrature) stage of refine_corners
# A corner fit at a given blur that ends its iterations with an undamped step below this many
# of its sds is close to its minimum but crawling there under damping (a model that misses a
# sharpened frame's edges): it gets _CRAWL_ITER more iterations (_batched_lm).
_CRAWL_SD = 1.0
_CRAWL_ITER = 70
_CRAWL_RUN = 10
_REL_TOL = 0.05  # a corner fit stops on steps below this fraction of each parameter's sd
_FINAL_FRACTION = 0.05  # of a corner's position sd: a bias or a step below it does not matter
# Largest position error of the Gaussian pixel model on noise-free corners against the blur
# (px, px), from ``python benchmarks/bench_refine.py --model-accuracy`` (docs/model.md).
_GAUSSIAN_BIAS_SIGMA = np.array([0.3, 0.5, 0.7, 1.0, 1.6])
_GAUSSIAN_BIAS = np.array([1.3e-2, 7.6e-4, 9.9e-5, 3.7e-5, 1.2e-5])


def gaussian_pixel_bias(sigma: float | np.ndarray) -> np.ndarray:
    """Bound on the corner position error (px) of the variance-matched Gaussian pixel model at
    a blur of ``sigma`` px across the edges: the measured errors of docs/model.md, interpolated
    in log-log; infinite below the smallest measured blur (0.3 px), the largest measured value
    scaled as ``sigma^-2.5`` above.

    Examples
    --------
    >>> round(float(gaussian_pixel_bias(0.5)), 6), bool(np.isinf(gaussian_pixel_bias(0.2)))
    (0.00076, True)
    """
    sig = np.asarray(sigma, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        logb = np.interp(np.log(np.maximum(sig, 1e-300)), np.log(_GAUSSIAN_BIAS_SIGMA),
                         np.log(_GAUSSIAN_BIAS), left=np.inf, right=np.nan)
        out = np.exp(logb)
        tail = _GAUSSIAN_BIAS[-1] * (sig / _GAUSSIAN_BIAS_SIGMA[-1]) ** -2.5
    return np.where(sig > _GAUSSIAN_BIAS_SIGMA[-1], tail, np.where(np.isfinite(sig), out, np.inf))
_BLUR_SAMPLE = 64  # corners, spread over the image's list, whose own fits give the shared blur
_STEEP_EDGE_BLUR = 0.5  # px: a shared blur below this with a large misfit is sharpening
_STEEP_EDGE_MISFIT = 0.03  # of the contrast: the sampled corners' median residual RMS above it
_SHARPEN_MAX_AMOUNT = 5.0  # largest unsharp-mask amount a sharpened PSF's fit may reach
_SHARPEN_START = SharpenedPSF(0.7, 0.5, 1.0)  # start of the sampled corners' sharpened fits
_SHARPEN_MIN_AMOUNT = 0.05  # a median amount at or below this is no sharpening
# iteration cap of the sampled corners' sharpened fits: on unsharp-masked renders they
# converge in 8 (median); on frames the PSF does not describe they would run to any cap
_SHARPEN_ITER = 15
_SHARPEN_GAIN = 0.85  # the sharpened PSF is used when its residual is at most this x Gaussian's
# of the contrast: the Gaussian fits' misfit from which a sharpened PSF is tried (renders at
# 2 DN noise: 0.010; unsharp-masked ones: 0.026; a real H.264 stream's frames: 0.06-0.08)
_SHARPEN_MIN_MISFIT = 0.015
_ANISO_SAMPLE = 48  # corners whose own anisotropic fits estimate the shared PSF covariance
_ANISO_CHI2 = 13.8  # chi^2 (2 dof) at p = 0.001: the anisotropy is beyond its noise
_ANISO_MIN_RATIO = 1.25  # major over minor PSF sd from which the anisotropy is used


def _cov_entries(sd: float) -> np.ndarray:
    """``(S_xx, S_xy, S_yy)`` of the isotropic covariance ``sd^2 I``."""
    return np.array([sd * sd, 0.0, sd * sd])


def _cov_eig_sd(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minor and major sd (px) of covariances given as ``(..., 3)`` entries ``(S_xx, S_xy,
    S_yy)``: the square roots of the eigenvalues ``tr / 2 -+ sqrt(((S_xx - S_yy) / 2)^2 +
    S_xy^2)``."""
    cov = np.asarray(cov, dtype=float)
    half_tr = 0.5 * (cov[..., 0] + cov[..., 2])
    d = np.hypot(0.5 * (cov[..., 0] - cov[..., 2]), cov[..., 1])
    return np.sqrt(np.maximum(half_tr - d, 0.0)), np.sqrt(np.maximum(half_tr + d, 0.0))


def _minor_sd(blur: Blur) -> float:
    """Smallest PSF sd, px, of a fixed blur (sd, covariance entries or sharpened PSF)."""
    if isinstance(blur, SharpenedPSF):
        return blur.sigma
    return float(blur) if np.ndim(blur) == 0 else float(_cov_eig_sd(blur)[0])


def _blur_window(blur: Blur, window: int, max_window: int) -> int:
    """Half-size that holds ``3 sigma_major + 2`` px of the blurred edges (of the narrow
    Gaussian of a sharpened PSF, which carries the position), in ``[window, max_window]``."""
    if isinstance(blur, SharpenedPSF):
        major = blur.wide
    else:
        major = float(blur) if np.ndim(blur) == 0 else float(_cov_eig_sd(blur)[1])
    return int(np.clip(np.ceil(3.0 * major) + 2, window, max_window))


def _sharpened_psf(blurs: _CornerChunk, img: np.ndarray, window: int, max_iter: int,
                   tol: float) -> tuple[SharpenedPSF | None, float]:
    """The sharpened PSF shared by the sampled corners, when it fits them clearly better than
    their own Gaussian blurs; and the ratio of the two fits' median residual RMS over the
    sample (the sharpened fits where they stopped, converged or not).

    Each sampled corner is refitted with its own ``(log sigma, amount, log radius)`` of a
    :class:`SharpenedPSF` (Gaussian pixel model, from ``(0.7, 0.5, 1.0)``, at most
    ``_SHARPEN_ITER`` iterations); the shared PSF is
    the median of each over the converged fits. It is used when at least half the sample
    converged, the median amount is above ``_SHARPEN_MIN_AMOUNT`` and the median residual RMS
    is at most ``_SHARPEN_GAIN`` times the Gaussian fits'. On an unsharp-masked render the fits
    find the mask (tests/test_refine.py); on frames whose residual is not the edge's profile
    (a compressed stream's ragged edges) most do not converge and the Gaussian blur is kept.
    """
    sample = _CornerChunk.start(img, blurs.p[:, :2] + blurs.origin, window,
                                slice(0, len(blurs.p)))
    sample.fit(_SHARPEN_START, "gaussian", 1, min(max_iter, _SHARPEN_ITER), tol, free=True)
    conv = sample.lm.converged
    rms_gauss = np.sqrt(blurs.lm.cost / np.maximum(blurs.weights.sum(axis=1), 1.0))
    rms = np.sqrt(sample.lm.cost / np.maximum(sample.weights.sum(axis=1), 1.0))
    gain = float(np.median(rms) / max(np.median(rms_gauss), 1e-300))
    if conv.mean() < 0.5:
        return None, gain
    psf = SharpenedPSF(float(np.exp(np.median(sample.p[conv, 6]))),
                       float(np.median(sample.p[conv, 7])),
                       float(np.exp(np.median(sample.p[conv, 8]))))
    if psf.amount <= _SHARPEN_MIN_AMOUNT or gain > _SHARPEN_GAIN:
        return None, gain
    return psf, gain


def _shared_blur(img: np.ndarray, chunks: list[_CornerChunk], window: int, max_window: int,
                 max_iter: int, tol: float, anisotropic: bool, sharpened: bool
                 ) -> tuple[Blur, float, float]:
    """The blur shared by the image's corners: an sd (px), a :class:`SharpenedPSF` or, when
    the data ask for it, the entries ``(S_xx, S_xy, S_yy)`` (px^2) of an anisotropic PSF
    covariance; the sampled corners' misfit, the median residual RMS over the median ``|a|``
    (contrast) of those whose blur fit converged; and, with ``sharpened``, the ratio of the
    sharpened PSF's residual to the Gaussian one's on the sample (:func:`_sharpened_psf`; NaN
    when not tried: the Gaussian fits' misfit at most ``_SHARPEN_MIN_MISFIT``).

    The blur of up to ``_BLUR_SAMPLE`` corners spread over the list is fitted (Gaussian pixel
    model); the median over converged ones is the isotropic estimate ``sigma`` (its standard
    error is a few thousandths of a pixel, far below what changes a position). With
    ``anisotropic``, up to ``_ANISO_SAMPLE`` of those corners are refitted, in a window grown
    for ``sigma``, with their own covariance ``S_k``; the anisotropy
    ``d_k = ((S_xx - S_yy) / 2, S_xy)`` is 0 for an isotropic PSF. Its median ``d`` over
    converged corners, with per-component standard errors ``se_j = 1.2533 * 1.4826 MAD_j /
    sqrt(n)`` (median of a normal sample), is significant when ``sum_j (d_j / se_j)^2 >
    _ANISO_CHI2``; the covariance (median of each entry) is used only when it is also
    physically large: major over minor sd at least ``_ANISO_MIN_RATIO``.
    """
    if not chunks:
        return 1.0, 0.0, float("nan")
    start = np.concatenate([c.p[:, :2] + c.origin for c in chunks])
    pick = np.unique(np.linspace(0, len(start) - 1, _BLUR_SAMPLE).round().astype(int))
    blurs = _CornerChunk.start(img, start[pick], window, slice(0, len(pick)))
    blurs.fit(None, "gaussian", 1, max_iter, tol)
    fitted = blurs.sigma_fitted()
    good = np.isfinite(fitted)
    sigma = float(np.median(fitted[good])) if np.any(good) else 1.0
    rms = np.sqrt(blurs.lm.cost / np.maximum(blurs.weights.sum(axis=1), 1.0))
    misfit = float(np.median(rms[good]) / max(np.median(np.abs(blurs.p[good, 4])), 1e-300)) \
        if np.any(good) else 0.0
    gain = float("nan")
    if sharpened and good.sum() >= 8 and misfit > _SHARPEN_MIN_MISFIT:
        psf, gain = _sharpened_psf(blurs.subset(good), img, window, max_iter, tol)
        if psf is not None:
            return psf, misfit, gain
    if not anisotropic or good.sum() < 8:
        return sigma, misfit, gain
    points = (blurs.p[:, :2] + blurs.origin)[good]
    pick = np.unique(np.linspace(0, len(points) - 1, _ANISO_SAMPLE).round().astype(int))
    sample = _CornerChunk.start(img, points[pick], _blur_window(sigma, window, max_window),
                                slice(0, len(pick)))
    sample.fit(sigma, "gaussian", 1, max_iter, tol)
    sample.fit(_cov_entries(sigma), "gaussian", 1, max_iter, tol, free=True)
    cov = sample.p[sample.lm.converged, 6:9]
    if len(cov) < 8:
        return sigma, misfit, gain
    d = np.column_stack([0.5 * (cov[:, 0] - cov[:, 2]), cov[:, 1]])
    d_med = np.median(d, axis=0)
    # the MAD by hand: scipy.stats.median_abs_deviation would import scipy.stats into every
    # detection worker (0.7 s, `python -X importtime -c "import zoomcalib.detect.refine"`)
    se = 1.2533 * 1.4826 * np.median(np.abs(d - d_med), axis=0) / np.sqrt(len(d))
    shared = np.median(cov, axis=0)
    minor, major = _cov_eig_sd(shared)
    significant = np.sum((d_med / np.maximum(se, 1e-12)) ** 2) > _ANISO_CHI2
    if significant and minor > 0 and major >= _ANISO_MIN_RATIO * minor:
        return shared, misfit, gain
    return sigma, misfit, gain


@dataclass
class _CornerChunk:
    """The windows of a batch of corners and the state of their fit, carried across stages.

    ``p`` holds ``(cx, cy, alpha1, alpha2, a, b)`` in window coordinates (origin at the pixel
    ``origin``), followed by the fitted blur when it is fitted: ``log sigma`` or the covariance
    entries ``(S_xx, S_xy, S_yy)``; ``lm`` is the last stage's Levenberg-Marquardt output.
    """

    data: np.ndarray
    weights: np.ndarray
    origin: np.ndarray
    window: int
    where: slice | np.ndarray
    p: np.ndarray
    lm: _LMOut | None = None
    n_iter: np.ndarray | None = None

    @classmethod
    def start(cls, img: np.ndarray, pts: np.ndarray, window: int, where: slice) -> _CornerChunk:
        """Windows around ``pts``, edge angles from the gradient histogram, ``a, b`` linear."""
        data, wts, origin = _extract(img, pts, window)
        local = pts - origin
        n = len(pts)
        # pixels outside the image take the mean of the inside ones (no false edge at the border)
        fill = (data * wts).sum(1, keepdims=True) / np.maximum(wts.sum(1, keepdims=True), 1.0)
        angles = _initial_angles(np.where(wts > 0, data, fill), window, local)
        p0 = np.column_stack([local, angles, np.ones(n), np.zeros(n)])
        pix, _ = _xj_eval(p0, np.ones(n), _window_grid(window), "gaussian", 1, jacobian=False)
        p0[:, 4], p0[:, 5] = _linear_ab(pix, data, wts)
        return cls(data, wts, origin, window, where, p0, None, np.zeros(n, int))

    def fit(self, blur: Blur | None, model: PixelModel, n_sub: int,
            max_iter: int | np.ndarray, tol: float, free: bool = False) -> None:
        """One Levenberg-Marquardt stage. ``blur`` is a fixed sd (px), covariance entries
        ``(S_xx, S_xy, S_yy)`` (px^2) or a :class:`SharpenedPSF`; None fits ``log sigma`` per
        corner; ``free=True`` fits the covariance, or the sharpened PSF's ``(log sigma, amount,
        log radius)``, per corner starting from ``blur``. ``max_iter`` is one cap or one per
        corner."""
        xy = _window_grid(self.window)
        n = len(self.p)
        sharpened = isinstance(blur, SharpenedPSF)
        if blur is None:
            n_par = 7
            p = self.p if self.p.shape[1] == 7 else np.column_stack([self.p[:, :6], np.zeros(n)])
        elif free and sharpened:
            n_par = 9
            start = [np.log(blur.sigma), blur.amount, np.log(blur.radius)]
            p = np.column_stack([self.p[:, :6], np.broadcast_to(start, (n, 3))])
        elif free:
            n_par = 9
            p = np.column_stack([self.p[:, :6], np.broadcast_to(blur, (n, 3))])
        else:
            n_par = 6
            p = self.p[:, :6]

        def fun(q, idx):
            if sharpened:
                k = len(q)
                shape = (q[:, 6:9].T if free else np.array(
                    [[np.log(blur.sigma)], [blur.amount], [np.log(blur.radius)]]
                ).repeat(k, axis=1))
                # a trial step far out of range (rejected by valid below) may overflow
                with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                    f, jac = _xj_eval_sharpened(q[:, :6], np.exp(shape[0]), shape[1],
                                                np.exp(shape[2]), xy, model, n_sub)
                return f, jac[..., :n_par]
            if n_par == 7:
                b_ = np.exp(q[:, 6])
            elif n_par == 9:
                b_ = q[:, 6:9]
            else:
                b_ = np.broadcast_to(np.asarray(blur, float), (len(q),) + np.shape(blur))
            f, jac = _xj_eval(q[:, :6], b_, xy, model, n_sub)
            return f, jac[..., :n_par]

        def valid(q):
            ok = np.all(np.abs(q[:, :2]) < self.window, axis=1)
            if n_par == 7 or (sharpened and free):
                ok &= (q[:, 6] > np.log(0.05)) & (q[:, 6] < np.log(self.window))
            if sharpened and free:
                ok &= (q[:, 7] >= 0.0) & (q[:, 7] < _SHARPEN_MAX_AMOUNT)
                ok &= (q[:, 8] > np.log(0.2)) & (q[:, 8] < np.log(self.window))
            elif n_par == 9:
                minor, major = _cov_eig_sd(q[:, 6:9])
                ok &= (minor > 0.05) & (major < self.window)
            return ok

        # at the cap, a fit at a given blur is judged by its position, the result it gives
        self.lm = _batched_lm(fun, p, self.data, self.weights, max_iter=max_iter, tol=tol,
                              rel_tol=_REL_TOL, valid=valid,
                              judged_at_cap=2 if n_par == 6 else None,
                              crawl_iter=_CRAWL_ITER if n_par == 6 else 0)
        self.p = self.lm.p
        self.n_iter = self.n_iter + self.lm.n_iter

    def gaussian_is_final(self, blur: Blur | None) -> np.ndarray:
        """Corners whose Gaussian-pixel-model fit is final: converged, and both that model's
        position bias at their blur (:func:`gaussian_pixel_bias`) and the stage's stopping step
        (1e-3 px) are within ``_FINAL_FRACTION`` of their own position sd."""
        edge = np.exp(self.p[:, 6]) if blur is None else self.edge_sd(blur)
        cov, _ = _covariance(self.lm, self.weights, self.p.shape[1])
        with np.errstate(invalid="ignore"):
            sd = np.sqrt(np.minimum(cov[:, 0, 0], cov[:, 1, 1]))
        limit = _FINAL_FRACTION * np.where(np.isfinite(sd), sd, 0.0)
        return self.lm.converged & (gaussian_pixel_bias(edge) <= limit) & (1e-3 <= limit)

    def sigma_fitted(self) -> np.ndarray:
        """Per-corner fitted blur, px; NaN where the stage did not converge."""
        return np.where(self.lm.converged, np.exp(self.p[:, 6]), np.nan)

    def regrow(self, img: np.ndarray, window: int) -> None:
        """Re-extract the windows with half-size ``window`` around the current corners."""
        if window == self.window:
            return
        pts = self.p[:, :2] + self.origin
        self.data, self.weights, origin = _extract(img, pts, window)
        self.p = self.p.copy()
        self.p[:, :2] = pts - origin
        self.origin, self.window = origin, window

    def fix_blur(self, blur: Blur) -> None:
        """Fix the blur (sd, covariance entries or sharpened PSF) for the next stage (``a, b``
        refitted)."""
        self.p = self.p[:, :6].copy()
        n = len(self.p)
        self.p[:, 4], self.p[:, 5] = 1.0, 0.0  # so that the model below is the pattern P
        xy = _window_grid(self.window)
        if isinstance(blur, SharpenedPSF):
            pix, _ = _xj_eval_sharpened(self.p, np.full(n, blur.sigma), np.full(n, blur.amount),
                                        np.full(n, blur.radius), xy, "gaussian", 1, False)
        else:
            fixed = np.broadcast_to(np.asarray(blur, float), (n,) + np.shape(blur))
            pix, _ = _xj_eval(self.p, fixed, xy, "gaussian", 1, jacobian=False)
        self.p[:, 4], self.p[:, 5] = _linear_ab(pix, self.data, self.weights)

    def edge_sd(self, blur: Blur) -> np.ndarray:
        """Per corner, the smaller blur across its two edges, px: ``sqrt(n_i^T S n_i)`` for a
        fixed covariance ``S``, ``sigma`` for a fixed sd or a sharpened PSF (its narrow
        Gaussian)."""
        if isinstance(blur, SharpenedPSF):
            return np.full(len(self.p), blur.sigma)
        if np.ndim(blur) == 0:
            return np.full(len(self.p), float(blur))
        a = self.p[:, 2:4]
        normals = np.stack([-np.sin(a), np.cos(a)], axis=-1).reshape(-1, 2)
        v, _, _ = _blur_variances(np.tile(np.asarray(blur, float), (len(normals), 1)),
                                  normals, normals)
        return np.sqrt(v.reshape(-1, 2).min(axis=1))

    def smallest_sigma(self, blur: Blur | None) -> float:
        """The smallest blur of the batch (across an edge, for a fixed covariance), px, for the
        pixel quadrature's order."""
        if blur is not None:
            return float(self.edge_sd(blur).min(initial=np.inf)) if len(self.p) else 1.0
        fitted = self.sigma_fitted()
        return float(np.nanmin(fitted)) if np.any(np.isfinite(fitted)) else 1.0

    def subset(self, keep: np.ndarray) -> _CornerChunk:
        """The corners ``keep`` (bool mask) of this batch, with their fit state."""
        where = (np.arange(self.where.start, self.where.stop)
                 if isinstance(self.where, slice) else self.where)
        lm = None if self.lm is None else _LMOut(
            self.lm.p[keep], self.lm.jac[keep], self.lm.resid[keep], self.lm.cost[keep],
            self.lm.converged[keep], self.lm.n_iter[keep])
        return _CornerChunk(self.data[keep], self.weights[keep], self.origin[keep],
                            self.window, where[keep], self.p[keep], lm, self.n_iter[keep])

    def store(self, out: RefineResult, blur: Blur | None) -> None:
        """Write the fit into ``out`` with the acceptance tests of :func:`refine_corners`."""
        n_par = self.p.shape[1]
        cov, rms = _covariance(self.lm, self.weights, n_par)
        p = _normalise_xj(self.p)
        n = len(p)
        if blur is None:
            entries = np.exp(2.0 * p[:, 6])[:, None] * np.array([1.0, 0.0, 1.0])
        elif isinstance(blur, SharpenedPSF):
            entries = np.tile(_cov_entries(blur.sigma), (n, 1))
        elif np.ndim(blur) == 0:
            entries = np.tile(_cov_entries(float(blur)), (n, 1))
        else:
            entries = np.tile(np.asarray(blur, float), (n, 1))
        d_ang = np.abs(np.sin(p[:, 2] - p[:, 3]))
        ok = (
            self.lm.converged
            & np.all(np.abs(p[:, :2]) < self.window - 1, axis=1)
            & (np.abs(p[:, 4]) > 5.0 * rms)
            & (d_ang > np.sin(np.deg2rad(10.0)))
            & np.all(np.isfinite(cov.reshape(len(p), -1)), axis=1)
        )
        sl = self.where
        out.points[sl] = p[:, :2] + self.origin
        out.cov[sl] = cov
        out.converged[sl] = ok
        out.rms[sl] = rms
        out.angles[sl] = p[:, 2:4]
        out.contrast[sl] = p[:, 4]
        out.offset[sl] = p[:, 5]
        out.sigma[sl] = np.sqrt(0.5 * (entries[:, 0] + entries[:, 2]))
        out.psf_cov[sl] = entries[:, [0, 1, 1, 2]].reshape(n, 2, 2)
        out.n_iter[sl] = self.n_iter


# ----------------------------------------------------------------------------------------------
# Dot refinement
# ----------------------------------------------------------------------------------------------
@dataclass
class DotResult:
    """Result of :func:`refine_dots`.

    Attributes
    ----------
    centres : (K, 2) ndarray
        Fitted ellipse centres, px, OpenCV convention. Under perspective the centre of the imaged
        ellipse is *not* the image of the circle's centre (the bias grows with the dot size and
        the tilt); a later stage corrects that.
    cov : (K, 2, 2) ndarray
        1-sigma covariance of ``centres`` from the fit, px^2.
    converged : (K,) bool
    rms : (K,) ndarray
        Residual RMS, intensity units.
    axes : (K, 2) ndarray
        Semi-axes (major, minor), px (of the half-intensity contour of the model; see the module
        docstring for the ~sigma^2 / 2R blur shift).
    angle : (K,) ndarray
        Direction of the major axis in [0, pi), rad from +x towards +y.
    contrast, offset : (K,) ndarray
        ``a`` (background minus dot) and ``b`` (dot level).
    sigma : (K,) ndarray
        PSF sd, px.
    n_iter : (K,) ndarray
    """

    centres: np.ndarray
    cov: np.ndarray
    converged: np.ndarray
    rms: np.ndarray
    axes: np.ndarray
    angle: np.ndarray
    contrast: np.ndarray
    offset: np.ndarray
    sigma: np.ndarray
    n_iter: np.ndarray


def refine_dots(
    image: np.ndarray,
    centres: np.ndarray,
    radius_guess: float | np.ndarray,
    *,
    window: int | None = None,
    sigma: float | None = None,
    n_sub: int | None = None,
    max_iter: int = 40,
    tol: float = 1e-5,
    chunk: int = 64,
) -> DotResult:
    """Model-based subpixel refinement of dark dots, imaged as ellipses.

    Fits, pixel-integrated (module docstring),

        I(x) = b + a Phi(d(x) / sigma + sigma kappa(x) / 2),

    with ``d`` the signed distance to the ellipse ``(x - c)^T Q (x - c) = 1`` and ``kappa`` its
    curvature, over ``(c_x, c_y, Q_11, Q_12, Q_22, a, b[, log sigma])`` by batched
    Levenberg-Marquardt with analytic Jacobians. ``Q`` (not axes and angle) is the shape
    parameter, so circles are not a singular point. Steps that make ``Q`` indefinite are
    rejected.

    The result is the centre of the *imaged ellipse*. Under perspective projection that is not
    the projection of the circle's centre; the offset is a known function of the pose and the
    dot radius and is corrected by a later stage (not here).

    Parameters
    ----------
    image : (H, W) ndarray
        Grey-level image, uint8 / uint16 / float (processed as float64).
    centres : (K, 2) ndarray
        Initial centres, px (within ~1 px, or ~radius/3 for large dots).
    radius_guess : float or (K,) ndarray
        Approximate dot radius, px.
    window : int, optional
        Half-size of the square fitting window, px; default ``ceil(1.5 R + 3 sigma + 2)`` with
        ``R`` the largest ``radius_guess`` and ``sigma`` 1 px when fitted. Neighbouring dots
        must lie outside it.
    sigma : float, optional
        Fixed PSF sd, px; fitted per dot when None.
    n_sub : int, optional
        Gauss-Legendre nodes per pixel axis; by default :func:`auto_n_sub` of the (fixed, or
        else fitted) blur: the fit is redone with more nodes if the fitted blur asks for them.
    max_iter, tol, chunk
        As in :func:`refine_corners`.

    Returns
    -------
    DotResult

    Raises
    ------
    ValueError
        If ``image`` is not 2-D, ``centres`` has non-finite values or a radius is not positive.

    References
    ----------
    Heikkila (1998); Mallon & Whelan (2007) -- see the module docstring.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:40, 0:40]
    >>> img = dot_image(np.column_stack([xx.ravel(), yy.ravel()]), [20.3, 19.6], [7.0, 5.0],
    ...                 0.4, 0.8).reshape(40, 40)
    >>> res = refine_dots(img, [[20.0, 20.0]], 6.0)
    >>> np.round(res.centres, 4).tolist(), np.round(res.axes, 3).tolist()
    ([[20.3, 19.6]], [[7.0, 5.0]])
    """
    img = _as_image(image)
    pts = _as_points(centres, "centres")
    K = pts.shape[0]
    rad = np.broadcast_to(np.asarray(radius_guess, dtype=float), (K,)).copy()
    if K and not np.all(rad > 0):
        raise ValueError("radius_guess must be positive")
    s0 = 1.0 if sigma is None else float(sigma)
    if window is None:
        window = int(np.ceil(1.5 * (rad.max() if K else 1.0) + 3.0 * s0 + 2.0))
    out = DotResult(
        centres=pts.copy(), cov=np.full((K, 2, 2), np.nan), converged=np.zeros(K, bool),
        rms=np.full(K, np.nan), axes=np.full((K, 2), np.nan), angle=np.full(K, np.nan),
        contrast=np.full(K, np.nan), offset=np.full(K, np.nan), sigma=np.full(K, np.nan),
        n_iter=np.zeros(K, int),
    )
    for start in range(0, K, chunk):
        sl = slice(start, min(start + chunk, K))
        _refine_dot_chunk(img, pts[sl], rad[sl], window, sigma, n_sub, max_iter, tol, out, sl)
    return out


def _refine_dot_chunk(img, pts, rad, window, sigma, n_sub, max_iter, tol, out, sl):
    data, wts, origin = _extract(img, pts, window)
    xy = _window_grid(window)
    n = data.shape[0]
    fit_sigma = sigma is None
    s_fixed = np.full(n, 1.0 if fit_sigma else float(sigma))
    nodes = [n_sub or auto_n_sub(float(s_fixed[0]) if not fit_sigma else 1.0)]
    q0 = _dot_params(np.column_stack([rad, rad]), np.zeros(n), rad)
    p0 = np.column_stack([pts - origin, q0, np.ones(n), np.zeros(n)])
    pix, _ = _dot_eval(p0, s_fixed, rad, xy, nodes[0], jacobian=False)
    p0[:, 5], p0[:, 6] = _linear_ab(pix, data, wts)
    if fit_sigma:
        p0 = np.column_stack([p0, np.log(s_fixed)])
    n_par = p0.shape[1]

    def fun(p, idx):
        s = np.exp(p[:, 7]) if fit_sigma else s_fixed[idx]
        f, jac = _dot_eval(p[:, :7], s, rad[idx], xy, nodes[-1])
        return f, jac[..., :n_par]

    def valid(p):
        ok = (p[:, 2] > 0) & (p[:, 4] > 0) & (p[:, 2] * p[:, 4] > p[:, 3] ** 2)
        ok &= np.all(np.abs(p[:, :2]) < window, axis=1)
        if fit_sigma:
            ok &= (p[:, 7] > np.log(0.05)) & (p[:, 7] < np.log(window))
        return ok

    lm = _batched_lm(fun, p0, data, wts, max_iter=max_iter, tol=tol, valid=valid)
    if n_sub is None and fit_sigma:
        need = auto_n_sub(float(np.exp(lm.p[:, 7]).min(initial=np.inf)))
        if need > nodes[-1]:  # a sharper image than assumed: redo with a finer pixel rule
            nodes.append(need)
            n_iter = lm.n_iter
            lm = _batched_lm(fun, lm.p, data, wts, max_iter=max_iter, tol=tol, valid=valid)
            lm.n_iter = lm.n_iter + n_iter
    cov, rms = _covariance(lm, wts, n_par)
    axes, angle = _dot_shape(lm.p[:, 2:5], rad)
    p = lm.p
    ok = (
        lm.converged
        & np.all(np.isfinite(axes), axis=1)
        & (axes[:, 0] + 1.0 < window)
        & (np.abs(p[:, 5]) > 5.0 * rms)
        & np.all(np.isfinite(cov.reshape(n, -1)), axis=1)
    )
    out.centres[sl] = p[:, :2] + origin
    out.cov[sl] = cov
    out.converged[sl] = ok
    out.rms[sl] = rms
    out.axes[sl] = axes
    out.angle[sl] = angle
    out.contrast[sl] = p[:, 5]
    out.offset[sl] = p[:, 6]
    out.sigma[sl] = np.exp(p[:, 7]) if fit_sigma else s_fixed
    out.n_iter[sl] = lm.n_iter
