"""A smooth zoom model: each camera parameter (fx, fy, cx, cy, distortion terms) as a smooth
function of the zoom value, fitted to per-step calibrations.

Units and conventions: fx, fy, cx, cy in px (OpenCV convention: the centre of the top-left pixel
is (0, 0)); distortion terms in OpenCV's normalised units and order; ``zoom`` in whatever unit the
per-zoom table uses (``[0, 1]`` for the simulator, folder numbers or EXIF focal lengths for real
sets). Uncertainties are 1-sigma.

Model
-----
Each parameter ``p`` is fitted on its own, as ``g(p(z)) = b(z) . c`` with

* ``g`` the identity, or ``log`` (fx and fy only): the focal length of many zoom lenses grows
  roughly exponentially with the zoom control (equal steps of the zoom ring give equal focal
  *ratios*), so ``log f`` is often nearly linear in zoom where ``f`` is not. With
  ``log_focal=None`` the choice is made by cross-validation, so it is checked, not assumed;
* ``b(z)`` a Legendre polynomial basis on the zoom range mapped to ``[-1, 1]``
  (``kind="poly"``), or cubic B-splines with a second-difference roughness penalty
  (a P-spline, ``kind="spline"``), in the zoom itself or in ``log zoom``: where the zoom is a
  focal length or a zoom ratio, equal focal ratios are equal steps in ``log zoom``, and a path
  that bends at the short end and flattens at the long one is a low-degree curve there and
  needs a high degree in the zoom (``log_zoom=None`` tries both where every zoom is
  positive);
* weighted least squares with weights ``1 / sd^2`` (in log space ``p^2 / sd^2``, the same
  weights to first order); equal weights where no sd is given.

The polynomial degree (or the spline's penalty), the abscissa and, for fx, fy, the transform
are chosen by leave-one-out cross-validation: the exact leave-one-out residual of a linear
smoother is ``r_i / (1 - h_ii)`` (``h`` the hat matrix), converted back to the parameter's
units, and the candidate with the smallest weighted mean square of those residuals wins
(ties: the simpler).

Uncertainty: the covariance of ``c`` is the weighted least-squares one, scaled by the reduced
chi-square of the fit when that exceeds 1 (per-step sds from OpenCV are often smaller than the
step-to-step scatter a real zoom mechanism shows); with no sds given, by the residual variance.
Choosing the degree from the same data adds an uncertainty of its own (where the truth bends
gently compared with the noise, the chosen degree can be too low and the curve biased), so the
spread of the other plausible candidates around the chosen curve, weighted by their
pseudo-Bayesian model-averaging weights ``exp(-n (MSE_j - MSE_min) / (2 MSE_ref))`` from the
leave-one-out mean squares (Yao, Vehtari, Simpson & Gelman 2018; ``MSE_ref`` the stated noise
variance or the best score, whichever is larger), is added to the variance.
:meth:`ZoomModel.predict` propagates it to the parameters (delta method through ``exp``): the
1-sigma of the fitted curve, not of a new calibration at that zoom (which also has its own
noise). Its calibration on synthetic sets: ``python benchmarks/zoom_model_coverage.py``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import scipy.optimize
import scipy.stats
from numpy.polynomial import legendre
from scipy.interpolate import BSpline

from zoomcalib.camera import CameraModel, Sensor

__all__ = ["ParamFit", "ZoomIntrinsics", "ZoomModel", "ZoomModelLike", "FOCAL_NAMES",
           "KINDS"]

#: Parameters that may be fitted in log space.
FOCAL_NAMES: tuple[str, ...] = ("fx", "fy")
#: Curve families.
KINDS: tuple[str, ...] = ("poly", "spline")
_DIST_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: The held-out test of a curve's misfit flags it at this significance level.
MISFIT_P = 1e-3
#: A misfit is added to the curve's 1-sigma where its held-out test has a p-value below this
#: (1: always, the moment estimate as it comes).
MISFIT_GATE = 1.0
#: Choose one abscissa for every curve of a model (else per curve).
POOL_ABSCISSA = True
#: Fewest interior steps to estimate and test a misfit from.
MIN_HELD_OUT = 3
#: Penalty grid of the spline, relative to trace(B'WB) / trace(D'D).
_LAM_GRID = tuple(float(v) for v in 10.0 ** np.linspace(-6.0, 6.0, 25))


@dataclass
class ParamFit:
    """The fitted curve of one parameter.

    Attributes
    ----------
    name : str
    transform : {'linear', 'log'}
    kind : {'poly', 'spline'}
    degree : int or None
        Polynomial degree (``kind="poly"``).
    lam : float or None
        Spline penalty, relative to ``trace(B'WB) / trace(D'D)`` (``kind="spline"``).
    knots : (nk,) ndarray or None
        Spline knot vector, zoom units (cubic, equally spaced, extended 3 intervals beyond
        the zoom range).
    coef : (p,) ndarray
        Basis coefficients, in the transformed space.
    cov : (p, p) ndarray
        Their covariance (scaled, see the module notes); NaN when it cannot be estimated.
    chi2_red : float
        Weighted residual sum of squares / effective degrees of freedom (NaN if none left).
    dof : float
        Effective degrees of freedom of the residuals, ``S - trace(H)``.
    loo_rms : float
        Weighted RMS of the leave-one-out residuals of the chosen candidate, parameter units.
    weighted : bool
        Whether per-step sds weighted the fit.
    selection : list of [str, float, float, str]
        Every candidate tried: ``[transform, degree or lam, loo_rms, abscissa]``.
    alternatives : list of dict
        The other candidates with a model-averaging weight of at least 1e-3: ``weight``,
        ``transform``, ``abscissa``, ``degree``, ``lam``, ``coef``. Their spread around this
        curve is part of the prediction's 1-sigma (module notes).
    abscissa : {'zoom', 'log zoom'}
        The variable the curve is a polynomial (or spline) in.
    misfit : float
        1-sigma of the curve's misfit between the steps, in the transformed space (px, or
        relative for ``transform='log'``), estimated from the held-out steps and added to
        every prediction's variance; 0 where the held-out steps show none or fewer than 3
        interior steps could be held out (module notes).
    holdout_chi2 : float
        Sum of the held-out errors squared over their predicted variance (the misfit left
        out); NaN when not tested.
    holdout_steps : int
        Interior steps held out for it (0: not tested).
    """

    name: str
    transform: str
    kind: str
    degree: int | None
    lam: float | None
    knots: np.ndarray | None
    coef: np.ndarray
    cov: np.ndarray
    chi2_red: float
    dof: float
    loo_rms: float
    weighted: bool
    selection: list = field(default_factory=list)
    alternatives: list = field(default_factory=list)
    abscissa: str = "zoom"
    misfit: float = 0.0
    holdout_chi2: float = math.nan
    holdout_steps: int = 0

    @property
    def misfit_flagged(self) -> bool:
        """The held-out steps miss the curve beyond their predicted scatter (chi-square test at
        :data:`MISFIT_P`)."""
        return (self.holdout_steps >= MIN_HELD_OUT and math.isfinite(self.holdout_chi2)
                and self.holdout_chi2 > scipy.stats.chi2.isf(MISFIT_P, self.holdout_steps))

    def to_dict(self) -> dict:
        return {"transform": self.transform, "kind": self.kind, "degree": self.degree,
                "lam": self.lam,
                "knots": None if self.knots is None else _floats(self.knots),
                "coef": _floats(self.coef), "cov": [_floats(r) for r in self.cov],
                "chi2_red": _float(self.chi2_red), "dof": float(self.dof),
                "loo_rms": _float(self.loo_rms), "weighted": bool(self.weighted),
                "abscissa": self.abscissa, "misfit": float(self.misfit),
                "holdout_chi2": _float(self.holdout_chi2),
                "holdout_steps": int(self.holdout_steps),
                "misfit_flagged": bool(self.misfit_flagged),
                "selection": [[s[0], float(s[1]), _float(s[2]), s[3]] for s in self.selection],
                "alternatives": [{"weight": float(a["weight"]), "transform": a["transform"],
                                  "abscissa": a["abscissa"], "degree": a["degree"],
                                  "lam": a["lam"], "coef": _floats(a["coef"])}
                                 for a in self.alternatives]}

    @classmethod
    def from_dict(cls, name: str, d: Mapping) -> ParamFit:
        knots = d.get("knots")
        return cls(name, str(d["transform"]), str(d["kind"]),
                   None if d.get("degree") is None else int(d["degree"]),
                   None if d.get("lam") is None else float(d["lam"]),
                   None if knots is None else np.asarray(knots, float),
                   np.asarray(d["coef"], float), _nan_array(d["cov"]),
                   _unfloat(d.get("chi2_red")), float(d.get("dof", 0.0)),
                   _unfloat(d.get("loo_rms")), bool(d.get("weighted", False)),
                   [(list(s) + ["zoom"])[:4] for s in d.get("selection", [])],
                   [{"abscissa": "zoom", **a, "coef": np.asarray(a["coef"], float)}
                    for a in d.get("alternatives", [])],
                   str(d.get("abscissa", "zoom")), float(d.get("misfit", 0.0)),
                   _unfloat(d.get("holdout_chi2")), int(d.get("holdout_steps", 0)))


def _float(v) -> float | None:
    v = float(v)
    return None if not math.isfinite(v) else v


def _unfloat(v) -> float:
    return float("nan") if v is None else float(v)


def _floats(a) -> list:
    return [_float(v) for v in np.asarray(a, float).ravel()]


def _nan_array(rows) -> np.ndarray:
    return np.array([[np.nan if v is None else v for v in r] for r in rows], float)


# ----------------------------------------------------------------------------------------------
# linear smoothers


def _knots(lo: float, hi: float, n_points: int) -> np.ndarray:
    """Equally spaced cubic knots, extended 3 intervals beyond the range (not clamped), so
    that the second-difference penalty's null space is exactly the straight lines (Eilers &
    Marx's P-splines)."""
    n_seg = max(1, min(n_points - 3, 12))
    step = (hi - lo) / n_seg
    return lo + step * np.arange(-3, n_seg + 4)


def _to_abscissa(z: np.ndarray | float, abscissa: str) -> np.ndarray:
    """Zoom values as the curve's variable: themselves, or their log (``'log zoom'``)."""
    return np.log(z) if abscissa == "log zoom" else np.asarray(z, float)


def _basis(z: np.ndarray, kind: str, lo: float, hi: float, degree: int | None,
           n_points: int, abscissa: str = "zoom") -> np.ndarray:
    """``(k, p)`` design matrix at zooms ``z`` of a curve over the zoom range ``[lo, hi]``, in
    ``abscissa``: Legendre polynomials on the range mapped to [-1, 1], or cubic B-splines on
    the knots :func:`_knots` places for ``n_points`` steps."""
    x = _to_abscissa(np.asarray(z, float).ravel(), abscissa)
    x_lo, x_hi = (float(v) for v in _to_abscissa(np.array([lo, hi]), abscissa))
    if kind == "poly":
        return legendre.legvander(2.0 * (x - x_lo) / (x_hi - x_lo) - 1.0, int(degree))
    return BSpline.design_matrix(x, _knots(x_lo, x_hi, n_points), 3, extrapolate=True).toarray()


def _penalty(nb: int) -> np.ndarray:
    d = np.diff(np.eye(nb), 2, axis=0)
    return d.T @ d


def _forward(v: np.ndarray, transform: str) -> np.ndarray:
    return np.log(v) if transform == "log" else v


def _inverse(y: np.ndarray, transform: str) -> np.ndarray:
    return np.exp(y) if transform == "log" else y


def _smoother(A: np.ndarray, y: np.ndarray, w: np.ndarray, lam_rel: float | None):
    """Weighted (penalised) least squares; returns coef, unscaled cov, hat diagonal, residuals.
    (Not ``scipy.interpolate.make_smoothing_spline``: it returns neither the coefficients'
    covariance nor the hat diagonal, which the curves' sigmas and the penalty's choice need.)

    ``w`` are the true weights (1 / variance of y, or arbitrary equal ones); they are normalised
    internally for conditioning and the covariance is returned for the true weights.
    """
    wmean = float(np.mean(w))
    wn = w / wmean
    AtW = A.T * wn
    N = AtW @ A
    M = N.copy()
    if lam_rel is not None:
        P = _penalty(A.shape[1])
        M = M + lam_rel * np.trace(N) / np.trace(P) * P
    Minv = np.linalg.pinv(M, rcond=1e-13, hermitian=True)
    coef = Minv @ (AtW @ y)
    h = wn * np.einsum("ij,jk,ik->i", A, Minv, A)
    cov = Minv @ N @ Minv / wmean
    return coef, cov, h, y - A @ coef


@dataclass
class _Data:
    z: np.ndarray
    v: np.ndarray
    sd: np.ndarray | None


def _weights_px(sd: np.ndarray | None, n: int) -> np.ndarray:
    return np.ones(n) if sd is None else 1.0 / sd**2


class _Candidate(NamedTuple):
    """One curve to try: value transform, abscissa and degree (poly) or penalty (spline)."""

    transform: str
    abscissa: str
    setting: float


def _candidates(name: str, z: np.ndarray, v: np.ndarray, kind: str, degree: int | None,
                lam: float | None, log_focal: bool | None, log_zoom: bool | None,
                max_degree: int) -> list[_Candidate]:
    """Every candidate for one parameter; ``None`` options are chosen by held-out steps, a
    log (of the value, of the zoom) only where every value is positive."""
    n = len(z)
    transforms = ("linear",)
    if name in FOCAL_NAMES and np.all(v > 0):
        transforms = {None: ("linear", "log"), True: ("log",), False: ("linear",)}[log_focal]
    abscissae = ("zoom",)
    if np.all(z > 0):
        abscissae = {None: ("zoom", "log zoom"), True: ("log zoom",),
                     False: ("zoom",)}[log_zoom]
    elif log_zoom:
        raise ValueError("log_zoom=True needs every zoom value positive")
    if kind == "poly":
        if degree is not None:
            settings = [int(degree)]
        else:
            dmax = min(max_degree, n - 2)
            settings = list(range(dmax + 1)) if dmax >= 1 else [min(1, n - 1)]
    else:
        settings = [float(lam)] if lam is not None else list(_LAM_GRID)
    return [_Candidate(t, a, s) for s in settings for a in abscissae for t in transforms]


@dataclass
class _Tried:
    """A candidate fitted: its weighted leave-one-out squared errors ``loo_sq`` (S,), px^2
    times the step's normalised weight (all ``inf`` when a step's leverage is 1)."""

    candidate: _Candidate
    complexity: float
    loo_sq: np.ndarray
    coef: np.ndarray
    cov: np.ndarray
    hat: np.ndarray
    resid: np.ndarray
    weight: np.ndarray

    @property
    def mse(self) -> float:
        return float(np.mean(self.loo_sq))


def _try(c: _Candidate, data: _Data, kind: str, A: np.ndarray) -> _Tried:
    """Fit one candidate, on its design matrix ``A`` at the data's zooms (:func:`_basis`), and
    its exact leave-one-out errors, ``r_i / (1 - h_ii)`` in the transformed space, taken back
    to the parameter's units."""
    z, v = data.z, data.v
    w_px = _weights_px(data.sd, len(z))
    degree = int(c.setting) if kind == "poly" else None
    lam_rel = float(c.setting) if kind == "spline" else None
    y = _forward(v, c.transform)
    w = w_px * v**2 if c.transform == "log" else w_px
    coef, cov, h, r = _smoother(A, y, w, lam_rel)
    loo_sq = np.full(len(z), np.inf)
    if np.all(h < 1.0 - 1e-8):
        pred_loo = _inverse(y - r / (1.0 - h), c.transform)
        loo_sq = w_px / np.mean(w_px) * (v - pred_loo) ** 2
    complexity = float(degree) if kind == "poly" else -math.log10(lam_rel)
    return _Tried(c, complexity, loo_sq, coef, cov, h, r, w)


def _choose(tried: list[_Tried]) -> _Tried:
    """The smallest held-out mean square wins; ties go to the simpler candidate. (The
    one-standard-error rule, the simplest candidate within a standard error of the best, was
    measured and is worse here: ``benchmarks/bench_zoom_curve.py``,
    docs/notes/calibration-zoom-model.md.)"""
    return min(tried, key=lambda t: (t.mse, t.complexity))


def _degree_lam(c: _Candidate, kind: str) -> tuple[int | None, float | None]:
    return (int(c.setting), None) if kind == "poly" else (None, float(c.setting))


def _alternatives(tried: list[_Tried], chosen: _Tried, data: _Data, kind: str) -> list[dict]:
    """The other candidates with their pseudo-Bayesian-model-averaging weights (at least
    1e-3) from their leave-one-out scores (Yao et al. 2018): ``exp(-n (MSE_j - MSE_min) /
    (2 MSE_ref))``, ``MSE_ref`` the stated noise variance or the best score, whichever is
    larger. Their spread around the chosen curve is added to its variance at prediction."""
    n = len(data.z)
    best_mse = min(t.mse for t in tried)
    mse_ref = best_mse if data.sd is None else max(n / float(np.sum(_weights_px(data.sd, n))),
                                                   best_mse)
    if not (math.isfinite(best_mse) and mse_ref > 0 and len(tried) > 1):
        return []
    logw = np.array([-0.5 * n * (t.mse - best_mse) / mse_ref if math.isfinite(t.mse)
                     else -np.inf for t in tried])
    wts = np.exp(logw - logw.max())
    wts /= wts.sum()
    out = []
    for wt, t in zip(wts, tried, strict=True):
        if wt >= 1e-3 and t is not chosen:
            degree, lam = _degree_lam(t.candidate, kind)
            out.append({"weight": float(wt), "transform": t.candidate.transform,
                        "abscissa": t.candidate.abscissa, "degree": degree, "lam": lam,
                        "coef": t.coef})
    return out


def _fit_param(name: str, data: _Data, kind: str, lo: float, hi: float, n_points: int,
               candidates: list[_Candidate]) -> ParamFit:
    """Every candidate fitted, one chosen (:func:`_choose`), its covariance scaled by the
    reduced chi-square where the scatter exceeds the stated sds (module notes)."""
    bases: dict[tuple[str, int | None], np.ndarray] = {}  # one per abscissa (and degree)
    tried = []
    for c in candidates:
        key = (c.abscissa, int(c.setting) if kind == "poly" else None)
        if key not in bases:
            bases[key] = _basis(data.z, kind, lo, hi, key[1], n_points, c.abscissa)
        tried.append(_try(c, data, kind, bases[key]))
    chosen = _choose(tried)
    c = chosen.candidate
    degree, lam = _degree_lam(c, kind)
    score = math.sqrt(chosen.mse) if len(tried) > 1 or math.isfinite(chosen.mse) else math.nan
    dof = float(len(data.z) - np.sum(chosen.hat))
    chi2 = float(np.sum(chosen.weight * chosen.resid**2))
    chi2_red = chi2 / dof if dof > 0.5 else math.nan
    if data.sd is not None:
        # Stated sds are kept unless the scatter shows them too small.
        scale = max(1.0, chi2_red) if math.isfinite(chi2_red) else 1.0
    else:
        scale = chi2_red
    x_lo, x_hi = (float(v) for v in _to_abscissa(np.array([lo, hi]), c.abscissa))
    knots = _knots(x_lo, x_hi, n_points) if kind == "spline" else None
    selection = [[t.candidate.transform, float(t.candidate.setting), math.sqrt(t.mse),
                  t.candidate.abscissa] for t in tried]
    return ParamFit(name, c.transform, kind, degree, lam, knots, chosen.coef,
                    chosen.cov * scale, chi2_red, dof, score, data.sd is not None, selection,
                    _alternatives(tried, chosen, data, kind), c.abscissa)


def _predict(fit: ParamFit, z: np.ndarray, lo: float, hi: float, n_points: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """The curve and its 1-sigma at zooms ``z``, the plausible alternatives' spread included."""
    A = _basis(z, fit.kind, lo, hi, fit.degree, n_points, fit.abscissa)
    y = A @ fit.coef
    var = np.einsum("ij,jk,ik->i", A, fit.cov, A) + fit.misfit**2
    sd_y = np.sqrt(np.maximum(var, 0.0))
    value = _inverse(y, fit.transform)
    sd = value * sd_y if fit.transform == "log" else sd_y
    if fit.alternatives:
        spread = np.zeros_like(value)
        for alt in fit.alternatives:
            B = _basis(z, fit.kind, lo, hi, alt["degree"], n_points, alt["abscissa"])
            other = _inverse(B @ np.asarray(alt["coef"], float), alt["transform"])
            spread += alt["weight"] * (other - value) ** 2
        sd = np.sqrt(sd**2 + spread)
    return value, sd


def _pooled_abscissa(fits) -> str:
    """``'zoom'`` or ``'log zoom'``: the abscissa whose best candidates have the smaller
    product of held-out mean squares over the parameters (the sum of their logs; parameters
    without a finite positive score in both are left out; ties: ``'zoom'``). One choice for
    the lens, as its curves share one zoom mechanism; per parameter, 5-7 steps choose it at
    random where both fit (``benchmarks/bench_zoom_curve.py``)."""
    score = {"zoom": 0.0, "log zoom": 0.0}
    for fit in fits:
        best = {a: min((row[2] for row in fit.selection if row[3] == a), default=math.nan)
                for a in score}
        if all(math.isfinite(b) and b > 0 for b in best.values()):
            for a, b in best.items():
                score[a] += 2.0 * math.log(b)
    return "log zoom" if score["log zoom"] < score["zoom"] else "zoom"


@dataclass
class _HeldOut:
    """Leave-one-out of one parameter's interior (or all) steps, each fold fitted afresh:
    ``error`` (k,) the held-out value less its prediction, ``sd_pred`` (k,) the prediction's
    1-sigma and ``sd_step`` (k,) the held-out step's own (stated, or for an unweighted
    parameter the fold's residual scatter), all in the parameter's units."""

    index: np.ndarray
    error: np.ndarray
    sd_pred: np.ndarray
    sd_step: np.ndarray


def _held_out(name: str, data: _Data, kind: str, lo: float, hi: float, index: list[int],
              candidates_of) -> _HeldOut:
    """Each step of ``index`` predicted by a fit to the others; ``candidates_of(fold_data)``
    gives the candidates of a fold (re-chosen, or the full fit's)."""
    n = len(data.z)
    error, sd_pred, sd_step = [], [], []
    for i in index:
        keep = np.arange(n) != i
        fold = _Data(data.z[keep], data.v[keep], None if data.sd is None else data.sd[keep])
        f = _fit_param(name, fold, kind, lo, hi, n, candidates_of(fold))
        value, sd = _predict(f, data.z[i:i + 1], lo, hi, n)
        error.append(data.v[i] - value[0])
        sd_pred.append(sd[0])
        own = data.sd[i] if data.sd is not None else math.sqrt(f.chi2_red)
        if f.transform == "log" and data.sd is None:
            own *= data.v[i]
        sd_step.append(own)
    return _HeldOut(np.asarray(index, int), np.asarray(error, float),
                    np.asarray(sd_pred, float), np.asarray(sd_step, float))


def _misfit(held: _HeldOut, values: np.ndarray, transform: str) -> tuple[float, float]:
    """The curve's misfit ``m`` between the steps and the held-out chi-square without it.

    In the transformed space (relative errors for ``log``) the held-out errors ``e_i`` are
    taken as ``N(0, s_i^2 + p_i^2 + m^2)`` (``s_i`` the step's own 1-sigma, ``p_i`` the
    prediction's); ``m^2`` solves ``sum e_i^2 / (s_i^2 + p_i^2 + m^2) = k``, the moment
    estimator of a random effect (Paule & Mandel 1982), 0 where the sum without it is at most
    ``k``. Returns ``(m, chi2)``; ``(0, nan)`` with fewer than :data:`MIN_HELD_OUT` steps or a
    non-finite term."""
    scale = values[held.index] if transform == "log" else 1.0
    e = held.error / scale
    var = (held.sd_step**2 + held.sd_pred**2) / scale**2
    k = len(e)
    if k < MIN_HELD_OUT or not (np.all(np.isfinite(e)) and np.all(np.isfinite(var))
                                and np.all(var > 0)):
        return 0.0, math.nan
    chi2 = float(np.sum(e**2 / var))
    if chi2 <= k or scipy.stats.chi2.sf(chi2, k) >= MISFIT_GATE:
        return 0.0, chi2
    m2 = scipy.optimize.brentq(lambda m2: float(np.sum(e**2 / (var + m2))) - k,
                               0.0, float(np.sum(e**2)))
    return math.sqrt(m2), chi2


@dataclass(frozen=True)
class ZoomIntrinsics:
    """The zoom model at one zoom value (:meth:`ZoomModel.at`).

    Attributes
    ----------
    zoom : float
    values : dict of str to float
        Every fitted parameter: fx, fy, cx, cy in px (OpenCV convention: the centre of the
        top-left pixel is (0, 0)), distortion terms in OpenCV's normalised units.
    sd : dict of str to float
        Their 1-sigma: of the fitted curve at ``zoom``, not of a new calibration there.
    extrapolated : bool
        ``zoom`` lies outside the calibrated range.
    """

    zoom: float
    values: dict[str, float]
    sd: dict[str, float]
    extrapolated: bool = False

    fx = property(lambda self: self.values["fx"], doc="Focal length along u, px.")
    fy = property(lambda self: self.values["fy"], doc="Focal length along v, px.")
    cx = property(lambda self: self.values["cx"], doc="Principal point u, px.")
    cy = property(lambda self: self.values["cy"], doc="Principal point v, px.")

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix, px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``: 8 terms when any
        of k4..k6 was fitted, else 5; terms not fitted are 0."""
        n = 8 if any(k in self.values for k in _DIST_ORDER[5:]) else 5
        return np.array([self.values.get(k, 0.0) for k in _DIST_ORDER[:n]])


def intrinsics_at(model, zoom: float, extrapolate: bool) -> ZoomIntrinsics:
    """``model.predict`` at one zoom as :class:`ZoomIntrinsics` (``model`` has ``zoom_range``,
    ``names`` and ``predict``); ValueError for a zoom that is not finite or, without
    ``extrapolate``, outside the calibrated range; KeyError when fx, fy, cx or cy is missing."""
    z = float(zoom)
    lo, hi = model.zoom_range
    if not math.isfinite(z):
        raise ValueError(f"zoom {z} is not finite")
    if not extrapolate and not lo <= z <= hi:
        raise ValueError(f"zoom {z:g} is outside the calibrated range [{lo:g}, {hi:g}]; "
                         "pass extrapolate=True to use the model there")
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in model.names]
    if missing:
        raise KeyError(f"zoom model has no {', '.join(missing)}")
    p = model.predict(z)
    return ZoomIntrinsics(z, {k: p[k] for k in model.names},
                          {k: p[f"sd_{k}"] for k in model.names}, not lo <= z <= hi)


# ----------------------------------------------------------------------------------------------
# the model


@runtime_checkable
class ZoomModelLike(Protocol):
    """What a zoom model offers whoever evaluates or checks it: :class:`ZoomModel` (curves
    fitted to a table's rows) and
    :class:`zoomcalib.calibrate.zoompath.PosteriorZoomModel` (the zoom-wide adjustment's own
    posterior) both do, and ``calibrate`` writes and reports either through this alone."""

    @property
    def names(self) -> list[str]: ...

    def predict(self, zoom: float | Sequence[float] | np.ndarray) -> dict: ...

    def at(self, zoom: float, *, extrapolate: bool = False) -> ZoomIntrinsics: ...

    def camera(self, zoom: float) -> CameraModel: ...

    def holdout_error(self) -> dict: ...

    def flags(self) -> list[str]: ...

    def summary(self) -> str: ...

    def to_dict(self) -> dict: ...


class ZoomModel:
    """Camera parameters as smooth functions of zoom (module docstring).

    Build with :meth:`fit` (or :meth:`from_table`, :meth:`from_dict`); evaluate with
    :meth:`predict` and :meth:`camera`; measure with :meth:`holdout_error`.

    Attributes
    ----------
    kind : {'poly', 'spline'}
    zoom : (S,) ndarray
        The calibrated zoom values.
    values : dict of str to (S,) ndarray
        Per-step parameter values (px for fx, fy, cx, cy).
    sd : dict of str to (S,) ndarray
        Per-step 1-sigma used as weights (only the parameters that had them).
    fits : dict of str to ParamFit
    zoom_range : (float, float)
        Smallest and largest calibrated zoom; predictions outside are extrapolations.
    sensor : Sensor or None
        Given to :meth:`camera`'s CameraModel (else CameraModel's default).
    options : dict
        The fit options (``degree``, ``lam``, ``log_focal``, ``log_zoom``, ``max_degree``;
        a model saved without ``log_zoom`` was fitted in zoom), reused by
        :meth:`holdout_error`.
    """

    def __init__(self, kind: str, zoom: np.ndarray, values: dict[str, np.ndarray],
                 sd: dict[str, np.ndarray], fits: dict[str, ParamFit],
                 zoom_range: tuple[float, float], sensor: Sensor | None = None,
                 options: dict | None = None) -> None:
        self.kind = kind
        self.zoom = np.asarray(zoom, float)
        self.values = {k: np.asarray(v, float) for k, v in values.items()}
        self.sd = {k: np.asarray(v, float) for k, v in sd.items()}
        self.fits = fits
        self.zoom_range = (float(zoom_range[0]), float(zoom_range[1]))
        self.sensor = sensor
        self.options = dict(options or {})

    # -- fitting ---------------------------------------------------------------------------

    @classmethod
    def fit(cls, zoom: Sequence[float] | np.ndarray, values: Mapping[str, Sequence[float]],
            sd: Mapping[str, Sequence[float] | None] | None = None,
            degree: int | Mapping[str, int] | None = None, kind: str = "poly", *,
            lam: float | None = None, log_focal: bool | None = None,
            log_zoom: bool | None = None, max_degree: int = 5,
            sensor: Sensor | None = None) -> ZoomModel:
        """Fit every parameter of ``values`` versus ``zoom``.

        Parameters
        ----------
        zoom : (S,) array_like
            Zoom value of each step (at least 2 distinct values).
        values : dict of str to (S,) array_like
            Parameter name (``fx, fy, cx, cy`` px, ``k1, k2, p1, p2, k3[, k4, k5, k6]``) to
            its per-step values.
        sd : dict of str to (S,) array_like, optional
            Per-step 1-sigma of the parameters that have one (same units). A parameter whose
            sds are missing, non-finite or not positive is fitted with equal weights.
        degree : int or dict of str to int, optional
            Polynomial degree (all parameters, or per name); default chosen by leave-one-out
            cross-validation from 0 to ``min(max_degree, S - 2)``.
        kind : {'poly', 'spline'}
            Legendre polynomial, or penalised cubic B-spline (needs S >= 4).
        lam : float, optional
            Spline penalty (relative, see :class:`ParamFit`); default chosen by leave-one-out
            cross-validation on a grid from 1e-6 to 1e6.
        log_focal : bool or None
            Fit fx, fy in log space (True), linearly (False), or choose by cross-validation
            (None).
        log_zoom : bool or None
            Curves in ``log zoom`` (True), in zoom (False), or choose per parameter by
            cross-validation (None; ``log zoom`` is tried only where every zoom is positive).
        max_degree : int
        sensor : Sensor, optional

        Returns
        -------
        ZoomModel

        Raises
        ------
        ValueError
            On mismatched lengths, non-finite values, fewer than 2 distinct zooms, a degree
            too high for the number of steps, or an unknown kind.
        """
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}; choose 'poly' or 'spline'")
        z = np.asarray(zoom, float).ravel()
        n = len(z)
        if not np.all(np.isfinite(z)):
            raise ValueError("zoom values must be finite")
        lo, hi = float(z.min(initial=np.inf)), float(z.max(initial=-np.inf))
        if n < 2 or not hi > lo:
            raise ValueError(f"a zoom model needs at least 2 distinct zoom values; got {n} steps")
        if kind == "spline" and n < 4:
            raise ValueError(f"kind='spline' needs at least 4 zoom steps; got {n}")
        if kind == "spline" and degree is not None:
            raise ValueError("degree applies to kind='poly'; the spline's smoothness is lam")
        vals, sds = {}, {}
        for name, v in values.items():
            v = np.asarray(v, float).ravel()
            if len(v) != n:
                raise ValueError(f"{name}: {len(v)} values for {n} zoom steps")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"{name}: values must be finite")
            s = None if sd is None else sd.get(name)
            if s is not None:
                s = np.asarray(s, float).ravel()
                if len(s) != n:
                    raise ValueError(f"sd {name}: {len(s)} values for {n} zoom steps")
                if not (np.all(np.isfinite(s)) and np.all(s > 0)):
                    s = None
            d = degree.get(name) if isinstance(degree, Mapping) else degree
            if d is not None and not 0 <= int(d) <= n - 1:
                raise ValueError(f"{name}: degree {d} needs at least {int(d) + 1} zoom steps; "
                                 f"got {n}")
            vals[name] = v
            if s is not None:
                sds[name] = s
        options = {"degree": dict(degree) if isinstance(degree, Mapping) else degree,
                   "lam": lam, "log_focal": log_focal, "log_zoom": log_zoom,
                   "max_degree": int(max_degree)}
        model = cls(kind, z, vals, sds, {}, (lo, hi), sensor, options)
        model._fit_curves()
        if log_zoom is None and POOL_ABSCISSA and np.all(z > 0):
            # one abscissa for the whole lens, the one its curves predict held-out steps best in
            model.options["log_zoom"] = _pooled_abscissa(model.fits.values()) == "log zoom"
            model._fit_curves()
        model.options["log_zoom_asked"] = log_zoom
        model._estimate_misfits()
        return model

    def _fit_curves(self) -> None:
        """Every parameter's curve, candidates as :attr:`options` give them."""
        lo, hi = self.zoom_range
        n = len(self.zoom)
        self.fits = {name: _fit_param(name, _Data(self.zoom, v, self.sd.get(name)), self.kind,
                                      lo, hi, n, self._candidates_of(name)(
                                          _Data(self.zoom, v, None)))
                     for name, v in self.values.items()}

    def _estimate_misfits(self) -> None:
        """Each curve's misfit between the steps from its interior steps held out, folds
        re-chosen (:func:`_misfit`); set on the fits, so every prediction carries it."""
        lo, hi = self.zoom_range
        interior = [i for i in range(len(self.zoom)) if lo < self.zoom[i] < hi]
        if len(interior) < MIN_HELD_OUT:
            return
        for name, fit in self.fits.items():
            data = _Data(self.zoom, self.values[name], self.sd.get(name))
            held = _held_out(name, data, self.kind, lo, hi, interior, self._candidates_of(name))
            fit.misfit, fit.holdout_chi2 = _misfit(held, data.v, fit.transform)
            fit.holdout_steps = len(interior)

    @classmethod
    def from_table(cls, rows: Sequence[Mapping], names: Sequence[str] | None = None,
                   **fit_options) -> ZoomModel:
        """Fit the rows of a per-zoom table (:func:`zoomcalib.calibrate.io.read_zoom_table`).

        Parameters
        ----------
        rows : sequence of dict
            Each with ``zoom`` and the parameters; ``sd_<name>`` columns weight them.
        names : sequence of str, optional
            Parameters to fit; default ``fx, fy, cx, cy`` and those of ``k1, k2, p1, p2, k3``
            (and ``k4..k6``) that every row has; no distortion term when some rows hold the
            rational model (``k4``) and others not: a rational step's k1..k3 are not a
            five-term step's, and one curve through both would be neither.
        **fit_options
            Passed to :meth:`fit`.
        """
        if names is None:
            rational = [r.get("k4") is not None for r in rows]
            mixed = any(rational) and not all(rational)
            names = ["fx", "fy", "cx", "cy"] + [
                k for k in _DIST_ORDER
                if not mixed and all(r.get(k) is not None for r in rows)]
        zoom = [float(r["zoom"]) for r in rows]
        values = {k: [float(r[k]) for r in rows] for k in names}
        sd = {}
        for k in names:
            col = [r.get(f"sd_{k}") for r in rows]
            if all(c is not None for c in col):
                sd[k] = [float(c) for c in col]
        return cls.fit(zoom, values, sd or None, **fit_options)

    # -- evaluation ------------------------------------------------------------------------

    @property
    def names(self) -> list[str]:
        """The fitted parameters."""
        return list(self.fits)

    def predict(self, zoom: float | Sequence[float] | np.ndarray) -> dict:
        """The parameters at any zoom value(s).

        Parameters
        ----------
        zoom : float or (k,) array_like

        Returns
        -------
        dict
            ``name`` -> value and ``"sd_" + name`` -> 1-sigma of the fitted curve there (NaN
            when the fit left no degrees of freedom to estimate it); floats for a scalar zoom,
            (k,) arrays otherwise. fx, fy, cx, cy in px.
        """
        scalar = np.ndim(zoom) == 0
        z = np.atleast_1d(np.asarray(zoom, float))
        out = {}
        for name, fit in self.fits.items():
            value, sd = _predict(fit, z, *self.zoom_range, len(self.zoom))
            out[name] = float(value[0]) if scalar else value
            out[f"sd_{name}"] = float(sd[0]) if scalar else sd
        return out

    def camera(self, zoom: float) -> CameraModel:
        """The camera at one zoom value (fx, fy, cx, cy in px; distortion terms not fitted are
        0; 8 terms if any of k4..k6 is fitted, else 5); outside the calibrated range the curves
        are extrapolated.

        Raises
        ------
        KeyError
            If fx, fy, cx or cy was not fitted.
        """
        lens = self.at(zoom, extrapolate=True)
        kwargs = {} if self.sensor is None else {"sensor": self.sensor}
        return CameraModel(lens.fx, lens.fy, lens.cx, lens.cy, lens.dist, **kwargs)

    def at(self, zoom: float, *, extrapolate: bool = False) -> ZoomIntrinsics:
        """The intrinsics and their 1-sigma at one zoom value, interpolated by the fitted curves.

        Parameters
        ----------
        zoom : float
            In the unit of the zoom table the model was fitted to.
        extrapolate : bool
            Allow a zoom outside :attr:`zoom_range` (the curves are then extrapolated and
            their 1-sigma grows quickly); by default that raises ValueError.

        Returns
        -------
        ZoomIntrinsics
            fx, fy, cx, cy in px (OpenCV convention), distortion in OpenCV order; the 1-sigma
            is that of the fitted curve at ``zoom`` (:meth:`predict`).

        Raises
        ------
        ValueError
            If ``zoom`` is not finite, or outside the calibrated range without
            ``extrapolate``.
        KeyError
            If fx, fy, cx or cy was not fitted.

        Examples
        --------
        A lens whose focal length grows exponentially with zoom, calibrated at 5 steps:

        >>> import numpy as np
        >>> z = np.linspace(0.0, 1.0, 5)
        >>> model = ZoomModel.fit(z, {"fx": 1000 * np.exp(z), "fy": 1000 * np.exp(z),
        ...                           "cx": 640 + 10 * z, "cy": 360 - 5 * z, "k1": -0.1 + 0 * z})
        >>> lens = model.at(0.5)
        >>> print(f"{lens.fx:.2f} {lens.cx:.2f} {lens.dist[0]:.2f} {len(lens.dist)}")
        1648.72 645.00 -0.10 5
        >>> model.at(1.5)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: zoom 1.5 is outside the calibrated range [0, 1]; pass extrapolate=True ...
        """
        return intrinsics_at(self, zoom, extrapolate)

    def holdout_error(self, interior_only: bool = True, reselect: bool = True,
                      details: bool = False) -> dict:
        """Interpolation error on held-out steps (leave-one-out).

        Each step in turn is left out, the model is fitted to the others and evaluated at the
        left-out zoom; the error is the left-out step's value minus that prediction.

        Parameters
        ----------
        interior_only : bool
            Hold out only the steps strictly inside the zoom range (leaving out an end step
            measures extrapolation, not interpolation).
        reselect : bool
            Choose degree / penalty and transform again without the left-out step (honest
            nested cross-validation); else reuse the full fit's choice.
        details : bool
            Return per-step errors as well.

        Returns
        -------
        dict
            ``name`` -> RMS of the errors (parameter units: px for fx, fy, cx, cy). With
            ``details``: ``name`` -> ``{"rms": float, "zoom": (k,), "error": (k,),
            "sd_pred": (k,)}`` with ``sd_pred`` the 1-sigma of each prediction.
        """
        lo, hi = self.zoom_range
        z = self.zoom
        idx = [i for i in range(len(z)) if not interior_only or lo < z[i] < hi]
        out = {}
        for name, fit in self.fits.items():
            data = _Data(z, self.values[name], self.sd.get(name))
            held = _held_out(name, data, self.kind, lo, hi, idx,
                             self._candidates_of(name) if reselect else
                             lambda fold, fit=fit: [_Candidate(
                                 fit.transform, fit.abscissa,
                                 fit.degree if self.kind == "poly" else fit.lam)])
            rms = float(np.sqrt(np.mean(held.error**2))) if len(idx) else math.nan
            out[name] = {"rms": rms, "zoom": z[idx].copy(), "error": held.error,
                         "sd_pred": held.sd_pred} if details else rms
        return out

    def _candidates_of(self, name: str):
        """The candidates of a fold of ``name``, as :meth:`fit` chose them."""
        d = self.options.get("degree")
        d = d.get(name) if isinstance(d, Mapping) else d
        return lambda fold: _candidates(
            name, fold.z, fold.v, self.kind, d, self.options.get("lam"),
            self.options.get("log_focal"), self.options.get("log_zoom", False),
            int(self.options.get("max_degree", 5)))

    def summary(self) -> str:
        """One line per parameter: curve, transform, abscissa, leave-one-out RMS, reduced
        chi-square, and a misfit where the held-out steps showed one."""
        lines = []
        for name, f in self.fits.items():
            what = f"degree {f.degree}" if f.kind == "poly" else f"spline lam {f.lam:.3g}"
            misfit = (f", misfit {f.misfit:.3g}{' (flagged)' if f.misfit_flagged else ''}"
                      if f.misfit > 0 else "")
            lines.append(f"{name}: {what} in {f.abscissa}, {f.transform}, "
                         f"loo rms {f.loo_rms:.4g}, chi2/dof {f.chi2_red:.3g}"
                         f"{'' if f.weighted else ' (unweighted)'}{misfit}")
        return "\n".join(lines)

    def flags(self) -> list[str]:
        """One line per curve whose held-out steps miss it beyond their scatter: its 1-sigma
        carries the misfit, but the curve does not follow the zoom between the steps."""
        out = []
        for name, f in self.fits.items():
            if f.misfit_flagged:
                unit = (" (relative)" if f.transform == "log"
                        else " px" if name in ("fx", "fy", "cx", "cy") else "")
                out.append(f"{name}: held-out steps miss the curve (chi2 {f.holdout_chi2:.1f} "
                           f"for {f.holdout_steps} steps); its 1-sigma includes a misfit of "
                           f"{f.misfit:.3g}{unit} between the steps; more steps would pin it")
        return out

    # -- saving ----------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """A JSON-able dict (plain lists and numbers; non-finite numbers become None)."""
        sensor = None if self.sensor is None else {
            "width_px": self.sensor.width_px, "height_px": self.sensor.height_px,
            "pixel_pitch_mm": self.sensor.pixel_pitch_mm}
        return {"format": "zoomcalib-zoom-model", "version": 1, "kind": self.kind,
                "zoom_range": list(self.zoom_range), "options": dict(self.options),
                "sensor": sensor,
                "data": {"zoom": _floats(self.zoom),
                         "values": {k: _floats(v) for k, v in self.values.items()},
                         "sd": {k: _floats(v) for k, v in self.sd.items()}},
                "params": {k: f.to_dict() for k, f in self.fits.items()}}

    @classmethod
    def from_dict(cls, d: Mapping) -> ZoomModel:
        """Inverse of :meth:`to_dict`."""
        if d.get("format") != "zoomcalib-zoom-model":
            raise ValueError("not a zoom model (format != 'zoomcalib-zoom-model')")
        if d.get("kind") == "posterior":
            raise ValueError("a zoom-wide adjustment's posterior zoom model: read it with "
                             "zoomcalib.calibrate.zoompath.zoom_model_from_dict")
        data = d["data"]
        sensor = None if d.get("sensor") is None else Sensor(**d["sensor"])
        fits = {k: ParamFit.from_dict(k, f) for k, f in d["params"].items()}
        return cls(str(d["kind"]), np.asarray(data["zoom"], float),
                   {k: np.asarray(v, float) for k, v in data["values"].items()},
                   {k: np.asarray(v, float) for k, v in data.get("sd", {}).items()},
                   fits, tuple(d["zoom_range"]), sensor, dict(d.get("options", {})))
