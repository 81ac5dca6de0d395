r"""What a step's reprojection residual is made of: each candidate cause an extension of the
step's model, fitted, and kept only when it pays on held-out views.

Protocol
--------
The views are split into ``folds`` groups (seeded). For each group, the step's model (its
distortion terms and aspect ratio, the nominal flat board) is calibrated by OpenCV on the other
views, started from the step's calibration. A *training* cause refits that with its extension:

``lens``
    the rational model's k4, k5, k6 freed beside the step's terms;
``board``
    a smooth warp of the board (the bundle adjustment, :func:`calibrate_bundle`, with its
    five terms; each point within 0.01 mm of the warp): a board that is not flat, one shape
    for the step's views (all of one capture session). OpenCV's ``calibrateCameraRO`` would
    need every view to see the whole board; on the real PTZ set 6 of 29 views at 1x do;
``points``
    every board point free (the same adjustment without its prior on the points): a print or
    a paper that differs from the nominal board point by point.

Each held-out view's corners are split into the two colours of a checkerboard over the
board's grid of points; the view's pose, and a *per-view* cause's own parameters, are fitted
on one half and the other half's residuals kept, then the reverse, so every corner is judged
by a fit that did not see it:

``focal``
    a focal length of the view's own, ``f_v = f e^{s_v}`` (zoom repeatability: the seed
    paper's mechanical error, here measured);
``readout``
    an image shift growing with the row, ``(du, dv) = (a_v, b_v) (v - h/2) / (h/2)``: a
    rolling shutter read out while the camera or board moves (the shift at the top and bottom
    rows, px).

Per held-out view ``v``, the mean square ``e_v`` (px^2) of the split residuals, for the
baseline and for each cause; the gain ``d_v = e_v(base) - e_v(cause)``, its mean over the
views and standard error ``sd(d) / sqrt(n)``; its *share* is ``mean d / mean e(base)``. A
cause *pays* when the mean of ``log(e_v(base) / e_v(cause))`` exceeds :data:`PAY_SE` of its
standard errors (the gains themselves are heavy-tailed over the views). The causes that pay
are then added by forward selection (largest share first; each kept when it pays again beside
those kept, judged the same way); what the kept ones leave, as a share of the baseline, is
``unexplained``. Causes that do not pay are reported as tried and rejected. Two paying causes
whose shares alone are within :data:`AMBIGUOUS` of each other are reported as not told apart
(``ambiguous_with``): per-view causes absorb any error smooth over a view, so a focal length
per view and a readout shift each explain most of the other's effect on tilted views.

Corner level
------------
How much of the residual any per-view cause could explain at most: each held-out view's
baseline residuals on one checkerboard half are fitted by a cubic in the image coordinates
(per axis, 10 terms) and taken off the other half's. What that leaves (``corner_level``, a
share of the baseline) is not smooth over a view: the corners' own noise (the detector, the
compression, the print), or a board that differs point by point. The corner noise alone
gives a share near ``1 / (1 + (geometric / noise)^2)``.

Sizes
-----
``board``, ``points``: RMS distance of the released points from the nominal board after the
best similarity transform (mm), mean over the folds (sd: their spread). ``focal``: the sd of
``s_v`` over the views with the fits' own variance taken out (``var = mean (s - mean s)^2 -
mean se^2``), a fraction; ``readout``: the RMS of ``(a_v, b_v)`` alike, px. Each with its
sd from the spread of the per-view values.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.optimize

from ..pool import map_in_processes
from .bundle import calibrate_bundle
from .geometry import fit_similarity
from .opencv_backend import calibrate_opencv
from .result import CalibrationResult, Observations

__all__ = ["AMBIGUOUS", "CAUSES", "PAY_SE", "Cause", "ResidualBudget", "residual_budget",
           "step_budgets", "session_budgets"]

#: The causes tried, in order: training (``lens``, ``board``), then per view.
CAUSES: dict[str, str] = {
    "lens": "lens model: rational terms k4-k6",
    "board": "board shape: a smooth warp of the board (bundle adjustment)",
    "points": "board points each free: a print or paper that differs point by point",
    "focal": "a focal length per view (zoom repeatability)",
    "readout": "an image shift growing with the row (rolling shutter with motion)",
}
_TRAINING = ("lens", "board", "points")
#: A cause pays when its mean held-out gain exceeds this many standard errors.
PAY_SE = 3.0
_DIST = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
_FIX = {"k1": cv2.CALIB_FIX_K1, "k2": cv2.CALIB_FIX_K2, "k3": cv2.CALIB_FIX_K3,
        "k4": cv2.CALIB_FIX_K4, "k5": cv2.CALIB_FIX_K5, "k6": cv2.CALIB_FIX_K6}


@dataclass
class Cause:
    """One candidate cause (module docstring): held-out RMS (px), mean gain and its standard
    error (px^2), share of the baseline's held-out mean square, whether it pays, and its
    fitted ``size`` (with ``size_sd`` and ``size_unit``); ``note`` says why it was not tried."""

    name: str
    description: str
    held_out_rms_px: float = math.nan
    gain_px2: float = math.nan
    gain_se_px2: float = math.nan
    share: float = math.nan
    pays: bool = False
    size: float = math.nan
    size_sd: float = math.nan
    size_unit: str = ""
    note: str = ""
    ambiguous_with: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in self.__dict__.items()}


#: Two paying causes cannot be told apart when the smaller share alone is at least this
#: fraction of the larger.
AMBIGUOUS = 0.8


@dataclass
class ResidualBudget:
    """A step's residual budget (module docstring). ``fit_rms_px`` is the step's own fit's
    RMS; ``held_out_rms_px`` the baseline's on held-out corners; ``combined`` the causes kept
    by forward selection and ``combined_rms_px`` their held-out RMS together; ``unexplained``
    the share of the baseline's held-out mean square they leave; ``corner_level`` (and its
    ``corner_level_rms_px``) the share that no error smooth over a view explains (module
    docstring, "Corner level")."""

    step: str
    views: int
    folds: int
    fit_rms_px: float
    held_out_rms_px: float
    causes: list[Cause] = field(default_factory=list)
    combined: list[str] = field(default_factory=list)
    combined_rms_px: float = math.nan
    unexplained: float = 1.0
    corner_level_rms_px: float = math.nan
    corner_level: float = math.nan

    @property
    def named(self) -> list[str]:
        """The causes kept: each pays beside those kept before it."""
        return list(self.combined)

    def summary(self) -> str:
        """One line: the held-out RMS, each cause's share (paying or rejected), what is left."""
        parts = []
        for c in self.causes:
            if not math.isfinite(c.share):
                parts.append(f"{c.name} not tried ({c.note})")
                continue
            size = f", {c.size:.3g} {c.size_unit}" if math.isfinite(c.size) else ""
            verdict = ("named" if c.name in self.combined else
                       f"{c.note}" if c.pays else "rejected")
            if c.ambiguous_with:
                verdict += "; not told apart from " + ", ".join(c.ambiguous_with)
            parts.append(f"{c.name} {100 * c.share:.0f} % ({verdict}{size})")
        return (f"{self.step}: held-out RMS {self.held_out_rms_px:.3g} px (fit "
                f"{self.fit_rms_px:.3g}); " + "; ".join(parts)
                + f"; unexplained {100 * self.unexplained:.0f} %; not smooth over a "
                f"view {100 * self.corner_level:.0f} %")

    def to_dict(self) -> dict:
        out = {k: v for k, v in self.__dict__.items() if k != "causes"}
        out["causes"] = [c.to_dict() for c in self.causes]
        out["named"] = self.named
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in out.items()}


def residual_budget(obs: Observations, start: CalibrationResult, step: str = "",
                    folds: int = 5, seed: int = 0) -> ResidualBudget:
    """The residual budget of one step (module docstring).

    Parameters
    ----------
    obs : Observations
        The step's detections (board points in mm, px).
    start : CalibrationResult
        The step's calibration: its distortion terms (``info["distortion_terms"]`` when
        given, else the nonzero ones of ``dist``), aspect ratio and starting values.
    folds : int
        Groups of held-out views (at least 2; at most the number of views).
    seed : int
        Seed of the split into folds.

    Raises
    ------
    ValueError
        With fewer than 6 views, or fewer than 2 folds.
    """
    n = len(obs.views)
    if n < 6:
        raise ValueError(f"step {step or '?'}: a residual budget needs 6 or more views; got {n}")
    folds = min(int(folds), n)
    if folds < 2:
        raise ValueError(f"folds must be at least 2; got {folds}")
    terms = _terms(start)
    group = np.random.default_rng(seed).permutation(n) % folds
    fold = _Folds(obs, start, terms, group)
    base = fold.held_out(())
    extras: dict[str, list] = {"focal": [], "readout": [], "board": fold.off_plane["board"],
                               "points": fold.off_plane["points"]}
    causes = []
    for name in CAUSES:
        if name in fold.notes:
            causes.append(Cause(name, CAUSES[name], note=fold.notes[name]))
            continue
        e = fold.held_out((name,), extras.get(name) if name not in _TRAINING else None)
        causes.append(_cause(name, e, base, extras.get(name)))
    budget = ResidualBudget(step, n, folds, float(start.rms_px),
                            float(np.sqrt(np.nanmean(base))), causes)
    # forward selection: the paying causes by share, each kept when it pays beside those kept
    kept, e_kept = [], base
    for c in sorted((c for c in causes if c.pays), key=lambda c: -c.share):
        e = fold.held_out((*kept, c.name))
        if _pays(e_kept, e):
            kept, e_kept = [*kept, c.name], e
        else:
            c.note = "pays alone, not beside " + " + ".join(kept)
    budget.combined = kept
    warp = fold.held_out(("warp",))
    ok = np.isfinite(warp) & np.isfinite(base)
    budget.corner_level_rms_px = float(np.sqrt(np.mean(warp[ok])))
    budget.corner_level = float(np.mean(warp[ok]) / np.mean(base[ok]))
    paying = [c for c in causes if c.pays]
    for c in paying:
        c.ambiguous_with = [o.name for o in paying if o is not c
                            and min(o.share, c.share) >= AMBIGUOUS * max(o.share, c.share)]
    ok = np.isfinite(e_kept) & np.isfinite(base)
    budget.combined_rms_px = float(np.sqrt(np.mean(e_kept[ok])))
    budget.unexplained = float(np.mean(e_kept[ok]) / np.mean(base[ok]))
    return budget


class _Folds:
    """The training fits of every fold (baseline and each training cause, fitted once), and
    the held-out judgement of a set of causes on every view."""

    def __init__(self, obs: Observations, start: CalibrationResult, terms: tuple[str, ...],
                 group: np.ndarray):
        self.obs, self.start, self.terms, self.group = obs, start, terms, group
        self.halves = _checker_halves(obs.object_points)
        self.models: list[dict] = []
        self.notes: dict[str, str] = {}
        self.off_plane: dict[str, list[float]] = {"board": [], "points": []}
        for f in range(int(group.max()) + 1):
            train = obs.subset(np.flatnonzero(group != f))
            models = {(): _train(train, start, terms, ())}
            for cause in _TRAINING:
                if cause in self.notes:
                    continue
                try:
                    models[(cause,)] = _train(train, start, terms, (cause,))
                except (cv2.error, ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
                    self.notes[cause] = " ".join(str(exc).split())[:120]
            for cause in ("board", "points"):
                if (cause,) in models:
                    self.off_plane[cause].append(_off_plane_rms(
                        models[(cause,)][2], np.asarray(obs.object_points, float)))
            self.models.append(models)

    def _model(self, f: int, training: tuple[str, ...]):
        if training not in self.models[f]:
            train = self.obs.subset(np.flatnonzero(self.group != f))
            self.models[f][training] = _train(train, self.start, self.terms, training)
        return self.models[f][training]

    def held_out(self, causes: tuple[str, ...], extra: list | None = None) -> np.ndarray:
        """(views,) held-out mean square (px^2) of each view under ``causes``; the per-view
        causes' parameters appended to ``extra``."""
        training = tuple(c for c in _TRAINING if c in causes)
        per_view = "+".join(c for c in causes if c not in _TRAINING) or "base"
        e = np.full(len(self.obs.views), np.nan)
        for f in range(len(self.models)):
            try:
                model = self._model(f, training)
            except (cv2.error, ValueError, RuntimeError, np.linalg.LinAlgError):
                continue
            for v in np.flatnonzero(self.group == f):
                idx, uv = self.obs.views[v]
                e[v], fitted = _held_out(model, idx, uv, self.halves[idx], per_view,
                                         self.obs.image_size)
                if extra is not None and fitted is not None:
                    extra.append(fitted)
        return e


def _pays(before: np.ndarray, after: np.ndarray) -> bool:
    """The mean per-view log ratio of the held-out mean squares, ``log(before / after)``,
    exceeds :data:`PAY_SE` standard errors (the log tames the views where a cause is large:
    a gain that is a square of the effect is heavy-tailed over the views)."""
    ok = np.isfinite(before) & np.isfinite(after) & (before > 0) & (after > 0)
    if ok.sum() < 3:
        return False
    d = np.log(before[ok] / after[ok])
    return bool(d.mean() > PAY_SE * d.std(ddof=1) / math.sqrt(len(d)))


# ----------------------------------------------------------------------------------------------
# training fits


def _terms(start: CalibrationResult) -> tuple[str, ...]:
    """The distortion terms the step's model frees."""
    given = start.info.get("distortion_terms")
    if given is not None:
        return tuple(given)
    return tuple(k for k, d in zip(_DIST, np.ravel(start.dist), strict=False) if d != 0.0)


def _flags(terms: tuple[str, ...], rational: bool) -> int:
    flags = cv2.CALIB_FIX_ASPECT_RATIO
    if not {"p1", "p2"} & set(terms):
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    free = set(terms) | ({"k4", "k5", "k6"} if rational else set())
    if rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    for k, bit in _FIX.items():
        if k not in free:
            flags |= bit
    return flags


def _guess_dist(start: CalibrationResult, terms: tuple[str, ...], rational: bool) -> np.ndarray:
    d = np.zeros(8)
    src = np.ravel(start.dist)[:8]
    d[:len(src)] = src
    d = np.array([v if k in terms else 0.0 for k, v in zip(_DIST, d, strict=True)])
    return d if rational else d[:5]


def _train(obs: Observations, start: CalibrationResult, terms: tuple[str, ...],
           training: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K, dist, board points)`` of the training views, with the ``training`` causes'
    extensions."""
    rational = "lens" in training
    flags = _flags(terms, rational)
    dist0 = _guess_dist(start, terms, rational)
    if "points" in training:
        return _train_board(obs, start.K, dist0, flags, None)
    if "board" in training:
        return _train_board(obs, start.K, dist0, flags, 0.01)
    res = calibrate_opencv(obs, flags=flags, K_guess=start.K, dist_guess=dist0,
                           camera_only=True)
    return res.K, np.ravel(res.dist), np.asarray(obs.object_points, float)


def _train_board(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int,
                 point_sigma_mm: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bundle adjustment with the board points released (:func:`calibrate_bundle`: its
    own five terms, the aspect ratio held), from ``K``, ``dist``: each point within
    ``point_sigma_mm`` of a smooth warp of the board (None: each point free)."""
    rational = bool(flags & cv2.CALIB_RATIONAL_MODEL)
    with warnings.catch_warnings():  # its guard's advice is for its own users; here the
        warnings.simplefilter("ignore", RuntimeWarning)  # held-out views judge the board
        res = calibrate_bundle(obs, model="rational" if rational else "standard", K0=K,
                               dist0=np.ravel(dist)[:8 if rational else 5],
                               refine_target=True, robust=False, fix_aspect=True,
                               target_sigma_mm=point_sigma_mm, scatter_check=False)
    return res.K, np.ravel(res.dist), np.asarray(res.object_points, float)


def _off_plane_rms(X: np.ndarray, nominal: np.ndarray | None = None) -> float:
    """RMS distance (mm) of released points ``X`` from the ``nominal`` board after the best
    similarity transform (Umeyama 1991); without ``nominal``, from their least-squares
    plane."""
    if nominal is None:
        centred = X - X.mean(axis=0)
        return float(np.linalg.svd(centred, compute_uv=False)[-1] / math.sqrt(len(X)))
    scale, R, t = fit_similarity(nominal, X)
    return float(np.sqrt(np.mean(np.sum((X - scale * nominal @ R.T - t) ** 2, axis=1))))


# ----------------------------------------------------------------------------------------------
# held-out views


def _checker_halves(X: np.ndarray) -> np.ndarray:
    """(N,) 0/1: the colour of each board point on a checkerboard over the board's grid."""
    X = np.asarray(X, float)
    pitch = [np.min(np.diff(np.unique(np.round(X[:, k], 6)))) if len(np.unique(X[:, k])) > 1
             else 1.0 for k in (0, 1)]
    ij = np.round((X[:, :2] - X[:, :2].min(axis=0)) / pitch).astype(int)
    return (ij[:, 0] + ij[:, 1]) % 2


def _held_out(model, idx: np.ndarray, uv: np.ndarray, half: np.ndarray, cause: str,
              size: tuple[int, int]) -> tuple[float, np.ndarray | None]:
    """Mean square (px^2) of a view's corners, each half predicted by a fit to the other;
    and, for a per-view cause, its parameters with their standard errors ((2, p) stacked:
    values, se), averaged over the two fits."""
    K, dist, X = model
    X = X[idx]
    sq, params = [], []
    for h in (0, 1):
        fit, test = half == h, half != h
        if fit.sum() < 6 or test.sum() < 1:
            return math.nan, None
        r, p = _fit_view(K, dist, X, uv, fit, test, cause, size)
        sq.append(r)
        if p is not None:
            params.append(p)
    value = float(np.mean(np.concatenate(sq)))
    if not params:
        return value, None
    vals = np.mean([p[0] for p in params], axis=0)
    se = np.sqrt(np.mean([p[1] ** 2 for p in params], axis=0) / 2)
    return value, np.stack([vals, se])


_EXTRA = {"base": 0, "lens": 0, "board": 0, "focal": 1, "readout": 2, "warp": 0}


def _fit_view(K, dist, X, uv, fit, test, cause, size):
    """Fit pose (+ the cause's per-view parameters) to ``fit`` points; the squared residuals
    of ``test`` points, and (values, se) of the extra parameters (None without)."""
    ok, rvec, tvec = cv2.solvePnP(X[fit], uv[fit], K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return np.full(int(test.sum()), np.nan), None
    n_extra = sum(_EXTRA[c] for c in cause.split("+"))
    h = size[1] / 2.0

    def predict(p, mask):
        Kp = K.copy()
        offset = 6
        for c in cause.split("+"):
            if c == "focal":
                Kp[0, 0] *= math.exp(p[offset])
                Kp[1, 1] *= math.exp(p[offset])
                offset += 1
        out = cv2.projectPoints(X[mask], p[:3], p[3:6], Kp, dist)[0].reshape(-1, 2)
        offset = 6
        for c in cause.split("+"):
            if c == "focal":
                offset += 1
            elif c == "readout":
                row = (uv[mask, 1:2] - h) / h
                out = out + row * p[offset:offset + 2]
                offset += 2
        return out

    p0 = np.concatenate([rvec.ravel(), tvec.ravel(), np.zeros(n_extra)])
    sol = scipy.optimize.least_squares(lambda p: (predict(p, fit) - uv[fit]).ravel(), p0,
                                       method="lm", x_scale="jac")
    resid = predict(sol.x, test) - uv[test]
    if cause == "warp":  # the fit half's residuals, a cubic in the image, taken off the test's
        basis = _cubic(uv, size)
        coef = np.linalg.lstsq(basis[fit], uv[fit] - predict(sol.x, fit), rcond=None)[0]
        resid = resid + basis[test] @ coef
    if not n_extra:
        return np.sum(resid**2, axis=1), None
    dof = max(2 * int(fit.sum()) - len(p0), 1)
    s2 = float(np.sum(sol.fun**2)) / dof
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
        se = np.sqrt(np.diag(cov)[6:])
    except np.linalg.LinAlgError:
        se = np.full(n_extra, np.nan)
    return np.sum(resid**2, axis=1), (sol.x[6:], se)


def _cubic(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(n, 10) the monomials of degree <= 3 in the image coordinates scaled to [-1, 1]."""
    x = (uv[:, 0] - size[0] / 2) / (size[0] / 2)
    y = (uv[:, 1] - size[1] / 2) / (size[1] / 2)
    return np.column_stack([x**i * y**j for i in range(4) for j in range(4 - i)])


# ----------------------------------------------------------------------------------------------
# verdicts


def _cause(name: str, e: np.ndarray, base: np.ndarray, extra: list | None) -> Cause:
    cause = Cause(name, CAUSES[name])
    ok = np.isfinite(e) & np.isfinite(base)
    if ok.sum() < 3:
        cause.note = f"{int(ok.sum())} views could be judged"
        return cause
    d = base[ok] - e[ok]
    cause.held_out_rms_px = float(np.sqrt(np.mean(e[ok])))
    cause.gain_px2 = float(np.mean(d))
    cause.gain_se_px2 = float(np.std(d, ddof=1) / math.sqrt(len(d)))
    cause.share = cause.gain_px2 / float(np.mean(base[ok]))
    cause.pays = _pays(base, e)
    if extra:
        cause.size, cause.size_sd, cause.size_unit = _size(name, extra)
    return cause


def _size(name: str, extra: list) -> tuple[float, float, str]:
    if name in ("board", "points"):
        v = np.asarray(extra, float)
        return (float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else math.nan,
                "mm RMS from the nominal board")
    vals = np.array([p[0] for p in extra])  # (views, p)
    se = np.array([p[1] for p in extra])
    if name == "focal":
        vals, se = vals[:, 0], se[:, 0]
        var = np.var(vals, ddof=1) - np.mean(se**2)
        unit = "sd of f_v / f"
    else:  # readout: the shift at the top and bottom rows, both axes pooled
        vals, se = vals.ravel(), se.ravel()
        var = np.mean(vals**2) - np.mean(se**2)
        unit = "px RMS at the top and bottom rows"
    size = math.sqrt(max(float(var), 0.0))
    # the sd of a variance from n values: sqrt(2 / n) of (var + noise); through the sqrt
    n = len(vals)
    sd = math.sqrt(2.0 / n) * (max(float(var), 0.0) + float(np.mean(se**2))) / max(2 * size,
                                                                                     1e-12)
    return size, sd, unit


# ----------------------------------------------------------------------------------------------
# every step of a run, and the capture sessions


def step_budgets(observations: dict[str, Observations], results: dict[str, CalibrationResult],
                 workers: int = 1, folds: int = 5, seed: int = 0
                 ) -> tuple[dict[str, ResidualBudget], dict[str, str]]:
    """:func:`residual_budget` of every step that has a result, in ``workers`` processes;
    returns the budgets and, per step that failed, the one-line reason (the others are kept).
    """
    names = [s for s in observations if s in results]
    items = [(observations[s], results[s], s, folds, seed) for s in names]
    budgets, failed = {}, {}
    outcomes = map_in_processes(_one_budget, items, workers)
    for name, outcome in zip(names, outcomes, strict=True):
        if isinstance(outcome, str):
            failed[name] = outcome
        else:
            budgets[name] = outcome
    return budgets, failed


def _one_budget(obs, result, step, folds, seed) -> ResidualBudget | str:
    try:
        return residual_budget(obs, result, step, folds, seed)
    except (ValueError, RuntimeError, cv2.error, np.linalg.LinAlgError) as exc:
        return " ".join(str(exc).split())


def session_budgets(budgets: dict[str, ResidualBudget], sessions: dict[str, str]
                    ) -> dict[str, dict]:
    """Per capture session (``sessions``: step -> label; one session when empty): its steps,
    each cause's share averaged over them (weighted by their views), the steps that named it,
    and the mean unexplained share."""
    groups: dict[str, list[str]] = {}
    for step in budgets:
        groups.setdefault(sessions.get(step, "") or "", []).append(step)
    out = {}
    for label, steps in groups.items():
        w = np.array([budgets[s].views for s in steps], float)
        shares = {}
        for name in CAUSES:
            vals = np.array([next((c.share for c in budgets[s].causes if c.name == name),
                                  math.nan) for s in steps])
            ok = np.isfinite(vals)
            shares[name] = float(np.average(vals[ok], weights=w[ok])) if ok.any() else None
        out[label] = {"steps": steps, "share": shares,
                      "named_in": {n: [s for s in steps if n in budgets[s].named]
                                   for n in CAUSES},
                      "unexplained": float(np.average([budgets[s].unexplained for s in steps],
                                                      weights=w))}
    return out
