"""The noise of a per-zoom principal-point table, estimated from the table itself.

Each row's principal point scatters, per axis, with the variance

    v_i = s^2 m_i + p^2 q_i                                               (px^2)

- ``m_i`` the table's own measurement variance, ``(sd_cx^2 + sd_cy^2) / 2``, and ``s`` a common
  scale of the reported sigmas (calibration sigmas are often optimistic or pessimistic by a
  common factor). A table without sigmas has ``m_i = 1`` and ``s`` is then the sd in px;
- ``q_i`` the shape of the random play of the lens groups over the zoom range (the tolerance
  file's play through the lens's sensitivities; without a lens model ``(fx_i / median fx)^2``:
  a decentre's image shift grows about like the focal length), and ``p`` its scale: 1 means the
  tolerance file's play.

``(log s, log p)`` are estimated by restricted maximum likelihood (REML: the likelihood of the
residuals with the model's linear parameters integrated out, which does not shrink the
variances by the parameters fitted), with weak Gaussian priors on ``log s`` and ``log p``
centred on the reported sigmas and the tolerance file (1-sigma :data:`PRIOR_SD_LOG`, a
factor of 3). The negative log posterior is

    L(s, p) = 1/2 [ sum_j log v_j + log det(A^T V^-1 A) + r^T V^-1 r ]
              + (log s)^2 / (2 t^2) + (log p)^2 / (2 t^2)

over the 2N residuals ``r = y - A beta_hat`` of the generalised least-squares fit (``A`` the
(2N, K) design, ``V = diag(v)`` repeated per axis, ``t = PRIOR_SD_LOG``). A term without prior
(no sigmas, no lens model) has a flat prior on its log. The 1-sigma of ``log s`` and ``log p``
come from the curvature of ``L`` at its minimum.

Rows whose measurements are correlated (the steps of one adjustment share its aspect ratio,
its boards and its print) carry their correlation ``R`` (2N, 2N); the measured part is then
``s^2 D R D`` (``D = diag(sqrt(m))`` per axis) and the play stays independent:

    V = s^2 D R D + p^2 diag(q),   sum_j log v_j -> log det V,   r^T V^-1 r as written

(:class:`RowWeights` holds ``V`` by its Cholesky factor). With ``R = I`` this is the diagonal
case, computed as before.

References
----------
H. D. Patterson, R. Thompson, "Recovery of inter-block information when block sizes are
unequal", Biometrika 58 (1971): REML.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import minimize

__all__ = ["NoiseShape", "NoiseFit", "RowWeights", "estimate_noise", "PRIOR_SD_LOG", "gls"]

#: 1-sigma of the priors on log s and log p: a factor of 3 either way
PRIOR_SD_LOG = float(np.log(3.0))
#: bounds of log s and log p in the search
LOG_BOUNDS = (-9.0, 7.0)
#: singular values below this fraction of the largest count as zero
RCOND = 1e-10


@dataclass(frozen=True)
class RowWeights:
    """The inverse noise covariance of the 2N rows ``(cx_0, cy_0, cx_1, ...)`` of a weighted
    least-squares fit: ``w`` (2N,) the inverse of each row's variance, and ``cov`` (2N, 2N) the
    full covariance ``V`` when the rows are correlated (None: ``V = diag(1 / w)``).

    Examples
    --------
    >>> import numpy as np
    >>> full = RowWeights.full(np.array([[4.0, 2.0], [2.0, 4.0]]))
    >>> round(full.chi2(np.array([1.0, 1.0])), 6), round(full.log_det(), 6)
    (0.333333, 2.484907)
    """

    w: np.ndarray
    cov: np.ndarray | None = None
    chol: np.ndarray | None = None

    @classmethod
    def full(cls, cov: np.ndarray) -> RowWeights:
        """Weights of the covariance ``cov`` (2N, 2N); LinAlgError when it is not positive
        definite."""
        cov = np.asarray(cov, float)
        return cls(1.0 / np.diag(cov), cov, np.linalg.cholesky(cov))

    def whiten(self, x: np.ndarray) -> np.ndarray:
        """``L^-1 x`` for ``V = L L^T`` (``x`` (2N,) or (2N, K)): rows of unit, independent
        noise."""
        if self.cov is None:
            sw = np.sqrt(self.w)
            return x * (sw if x.ndim == 1 else sw[:, None])
        return solve_triangular(self.chol, x, lower=True, check_finite=False)

    def chi2(self, r: np.ndarray) -> float:
        """``r^T V^-1 r``."""
        if self.cov is None:
            return float(np.sum(self.w * r ** 2))
        return float(np.sum(self.whiten(r) ** 2))

    def normal(self, A: np.ndarray) -> np.ndarray:
        """``A^T V^-1 A`` (K, K)."""
        if self.cov is None:
            return (A * self.w[:, None]).T @ A
        white = self.whiten(A)
        return white.T @ white

    def log_det(self) -> float:
        """``log det V``."""
        if self.cov is None:
            return float(np.sum(np.log(1.0 / self.w)))
        return float(2.0 * np.sum(np.log(np.diag(self.chol))))

    def subset(self, keep: np.ndarray) -> RowWeights:
        """The weights of the rows ``keep`` (a boolean mask or indices) alone."""
        if self.cov is None:
            return RowWeights(self.w[keep])
        return RowWeights.full(self.cov[np.ix_(keep, keep)])

    def stacked(self, w_more: np.ndarray) -> RowWeights:
        """These rows followed by independent ones of weights ``w_more``."""
        w_more = np.asarray(w_more, float)
        if self.cov is None:
            return RowWeights(np.concatenate([self.w, w_more]))
        n, m = len(self.w), len(w_more)
        cov = np.zeros((n + m, n + m))
        cov[:n, :n], cov[n:, n:] = self.cov, np.diag(1.0 / w_more)
        return RowWeights.full(cov)


@dataclass(frozen=True)
class NoiseShape:
    """The two variance shapes of the rows and whether each has a prior.

    Attributes
    ----------
    measured_var : (N,) ndarray
        ``m_i``, px^2 per axis (ones when the table has no sigmas).
    play_var : (N,) ndarray
        ``q_i``, px^2 per axis at ``p = 1``.
    sd_prior, play_prior : bool
        Whether ``log s`` (the table has sigmas) and ``log p`` (a tolerance file) have priors.
    play_source : str
        Where ``q`` comes from, for the report.
    correlation : (2N, 2N) ndarray or None
        ``R``, the correlation of the rows' measured principal points, ordered
        ``(cx_0, cy_0, cx_1, ...)`` (None: independent rows).
    """

    measured_var: np.ndarray
    play_var: np.ndarray
    sd_prior: bool
    play_prior: bool
    play_source: str = "tolerance file"
    correlation: np.ndarray | None = None

    def variance(self, sigma_scale: float, play_scale: float) -> np.ndarray:
        """(N,) per-axis variance ``s^2 m + p^2 q``, px^2."""
        return sigma_scale ** 2 * self.measured_var + play_scale ** 2 * self.play_var

    def weights(self, sigma_scale: float, play_scale: float) -> RowWeights:
        """The rows' weights at ``s``, ``p``: ``V = s^2 D R D + p^2 diag(q)`` (module notes),
        diagonal without a correlation."""
        if self.correlation is None:
            return RowWeights(np.repeat(1.0 / self.variance(sigma_scale, play_scale), 2))
        d = np.repeat(np.sqrt(self.measured_var), 2)
        cov = (sigma_scale ** 2 * self.correlation * np.outer(d, d)
               + np.diag(np.repeat(play_scale ** 2 * self.play_var, 2)))
        return RowWeights.full(cov)


@dataclass(frozen=True)
class NoiseFit:
    """Estimated noise scales and the row variances they give.

    Attributes
    ----------
    sigma_scale, play_scale : float
        ``s`` and ``p`` at the REML minimum.
    sigma_scale_sd_log, play_scale_sd_log : float
        1-sigma of ``log s`` and ``log p`` (NaN when the curvature is not positive).
    variance : (N,) ndarray
        ``v_i``, px^2 per axis.
    converged : bool
        The optimiser stopped at a minimum below the upper bounds.
    weights : RowWeights or None
        The rows' weights at ``s``, ``p`` (:meth:`NoiseShape.weights`).
    """

    sigma_scale: float
    play_scale: float
    sigma_scale_sd_log: float
    play_scale_sd_log: float
    variance: np.ndarray
    converged: bool
    weights: RowWeights | None = None

    def to_dict(self) -> dict:
        return {"sigma_scale": self.sigma_scale,
                "sigma_scale_sd": self.sigma_scale * self.sigma_scale_sd_log,
                "play_scale": self.play_scale,
                "play_scale_sd": self.play_scale * self.play_scale_sd_log,
                "converged": self.converged}


def gls(A: np.ndarray, y: np.ndarray, w: np.ndarray | RowWeights
        ) -> tuple[np.ndarray, int, np.ndarray]:
    """Generalised least squares: the solution, the rank and the singular values of the
    whitened design (``sqrt(w) A``, or ``L^-1 A`` for ``V = L L^T``).

    Parameters
    ----------
    A : (M, K) ndarray
    y : (M,) ndarray
        Observations.
    w : (M,) ndarray or RowWeights
        Their weights ``1 / variance``, or the weights of their full covariance.
    """
    weights = w if isinstance(w, RowWeights) else RowWeights(np.asarray(w, float))
    beta, _, rank, sv = np.linalg.lstsq(weights.whiten(A), weights.whiten(y), rcond=RCOND)
    return beta, int(rank), sv


def _restricted_terms(A: np.ndarray, y: np.ndarray, weights: RowWeights
                      ) -> tuple[float, float]:
    """``log det(A^T V^-1 A)`` over the determined directions and ``r^T V^-1 r`` of the GLS
    fit, from the eigen-decomposition of the (K, K) normal matrix (cheaper than a tall
    solve)."""
    if weights.cov is None:
        w = weights.w
        normal, ATy, yy = (A * w[:, None]).T @ A, A.T @ (w * y), np.sum(w * y ** 2)
    else:
        white_A, white_y = weights.whiten(A), weights.whiten(y)
        normal, ATy, yy = white_A.T @ white_A, white_A.T @ white_y, np.sum(white_y ** 2)
    eigval, eigvec = np.linalg.eigh(normal)
    keep = eigval > RCOND ** 2 * max(eigval[-1], 0.0)
    rhs = eigvec[:, keep].T @ ATy
    chi2 = float(yy - np.sum(rhs ** 2 / eigval[keep]))
    return float(np.sum(np.log(eigval[keep]))), max(chi2, 0.0)


def _neg_log_posterior(theta: np.ndarray, A: np.ndarray, y: np.ndarray,
                       shape: NoiseShape) -> float:
    if shape.correlation is None:
        v = np.repeat(shape.variance(np.exp(theta[0]), np.exp(theta[1])), 2)
        weights, log_det_v = RowWeights(1.0 / v), float(np.sum(np.log(v)))
    else:
        try:
            weights = shape.weights(np.exp(theta[0]), np.exp(theta[1]))
        except np.linalg.LinAlgError:
            return float("inf")  # a covariance rounding left indefinite: not a candidate
        log_det_v = weights.log_det()
    log_det, chi2 = _restricted_terms(A, y, weights)
    value = 0.5 * (log_det_v + log_det + chi2)
    if shape.sd_prior:
        value += 0.5 * (theta[0] / PRIOR_SD_LOG) ** 2
    if shape.play_prior:
        value += 0.5 * (theta[1] / PRIOR_SD_LOG) ** 2
    return float(value)


def _curvature_sd(f, theta: np.ndarray, step: float = 1e-3) -> np.ndarray:
    """1-sigma from the inverse of the finite-difference Hessian of ``f`` at ``theta``."""
    n = len(theta)
    hess = np.empty((n, n))
    eye = np.eye(n) * step
    for i in range(n):
        for j in range(n):
            hess[i, j] = (f(theta + eye[i] + eye[j]) - f(theta + eye[i] - eye[j])
                          - f(theta - eye[i] + eye[j])
                          + f(theta - eye[i] - eye[j])) / (4 * step ** 2)
    try:
        cov = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        return np.full(n, np.nan)
    d = np.diag(cov)
    return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)


def estimate_noise(A: np.ndarray, y: np.ndarray, shape: NoiseShape) -> NoiseFit:
    """REML estimate of the sigma scale ``s`` and the play scale ``p`` for the design ``A``.

    Parameters
    ----------
    A : (2N, K) ndarray
        The model's columns, rows ordered (cx_0, cy_0, cx_1, ...).
    y : (2N,) ndarray
        Measured principal points in the same order, px.
    shape : NoiseShape

    Returns
    -------
    NoiseFit
    """
    def objective(theta: np.ndarray) -> float:
        return _neg_log_posterior(theta, A, y, shape)

    # start from a scale that matches the residuals of an unweighted fit
    beta, _, _ = gls(A, y, np.ones_like(y))
    rms2 = float(np.mean((y - A @ beta) ** 2))
    start_s = 0.5 * np.log(max(rms2, 1e-12) / max(np.mean(shape.measured_var), 1e-12))
    starts = [np.array([0.0, 0.0]), np.array([np.clip(start_s, *LOG_BOUNDS), -3.0])]
    start = min(starts, key=objective)  # the better start only: one search per model
    best = minimize(objective, start, method="Nelder-Mead", bounds=[LOG_BOUNDS] * 2,
                    options={"xatol": 1e-3, "fatol": 1e-5})
    theta = best.x
    # a scale at the lower bound is a variance component the data do not see (a valid
    # estimate of zero); one at the upper bound is a search that ran out of room
    at_bound = bool(np.any(np.isclose(theta, LOG_BOUNDS[1])))
    sd_log = _curvature_sd(objective, theta)
    s, p = float(np.exp(theta[0])), float(np.exp(theta[1]))
    return NoiseFit(s, p, float(sd_log[0]), float(sd_log[1]), shape.variance(s, p),
                    bool(best.success) and not at_bound, shape.weights(s, p))
