r"""Step status: may a step's calibration be used, and what to do when it may not.

Every step of a calibrate run gets one status, from the zoom table's result of the step (and,
for the zoom-wide adjustment, the step's own per-step calibration):

``unusable``
    Not a camera, or a camera the data do not determine. Its row stays in the zoom table and
    ``calibration.json`` with the status, but no ROS or mrcal file is written for it and the
    zoom model leaves it out. Reasons:

    - the focal length is not positive or not finite;
    - the principal point lies outside the image (a lens's axis meets the sensor);
    - the 1-sigma of ``cx`` (``cy``) exceeds a quarter of the image width (height): the data
      put the principal point anywhere in the central half;
    - the aspect ratio ``fy / fx`` differs from the sensor's by more than
      :data:`ASPECT_TOLERANCE` and 3 of its sigmas (pixels do not change shape with the zoom;
      the sensor's ratio is the precision-weighted median over the steps, :func:`sensor_aspect`);
    - the radial distortion folds inside the image: ``d r_d / d r <= 0`` before the distorted
      radius reaches the image corner farthest from the principal point, with
      ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`` on the
      normalised radius (two directions would image to one pixel).

``imprecise``
    A camera, but one to use with care. Reasons:

    - the 1-sigma of ``cx`` or ``cy`` exceeds :data:`PP_SD_LIMIT` of the image diagonal, or
      that of ``fx`` exceeds :data:`FX_SD_LIMIT` of ``fx``;
    - the solve did not converge;
    - the halves disagree (cross-validation ``|z| > 3``);
    - the zoom-wide adjustment moved ``fx``, ``cx`` or ``cy`` by more than :data:`MOVE_LIMIT`
      of the step's own per-step sigmas where that per-step result is itself well determined:
      the step's views and the rest of the zoom range (one board, the smoothness prior)
      disagree, so one of them is wrong for this step. The reason says which: where the step
      alone, fitted on the adjustment's estimated board (the basin check's fit), lands within
      :data:`MOVE_LIMIT` of those sigmas of the adjustment, the board's shape moved it (the
      per-step fit takes the board printed exactly and flat), else the other steps did.

``ok``
    None of the above. The step's other flags
    (:func:`~zoomcalib.calibrate.checks.conditioning_flags`) remain notes: their sigmas are
    already widened.

Each reason carries one remedy, an action on the capture or the options.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .result import CalibrationResult

__all__ = ["StepStatus", "step_status", "sensor_aspect", "distortion_fold_radius",
           "STATUSES", "ASPECT_TOLERANCE", "PP_SD_LIMIT", "FX_SD_LIMIT", "MOVE_LIMIT"]

#: The statuses, best first.
STATUSES = ("ok", "imprecise", "unusable")
#: Relative departure of ``fy / fx`` from the sensor's beyond which a step is unusable (and
#: beyond 3 of the ratio's sigmas).
ASPECT_TOLERANCE = 0.01
#: 1-sigma of cx or cy, as a fraction of the image diagonal, beyond which a step is imprecise.
PP_SD_LIMIT = 0.01
#: Relative 1-sigma of fx beyond which a step is imprecise.
FX_SD_LIMIT = 0.01
#: Shift of a well-determined step by the zoom-wide adjustment, in the step's own sigmas,
#: beyond which the step is imprecise.
MOVE_LIMIT = 3.0

_REMEDY = {
    "focal": "recalibrate the step with more views; check the pattern spec",
    "pp_outside": "add 8-10 views with the board tilted 30-45 degrees about the horizontal and "
                  "the vertical axis, placed in the image corners",
    "pp_sd": "add views with the board tilted 30-45 degrees about both axes, placed in the "
             "image corners",
    "aspect": "add views tilted 30-45 degrees; the other steps fix the sensor's aspect ratio",
    "fold": "use fewer distortion terms, or add views whose board reaches the image corners",
    "fx_sd": "add views tilted 30-45 degrees at two or more distances",
    "converged": "rerun; if it persists, add tilted views",
    "halves": "add views; keep the board rigid and the zoom fixed while capturing the step",
    "moved": "compare with the step's per-step result in calibration.json; a board re-taped "
             "or a zoom changed between this step and the others is the usual cause",
    "moved_board": "if the board was re-taped or bent between this step's frames and those of "
                   "the other steps of its session, give the step a session of its own (the "
                   "session column of steps.csv)",
}


@dataclass
class StepStatus:
    """A step's status (``ok``, ``imprecise`` or ``unusable``) with its reasons, the remedies
    (one per kind of finding) and, where the calibrate job made it, the capture advice
    (:meth:`zoomcalib.calibrate.advice.CaptureAdvice.to_dict`)."""

    status: str = "ok"
    reasons: list[str] = field(default_factory=list)
    remedies: list[str] = field(default_factory=list)
    advice: dict | None = None

    def add(self, status: str, reason: str, remedy_key: str) -> None:
        """Record one finding; the status becomes the worse of the two."""
        if STATUSES.index(status) > STATUSES.index(self.status):
            self.status = status
        self.reasons.append(reason)
        remedy = _REMEDY[remedy_key]
        if remedy not in self.remedies:
            self.remedies.append(remedy)

    @property
    def usable(self) -> bool:
        return self.status != "unusable"

    def summary(self) -> str:
        """One line: the status, then its reasons (empty reasons for ``ok``)."""
        return self.status + (": " + "; ".join(self.reasons) if self.reasons else "")

    def to_dict(self) -> dict:
        return {"status": self.status, "reasons": list(self.reasons),
                "remedies": list(self.remedies), "advice": self.advice}


def sensor_aspect(results: Mapping[str, CalibrationResult]) -> tuple[float, float] | None:
    """The sensor's aspect ratio ``fy / fx`` and its sigma from the steps' results: the median
    weighted by ``1 / sd^2`` of each step's ratio (sd from fx's and fy's 1-sigma, their
    correlation ignored, which overstates it), and the sigma of the weighted mean. Steps with
    a non-positive focal length or no finite sigma are left out; None when none is left.

    Examples
    --------
    >>> import numpy as np
    >>> def cam(fx, fy, sd):
    ...     return CalibrationResult("opencv", np.array([[fx, 0, 640], [0, fy, 360], [0, 0, 1.]]),
    ...                              np.zeros(5), {"fx": sd, "fy": sd}, 0.1, np.zeros(1),
    ...                              np.zeros((1, 3)), np.zeros((1, 3)))
    >>> a, sd = sensor_aspect({"1x": cam(1000, 1001, 1), "2x": cam(2000, 2002, 2),
    ...                        "9x": cam(9000, 10500, 90)})
    >>> round(a, 4)
    1.001
    """
    ratio, sd = _aspects(results)
    keep = np.isfinite(ratio) & np.isfinite(sd) & (sd > 0)
    if not keep.any():
        return None
    ratio, w = ratio[keep], 1.0 / sd[keep] ** 2
    order = np.argsort(ratio)
    cum = np.cumsum(w[order])
    median = float(ratio[order][np.searchsorted(cum, 0.5 * cum[-1])])
    return median, float(np.sqrt(1.0 / w.sum()))


def _aspects(results: Mapping[str, CalibrationResult]) -> tuple[np.ndarray, np.ndarray]:
    ratio, sd = [], []
    for res in results.values():
        fx, fy = res.fx, res.fy
        if not (fx > 0 and fy > 0 and np.isfinite(fx) and np.isfinite(fy)):
            ratio.append(np.nan)
            sd.append(np.nan)
            continue
        ratio.append(fy / fx)
        sd.append(fy / fx * np.hypot(res.sd.get("fx", np.nan) / fx,
                                     res.sd.get("fy", np.nan) / fy))
    return np.array(ratio, float), np.array(sd, float)


def distortion_fold_radius(dist: np.ndarray, r_max: float = 4.0, samples: int = 4000
                           ) -> tuple[float, float]:
    """Where the radial distortion folds: the first normalised undistorted radius ``r`` in
    ``(0, r_max]`` at which ``d r_d / d r <= 0`` (module docstring), and the distorted radius
    ``r_d`` reached there (the largest the lens images without folding). ``(inf, inf)`` when
    it does not fold below ``r_max``; tangential terms are left out (they do not fold a radius).

    Examples
    --------
    >>> import numpy as np
    >>> distortion_fold_radius(np.array([0.1, 0.0, 0, 0, 0]))
    (inf, inf)
    >>> r, rd = distortion_fold_radius(np.array([-1.0, 0.0, 0, 0, 0]))  # r_d = r - r^3
    >>> round(r, 3), round(rd, 3)
    (0.577, 0.385)
    """
    d = np.zeros(8)
    d[:min(len(dist), 8)] = np.asarray(dist, float)[:8]
    k1, k2, _, _, k3, k4, k5, k6 = d
    r = np.linspace(0.0, r_max, samples + 1)[1:]
    r2 = r * r
    rd = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    slope = np.diff(rd, prepend=0.0)
    bad = np.flatnonzero(~(slope > 0))
    if not len(bad):
        return float("inf"), float("inf")
    i = int(bad[0])
    return float(r[i - 1] if i else 0.0), float(rd[i - 1] if i else 0.0)


def step_status(res: CalibrationResult, image_size: tuple[int, int],
                aspect: tuple[float, float] | None = None,
                own: CalibrationResult | None = None,
                halves_z: Mapping[str, float] | None = None) -> StepStatus:
    """The status of one step's calibration ``res`` (module docstring).

    Parameters
    ----------
    res : CalibrationResult
        The zoom table's result of the step.
    image_size : (int, int)
        (width, height), px.
    aspect : (float, float), optional
        The sensor's ``fy / fx`` and its sigma (:func:`sensor_aspect`); the aspect check is
        skipped without it.
    own : CalibrationResult, optional
        The step calibrated on its own (per-step OpenCV), when ``res`` comes from the zoom-wide
        adjustment.
    halves_z : dict, optional
        The cross-validation's ``z`` of the step by parameter (and ``projection``: the RMS z of
        the halves' projections over the observed region).

    Examples
    --------
    >>> import numpy as np
    >>> K = np.array([[9000.0, 0, 650], [0, 10500, -660], [0, 0, 1]])
    >>> res = CalibrationResult("zoom-wide", K, np.zeros(5), {"fx": 90.0, "fy": 90.0,
    ...                         "cx": 4.0, "cy": 140.0}, 1.2, np.zeros(20),
    ...                         np.zeros((20, 3)), np.zeros((20, 3)), info={"converged": True})
    >>> st = step_status(res, (1280, 720), aspect=(1.0, 0.001))
    >>> st.status
    'unusable'
    >>> for reason in st.reasons:
    ...     print(reason)
    principal point (650, -660) outside the 1280x720 image
    aspect ratio fy/fx 1.167 where the sensor's is 1.000
    sd cy 140.0 px > 1 % of the image diagonal
    """
    status = StepStatus()
    w, h = image_size
    fx, fy, cx, cy = res.fx, res.fy, res.cx, res.cy
    if not (fx > 0 and fy > 0 and np.isfinite(fx) and np.isfinite(fy)):
        status.add("unusable", f"focal length ({fx:.1f}, {fy:.1f}) px is not a camera's",
                   "focal")
        return status
    if not (0.0 <= cx <= w - 1 and 0.0 <= cy <= h - 1):
        status.add("unusable", f"principal point ({cx:.0f}, {cy:.0f}) outside the "
                   f"{w}x{h} image", "pp_outside")
    sd = {q: res.sd.get(q, np.nan) for q in ("fx", "fy", "cx", "cy")}
    for q, extent in (("cx", w), ("cy", h)):
        if not np.isfinite(sd[q]):
            status.add("unusable", f"sd {q} not known: the fit gave no finite sigma", "pp_sd")
        elif sd[q] > extent / 4.0:
            status.add("unusable", f"sd {q} {sd[q]:.0f} px > a quarter of the image "
                       f"({extent / 4.0:.0f} px): not determined", "pp_sd")
    if aspect is not None:
        ratio = fy / fx
        sd_ratio = ratio * np.hypot(sd["fx"] / fx, sd["fy"] / fy)
        sd_diff = np.hypot(sd_ratio, aspect[1]) if np.isfinite(sd_ratio) else 0.0
        off = ratio - aspect[0]
        if abs(off) > max(ASPECT_TOLERANCE * aspect[0], 3.0 * sd_diff):
            status.add("unusable", f"aspect ratio fy/fx {ratio:.3f} where the sensor's is "
                       f"{aspect[0]:.3f}", "aspect")
    corner = _corner_radius(res, image_size)
    r_fold, rd_fold = distortion_fold_radius(res.dist)
    if rd_fold < corner:
        status.add("unusable", f"radial distortion folds {rd_fold * fx:.0f} px from the "
                   f"principal point, inside the image (corner {corner * fx:.0f} px)", "fold")
    diagonal = float(np.hypot(w, h))
    for q in ("cx", "cy"):
        if PP_SD_LIMIT * diagonal < sd[q] <= (w if q == "cx" else h) / 4.0:
            status.add("imprecise", f"sd {q} {sd[q]:.1f} px > {100 * PP_SD_LIMIT:.0f} % of "
                       f"the image diagonal", "pp_sd")
    if not np.isfinite(sd["fx"]):
        status.add("imprecise", "sd fx not known: the fit gave no finite sigma", "fx_sd")
    elif sd["fx"] > FX_SD_LIMIT * fx:
        status.add("imprecise", f"sd fx {100 * sd['fx'] / fx:.2f} % > "
                   f"{100 * FX_SD_LIMIT:.0f} %", "fx_sd")
    if not res.converged:
        status.add("imprecise", f"did not converge ({res.info.get('stop_reason', 'unknown')})",
                   "converged")
    bad = {q: z for q, z in (halves_z or {}).items() if not abs(z) <= 3.0}
    if bad:
        status.add("imprecise", "halves disagree (" + ", ".join(
            f"z_{q} {z:+.1f}" for q, z in bad.items()) + ")", "halves")
    if own is not None and own is not res:
        _moved(status, res, own, image_size)
    return status


def _corner_radius(res: CalibrationResult, image_size: tuple[int, int]) -> float:
    """Normalised distorted radius of the image corner farthest from the principal point."""
    w, h = image_size
    dx = max(abs(res.cx), abs(w - 1 - res.cx)) / res.fx
    dy = max(abs(res.cy), abs(h - 1 - res.cy)) / res.fy
    return float(np.hypot(dx, dy))


def _moved(status: StepStatus, res: CalibrationResult, own: CalibrationResult,
           image_size: tuple[int, int]) -> None:
    """Flag a shift beyond :data:`MOVE_LIMIT` own sigmas of a step well determined alone."""
    alone = step_status(own, image_size)
    if alone.status != "ok":
        return
    shifts = []
    for q in ("fx", "cx", "cy"):
        sd = own.sd.get(q, np.nan)
        z = (getattr(res, q) - getattr(own, q)) / sd if sd > 0 else np.nan
        if abs(z) > MOVE_LIMIT:
            shifts.append(f"{q} {getattr(res, q) - getattr(own, q):+.1f} px ({z:+.1f} sd)")
    if not shifts:
        return
    why, key = _why_moved(res, own, [s.split()[0] for s in shifts])
    status.add("imprecise", "the zoom-wide adjustment moved " + ", ".join(shifts)
               + " from the step alone" + why, key)


def _why_moved(res: CalibrationResult, own: CalibrationResult, moved: list[str]
               ) -> tuple[str, str]:
    """What moved a step (:func:`_moved`): where the zoom-wide basin check fitted the step alone
    on the adjustment's board (``info["basin"]["alone"]``), the board's estimated shape when
    that fit lies within :data:`MOVE_LIMIT` of the step's own sigmas of the adjustment for
    every moved parameter, else the other steps (the shared aspect ratio, the smoothness
    prior). Returns the words to add to the reason and the remedy's key."""
    alone = (res.info.get("basin") or {}).get("alone")
    if not alone:
        return "", "moved"
    far = [f"{q} {getattr(res, q) - alone[q]:+.1f} px" for q in moved
           if abs(getattr(res, q) - alone[q]) > MOVE_LIMIT * own.sd[q]]
    if not far:
        return ("; the step alone on the adjustment's board is within 3 sd of it: the board's "
                "estimated shape moved it", "moved_board")
    return (f"; from the step alone on the adjustment's board too ({', '.join(far)}): the "
            "other steps moved it", "moved")
