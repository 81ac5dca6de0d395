r"""Which basin a step's principal point is in: a coarse profile of the cost over the image.

At the long end of a zoom a step's views are nearly fronto-parallel, and a principal point
moved by :math:`\delta` is taken up, to first order, by the views' rotations; what is left is
quadratic over the field, as the decentring terms are (:math:`\delta y = p_1 (r^2 + 2 y^2)
+ 2 p_2 x y`, and alike in x). The cost of one step's views as a function of the principal
point then has more than one minimum, the decentring of opposite signs in each: on a
synthetic sweep that imitates a real PTZ camera (``benchmarks/bench_real_mc.py``) the 9x
step's profile in cy had its minimum 40 px from the truth and a second one 290 px from it,
with p1 of the other sign, and a solve started in the second stayed there with a sigma of
9 px. A linearised sigma says nothing of another basin.

:func:`best_basin` profiles the cost over the image: the principal point held at a grid of
rows (then of columns, at the best row), every other intrinsic and each view's pose fitted by
OpenCV from no decentring; a free fit from the grid's best fit is compared with a free fit from
the given camera, and the lower cost wins by more than :data:`MIN_GAIN` noise variances. The
views' cost differences ``d_v`` (given minus other, px^2) are also put to a one-sided paired
test, ``t = mean(d) / (sd(d) / sqrt(V))`` against Student's quantile of ``V - 1`` degrees of
freedom at :data:`VIEW_TEST_LEVEL` (3 sigma); it is reported, not required. Required, it kept
half of a real narrow step's frames in the basin the other half chose where a few views had
made another 110 noise variances cheaper, but it left synthetic sweeps with the real views'
own errors (``benchmarks/bench_real_mc.py``) in the wrong basin at 6x-10x (their cy spread
80-170 px, pooled RMS z 3.65): the views' errors hide right moves too
(``docs/notes/real-camera-halves.md``, "The halves"). A move the views do not agree on is
flagged. The fits use the board's estimated 3-D points, so a waving board does not make a
basin of its own.

A free fit also starts from the other basin that the decentring predicts (:func:`_mirrored`):
where a step has k1, the same centre of distortion is reached with the decentring negated and
the principal point ``2 f (p2, p1) / k1`` away. The profile alone can miss that basin when it
lies far off in both coordinates, its rows being held at the given (wrong) column.

The basin not chosen is reported (``BasinCheck.second``) when its principal point is distinct
from the chosen one's (more than :data:`DISTINCT_SD` of their combined sigma apart): the best
free fit, from the profile's starts, the mirrored one or the given camera, that lands
elsewhere, with its cost.

*Two basins the views do not tell apart.* The chosen basin is put to the same paired test
against the second one (``second_view_t``: the views' cost drops from the second basin to the
chosen). Where it does not pass, which basin holds the principal point rests on a few views,
and neither basin's linearised sigma says so: the halves of a real narrow step's frames (15
each) chose basins 120 px apart in cx, each by 140-480 noise variances, with sigmas of 10-20
px. The step is then a mixture of the two, and each of ``fx``, ``cx``, ``cy`` takes the
variance that an even choice between them adds, ``(Delta / 2)^2`` with ``Delta`` the
distance between the two fits (and so does each distortion term: the second basin's
decentring has the other sign) (:meth:`BasinCheck.half_gap`; the zoom-wide adjustment adds it
to its covariance).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.stats

from .opencv_backend import (
    START_CRITERIA,
    calibrate_opencv,
    not_a_camera,
    pose_sigmas_unused,
)
from .result import CalibrationResult, Observations, one_opencv_thread

#: OpenCV's distortion terms, in its order.
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: Rows (and columns) of the profile, as fractions of the image's height (width).
GRID = (1 / 14, 3 / 14, 5 / 14, 7 / 14, 9 / 14, 11 / 14, 13 / 14)
#: OpenCV's stop rule for the grid's fits: the profile needs the basin, not its last digit.
GRID_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-6)
#: The other basin replaces the given one when its cost is lower by more than this many noise
#: variances (a likelihood ratio of exp(MIN_GAIN / 2)).
MIN_GAIN = 9.0
#: One-sided level of the views' paired test (the normal's 3 sigma): is the other basin lower
#: over the views consistently, or by a few views' errors?
VIEW_TEST_LEVEL = 0.00135
#: Two basins are distinct when their principal points lie more than this many of their
#: combined sigmas (the fits' own, ``hypot`` over cx and cy) apart.
DISTINCT_SD = 3.0


@dataclass
class BasinCheck:
    """The outcome of :func:`best_basin`.

    ``fit``: the free OpenCV fit in the best basin found (None when no fit is a camera);
    ``moved``: it is not the given camera's basin; ``cost_px2`` and ``other_cost_px2``: the sum of
    squared reprojection errors (px^2) from the given camera and from the profile's best;
    ``profile``: per grid value tried, ``(axis, value px, cost px^2)`` (``inf``: no camera);
    ``why``: why nothing was checked, else None; ``start_px``: the given camera's principal
    point ``(cx, cy)``, px; ``second``: the free fit in the best distinct basin not chosen
    (None when every fit found lands in the chosen one), ``second_cost_px2`` its cost;
    ``noise_px``: the corner noise the costs are compared in; ``view_t``: the views' paired
    test statistic of the cost's drop from the given basin to the best other fit (NaN with
    fewer than 2 views or no other fit), ``view_t_needed`` the quantile it passes when the
    views agree on the drop. ``terms``: the distortion terms the basins were judged with, as
    the caller names them (empty when it does not).
    """

    fit: CalibrationResult | None
    moved: bool
    start_px: tuple[float, float] = (float("nan"), float("nan"))
    cost_px2: float = float("nan")
    other_cost_px2: float = float("nan")
    profile: list[tuple[str, float, float]] | None = None
    why: str | None = None
    second: CalibrationResult | None = None
    second_cost_px2: float = float("nan")
    noise_px: float = float("nan")
    view_t: float = float("nan")
    view_t_needed: float = float("nan")
    second_view_t: float = float("nan")
    second_view_t_needed: float = float("nan")
    terms: tuple[str, ...] = ()

    @property
    def chosen_cost_px2(self) -> float:
        """The cost of the chosen basin's fit, px^2."""
        return self.other_cost_px2 if self.moved else self.cost_px2

    @property
    def views_disagree(self) -> bool:
        """It moved, and the views' paired test does not support the move (False where there
        was no test: fewer than 2 views)."""
        return bool(self.moved and np.isfinite(self.view_t)
                    and self.view_t <= self.view_t_needed)

    @property
    def ambiguous(self) -> bool:
        """There is a second basin and the views' paired test does not say the chosen one is
        lower (``second_view_t`` at most its quantile): which basin holds the principal point
        rests on a few views' errors (module docstring, "Two basins the views do not tell
        apart")."""
        return bool(self.fit is not None and self.second is not None
                    and np.isfinite(self.second_view_t)
                    and self.second_view_t <= self.second_view_t_needed)

    def half_gap(self) -> dict[str, float]:
        """Half the distance between the chosen and the second basin's ``fx``, ``cx``, ``cy``
        (px) and distortion terms (OpenCV's names, as many as both fits have), where
        :attr:`ambiguous` (else empty): the sd a choice between the two adds."""
        if not self.ambiguous:
            return {}
        gap = {q: 0.5 * abs(getattr(self.fit, q) - getattr(self.second, q))
               for q in ("fx", "cx", "cy")}
        a, b = np.ravel(self.fit.dist), np.ravel(self.second.dist)
        n = min(len(a), len(b))
        return gap | {q: 0.5 * abs(float(x - y))
                      for q, x, y in zip(DISTORTION_NAMES[:n], a[:n], b[:n], strict=True)}

    @property
    def second_excess(self) -> float:
        """How much costlier the basin not chosen is, in noise variances (NaN without one)."""
        if self.second is None:
            return float("nan")
        return float((self.second_cost_px2 - self.chosen_cost_px2) / self.noise_px**2)

    def summary(self) -> str:
        """What moved, in words (empty when nothing did)."""
        if not self.moved or self.fit is None:
            return ""
        return (f"the principal point started in a basin of higher cost (cx, cy "
                f"{self.start_px[0]:.0f}, {self.start_px[1]:.0f} px) and was moved to "
                f"{self.fit.cx:.0f}, {self.fit.cy:.0f} px, "
                f"{self.cost_px2 - self.other_cost_px2:.3g} px^2 lower")

    def to_dict(self) -> dict:
        def number(x: float) -> float | None:  # JSON has no inf or NaN
            return float(x) if np.isfinite(x) else None

        out = {"moved": self.moved, "start_px": [number(v) for v in self.start_px],
               "cost_px2": number(self.cost_px2),
               "other_cost_px2": number(self.other_cost_px2), "why": self.why,
               "view_t": number(self.view_t), "view_t_needed": number(self.view_t_needed),
               "views_disagree": self.views_disagree, "ambiguous": self.ambiguous,
               "half_gap": self.half_gap(), "terms": list(self.terms)}
        if self.fit is not None:  # the step alone on the adjustment's board
            out["alone"] = {"fx": self.fit.fx, "cx": self.fit.cx, "cy": self.fit.cy}
        if self.moved and self.fit is not None:
            out |= {"cx": self.fit.cx, "cy": self.fit.cy, "summary": self.summary()}
        if self.second is not None:
            out["second"] = {"cx": self.second.cx, "cy": self.second.cy,
                             "fx": self.second.fx, "p1": float(self.second.dist[2]),
                             "cost_px2": number(self.second_cost_px2),
                             "excess_noise_variances": number(self.second_excess),
                             "view_t": number(self.second_view_t),
                             "view_t_needed": number(self.second_view_t_needed)}
        return out


def _cost(fit: CalibrationResult) -> float:
    return float(fit.rms_px**2 * fit.info["n_points"])


def _fit(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int
         ) -> CalibrationResult | None:
    """OpenCV from ``K`` and ``dist`` (aspect ratio held), or None when that is no camera."""
    try:
        with pose_sigmas_unused():  # a pose's sigma is not used here
            fit = calibrate_opencv(obs, flags=flags, fix_aspect=True, K_guess=K, dist_guess=dist,
                                   keystone=False, criteria=START_CRITERIA)
    except (ValueError, RuntimeError, cv2.error):
        return None
    return None if not_a_camera(fit, obs.image_size) is not None else fit


def _held_point_cost(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """``cv2.calibrateCamera`` with the principal point and the aspect ratio held at ``K``'s:
    the sum of squared errors (px^2; ``inf`` when OpenCV fails) and the camera matrix and
    distortion it ends at (no sigmas: only the profile's cost is needed)."""
    objects = [obs.object_points[ids].astype(np.float32) for ids, _ in obs.views]
    images = [pts.astype(np.float32).reshape(-1, 1, 2) for _, pts in obs.views]
    flags |= (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT
              | cv2.CALIB_FIX_ASPECT_RATIO)
    try:
        with one_opencv_thread():
            rms, K_out, dist_out, _, _ = cv2.calibrateCamera(
                objects, images, tuple(obs.image_size), K.copy(), dist.copy(), flags=flags,
                criteria=GRID_CRITERIA)
    except cv2.error:
        return np.inf, K, dist
    cost = rms**2 * sum(len(ids) for ids, _ in obs.views)
    return (float(cost) if np.isfinite(cost) else np.inf), K_out, dist_out.ravel()


def best_basin(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int,
               noise_px: float) -> BasinCheck:
    """The basin of the lowest cost for the principal point of one step (module docstring).

    Parameters
    ----------
    obs : Observations
        The step's views, ``object_points`` the board's estimated 3-D points (board frame).
    K : (3, 3) ndarray
        The camera found, px (its ``fy / fx`` is held).
    dist : (5,) or (8,) ndarray
        Its distortion, OpenCV order.
    flags : int
        OpenCV flags fixing the terms the step does not estimate (``CALIB_FIX_K3`` ...).
    noise_px : float
        The corner noise's sd per coordinate, px: the other basin must lower the cost by
        more than ``MIN_GAIN * noise_px**2``.

    Returns
    -------
    BasinCheck
    """
    K, dist = np.asarray(K, float), np.asarray(dist, float).copy()
    given = (float(K[0, 2]), float(K[1, 2]))
    here = _fit(obs, K, dist, flags)
    if here is None:
        return BasinCheck(None, False, given, why="no fit from the given camera is a camera",
                          noise_px=noise_px)
    profile, ends = _profile(obs, here.K, here.dist, flags)
    starts = [ends[i] for i in _starts([c for _, _, c in profile])] + _mirrored(here, obs)
    fits = [f for f in (_fit(obs, K0, d0, flags) for K0, d0 in starts) if f is not None]
    cost_here = _cost(here)
    best = min(fits, key=_cost, default=None)
    view_t, needed = _paired_views(obs, here, best)
    moved = best is not None and _cost(best) < cost_here - MIN_GAIN * noise_px**2
    chosen = best if moved else here
    others = [f for f in [here, *fits] if _distinct(f, chosen)]
    second = min(others, key=_cost, default=None)
    second_t, second_needed = _paired_views(obs, second, chosen) if second is not None else (
        float("nan"), float("inf"))
    return BasinCheck(chosen, moved, given, cost_here,
                      np.inf if best is None else _cost(best), profile, None, second,
                      np.nan if second is None else _cost(second), noise_px, view_t, needed,
                      second_t, second_needed)


def _paired_views(obs: Observations, here: CalibrationResult,
                  other: CalibrationResult | None) -> tuple[float, float]:
    """The views' paired test of ``other`` against ``here`` (module docstring): ``t`` of the
    per-view cost drops (px^2, ``rms_v^2 n_v``) and the quantile it must pass; NaN, inf with
    fewer than 2 views or no other fit."""
    if other is None or len(here.per_view_rms_px) < 2:
        return float("nan"), float("inf")
    n_v = np.array([len(ids) for ids, _ in obs.views], float)
    drop = n_v * (np.asarray(here.per_view_rms_px) ** 2 - np.asarray(other.per_view_rms_px) ** 2)
    spread = np.std(drop, ddof=1)
    views = len(drop)
    t = np.inf * np.sign(drop.mean()) if spread == 0 else drop.mean() / (spread / np.sqrt(views))
    return float(t), float(scipy.stats.t.ppf(1.0 - VIEW_TEST_LEVEL, views - 1))


def _profile(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int
             ) -> tuple[list[tuple[str, float, float]], list[tuple[np.ndarray, np.ndarray]]]:
    """The cost held at :data:`GRID`'s rows (cx at ``K``'s), then at its columns (at the best
    row): per grid value ``(axis, value px, cost px^2)`` and the camera matrix and distortion
    its fit ended at. A row is fitted from no decentring and from the decentring of ``dist``
    negated (each basin's decentring has its own sign; once where ``dist`` has none), the
    lower kept; a column from no decentring."""
    none, flipped = dist.copy(), dist.copy()
    none[2:4] = 0.0
    flipped[2:4] *= -1.0
    # without decentring the two row starts are one: fitted once
    row_starts = (none, flipped) if np.any(dist[2:4]) else (none,)
    profile, ends, best = [], [], (np.inf, K)
    w, h = obs.image_size
    for axis, size, starts in (("cy", h, row_starts), ("cx", w, (none,))):
        column = (1, 2) if axis == "cy" else (0, 2)
        for fraction in GRID:
            trial = best[1].copy()
            trial[column] = fraction * size
            cost, K_end, dist_end = min((_held_point_cost(obs, trial, d, flags)
                                         for d in starts), key=lambda fit: fit[0])
            profile.append((axis, float(trial[column]), cost))
            ends.append((K_end, dist_end))
            if cost < best[0]:
                best = (cost, K_end)
    return profile, ends


def _starts(costs: list[float]) -> list[int]:
    """The profile's entries a free fit starts from: its lowest, and the lowest other local
    minimum of the row profile (the first ``len(GRID)`` entries), if any."""
    costs = np.asarray(costs, float)
    if not np.any(np.isfinite(costs)):
        return []
    lowest = int(np.argmin(costs))
    rows = np.r_[np.inf, costs[:len(GRID)], np.inf]
    minima = [i for i in range(len(GRID)) if np.isfinite(rows[i + 1])
              and rows[i + 1] <= rows[i] and rows[i + 1] <= rows[i + 2] and i != lowest]
    return [lowest] + sorted(minima, key=lambda i: costs[i])[:1]


def _mirrored(fit: CalibrationResult, obs: Observations
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The start in the other basin of :func:`best_basin`'s module docstring: over a narrow
    field, decentring ``(p1, p2)`` acts as the radial term moved off the principal point by
    ``f (p2, p1) / k1`` (normalised ``(x, y) k1 r^2`` about a centre moved by ``d`` gains
    ``k1 (3 x^2 + y^2, 2 x y) d_x``, the ``p2`` pattern), so the same centre of distortion
    is reached from a principal point ``2 f (p2, p1) / k1`` away with the decentring negated.
    Empty where the step has no k1 or that point lies more than an image size outside the
    image."""
    k1, p1, p2 = float(fit.dist[0]), float(fit.dist[2]), float(fit.dist[3])
    if k1 == 0.0 or (p1 == 0.0 and p2 == 0.0):
        return []
    K, dist = fit.K.copy(), fit.dist.copy()
    K[0, 2] -= 2.0 * fit.fx * p2 / k1
    K[1, 2] -= 2.0 * fit.fy * p1 / k1
    dist[2:4] *= -1.0
    size = np.asarray(obs.image_size, float)
    if np.any(K[:2, 2] < -size) or np.any(K[:2, 2] > 2 * size):
        return []
    return [(K, dist)]


def _distinct(a: CalibrationResult, b: CalibrationResult) -> bool:
    """The two fits' principal points lie more than :data:`DISTINCT_SD` combined sigmas
    apart."""
    var = sum(a.sd[q] ** 2 + b.sd[q] ** 2 for q in ("cx", "cy"))
    return bool(np.hypot(a.cx - b.cx, a.cy - b.cy) > DISTINCT_SD * np.sqrt(var))
