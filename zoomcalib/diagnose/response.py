"""How each calibration of a zoom table answers the lens's mechanical errors.

The diagnosis's group terms model a decentre or tilt of a group by the chief ray's image shift,
``-S_g(z) d / pitch`` (paraxial): the principal point that a camera model fitted over the whole
field would report. A calibration from a few views of a board also takes part of the same
error's decentring distortion into its principal point (and into ``p1``, ``p2``), by an amount
that depends on its views and on the terms it fits: on ``laikin-10x`` 1.27-1.95 times the
paraxial shift over the zoom range (``benchmarks/decentre_response.py``).

When the diagnosis has each row's calibration (its observations and its solution), it uses that
calibration's own answer instead. For a unit error ``e`` (1 mm of decentre, 1 rad of tilt) of a
group along the lens's x or y axis, the exact tracer gives the displacement of every observed
point's image, ``delta_e = P_e(x_n) - P_0(x_n)`` (``x_n`` the point's scene direction in the
calibration's solution, ``P`` the chief-ray projection at the row's lens state and pixel pitch,
central differences), and the calibration's linearised fit turns it into

    G(z) = d(cx, cy, p1, p2) / d(e_x, e_y)        (4, 2): px per mm (or rad), then 1 per mm

(:func:`zoomcalib.calibrate.opencv_backend.displacement_response`). A term's principal-point
columns are then ``G[:2] R(m phi)``, its distortion rows ``G[2:] R(m phi)``, in place of
``-S_g / pitch R(m phi)`` and the camera fits' distortion Jacobians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calibrate.opencv_backend import displacement_response, solution_points
from ..calibrate.result import CalibrationResult, Observations
from ..camera import Sensor
from ..optics.cam import solve_gaps
from ..optics.lens_camera import exact_projection
from ..optics.misalignment import Misalignment
from ..optics.prescription import Prescription

__all__ = ["RowCalibration", "traced_displacement", "calibration_response", "opposite_errors",
           "ERROR_STEP"]

#: central-difference steps of a group's error: decentre (mm) and tilt (rad)
ERROR_STEP = {"decenter": 0.01, "tilt": 2e-4}


@dataclass
class RowCalibration:
    """One row's per-step calibration: the points it used and its solution."""

    result: CalibrationResult
    observations: Observations

    def views(self) -> list[np.ndarray]:
        """Per view, the target points it saw ``(k, 3)``, in the order the result has them."""
        pts = np.asarray(self.observations.object_points, float)
        return [pts[ids] for ids, _ in self.observations.views]


def traced_displacement(lens: Prescription, z: float, xn: np.ndarray, sensor: Sensor,
                        group: str, kind: str) -> np.ndarray:
    """(2, M, 2) displacement of the images of scene directions ``xn`` (M, 2) per unit error
    (mm of decentre, rad of tilt) of ``group`` along the lens's x, then y axis, px, from the
    exact tracer by central differences."""
    thickness = lens.thickness_at(solve_gaps(lens, [z]))[0]
    step = ERROR_STEP[kind]
    out = []
    for axis in np.eye(2):
        plus, minus = opposite_errors(lens, group, kind, step * axis)
        out.append((exact_projection(lens, thickness, xn, plus, sensor)
                    - exact_projection(lens, thickness, xn, minus, sensor)) / (2 * step))
    return np.array(out)


def opposite_errors(lens: Prescription, group: str, kind: str, error: np.ndarray
                    ) -> tuple[Misalignment, Misalignment]:
    """The misalignments ``+error`` and ``-error`` ((2,) mm of decentre or rad of tilt, by
    ``kind``) of ``group`` alone, for central differences."""
    names = list(lens.group_names)
    if group not in names:
        raise ValueError(f"lens {lens.name!r} has no group {group!r}")
    moved = np.zeros((len(names), 2))
    moved[names.index(group)] = error
    zero = np.zeros_like(moved)
    return tuple((Misalignment(m, zero) if kind == "decenter" else Misalignment(zero, m))
                 for m in (moved, -moved))


def calibration_response(lens: Prescription, z: float, pitch_mm: float,
                         row: RowCalibration, group: str, kind: str) -> np.ndarray | None:
    """``G`` (4, 2): the change of the row's calibrated (cx, cy) (px) and (p1, p2) per unit
    error of ``group`` along x, y (module docstring); None when the calibration's normal
    matrix is singular."""
    res = row.result
    obj = row.views()
    _, xn = solution_points(obj, res.K, res.dist, res.rvecs, res.tvecs)
    sizes = np.cumsum([0] + [len(v) for v in xn])
    w, h = (int(v) for v in row.observations.image_size)
    moved = traced_displacement(lens, z, np.concatenate(xn), Sensor(w, h, pitch_mm), group,
                                kind)
    fields = [[moved[a, sizes[i]:sizes[i + 1]] for i in range(len(xn))] for a in range(2)]
    resp = displacement_response(obj, res.K, res.dist, res.rvecs, res.tvecs,
                                 int(res.info.get("flags", 0)), len(res.dist), fields)
    return None if resp is None else resp[:, [2, 3, 6, 7]].T
