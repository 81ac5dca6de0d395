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
fits use the board's estimated 3-D points, so a waving board does not make a basin of its own.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from .opencv_backend import calibrate_opencv, not_a_camera
from .result import CalibrationResult, Observations, one_opencv_thread

#: Rows (and columns) of the profile, as fractions of the image's height (width).
GRID = (1 / 14, 3 / 14, 5 / 14, 7 / 14, 9 / 14, 11 / 14, 13 / 14)
#: OpenCV's stop rule for the grid's fits: the profile needs the basin, not its last digit.
GRID_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-6)
#: The other basin replaces the given one when its cost is lower by more than this many noise
#: variances (a likelihood ratio of exp(MIN_GAIN / 2)).
MIN_GAIN = 9.0


@dataclass
class BasinCheck:
    """The outcome of :func:`best_basin`.

    ``fit``: the free OpenCV fit in the best basin found (None when no fit is a camera);
    ``moved``: it is not the given camera's basin; ``cost_px2`` and ``other_cost_px2``: the sum of
    squared reprojection errors (px^2) from the given camera and from the profile's best;
    ``profile``: per grid value tried, ``(axis, value px, cost px^2)`` (``inf``: no camera);
    ``why``: why nothing was checked, else None; ``start_px``: the given camera's principal
    point ``(cx, cy)``, px.
    """

    fit: CalibrationResult | None
    moved: bool
    start_px: tuple[float, float] = (float("nan"), float("nan"))
    cost_px2: float = float("nan")
    other_cost_px2: float = float("nan")
    profile: list[tuple[str, float, float]] | None = None
    why: str | None = None

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
               "other_cost_px2": number(self.other_cost_px2), "why": self.why}
        if self.moved and self.fit is not None:
            out |= {"cx": self.fit.cx, "cy": self.fit.cy, "summary": self.summary()}
        return out


def _cost(fit: CalibrationResult) -> float:
    return float(fit.rms_px**2 * fit.info["n_points"])


def _fit(obs: Observations, K: np.ndarray, dist: np.ndarray, flags: int
         ) -> CalibrationResult | None:
    """OpenCV from ``K`` and ``dist`` (aspect ratio held), or None when that is no camera."""
    try:
        with warnings.catch_warnings():  # a pose's sigma is not used here
            warnings.simplefilter("ignore", RuntimeWarning)
            fit = calibrate_opencv(obs, flags=flags, fix_aspect=True, K_guess=K, dist_guess=dist)
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
        return BasinCheck(None, False, given, why="no fit from the given camera is a camera")
    start = dist.copy()
    start[2:4] = 0.0  # no decentring: the grid point's own basin, not the given one's
    profile, best = [], (np.inf, here.K, start)
    w, h = obs.image_size
    for axis, size in (("cy", h), ("cx", w)):
        column = (1, 2) if axis == "cy" else (0, 2)
        for fraction in GRID:
            trial = best[1].copy()
            trial[column] = fraction * size
            cost, K_end, dist_end = _held_point_cost(obs, trial, start, flags)
            profile.append((axis, float(trial[column]), cost))
            if cost < best[0]:
                best = (cost, K_end, dist_end)
    other = None if not np.isfinite(best[0]) else _fit(obs, best[1], best[2], flags)
    cost_here = _cost(here)
    if other is None or _cost(other) >= cost_here - MIN_GAIN * noise_px**2:
        return BasinCheck(here, False, given, cost_here,
                          np.inf if other is None else _cost(other), profile)
    return BasinCheck(other, True, given, cost_here, _cost(other), profile)
