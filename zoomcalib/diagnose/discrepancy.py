"""Find what the simulation's principal-point model gets wrong on measured per-zoom data.

The baseline is the paper's model fitted to the measured principal points: a sensor offset plus,
for every moving group, the decentre locked to the barrel rotation (amplitude and phase, through
the group's sensitivity curve from the lens model; see :mod:`zoomcalib.diagnose.model`). A locked
tilt adds little: a group's shift per tilt is nearly proportional to its shift per decentre (the
ratio, the neutral pivot, changes by 10-25 % over the zoom range of ``laikin-10x``), so the fitted
decentre absorbs it; ``locked_tilt=True`` adds the tilt columns all the same. Without a lens
model (``response=None``) the baseline is a principal-point path smooth in log focal length
(Legendre degree chosen by BIC), and only the causes that need no optics are tested.

Noise. Each row's per-axis variance is ``v_i = s^2 sd_i^2 + p^2 play_i^2``: the table's own
sigmas times a common scale ``s``, and the random play of the lens model (the tolerance file's)
times a scale ``p``; both scales are estimated for every model by REML with the table's sigmas
and the tolerance file as weak priors (:mod:`zoomcalib.diagnose.noise`).

Every candidate cause adds a few columns to the baseline and is fitted by weighted linear least
squares. Models are compared by

- the Bayesian information criterion ``BIC = -2 ln L + k ln n`` (``L`` the Gaussian likelihood at
  the model's own noise estimate, n residuals, k parameters);
- cross-validation on held-out zoom settings (every row of one zoom setting left out in turn):
  ``cv_rms_px`` the RMS of the held-out residuals (px) and, for a fair comparison of rows whose
  sigmas differ many-fold, ``cv_norm_ratio``: the RMS of the held-out residuals divided by each
  row's sigma, baseline over extended, both at the extended model's noise.

Causes are selected together, forward then backward (:func:`select_causes`): a cause enters when
it lowers the BIC by more than :data:`BIC_MARGIN` and the held-out normalised residuals too, and
leaves when removing it raises the BIC by less than that. The answer is then checked absolutely
(:func:`fit_check`): what the chosen model leaves must show no structure over the zoom setting,
the direction of the last zoom move or the capture order (F-tests), and its estimated noise must
not exceed :data:`NOISE_SCALE_MAX` times what the table's sigmas and the tolerance file claim.
A model that fails is reported as ``explained: false`` with what remains, and its causes as
improving, not as the answer (``cause = 'unexplained'``).

References
----------
A. Gardel, J. L. Lázaro, J. M. Lavest, "Influence of mechanical errors in a zoom camera",
Image Anal. Stereol. 21 (2002).
R. E. Kass, A. E. Raftery, "Bayes factors", J. Am. Stat. Assoc. 90 (1995): a BIC difference
above 10 is "very strong" evidence.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from ..optics.mechanics import Tolerances
from .model import (
    Context,
    LensResponse,
    Term,
    axis_tilt_term,
    covariate_curve_term,
    covariate_term,
    design_matrix,
    direction_offset_term,
    group_term,
    log_focal_coordinate,
    offset_term,
    setting_term,
    smooth_path_term,
)
from .noise import NoiseFit, NoiseShape, RowWeights, estimate_noise, gls
from .table import ZoomTable

__all__ = ["CAUSES", "BIC_MARGIN", "AMBIGUITY_BIC", "ALPHA", "NOISE_SCALE_MAX", "LinearFit",
           "Candidate", "Diagnosis", "baseline_terms", "cause_variants", "fit_terms",
           "select_causes", "fit_check", "diagnose_table", "fit_pixel_pitch", "noise_shape"]

CAUSES = ("axis_tilt", "backlash", "thermal_drift", "cam_harmonic", "static_decenter",
          "focus_shift")
BIC_MARGIN = 10.0
#: causes whose BIC is within this of the named one's are reported as not told apart
AMBIGUITY_BIC = 6.0
#: family-wise false-alarm rate of the structure tests of :func:`fit_check`
ALPHA = 0.01
#: the rows may scatter up to this factor more than the table's sigmas and the tolerance
#: file's play say (RMS over the rows) and the model still explain them
NOISE_SCALE_MAX = 3.0
#: a fit whose held-out rows miss by more than this many of their sigmas (RMS, ``cv_norm``)
#: does not explain the table, whatever else could be checked (honest fits: about 1-2)
CV_NORM_MAX = 10.0
#: degree of the capture-order drift the fit check tests against (the drift causes go to 3)
ORDER_TEST_DEGREE = 5
#: most causes selected together
MAX_CAUSES = 3
#: highest degree of the smooth path of a lens without a model (and at most the number of
#: zoom settings less 2)
MAX_PATH_DEGREE = 8


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


def _both_directions(table: ZoomTable) -> bool:
    return table.direction is not None and {-1.0, 1.0} <= set(np.unique(table.direction))


NEEDS_OPTICS = "needs the lens model's barrel angle and sensitivities (--lens none)"
TILT_NOT_IDENTIFIABLE = ("without a lens model the baseline is a smooth path in log f, and an "
                         "axis tilt's fx * theta is itself smooth in log f: not identifiable")


def cause_variants(table: ZoomTable, groups: tuple[str, ...] | None
                   ) -> tuple[dict[str, list[tuple[Term, ...]]], dict[str, str]]:
    """The extensions to try, per cause, and the causes the table cannot test (with why).

    Each cause has one or more variants (e.g. one per moving group); the best variant by BIC
    stands for the cause. ``groups`` None: no lens model, only the causes that need no optics.
    """
    variants: dict[str, list[tuple[Term, ...]]] = {}
    skipped: dict[str, str] = {}
    if groups is None:
        skipped["axis_tilt"] = TILT_NOT_IDENTIFIABLE
    else:
        variants["axis_tilt"] = [(axis_tilt_term(),)]
    if _both_directions(table):
        variants["backlash"] = [(direction_offset_term(),)] + [
            (group_term(g, "decenter", 1, "backlash", signed_by="direction"),)
            for g in groups or ()]
        if groups is None:
            fx = table.fx
            variants["backlash"] += [
                (smooth_path_term(d, float(fx.min()), float(fx.max()), signed=True),)
                for d in range(1, min(3, _max_path_degree(table)) + 1)]
    else:
        skipped["backlash"] = "needs a direction column with both 'in' and 'out' rows"
    if _varies(table.temperature):
        variants["thermal_drift"] = [(covariate_term("temperature", "K", "thermal drift"),)] + [
            (covariate_curve_term("temperature", d, "thermal drift"),) for d in (2, 3)]
    elif _varies(table.sequence):
        variants["thermal_drift"] = [
            (covariate_term("sequence", "capture", "drift with capture order"),)] + [
            (covariate_curve_term("sequence", d, "drift with capture order"),) for d in (2, 3)]
    else:
        skipped["thermal_drift"] = "needs a temperature or sequence column"
    if groups is None:
        skipped["cam_harmonic"] = skipped["static_decenter"] = NEEDS_OPTICS
    else:
        variants["cam_harmonic"] = [(group_term(g, "decenter", 2, "cam harmonic"),)
                                    for g in groups]
        variants["static_decenter"] = [(group_term(g, "decenter", 0, "static decentre"),)
                                       for g in groups]
    if _varies(table.focus):
        variants["focus_shift"] = [(covariate_term("focus", "focus_unit", "focus shift"),)]
    else:
        skipped["focus_shift"] = "needs a focus column that varies"
    return variants, {c: skipped[c] for c in CAUSES if c in skipped}


@dataclass
class LinearFit:
    """Weighted linear least-squares fit of principal points.

    Attributes
    ----------
    terms : tuple of Term
    params : (K,) ndarray
    cov : (K, K) ndarray
        Covariance of the parameters at the fit's noise.
    residual_px : (N, 2) ndarray
        Measured minus fitted (cx, cy), px.
    variance : (N,) ndarray
        Per-axis noise variance of each row used by the fit, px^2.
    chi2 : float
        Sum of squared residuals over ``variance``; ``chi2_dof`` per degree of freedom.
    rms_px, cv_rms_px : float
        RMS of the residuals and of the held-out residuals, px.
    bic : float
        ``-2 ln L + K ln n`` without the constant ``n ln 2 pi``.
    cv_residual_px : (N, 2) ndarray
        Held-out residuals (every row of a zoom setting left out together; without a lens
        model every row on its own).
    rank : int
        Number of independent columns: a linear least-squares fit is solved in one step, and
        its solution is the minimum only of the directions the data determine.
    converged : bool
        Every parameter is determined (``rank`` equals the number of parameters) and a noise
        estimate, when made, converged.
    stop_reason : str
        ``'exact'`` (closed-form solve, full rank), ``'rank deficient'`` or ``'noise not
        converged'``.
    noise : NoiseFit or None
        The estimated noise scales (None when the noise was given).
    weights : RowWeights or None
        The weights the fit used (None: ``variance`` per row, independent rows).
    """

    terms: tuple[Term, ...]
    params: np.ndarray
    cov: np.ndarray
    residual_px: np.ndarray
    variance: np.ndarray
    chi2: float
    chi2_dof: float
    rms_px: float
    bic: float
    cv_rms_px: float
    cv_residual_px: np.ndarray
    rank: int = 0
    converged: bool = False
    stop_reason: str = ""
    noise: NoiseFit | None = None
    weights: RowWeights | None = None

    @property
    def names(self) -> list[str]:
        return [p for t in self.terms for p in t.params]

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def cv_norm_rms(self, variance: np.ndarray | None = None) -> float:
        """RMS of the held-out residuals over each row's sigma (``variance`` default: the
        fit's own), dimensionless."""
        v = self.variance if variance is None else variance
        return float(np.sqrt(np.mean(self.cv_residual_px ** 2 / v[:, None])))

    def param_dict(self, skip: int = 0) -> tuple[dict[str, float], dict[str, float]]:
        """Values and 1-sigma of the parameters after the first ``skip`` ones. A name that two
        terms share (e.g. a static decentre and a cam harmonic of one group) is qualified by
        its term's name, ``"variator_x_um (cam harmonic, variator)"``."""
        labels = [(p, t.name) for t in self.terms for p in t.params][skip:]
        repeated = {p for p, _ in labels if sum(q == p for q, _ in labels) > 1}
        names = [f"{p} ({term})" if p in repeated else p for p, term in labels]
        return ({n: float(v) for n, v in zip(names, self.params[skip:], strict=True)},
                {n: float(s) for n, s in zip(names, self.sd[skip:], strict=True)})

    def summary(self) -> dict:
        return {"rms_px": self.rms_px, "chi2_dof": self.chi2_dof, "cv_rms_px": self.cv_rms_px,
                "cv_norm_rms": self.cv_norm_rms(), "bic": self.bic,
                "n_params": len(self.params), "rank": self.rank, "converged": self.converged,
                "stop_reason": self.stop_reason,
                "noise": self.noise.to_dict() if self.noise is not None else None}


def _held_out(A: np.ndarray, y: np.ndarray, weights: RowWeights, groups: np.ndarray
              ) -> np.ndarray:
    """(2N,) residuals of every group's rows predicted from the other groups' rows (their
    weights among themselves: a correlated held-out row does not inform the fit)."""
    rows = np.repeat(groups, 2)
    cv = np.empty_like(y)
    for label in np.unique(groups):
        out = rows == label
        beta, _, _ = gls(A[~out], y[~out], weights.subset(~out))
        cv[out] = y[out] - A[out] @ beta
    return cv


def fit_terms(terms: tuple[Term, ...], ctx: Context, noise: NoiseShape | np.ndarray,
              groups: np.ndarray) -> LinearFit:
    """Fit ``terms`` to the measured principal points of ``ctx.table``.

    Parameters
    ----------
    noise : NoiseShape or (N,) ndarray
        The noise shapes, whose scales are estimated for this model by REML (with the rows'
        correlation when the shape has one), or the 1-sigma per axis of each row, px, taken
        as known (independent rows).
    groups : (N,) int ndarray
        Rows sharing a label are held out together in the cross-validation.
    """
    A = design_matrix(terms, ctx)  # shape (2N, K)
    y = ctx.table.principal_point.reshape(-1)  # shape (2N,)
    n, k = A.shape
    if n <= k:
        raise ValueError(f"{ctx.table.source}: {n // 2} rows cannot fit {k} parameters")
    noise_fit = estimate_noise(A, y, noise) if isinstance(noise, NoiseShape) else None
    if noise_fit is not None:
        variance, weights = noise_fit.variance, noise_fit.weights
    else:
        variance = np.asarray(noise) ** 2
        weights = RowWeights(np.repeat(1.0 / variance, 2))
    beta, rank, _ = gls(A, y, weights)
    r = y - A @ beta
    chi2 = weights.chi2(r)
    cov = np.linalg.pinv(weights.normal(A), rcond=1e-12)
    cv = _held_out(A, y, weights, groups)
    converged = rank == k and (noise_fit is None or noise_fit.converged)
    reason = ("rank deficient" if rank < k else
              "noise not converged" if not converged else "exact")
    return LinearFit(terms, beta, cov, r.reshape(-1, 2), variance, chi2, chi2 / (n - k),
                     float(np.sqrt(np.mean(r ** 2))),
                     float(chi2 + weights.log_det() + k * np.log(n)),
                     float(np.sqrt(np.mean(cv ** 2))), cv.reshape(-1, 2), rank, converged,
                     reason, noise_fit, weights)


class Fitter:
    """``fit_terms`` over one table and noise, remembering the fits it has made (the selection
    revisits the same models)."""

    def __init__(self, ctx: Context, noise: NoiseShape | np.ndarray, groups: np.ndarray,
                 holdout: np.ndarray | None = None):
        self.ctx, self.noise, self.groups = ctx, noise, groups
        self.holdout = groups if holdout is None else holdout
        self._fits: dict[tuple[str, ...], LinearFit] = {}

    def can_fit(self, terms: tuple[Term, ...]) -> bool:
        """Whether the rows outside any one zoom setting determine every parameter."""
        _, counts = np.unique(self.groups, return_counts=True)
        return sum(len(t.params) for t in terms) <= 2 * (len(self.groups) - counts.max())

    def __call__(self, terms: tuple[Term, ...]) -> LinearFit:
        key = tuple(sorted(t.name for t in terms))
        if key not in self._fits:
            self._fits[key] = fit_terms(terms, self.ctx, self.noise, self.holdout)
        return self._fits[key]


def cv_norm_ratio(before: LinearFit, after: LinearFit) -> float:
    """Held-out RMS of sigma-normalised residuals, ``before`` over ``after``, both normalised
    by ``after``'s noise (the model that claims to explain more sets the yardstick)."""
    return before.cv_norm_rms(after.variance) / after.cv_norm_rms()


@dataclass
class Candidate:
    """A cause (or several, joined by ``' + '``) added to the baseline, and its fit."""

    cause: str
    fit: LinearFit
    n_baseline: int
    delta_bic: float
    variant: str

    def to_dict(self) -> dict:
        params, sds = self.fit.param_dict(self.n_baseline)
        return {"cause": self.cause, "variant": self.variant, "cv_rms_px": self.fit.cv_rms_px,
                "cv_norm_rms": self.fit.cv_norm_rms(), "rms_px": self.fit.rms_px,
                "chi2_dof": self.fit.chi2_dof, "delta_bic": self.delta_bic, "params": params,
                "params_sd": sds}


@dataclass
class Selected:
    """One cause of the selected model: its terms, and what removing it costs.

    ``drop_bic`` is the rise of the BIC when the cause is taken out of the selected model (the
    larger, the stronger the evidence); ``params``/``params_sd`` its parameters in that model.
    ``evidence``: why the cause is in the model when other evidence than the principal points
    put it there (:func:`select_causes` ``required``), else empty.
    """

    cause: str
    terms: tuple[Term, ...]
    drop_bic: float = 0.0
    params: dict = field(default_factory=dict)
    params_sd: dict = field(default_factory=dict)
    evidence: str = ""

    @property
    def variant(self) -> str:
        return " + ".join(t.name for t in self.terms)

    def to_dict(self) -> dict:
        out = {"cause": self.cause, "variant": self.variant, "drop_bic": self.drop_bic,
               "params": self.params, "params_sd": self.params_sd}
        return out | ({"evidence": self.evidence} if self.evidence else {})


def _with(base: tuple[Term, ...], chosen: list[Selected]) -> tuple[Term, ...]:
    return base + tuple(t for s in chosen for t in s.terms)


def _better(current: LinearFit, trial: LinearFit) -> bool:
    """``trial`` beats ``current`` by BIC and predicts held-out settings better (normalised
    by ``trial``'s noise)."""
    return (trial.bic < current.bic - BIC_MARGIN
            and trial.cv_norm_rms() < current.cv_norm_rms(trial.variance))


def _best_variant(fitter: Fitter, base, chosen, cause, options
                  ) -> tuple[LinearFit, Selected] | None:
    """The variant of ``cause`` that, added to ``base`` and ``chosen``, has the lowest BIC
    (None when the table has too few rows for any)."""
    trials = [(fitter(_with(base, chosen + [Selected(cause, extra)])), Selected(cause, extra))
              for extra in options
              if fitter.can_fit(_with(base, chosen + [Selected(cause, extra)]))]
    return min(trials, key=lambda fs: fs[0].bic, default=None)


def select_causes(fitter: Fitter, base: tuple[Term, ...],
                  variants: dict[str, list[tuple[Term, ...]]],
                  required: dict[str, str] | None = None
                  ) -> tuple[LinearFit, list[Selected]]:
    """Forward-backward selection of causes over the baseline.

    Forward: of the causes not yet in, the one whose best variant gives the lowest BIC enters
    when it beats the current model (:data:`BIC_MARGIN` and held-out normalised residuals).
    Backward: the cause whose removal raises the BIC least leaves when that rise is below
    :data:`BIC_MARGIN`. Repeated until nothing changes (a set of causes is entered once),
    with at most :data:`MAX_CAUSES`. ``required`` causes (name: the evidence for it) are in
    from the start, by their best variant, and never leave.

    Returns
    -------
    The selected model's fit and its causes, with ``drop_bic`` and parameters filled in.
    """
    chosen = _required(fitter, base, variants, required or {})
    base_fit = fitter(_with(base, chosen))
    current, seen = base_fit, {frozenset(s.cause for s in chosen)}
    keep = len(chosen)  # the required causes lead the list and stay
    changed = True
    while changed:
        changed = False
        names = {s.cause for s in chosen}
        if len(chosen) < MAX_CAUSES:
            trials = [_best_variant(fitter, base, chosen, c, opts)
                      for c, opts in variants.items() if c not in names]
            trials = [(f, s) for f, s in filter(None, trials) if _better(current, f)
                      and frozenset(names | {s.cause}) not in seen]
            if trials:
                current, new = min(trials, key=lambda fs: fs[0].bic)
                chosen.append(new)
                seen.add(frozenset(names | {new.cause}))
                changed = True
        if len(chosen) > max(1, keep):
            rise, i, fit = min(((f.bic - current.bic, i, f) for i, f in
                                enumerate(_drop_each(fitter, base, chosen)) if i >= keep),
                               key=lambda t: t[0])
            if rise < BIC_MARGIN:
                chosen.pop(i)
                current, changed = fit, True
    _describe(fitter, base, chosen, current)
    return current, chosen


def _required(fitter: Fitter, base, variants, required: dict[str, str]) -> list[Selected]:
    """The ``required`` causes, each by its best variant, with its evidence."""
    chosen: list[Selected] = []
    for cause, evidence in required.items():
        if cause not in variants:
            raise ValueError(f"{fitter.ctx.table.source}: cause {cause!r} cannot be required: "
                             f"the table cannot test it")
        best = _best_variant(fitter, base, chosen, cause, variants[cause])
        if best is not None:
            chosen.append(best[1])
            chosen[-1].evidence = evidence
    return chosen


def _drop_each(fitter: Fitter, base, chosen) -> list[LinearFit]:
    """The fits of the model with each chosen cause taken out in turn."""
    return [fitter(_with(base, chosen[:i] + chosen[i + 1:])) for i in range(len(chosen))]


def _describe(fitter: Fitter, base, chosen, final) -> None:
    """Fill in each chosen cause's ``drop_bic`` and parameters from the final model, and
    order them: the required ones first (other evidence than the principal points put them
    in, so their ``drop_bic`` on the principal points understates them), then by
    ``drop_bic``."""
    drops = _drop_each(fitter, base, chosen)
    start = sum(len(t.params) for t in base)
    names = final.names
    for s, without in zip(chosen, drops, strict=True):
        k = sum(len(t.params) for t in s.terms)
        own = slice(start, start + k)
        s.params = dict(zip(names[own], final.params[own].tolist(), strict=True))
        s.params_sd = dict(zip(names[own], final.sd[own].tolist(), strict=True))
        s.drop_bic = float(without.bic - final.bic)
        start += k
    chosen.sort(key=lambda s: (not s.evidence, -s.drop_bic))


def _structure_terms(ctx: Context, groups: np.ndarray) -> list[tuple[str, tuple[Term, ...]]]:
    """The alternatives the fit check tests the residuals against, by name."""
    table = ctx.table
    n_settings = len(np.unique(groups))
    if n_settings < table.n:  # repeated visits: any function of the zoom setting
        zoom = setting_term(groups)
    else:
        zoom = smooth_path_term(min(3, n_settings - 2), table.fx.min(), table.fx.max())
    tests = [("zoom", (zoom,))]
    if _both_directions(table):
        if _each_setting_both_ways(table, groups):  # any in/out difference at any setting
            tests.append(("direction", (setting_term(groups, signed=True),)))
        else:
            tests.append(("direction", (direction_offset_term(),)))
    if _varies(table.sequence):
        tests.append(("order", (covariate_curve_term("sequence", ORDER_TEST_DEGREE,
                                                     "capture order"),)))
    return tests


def _each_setting_both_ways(table: ZoomTable, groups: np.ndarray) -> bool:
    return all({-1.0, 1.0} <= set(table.direction[groups == g]) for g in np.unique(groups))


def _f_test(fit: LinearFit, ctx: Context, extra: tuple[Term, ...]) -> dict:
    """F-test of the fit against the fit with ``extra`` columns, at the fit's noise."""
    A = design_matrix(fit.terms, ctx)
    B = np.hstack([A, design_matrix(extra, ctx)])
    y = ctx.table.principal_point.reshape(-1)
    weights = fit.weights or RowWeights(np.repeat(1.0 / fit.variance, 2))
    beta, rank, _ = gls(B, y, weights)
    rss = weights.chi2(y - B @ beta)
    q, dof = rank - fit.rank, len(y) - rank
    if q <= 0 or dof <= 0:
        return {"tested": False, "q": q, "dof": dof}
    f = ((fit.chi2 - rss) / q) / (rss / dof)
    return {"tested": True, "q": q, "dof": dof, "F": float(f),
            "p_value": float(stats.f.sf(f, q, dof))}


def fit_check(fit: LinearFit, ctx: Context, groups: np.ndarray,
              shape: NoiseShape | None = None) -> dict:
    """Whether ``fit`` explains the table: no structure left, and plausible noise.

    Three F-tests ask whether what the fit leaves still depends on

    - ``zoom``: the zoom setting (a free principal point per setting when settings were
      visited more than once, else a cubic in log f);
    - ``direction``: the direction of the last zoom move (a free difference between moves in
      and out at every setting when each was reached both ways, else an offset signed by it);
    - ``order``: the capture order (a drift of degree :data:`ORDER_TEST_DEGREE`, above the
      drifts the causes fit),

    each at the fit's noise, ``F = ((chi2 - chi2_alt) / q) / (chi2_alt / dof_alt)``, significant
    below ``ALPHA / (number of tests)`` (Bonferroni). With a lens model and a table with
    sigmas, the noise must also be plausible: the estimated scatter ``noise_scale =
    sqrt(mean(v_i / v0_i))`` against the noise the table and the tolerance file claim
    (``v0``: ``s = p = 1``) at most :data:`NOISE_SCALE_MAX`; ``chi2_dof_assumed`` is the fit's
    chi2 per degree of freedom at ``v0`` (the classic chi2 check, reported).

    Returns
    -------
    dict with ``explained`` (True, False, or None when nothing could be tested), ``tests``
    (per test its F, q, dof, p_value and ``significant``), ``chi2_dof_assumed`` and
    ``noise_scale`` (None without sigmas or lens model) and ``remaining`` (what the fit leaves
    unexplained, in words). Whatever else can be checked, a fit whose held-out rows miss by
    more than :data:`CV_NORM_MAX` of their sigmas (``cv_norm_rms``) does not explain the table.
    """
    tests = {name: _f_test(fit, ctx, extra) for name, extra in _structure_terms(ctx, groups)}
    tested = [t for t in tests.values() if t["tested"]]
    for t in tested:
        t["significant"] = t["p_value"] < ALPHA / len(tested)
    remaining = [f"structure over the {name} (F = {t['F']:.1f}, p = {t['p_value']:.1g})"
                 for name, t in tests.items() if t.get("significant")]
    assumed = ctx.table.has_sd and shape is not None and shape.play_prior
    scale = chi2_assumed = None
    if assumed:
        # the noise the table and the tolerance file claim: s = 1, p = 1
        v0 = shape.variance(1.0, 1.0)
        scale = float(np.sqrt(np.mean(fit.variance / v0)))
        chi2_assumed = float(np.sum(fit.residual_px ** 2 / v0[:, None])
                             / (2 * ctx.table.n - fit.rank))
        if scale > NOISE_SCALE_MAX:
            remaining.append(f"scatter {scale:.1f}x what the table's sigmas and the tolerance "
                             f"file's play allow (more than {NOISE_SCALE_MAX:g}x)")
    elif ctx.table.has_sd and shape is not None:
        # no play to weigh it against (no lens model): the table's own sigmas alone
        scale = float(np.sqrt(np.mean(fit.variance / np.maximum(shape.measured_var, 1e-300))))
        chi2_assumed = float(np.sum(fit.residual_px ** 2 / shape.measured_var[:, None])
                             / max(2 * ctx.table.n - fit.rank, 1))
        assumed = True
        if scale > NOISE_SCALE_MAX:
            remaining.append(f"scatter {scale:.1f}x the table's own sigmas (more than "
                             f"{NOISE_SCALE_MAX:g}x): the path leaves what the rows' "
                             "calibrations do not allow")
    held_out = fit.cv_norm_rms()
    if held_out > CV_NORM_MAX:
        remaining.append(f"held-out rows missed by {held_out:.3g} of their sigmas (RMS; more "
                         f"than {CV_NORM_MAX:g}): the model does not predict the rows it did not "
                         "see")
    explained = (None if not tested and not assumed and held_out <= CV_NORM_MAX
                 else not remaining)
    return {"explained": explained, "tests": tests, "chi2_dof_assumed": chi2_assumed,
            "cv_norm_rms": held_out, "cv_norm_max": CV_NORM_MAX,
            "noise_scale": scale, "alpha": ALPHA, "noise_scale_max": NOISE_SCALE_MAX,
            "remaining": "; ".join(remaining)}


@dataclass
class Diagnosis:
    """Result of :func:`diagnose_table`.

    Attributes
    ----------
    cause : str
        The strongest selected cause when the selected model explains the table (or cannot be
        checked), ``"unexplained"`` when it does not (see ``explained``), else ``"none"``.
    baseline : LinearFit
    candidates : list of Candidate
        Each cause alone over the baseline, sorted by ``delta_bic`` (best first).
    extended : Candidate or None
        The selected model (all of ``causes``); None when no cause was selected.
    causes : list of Selected
        The selected causes, strongest first.
    explained : dict
        :func:`fit_check` of the selected model (of the baseline when none was selected).
    z : (N,) ndarray
        Lens state of every row (from its focal length; without a lens model the log focal
        length on [0, 1]).
    sigma_px : (N,) ndarray
        Per-row noise 1-sigma of the selected model (estimated), px.
    play_sd_px : (N,) ndarray
        The tolerance file's play per row, px (the fitted lens-free shape without a lens).
    pitch_mm : float or None
        None without a lens model.
    pitch_fit : dict or None
        Fitted pitch and its 1-sigma when the pitch was fitted.
    skipped : dict
        Causes the table (or a missing lens model) cannot test, with why.
    distortion : dict or None
        :func:`zoomcalib.diagnose.tangential.distortion_evidence` when an axis tilt and a
        static decentre were weighed on the tangential distortion too, with ``margin`` and
        ``excluded``; None otherwise.
    """

    cause: str
    baseline: LinearFit
    candidates: list[Candidate]
    extended: Candidate | None
    table: ZoomTable
    response: LensResponse | None
    z: np.ndarray
    sigma_px: np.ndarray
    play_sd_px: np.ndarray
    pitch_mm: float | None
    pitch_fit: dict | None = None
    skipped: dict = field(default_factory=dict)
    causes: list[Selected] = field(default_factory=list)
    explained: dict = field(default_factory=dict)
    distortion: dict | None = None

    @property
    def best(self) -> Candidate | None:
        return self.candidates[0] if self.candidates else None

    @property
    def final(self) -> LinearFit:
        """The selected model's fit (the baseline when no cause was selected)."""
        return self.extended.fit if self.extended is not None else self.baseline

    @property
    def converged(self) -> bool:
        """Every fit behind the answer determined all its parameters (full rank) and its noise,
        and a fitted pitch has its minimum inside the admissible range."""
        fits = [self.baseline, self.final] + [c.fit for c in self.candidates]
        return (all(f.converged for f in fits)
                and (self.pitch_fit is None or self.pitch_fit["converged"]))

    @property
    def ambiguous_with(self) -> list[str]:
        """Causes not selected that fit, alone, almost as well as the strongest selected one
        (BIC within AMBIGUITY_BIC of it), less one the tangential distortion contradicts
        (``distortion['excluded']``), and the one it does not tell from a tilt it required
        (``distortion['ambiguous']``)."""
        if not self.causes:
            return []
        evidence = self.distortion or {}
        named = {s.cause for s in self.causes} | {evidence.get("excluded")}
        alone = {c.cause: c.delta_bic for c in self.candidates}
        top = alone[self.causes[0].cause]
        close = [c.cause for c in self.candidates if c.cause not in named
                 and c.delta_bic - top < AMBIGUITY_BIC and c.delta_bic < -BIC_MARGIN]
        other = evidence.get("ambiguous")
        return close + ([other] if other and other not in named | set(close) else [])

    @property
    def data_advice(self) -> list[str]:
        """What more data would tell, in words: the columns the skipped causes need, repeated
        settings when no setting was visited twice, the tangential distortion where axis tilt
        and static decentre are not told apart, and repeated captures across sessions where
        the table is not explained."""
        advice = [f"to test {cause}, give the camera's lens prescription (--lens): without "
                  "one there is no barrel angle or group sensitivities" if why == NEEDS_OPTICS
                  else f"to test {cause}, the table {why}"
                  for cause, why in self.skipped.items() if why.startswith("needs")]
        if self.table.n == len(np.unique(self.table.zoom_groups())):
            advice.append("repeated settings (each zoom step visited more than once, from both "
                          "sides) measure the play itself and let the fit be checked")
        named = {s.cause for s in self.causes} | set(self.ambiguous_with)
        if {"axis_tilt", "static_decenter"} <= named and not self.distortion:
            advice.append("p1, p2 and their sigmas per row (a per-step calibration table) tell "
                          "axis_tilt from static_decenter (docs/diagnose.md)")
        advice += _session_advice(self.table)
        if self.cause == "unexplained":
            advice.append("the same steps captured again, in the same session and on another "
                          "day, would show whether what is left moves between sessions (a "
                          "camera re-mounted, a zoom that does not return) or is noise the "
                          "table's sigmas understate")
        return advice

    def _extended_dict(self) -> dict:
        if self.extended is None:
            return {"cause": "none", "variant": "", **self.baseline.summary(), "params": {},
                    "params_sd": {}}
        params, sds = self.final.param_dict(self.extended.n_baseline)
        return {"cause": self.extended.cause, "variant": self.extended.variant,
                **self.final.summary(), "params": params, "params_sd": sds}

    def _group_columns(self) -> str:
        """How the group terms were modelled, with any fallback to the paraxial shift."""
        if self.table.calibrations is None or self.response is None:
            return "paraxial image shift"
        failed = self.table.response_cache.get("failed", [])
        return ("each row's calibration response (diagnose/response.py)"
                + (f"; paraxial image shift for the {'; '.join(failed)}" if failed else ""))

    def _noise_dict(self) -> dict:
        noise = self.final.noise.to_dict() if self.final.noise is not None else {}
        return {**noise, "rms_sigma_px": float(np.sqrt(np.mean(self.sigma_px ** 2))),
                "rms_play_px": float(np.sqrt(np.mean(self.play_sd_px ** 2))),
                "measurement_sd_used": self.table.has_sd,
                "row_correlation": self._correlation_dict(),
                "play_shape": "tolerance file" if self.response is not None
                else "(fx / median fx), no lens model"}

    def _correlation_dict(self) -> dict | None:
        """Whether the rows were weighed with their correlation, and its largest value
        between two rows' principal points (None: independent rows)."""
        corr = self.table.pp_correlation
        if corr is None or not self.table.has_sd:
            return None
        off = np.abs(corr - np.diag(np.diag(corr)))
        return {"used": True, "largest": float(off.max(initial=0.0))}

    def to_dict(self) -> dict:
        """The ``diagnosis.json`` document."""
        base_params, base_sd = self.baseline.param_dict()
        final = self.final
        return {
            "cause": self.cause,
            "causes": [s.to_dict() for s in self.causes],
            "explained": self.explained,
            "converged": self.converged,
            "ambiguous_with": self.ambiguous_with,
            "baseline": {**self.baseline.summary(), "params": base_params,
                         "params_sd": base_sd},
            "extended": self._extended_dict(),
            "gain": {"cv_rms_ratio": self.baseline.cv_rms_px / final.cv_rms_px,
                     "cv_norm_ratio": cv_norm_ratio(self.baseline, final)},
            "candidates": [c.to_dict() for c in self.candidates],
            "skipped": [{"cause": k, "reason": v} for k, v in self.skipped.items()],
            "data_advice": self.data_advice,
            "distortion_evidence": self.distortion,
            "selection": {"bic_margin": BIC_MARGIN, "ambiguity_bic": AMBIGUITY_BIC,
                          "max_causes": MAX_CAUSES,
                          "rule": "forward-backward over causes: a cause enters when it lowers "
                                  "the BIC by more than bic_margin and the held-out normalised "
                                  "residuals too, and leaves when removing it raises the BIC "
                                  "by less than bic_margin; 'cause' is the strongest when the "
                                  "model explains the table, 'unexplained' when not, else "
                                  "'none'"},
            "lens": self.response.lens.name if self.response is not None else "none",
            "group_columns": self._group_columns(),
            "moving_groups": list(self.response.groups) if self.response is not None else [],
            "pixel_pitch_mm": self.pitch_mm, "pitch_fit": self.pitch_fit,
            "noise": self._noise_dict(),
            "rows": [{"step": s, "zoom": float(zz), "lens_state": float(z),
                      "efl_mm": float(f * self.pitch_mm) if self.pitch_mm else None,
                      "sigma_px": float(sg),
                      "baseline_residual_px": [float(v) for v in rb],
                      "extended_residual_px": [float(v) for v in re]}
                     for s, zz, z, f, sg, rb, re in zip(
                         self.table.step, self.table.zoom, self.z, self.table.fx,
                         self.sigma_px, self.baseline.residual_px, final.residual_px,
                         strict=True)],
        }


def noise_shape(table: ZoomTable, play_px: np.ndarray, with_lens: bool = True) -> NoiseShape:
    """The table's noise shapes: its sigmas (ones when it has none), their correlation across
    rows when the table has one (``pp_correlation``) and the play ``play_px`` ((N,) px per
    axis; ignored without a lens, where ``fx / median fx`` takes its place)."""
    measured = (0.5 * (table.sd_cx ** 2 + table.sd_cy ** 2) if table.has_sd
                else np.ones(table.n))
    measured = np.where(measured > 0, measured, np.min(measured[measured > 0], initial=1.0))
    correlation = table.pp_correlation if table.has_sd else None
    if with_lens:
        return NoiseShape(measured, np.asarray(play_px) ** 2, table.has_sd, True,
                          correlation=correlation)
    relative = table.fx / np.median(table.fx)
    return NoiseShape(measured, relative ** 2, table.has_sd, False, "fx / median fx",
                      correlation)


def _noise(table: ZoomTable, response: LensResponse, z: np.ndarray,
           tolerances: Tolerances) -> tuple[np.ndarray, np.ndarray]:
    """Per-row 1-sigma at the tolerance file's play and the table's sigmas (px), and the play."""
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
    # a grid, not scipy.optimize.minimize_scalar: the spiral's phase makes D multimodal in the
    # pitch, and the grid also gives the D - min D <= 1 interval
    grid = np.geomspace(lo, hi, n_grid) if hi > lo else np.array([lo])
    table = replace(table, calibrations=None)  # the paraxial shift: one trace per pitch is too dear
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


def _max_path_degree(table: ZoomTable) -> int:
    """Highest degree of a lens-free path: two below the number of zoom settings."""
    return max(1, min(MAX_PATH_DEGREE, len(np.unique(table.zoom_groups())) - 2))


def _lens_free_baseline(fitter: Fitter, chosen: list[Selected] | None = None
                        ) -> tuple[Term, ...]:
    """Offset + a path smooth in log f, of the degree with the lowest BIC (with the
    ``chosen`` causes beside it)."""
    fx = fitter.ctx.table.fx
    chosen = chosen or []
    options = [(offset_term(), smooth_path_term(degree, float(fx.min()), float(fx.max())))
               for degree in range(1, _max_path_degree(fitter.ctx.table) + 1)]
    options = [terms for terms in options if fitter.can_fit(_with(terms, chosen))] or options[:1]
    return min(options, key=lambda terms: fitter(_with(terms, chosen)).bic)


def _single_causes(fitter: Fitter, base, variants) -> list[Candidate]:
    """Each cause alone over the baseline (its best variant), best first."""
    base_fit = fitter(base)
    out = []
    for cause, options in variants.items():
        best = _best_variant(fitter, base, [], cause, options)
        if best is None:
            continue
        f, sel = best
        out.append(Candidate(cause, f, len(base_fit.params), f.bic - base_fit.bic, sel.variant))
    return sorted(out, key=lambda c: c.delta_bic)


def _session_advice(table: ZoomTable) -> list[str]:
    """Where the table's capture sessions each hold their own range of zoom, a jump of the
    principal point between sessions is not told from its path over zoom: say which."""
    if table.session is None or len(set(table.session)) < 2:
        return []
    labels = list(dict.fromkeys(table.session))
    spans = {lab: (min(z for z, s in zip(table.zoom, table.session, strict=True) if s == lab),
                   max(z for z, s in zip(table.zoom, table.session, strict=True) if s == lab))
             for lab in labels}
    apart = all(spans[a][1] < spans[b][0] or spans[b][1] < spans[a][0]
                for i, a in enumerate(labels) for b in labels[i + 1:])
    if not apart:
        return []
    listed = "; ".join(f"{lab}: zoom {lo:g}-{hi:g}" if lo != hi else f"{lab}: zoom {lo:g}"
                       for lab, (lo, hi) in spans.items())
    return [f"each capture session holds its own zoom range ({listed}): a principal point "
            "that moves between sessions (a camera re-mounted, a zoom re-initialised) is not "
            "told from its path over zoom; steps captured in more than one session would tell"]


def _narrow_variants(table: ZoomTable, variants: dict, skipped: dict, exclude: dict[str, str],
                     restrict: dict[str, str]) -> None:
    """Drop the ``exclude`` causes from ``variants`` (each reported under ``skipped`` with its
    why) and keep of each ``restrict`` cause its named variant only (ValueError when it has
    none of that name); in place."""
    for cause, why in exclude.items():
        if variants.pop(cause, None) is not None:
            skipped[cause] = why
    for cause, name in restrict.items():
        kept = [v for v in variants.get(cause, []) if " + ".join(t.name for t in v) == name]
        if not kept:
            raise ValueError(f"{table.source}: cause {cause!r} has no variant {name!r}")
        variants[cause] = kept


def diagnose_table(table: ZoomTable, response: LensResponse | None,
                   tolerances: Tolerances | None = None, fit_pitch: bool = False,
                   locked_tilt: bool = False, exclude: dict[str, str] | None = None,
                   require: dict[str, str] | None = None,
                   restrict: dict[str, str] | None = None) -> Diagnosis:
    """Fit the baseline, select the causes that the table supports, and check the result.

    Parameters
    ----------
    table : ZoomTable
    response : LensResponse or None
        The lens model and the pixel pitch (ignored when ``fit_pitch``); None for a lens
        without a model (a smooth path in log f as the baseline, causes without optics only).
    tolerances : Tolerances, optional
        The random play's prior (default: the built-in tolerances).
    fit_pitch : bool
        Fit the pixel pitch too (:func:`fit_pixel_pitch`).
    locked_tilt : bool
        Give the baseline the locked tilt of each moving group as well as its decentre.
    exclude : dict, optional
        Causes not to test, each with why (reported under ``skipped``), e.g. one that other
        evidence contradicts (:func:`zoomcalib.diagnose.tangential.resolve_with_distortion`).
    require : dict, optional
        Causes other evidence names (each with that evidence): in the selected model whatever
        the principal points say (:func:`select_causes`).
    restrict : dict, optional
        Causes to try in one variant only (cause: variant name, e.g. ``"static decentre,
        variator"``), which other evidence chose.

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
    >>> diag.cause, diag.explained["explained"], diag.to_dict()["gain"]["cv_norm_ratio"] > 2
    ('backlash', True, True)
    """
    from ..optics.mechanics import load_tolerances

    groups = table.zoom_groups()
    if len(np.unique(groups)) < 3:
        raise ValueError(f"{table.source}: {len(np.unique(groups))} distinct zoom settings; "
                         f"at least 3 are needed to hold steps out")
    pitch_fit = None
    if response is None:
        if fit_pitch:
            raise ValueError(f"{table.source}: a pixel pitch can only be fitted with a lens model")
        z = 0.5 * (log_focal_coordinate(table.fx, table.fx.min(), table.fx.max()) + 1.0)
        shape = noise_shape(table, np.zeros(table.n), with_lens=False)
        # a lens-free path cannot predict a zoom setting it has not seen (a polynomial
        # extrapolates, and between settings it can swing): rows are held out one at a time
        fitter = Fitter(Context.build(table, z, None), shape, groups,
                        holdout=np.arange(table.n))
        base = _lens_free_baseline(fitter)
        variants, skipped = cause_variants(table, None)
    else:
        tolerances = tolerances if tolerances is not None else load_tolerances()
        if fit_pitch:
            pitch_fit = fit_pixel_pitch(table, response, tolerances, locked_tilt=locked_tilt)
            response = response.with_pitch(pitch_fit["pitch_mm"])
        z = response.state_of_focal(table.fx, table.source)
        shape = noise_shape(table, response.play_sd_px(z, tolerances))
        fitter = Fitter(Context.build(table, z, response), shape, groups)
        base = baseline_terms(response.groups, locked_tilt)
        variants, skipped = cause_variants(table, response.groups)
    _narrow_variants(table, variants, skipped, exclude or {}, restrict or {})
    final, chosen = select_causes(fitter, base, variants, require)
    if response is None and chosen and _lens_free_baseline(fitter, chosen) != base:
        # the path's degree chosen with the causes beside it, and the causes again
        base = _lens_free_baseline(fitter, chosen)
        final, chosen = select_causes(fitter, base, variants, require)
    base_fit = fitter(base)
    candidates = _single_causes(fitter, base, variants)
    check = fit_check(final, fitter.ctx, groups, shape)
    extended = (Candidate(" + ".join(s.cause for s in chosen), final, len(base_fit.params),
                          final.bic - base_fit.bic, " + ".join(s.variant for s in chosen))
                if chosen else None)
    cause = ("unexplained" if check["explained"] is False
             else chosen[0].cause if chosen else "none")
    play_scale = final.noise.play_scale if final.noise is not None else 1.0
    return Diagnosis(cause, base_fit, candidates, extended, table, response, z,
                     np.sqrt(final.variance), play_scale * np.sqrt(shape.play_var),
                     response.pitch_mm if response is not None else None, pitch_fit, skipped,
                     chosen, check)
