r"""Each zoom step on its own, before the zoom-wide adjustment: the distortion terms its held-out
views choose, and the OpenCV calibration the adjustment starts it from.

*Terms.* :func:`select_distortion` fits each term set of :data:`DISTORTION_SETS` on half of a
step's views and places the other half with those intrinsics (:func:`held_out_errors`, two
folds): the simplest set whose held-out error is within a tolerance of the best set's is
chosen, and the rational model only where it beats the best five-term set view by view. The
choice is made again on the board's estimated shape once the adjustment has one
(:func:`_select_on_board`). :func:`with_decentring` adds p1, p2 to a set with a radial term
(the centre of distortion is not the principal point).

*Starts.* :func:`step_starts` gives every step its chosen terms, their held-out errors and an
OpenCV calibration with them, in worker processes: from OpenCV's own start and, where that is
ill-posed (views near fronto-parallel), from a range of focal lengths (:func:`_robust_start`),
with fewer terms where a long-end step's distortion cannot be separated
(:func:`_opencv_start`). A step that cannot be started says why, and the adjustment goes on
without it. An adjustment that differs only in its later options (the prior, the board, the
principal point's model) can reuse them (:class:`StepStarts`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.stats

from ..pool import map_in_processes
from .opencv_backend import (
    FRONTO_PARALLEL_DEG,
    START_CRITERIA,
    calibrate_opencv,
    calibrate_opencv_camera,
    calibrate_opencv_multistart,
    calibrate_opencv_robust,
    not_a_camera,
)
from .result import CalibrationResult, Observations

__all__ = ["DISTORTION_TERMS", "DISTORTION_SETS", "RATIONAL_TERMS", "StepStarts", "TermChoice",
           "observations_fingerprint", "select_distortion", "held_out_errors", "step_starts",
           "with_decentring"]

#: OpenCV's distortion terms, in its order (the zoom-wide adjustment's intrinsics after fx, fy,
#: cx, cy).
DISTORTION_TERMS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: Distortion term sets, simplest first.
DISTORTION_SETS: dict[str, tuple[str, ...]] = {
    "none": (), "k1": ("k1",), "k1k2": ("k1", "k2"), "k1k2p": ("k1", "k2", "p1", "p2"),
    "k1k2p1p2k3": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
_FIX_FLAGS = {"k1": cv2.CALIB_FIX_K1, "k2": cv2.CALIB_FIX_K2, "k3": cv2.CALIB_FIX_K3,
              "k4": cv2.CALIB_FIX_K4, "k5": cv2.CALIB_FIX_K5, "k6": cv2.CALIB_FIX_K6}
#: The rational model's denominator terms (OpenCV's ``CALIB_RATIONAL_MODEL``).
RATIONAL_TERMS = ("k4", "k5", "k6")


def _distortion_flags(terms: tuple[str, ...]) -> int:
    flags = 0 if {"p1", "p2"} & set(terms) else cv2.CALIB_ZERO_TANGENT_DIST
    if set(RATIONAL_TERMS) & set(terms):
        flags |= cv2.CALIB_RATIONAL_MODEL
    for k, bit in _FIX_FLAGS.items():
        if k not in terms:
            flags |= bit
    return flags


def _eight(dist) -> np.ndarray:
    """(8,) OpenCV's first eight distortion terms of ``dist`` (zeros where it has fewer)."""
    d = np.zeros(8)
    d[:min(len(np.ravel(dist)), 8)] = np.ravel(dist)[:8]
    return d


def _guess(start: CalibrationResult, terms: tuple[str, ...]) -> dict:
    """``start``'s camera matrix and distortion as OpenCV's initial guess for a fit of
    ``terms`` (the others zero; five terms unless ``terms`` has a rational one)."""
    start_dist = _eight(start.dist)
    rational = bool(set(RATIONAL_TERMS) & set(terms))
    if not rational and np.any(start_dist[5:]):
        start_dist[:] = 0.0  # a rational fit's k1, k2, k3 mean other things
    dist = [d if p in terms else 0.0 for p, d in zip(DISTORTION_TERMS, start_dist, strict=True)]
    return {"K_guess": start.K, "dist_guess": np.array(dist if rational else dist[:5])}


def with_decentring(terms: tuple[str, ...], decentring: bool = True) -> tuple[str, ...]:
    """``terms`` with p1, p2 added when a radial term is among them (in
    :data:`DISTORTION_TERMS` order; ``decentring`` False: ``terms`` as they are).

    OpenCV's model centres the radial distortion on the principal point; a real lens's centre
    of distortion lies elsewhere by some px (Willson & Shafer, CMU-CS-93-122, 1993: the image
    centres of a zoom lens). To first order in the offset ``e`` (normalised), radial
    distortion about ``e`` is radial distortion about the principal point plus the tangential
    terms ``p1 = -k1 e_y``, ``p2 = -k1 e_x``. Held at zero, they make the distortion's centre
    pin the principal point: at the long end, where the views' perspective barely does, the
    principal point then lands on the centre of distortion with a sigma of hundredths of a
    px, however far that is from it. The held-out choice does not ask for them (their effect
    on the image points is what a pose and a principal-point shift take up)."""
    if not decentring or not {"k1", "k2", "k3"} & set(terms):
        return tuple(terms)
    return tuple(q for q in DISTORTION_TERMS if q in terms or q in ("p1", "p2"))


def held_out_errors(obs: Observations, terms: tuple[str, ...],
                    board_points: np.ndarray | None = None,
                    start: CalibrationResult | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Squared reprojection errors of held-out views, two folds (even and odd views):
    intrinsics from one half with ``terms`` free
    (:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_camera`: the camera alone),
    each view of the other half placed by
    ``cv2.solvePnP`` with those intrinsics. Returns per view the sum of squared errors (px^2)
    and the number of points, both (V,); a view that cannot be placed has 0 points (the
    caller sees it: :func:`select_distortion` judges every set on the views all placed).
    RuntimeError when a fold's fit is no camera
    (:func:`~zoomcalib.calibrate.opencv_backend.not_a_camera`).

    ``board_points`` (n, 3), board frame: the board's estimated shape (a waving board's
    heights), used in place of ``obs.object_points``; OpenCV then needs a start, ``start``'s
    camera matrix and distortion (the terms not in ``terms`` set to zero).
    """
    flags = _distortion_flags(terms)
    if board_points is not None:
        obs = Observations(np.asarray(board_points, float), obs.views, obs.image_size, obs.names)
    guess = {}
    if start is not None:
        guess = _guess(start, terms)
    elif board_points is not None:
        raise ValueError("held_out_errors: a board shape needs a start calibration")
    idx = np.arange(obs.n_views)
    squared, count = np.zeros(obs.n_views), np.zeros(obs.n_views)
    for train, test in ((idx[0::2], idx[1::2]), (idx[1::2], idx[0::2])):
        K, dist = calibrate_opencv_camera(obs.subset(train), flags, criteria=START_CRITERIA,
                                          **guess)
        if (why := not_a_camera(K, obs.image_size)) is not None:
            raise RuntimeError(f"held-out fit of {'+'.join(terms) or 'no distortion'} "
                               f"diverged: {why}")
        for i in test:
            ids, pts = obs.views[i]
            obj = obs.object_points[ids].astype(np.float64)
            try:
                ok, r, t = cv2.solvePnP(obj, pts.astype(np.float64), K, dist)
                if ok:
                    proj, _ = cv2.projectPoints(obj, r, t, K, dist)
                    squared[i], count[i] = np.sum((proj.reshape(-1, 2) - pts) ** 2), len(pts)
            except cv2.error:
                continue                   # not placed: 0 points, seen by the caller
    return squared, count


@dataclass
class TermChoice:
    """What :func:`select_distortion` chose, and why.

    ``terms``: the chosen distortion terms. ``mse_px2``: held-out mean squared error per term
    set (px^2 per point; ``inf`` where the set could not be fitted). ``excess_se_px2``: the
    standard error of each set's excess over the best set, from the view-by-view differences.
    ``board``: ``"flat"`` or ``"estimated"``, the board shape the choice was made on.
    ``five_terms``: the best five-term set's name; ``rational_log_ratio``: the mean and the
    standard error of the per-view log ratio of the rational model's held-out mean squared
    error over that set's (:func:`_log_ratio`), None where not both could be fitted.
    ``failed``: per term set that could not be fitted on the held-out halves, why (such a set
    is not a candidate); ``why``: why no choice was made (too few views, no set fitted, or
    only the set without distortion: half the views of a narrow step that cannot hold a
    principal point with any term are no evidence that it has none), else None, the terms
    then all five. ``unplaced``: per term set, the held-out views its
    intrinsics could not place (``cv2.solvePnP`` failed); every set is then judged on the
    views all of them placed.
    """

    terms: tuple[str, ...]
    mse_px2: dict[str, float] = field(default_factory=dict)
    excess_se_px2: dict[str, float] = field(default_factory=dict)
    board: str = "flat"
    five_terms: str = "k1k2p1p2k3"
    rational_log_ratio: tuple[float, float] | None = None
    failed: dict[str, str] = field(default_factory=dict)
    why: str | None = None
    unplaced: dict[str, int] = field(default_factory=dict)

    @property
    def rational(self) -> bool:
        """The rational model was chosen."""
        return bool(set(RATIONAL_TERMS) & set(self.terms))

    def other_model_weight(self, tolerance: float = 0.01) -> float:
        """The probability that the model not chosen (rational or the best five-term set) is
        the better one: that the rational model's held-out error is below the five terms' by
        more than ``tolerance`` (relative), or is not, from the per-view log ratio's mean ``m``
        and standard error ``s`` (normal): ``P = Phi((log(1 - tolerance) - m) / s)``, and
        ``1 - P`` where the rational model was chosen. 0 when unknown."""
        if self.rational_log_ratio is None or not self.rational_log_ratio[1] > 0:
            return 0.0
        mean, se = self.rational_log_ratio
        better = float(scipy.stats.norm.cdf((np.log1p(-tolerance) - mean) / se))
        return 1.0 - better if self.rational else better

    def to_dict(self) -> dict:
        return {"terms": list(self.terms), "mse_px2": self.mse_px2,
                "excess_se_px2": self.excess_se_px2, "board": self.board,
                "five_terms": self.five_terms,
                "rational_log_ratio": (None if self.rational_log_ratio is None
                                       else list(self.rational_log_ratio)),
                "failed": dict(self.failed), "why": self.why, "unplaced": dict(self.unplaced)}


def select_distortion(obs: Observations, tolerance: float = 0.01,
                      board_points: np.ndarray | None = None,
                      start: CalibrationResult | None = None, n_se: float = 2.0) -> TermChoice:
    """The simplest distortion term set whose held-out error (:func:`held_out_errors`, with
    the board's shape ``board_points`` and the ``start`` calibration if given) exceeds the
    best set's by less than ``tolerance`` (relative), ``n_se`` standard errors included:
    ``excess + n_se * se(excess) <= tolerance * mse_best``. All five terms when the step has
    fewer than 6 views. The rational model (OpenCV's eight terms) is an extension, not a
    candidate of the same rank: it replaces that choice only where its held-out error is below
    the best five-term set's by more than ``tolerance``, ``n_se`` standard errors included, view
    by view (:func:`_log_ratio`: a wide field the five terms do not fit); where the data
    cannot tell, its nearly collinear terms would only trade with the others.

    With the board's shape known, the held-out error of the right terms is the detection noise
    alone, so ``tolerance`` leaves out a term only when the systematic error it removes is
    below about ``sqrt(tolerance)`` (10 %) of the noise per point; the standard errors keep it
    where the data cannot tell (a choice that would otherwise change with the noise draw, each
    draw reporting the sigma of its own choice). With a flat board its misfit sits in every
    set's error and hides such terms.
    """
    if obs.n_views < 6:
        return TermChoice(DISTORTION_SETS["k1k2p1p2k3"],
                          why=f"{obs.n_views} views, fewer than 6: all five terms")
    per_view, failed = {}, {}
    for name, terms in DISTORTION_SETS.items():
        try:
            per_view[name] = held_out_errors(obs, terms, board_points, start)
        except (ValueError, RuntimeError) as exc:
            failed[name] = " ".join(str(exc).split())
    board = "flat" if board_points is None else "estimated"
    # a view one set cannot place is judged by none: the sets are compared on the same views
    placed = np.all([c > 0 for _, c in per_view.values()], axis=0) if per_view else None
    unplaced = {k: int(np.sum(c == 0)) for k, (_, c) in per_view.items() if np.any(c == 0)}
    if per_view and placed.sum() < 2:
        per_view = {}
    if not per_view:
        return TermChoice(DISTORTION_SETS["k1k2p1p2k3"], board=board, failed=failed,
                          why="no term set could be fitted on held-out views: all five terms",
                          unplaced=unplaced)
    if set(per_view) == {"none"}:
        # every set with a term diverged on half the views (a narrow step's principal point
        # leaves the image): the folds cannot tell, which is no evidence for no distortion
        return TermChoice(DISTORTION_SETS["k1k2p1p2k3"], board=board, failed=failed,
                          why="only the set without distortion could be fitted on held-out "
                              "views: all five terms", unplaced=unplaced)
    per_view = {k: (sq[placed], c[placed]) for k, (sq, c) in per_view.items()}
    n_points = {k: c.sum() for k, (_, c) in per_view.items()}
    mse = {k: sq.sum() / n_points[k] if n_points[k] else np.inf
           for k, (sq, _) in per_view.items()}
    standard = [k for k in per_view if k != "rational"] or list(per_view)
    best = min(standard, key=mse.get)
    se = {k: float(np.std(sq - per_view[best][0], ddof=1) * np.sqrt(len(sq))
                   / max(n_points[best], 1)) for k, (sq, _) in per_view.items()}
    chosen = next(k for k in standard
                  if mse[k] - mse[best] + n_se * se[k] <= tolerance * mse[best])
    ratio = (_log_ratio(per_view["rational"], per_view[best])
             if "rational" in per_view and "rational" not in standard else None)
    if ratio is not None and ratio[0] + n_se * ratio[1] < np.log1p(-tolerance):
        chosen = "rational"
    return TermChoice(DISTORTION_SETS[chosen],
                      {k: float(mse.get(k, np.inf)) for k in DISTORTION_SETS},
                      {k: se[k] for k in per_view}, board, best, ratio, failed,
                      unplaced=unplaced)


def _log_ratio(rational: tuple[np.ndarray, np.ndarray], best: tuple[np.ndarray, np.ndarray]
               ) -> tuple[float, float] | None:
    """The mean and standard error of the per-view log ratio of the rational model's held-out
    mean squared error over the best five-term set's (per view: squared sum, points). Judged
    view by view, a view that one set places badly does not decide it; None below 4 views
    placed by both. The rational model is chosen where the mean, ``n_se`` standard errors
    included, is below ``log(1 - tolerance)`` (:func:`select_distortion`)."""
    (sq_r, n_r), (sq_b, n_b) = rational, best
    both = (n_r > 0) & (n_b > 0) & (sq_b > 0) & (sq_r > 0)
    if both.sum() < 4:
        return None
    log_ratio = np.log(sq_r[both] / n_r[both]) - np.log(sq_b[both] / n_b[both])
    return (float(np.mean(log_ratio)),
            float(np.std(log_ratio, ddof=1) / np.sqrt(len(log_ratio))))


def _map_steps(function, items: list, workers: int) -> list:
    """``[function(*item) for item in items]``, in ``workers`` processes when more than one
    (each step's OpenCV fits are independent of the others'; the results, in order, are the
    same either way)."""
    return map_in_processes(function, items, workers)


def _initial_step(name: str, obs: Observations, select: bool, decentring: bool,
                  held_terms: tuple[str, ...] = (), model: str = "standard"):
    """One step of :func:`step_starts`: ``(terms, held-out choice or None, start or None, why
    it could not be started or None)``; no term of ``held_terms`` is chosen. Without
    ``select`` the terms are ``model``'s all (five, or the rational model's eight)."""
    seed, seed_failure = _robust_start(obs, held_terms)
    held = select_distortion(obs, start=seed) if select else None
    every = DISTORTION_SETS["rational" if model == "rational" else "k1k2p1p2k3"]
    terms = {name: _without(with_decentring(held.terms, decentring) if select else every,
                            held_terms)}
    try:
        return terms[name], held, _opencv_start(name, obs, terms, seed, held_terms), None
    except ValueError as exc:
        why = str(exc) if seed_failure is None else f"{exc}; robust start: {seed_failure}"
        return terms[name], held, None, why


@dataclass
class StepStarts:
    """Every step's own fits before a zoom-wide adjustment (:func:`step_starts`).

    ``terms``: step -> its distortion terms; ``held``: step -> the held-out choice
    (:class:`TermChoice`) where terms were chosen; ``init``: step -> the OpenCV calibration the
    adjustment starts it from; ``skipped``: step -> why it could not be started.
    ``made_for``: the choices the fits depend on (``select``, ``decentring``, the held terms,
    the model) and the observations' fingerprint (:func:`observations_fingerprint`). An
    adjustment of the same observations with the same choices, and any other options, can
    start from them (``calibrate_zoom_wide(..., starts=...)``); it refuses others.
    """

    terms: dict[str, tuple[str, ...]]
    held: dict[str, TermChoice]
    init: dict[str, CalibrationResult]
    skipped: dict[str, str]
    made_for: tuple


def observations_fingerprint(observations: Mapping[str, Observations]) -> str:
    """A SHA-1 hex digest of the steps' names, image sizes, board points and every view's
    point ids and image points: equal for the same observations, to the bit."""
    digest = hashlib.sha1()
    for name, obs in observations.items():
        digest.update(f"{name}|{tuple(obs.image_size)}|{obs.n_views}|".encode())
        digest.update(np.ascontiguousarray(obs.object_points, float).tobytes())
        for ids, pts in obs.views:
            digest.update(np.ascontiguousarray(ids, np.int64).tobytes())
            digest.update(np.ascontiguousarray(pts, float).tobytes())
    return digest.hexdigest()


def step_starts(observations: Mapping[str, Observations], select: bool = True,
                decentring: bool = True, workers: int = 1, held_terms: tuple[str, ...] = (),
                model: str = "standard") -> StepStarts:
    """Per step: chosen terms (``select``; else all of ``model``'s), their held-out errors and
    an OpenCV calibration with them; a step that cannot be started is left out (``skipped``:
    step -> reason). The held-out fits start from :func:`_robust_start`. Steps run in
    ``workers`` processes (the results do not depend on it)."""
    terms, held, init, skipped = {}, {}, {}, {}
    items = [(name, obs, select, decentring, held_terms, model)
             for name, obs in observations.items()]
    for (name, *_), (term, choice, start, why) in zip(
            items, _map_steps(_initial_step, items, workers), strict=True):
        terms[name] = term
        if choice is not None:
            held[name] = choice
        if start is not None:
            init[name] = start
        else:
            skipped[name] = why
    made_for = (bool(select), bool(decentring), tuple(held_terms), model,
                observations_fingerprint(observations))
    return StepStarts(terms, held, init, skipped, made_for)


def _robust_start(obs: Observations, held_terms: tuple[str, ...] = ()
                  ) -> tuple[CalibrationResult | None, str | None]:
    """A calibration with k1 (unless held) that does not hang on OpenCV's own start where that
    is ill-posed (:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_robust`: a range
    of focal lengths tried too where its views are all within
    :data:`~zoomcalib.calibrate.opencv_backend.FRONTO_PARALLEL_DEG` of fronto-parallel, or its
    result is no camera) and None; or None and why no start gave a camera (the step then
    starts from OpenCV's own start alone, and a step that cannot start says both reasons)."""
    try:
        return calibrate_opencv_robust(obs, flags=_distortion_flags(
            _without(("k1",), held_terms)), fronto_parallel_deg=FRONTO_PARALLEL_DEG,
            camera_only=True, criteria=START_CRITERIA), None
    except (ValueError, RuntimeError) as exc:
        return None, " ".join(str(exc).split()) or type(exc).__name__


def _opencv_start(name: str, obs: Observations, terms: dict,
                  seed: CalibrationResult | None = None, held_terms: tuple[str, ...] = ()
                  ) -> CalibrationResult:
    """OpenCV with the step's chosen terms, then with k1 alone, then with no distortion (a
    long-end step whose distortion OpenCV cannot separate): the start the adjustment then
    improves. Each from OpenCV's own start and from ``seed`` (:func:`_robust_start`), the
    result with the smallest RMS that is a camera
    (:func:`~zoomcalib.calibrate.opencv_backend.not_a_camera`) kept; with neither, from a
    range of focal lengths
    (:func:`~zoomcalib.calibrate.opencv_backend.calibrate_opencv_multistart`).
    ``terms[name]`` is set to the set used; ValueError when no set gives a camera."""
    reasons = []
    for attempt in dict.fromkeys((terms[name], _without(("k1",), held_terms), ())):
        flags = _distortion_flags(attempt)
        candidates, reason = [], "no start"
        guesses = [{}] + ([] if seed is None else [_guess(seed, attempt)])
        for guess in guesses:
            try:
                result = calibrate_opencv(obs, flags=flags, keystone=False,
                                          criteria=START_CRITERIA, **guess)
                reason = not_a_camera(result, obs.image_size)
            except (ValueError, RuntimeError) as exc:
                result, reason = None, str(exc)
            candidates += [result] if reason is None else []
        if not candidates:
            candidates = [r for r in [calibrate_opencv_multistart(
                obs, flags=flags, criteria=START_CRITERIA)] if r]
        if candidates:
            terms[name] = attempt
            return min(candidates, key=lambda r: r.rms_px)
        reasons.append(f"{'+'.join(attempt) or 'no distortion'}: {reason}")
    raise ValueError(f"step {name}: no starting calibration ({'; '.join(reasons)})")


def _without(terms: tuple[str, ...], held_terms: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(t for t in terms if t not in held_terms)


def _select_on_board(observations: Mapping[str, Observations],
                     init: Mapping[str, CalibrationResult], board_points: list[np.ndarray],
                     terms: dict[str, tuple[str, ...]], held: dict[str, TermChoice],
                     decentring: bool = True, workers: int = 1,
                     held_terms: tuple[str, ...] = ()) -> bool:
    """Choose each started step's distortion terms again, by held-out views on the board's
    estimated shape (``board_points``, one (n, 3) array per step of ``init``, in its order;
    :func:`select_distortion`, steps in ``workers`` processes); ``terms`` and ``held`` are
    updated in place. True when a step's terms changed."""
    changed = False
    items = [(observations[name], 0.01, points, start)
             for (name, start), points in zip(init.items(), board_points, strict=True)]
    for name, choice in zip(init, _map_steps(select_distortion, items, workers), strict=True):
        if not choice.excess_se_px2:
            continue  # too few views, or no set could be fitted: keep the flat-board choice
        held[name] = choice
        chosen = _without(with_decentring(choice.terms, decentring), held_terms)
        changed |= chosen != terms[name]
        terms[name] = chosen
    return changed
