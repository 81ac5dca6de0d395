r"""How a per-step intrinsic follows the zoom: a difference prior of its path in ``u = log fx``,
its strength by restricted maximum likelihood, and the choice of model by held-out steps.

Difference prior of order ``k``
-------------------------------
With the steps sorted by ``u``, the ``k``-th divided differences scaled by ``k!``,

.. math::

    (D_k q)_i = k!\, q[u_i, \dots, u_{i+k}],\qquad
    q[u_i..u_{i+k}] = \frac{q[u_{i+1}..u_{i+k}] - q[u_i..u_{i+k-1}]}{u_{i+k} - u_i},

equal the ``k``-th derivative on a polynomial of degree ``k`` (``D_2`` on a quadratic is its
second derivative). The prior ``D_k q ~ N(0, tau^2 I)`` leaves the polynomials of degree
``k - 1`` free (its null space). Written as a model of the values,
``q = A beta + tau N (D_k N)^{-1} w``, ``w ~ N(0, I)``, ``A`` the Vandermonde of degree ``k - 1``
in ``u`` with a flat prior on ``beta``, ``N`` an orthonormal basis of the complement of ``A``.

A free offset
-------------
A chain may carry an ``offset`` direction ``w`` (n,): the values are then ``w q`` for a path
``q`` whose constant offset is free. With ``w = 1 / fx`` this is the prior on the angular
principal point (:mod:`zoomcalib.calibrate.zoomwide`): ``(cx - c) / fx`` is smooth in ``u``
for an unknown ``c``, so ``cx = c + fx (a + b u)`` costs nothing. ``w`` joins the fixed
effects ``A``; the rough part keeps the shape of the difference prior. In the adjustment the
offset is integrated out with a flat prior (:func:`prior_operator`).

Candidates
----------
``prior2``, ``prior3``
    ``D_k q ~ N(0, tau^2)``, ``k = 2, 3``, ``tau`` by REML (:func:`pooled_prior_strength`).
``poly1``, ``poly2``, ``poly3``
    A polynomial of degree ``d`` in ``u``: the prior of order ``d + 1`` with ``tau -> 0``
    (in the adjustment ``tau`` is 1e-2 of the noise's own RMS difference: the path follows the
    polynomial to far below its noise).

Held-out choice
---------------
From per-step estimates ``q_hat = q + e``, ``e ~ N(0, S)`` (``S`` their joint covariance, e.g.
of a zoom-wide solve without the prior), each candidate predicts every step ``i`` from the
others: with ``C = S + tau^2 G G^T`` (``G = N (D_k N)^{-1}``) and the restricted precision
``Q = C^{-1} - C^{-1} A (A^T C^{-1} A)^{-1} A^T C^{-1}`` (``beta`` integrated out), the
prediction of ``q_hat_i`` from ``q_hat_{-i}`` is Gaussian with residual ``(Q q_hat)_i / Q_ii``
and variance ``1 / Q_ii`` (the conditional of a Gaussian, prediction variance included). For a
prior, ``tau`` is re-estimated without step ``i``. The score is the sum of the log predictive
densities over the steps (and chains). ``prior2`` is kept unless another candidate's score is
higher by more than 2 standard errors of the difference (:func:`select_zoom_model`).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import factorial

import numpy as np
import scipy.linalg

__all__ = ["CANDIDATES", "PathPrior", "divided_difference", "second_difference", "prior_operator",
           "prior_strength", "pooled_prior_strength", "tau_posterior", "path_posterior",
           "marginal_tau", "held_out_densities", "held_out_score", "held_out_residuals",
           "path_between", "kernel_energy", "select_zoom_model"]

#: Candidate models: name -> (difference order, REML tau (True) or a polynomial (False)).
CANDIDATES: dict[str, tuple[int, bool]] = {
    "prior2": (2, True), "prior3": (3, True),
    "poly1": (2, False), "poly2": (3, False), "poly3": (4, False),
}
#: The tau of a polynomial in the adjustment, as a fraction of the noise's RMS difference.
POLY_TAU_FRACTION = 1e-2
#: Another candidate replaces ``prior2`` when its held-out score is higher by this many
#: standard errors of the difference (:func:`select_zoom_model`).
MARGIN = 2.0


@dataclass
class PathPrior:
    """The smoothness prior chosen for one parameter's path: ``name`` (a key of
    :data:`CANDIDATES`), difference ``order``, ``tau`` (units of the parameter per
    ``u^order``; ``inf``: no prior),
    ``tau_at_bound`` (REML's maximum at the grid's lower end) and the held-out ``scores`` (log
    predictive density) of every candidate; ``tau_kind`` says where ``tau`` came from. With
    ``tau`` marginalised (:func:`marginal_tau`): ``tau`` is its posterior median, ``tau_reml``
    the REML value and ``tau_interval`` the posterior's 5 % and 95 % quantiles."""

    name: str
    order: int
    tau: float
    tau_at_bound: bool = False
    scores: dict[str, float] | None = None
    tau_reml: float | None = None
    tau_interval: tuple[float, float] | None = None
    tau_kind: str = "restricted maximum likelihood"

    def to_dict(self) -> dict:
        """JSON-ready; a candidate that could not predict a step has the score None."""
        scores = {k: (float(v) if np.isfinite(v) else None) for k, v in (self.scores or {}).items()}
        out = {"model": self.name, "order": self.order,
               "tau": float(self.tau) if np.isfinite(self.tau) else None,
               "tau_at_lower_bound": bool(self.tau_at_bound), "held_out_log_density": scores,
               "tau_kind": self.tau_kind}
        if self.tau_interval is not None:
            out.update(tau_reml=self.tau_reml, tau_interval_90=list(self.tau_interval))
        return out


def divided_difference(u: np.ndarray, order: int = 2) -> np.ndarray:
    """``(n - k, n)`` matrix of the ``k``-th divided differences times ``k!`` over increasing
    abscissae ``u`` (module docstring)."""
    u = np.asarray(u, float)
    n = len(u)
    F = np.eye(n)
    for k in range(1, order + 1):
        F = (F[1:] - F[:-1]) / (u[k:] - u[:-k])[:, None] if n > k else np.zeros((0, n))
    return factorial(order) * F


def second_difference(u: np.ndarray) -> np.ndarray:
    """``(n - 2, n)`` second divided differences times 2 (:func:`divided_difference`)."""
    return divided_difference(u, 2)


def prior_operator(u: np.ndarray, order: int = 2, weight: np.ndarray | None = None,
                   offset: bool = True) -> np.ndarray:
    """Rows ``R`` (n - k, n) of the difference prior ``R q ~ N(0, tau^2 I)`` on a path ``q``
    over increasing ``u``: ``D_k`` itself, or with a ``weight`` ``w`` (n,) the differences of
    ``w q``: ``D_k diag(w)``, or with ``offset`` a free constant offset of ``q`` integrated out
    (flat prior): ``R = P D_k diag(w)``, ``P`` the projector off ``a = D_k w``.
    """
    D = divided_difference(u, order)
    if weight is None or len(D) == 0:
        return D
    Dw = D * np.asarray(weight, float)[None, :]
    if not offset:
        return Dw
    a = Dw.sum(axis=1)
    if not np.any(a):
        return Dw
    return Dw - np.outer(a, a @ Dw) / (a @ a)


def _null_basis(u: np.ndarray, order: int, offset: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (n, k): the polynomials of degree < ``order`` in ``u`` (centred, scaled), and the
    ``offset`` direction when given and not among them; ``N`` an orthonormal basis of the
    complement of ``A``."""
    t = (u - u.mean()) / max(np.ptp(u), 1e-12)
    A = np.vander(t, order, increasing=True)
    if offset is not None:
        w = np.asarray(offset, float) / np.linalg.norm(offset)
        if np.linalg.norm(w - A @ np.linalg.lstsq(A, w, rcond=None)[0]) > 1e-9:
            A = np.column_stack([A, w])
    return A, scipy.linalg.null_space(A.T)


def _rough_basis(u: np.ndarray, order: int) -> np.ndarray:
    """``G = N (D_k N)^{-1}`` (n, n - k): the path's rough part ``q = G z`` has ``D_k q = z``."""
    _, N = _null_basis(u, order)
    return N @ np.linalg.inv(divided_difference(u, order) @ N)


def _unpack(chain: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(values, sd, u[, offset])`` of a chain as arrays (``offset`` None when absent)."""
    values, sd, u = chain[:3]
    offset = chain[3] if len(chain) > 3 else None
    return (np.asarray(values, float), sd, np.asarray(u, float),
            None if offset is None else np.asarray(offset, float))


def _as_covariance(values: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """``sd`` as an (n, n) covariance: a diagonal of squares when given (n,) sigmas (unusable
    sigmas replaced by one larger than every value)."""
    sd = np.asarray(sd, float)
    if sd.ndim == 2:
        return sd
    sd = np.where(np.isfinite(sd) & (sd > 0), sd, np.nanmax(np.abs(values)) + 1.0)
    return np.diag(sd ** 2)


def prior_strength(values: np.ndarray, sd: np.ndarray, u: np.ndarray, order: int = 2
                   ) -> tuple[float, bool]:
    """Restricted maximum-likelihood ``tau`` of the difference prior of ``order``.

    Model: ``q_hat = q + e``, ``e ~ N(0, S)`` with ``S = diag sd^2`` (or ``sd`` itself when it
    is an ``(n, n)`` covariance), ``D_k q ~ N(0, tau^2 I)`` with a flat prior on the
    polynomials of degree ``k - 1`` in ``u`` (the null space of ``D_k``). With ``N`` an
    orthonormal basis of their complement, ``y = N^T q_hat ~ N(0, tau^2 (D N)^{-1} (D N)^{-T}
    + N^T S N)``; ``tau`` maximises that likelihood over a log grid.

    Returns
    -------
    tau : float
        In units of ``q`` per ``u^k``; ``inf`` (no prior) when no chain has more steps than
        its free polynomial (and offset) take.
    at_bound : bool
        The maximum lies at the grid's lower end: the data are as smooth as their noise shows.
    """
    return pooled_prior_strength([(values, sd, u)], order)


def pooled_prior_strength(chains: list[tuple], order: int = 2) -> tuple[float, bool]:
    """:func:`prior_strength` of one ``tau`` shared by several chains ``(values, sd, u[,
    offset])`` (e.g. the zoom-in and the zoom-out sweep of one lens): the chains' restricted
    likelihoods add. ``offset``: module docstring, "A free offset"."""
    grid, loglik = _restricted_loglik(chains, order)
    if grid is None:
        return float("inf"), False
    best = int(np.argmax(loglik))
    return float(grid[best]), best == 0


def _restricted_loglik(chains: list[tuple], order: int
                       ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The log grid of ``tau`` and the pooled restricted log likelihood on it; ``(None,
    None)`` when no chain has more than ``order`` steps."""
    terms = [_restricted_terms(c, order) for c in chains if len(c[0]) > order]
    terms = [t for t in terms if len(t[0])]  # a chain whose fixed effects take every step
    if not terms:
        return None, None
    top = max(max(t[3] for t in terms), 1e-12)
    # below 1 % of the noise's own differences the likelihood is flat: the grid stops
    # there (a smaller tau only makes the problem ill-conditioned)
    bottom = max(min(t[4] for t in terms) * 1e-2, top * 1e-6)
    grid = np.geomspace(bottom, max(top * 1e4, bottom * 1e2), 201)
    loglik = np.zeros(len(grid))
    for y, shape, noise, *_ in terms:
        loglik += _gauss_loglik(y, (grid * grid)[:, None, None] * shape + noise)
    return grid, loglik


def tau_posterior(chains: list[tuple], order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    r"""The posterior of ``tau`` on the grid of :func:`pooled_prior_strength`: the restricted
    likelihood times a half-Cauchy prior ``p(tau) \propto 1 / (1 + (tau / s)^2)`` whose scale
    ``s`` is the noise's own RMS difference (:func:`noise_roughness`, the largest over the
    chains): a path smoother than its noise can show is as plausible as one as rough as it, and
    rougher paths must be shown by the data (Gelman, Bayesian Anal. 2006, for the scale of a
    hierarchical variance). Returns the grid and the weights (sum 1); both empty when no chain
    is long enough."""
    grid, loglik = _restricted_loglik(chains, order)
    if grid is None:
        return np.zeros(0), np.zeros(0)
    scale = max(noise_roughness(c[1], c[2], order) for c in chains if len(c[0]) > order)
    # the grid is uniform in log tau: d tau = tau d log tau
    logpost = loglik - np.log1p((grid / max(scale, 1e-300)) ** 2) + np.log(grid)
    weight = np.exp(logpost - logpost.max())
    return grid, weight / weight.sum()


def path_posterior(chain: tuple, order: int, tau: float | np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mean (n,) and covariance (n, n) of the true path of a chain ``(values, sd, u[,
    offset])`` given its estimates at a fixed ``tau``: with the restricted precision ``Q``
    (module docstring, "Held-out choice"), ``m = q_hat - S Q q_hat`` and ``P = S - S Q S``
    (the fixed effects integrated out under their flat prior). For ``tau`` of shape (T,), the
    stacks (T, n) and (T, n, n), one per ``tau``."""
    values, sd, u, offset = _unpack(chain)
    S = _as_covariance(values, sd)
    Q = _restricted_precision(S, u, order, tau, offset)
    SQ = S @ Q
    return values - SQ @ values, S - SQ @ S


def marginal_tau(model: PathPrior, chains: list[tuple]) -> list[np.ndarray]:
    r"""Marginalise the ``tau`` of a REML prior ``model`` (in place) over :func:`tau_posterior`
    and return, per chain, the covariance (n, n) to add to the path's covariance at the new
    plug-in ``tau`` so that it covers the uncertainty of ``tau`` itself.

    The plug-in becomes the posterior median (``model.tau``; the REML value and the 90 %
    interval are kept in the model). The expected squared error of the plug-in mean ``m(tau)``
    is ``E[P(t)] + E[(m(t) - m(tau))(m(t) - m(tau))^T]`` over the posterior of ``t``
    (:func:`path_posterior`; the law of total variance about ``m(tau)``; Kass & Steffey, JASA
    1989, for this correction of an empirical-Bayes covariance). Its difference from
    ``P(tau)`` is returned with negative eigenvalues set to zero. With 7 steps a second
    difference prior has 4-5 differences to learn ``tau`` from: REML can sit at its lower bound
    on a path that the noise cannot tell from a straight line, while the data allow paths
    rough enough to move the long end by more than its sigma.
    """
    grid, weight = tau_posterior(chains, model.order)
    if not len(grid) or not np.isfinite(model.tau):
        return [np.zeros((len(c[0]),) * 2) for c in chains]
    cdf = np.cumsum(weight)
    model.tau_reml = float(model.tau)
    model.tau_interval = tuple(float(grid[np.searchsorted(cdf, p)]) for p in (0.05, 0.95))
    model.tau = float(grid[np.searchsorted(cdf, 0.5)])
    model.tau_kind = "posterior median"
    keep = weight >= 1e-6 * weight.max()
    out = []
    for chain in chains:
        n = len(chain[0])
        if n <= model.order:
            out.append(np.zeros((n, n)))
            continue
        m0, P0 = path_posterior(chain, model.order, model.tau)
        second_moment = np.zeros((n, n))
        means, covs = path_posterior(chain, model.order, grid[keep])
        for m, P, w in zip(means, covs, weight[keep], strict=True):
            second_moment += w * (P + np.outer(m - m0, m - m0))
        extra = second_moment / weight[keep].sum() - P0
        vals, vecs = np.linalg.eigh(0.5 * (extra + extra.T))
        out.append((vecs * np.clip(vals, 0.0, None)) @ vecs.T)
    return out


def noise_roughness(sd: np.ndarray, u: np.ndarray, order: int) -> float:
    """RMS of ``D_k e`` for noise ``e ~ N(0, S)`` (``sd`` as in :func:`prior_strength`)."""
    S = _as_covariance(np.zeros(len(u)), sd)
    D = divided_difference(np.asarray(u, float), order)
    return float(np.sqrt(np.mean(np.diag(D @ S @ D.T)))) if len(D) else 0.0


def _restricted_terms(chain: tuple, order: int):
    """``y = N^T q_hat``, the prior's shape ``N^T G G^T N`` (:func:`_rough_basis`), the noise
    ``N^T S N``, the scale of the values' roughness and the RMS difference of the noise alone,
    of one chain (see :func:`prior_strength`)."""
    values, sd, u, offset = _unpack(chain)
    S = _as_covariance(values, sd)
    _, N = _null_basis(u, order, offset)
    NG = N.T @ _rough_basis(u, order)
    scale = float(np.std(values)) / max(np.ptp(u), 1e-9) ** order
    return N.T @ values, NG @ NG.T, N.T @ S @ N, scale, noise_roughness(S, u, order)


def _gauss_loglik(y: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Log density of ``y`` (k,) under ``N(0, cov)`` up to a constant, for each of a stack of
    covariances ``cov`` (..., k, k): shape ``(...)`` (small matrices: batched NumPy)."""
    c = np.linalg.cholesky(cov)
    z = np.linalg.solve(c, np.broadcast_to(y[:, None], c.shape[:-1] + (1,)))[..., 0]
    return (-np.sum(np.log(np.diagonal(c, axis1=-2, axis2=-1)), axis=-1)
            - 0.5 * (z[..., None, :] @ z[..., :, None])[..., 0, 0])


def _restricted_precision(S: np.ndarray, u: np.ndarray, order: int, tau: float | np.ndarray,
                          offset: np.ndarray | None = None,
                          bases: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``Q = C^{-1} - C^{-1} A (A^T C^{-1} A)^{-1} A^T C^{-1}``, ``C = S + tau^2 G G^T``
    (module docstring, "Held-out choice"), (n, n); for ``tau`` of shape (T,), the stack
    (T, n, n), one per ``tau``. ``bases``: ``(A, G)`` at ``tau = 1`` of
    :func:`_precision_bases`, which do not depend on ``tau`` (given for many ``tau``)."""
    A, G = _precision_bases(u, order, offset) if bases is None else bases
    G = G * np.asarray(tau, float)[..., None, None]
    C_inv = np.linalg.inv(S + G @ np.swapaxes(G, -1, -2))
    CA = C_inv @ A
    return C_inv - CA @ np.linalg.solve(A.T @ CA, np.swapaxes(CA, -1, -2))


def _precision_bases(u: np.ndarray, order: int, offset: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The fixed effects' columns ``A`` (:func:`_null_basis`) and the rough basis ``G``
    (:func:`_rough_basis`) of :func:`_restricted_precision`."""
    return _null_basis(u, order, offset)[0], _rough_basis(u, order)


def _loo_density(values: np.ndarray, S: np.ndarray, u: np.ndarray, order: int, tau: float,
                 i: int, offset: np.ndarray | None = None) -> float:
    """Log density of step ``i``'s value predicted from the others (module docstring)."""
    Q = _restricted_precision(S, u, order, tau, offset)
    q_ii = Q[i, i]
    resid = (Q @ values)[i] / q_ii
    return float(0.5 * np.log(q_ii / (2 * np.pi)) - 0.5 * resid * resid * q_ii)


def held_out_densities(chains: list[tuple], order: int, reml: bool) -> np.ndarray | None:
    """The leave-one-step-out log predictive density of every step of every chain under a
    candidate (module docstring); None when a chain is too short to predict a step."""
    out = []
    for chain in chains:
        values, sd, u, offset = _unpack(chain)
        S, n = _as_covariance(values, sd), len(values)
        if n < order + (2 if reml else 1) + (offset is not None):
            return None
        for i in range(n):
            keep = np.arange(n) != i
            rest = (values[keep], S[np.ix_(keep, keep)], u[keep])
            rest += () if offset is None else (offset[keep],)
            tau = pooled_prior_strength([rest], order)[0] if reml else 0.0
            out.append(_loo_density(values, S, u, order, tau, i, offset))
    return np.array(out)


def held_out_residuals(chain: tuple, order: int, tau: float, reml: bool,
                       marginal: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """Each step of a chain ``(values, sd, u[, offset])`` predicted from the others under the
    difference prior of ``order``: the residual (value minus prediction) and the predictive
    1-sigma ``1 / sqrt(Q_ii)`` (the step's own noise included; module docstring, "Held-out
    choice"), both (n,) in the chain's units. ``tau`` is used as given, or with ``reml``
    estimated again without the step. None when the chain is too short to predict a step.

    With ``reml`` and ``marginal`` the prediction is averaged over the posterior of ``tau``
    given the other steps (:func:`tau_posterior`) instead of taken at its REML value: the
    residual is the posterior mean of ``r(t) = (Q(t) q)_i / Q(t)_ii`` and the variance
    ``E[1 / Q(t)_ii] + Var[r(t)]`` (the law of total variance, as in :func:`marginal_tau`).
    From the few differences of a short chain REML can sit at a ``tau`` far smoother than the
    data allow, and a plug-in prediction is then too sure of itself.

    Examples
    --------
    A straight path with noise 0.1: every step is predicted within a few sigmas.

    >>> import numpy as np
    >>> u = np.linspace(0.0, 2.0, 8)
    >>> noise = 0.1 * np.array([1, -1, 0.5, 0, -0.5, 1, 0, -1])
    >>> resid, sd = held_out_residuals((3 + 2 * u + noise, np.full(8, 0.1), u), 2, 0.0, False)
    >>> bool(np.all(np.abs(resid / sd) < 3))
    True
    """
    values, sd, u, offset = _unpack(chain)
    S, n = _as_covariance(values, sd), len(values)
    if n < order + (2 if reml else 1) + (offset is not None):
        return None
    resid, spread = np.empty(n), np.empty(n)
    bases = _precision_bases(u, order, offset)
    for i in range(n):
        taus, weights = np.array([tau]), np.ones(1)
        if reml:
            keep = np.arange(n) != i
            rest = [(values[keep], S[np.ix_(keep, keep)], u[keep])
                    + (() if offset is None else (offset[keep],))]
            taus, weights = tau_posterior(rest, order) if marginal else (np.zeros(0),) * 2
            if len(taus):
                keep_t = weights >= 1e-6 * weights.max()
                taus, weights = taus[keep_t], weights[keep_t]
            else:  # the plug-in (also where the other steps give no posterior)
                taus, weights = np.array([pooled_prior_strength(rest, order)[0]]), np.ones(1)
        Q = _restricted_precision(S, u, order, taus, offset, bases)  # (T, n, n)
        r_t, var_t = (Q @ values)[:, i] / Q[:, i, i], 1.0 / Q[:, i, i]
        weights = weights / weights.sum()
        resid[i] = weights @ r_t
        spread[i] = np.sqrt(weights @ var_t + weights @ (r_t - resid[i]) ** 2)
    return resid, spread


def path_between(u: np.ndarray, u_new: float, order: int, tau: float,
                 offset: np.ndarray | None = None, offset_new: float | None = None
                 ) -> tuple[np.ndarray, float]:
    r"""The path at a new abscissa ``u_new`` given its values ``v`` (n,) at increasing ``u``
    (n,), under the difference prior of ``order`` with strength ``tau``: weights ``lam`` (n,)
    and variance ``V`` with ``v_new | v ~ N(lam^T v, V)``.

    The difference prior describes the path on the steps' grid only; between the steps it is
    read as the continuous process whose ``k``-th derivative is white noise of intensity
    ``sigma^2`` (an integrated Wiener process; a cubic smoothing spline's prior for ``k = 2``),
    whose scaled divided differences have the prior's variance on that grid: a row's
    ``k! f[u_i..u_{i+k}] = \int f^{(k)}(t) M_i(t) dt`` (``M_i`` its Peano kernel, a B-spline of
    unit integral), so ``tau^2 = sigma^2 mean_i \int M_i^2`` (:func:`kernel_energy`). The
    process has the generalised covariance ``K(d) = (-1)^k sigma^2 |d|^{2k-1} / (2 (2k-1)!)``
    on the increments that annihilate the polynomials of degree ``< k`` (and the ``offset``
    direction ``w``, with ``offset_new`` its value at ``u_new``), and ``lam`` is the universal
    kriging predictor of the steps: ``[K A; A^T 0] [lam; mu] = [k_*; a_*]``, ``V = lam^T K lam
    - 2 lam^T k_*``. At a step ``V`` is 0; between them it grows as the gap to the power
    ``2k - 1``; with ``tau = 0`` (a polynomial) it is 0 and ``lam`` interpolates by splines of
    degree ``2k - 1``. (Read as a prior on a finer grid, the difference prior itself would
    shrink ``V`` with the gap too fast: on integrated Wiener paths with ``tau`` by REML from
    10 steps, its points between the steps missed by 1.6-2.2 sigma RMS, 7-11 % beyond 3, and
    this model's by 1.1-1.3, 1-4 %: ``benchmarks/bench_zoom_path.py --wiener 8``.)

    Examples
    --------
    Halfway along a straight path, by the second-difference prior:

    >>> import numpy as np
    >>> lam, var = path_between(np.array([0.0, 1.0, 2.0, 3.0]), 1.5, 2, 0.0)
    >>> print(round(float(lam @ np.array([1.0, 3.0, 5.0, 7.0])), 6), var)
    4.0 0.0
    """
    u = np.asarray(u, float)
    n = len(u)
    hit = np.flatnonzero(np.abs(u - u_new) <= 1e-12 * max(1.0, float(np.ptp(u))))
    if len(hit):
        lam = np.zeros(n)
        lam[hit[0]] = 1.0
        return lam, 0.0
    centre, span = float(u.mean()), max(float(np.ptp(u)), 1e-12)
    t, t_new = (u - centre) / span, (u_new - centre) / span
    A = np.vander(t, order, increasing=True)
    a = np.vander(np.array([t_new]), order, increasing=True)[0]
    if offset is not None:
        A, a = np.column_stack([A, offset]), np.append(a, float(offset_new))
    p = A.shape[1]
    if n <= p or np.linalg.matrix_rank(A / np.linalg.norm(A, axis=0)) < p:
        raise np.linalg.LinAlgError(f"{n} steps do not determine the path at u = {u_new:g} "
                                    f"under a prior of order {order}")

    def gc(d: np.ndarray) -> np.ndarray:  # in units of span^(2k-1) sigma^2
        return ((-1) ** order * np.abs(d) ** (2 * order - 1)
                / (2 * factorial(2 * order - 1)))

    K, k = gc(t[:, None] - t[None, :]), gc(t - t_new)
    system = np.block([[K, A], [A.T, np.zeros((p, p))]])
    lam = np.linalg.solve(system, np.append(k, a))[:n]
    var = float(lam @ K @ lam - 2 * lam @ k) * span ** (2 * order - 1)
    sigma2 = float(tau) ** 2 / float(np.mean(kernel_energy(u, order)))
    return lam, max(var, 0.0) * sigma2


def kernel_energy(u: np.ndarray, order: int) -> np.ndarray:
    r"""``\int M_i^2`` (n - k,) of each row of :func:`divided_difference` over increasing ``u``:
    ``M_i(t) = (D_k (u - t)_+^{k-1})_i / (k-1)!``, the Peano kernel with
    ``(D_k f)_i = \int f^{(k)} M_i`` (units ``1 / u``). Equal spacing ``h``: ``2 / (3 h)`` for
    ``k = 2``.

    >>> print(round(float(kernel_energy(np.array([0.0, 0.5, 1.0]), 2)[0]), 3))
    1.333
    """
    u = np.asarray(u, float)
    D = divided_difference(u, order)
    t = np.linspace(u[0], u[-1], 4001)
    M = D @ (np.clip(u[:, None] - t[None, :], 0.0, None) ** (order - 1)) / factorial(order - 1)
    return np.trapezoid(M**2, t, axis=1)


def held_out_score(chains: list[tuple], order: int, reml: bool) -> float:
    """Sum of :func:`held_out_densities`; ``-inf`` when a chain is too short."""
    dens = held_out_densities(chains, order, reml)
    return -np.inf if dens is None else float(np.sum(dens))


def select_zoom_model(chains: list[tuple], candidates: tuple[str, ...] = tuple(CANDIDATES)
                      ) -> PathPrior:
    """The zoom model of one parameter from its chains ``(values, sd, u[, offset])`` (module
    docstring).

    ``prior2`` unless another candidate beats it clearly: by more than ``MARGIN`` standard
    errors of the summed step-wise difference ``d_i`` of their held-out log densities
    (``se = sqrt(n var d)``; Vehtari, Gelman & Gabry, Stat. Comput. 2017); of those that do, the
    one with the highest score. A polynomial is exact where a prior only shrinks, and a prior of
    order 3 leaves a quadratic free and has its ``tau`` from fewer differences: chosen on a
    near tie they claim a precision the data do not support. ``tau``: by REML for a prior,
    1e-2 of the noise's RMS difference for a polynomial.
    """
    dens = {name: held_out_densities(chains, *CANDIDATES[name]) for name in candidates}
    scores = {k: (-np.inf if d is None else float(np.sum(d))) for k, d in dens.items()}
    best = "prior2"
    if dens.get("prior2") is not None:
        better = [k for k in candidates if _clearly_better(dens[k], dens["prior2"])]
        best = max(better, key=lambda k: scores[k], default="prior2")
    order, reml = CANDIDATES[best]
    if reml:
        tau, at_bound = pooled_prior_strength(chains, order)
    else:
        usable = [noise_roughness(c[1], c[2], order) for c in chains if len(c[2]) > order]
        tau, at_bound = POLY_TAU_FRACTION * min(usable), False
    kind = "restricted maximum likelihood" if reml else "polynomial (1e-2 of the noise)"
    return PathPrior(best, order, tau, at_bound, scores, tau_kind=kind)


def _clearly_better(dens: np.ndarray | None, than: np.ndarray) -> bool:
    """The summed difference of the step-wise log densities exceeds ``MARGIN`` of its
    standard errors."""
    if dens is None:
        return False
    d = dens - than
    return float(np.sum(d)) > MARGIN * float(np.sqrt(len(d) * np.var(d, ddof=1)))
