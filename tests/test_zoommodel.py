"""The zoom models of a per-step intrinsic and their choice by held-out steps, on seeded chains
whose paths and noise come from generators other than the candidates' own: a quadratic or a
straight line in log fx seen through correlated noise, a kinked path, an integrated random walk,
and the principal point of the ray-traced zoom lens."""

import math
from collections import Counter

import numpy as np
import pytest

from zoomcalib.calibrate.zoommodel import (
    PathPrior,
    divided_difference,
    held_out_residuals,
    marginal_tau,
    path_posterior,
    pooled_prior_strength,
    prior_operator,
    select_zoom_model,
)
from zoomcalib.render.pp_path import traced_path

STEPS = 7
U = np.log(np.geomspace(2300.0, 23000.0, STEPS) / 2300.0)
# per-step sigmas like the zoom-wide solve without the prior (0.03 px short, 1.3 px long end),
# correlated between neighbours through the shared board
SD = np.geomspace(0.03, 1.3, STEPS)
COV = np.outer(SD, SD) * 0.3 ** np.abs(np.subtract.outer(range(STEPS), range(STEPS)))
CHOL = np.linalg.cholesky(COV)


def _choices(rng, path_of, trials=30) -> Counter:
    return Counter(select_zoom_model([(path_of(rng) + CHOL @ rng.normal(size=STEPS), COV, U)]).name
                   for _ in range(trials))


@pytest.mark.parametrize("order", [2, 3, 4])
def test_divided_differences_are_the_derivative_on_polynomials(rng, order):
    u = np.sort(rng.uniform(0, 3, 9))
    coef = rng.normal(size=order + 1)
    got = divided_difference(u, order) @ np.polyval(coef, u)
    np.testing.assert_allclose(got, coef[0] * math.factorial(order), rtol=1e-7)


def test_held_out_choice_picks_the_polynomial_of_a_low_degree_path(rng):
    def quadratic(r):  # curvature 3-6 px/u^2: the long end bends by 16-32 px
        return r.uniform(-10, 10) * U + r.choice([-1, 1]) * r.uniform(3, 6) * U**2

    got = _choices(rng, quadratic)
    # 30 chains; a polynomial must beat the prior by 2 standard errors of the held-out
    # difference, which the quadratic did in 26 of 30 chains of another seed (21 poly2, 5
    # poly3); a line never fits
    assert got["poly2"] + got["poly3"] >= 20 and got["poly1"] == 0, got


def test_held_out_choice_keeps_the_prior_where_a_polynomial_cannot_follow(rng):
    def kink(r):  # the slope changes by 8-15 px/u somewhere in the middle of the range
        return r.uniform(-10, 10) * U + r.choice([-1, 1]) * r.uniform(8, 15) * np.maximum(
            U - r.uniform(0.8, 1.5), 0)

    def traced(r):  # the lens's principal point with its cam-track run-out
        return traced_path(U / U[-1], (2300.0, 23000.0), 40.0, int(r.integers(1 << 30)))[0][:, 0]

    for path in (kink, traced):
        got = _choices(rng, path, trials=10)
        assert sum(v for k, v in got.items() if k.startswith("poly")) <= 1, got


def test_angular_prior_leaves_an_offset_and_a_line_in_angle_free(rng):
    u = np.sort(rng.uniform(0, 2.3, 9))
    fx = 2300.0 * np.exp(u)
    R = prior_operator(u, 2, 1.0 / fx)
    c, a, b = rng.uniform(-50, 50), rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3)
    np.testing.assert_allclose(R @ (c + fx * (a + b * u)), 0.0, atol=1e-12)
    # on any other path it is the second difference of (q - c) / fx at the best offset c
    q = rng.normal(0, 10, len(u))
    D = divided_difference(u, 2)
    best = min(np.linalg.norm(D @ ((q - k) / fx))
               for k in np.linspace(-2000, 2000, 400001))
    assert abs(np.linalg.norm(R @ q) - best) < 1e-6 * best


def test_angular_prior_strength_recovers_the_roughness(rng):
    # a path smooth in angle (integrated Wiener process in u) plus a sensor offset of 25 px;
    # REML with the offset free must find the angle's roughness, not the offset's 1/fx curve
    n, sd_px = 25, 0.05
    u = np.linspace(0, 2.3, n)
    fx = 2300.0 * np.exp(u)
    fine = np.linspace(-0.05, 2.35, 24001)
    dt = fine[1] - fine[0]
    for intensity in (3e-4, 3e-3):
        slope = np.cumsum(intensity * np.sqrt(dt) * rng.normal(size=len(fine)))
        angle = np.interp(u, fine, np.cumsum(slope) * dt)
        q = 25.0 + fx * angle + rng.normal(0, sd_px, n)
        got, _ = pooled_prior_strength([(q / fx, sd_px / fx, u, 1.0 / fx)], 2)
        implied = np.sqrt(np.mean((divided_difference(u, 2) @ angle) ** 2))
        # 23 differences: the estimate scatters by ~15 %; 2x allows 4 sigma
        assert 0.5 < got / implied < 2.0, (intensity, got, implied)


def _bent_angle_chains(rng, draws: int, amplitude: float):
    """Angular principal-point paths (rad) that bend once, at a drawn zoom position in the
    upper half (a softplus of width 0.08 in normalised log fx, slope drawn with sd
    ``amplitude``), plus a drawn straight line, seen through independent noise whose sd grows
    from 0.15 px to 6 px over the sweep: ``(path px, chain)`` per draw (not the prior's own
    Gaussian model)."""
    fx = np.geomspace(2300.0, 23000.0, STEPS)
    u, w = np.log(fx), 1.0 / fx
    s = (u - u[0]) / (u[-1] - u[0])
    sd = 0.15 * (fx / 2300.0) ** 1.6
    out = []
    for _ in range(draws):
        bend = 0.08 * np.logaddexp(0.0, (s - rng.uniform(0.5, 0.85)) / 0.08)
        path = 600.0 + fx * (rng.normal(0, amplitude) * bend + rng.normal(0, 1e-3) * s)
        q = path + rng.normal(0, sd)
        out.append((path, (w * q, w * sd, u, w)))
    return out


def test_marginalised_tau_covers_paths_that_reml_calls_straight(rng):
    # a bend at the long end of the size of its noise: REML's tau often sits at its lower bound
    # and its plug-in sigma then misses; with tau marginalised the errors stay within their sigma
    z_plugin, z_marginal, at_bound = [], [], []
    for path, chain in _bent_angle_chains(rng, 200, 3e-3):
        w = chain[3]
        tau, bound = pooled_prior_strength([chain], 2)
        m, P = path_posterior(chain, 2, tau)
        z_plugin.append((m - w * path) / np.sqrt(np.diag(P)))
        model = PathPrior("angle2", 2, tau, bound)
        extra = marginal_tau(model, [chain])[0]
        assert model.tau_reml == tau
        assert model.tau_interval[0] <= model.tau <= model.tau_interval[1]
        m, P = path_posterior(chain, 2, model.tau)
        z_marginal.append((m - w * path) / np.sqrt(np.diag(P + extra)))
        at_bound.append(bound)
    z_plugin, z_marginal = np.abs(z_plugin), np.abs(z_marginal)
    assert sum(at_bound) > 40  # the case the marginalisation is for does occur
    # 1400 z values, correlated within a draw: the RMS is known to about 5 %
    assert 0.8 < np.sqrt(np.mean(z_marginal ** 2)) < 1.1
    assert np.mean(z_marginal > 2) < 0.0455  # no more misses than a Gaussian's
    assert z_marginal.max() < z_plugin.max()


def test_held_out_steps_are_predicted_with_tau_marginalised(rng):
    # the same bent paths, each step predicted from the others: at REML's plug-in tau the
    # predictions are too sure where the others look straight (more misses beyond 2 and 3
    # sigma than a Gaussian's); averaged over tau's posterior they are not, at the price of
    # sigmas somewhat wide on average
    z_plugin, z_marginal = [], []
    for _, chain in _bent_angle_chains(rng, 40, 3e-3):
        for marginal, z in ((False, z_plugin), (True, z_marginal)):
            resid, sd = held_out_residuals(chain, 2, 0.0, True, marginal=marginal)
            z.extend(resid / sd)
    z_plugin, z_marginal = np.abs(z_plugin), np.abs(z_marginal)
    rms = np.sqrt(np.mean(z_marginal ** 2))
    for name, z in (("plug-in", z_plugin), ("marginalised", z_marginal)):
        print(f"{name}: RMS z {np.sqrt(np.mean(z ** 2)):.3f}, beyond 2 {np.mean(z > 2):.3f}, "
              f"beyond 3 {int(np.sum(z > 3))} of {len(z)}")
    # 280 z values, correlated within a draw: two-sided, the RMS known to about 10 %
    assert 0.6 < rms < 1.1 and rms < np.sqrt(np.mean(z_plugin ** 2))
    assert np.mean(z_marginal > 2) < 0.0455 < np.mean(z_plugin > 2)
    assert np.sum(z_marginal > 3) < np.sum(z_plugin > 3)


def test_marginalised_tau_adds_little_where_the_data_pin_tau_down(rng):
    # 40 steps of a rough path in angle: the posterior of tau is narrow, and the extra
    # covariance is a small part of the covariance at the plug-in tau
    n = 40
    fx = np.geomspace(2300.0, 23000.0, n)
    u = np.log(fx)
    angle = np.cumsum(np.cumsum(rng.normal(0, 0.02, n))) * (u[1] - u[0]) ** 2
    q = 25.0 + fx * angle + rng.normal(0, 0.05, n)
    chain = (q / fx, 0.05 / fx, u, 1.0 / fx)
    model = PathPrior("angle2", 2, *pooled_prior_strength([chain], 2))
    extra = marginal_tau(model, [chain])[0]
    assert model.tau_interval[1] / model.tau_interval[0] < 2.5
    _, P = path_posterior(chain, 2, model.tau)
    assert np.trace(extra) < 0.1 * np.trace(P)


def test_a_chain_the_free_terms_take_whole_has_no_prior_strength(rng):
    # three steps under the angular prior: the offset and the line in angle take all of them,
    # so the data say nothing of tau (not "at its lower bound")
    fx = np.geomspace(2300.0, 9000.0, 3)
    q = 640.0 + rng.normal(0, 1.0, 3)
    tau, at_bound = pooled_prior_strength([(q / fx, 0.5 / fx, np.log(fx), 1.0 / fx)], 2)
    assert tau == np.inf and not at_bound
    # a fourth step leaves one difference: a finite tau
    fx = np.geomspace(2300.0, 9000.0, 4)
    q = 640.0 + rng.normal(0, 1.0, 4)
    assert np.isfinite(pooled_prior_strength([(q / fx, 0.5 / fx, np.log(fx), 1.0 / fx)], 2)[0])


def test_a_stack_of_taus_gives_each_taus_own_precision_and_path(rng):
    """The held-out predictions and the marginal covariance take the restricted precision and
    the path posterior for many ``tau`` in one stacked call: each slice is that ``tau``'s own,
    on a correlated chain too."""
    from zoomcalib.calibrate.zoommodel import _restricted_precision, path_posterior

    n = 9
    u = np.sort(rng.uniform(0.0, 3.0, n))
    values = np.cumsum(rng.normal(0.0, 1.0, n))
    sd = rng.uniform(0.2, 1.0, n)
    taus = np.geomspace(0.01, 10.0, 7)
    for noise in (sd, np.outer(sd, sd) * (0.3 + 0.7 * np.eye(n))):
        S = noise if noise.ndim == 2 else np.diag(noise**2)
        stack = _restricted_precision(S, u, 2, taus)
        means, covs = path_posterior((values, noise, u), 2, taus)
        for k, tau in enumerate(taus):
            np.testing.assert_allclose(stack[k], _restricted_precision(S, u, 2, tau),
                                       rtol=1e-12, atol=1e-12)
            m, P = path_posterior((values, noise, u), 2, tau)
            np.testing.assert_allclose(means[k], m, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(covs[k], P, rtol=1e-12, atol=1e-12)
