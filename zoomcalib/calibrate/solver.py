"""One Levenberg-Marquardt engine for the calibration problems whose unknowns are global
parameters (intrinsics, board shape, target points) and one pose per view.

A problem's normal equations ``J^T J delta = -J^T r`` come in blocks
(:class:`NormalBlocks`): the global block ``U`` (G, G), the coupling ``W`` (G, 6 n_views)
of the globals with the poses, the per-view pose blocks ``V`` (n_views, 6, 6) (the views do
not couple: a corner's rows touch its own view's pose only), and the gradient's parts
``g_glob``, ``g_pose``. A step eliminates the poses (the Schur complement
``S = U - W V^-1 W^T``, [1]) with Marquardt's scaling: the damped system is
``(A + lam diag A) delta = -g``.

The engine (:func:`levenberg_marquardt`) stops on the decrease of the cost that the
quadratic model predicts for the Gauss-Newton step from the current state ([2]): below
``tol`` times the cost, nothing is left to gain, whatever the damping of the last step was
(``"tolerance"``, converged). It gives up at the iteration cap (``"iteration cap"``) or when
the damping passes :data:`MAX_DAMPING` without a step that lowers the cost (``"damping
limit"``); both are not converged, and the caller says so.

A problem supplies ``linearise(state) -> (cost, NormalBlocks)``, ``cost(state) -> float``
(the sum of squared weighted residuals, priors included) and ``apply(state, delta) ->
state`` (``delta``: the globals, then six pose unknowns per view).

References
----------
.. [1] B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment — a modern
   synthesis", Vision Algorithms: Theory and Practice, LNCS 1883, 2000.
.. [2] K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares
   problems", IMM, DTU, 2004.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np
import scipy.linalg

__all__ = ["NormalBlocks", "LeastSquaresProblem", "Solve", "levenberg_marquardt",
           "schur_step", "predicted_decrease", "STOP_TOLERANCE", "STOP_ITERATION_CAP",
           "STOP_DAMPING_LIMIT", "GAUSS_NEWTON", "MAX_DAMPING"]

#: Why a solve stopped: converged, and the two ways it is not.
STOP_TOLERANCE = "tolerance"
STOP_ITERATION_CAP = "iteration cap"
STOP_DAMPING_LIMIT = "damping limit"
#: The damping of the step the stop rule predicts from: Gauss-Newton's, with a ridge of 1e-9 of
#: each column's own curvature so that a barely determined direction does not make it singular.
GAUSS_NEWTON = 1e-9
#: The damping beyond which a solve that finds no lower cost gives up.
MAX_DAMPING = 1e12


class NormalBlocks(NamedTuple):
    """``J^T J`` split into the global block ``U`` (G, G), the coupling ``W`` (G, 6 n_views)
    and the per-view 6 x 6 pose blocks ``V`` (n_views, 6, 6); and ``J^T r`` split likewise
    into ``g_glob`` (G,) and ``g_pose`` (6 n_views,)."""

    U: np.ndarray
    W: np.ndarray
    V: np.ndarray
    g_glob: np.ndarray
    g_pose: np.ndarray


class LeastSquaresProblem(Protocol):
    """What :func:`levenberg_marquardt` needs of a problem (module docstring)."""

    def linearise(self, state: Any) -> tuple[float, NormalBlocks]: ...

    def cost(self, state: Any) -> float: ...

    def apply(self, state: Any, delta: np.ndarray) -> Any: ...


@dataclass
class Solve:
    """The end of a solve: the state, its cost, the linearisations accepted
    (``iterations``), why it stopped (``STOP_*``) and the normal blocks at the state (None
    when it stopped before linearising there)."""

    state: Any
    cost: float
    iterations: int
    stop_reason: str
    blocks: NormalBlocks | None = None

    @property
    def converged(self) -> bool:
        return self.stop_reason == STOP_TOLERANCE


def schur_step(blocks: NormalBlocks, lam: float) -> np.ndarray | None:
    """Solve ``(A + lam diag A) delta = -g`` by eliminating the poses:
    ``S = U - W V^-1 W^T`` (each column scaled by its own curvature, plus a ridge of 1e-14 of
    it on the globals). Returns ``delta`` (globals, then the poses view by view), or None when
    a pose block or ``S`` is not positive definite."""
    U, W, V, g_glob, g_pose = blocks
    n_views, n_glob = len(V), len(U)
    global_damped = U + np.diag((lam + 1e-14) * np.diag(U))
    pose_damped = V + lam * np.einsum("vii->vi", V)[:, :, None] * np.eye(6)
    try:
        pose_inverse = np.linalg.inv(pose_damped)
    except np.linalg.LinAlgError:
        return None
    coupling = W.reshape(n_glob, n_views, 6)
    # W V^-1 view by view (batched 6 x 6 products), then the sums over views as one BLAS
    # product of the (globals, views x 6) matrices
    coupling_vinv = np.matmul(coupling.transpose(1, 0, 2), pose_inverse
                              ).transpose(1, 0, 2).reshape(n_glob, -1)
    schur = global_damped - coupling_vinv @ W.T
    schur_rhs = g_glob - coupling_vinv @ g_pose
    try:
        d_glob = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(schur), schur_rhs)
    except (np.linalg.LinAlgError, ValueError):
        return None
    pose_rhs = g_pose.reshape(n_views, 6) + (W.T @ d_glob).reshape(n_views, 6)
    d_pose = -np.matmul(pose_inverse, pose_rhs[:, :, None])[:, :, 0]
    return np.concatenate([d_glob, d_pose.ravel()])


def predicted_decrease(blocks: NormalBlocks, delta: np.ndarray | None) -> float:
    """The decrease of the cost that the quadratic model predicts for the undamped step
    ``delta`` (``A delta = -g``): ``-2 g^T delta - delta^T A delta = delta^T A delta``.
    ``inf`` without a step (a singular system: no prediction)."""
    if delta is None:
        return np.inf
    U, W, V = blocks.U, blocks.W, blocks.V
    d_glob, d_pose = delta[:len(U)], delta[len(U):].reshape(len(V), 6)
    quad = (d_glob @ U @ d_glob + 2.0 * d_glob @ W @ d_pose.ravel()
            + np.einsum("vi,vij,vj->", d_pose, V, d_pose))
    return float(max(quad, 0.0))


def levenberg_marquardt(problem: LeastSquaresProblem, state: Any, max_iterations: int = 50,
                        tol: float = 1e-9, lam: float = 1e-4) -> Solve:
    """Minimise ``problem.cost`` from ``state`` (module docstring): Marquardt-scaled steps
    (:func:`schur_step`); after a step that lowers the cost the damping is divided by 10
    (down to 1e-12), after one that does not it is multiplied by 10. Stops with
    :data:`STOP_TOLERANCE` when the Gauss-Newton step is predicted to lower the cost by less
    than ``tol`` of it, :data:`STOP_ITERATION_CAP` after ``max_iterations`` accepted steps,
    :data:`STOP_DAMPING_LIMIT` when the damping passes :data:`MAX_DAMPING`."""
    cost, blocks = problem.linearise(state)
    for it in range(1, max_iterations + 1):
        if predicted_decrease(blocks, schur_step(blocks, GAUSS_NEWTON)) < tol * cost:
            return Solve(state, cost, it - 1, STOP_TOLERANCE, blocks)
        while True:
            delta = schur_step(blocks, lam)
            if delta is not None:
                trial = problem.apply(state, delta)
                cost_t = problem.cost(trial)
                if np.isfinite(cost_t) and cost_t <= cost:
                    break
            lam *= 10.0
            if lam > MAX_DAMPING:
                return Solve(state, cost, it, STOP_DAMPING_LIMIT, blocks)
        state, cost = trial, cost_t
        lam = max(lam / 10.0, 1e-12)
        blocks = problem.linearise(state)[1]
    if predicted_decrease(blocks, schur_step(blocks, GAUSS_NEWTON)) < tol * cost:
        return Solve(state, cost, max_iterations, STOP_TOLERANCE, blocks)
    return Solve(state, cost, max_iterations, STOP_ITERATION_CAP, blocks)
