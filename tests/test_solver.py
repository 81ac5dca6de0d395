"""The Levenberg-Marquardt engine (zoomcalib/calibrate/solver.py) on a small problem of its
shape (two global unknowns, six per view), against scipy's least_squares on the same residuals,
and its three ways to stop."""

import numpy as np
import pytest
import scipy.optimize

from zoomcalib.calibrate.solver import (
    STOP_DAMPING_LIMIT,
    STOP_ITERATION_CAP,
    STOP_TOLERANCE,
    NormalBlocks,
    levenberg_marquardt,
)


class Curves:
    """Per view ``v`` and abscissa ``x_j``: ``a0 b(x - p_v0) + a1 x + sum_k p_vk B_k(x)``,
    ``b(d) = exp(-(d / w)^2)`` a narrow bump (no polynomial ``B_k`` of degree 4 mimics it),
    against noisy ordinates; ``a`` (2,) is global, ``p_v`` (6,) a view's own."""

    width = 0.2

    def __init__(self, rng, views: int = 5):
        self.x = np.linspace(-1.0, 1.0, 41)
        self.basis = np.stack([self.x**2, self.x**3, np.sin(3 * self.x), np.cos(2 * self.x),
                               self.x**4], axis=1)
        self.truth = (np.array([1.5, -0.7]), rng.normal(0.0, 0.3, (views, 6)))
        self.y = self.model(self.truth) + rng.normal(0.0, 0.01, (views, len(self.x)))

    def model(self, state):
        a, p = state
        bump = np.exp(-((self.x - p[:, :1]) / self.width) ** 2)
        return a[0] * bump + a[1] * self.x + p[:, 1:] @ self.basis.T

    def residuals(self, state):
        return (self.model(state) - self.y).ravel()

    def cost(self, state) -> float:
        r = self.residuals(state)
        return float(r @ r)

    def apply(self, state, delta):
        return state[0] + delta[:2], state[1] + delta[2:].reshape(-1, 6)

    def linearise(self, state):
        a, p = state
        e = np.exp(-((self.x - p[:, :1]) / self.width) ** 2)            # (m, n)
        j_glob = np.stack([e, np.broadcast_to(self.x, e.shape)], axis=-1)  # (m, n, 2)
        j_pose = np.concatenate([(2.0 * a[0] * (self.x - p[:, :1]) / self.width**2 * e)[..., None],
                                 np.broadcast_to(self.basis, e.shape + (5,))], axis=-1)
        r = self.model(state) - self.y
        U = np.einsum("vni,vnj->ij", j_glob, j_glob)
        W = np.einsum("vni,vnk->ivk", j_glob, j_pose).reshape(2, -1)
        V = np.einsum("vnk,vnl->vkl", j_pose, j_pose)
        blocks = NormalBlocks(U, W, V, np.einsum("vni,vn->i", j_glob, r),
                              np.einsum("vnk,vn->vk", j_pose, r).ravel())
        return float(np.sum(r * r)), blocks


def _start(problem, rng):
    a, p = problem.truth
    shift = rng.normal(0, 0.3, p.shape)
    shift[:, 0] *= 0.1                 # the bumps' places within their width
    return a + rng.normal(0, 0.3, 2), p + shift


def test_the_engine_reaches_scipys_least_squares_solution(rng):
    problem = Curves(rng)
    start = _start(problem, rng)
    solve = levenberg_marquardt(problem, start, max_iterations=100, tol=1e-12)
    assert solve.stop_reason == STOP_TOLERANCE and solve.converged
    flat = np.concatenate([start[0], start[1].ravel()])
    ref = scipy.optimize.least_squares(
        lambda v: problem.residuals((v[:2], v[2:].reshape(-1, 6))), flat, method="lm",
        xtol=1e-14, ftol=1e-14, gtol=1e-14)
    ours = np.concatenate([solve.state[0], solve.state[1].ravel()])
    assert np.max(np.abs(ours - ref.x)) < 1e-6
    assert solve.cost == pytest.approx(2 * ref.cost, rel=1e-9)   # scipy's cost is |r|^2 / 2
    # the blocks returned are those at the solution, where the gradient vanishes
    _, at_end = problem.linearise(solve.state)
    assert np.array_equal(at_end.U, solve.blocks.U)
    assert np.abs(np.concatenate([at_end.g_glob, at_end.g_pose])).max() < 1e-6


def test_the_engine_stops_at_its_cap_and_its_damping_limit_and_says_so(rng):
    problem = Curves(rng)
    start = _start(problem, rng)
    capped = levenberg_marquardt(problem, start, max_iterations=1, tol=1e-12)
    assert capped.stop_reason == STOP_ITERATION_CAP and not capped.converged
    assert capped.iterations == 1 and capped.cost < problem.cost(start)

    class NoStep(Curves):
        def cost(self, state):  # every trial step is worse: the damping grows to its limit
            return np.inf if state is not start else super().cost(state)

    stuck = NoStep.__new__(NoStep)
    stuck.__dict__.update(problem.__dict__)
    limited = levenberg_marquardt(stuck, start, max_iterations=50)
    assert limited.stop_reason == STOP_DAMPING_LIMIT and not limited.converged
    assert limited.state is start and limited.iterations == 1
