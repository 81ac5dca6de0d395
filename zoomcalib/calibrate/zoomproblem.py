r"""The zoom-wide adjustment's least-squares problem: its unknowns, weighted residuals and normal
equations, the noise and the board's point heights re-estimated between solves, the posterior
covariance with its per-view scatter check, and the print test.

The model, its priors and why each is there: :mod:`zoomcalib.calibrate.zoomwide`, which sets the
problem up from the steps' own fits (:mod:`zoomcalib.calibrate.stepfits`), solves it with the
shared engine (:mod:`zoomcalib.calibrate.solver`) and reports it.

Unknowns, in :class:`_ZoomProblem`'s order: the global ones (each step's free intrinsics of
:data:`PARAMS`, each session's board modes, the print's in-plane modes, the shared aspect
ratio), then six per view (rotation, translation). :meth:`_ZoomProblem.normal_equations` sums
``J^T J`` and ``J^T r`` step by step and view by view without forming ``J``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.stats

from .geometry import project_jacobian
from .result import CalibrationResult, Observations
from .scatter import ViewScatter, deletion_steps, noise_share, view_groups, view_scatter
from .solver import NormalBlocks, Solve
from .stepfits import DISTORTION_TERMS, RATIONAL_TERMS
from .zoommodel import prior_operator

#: Per-step intrinsics of the adjustment, in this order.
PARAMS = ("fx", "fy", "cx", "cy", *DISTORTION_TERMS)


#: Parameters tied across zoom by the smoothness prior. Not the rational model's k4, k5, k6:
#: nearly collinear with k1, k2, k3 (to first order ``k4 = -k1``), they are told apart only by
#: a wide field's views, so only the steps whose held-out views choose them estimate them.
SMOOTHED = ("cx", "cy", "k1", "k2", "p1", "p2", "k3")


#: Parameters whose zoom model is chosen by held-out steps (``pp_model="select"``).
SELECTED = ("cx", "cy")


#: Per distortion term, the power ``p`` of the corner's normalised radius ``d / fx`` that turns
#: it into its displacement at the image corner as a fraction of the half-diagonal ``d``
#: (radial ``k r^(p+1)``, tangential ``p r^2``; the rational model's denominator terms k4, k5, k6
#: act to first order as -k1, -k2, -k3).
CORNER_POWER = {"k1": 2, "k2": 4, "p1": 1, "p2": 1, "k3": 6, "k4": 2, "k5": 4, "k6": 6}


_OUTLIER_SIGMA = 5.0


def board_height_modes(points: np.ndarray, max_degree: int = 4) -> np.ndarray:
    """Height modes ``phi_m`` of a board, ``(n, M)``: Legendre products of total degree 2..d.

    ``points`` (n, 3) board frame; coordinates normalised to [-1, 1] over the board's extent.
    """
    xy = np.asarray(points, float)[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    t = 2.0 * (xy - lo) / np.maximum(hi - lo, 1e-12) - 1.0
    cols = [np.polynomial.legendre.legval(t[:, 0], np.eye(k + 1)[k])
            * np.polynomial.legendre.legval(t[:, 1], np.eye(d - k + 1)[d - k])
            for d in range(2, max_degree + 1) for k in range(d + 1)]
    return np.column_stack(cols) if cols else np.zeros((len(xy), 0))


def _tied(free: np.ndarray, j: int) -> np.ndarray:
    """(S,) bool: the steps whose parameter ``j`` the smoothness prior ties (``free`` (S, 12)):
    those that estimate it, but for k1, k2, k3 not the steps with the rational model, whose
    radial terms are the numerator of a ratio and mean something else."""
    tied = free[:, j].copy()
    if PARAMS[j] in ("k1", "k2", "k3"):
        tied &= ~free[:, [PARAMS.index(k) for k in RATIONAL_TERMS]].any(axis=1)
    return tied


@dataclass
class _Step:
    """One zoom step's observations, flattened: ``view`` (N,) index into the step's views,
    ascending (the corners come view after view), ``point`` (N,) board point ids, ``uv``
    (N, 2) px; ``inlier`` (N,) bool; ``group`` (n_views,) views of nearly one pose
    (:func:`~zoomcalib.calibrate.scatter.view_groups`)."""

    name: str
    view: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    n_views: int
    inlier: np.ndarray
    group: np.ndarray
    sigma: float = 1.0
    #: effective number of board point heights this step's corners determine (their share)
    height_params: float = 0.0

    @classmethod
    def from_observations(cls, name: str, obs: Observations, sigma: float) -> _Step:
        view = np.concatenate([np.full(len(ids), i) for i, (ids, _) in enumerate(obs.views)])
        point = np.concatenate([ids for ids, _ in obs.views]).astype(np.int64)
        uv = np.concatenate([pts for _, pts in obs.views]).astype(np.float64)
        return cls(name, view, point, uv, obs.n_views, np.ones(len(view), bool),
                   view_groups(obs.views, obs.image_size), sigma)


@dataclass
class _State:
    """Unknowns: ``cams`` (S, 12) in ``PARAMS`` order, ``modes`` (M,) mm, ``rvecs``/``tvecs``
    (V, 3) for the views of all steps, step after step; ``aspect`` the sensor's ``fy / fx``
    shared by every step (NaN: each step has its own ``fy``; when shared, ``cams[:, 1]`` is
    kept at ``aspect * cams[:, 0]``); ``heights`` (sessions, N) mm, each session's board
    point heights beyond the modes (:func:`_update_heights`; None: none), held fixed by the
    Levenberg-Marquardt steps."""

    cams: np.ndarray
    modes: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    aspect: float = float("nan")
    heights: np.ndarray | None = None

    def vector(self, free: np.ndarray, aspect_free: bool = True) -> np.ndarray:
        """The unknowns in column order (``free`` (S, 12) selects the free intrinsics; the
        shared aspect ratio is one unless it is held, ``aspect_free`` False)."""
        shared = [] if np.isnan(self.aspect) or not aspect_free else [self.aspect]
        return np.concatenate([self.cams[free], self.modes, shared,
                               np.column_stack([self.rvecs, self.tvecs]).ravel()])


@dataclass(frozen=True)
class _Form:
    """How the smoothness prior reads one parameter's path (module docstring): ``prior2`` its
    second differences in its own units; ``angle2`` those of ``q / fx`` (``weight``, per
    step) with a free offset of ``q`` (``offset``); ``corner2`` those of a distortion term's
    displacement at the image corner, ``q (d / fx)^p``, without an offset."""

    name: str = "prior2"
    weight: np.ndarray | None = None
    offset: bool = True
    #: ``weight = (scale / fx)^power`` (power 0: no weight)
    power: int = 0
    scale: float = 1.0

    def at(self, steps) -> np.ndarray | None:
        """``weight`` of the given steps (None for a prior in the parameter's units)."""
        return None if self.weight is None else self.weight[steps]

    def to_dict(self) -> dict:
        """The form without its per-step weights: ``weight = (scale / fx)^power``."""
        return {"name": self.name, "power": self.power, "scale": self.scale,
                "offset": bool(self.offset and self.power != 0)}

    @classmethod
    def of(cls, pp_model: str, fx: np.ndarray, half_diagonal_px: float) -> dict[str, _Form]:
        """The forms of the smoothed parameters (``fx`` (S,) the steps' focal lengths, px):
        ``corner2`` for the distortion terms, and for cx and cy the one of ``pp_model``."""
        forms = {q: cls("corner2", weight=(half_diagonal_px / fx) ** power, offset=False,
                        power=power, scale=half_diagonal_px)
                 for q, power in CORNER_POWER.items()}
        if pp_model == "angle2":
            forms.update({q: cls("angle2", weight=1.0 / fx, power=1) for q in SELECTED})
        return forms


class _ZoomProblem:
    """Residuals and sparse Jacobian of the zoom-wide cost (module docstring).

    Columns: the free intrinsics of every step (``free`` (S, 12) bool), then the board modes,
    then the shared aspect ratio (``shared_aspect``; ``fy`` is then not free at any step),
    then six pose columns per view (from ``n_glob``). Rows: two per inlier observation
    (scaled by ``1/sigma_s``), then the smoothness rows ``D q / tau_q``, then ``a / board_prior``.
    """

    def __init__(self, setup: _Setup, free: np.ndarray, tau: dict[str, float],
                 order: dict[str, int] | None = None, forms: dict[str, _Form] | None = None):
        """The problem of ``setup``'s steps (:class:`_Setup`: the steps, board, height modes,
        chains, ``u``, sessions, the aspect's and the print's choices) with the camera
        unknowns ``free`` (steps, 12) and the smoothness prior's ``tau``, ``order`` and
        ``forms`` per parameter (empty: no prior)."""
        steps, modes_basis = setup.steps, setup.phi
        shared_aspect, aspect_held = setup.shared_aspect, setup.aspect_held
        print_shape = setup.keep_print
        self.steps, self.board, self.phi = steps, setup.board, modes_basis
        # each step's board session: its own height amplitudes (``n_basis`` per session)
        self.session = np.asarray(setup.session, int)
        self.free, self.chains, self.u, self.tau = free, setup.chain_idx, setup.u, tau
        self.order, self.forms = order or {}, forms or {}
        self.board_prior = setup.board_prior_mm
        self.rational_sd = setup.rational_sd
        self.cam_col = np.full(free.shape, -1)
        self.cam_col[free] = np.arange(int(free.sum()))
        self.n_cam = int(free.sum())
        self.n_basis = modes_basis.shape[1]
        # the print's in-plane modes (x, then y; shared by every session) follow the heights'
        self.n_print = 2 * self.n_basis if print_shape else 0
        self.n_modes = self.n_basis * (int(self.session.max()) + 1) + self.n_print
        self.shared_aspect = shared_aspect
        aspect_free = shared_aspect and not aspect_held
        self.aspect_col = self.n_cam + self.n_modes if aspect_free else -1
        self.n_glob = self.n_cam + self.n_modes + int(aspect_free)
        self.view_start = np.cumsum([0] + [s.n_views for s in steps])
        self.n_unknowns = self.n_glob + 6 * int(self.view_start[-1])
        self.prior_rows = self._prior_rows()
        self.covariance_ridge = 0.0  # set by the posterior covariance (_inverse_or_ridge)

    def _prior_rows(self) -> scipy.sparse.csr_matrix:
        rows = []
        for name in SMOOTHED:
            j = PARAMS.index(name)
            tau, order = self.tau.get(name, np.inf), self.order.get(name, 2)
            tied = _tied(self.free, j)
            for chain in self.chains:
                steps = [s for s in chain if tied[s]]
                if len(steps) <= order or not np.isfinite(tau):
                    continue
                form = self.forms.get(name, _Form())
                D = prior_operator(self.u[steps], order, form.at(steps), form.offset) / tau
                block = np.zeros((len(D), self.n_unknowns))
                block[:, self.cam_col[steps, j]] = D
                rows.append(block)
        steps, terms = np.nonzero(self.free[:, [PARAMS.index(q) for q in RATIONAL_TERMS]])
        if len(steps):  # the rational model's terms: a weak prior (module docstring)
            block = np.zeros((len(steps), self.n_unknowns))
            columns = self.cam_col[steps, PARAMS.index(RATIONAL_TERMS[0]) + terms]
            block[np.arange(len(steps)), columns] = 1.0 / self.rational_sd[steps, terms]
            rows.append(block)
        if self.n_modes:
            block = np.zeros((self.n_modes, self.n_unknowns))
            block[:, self.n_cam:self.n_cam + self.n_modes] = np.eye(self.n_modes) / self.board_prior
            rows.append(block)
        if not rows:
            return scipy.sparse.csr_matrix((0, self.n_unknowns))
        return scipy.sparse.csr_matrix(np.vstack(rows))

    def points(self, state: _State, s: int = 0) -> np.ndarray:
        """The board's 3-D points (n, 3) seen by step ``s`` in ``state``: the height modes of
        the step's session and, if any, its point heights; the print's in-plane modes."""
        first = self.n_basis * int(self.session[s])
        X = self.board.copy()
        X[:, 2] += self.phi @ state.modes[first:first + self.n_basis]
        if self.n_print:
            X[:, :2] += self.phi @ self.print_modes(state.modes).T
        if state.heights is not None:
            X[:, 2] += state.heights[self.session[s]]
        return X

    def print_modes(self, modes: np.ndarray) -> np.ndarray:
        """(2, n_basis) the in-plane amplitudes of the print, mm, in ``modes`` (x, then y)."""
        return modes[len(modes) - self.n_print:].reshape(2, self.n_basis)

    def evaluate(self, state: _State, jacobian: bool = True):
        """Weighted residuals (model minus observed, over sigma) and, optionally, the Jacobian."""
        res, rows, cols, vals = [], [], [], []
        row0 = 0
        for s, step in enumerate(self.steps):
            X = self.points(state, s)
            v0, v1 = self.view_start[s], self.view_start[s + 1]
            sel = step.inlier
            cam = state.cams[s]
            out = project_jacobian(cam, state.rvecs[v0:v1], state.tvecs[v0:v1], X,
                                   step.view[sel], step.point[sel], jacobian=jacobian)
            uv = out[0] if jacobian else out
            res.append(((uv - step.uv[sel]) / step.sigma).ravel())
            if jacobian:
                self._jacobian_entries(s, step, out[1:], row0, rows, cols, vals, state)
            row0 += 2 * int(sel.sum())
        r = np.concatenate(res)
        x = state.vector(self.free, self.aspect_col >= 0)
        prior = self.prior_rows @ x
        r = np.concatenate([r, prior])
        if not jacobian:
            return r
        J = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                     np.concatenate(cols))), shape=(row0, self.n_unknowns))
        return r, scipy.sparse.vstack([J, self.prior_rows], format="csr")

    def _global_block(self, s: int, step: _Step, Jc: np.ndarray, Jx: np.ndarray,
                      state: _State, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Step ``s``'s derivatives by the global unknowns it touches times ``scale``, (n, 2,
        k), and their columns (k,): its free intrinsics, the shared aspect ratio, its
        session's board modes and the print's in-plane modes. Written into one array, block
        by block (the normal equations' largest array: no concatenation, no copies)."""
        sel = step.inlier
        free = np.flatnonzero(self.free[s])
        n_basis, n_print = self.n_basis, self.n_print
        aspect = self.aspect_col >= 0
        k = len(free) + int(aspect) + (n_basis + n_print if n_basis else 0)
        G = np.empty((Jc.shape[0], 2, k))
        G[:, :, :len(free)] = Jc[:, :, free]
        if self.shared_aspect and len(free) and free[0] == 0:  # fy = aspect fx: fx moves fy
            G[:, :, 0] += state.aspect * Jc[:, :, 1]
        cols = [self.cam_col[s, free]]
        at = len(free)
        if aspect:
            np.multiply(Jc[:, :, 1], state.cams[s, 0], out=G[:, :, at])
            cols.append(np.array([self.aspect_col]))
            at += 1
        if n_basis:
            phi = self.phi[step.point[sel]][:, None, :]
            first = self.n_cam + n_basis * int(self.session[s])
            np.multiply(Jx[:, :, 2:3], phi, out=G[:, :, at:at + n_basis])
            cols.append(first + np.arange(n_basis))
            if n_print:
                np.multiply(Jx[:, :, 0:1], phi, out=G[:, :, at + n_basis:at + 2 * n_basis])
                np.multiply(Jx[:, :, 1:2], phi, out=G[:, :, at + 2 * n_basis:at + 3 * n_basis])
                cols.append(self.n_cam + self.n_modes - n_print + np.arange(n_print))
        if scale != 1.0:
            G *= scale
        return G, np.concatenate(cols)

    def _jacobian_entries(self, s, step, jac, row0, rows, cols, vals, state: _State):
        Jc, Jp, Jx = jac
        sel = step.inlier
        n = int(sel.sum())
        row = row0 + np.arange(2 * n).reshape(n, 2)
        w = 1.0 / step.sigma
        pose_col = self.n_glob + 6 * (self.view_start[s] + step.view[sel])
        G, g_cols = self._global_block(s, step, Jc, Jx, state)
        for block, col in ((G, np.broadcast_to(g_cols, (n, len(g_cols)))),
                           (Jp, pose_col[:, None] + np.arange(6))):
            k = block.shape[2]
            rows.append(np.repeat(row, k, axis=1).ravel())
            cols.append(np.repeat(col[:, None, :], 2, axis=1).ravel())
            vals.append((block * w).ravel())

    def linearise(self, state: _State) -> tuple[float, NormalBlocks]:
        """The cost ``|r|^2`` (prior rows included) and the normal blocks at ``state`` (the
        :class:`~zoomcalib.calibrate.solver.LeastSquaresProblem` protocol)."""
        r, blocks = self.normal_equations(state)
        return float(r @ r), blocks

    def cost(self, state: _State) -> float:
        """``|r|^2`` at ``state``, prior rows included."""
        r = self.evaluate(state, jacobian=False)
        return float(r @ r)

    def normal_equations(self, state: _State) -> tuple[np.ndarray, NormalBlocks]:
        """The weighted residuals (as :meth:`evaluate`) and the blocks of ``J^T J`` and
        ``J^T r`` (:class:`NormalBlocks`), summed step by step and view by view from the dense
        derivatives without forming ``J``: a corner's rows touch its step's global columns and
        its view's six pose columns only, and the prior rows the global columns only."""
        n_views = int(self.view_start[-1])
        U = np.zeros((self.n_glob, self.n_glob))
        W = np.zeros((self.n_glob, n_views, 6))
        V = np.zeros((n_views, 6, 6))
        g_glob, g_pose = np.zeros(self.n_glob), np.zeros((n_views, 6))
        res = []
        for s, step in enumerate(self.steps):
            sel = step.inlier
            uv, Jc, Jp, Jx = project_jacobian(
                state.cams[s], state.rvecs[self.view_start[s]:self.view_start[s + 1]],
                state.tvecs[self.view_start[s]:self.view_start[s + 1]],
                self.points(state, s), step.view[sel], step.point[sel])
            w = 1.0 / step.sigma
            r = (uv - step.uv[sel]) * w                                       # (n, 2)
            res.append(r.ravel())
            G, cols = self._global_block(s, step, Jc, Jx, state, w)
            # the sums as matrix products (BLAS), the corners' two rows stacked; a step's
            # corners come view after view, so each view's are one slice of rows
            G2, P2, r2 = G.reshape(-1, G.shape[2]), (Jp * w).reshape(-1, 6), r.ravel()
            U[np.ix_(cols, cols)] += G2.T @ G2
            g_glob[cols] += G2.T @ r2
            v0 = self.view_start[s]
            rows = 2 * np.searchsorted(step.view[sel], np.arange(step.n_views + 1))
            coupling = np.empty((len(cols), step.n_views, 6))
            for v, (a, b) in enumerate(zip(rows[:-1], rows[1:], strict=True)):
                pose = P2[a:b]
                V[v0 + v] += pose.T @ pose
                g_pose[v0 + v] += pose.T @ r2[a:b]
                coupling[:, v] = G2[a:b].T @ pose
            W[cols, v0:v0 + step.n_views] += coupling
        r = np.concatenate(res)
        prior = self.prior_rows @ state.vector(self.free, self.aspect_col >= 0)
        glob = self.prior_rows[:, :self.n_glob]
        U += (glob.T @ glob).toarray()
        g_glob += glob.T @ prior
        return (np.concatenate([r, prior]),
                NormalBlocks(U, W.reshape(self.n_glob, -1), V, g_glob, g_pose.ravel()))

    def apply(self, state: _State, delta: np.ndarray) -> _State:
        cams = state.cams.copy()
        cams[self.free] += delta[:self.n_cam]
        modes = state.modes + delta[self.n_cam:self.n_cam + self.n_modes]
        aspect = state.aspect
        if self.aspect_col >= 0:
            aspect = float(aspect + delta[self.aspect_col])
        if self.shared_aspect:
            cams[:, 1] = aspect * cams[:, 0]
        pose = delta[self.n_glob:].reshape(-1, 6)
        return _State(cams, modes, state.rvecs + pose[:, :3], state.tvecs + pose[:, 3:],
                      aspect, state.heights)


def _normal_blocks(prob: _ZoomProblem, J: scipy.sparse.csr_matrix, r: np.ndarray
                   ) -> NormalBlocks:
    """:class:`NormalBlocks` from an assembled sparse ``J`` (the reference for
    :meth:`_ZoomProblem.normal_equations`, which sums them without forming ``J``)."""
    n_glob = prob.n_glob
    A = (J.T @ J).tocsr()
    g = J.T @ r
    V = scipy.sparse.bsr_matrix(A[n_glob:, n_glob:], blocksize=(6, 6))
    V.sort_indices()
    if len(V.data) != V.shape[0] // 6:
        raise RuntimeError("zoom-wide problem: two views are coupled (internal error)")
    return NormalBlocks(A[:n_glob, :n_glob].toarray(), A[:n_glob, n_glob:].toarray(), V.data,
                         g[:n_glob], g[n_glob:])


@dataclass(frozen=True)
class PrintTest:
    """Whether the print's in-plane modes pay: the Wald statistic ``b^T C_b^-1 b`` of their
    amplitudes ``b`` in the solve without the smoothness prior, with k1, k2, p1, p2 and k3
    free at every step (``C_b`` their posterior covariance), against the chi-square quantile
    of ``dof`` at :data:`PRINT_TEST_P`. Kept when it exceeds it; otherwise the print is taken
    to be exact (a free print costs the narrow steps' principal point a factor of 2-4 in sigma
    where there is nothing to find)."""

    wald: float
    dof: int
    threshold: float
    kept: bool
    #: largest amplitude, mm, and its sigma
    largest_mm: float
    largest_sd_mm: float
    #: why the print could not be judged (its solve did not converge, or has no covariance);
    #: None when it was
    why: str | None = None
    #: the distortion terms free in the test's solve
    terms: str = "k1, k2, p1, p2, k3 at every step"

    def to_dict(self) -> dict:
        return {"wald": self.wald, "dof": self.dof, "threshold": self.threshold,
                "kept": self.kept, "largest_mm": self.largest_mm,
                "largest_sd_mm": self.largest_sd_mm, "why": self.why, "terms": self.terms}

    def summary(self) -> str:
        """One line for a run's log."""
        if self.why is not None:
            return (f"the print's shape could not be judged ({self.why}): the print is taken "
                    "to be exact")
        judged = "" if self.terms == PrintTest.terms else f", judged with {self.terms}"
        return (f"the print's shape: Wald {self.wald:.0f} on {self.dof} (threshold "
                f"{self.threshold:.1f}): {'kept' if self.kept else 'exact'}; largest mode "
                f"{self.largest_mm:+.3f} +- {self.largest_sd_mm:.3f} mm{judged}")


#: Level of the test that keeps the print's in-plane modes (:class:`PrintTest`).
PRINT_TEST_P = 1e-3


def _print_test(prob: _ZoomProblem, solve: Solve) -> PrintTest:
    """:class:`PrintTest` of the print's modes of ``prob`` solved by ``solve`` (not kept, NaN
    and ``why`` said, when the solve did not converge or has no covariance: the print cannot
    be judged)."""
    cols = np.arange(prob.n_cam + prob.n_modes - prob.n_print, prob.n_cam + prob.n_modes)
    b = solve.state.modes[len(solve.state.modes) - prob.n_print:]
    wald, sd, why = float("nan"), np.full(len(b), np.nan), None
    if not solve.converged:
        why = f"its solve without the smoothness prior stopped at the {solve.stop_reason}"
    else:
        try:
            cov = _posterior_covariance(prob, solve.state, check=False)[0][np.ix_(cols, cols)]
            wald = float(b @ np.linalg.solve(cov, b))
            sd = np.sqrt(np.diag(cov))
        except np.linalg.LinAlgError:
            why = "its solve without the smoothness prior has no covariance"
    threshold = float(scipy.stats.chi2.isf(PRINT_TEST_P, len(b)))
    i = int(np.argmax(np.abs(b)))
    return PrintTest(wald, len(b), threshold, bool(wald > threshold), float(b[i]), float(sd[i]),
                     why)


def _joint_covariance(prob: _ZoomProblem, state: _State):
    """``cov(steps, j)`` of the per-step intrinsics of a solved problem, or None when its
    posterior covariance is not positive definite. ``j`` is a parameter's index in
    :data:`PARAMS`, or a sequence of them: the block then holds, step by step, each of those
    parameters (``(cx_0, cy_0, cx_1, ...)`` for ``j = (2, 3)``). A held parameter's rows and
    columns are zero."""
    try:
        cov = _posterior_covariance(prob, state, check=False)[0]
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        return None

    def block(steps: list[int], j) -> np.ndarray:
        col = prob.cam_col[np.ix_(np.asarray(steps), np.atleast_1d(j))].reshape(-1)
        out = cov[np.ix_(col, col)]
        held = col < 0
        out[held, :], out[:, held] = 0.0, 0.0
        return out
    return block


def _update_noise(prob: _ZoomProblem, state: _State, free: np.ndarray) -> bool:
    """Re-estimate each step's noise sigma and its inliers; True when anything changed."""
    changed = False
    for s, step in enumerate(prob.steps):
        X = prob.points(state, s)
        v0, v1 = prob.view_start[s], prob.view_start[s + 1]
        cam = state.cams[s]
        uv = project_jacobian(cam, state.rvecs[v0:v1], state.tvecs[v0:v1], X, step.view,
                              step.point, jacobian=False)
        err = np.linalg.norm(uv - step.uv, axis=1)
        dof = max(2 * int(step.inlier.sum()) - 6 * step.n_views - int(free[s].sum())
                  - step.height_params, 1)
        sigma = float(np.sqrt(np.sum(err[step.inlier] ** 2) / dof))
        inlier = err <= _OUTLIER_SIGMA * sigma
        if abs(sigma - step.sigma) > 0.01 * step.sigma or np.any(inlier != step.inlier):
            changed = True
        step.sigma, step.inlier = sigma, inlier
    return changed


@dataclass
class _Setup:
    """What every solve of one adjustment shares: the steps (their names, corners, noise and
    inliers), the board and its height modes, each step's ``u = log fx`` at the start, its
    chain and capture session, the steps' own fits (``init``, their terms, ``held`` and the
    ``skipped`` steps), whether the aspect ratio is shared or held and whether the print's
    shape is fitted (``keep_print``; the print test can turn it off)."""

    names: list[str]
    steps: list[_Step]
    board: np.ndarray
    phi: np.ndarray
    u: np.ndarray
    chain_idx: np.ndarray
    labels: list[str]
    session_names: list[str]
    session: np.ndarray
    init: dict[str, CalibrationResult]
    terms: dict
    held: dict
    skipped: dict[str, str]
    sds: np.ndarray
    shared_aspect: bool
    aspect_held: bool
    keep_print: bool
    board_prior_mm: float
    #: (S, 3) prior sd of each step's k4, k5, k6 (:data:`RATIONAL_PRIOR_AT_CORNER`)
    rational_sd: np.ndarray
    #: the steps whose start lay far up the rational model's ridge (:func:`_off_the_ridge`)
    restarted: tuple[str, ...] = ()

    def problem(self, free: np.ndarray, tau=None, models=None, forms=None) -> _ZoomProblem:
        order = {k: m.order for k, m in (models or {}).items()}
        return _ZoomProblem(self, free, tau or {}, order, forms)


#: Prior sd of a board point's height beyond the modes, mm (a paper board on a wall: 1-2 mm).
POINT_HEIGHT_PRIOR_MM = 3.0


#: The point heights have settled when no round moves one by more than this, mm.
HEIGHT_TOL_MM = 0.02


def _update_heights(prob: _ZoomProblem, state: _State) -> float:
    r"""One Gauss-Newton step of each session's board point heights ``h`` (``state.heights``,
    updated) with the cameras, poses and modes held; returns the largest move, mm.

    Per point ``i`` of session ``k``, over the inlier corners of its steps' views,
    ``a_i = sum |dq/dz|^2 / sigma^2`` and ``b_i = sum (dq/dz . r) / sigma^2`` (``r`` model minus
    observed), and with the prior ``h ~ N(0, POINT_HEIGHT_PRIOR_MM^2)``

    .. math:: h_i \leftarrow h_i - (b_i + h_i / \sigma_h^2) / (a_i + 1 / \sigma_h^2),

    then the part in the span of a constant, the two board coordinates and the height modes
    is taken out: that part is a pose or a mode, which the adjustment itself estimates. The
    heights are fitted point by point, so they take no part in the posterior covariance; each
    step's noise estimate counts the heights its corners determine (``a_i`` over
    ``a_i + 1 / sigma_h^2``, shared by the steps' ``a``) as used degrees of freedom."""
    n = len(prob.board)
    a, b = np.zeros((len(prob.steps), n)), np.zeros((len(prob.steps), n))
    for s, step in enumerate(prob.steps):
        sel = step.inlier
        v0, v1 = prob.view_start[s], prob.view_start[s + 1]
        uv, _, _, Jx = project_jacobian(state.cams[s], state.rvecs[v0:v1], state.tvecs[v0:v1],
                                        prob.points(state, s), step.view[sel], step.point[sel])
        dz = Jx[:, :, 2] / step.sigma
        r = (uv - step.uv[sel]) / step.sigma
        a[s] = np.bincount(step.point[sel], np.sum(dz * dz, axis=1), n)
        b[s] = np.bincount(step.point[sel], np.sum(dz * r, axis=1), n)
    xy = prob.board[:, :2] - prob.board[:, :2].mean(axis=0)
    low = np.column_stack([np.ones(n), xy, prob.phi])
    high_pass = np.eye(n) - low @ np.linalg.pinv(low)
    prior = 1.0 / POINT_HEIGHT_PRIOR_MM ** 2
    new = state.heights.copy()
    for k in range(len(new)):
        on = np.flatnonzero(prob.session == k)
        info = a[on].sum(axis=0) + prior
        h = new[k] - (b[on].sum(axis=0) + new[k] * prior) / info
        new[k] = high_pass @ h
        for s in on:
            prob.steps[s].height_params = float(np.sum(a[s] / info))
    moved = float(np.max(np.abs(new - state.heights), initial=0.0))
    state.heights = new
    return moved


def _posterior_covariance(prob: _ZoomProblem, state: _State, check: bool = True
                          ) -> tuple[np.ndarray, ViewScatter | None]:
    """Posterior covariance ``[(J^T J)^{-1}]`` of the intrinsics and board modes (the poses
    marginalised: the inverse of the Schur complement), weighted problem with its prior rows;
    and, if ``check``, the view-scatter check of the intrinsics (:func:`_view_scatter`)."""
    r, J = prob.evaluate(state)
    U, W, V, _, _ = prob.normal_equations(state)[1]
    coupling_by_view = W.reshape(len(U), len(V), 6)
    through_pose = np.einsum("gvi,vij->gvj", coupling_by_view, np.linalg.inv(V))        # W_v V_v^-1
    S = U - np.einsum("gvj,hvj->gh", through_pose, coupling_by_view)
    cov = _inverse_or_ridge(S, prob)
    if not check:
        return cov, None
    camera_rows = cov[:prob.n_cam]
    A, g = _view_blocks(prob, r, J, coupling_by_view, V)
    share = noise_share(camera_rows.T, A @ camera_rows.T, cov,
                        model_variance=np.einsum("ii->i", camera_rows[:, :prob.n_cam]))
    return cov, _view_scatter(prob, r, J, camera_rows @ through_pose.reshape(len(U), -1),
                              camera_rows, lambda: deletion_steps(S, A, g)[:, :prob.n_cam],
                              share)


#: Ridges (relative to each column's information), smallest first, added to a posterior
#: information that rounding left indefinite: a direction the data do not determine (the
#: rational model's k1..k6 of a step of a dozen views) then gets a variance of ``1 / r`` times
#: its conditional one. The information ``U - W V^-1 W^T`` is formed by a difference of nearly
#: equal terms, so along such a direction its rounding can reach 1e-5 of the diagonal (a
#: half of a real wide-angle sweep's 7 steps, rational model at its widest).
_COVARIANCE_RIDGES = (1e-6, 1e-5, 1e-4, 1e-3)


def _inverse_or_ridge(S: np.ndarray, prob: _ZoomProblem) -> np.ndarray:
    """``S^-1`` by Cholesky on the unit-diagonal scaling of ``S``; where rounding leaves ``S``
    indefinite, ``(S + r diag S)^-1`` with the smallest ``r`` of :data:`_COVARIANCE_RIDGES`
    that makes it positive definite, recorded in ``prob.covariance_ridge`` (0 otherwise).
    LinAlgError, saying so, if none does."""
    d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
    scaled = d[:, None] * S * d
    for ridge in (0.0, *_COVARIANCE_RIDGES):
        try:
            factor = scipy.linalg.cho_factor(scaled + ridge * np.eye(len(S)))
        except np.linalg.LinAlgError:
            continue
        prob.covariance_ridge = ridge
        return d[:, None] * scipy.linalg.cho_solve(factor, np.eye(len(S))) * d
    raise np.linalg.LinAlgError(
        f"the posterior information is indefinite beyond rounding (no ridge up to "
        f"{_COVARIANCE_RIDGES[-1]:g} of its diagonal makes it positive definite)")


def _view_rows(prob: _ZoomProblem) -> np.ndarray:
    """The view of each inlier corner (residual rows ``2 i, 2 i + 1``), in row order."""
    return np.concatenate([prob.view_start[s] + step.view[step.inlier]
                           for s, step in enumerate(prob.steps)])


def _view_groups(prob: _ZoomProblem) -> np.ndarray:
    """(views,) the group of every view of the sweep, numbered across steps."""
    offsets = np.cumsum([0] + [int(step.group.max()) + 1 for step in prob.steps])
    return np.concatenate([offsets[s] + step.group for s, step in enumerate(prob.steps)])


def _view_blocks(prob: _ZoomProblem, r: np.ndarray, J, coupling_by_view: np.ndarray, V: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per group of views (:func:`_view_groups`), its share of the Schur complement and of the
    gradient, ``A_g`` (groups, n_glob, n_glob) and ``g_g`` (groups, n_glob): the sums of
    ``Jt_v^T Jt_v`` and ``Jt_v^T r_v`` over its views, ``Jt_v = J_g,v - J_p,v V_v^-1 W_v^T``
    a view's rows over the intrinsics and board modes, its pose projected out
    (:mod:`zoomcalib.calibrate.scatter`); ``coupling_by_view`` (n_glob, views, 6). The
    intrinsics' move when a group is left out is ``(S - A_g)^-1 g_g``."""
    n_glob, n_views = prob.n_glob, len(V)
    row_view = np.repeat(_view_rows(prob), 2)
    order = np.argsort(row_view, kind="stable")
    bounds = np.searchsorted(row_view[order], np.arange(n_views + 1))
    data = J[:len(row_view)].tocsr()[order]
    residual = r[:len(row_view)][order]
    through_pose = np.linalg.solve(V, coupling_by_view.transpose(1, 2, 0))  # (views, 6, n_glob)
    groups = _view_groups(prob)
    A, g = np.zeros((groups.max() + 1, n_glob, n_glob)), np.zeros((groups.max() + 1, n_glob))
    for v in range(n_views):                       # dense blocks of a few hundred rows each
        rows = data[bounds[v]:bounds[v + 1]]
        pose = rows[:, n_glob + 6 * v:n_glob + 6 * v + 6].toarray()
        Jt = rows[:, :n_glob].toarray() - pose @ through_pose[v]
        A[groups[v]] += Jt.T @ Jt
        g[groups[v]] += Jt.T @ residual[bounds[v]:bounds[v + 1]]
    return A, g


def _view_scatter(prob: _ZoomProblem, r: np.ndarray, J, camera_pose: np.ndarray,
                  camera_rows: np.ndarray, deletions, null_share: np.ndarray) -> ViewScatter:
    """The view-scatter check (:mod:`zoomcalib.calibrate.scatter`) of every step's free
    intrinsics: corner ``i``'s share of their move is ``S^-1[cam, :] (J_g,i^T r_i - W_v V_v^-1
    J_p,i^T r_i)``; ``camera_rows`` is ``S^-1[cam, :]`` (n_cam, n_glob), ``camera_pose`` the
    same times ``W V^-1`` (n_cam, 6 views), ``r``, ``J`` the weighted residuals and Jacobian,
    ``deletions`` a callable giving each group's move when left out, ``null_share`` the
    clustered sum's expectation under the noise model over the posterior variance
    (:func:`~zoomcalib.calibrate.scatter.noise_share`, the smoothness prior part of the noise
    model)."""
    n_glob = prob.n_glob
    n_rows = sum(2 * int(step.inlier.sum()) for step in prob.steps)
    corner = scipy.sparse.csr_matrix((np.ones(n_rows), (np.arange(n_rows) // 2,
                                                         np.arange(n_rows))))
    scores = corner @ scipy.sparse.diags(r[:n_rows]) @ J[:n_rows]       # (corners, unknowns)
    influence = (scores[:, :n_glob] @ camera_rows.T
                 - scores[:, n_glob:] @ camera_pose.T)                   # (corners, n_cam)
    groups = _view_groups(prob)
    names = [f"{prob.steps[s].name}:{PARAMS[j]}" for s, j in zip(*np.nonzero(prob.free),
                                                                  strict=True)]
    model_sd = np.sqrt(np.einsum("ii->i", camera_rows[:, :prob.n_cam]))
    points = np.concatenate([step.point[step.inlier] for step in prob.steps])
    return view_scatter(np.asarray(influence), groups[_view_rows(prob)], int(groups.max()) + 1,
                        tuple(names), model_sd, deletions, null_share, points)


def _step_scale(prob: _ZoomProblem, s: int, scale: np.ndarray) -> np.ndarray:
    """(12,) the view-scatter factor applied to each of step ``s``'s ``PARAMS`` (1 if fixed)."""
    cols = prob.cam_col[s]
    return np.where(cols >= 0, scale[np.maximum(cols, 0)], 1.0)
