r"""Capture advice: which views to add to a step, and the sigmas they are predicted to give.

For a step whose status is not ``ok`` (:mod:`zoomcalib.calibrate.status`), candidate sets of
extra views are laid out (:func:`planned_poses`): ``n`` views of the board at the median
distance of the step's views or closer (:data:`DISTANCES`), its centre placed in turn at the
centres of the image's four quadrants and at the image centre, the board tilted by ``theta``
about the camera's horizontal axis (both signs) and about its vertical axis (both signs), one
after the other. Each candidate's information about the intrinsics ``q`` is added to that of
the step's own views, the poses marginalised view by view:

.. math::

    A_v = \frac{1}{s^2}\left(J_q^T J_q - J_q^T J_p (J_p^T J_p)^{-1} J_p^T J_q\right),\qquad
    C_{new} = \left(C^{-1} + \sum_v A_v / F^2\right)^{-1},

``J_q``, ``J_p`` a view's Jacobians with respect to the free intrinsics and its pose
(``cv2.projectPoints``), over the board points that land inside the image, ``s^2`` the step's
residual variance per coordinate (:func:`~zoomcalib.calibrate.quality.view_information`), and
``C`` the step's reported covariance (:func:`~zoomcalib.calibrate.quality.intrinsics_covariance`:
what its own views, and for the zoom-wide adjustment its neighbours through the prior, tell).
Where the step's views disagree beyond the corner noise (its sigmas widened by a factor ``F``,
the median over fx, cx, cy of reported over noise-model sigma), the new views are taken to
carry the same excess: their information is divided by ``F^2``.

The Jacobians are taken at the step's camera with the distortion terms its views do not
determine (``|k| < 2 sd``) set to zero: in a nearly singular step those terms are fitted
noise, and linearised at them the predicted principal-point sigma changed 3-fold between noise
draws of one set of views (1.65 times too small against the spread of 40 redrawn
calibrations; 1.18 times with them zeroed).

At a zoom's long end the principal point trades with the distortion terms and the poses
whatever the tilt; there a closer board, which fills more of the narrow field, is what helps
(on a 9x6 board filling 40 % of the width at fx 7000 px, 24 views tilted 20 degrees give a cx
sigma of 19 px at the step's distance and 8 px at 0.6 of it).

The advice is the smallest candidate (fewest views, then the largest distance, then the
least tilt) whose predicted
sigmas meet the ``ok`` limits (:data:`~zoomcalib.calibrate.status.PP_SD_LIMIT` of the image
diagonal for cx and cy, :data:`~zoomcalib.calibrate.status.FX_SD_LIMIT` of fx), else the
candidate with the smallest predicted principal-point sigma, marked as not reaching them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .quality import intrinsics_covariance, view_information
from .result import DIST_NAMES, CalibrationResult, Observations
from .status import FX_SD_LIMIT, PP_SD_LIMIT

__all__ = ["CaptureAdvice", "advise", "planned_poses", "predicted_sd", "median_distance",
           "TILTS_DEG", "COUNTS", "DISTANCES", "PLACES"]

#: Board tilts tried, degrees.
TILTS_DEG = (20.0, 30.0, 45.0)
#: Numbers of added views tried.
COUNTS = (4, 8, 12, 16, 24)
#: Distances tried, as fractions of the median distance of the step's views.
DISTANCES = (1.0, 0.7, 0.5)
#: Where the board's centre is placed, as fractions of the image width and height, in turn.
PLACES = ((0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7), (0.5, 0.5))
#: Rotation axis and sign of the added views, in turn: about the camera's horizontal axis
#: (x), its vertical axis (y), then both again with the other sign.
_AXES = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))


@dataclass
class CaptureAdvice:
    """Views to add to one step (module docstring) and what they are predicted to give.

    ``views`` board views tilted ``tilt_deg`` (about the horizontal and the vertical axis in
    turn, both signs), at ``distance_mm`` from the camera (``distance_ratio`` times the median
    of the step's views), the board's centre in the four
    quadrants and the centre of the image in turn; ``current_sd`` and ``predicted_sd`` the
    1-sigma of fx, cx, cy (px) now and with them; ``reaches`` whether that meets the ``ok``
    limits.
    """

    views: int
    tilt_deg: float
    distance_mm: float
    distance_ratio: float = 1.0
    current_sd: dict[str, float] = field(default_factory=dict)
    predicted_sd: dict[str, float] = field(default_factory=dict)
    reaches: bool = False

    def text(self) -> str:
        """One line for a person."""
        sd = ", ".join(f"{q} {self.current_sd[q]:.3g} -> {self.predicted_sd[q]:.3g} px"
                       for q in ("fx", "cx", "cy"))
        verdict = "" if self.reaches else " (still short of the ok limits)"
        return (f"add {self.views} views with the board tilted {self.tilt_deg:.0f} degrees, "
                f"in turn about the horizontal and the vertical axis, both ways, at "
                f"{self.distance_mm / 1000:.2g} m ({self.distance_ratio:.1f} x the views' "
                f"median), its centre in each quadrant of the image and at its centre: "
                f"predicted sd {sd}{verdict}")

    def to_dict(self) -> dict:
        return {"views": self.views, "tilt_deg": self.tilt_deg,
                "distance_mm": self.distance_mm, "distance_ratio": self.distance_ratio,
                "positions": [list(p) for p in PLACES],
                "current_sd": dict(self.current_sd), "predicted_sd": dict(self.predicted_sd),
                "reaches": self.reaches, "text": self.text()}


def _board_centre(obs: Observations) -> np.ndarray:
    return np.asarray(obs.object_points, float).mean(axis=0)


def median_distance(result: CalibrationResult, obs: Observations) -> float:
    """Median depth of the board's centre over the step's views, in the board's units."""
    c = _board_centre(obs)
    depth = [(cv2.Rodrigues(np.asarray(r, float))[0] @ c + np.asarray(t, float))[2]
             for r, t in zip(result.rvecs, result.tvecs, strict=True)]
    return float(np.median(depth))


def planned_poses(result: CalibrationResult, obs: Observations, views: int, tilt_deg: float,
                  distance: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """``views`` poses ``(rvec, tvec)`` (``Rt_cam_board``) laid out as the module docstring
    says, at ``distance`` (default :func:`median_distance`)."""
    d = median_distance(result, obs) if distance is None else float(distance)
    w, h = obs.image_size
    c = _board_centre(obs)
    K_inv = np.linalg.inv(result.K)
    poses = []
    for i in range(views):
        ax, ay = _AXES[i % len(_AXES)]
        R = cv2.Rodrigues(np.deg2rad(tilt_deg) * np.array([ax, ay, 0.0]))[0]
        fx_, fy_ = PLACES[i % len(PLACES)]
        ray = K_inv @ np.array([fx_ * (w - 1), fy_ * (h - 1), 1.0])
        t_centre = d * ray / ray[2]
        poses.append((cv2.Rodrigues(R)[0].ravel(), t_centre - R @ c))
    return poses


def _added_information(result: CalibrationResult, obs: Observations,
                       poses: list[tuple[np.ndarray, np.ndarray]], free: np.ndarray
                       ) -> np.ndarray:
    """Sum over the planned views of their information on the free intrinsics (unit noise),
    each view's pose marginalised; points outside the image are left out."""
    w, h = obs.image_size
    X = np.asarray(obs.object_points if result.object_points is None
                   else result.object_points, np.float64)
    info = np.zeros((len(free), len(free)))
    for rvec, tvec in poses:
        uv, jac = cv2.projectPoints(X, rvec, tvec, result.K, result.dist)
        uv = uv.reshape(-1, 2)
        inside = np.all((uv >= 0) & (uv <= np.array([w - 1, h - 1])), axis=1)
        if inside.sum() < 8:
            continue
        rows = np.repeat(inside, 2)
        jp, jq = jac[rows, :6], jac[rows, 6:][:, free]
        info += jq.T @ jq - jq.T @ jp @ np.linalg.solve(jp.T @ jp, jp.T @ jq)
    return info


def _determined(result: CalibrationResult) -> CalibrationResult:
    """``result`` with the distortion terms within 2 of their sigmas of zero set to zero."""
    dist = np.array(result.dist, float)
    for i, name in enumerate(DIST_NAMES[:len(dist)]):
        if not abs(dist[i]) >= 2.0 * result.sd.get(name, np.inf):
            dist[i] = 0.0
    return replace(result, dist=dist)


def _scatter_factor(result: CalibrationResult) -> float:
    """How far the step's views disagree beyond the corner noise: the median over fx, cx, cy
    of the reported sigma over the noise model's (``info['sd_noise_model']``), at least 1."""
    model = result.info.get("sd_noise_model") or {}
    ratios = [result.sd[q] / model[q] for q in ("fx", "cx", "cy")
              if model.get(q, 0) > 0 and np.isfinite(result.sd.get(q, np.nan))]
    return max(float(np.median(ratios)), 1.0) if ratios else 1.0


def predicted_sd(result: CalibrationResult, obs: Observations,
                 poses: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """1-sigma of fx, cx, cy (px) once the views of ``poses`` are added (module docstring)."""
    names, current = intrinsics_covariance(result, obs)
    _, _, _, s2 = view_information(result, obs)
    linear = _determined(result)
    _, free, _, _ = view_information(linear, obs)
    added = _added_information(linear, obs, poses, free) / (s2 * _scatter_factor(result) ** 2)
    scale = np.sqrt(np.diag(current))
    info = np.linalg.pinv(current / np.outer(scale, scale)) / np.outer(scale, scale)
    new = np.linalg.pinv(info + added)
    return {q: float(np.sqrt(max(new[names.index(q), names.index(q)], 0.0)))
            for q in ("fx", "cx", "cy")}


def _meets(sd: dict[str, float], result: CalibrationResult, image_size) -> bool:
    diagonal = float(np.hypot(*image_size))
    return (sd["cx"] <= PP_SD_LIMIT * diagonal and sd["cy"] <= PP_SD_LIMIT * diagonal
            and sd["fx"] <= FX_SD_LIMIT * result.fx)


def advise(result: CalibrationResult, obs: Observations, tilts=TILTS_DEG, counts=COUNTS,
           distances=DISTANCES) -> CaptureAdvice | None:
    """The views to add to the step of ``result`` (calibrated from ``obs``), or None when its
    information cannot be formed (no free fx, cx, cy, or no views).

    Examples
    --------
    >>> import numpy as np
    >>> from zoomcalib.calibrate.opencv_backend import calibrate_opencv
    >>> from zoomcalib.targets import parse_pattern
    >>> rng = np.random.default_rng(0)
    >>> X = parse_pattern("chessboard:9x6:25").object_points.astype(float)
    >>> K = np.array([[3000.0, 0, 640], [0, 3000, 360], [0, 0, 1]])
    >>> views = []
    >>> for _ in range(8):  # nearly fronto-parallel: the principal point is poorly determined
    ...     r = np.deg2rad(rng.uniform(-3, 3, 3))
    ...     t = np.array([-100.0, -60, 1500]) + rng.uniform(-20, 20, 3)
    ...     p = cv2.projectPoints(X, r, t, K, np.zeros(5))[0].reshape(-1, 2)
    ...     views.append((np.arange(len(X)), p + rng.normal(0, 0.1, p.shape)))
    >>> obs = Observations(X, views, (1280, 720))
    >>> res = calibrate_opencv(obs)
    >>> advice = advise(res, obs)
    >>> advice.views, advice.tilt_deg, advice.reaches
    (4, 20.0, True)
    """
    try:
        return _advise(result, obs, tilts, counts, distances)
    except (ValueError, np.linalg.LinAlgError, cv2.error):
        return None  # no information to build on (a camera OpenCV cannot project with)


def _advise(result: CalibrationResult, obs: Observations, tilts, counts, distances
            ) -> CaptureAdvice | None:
    names, *_ = view_information(result, obs)
    if not obs.views or not {"fx", "cx", "cy"} <= set(names):
        return None
    median = median_distance(result, obs)
    current = {q: float(result.sd[q]) for q in ("fx", "cx", "cy")}
    best = None
    for n in counts:
        for ratio in distances:
            for tilt in tilts:
                poses = planned_poses(result, obs, n, tilt, ratio * median)
                sd = predicted_sd(result, obs, poses)
                plan = CaptureAdvice(n, tilt, ratio * median, ratio, current, sd,
                                     _meets(sd, result, obs.image_size))
                if plan.reaches:
                    return plan
                if best is None or np.hypot(sd["cx"], sd["cy"]) < np.hypot(
                        best.predicted_sd["cx"], best.predicted_sd["cy"]):
                    best = plan
    return best
