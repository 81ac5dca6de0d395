"""Find what the simulation's principal-point model gets wrong on measured per-zoom data.

The baseline is the paper's model fitted to the measured principal points: a sensor offset plus,
for every moving group, the decentre locked to the barrel rotation (amplitude and phase, through
the group's sensitivity curve from the lens model; see :mod:`zoomcalib.diagnose.model`). A locked
tilt adds little: a group's shift per tilt is nearly proportional to its shift per decentre (the
ratio, the neutral pivot, changes by 10-25 % over the zoom range of ``laikin-10x``), so the fitted
decentre absorbs it; ``locked_tilt=True`` adds the tilt columns all the same.
Each row's noise is its measurement 1-sigma and the random-play scatter of the lens model added in
quadrature, ``sigma_i^2 = sd_i^2 + sigma_play(z_i)^2``.

Every candidate cause adds a few columns to the baseline and is fitted by weighted linear least
squares. Candidates are compared by

- cross-validation on held-out zoom settings (every row of one zoom setting left out in turn),
  ``cv_rms_px`` being the RMS of the held-out residuals (cx and cy, px);
- the Bayesian information criterion with the noise scale profiled out,
  ``BIC = n ln(chi2 / n) + k ln n`` (n residuals, k parameters), which stays fair when the
  table's sigmas are off by a common factor.

A cause is named only when its BIC is lower than the baseline's by more than
:data:`BIC_MARGIN` and it also predicts held-out steps better; otherwise the answer is ``none``.

References
----------
A. Gardel, J. L. Lázaro, J. M. Lavest, "Influence of mechanical errors in a zoom camera",
Image Anal. Stereol. 21 (2002).
R. E. Kass, A. E. Raftery, "Bayes factors", J. Am. Stat. Assoc. 90 (1995): a BIC difference
above 10 is "very strong" evidence.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..optics.mechanics import Tolerances
from .model import (
    Context,
    LensResponse,
    Term,
    axis_tilt_term,
    covariate_term,
    design_matrix,
    direction_offset_term,
    group_term,
    offset_term,
)
from .table import ZoomTable

__all__ = ["CAUSES", "BIC_MARGIN", "AMBIGUITY_BIC", "LinearFit", "Candidate", "Diagnosis",
           "baseline_terms", "cause_variants", "fit_terms", "diagnose_table", "fit_pixel_pitch"]

CAUSES = ("axis_tilt", "backlash", "thermal_drift", "cam_harmonic", "static_decenter",
          "focus_shift")
BIC_MARGIN = 10.0
#: causes whose BIC is within this of the named one's are reported as not told apart
AMBIGUITY_BIC = 6.0


def baseline_terms(groups: tuple[str, ...], locked_tilt: bool = False) -> tuple[Term, ...]:
    """Sensor offset + rotation-locked decentre (and optionally tilt) of each moving group."""
    terms = [offset_term()]
    for g in groups:
        terms.append(group_term(g, "decenter", 1, "locked decentre"))
        if locked_tilt:
            terms.append(group_term(g, "tilt", 1, "locked tilt"))
    return tuple(terms)


def _varies(col: np.ndarray | None) -> bool:
    return col is not None and np.ptp(col) > 0


def cause_variants(table: ZoomTable, groups: tuple[str, ...]
                   ) -> tuple[dict[str, list[tuple[Term, ...]]], dict[str, str]]:
    """The extensions to try, per cause, and the causes the table cannot test (with why).

    Each cause has one or more variants (e.g. one per moving group); the best variant by BIC
    stands for the cause.
    """
    variants: dict[str, list[tuple[Term, ...]]] = {}
    skipped: dict[str, str] = {}
    variants["axis_tilt"] = [(axis_tilt_term(),)]
    if table.direction is not None and {-1.0, 1.0} <= set(np.unique(table.direction)):
        variants["backlash"] = [(direction_offset_term(),)] + [
            (group_term(g, "decenter", 1, "backlash", signed_by="direction"),) for g in groups]
    else:
        skipped["backlash"] = "needs a direction column with both 'in' and 'out' rows"
    if _varies(table.temperature):
        variants["thermal_drift"] = [(covariate_term("temperature", "K", "thermal drift"),)]
    elif _varies(table.sequence):
        variants["thermal_drift"] = [(covariate_term("sequence", "capture",
                                                     "drift with capture order"),)]
    else:
        skipped["thermal_drift"] = "needs a temperature or sequence column"
    variants["cam_harmonic"] = [(group_term(g, "decenter", 2, "cam harmonic"),) for g in groups]
    variants["static_decenter"] = [(group_term(g, "decenter", 0, "static decentre"),)
                                   for g in groups]
    if _varies(table.focus):
        variants["focus_shift"] = [(covariate_term("focus", "focus_unit", "focus shift"),)]
    else:
        skipped["focus_shift"] = "needs a focus column that varies"
    return variants, skipped


@dataclass
class LinearFit:
    """Weighted linear least-squares fit of principal points.

    Attributes
    ----------
    terms : tuple of Term
    params : (K,) ndarray
    cov : (K, K) ndarray
        Covariance of the parameters, scaled by ``chi2_dof``.
    residual_px : (N, 2) ndarray
        Measured minus fitted (cx, cy), px.
    chi2, chi2_dof, rms_px, bic, cv_rms_px : float
    cv_residual_px : (N, 2) ndarray
        Held-out residuals.
    rank : int
        Number of independent columns: a linear least-squares fit is solved in one step, and
        its solution is the minimum only of the directions the data determine.
    converged : bool
        True when every parameter is determined (``rank`` equals the number of parameters).
    stop_reason : str
        ``'exact'`` (closed-form solve, full rank) or ``'rank deficient'``.
    """

    terms: tuple[Term, ...]
    params: np.ndarray
    cov: np.ndarray
    residual_px: np.ndarray
    chi2: float
    chi2_dof: float
    rms_px: float
    bic: float
    cv_rms_px: float
    cv_residual_px: np.ndarray
    rank: int = 0
    converged: bool = False
    stop_reason: str = ""

    @property
    def names(self) -> list[str]:
        return [p for t in self.terms for p in t.params]

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def param_dict(self, skip: int = 0) -> tuple[dict[str, float], dict[str, float]]:
        """Values and 1-sigma of the parameters after the first ``skip`` ones."""
        names = self.names[skip:]
        return ({n: float(v) for n, v in zip(names, self.params[skip:], strict=True)},
                {n: float(s) for n, s in zip(names, self.sd[skip:], strict=True)})

    def summary(self) -> dict:
        return {"rms_px": self.rms_px, "chi2_dof": self.chi2_dof, "cv_rms_px": self.cv_rms_px,
                "bic": self.bic, "n_params": len(self.params), "rank": self.rank,
                "converged": self.converged, "stop_reason": self.stop_reason}


#: singular values below this fraction of the largest count as zero (rank of a fit)
RCOND = 1e-10


def _solve(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, int]:
    """Weighted least-squares solution and the rank of the weighted design matrix."""
    sw = np.sqrt(w)
    beta, _, rank, _ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=RCOND)
    return beta, int(rank)


def fit_terms(terms: tuple[Term, ...], ctx: Context, sigma_px: np.ndarray,
              groups: np.ndarray) -> LinearFit:
    """Fit ``terms`` to the measured principal points of ``ctx.table``.

    Parameters
    ----------
    sigma_px : (N,) ndarray
        1-sigma per axis of each row's principal point, px.
    groups : (N,) int ndarray
        Rows sharing a label are held out together in the cross-validation.
    """
    A = design_matrix(terms, ctx)  # shape (2N, K)
    y = ctx.table.principal_point.reshape(-1)  # shape (2N,)
    w = np.repeat(1.0 / sigma_px ** 2, 2)
    n, k = A.shape
    if n <= k:
        raise ValueError(f"{ctx.table.source}: {n // 2} rows cannot fit {k} parameters")
    beta, rank = _solve(A, y, w)
    r = y - A @ beta
    chi2 = float(np.sum(w * r ** 2))
    dof = n - k
    cov = np.linalg.pinv((A * w[:, None]).T @ A, rcond=1e-12) * (chi2 / dof)
    rows = np.repeat(groups, 2)
    cv = np.empty_like(y)
    for label in np.unique(groups):
        out = rows == label
        b, _ = _solve(A[~out], y[~out], w[~out])
        cv[out] = y[out] - A[out] @ b
    return LinearFit(terms, beta, cov, r.reshape(-1, 2), chi2, chi2 / dof,
                     float(np.sqrt(np.mean(r ** 2))),
                     float(n * np.log(chi2 / n) + k * np.log(n)),
                     float(np.sqrt(np.mean(cv ** 2))), cv.reshape(-1, 2), rank, rank == k,
                     "exact" if rank == k else "rank deficient")


@dataclass
class Candidate:
    """One cause's best variant."""

    cause: str
    fit: LinearFit
    n_baseline: int
    delta_bic: float
    variant: str

    def to_dict(self) -> dict:
        params, sds = self.fit.param_dict(self.n_baseline)
        return {"cause": self.cause, "variant": self.variant, "cv_rms_px": self.fit.cv_rms_px,
                "rms_px": self.fit.rms_px, "chi2_dof": self.fit.chi2_dof,
                "delta_bic": self.delta_bic, "params": params, "params_sd": sds}


@dataclass
class Diagnosis:
    """Result of :func:`diagnose_table`.

    Attributes
    ----------
    cause : str
        The named cause, or ``"none"``.
    baseline : LinearFit
    candidates : list of Candidate
        Sorted by ``delta_bic`` (best first).
    extended : Candidate or None
        The named cause's fit (None when ``cause == 'none'``).
    z : (N,) ndarray
        Lens state of every row, from its focal length.
    sigma_px : (N,) ndarray
        Per-row noise used (measurement and play in quadrature), px.
    play_sd_px : (N,) ndarray
    pitch_mm : float
    pitch_fit : dict or None
        Fitted pitch and its 1-sigma when the pitch was fitted.
    skipped : dict
        Causes the table cannot test, with why.
    """

    cause: str
    baseline: LinearFit
    candidates: list[Candidate]
    extended: Candidate | None
    table: ZoomTable
    response: LensResponse
    z: np.ndarray
    sigma_px: np.ndarray
    play_sd_px: np.ndarray
    pitch_mm: float
    pitch_fit: dict | None = None
    skipped: dict = field(default_factory=dict)

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None

    @property
    def converged(self) -> bool:
        """Every fit behind the answer determined all its parameters (full rank), and a fitted
        pitch has its minimum inside the admissible range."""
        fits = [self.baseline] + [c.fit for c in self.candidates]
        return (all(f.converged for f in fits)
                and (self.pitch_fit is None or self.pitch_fit["converged"]))

    @property
    def ambiguous_with(self) -> list[str]:
        """Other causes that fit almost as well as the named one (BIC within AMBIGUITY_BIC)."""
        if self.extended is None:
            return []
        return [c.cause for c in self.candidates[1:]
                if c.delta_bic - self.extended.delta_bic < AMBIGUITY_BIC
                and c.delta_bic < -BIC_MARGIN]

    def to_dict(self) -> dict:
        """The ``diagnosis.json`` document."""
        if self.extended is not None:
            ext_fit = self.extended.fit
            params, sds = ext_fit.param_dict(self.extended.n_baseline)
            ext = {"cause": self.cause, "variant": self.extended.variant, **ext_fit.summary(),
                   "params": params, "params_sd": sds}
        else:
            ext_fit = self.baseline
            ext = {"cause": "none", "variant": "", **ext_fit.summary(), "params": {},
                   "params_sd": {}}
        base_params, base_sd = self.baseline.param_dict()
        return {
            "cause": self.cause,
            "converged": self.converged,
            "ambiguous_with": self.ambiguous_with,
            "baseline": {**self.baseline.summary(), "params": base_params,
                         "params_sd": base_sd},
            "extended": ext,
            "gain": {"cv_rms_ratio": self.baseline.cv_rms_px / ext_fit.cv_rms_px},
            "candidates": [c.to_dict() for c in self.candidates],
            "skipped": [{"cause": k, "reason": v} for k, v in self.skipped.items()],
            "selection": {"bic_margin": BIC_MARGIN, "ambiguity_bic": AMBIGUITY_BIC,
                          "rule": "name the cause with the lowest BIC when it beats the "
                                  "baseline by more than bic_margin and also lowers the "
                                  "held-out-step cv_rms_px; else 'none'"},
            "lens": self.response.lens.name, "moving_groups": list(self.response.groups),
            "pixel_pitch_mm": self.pitch_mm, "pitch_fit": self.pitch_fit,
            "noise": {"rms_sigma_px": float(np.sqrt(np.mean(self.sigma_px ** 2))),
                      "rms_play_px": float(np.sqrt(np.mean(self.play_sd_px ** 2))),
                      "measurement_sd_used": self.table.has_sd},
            "rows": [{"step": s, "zoom": float(zz), "lens_state": float(z),
                      "efl_mm": float(f * self.pitch_mm), "sigma_px": float(sg),
                      "baseline_residual_px": [float(v) for v in rb],
                      "extended_residual_px": [float(v) for v in re]}
                     for s, zz, z, f, sg, rb, re in zip(
                         self.table.step, self.table.zoom, self.z, self.table.fx,
                         self.sigma_px, self.baseline.residual_px, ext_fit.residual_px,
                         strict=True)],
        }


def _noise(table: ZoomTable, response: LensResponse, z: np.ndarray,
           tolerances: Tolerances) -> tuple[np.ndarray, np.ndarray]:
    play = response.play_sd_px(z, tolerances)
    meas2 = 0.5 * (table.sd_cx ** 2 + table.sd_cy ** 2)
    sigma = np.sqrt(meas2 + play ** 2)
    if not np.all(sigma > 0):
        # no sigma known anywhere: equal weights, the scale comes from the residuals
        sigma = np.ones(table.n)
    return sigma, play


def fit_pixel_pitch(table: ZoomTable, response: LensResponse, tolerances: Tolerances,
                    n_grid: int = 121, locked_tilt: bool = False) -> dict:
    """Fit the pixel pitch (a scale between measured px and the lens's mm) with the baseline.

    The admissible pitches keep every measured focal length inside the lens's EFL range. On a
    geometric grid of them the baseline is fitted and scored by its Gaussian deviance
    ``D = chi2 + 2 sum ln sigma_i`` (the play part of ``sigma_i`` is in px and so depends on the
    pitch; chi2 alone would favour the pitch with the largest play). The pitch is told by where the
    spiral's phase, locked to the barrel angle of each row's lens state, fits best; the 1-sigma
    is half the width of the interval with ``D - min D <= 1`` (``D`` scaled by the best fit's
    ``chi2_dof`` when that exceeds 1). ``at_range_end`` flags a minimum at an end of the
    admissible range: the data do not determine the pitch.

    Returns
    -------
    dict with ``pitch_mm``, ``sd_mm``, ``range_mm``, ``at_range_end``, ``converged`` (a
    minimum inside the range) and ``stop_reason`` (``'grid minimum'`` or ``'range end'``).
    """
    lo, hi = response.pitch_range(table.fx, table.source)
    grid = np.geomspace(lo, hi, n_grid) if hi > lo else np.array([lo])
    groups = table.zoom_groups()
    terms = baseline_terms(response.groups, locked_tilt)
    deviance = np.empty(len(grid))
    chi2_dof = np.empty(len(grid))
    for i, p in enumerate(grid):
        r = response.with_pitch(p)
        z = r.state_of_focal(table.fx, table.source)
        sigma, _ = _noise(table, r, z, tolerances)
        f = fit_terms(terms, Context.build(table, z, r), sigma, groups)
        deviance[i] = f.chi2 + 4.0 * np.sum(np.log(sigma))  # two coordinates per row
        chi2_dof[i] = f.chi2_dof
    best = int(np.argmin(deviance))
    scale = max(chi2_dof[best], 1.0)
    inside = grid[(deviance - deviance[best]) / scale <= 1.0]
    at_end = best in (0, len(grid) - 1)
    return {"pitch_mm": float(grid[best]), "sd_mm": float(0.5 * np.ptp(inside)),
            "range_mm": [lo, hi], "at_range_end": at_end, "converged": not at_end,
            "stop_reason": "range end" if at_end else "grid minimum"}


def diagnose_table(table: ZoomTable, response: LensResponse,
                   tolerances: Tolerances | None = None, fit_pitch: bool = False,
                   locked_tilt: bool = False) -> Diagnosis:
    """Fit the baseline and every testable cause to ``table``; name the cause, or ``none``.

    Parameters
    ----------
    table : ZoomTable
    response : LensResponse
        The lens model and the pixel pitch (ignored when ``fit_pitch``).
    tolerances : Tolerances, optional
        For the random-play scatter (default: the built-in tolerances).
    fit_pitch : bool
        Fit the pixel pitch too (:func:`fit_pixel_pitch`).
    locked_tilt : bool
        Give the baseline the locked tilt of each moving group as well as its decentre.

    Returns
    -------
    Diagnosis

    Examples
    --------
    A table with a hidden backlash of the moving groups (8x the noise), from the exact tracer:

    >>> import numpy as np
    >>> from zoomcalib.diagnose import LensResponse, ZoomTable, synthetic_zoom_table
    >>> from zoomcalib.optics.prescription import load_prescription
    >>> lens = load_prescription("laikin-10x")
    >>> rows, truth = synthetic_zoom_table(lens, "backlash", np.random.default_rng(1),
    ...                                    magnitude=8.0)
    >>> diag = diagnose_table(ZoomTable.from_rows(rows), LensResponse.of(lens))
    >>> diag.cause, diag.to_dict()["gain"]["cv_rms_ratio"] > 2
    ('backlash', True)
    """
    from ..optics.mechanics import load_tolerances

    tolerances = tolerances if tolerances is not None else load_tolerances()
    pitch_fit = None
    if fit_pitch:
        pitch_fit = fit_pixel_pitch(table, response, tolerances, locked_tilt=locked_tilt)
        response = response.with_pitch(pitch_fit["pitch_mm"])
    z = response.state_of_focal(table.fx, table.source)
    sigma, play = _noise(table, response, z, tolerances)
    ctx = Context.build(table, z, response)
    groups = table.zoom_groups()
    if len(np.unique(groups)) < 3:
        raise ValueError(f"{table.source}: {len(np.unique(groups))} distinct zoom settings; "
                         f"at least 3 are needed to hold steps out")
    base_terms = baseline_terms(response.groups, locked_tilt)
    base = fit_terms(base_terms, ctx, sigma, groups)
    variants, skipped = cause_variants(table, response.groups)
    candidates = []
    for cause, options in variants.items():
        fits = [(fit_terms(base_terms + extra, ctx, sigma, groups), extra) for extra in options]
        f, extra = min(fits, key=lambda fe: fe[0].bic)
        candidates.append(Candidate(cause, f, len(base.params), f.bic - base.bic,
                                    " + ".join(t.name for t in extra)))
    candidates.sort(key=lambda c: c.delta_bic)
    best = candidates[0] if candidates else None
    named = (best is not None and best.delta_bic < -BIC_MARGIN
             and best.fit.cv_rms_px < base.cv_rms_px)
    return Diagnosis(best.cause if named else "none", base, candidates,
                     best if named else None, table, response, z, sigma, play,
                     response.pitch_mm, pitch_fit, skipped)
