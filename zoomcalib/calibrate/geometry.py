"""Geometry of the calibration problems: Rodrigues rotations and their derivatives, the
projection of target points with its analytic Jacobian (OpenCV's camera model, rational
distortion included), the similarity and warp motions of a target, and the least-squares
similarity between two point sets. Shared by the bundle (:mod:`zoomcalib.calibrate.bundle`)
and the zoom-wide adjustment (:mod:`zoomcalib.calibrate.zoomwide`).

Conventions: ``Rt_cam_board`` poses (``X_cam = R(r) X + t``, ``r`` a Rodrigues vector, rad),
pixels in OpenCV's convention (the centre of the top-left pixel at (0, 0)), camera parameters
``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`` in that order (px; distortion as OpenCV's).

References
----------
.. [3] G. Gallego, A. Yezzi, "A compact formula for the derivative of a 3-D rotation in
   exponential coordinates", J. Math. Imaging Vis. 51, 2015.
.. [5] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import numpy as np
from skimage.transform import SimilarityTransform

__all__ = ["rodrigues", "left_jacobian", "project_jacobian", "similarity_basis", "warp_basis",
           "fit_similarity"]



def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices ``[v]_x`` (``[v]_x a = v x a``)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rodrigues(rvecs: np.ndarray, derivative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    r"""Rotation matrices of Rodrigues vectors and their derivatives.

    .. math::

        R = I + \frac{\sin\theta}{\theta}[r]_\times + \frac{1 - \cos\theta}{\theta^2}[r]_\times^2,
        \quad \theta = \|r\|,

        \frac{\partial R}{\partial r_k} = \frac{r_k [r]_\times + [r \times (I - R) e_k]_\times}
        {\theta^2} R \quad [3],

    and ``dR/dr_k = [e_k]_x + ([e_k]_x [r]_x + [r]_x [e_k]_x) / 2`` for ``theta < 1e-7``
    (error O(theta^2)).

    Parameters
    ----------
    rvecs : (m, 3) ndarray
        Rodrigues vectors, rad.
    derivative : bool
        Also compute ``dR`` (else it is None).

    Returns
    -------
    R : (m, 3, 3) ndarray
    dR : (m, 3, 3, 3) ndarray or None
        ``dR[v, k]`` = derivative of ``R[v]`` with respect to ``rvecs[v, k]``.
    """
    r = np.asarray(rvecs, dtype=float).reshape(-1, 3)
    theta2 = np.einsum("vi,vi->v", r, r)
    theta = np.sqrt(theta2)
    small = theta < 1e-7
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta2 / 24.0, 2.0 * (np.sin(0.5 * th) / th) ** 2)  # (1-cos)/th^2
    Kx = _skew(r)
    eye = np.eye(3)
    IR = -(a[:, None, None] * Kx + b[:, None, None] * (Kx @ Kx))      # I - R, no cancellation
    R = eye - IR
    if not derivative:
        return R, None
    # c[v, k] = r x ((I - R) e_k); (I - R) e_k is column k of I - R
    c = np.cross(r[:, None, :], IR.transpose(0, 2, 1))
    num = r[:, :, None, None] * Kx[:, None] + _skew(c)
    dR = (num @ R[:, None]) / np.where(small, 1.0, theta2)[:, None, None, None]
    if np.any(small):
        E = _skew(eye)[None]                                  # (1, 3, 3, 3): [e_k]_x
        Ks = Kx[small][:, None]
        dR[small] = E + 0.5 * (E @ Ks + Ks @ E)
    return R, dR


def left_jacobian(rvecs: np.ndarray) -> np.ndarray:
    r"""Left Jacobian of SO(3) at Rodrigues vectors ``r``.

    .. math::

        J_l(r) = I + \frac{1 - \cos\theta}{\theta^2}[r]_\times
                 + \frac{\theta - \sin\theta}{\theta^3}[r]_\times^2,

    so that ``Rod(r + dr) = Exp([J_l(r) dr]_x) Rod(r)`` to first order, i.e.
    ``dR/dr_k = [J_l(r) e_k]_x R`` — the same derivative as :func:`rodrigues`, factored into a
    rotation about the camera axes followed by ``J_l``.

    Parameters
    ----------
    rvecs : (m, 3) ndarray

    Returns
    -------
    Jl : (m, 3, 3) ndarray
    """
    r = np.asarray(rvecs, dtype=float).reshape(-1, 3)
    t2 = np.einsum("vi,vi->v", r, r)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    b = np.where(small, 0.5 - t2 / 24.0, 2.0 * (np.sin(0.5 * ts) / ts) ** 2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    Kx = _skew(r)
    return np.eye(3) + b[:, None, None] * Kx + c[:, None, None] * (Kx @ Kx)


def project_jacobian(cam: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray, points: np.ndarray,
                     view_idx: np.ndarray, point_idx: np.ndarray, jacobian: bool = True,
                     point_jacobian: bool = True, local_rotation: bool = False):
    r"""Project target points into views, with the analytic Jacobian.

    Parameters
    ----------
    cam : (12,) ndarray
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`` (px; distortion in OpenCV order).
    rvecs, tvecs : (m, 3) ndarray
        ``Rt_cam_board`` poses (Rodrigues vector, rad; translation, target units).
    points : (n, 3) ndarray
        Target points, target frame.
    view_idx, point_idx : (N,) int ndarray
        Which view and which point each observation is.
    jacobian : bool
        Also return the derivatives.
    point_jacobian : bool
        Compute ``Jx`` (else it is None).
    local_rotation : bool
        Rotation columns of ``Jp`` with respect to a small rotation ``omega`` of the camera
        frame, ``R -> Exp([omega]_x) R``, instead of the Rodrigues vector; multiply them by
        :func:`left_jacobian` of the view to get the latter.

    Returns
    -------
    uv : (N, 2) ndarray
        Projections, px (OpenCV convention); returned alone if ``jacobian`` is False.
    Jc : (N, 2, 12) ndarray
        ``d uv / d cam``.
    Jp : (N, 2, 6) ndarray
        ``d uv / d (rvec, tvec)`` of the observation's view.
    Jx : (N, 2, 3) ndarray or None
        ``d uv / d X_j`` of the observation's point.

    Notes
    -----
    With ``rad = a/b`` (numerator and denominator of the rational radial factor) and
    ``rad' = (a' - rad b') / b`` its derivative with respect to ``r^2``:

    .. math::

        \partial x_d/\partial x = rad + 2 x^2 rad' + 2 p_1 y + 6 p_2 x,\quad
        \partial x_d/\partial y = 2 x y\, rad' + 2 p_1 x + 2 p_2 y = \partial y_d/\partial x,

        \partial y_d/\partial y = rad + 2 y^2 rad' + 6 p_1 y + 2 p_2 x,

    ``B = d(u, v)/d(X, Y, Z) = diag(f_x, f_y) D [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]``
    (``D = d(x_d, y_d)/d(x, y)``), ``d uv/dX_j = B R``, ``d uv/dt = B``,
    ``d uv/d omega = -B [R X_j]_x`` and ``d uv/dr = -B [R X_j]_x J_l(r)``.
    """
    m, n = len(rvecs), len(points)
    R, _ = rodrigues(rvecs, False)
    if m * n <= 3 * len(view_idx):                       # (nearly) every point in every view
        RP = (points[None] @ R.transpose(0, 2, 1))[view_idx, point_idx]
    else:
        RP = np.einsum("nij,nj->ni", R[view_idx], points[point_idx])
    Xc = RP + tvecs[view_idx]
    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = (float(c) for c in cam)
    iz = 1.0 / Xc[:, 2]
    x = Xc[:, 0] * iz
    y = Xc[:, 1] * iz
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    r4 = r2 * r2
    r6 = r4 * r2
    a = 1.0 + k1 * r2 + k2 * r4 + k3 * r6
    ib = 1.0 / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    rad = a * ib
    xd = x * rad + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xx)
    yd = y * rad + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy
    uv = np.stack([fx * xd + cx, fy * yd + cy], -1)
    if not jacobian:
        return uv
    n_obs = len(x)
    Jc = _camera_columns(fx, fy, x, y, (xd, yd), (r2, r4, r6), rad, ib)
    da = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r4
    db = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r4
    drad = (da - rad * db) * ib
    dxx = rad + 2.0 * xx * drad + 2.0 * p1 * y + 6.0 * p2 * x
    dxy = 2.0 * xy * drad + 2.0 * p1 * x + 2.0 * p2 * y
    dyy = rad + 2.0 * yy * drad + 6.0 * p1 * y + 2.0 * p2 * x
    B = np.empty((n_obs, 2, 3))  # d uv / d (X, Y, Z) camera frame
    B[:, 0, 0] = fx * dxx * iz
    B[:, 0, 1] = fx * dxy * iz
    B[:, 0, 2] = -(B[:, 0, 0] * x + B[:, 0, 1] * y)
    B[:, 1, 0] = fy * dxy * iz
    B[:, 1, 1] = fy * dyy * iz
    B[:, 1, 2] = -(B[:, 1, 0] * x + B[:, 1, 1] * y)
    Jp = np.empty((n_obs, 2, 6))
    Jp[:, :, 3:] = B
    # -B [a]_x has rows -(B_i x a)
    Jp[:, :, :3] = -np.cross(B, RP[:, None, :])
    if not local_rotation:
        Jp[:, :, :3] = Jp[:, :, :3] @ left_jacobian(rvecs)[view_idx]
    Jx = B @ R[view_idx] if point_jacobian else None
    return uv, Jc, Jp, Jx


def _camera_columns(fx: float, fy: float, x: np.ndarray, y: np.ndarray, distorted: tuple,
                    powers: tuple, rad: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """``d uv / d cam`` (N, 2, 12) of :func:`project_jacobian` from the normalised point
    ``(x, y)``, its distorted ``(x_d, y_d)``, ``(r^2, r^4, r^6)``, the radial factor and
    ``1 / b``."""
    xd, yd = distorted
    r2, r4, r6 = powers
    xx, yy, xy = x * x, y * y, x * y
    Jc = np.zeros((len(x), 2, 12))
    Jc[:, 0, 0] = xd
    Jc[:, 1, 1] = yd
    Jc[:, 0, 2] = 1.0
    Jc[:, 1, 3] = 1.0
    # du/dk1..3 = fx x r^(2i) / b, du/dk4..6 = -fx x rad r^(2i) / b (v likewise)
    fxx, fyy = fx * x * ib, fy * y * ib
    fxr, fyr = -fx * x * rad * ib, -fy * y * rad * ib
    for col, pw in ((4, r2), (5, r4), (8, r6)):
        Jc[:, 0, col] = fxx * pw
        Jc[:, 1, col] = fyy * pw
    for col, pw in ((9, r2), (10, r4), (11, r6)):
        Jc[:, 0, col] = fxr * pw
        Jc[:, 1, col] = fyr * pw
    Jc[:, 0, 6] = fx * 2.0 * xy
    Jc[:, 1, 6] = fy * (r2 + 2.0 * yy)
    Jc[:, 0, 7] = fx * (r2 + 2.0 * xx)
    Jc[:, 1, 7] = fy * 2.0 * xy
    return Jc


def similarity_basis(points: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the 7 infinitesimal similarity motions of a point set.

    Translations ``e_k``, rotations ``omega_k x (X_j - Xbar)`` and the scaling ``X_j - Xbar``,
    stacked over the points and orthonormalised.

    Parameters
    ----------
    points : (n, 3) ndarray

    Returns
    -------
    Q : (3 n, 7) ndarray
        Orthonormal columns; ``I - Q Q^T`` projects out the similarity.
    """
    c = points - points.mean(axis=0)
    n = len(points)
    modes = np.zeros((7, n, 3))
    for k in range(3):
        modes[k, :, k] = 1.0
        e = np.zeros(3)
        e[k] = 1.0
        modes[3 + k] = np.cross(e, c)
    modes[6] = c
    Q, _ = np.linalg.qr(modes.reshape(7, -1).T)
    return Q


def warp_basis(points: np.ndarray) -> np.ndarray:
    """The 3 smooth out-of-plane warp modes of a (nearly) planar target.

    Displacements along the normal of the best-fit plane by ``u^2``, ``u v`` and ``v^2``, where
    ``(u, v)`` are in-plane coordinates from the centroid divided by the largest distance from
    it (so a mode's largest displacement is about 1). The span is independent of the choice
    of in-plane axes; it holds a bow (``z = b (1 - r^2/R^2)`` up to a similarity), cylindrical
    bows along either axis and a twist.

    Parameters
    ----------
    points : (n, 3) ndarray

    Returns
    -------
    B : (3 n, 3) ndarray
        Unnormalised modes, stacked as ``x`` (point-major).
    """
    c = points - points.mean(axis=0)
    _, _, Vt = np.linalg.svd(c, full_matrices=False)
    scale = np.sqrt((c * c).sum(axis=1).max())
    u, v = (c @ Vt[0]) / scale, (c @ Vt[1]) / scale
    return np.stack([np.outer(f, Vt[2]).ravel() for f in (u * u, u * v, v * v)], axis=1)


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    r"""Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991; scikit-image's
    :class:`~skimage.transform.SimilarityTransform`).

    Parameters
    ----------
    src, dst : (n, 3) ndarray

    Returns
    -------
    s : float
    R : (3, 3) ndarray
    t : (3,) ndarray

    Raises
    ------
    ValueError
        When the points do not determine a similarity (scikit-image's reason).
    """
    fit = SimilarityTransform.from_estimate(np.asarray(src, float), np.asarray(dst, float))
    if not fit:
        raise ValueError(f"no similarity between the point sets: {fit}")
    s = float(fit.scale)
    return s, fit.params[:3, :3] / s, fit.params[:3, 3].copy()
