r"""The bundle adjustment's least-squares problem: its state, data, residuals and Jacobians, the
normal equations with the poses' blocks kept apart, and the target shape's prior.

The model, its gauge and why the target points are unknowns:
:mod:`zoomcalib.calibrate.bundle`, which solves this problem in stages. The per-step OpenCV
backend (:mod:`zoomcalib.calibrate.opencv_backend`) builds the same problem at OpenCV's
solution to check that it is stationary and to compute its covariance.

Unknowns, in :class:`_Problem`'s order: the free camera parameters (columns of ``cam_map`` over
:data:`CAMERA_NAMES`) and the free target coordinates, then six per view (Rodrigues vector,
translation). The normal equations come as blocks ``U`` (camera and target), ``W`` (their
coupling to each pose) and ``V`` (each pose's 6 x 6), the form the shared engine
(:mod:`zoomcalib.calibrate.solver`) eliminates the poses from.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse

from zoomcalib.calibrate.geometry import (
    fit_similarity,
    left_jacobian,
    project_jacobian,
    similarity_basis,
    warp_basis,
)
from zoomcalib.calibrate.result import DIST_NAMES
from zoomcalib.calibrate.scatter import deletion_steps, noise_share
from zoomcalib.calibrate.solver import NormalBlocks

__all__ = ["CAMERA_NAMES", "shape_precision", "scaled_inverse", "as_blocks"]


#: Names of the 12 camera parameters in the internal (full rational) order.
CAMERA_NAMES = ("fx", "fy", "cx", "cy") + DIST_NAMES


def shape_precision(points: np.ndarray, target_sigma_mm: float,
                    warp_sigma_mm: float | None) -> np.ndarray:
    r"""Precision matrix of the target-shape prior.

    .. math::

        \Lambda = \frac{I - Q Q^T - B B^T}{\sigma_t^2} + \frac{B (T T^T)^{-1} B^T}{\sigma_w^2},

    ``Q`` the orthonormal similarity basis (:func:`similarity_basis`), ``B_0 = B T`` (QR) the
    smooth warp modes (:func:`warp_basis`) less their projection on ``Q``, so that the last
    term is ``|alpha|^2 / sigma_w^2`` for a deformation ``B_0 alpha`` (amplitudes ``alpha``,
    the displacement at the point farthest from the centroid). The prior ``d^T Lambda d`` on a
    deviation ``d`` from the nominal board leaves the similarity free (gauge), lets each warp
    amplitude move with 1-sigma ``warp_sigma_mm`` and holds every other deformation to
    ``target_sigma_mm`` per coordinate. ``warp_sigma_mm=None``: the warp modes get
    ``target_sigma_mm`` too.

    Parameters
    ----------
    points : (n, 3) ndarray
        Nominal target.
    target_sigma_mm, warp_sigma_mm : float
        In the units of ``points``.

    Returns
    -------
    Lam : (3 n, 3 n) ndarray
        In 1 / unit^2.
    """
    return _precision(_shape_modes(points), target_sigma_mm, warp_sigma_mm)


def _precision(modes, target_sigma_mm: float, warp_sigma_mm: float | None) -> np.ndarray:
    """:func:`shape_precision` from ``_shape_modes`` output."""
    Q, B, Ti = modes
    P = np.eye(Q.shape[0]) - Q @ Q.T
    if warp_sigma_mm is None:
        return P / target_sigma_mm**2
    return (P - B @ B.T) / target_sigma_mm**2 + B @ (Ti @ Ti.T) @ B.T / warp_sigma_mm**2


@dataclass
class _ShapePrior:
    """The shape prior's precision in factored form, ``Lambda = a I + U D U^T`` (3n, 3n).

    Rotating it by ``I (x) R`` only rotates the few columns of ``U``, which makes the rotated
    block of the free coordinates cheap (``shape_precision`` has ``k = 10`` columns).
    """

    a: float
    U: np.ndarray  # shape (3n, k)
    D: np.ndarray  # shape (k, k)

    @classmethod
    def dense(cls, Lam: np.ndarray) -> _ShapePrior:
        return cls(0.0, np.eye(len(Lam)), np.asarray(Lam, dtype=float))

    @classmethod
    def from_modes(cls, modes, target_sigma_mm: float,
                   warp_sigma_mm: float | None) -> _ShapePrior:
        """The factored form of :func:`_precision`."""
        Q, B, Ti = modes
        a = 1.0 / target_sigma_mm**2
        if warp_sigma_mm is None:
            return cls(a, Q, -a * np.eye(Q.shape[1]))
        k = Q.shape[1]
        D = np.zeros((k + 3, k + 3))
        D[:k, :k] = -a * np.eye(k)
        D[k:, k:] = -a * np.eye(3) + (Ti @ Ti.T) / warp_sigma_mm**2
        return cls(a, np.hstack([Q, B]), D)

    def matvec(self, d: np.ndarray) -> np.ndarray:
        return self.a * d + self.U @ (self.D @ (self.U.T @ d))

    def rotated_columns(self, R: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``[(I (x) R) U][idx]``: the rotated precision is ``a I + U_r D U_r^T``."""
        n3, k = self.U.shape
        return (R @ self.U.reshape(n3 // 3, 3, k)).reshape(n3, k)[idx]

    def rotated(self, R: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """``[(I (x) R) Lambda (I (x) R)^T][idx, idx]``."""
        Ur = self.rotated_columns(R, idx)
        out = Ur @ self.D @ Ur.T
        out.ravel()[:: len(idx) + 1] += self.a
        return out


@dataclass
class _PointCovariance:
    """Covariance of the free point coordinates, ``C = s2 (S - c S (a I + G' D G'^T) S)``
    kept as ``S`` (nx, nx), ``G = S U_r`` (nx, k) and the scalars, so that its diagonal and its
    products with a few vectors cost O(nx^2) instead of forming ``C`` (O(nx^3)).

    ``S`` is the points' block of the inverse reduced normal matrix, ``c (a I + U_r D U_r^T)``
    the shape prior's precision on them (``c = 0``: no prior)."""

    S: np.ndarray
    s2: float
    ca: float = 0.0
    G: np.ndarray | None = None
    cD: np.ndarray | None = None

    def diag(self) -> np.ndarray:
        d = np.einsum("ii->i", self.S) - self.ca * np.einsum("ij,ij->i", self.S, self.S)
        if self.G is not None:
            d = d - np.einsum("ij,ij->i", self.G @ self.cD, self.G)
        return self.s2 * d

    def __matmul__(self, V: np.ndarray) -> np.ndarray:
        SV = self.S @ V
        out = SV - self.ca * (self.S @ SV)
        if self.G is not None:
            out = out - self.G @ (self.cD @ (self.G.T @ V))
        return self.s2 * out


def _rotate_precision(Lam: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``(I (x) R) Lam (I (x) R)^T``: a (3n, 3n) precision of point-major coordinates, rotated."""
    n = Lam.shape[0] // 3
    left = (R @ Lam.reshape(n, 3, 3 * n)).reshape(3 * n, 3 * n)       # rows rotated
    return (left.reshape(3 * n, n, 3) @ R.T).reshape(3 * n, 3 * n)     # columns rotated


def _shape_modes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Q`` (3n, 7) similarity basis, ``B`` (3n, 3) orthonormal warp basis orthogonal to ``Q``
    and ``T^-1`` (3, 3), so that warp amplitudes are ``alpha = T^-1 B^T d``."""
    Q = similarity_basis(points)
    B0 = warp_basis(points)
    B0 = B0 - Q @ (Q.T @ B0)               # the warp modes less their similarity part
    B, T = np.linalg.qr(B0)                # B0 = B T
    return Q, B, np.linalg.inv(T)


@dataclass
class _State:
    cam: np.ndarray      # (12,)
    rvecs: np.ndarray    # (m, 3)
    tvecs: np.ndarray    # (m, 3)
    X: np.ndarray        # (n, 3)

    def copy(self) -> _State:
        return _State(self.cam.copy(), self.rvecs.copy(), self.tvecs.copy(), self.X.copy())


@dataclass
class _Data:
    """The flattened observations: view and point index, uv (px) and weight of each, the
    numbers of views and points, and the nominal target (n, 3)."""

    vi: np.ndarray
    pi: np.ndarray
    uv: np.ndarray
    w: np.ndarray
    m: int
    n: int
    X0: np.ndarray


class _Problem:
    """Observations (sorted by view), parameter maps and the normal equations.

    Unknowns are split into ``y`` (free camera parameters, then free target coordinates) and
    ``p`` (6 pose parameters per view); the normal equations are returned as the blocks
    ``U = J_y^T J_y (+ prior)``, ``W_v = J_y^T J_{p_v}``, ``V_v = J_{p_v}^T J_{p_v}`` and the
    gradients ``g_y = J_y^T r``, ``g_p = J_p^T r``.
    """

    def __init__(self, data: _Data, cam_map: np.ndarray, free_pts: np.ndarray,
                 Lam: _ShapePrior | None, sig2: float):
        vi, pi, uv, w, m, n, X0 = (data.vi, data.pi, data.uv, data.w, data.m, data.n, data.X0)
        order = np.argsort(vi, kind="stable")
        self.vi, self.pi = vi[order], pi[order]
        self.uv, self.w = uv[order], w[order]
        self.order = order
        self.m, self.n = m, n
        self.N = len(self.vi)
        self.starts = np.searchsorted(self.vi, np.arange(m))
        self.cam_map = cam_map               # (12, nc)
        self.nc = nc = cam_map.shape[1]
        self.free_pts = free_pts             # (n, 3) bool
        self.free_idx = np.flatnonzero(free_pts.ravel())
        self.nx = nx = len(self.free_idx)
        self.X0 = X0
        # shape prior: precision Lam (3n, 3n, 1/mm^2) of the deviation from the nominal board
        # aligned on the current points; cost weight sig2 = sigma_px^2
        if isinstance(Lam, np.ndarray):
            Lam = _ShapePrior.dense(Lam)
        self.Lam = Lam if (Lam is not None and nx) else None
        self.sig2 = sig2
        # dense (view, point) grid when at least a third of it is observed
        self.dense = m * n <= 3 * self.N
        self.cell = self.vi * n + self.pi
        self.one_per_cell = len(np.unique(self.cell)) == self.N
        self._A_pt = None                        # (n, N) point-observation incidence, lazily
        self.last_normal: tuple | None = None    # normal_equations at the last linearisation
        if nx:
            pos = np.full(3 * n, -1)
            pos[self.free_idx] = np.arange(nx)
            pos = pos.reshape(n, 3)
            # block-diagonal J_x^T J_x entries (point j, a, b) that land in U (both free)
            j, a, b = np.nonzero(free_pts[:, :, None] & free_pts[:, None, :])
            self.ux_src = (j * 9 + a * 3 + b)
            self.ux_dst = (nc + pos[j, a]) * (nc + nx) + nc + pos[j, b]
            # W rows of the observations' free point coordinates
            o, a = np.nonzero(free_pts[self.pi])
            self.wx_obs, self.wx_a, self.wx_row = o, a, nc + pos[self.pi[o], a]

    def shape_deviation(self, X: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """Deviation ``(n, 3)`` of ``X`` from the nominal board aligned on it, expressed in the
        nominal frame: ``d = R^T (X - s R X_0 - t) / s`` with ``(s, R, t)`` the least-squares
        similarity from ``X_0`` to ``X``; also ``s`` and ``R``."""
        sc, Rs, t = fit_similarity(self.X0, X)
        return ((X - t) @ Rs) / sc - self.X0, sc, Rs

    @property
    def n_unknowns(self) -> int:
        return self.nc + 6 * self.m + self.nx

    def residuals(self, s: _State) -> np.ndarray:
        """(N, 2) weighted residuals ``w_i (uv_hat - uv)``, px (observation order sorted)."""
        uv = project_jacobian(s.cam, s.rvecs, s.tvecs, s.X, self.vi, self.pi, jacobian=False)
        return (uv - self.uv) * self.w[:, None]

    def cost(self, s: _State) -> float:
        """Sum of squared weighted residuals, px^2, and the shape prior's term."""
        return self._cost_of(s, self.residuals(s))

    def _cost_of(self, s: _State, r: np.ndarray) -> float:
        F = float(np.einsum("ij,ij->", r, r))
        if self.Lam is not None:
            d = self.shape_deviation(s.X)[0].ravel()
            F += self.sig2 * float(d @ self.Lam.matvec(d))
        return F

    def linearise(self, s: _State) -> tuple[float, NormalBlocks]:
        """The cost and the normal blocks at ``s`` in the engine's layout
        (:mod:`zoomcalib.calibrate.solver`); :meth:`normal_equations`' own tuple is kept in
        ``last_normal`` (the covariance is computed from it)."""
        self.last_normal = self.normal_equations(s)
        U, W, V, g, gp, r = self.last_normal
        return self._cost_of(s, r), as_blocks(U, W, V, g, gp)

    def jacobians(self, s: _State):
        """Per observation, weighted: residuals ``r`` (N, 2), px, and the Jacobians of ``r``
        over the free camera parameters ``J_c`` (N, 2, nc), the pose ``J_p`` (N, 2, 6; rotation
        columns w.r.t. a small rotation of the camera frame, to be multiplied by the view's
        :func:`left_jacobian` for the Rodrigues vector) and the point ``J_x`` (N, 2, 3; None
        when no target coordinate is free)."""
        uv, Jc, Jp, Jx = project_jacobian(s.cam, s.rvecs, s.tvecs, s.X, self.vi, self.pi,
                                          point_jacobian=self.nx > 0, local_rotation=True)
        w = self.w[:, None, None]
        r = (uv - self.uv) * self.w[:, None]
        Jc = (Jc * w) @ self.cam_map
        Jp *= w
        if self.nx:
            Jx *= w
        return r, Jc, Jp, Jx

    def prior_gradient(self, s: _State) -> tuple[np.ndarray, float, np.ndarray]:
        """The shape prior's gradient over every target coordinate ``(3n,)``, in the units of
        ``g_x = J_x^T r`` (``sig2 / s R Lam d`` per point, :meth:`shape_deviation`), with
        ``s`` and ``R``."""
        d, sc, Rs = self.shape_deviation(s.X)
        g = (self.sig2 / sc) * (self.Lam.matvec(d.ravel()).reshape(self.n, 3) @ Rs.T)
        return g.ravel(), sc, Rs

    def camera_influence(self, s: _State, W: np.ndarray, V: np.ndarray,
                         camera_rows: np.ndarray, hold_points: bool = False) -> np.ndarray:
        """Each corner's share of the camera's move, ``a_i = S^-1[cam, :] Jt_i^T r_i`` (N, 12)
        over ``CAMERA_NAMES`` (observation order; zero columns for fixed parameters), with
        ``Jt_i = J_y,i - J_p,i V_v^-1 W_v^T`` the corner's Jacobian with its view's pose projected
        out (:mod:`zoomcalib.calibrate.scatter`). ``W`` (m, ny, 6), ``V`` (m, 6, 6): blocks of
        :meth:`normal_equations` at ``s``; ``camera_rows``: ``S^-1[:nc, :]`` (nc, ny).
        ``hold_points``: leave out the term through the corner's own point coordinates,
        ``S^-1[cam, x_p] J_x,i^T r_i`` (the board-point check's influence)."""
        r, Jc, Jp, Jx = self.jacobians(s)
        nc = self.nc
        influence = np.einsum("nkc,nk->nc", Jc, r) @ camera_rows[:, :nc].T
        if self.nx and not hold_points:
            o, a, row = self.wx_obs, self.wx_a, self.wx_row
            point_score = np.einsum("nka,nk->na", Jx, r)[o, a]
            np.add.at(influence, o, point_score[:, None] * camera_rows[:, row].T)
        # the pose's share S^-1[cam, :] W_v V_v^-1 T_v^T J_p,i^T r_i, in Rodrigues columns
        pose_score = np.einsum("nka,nk->na", Jp, r)
        T = left_jacobian(s.rvecs)[self.vi]
        pose_score[:, :3] = np.einsum("nba,nb->na", T, pose_score[:, :3])
        through_pose = (camera_rows @ W) @ np.linalg.inv(V)                 # (m, nc, 6)
        influence -= np.einsum("nca,na->nc", through_pose[self.vi], pose_score)
        return influence @ self.cam_map.T

    def pose_free_rows(self, s: _State, W: np.ndarray, V: np.ndarray
                       ) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
        """A function of a view ``v`` giving its rows with the pose projected out,
        ``Jt_v = J_y,v - J_p,v V_v^-1 W_v^T`` (2k, ny) over camera and free target coordinates,
        and its residuals ``r_v`` (2k,), px (k corners; ``W, V`` blocks of
        :meth:`normal_equations` at ``s``)."""
        r, Jc, Jp, Jx = self.jacobians(s)
        T = left_jacobian(s.rvecs)[self.vi]
        Jp[:, :, :3] = Jp[:, :, :3] @ T                                     # Rodrigues columns
        through_pose = np.linalg.solve(V, W.transpose(0, 2, 1))             # (m, 6, ny)
        nc, ny = self.nc, self.nc + self.nx
        ends = np.append(self.starts, self.N)
        free_at = np.searchsorted(self.wx_obs, ends) if self.nx else None

        def rows(v: int) -> tuple[np.ndarray, np.ndarray]:
            lo, hi = ends[v], ends[v + 1]
            Jy = np.zeros((hi - lo, 2, ny))
            Jy[:, :, :nc] = Jc[lo:hi]
            if self.nx:
                f = slice(free_at[v], free_at[v + 1])
                o, a = self.wx_obs[f], self.wx_a[f]
                Jy[o - lo, :, self.wx_row[f]] = Jx[o, :, a]
            return (Jy - Jp[lo:hi] @ through_pose[v]).reshape(-1, ny), r[lo:hi].ravel()
        return rows

    def camera_deletions(self, s: _State, U: np.ndarray, W: np.ndarray, V: np.ndarray,
                         groups: np.ndarray | None = None) -> np.ndarray | None:
        """Per group of views (``groups`` (m,) labels ``0..G-1``; default one view each), the
        camera's move when the group is left out, ``(S - A_g)^-1 g_g`` (G, 12) over
        ``CAMERA_NAMES``, with ``g_g = sum_{i in g} Jt_i^T r_i`` and ``A_g = sum_{i in g}
        Jt_i^T Jt_i`` the group's share of the gradient and of the Schur complement
        ``S = U - sum_v W_v V_v^-1 W_v^T`` over camera and free target coordinates (one
        Gauss-Newton step: the delete-one-view jackknife of :mod:`zoomcalib.calibrate.scatter`;
        ``U, W, V`` blocks of :meth:`normal_equations`; :meth:`pose_free_rows`). None when
        there are more than :data:`DELETION_MAX_UNKNOWNS` of those (``S`` then costs too much
        to solve once per view); NaN rows where a group carries a parameter alone."""
        ny = self.nc + self.nx
        if ny > DELETION_MAX_UNKNOWNS:
            return None
        groups = np.arange(self.m) if groups is None else np.asarray(groups)
        rows = self.pose_free_rows(s, W, V)
        S = U - np.einsum("vci,vid->cd", W, np.linalg.solve(V, W.transpose(0, 2, 1)))
        moves = np.empty((int(groups.max()) + 1, ny))
        for group in range(len(moves)):
            A, g = np.zeros((ny, ny)), np.zeros(ny)
            for v in np.flatnonzero(groups == group):
                Jt, r = rows(v)
                A += Jt.T @ Jt
                g += Jt.T @ r
            moves[group] = deletion_steps(S, A[None], g[None])[0]
        return moves[:, :self.nc] @ self.cam_map.T

    def camera_noise_share(self, s: _State, W: np.ndarray, V: np.ndarray,
                           inverse: np.ndarray, groups: np.ndarray | None = None,
                           prior: Callable[[np.ndarray], np.ndarray] | None = None
                           ) -> np.ndarray:
        """(12,) over ``CAMERA_NAMES``: the view-clustered sum's expectation under the noise
        model over the camera's (repeatability) variance, per group of views
        (:func:`~zoomcalib.calibrate.scatter.noise_share`, with ``B_g = sum_{v in g} Jt_v^T
        (Jt_v C)`` from :meth:`pose_free_rows`). ``inverse``: ``S^-1`` (ny, ny) over camera
        and free target coordinates; ``prior(X)``: ``diag(X^T P X)`` of the shape prior's
        block ``P`` for ``X`` (ny, p). NaN for fixed parameters."""
        groups = np.arange(self.m) if groups is None else np.asarray(groups)
        columns = inverse[:, :self.nc] @ self.cam_map.T                    # (ny, 12)
        blocks = np.zeros((int(groups.max()) + 1, *columns.shape))
        np.add.at(blocks, groups, self.view_products(s, W, V, columns))
        return noise_share(columns, blocks, inverse, prior=prior)

    def view_products(self, s: _State, W: np.ndarray, V: np.ndarray, columns: np.ndarray
                      ) -> np.ndarray:
        """``Jt_v^T (Jt_v C)`` (m, ny, p) per view for ``C = columns`` (ny, p), with ``Jt_v``
        the view's rows with its pose projected out (:meth:`pose_free_rows`), vectorised over
        the corners: with ``P_i = Jt_i C = J_y,i C - J_p,i V_v^-1 W_v^T C``,
        ``Jt_v^T P_v = sum_{i in v} J_y,i^T P_i - W_v V_v^-1 sum_{i in v} J_p,i^T P_i``."""
        _, Jc, Jp, Jx = self.jacobians(s)
        to_rodrigues = left_jacobian(s.rvecs)
        nc, n, p = self.nc, self.n, columns.shape[1]
        pose_columns = np.linalg.solve(V, W.transpose(0, 2, 1) @ columns)  # (m, 6, p)
        P = np.zeros((self.N, 2, p))
        if self.nx:
            point_columns = np.zeros((3 * n, p))                           # 0: fixed coordinates
            point_columns[self.free_idx] = columns[nc:]
            point_columns = point_columns.reshape(n, 3, p)[self.pi]        # (N, 3, p)
            P = sum(Jx[:, :, a, None] * point_columns[:, None, a] for a in range(3))
        ends = np.append(self.starts, self.N)
        products = np.empty((self.m, nc + self.nx, p))
        through_pose = np.empty((self.m, 6, p))
        for v in range(self.m):     # products per view: few, and far faster than batched 2-row ones
            rows = slice(ends[v], ends[v + 1])
            camera, pose = Jc[rows].reshape(-1, nc), Jp[rows].reshape(-1, 6)
            pose[:, :3] = pose[:, :3] @ to_rodrigues[v]
            view_P = P[rows].reshape(-1, p) + camera @ columns[:nc] - pose @ pose_columns[v]
            P[rows] = view_P.reshape(-1, 2, p)
            products[v, :nc] = camera.T @ view_P
            through_pose[v] = pose.T @ view_P
        if self.nx:
            o, a, row = self.wx_obs, self.wx_a, self.wx_row
            point_P = Jx[o, 0, a, None] * P[o, 0] + Jx[o, 1, a, None] * P[o, 1]    # (E, p)
            products[:, nc:] = 0.0
            if self.one_per_cell:
                products[self.vi[o], row] = point_P
            else:                                        # a point seen twice in a view
                np.add.at(products, (self.vi[o], row), point_P)
        return products - W @ np.linalg.solve(V, through_pose)

    def normal_equations(self, s: _State):
        """Blocks ``U (ny, ny), W (m, ny, 6), V (m, 6, 6), g_y (ny,), g_p (m, 6)``, residuals."""
        # the Rodrigues columns are the local rotation's times T_v, applied per view below
        r, Jc, Jp, Jx = self.jacobians(s)
        nc, m, n, nx = self.nc, self.m, self.n, self.nx
        sums = self._sums_dense if self.dense else self._sums_sparse
        Ucc, gc, Wc, V, gp, Uxx, Ucx, gx = sums(Jc, Jp, Jx, r)
        ny = nc + nx
        U = np.zeros((ny, ny))
        U[:nc, :nc] = Ucc
        g = np.empty(ny)
        g[:nc] = gc
        W = np.zeros((m, ny, 6))
        W[:, :nc] = Wc
        if nx:
            gx = gx.ravel()
            if self.Lam is not None:
                prior_gx, sc, Rs = self.prior_gradient(s)
                gx += prior_gx
                U[nc:, nc:] = (self.sig2 / sc**2) * self.Lam.rotated(Rs, self.free_idx)
            U.ravel()[self.ux_dst] += Uxx.ravel()[self.ux_src]
            f = self.free_idx
            U[:nc, nc:] = Ucx.transpose(1, 0, 2).reshape(nc, 3 * n)[:, f]
            U[nc:, :nc] = U[:nc, nc:].T
            o, a = self.wx_obs, self.wx_a
            # W entries J_x^T J_p of each observation's free point coordinates
            W[self.vi[o], self.wx_row] = (Jx[o, 0, a, None] * Jp[o, 0]
                                          + Jx[o, 1, a, None] * Jp[o, 1])
            g[nc:] = gx[f]
        T = np.zeros((m, 6, 6))
        T[:, :3, :3] = left_jacobian(s.rvecs)
        T[:, 3:, 3:] = np.eye(3)
        TT = T.transpose(0, 2, 1)
        return U, W @ T, TT @ V @ T, g, (TT @ gp[:, :, None])[:, :, 0], r

    def _sums_sparse(self, Jc, Jp, Jx, r):
        """Per-view and per-point sums of the Jacobian products, for any pattern of views."""
        st, N, n, nc = self.starts, self.N, self.n, self.nc
        JpT = Jp.transpose(0, 2, 1)
        V = np.add.reduceat(JpT @ Jp, st, axis=0)
        gp = np.add.reduceat(JpT @ r[:, :, None], st, axis=0)[:, :, 0]
        Jc2 = Jc.reshape(2 * N, nc)
        Wc = np.add.reduceat(Jc.transpose(0, 2, 1) @ Jp, st, axis=0)
        Uxx = Ucx = gx = None
        if self.nx:
            JxT = Jx.transpose(0, 2, 1)
            if self._A_pt is None:
                self._A_pt = scipy.sparse.csr_matrix(
                    (np.ones(N), (self.pi, np.arange(N))), shape=(n, N))
            A = self._A_pt
            Uxx = (A @ (JxT @ Jx).reshape(N, 9)).reshape(n, 3, 3)
            Ucx = (A @ (Jc.transpose(0, 2, 1) @ Jx).reshape(N, nc * 3)).reshape(n, nc, 3)
            gx = A @ (JxT @ r[:, :, None]).reshape(N, 3)
        return Jc2.T @ Jc2, Jc2.T @ r.ravel(), Wc, V, gp, Uxx, Ucx, gx

    def _sums_dense(self, Jc, Jp, Jx, r):
        """The same sums on the dense (view, point) grid, unobserved pairs zero: batched
        matrix products per view and per point instead of per observation."""
        m, n, nc = self.m, self.n, self.nc
        K = 6 + nc + (3 if self.nx else 0)
        G = np.zeros((m * n, 2, K + 1))                    # columns: pose, camera, point, r
        G[self.cell, :, :6] = Jp
        G[self.cell, :, 6:6 + nc] = Jc
        if self.nx:
            G[self.cell, :, 6 + nc:K] = Jx
        G[self.cell, :, K] = r
        Gv = G.reshape(m, 2 * n, K + 1)
        Av = Gv[:, :, :6 + nc].transpose(0, 2, 1) @ Gv[:, :, list(range(6 + nc)) + [K]]
        V, Wc, gp = Av[:, :6, :6], Av[:, 6:, :6], Av[:, :6, -1]
        Ucc, gc = Av[:, 6:, 6:-1].sum(axis=0), Av[:, 6:, -1].sum(axis=0)
        Uxx = Ucx = gx = None
        if self.nx:
            Gp = G.reshape(m, n, 2, K + 1)[:, :, :, 6:].transpose(1, 0, 2, 3).reshape(
                n, 2 * m, nc + 4)
            Ap = Gp[:, :, nc:nc + 3].transpose(0, 2, 1) @ Gp
            Uxx, Ucx, gx = Ap[:, :, nc:nc + 3], Ap[:, :, :nc].transpose(0, 2, 1), Ap[:, :, -1]
        return Ucc, gc, Wc, V, gp, Uxx, Ucx, gx

    def apply(self, s: _State, delta: np.ndarray) -> _State:
        """``s`` moved by the engine's step (the camera and free target unknowns, then six
        pose unknowns per view)."""
        ny = self.nc + self.nx
        return self._moved(s, delta[:ny], delta[ny:].reshape(-1, 6))

    def _moved(self, s: _State, dy: np.ndarray, dp: np.ndarray) -> _State:
        t = s.copy()
        t.cam = s.cam + self.cam_map @ dy[: self.nc]
        if self.nx:
            X = t.X.ravel()
            X[self.free_idx] += dy[self.nc:]
        t.rvecs += dp[:, :3]
        t.tvecs += dp[:, 3:]
        return t


#: Most camera and free target unknowns for which :meth:`_Problem.camera_deletions` solves
#: once per view (a 10 x 10 board with its coordinates free has 312).
DELETION_MAX_UNKNOWNS = 400


def _inverse_from_cholesky(c: np.ndarray) -> np.ndarray:
    """``A^-1`` from the upper Cholesky factor of ``A`` (``scipy.linalg.cho_factor``), by
    LAPACK ``potri``: a third of the work of solving against the identity."""
    inv, info = scipy.linalg.lapack.dpotri(c, lower=0)
    if info != 0:
        raise np.linalg.LinAlgError(f"potri failed (info {info})")
    return np.triu(inv) + np.triu(inv, 1).T


def scaled_inverse(A: np.ndarray, rcond: float = 1e-13) -> tuple[np.ndarray, bool]:
    r"""Inverse of a symmetric positive semi-definite ``A`` (k, k) whose columns differ in
    scale, and whether it has full rank.

    ``A^-1 = D^-1 (D^-1 A D^-1)^-1 D^-1`` with ``D = diag(A)^1/2``: the scaled matrix has a unit
    diagonal, so its condition is that of the problem, not of its units (fx in px beside a k3
    seen through a 2-degree field: 10^10 apart). Eigenvalues of the scaled matrix at or below
    ``rcond`` times the largest are dropped (a pseudo-inverse), and the rank is then not full.
    A zero diagonal entry leaves its row and column zero.
    """
    d = np.sqrt(np.clip(np.diag(A), 0.0, None))
    scale = np.divide(1.0, d, out=np.zeros_like(d), where=d > 0)
    eig, vec = np.linalg.eigh(A * np.outer(scale, scale))
    keep = eig > rcond * max(eig[-1], 0.0)
    inv = (vec[:, keep] / eig[keep]) @ vec[:, keep].T
    return inv * np.outer(scale, scale), bool(keep.all() and np.all(d > 0))


def as_blocks(U: np.ndarray, W: np.ndarray, V: np.ndarray, g: np.ndarray, gp: np.ndarray
              ) -> NormalBlocks:
    """:meth:`_Problem.normal_equations`' blocks (``W`` (m, ny, 6), ``gp`` (m, 6)) in the
    engine's layout (:class:`~zoomcalib.calibrate.solver.NormalBlocks`: ``W`` (ny, 6 m),
    ``g_pose`` (6 m,), view by view)."""
    return NormalBlocks(U, W.transpose(1, 0, 2).reshape(len(U), -1), V, g, gp.ravel())
