"""Paraxial (y-nu) ray tracing with 3x3 misalignment matrices.

In each meridional plane (x-z and y-z separately, since paraxial optics decouples them) a ray is
the vector ``(y, n u, 1)``: height ``y`` (mm), reduced angle ``n u`` (``u`` the slope dy/dz) and a
constant 1 that carries the misalignment terms. A surface of power ``phi = c (n' - n)``
whose vertex is displaced laterally by ``delta`` and whose axis is tilted by ``t`` refracts as

    n'u' = n u - phi (y - delta) + (n' - n) t

(refraction in the surface's own frame, where the ray height is ``y - delta`` and its slope
``u - t``), and the ray then travels ``thickness`` to the next vertex: ``y <- y + thickness u'``.
As a matrix acting on ``(y, n u, 1)``::

    refraction  [[1, 0, 0], [-phi, 1, phi delta + (n' - n) t], [0, 0, 1]]
    transfer    [[1, thickness / n', 0], [0, 1, 0], [0, 0, 1]]

The linear part (upper-left 2x2) depends only on the zoom state; the misalignment enters only
the third column, so the image shift is exactly linear in the group decentres and tilts.
The tracer below applies these matrices to batches of rays elementwise (no 3x3 products per
state), which keeps it vectorised over zoom states x error draws x rays.

References
----------
W. J. Smith, *Modern Optical Engineering*, 4th ed., ch. 3 (y-nu trace).
A. Gardel, J. L. Lázaro, J. M. Lavest, "Influence of mechanical errors in a zoom camera",
Image Anal. Stereol. 21 (2002): the 3x3 misalignment matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .misalignment import Misalignment, vertex_z
from .prescription import Prescription

__all__ = [
    "ParaxialRays", "trace_paraxial", "system_abcd", "effective_focal_length",
    "surface_matrices", "chief_ray_image", "image_shift_sensitivity",
]


@dataclass
class ParaxialRays:
    """Heights of traced rays at the stop and on the image plane.

    Attributes
    ----------
    y_stop : (..., 2) ndarray
        Ray height (x, y) on the stop surface's vertex plane, mm.
    y_image : (..., 2) ndarray
        Ray height (x, y) on the image plane, mm.
    u_image : (..., 2) ndarray
        Ray slope in image space.
    """

    y_stop: np.ndarray
    y_image: np.ndarray
    u_image: np.ndarray


def trace_paraxial(lens: Prescription, thickness: np.ndarray, y: np.ndarray, u: np.ndarray,
                   misalignment: Misalignment | None = None) -> ParaxialRays:
    """Trace paraxial rays from the first vertex plane to the image plane.

    Parameters
    ----------
    lens : Prescription
    thickness : (..., N) ndarray
        Axial thicknesses of the lens state(s), mm (see :meth:`Prescription.thickness_at`).
    y : (..., 2) ndarray
        Ray heights (x, y) at the plane of the first vertex, mm.
    u : (..., 2) ndarray
        Ray slopes in object space (air).
    misalignment : Misalignment, optional
        Group decentres and tilts; batch shape must broadcast with the rays'.

    Returns
    -------
    ParaxialRays
    """
    z = vertex_z(thickness)
    n_before, n_after = lens.n_before, lens.n_after
    group_of = lens.surface_group_index()
    y = np.asarray(y, dtype=float)
    w = np.asarray(u, dtype=float) * 1.0  # reduced angle n u, n = 1 in object space
    y_stop = None
    for k in range(lens.n_surfaces):
        phi = lens.curvature[k] * (n_after[k] - n_before[k])
        w = w - phi * y
        if misalignment is not None:
            delta, t = misalignment.surface(lens, z, k, group_of)
            w = w + phi * delta + (n_after[k] - n_before[k]) * t
        if k == lens.stop:
            y_stop = y if misalignment is None else y - delta
        y = y + thickness[..., k, None] * w / n_after[k]
    return ParaxialRays(y_stop=y_stop, y_image=y, u_image=w / n_after[-1])


def system_abcd(lens: Prescription, thickness: np.ndarray) -> np.ndarray:
    """The 2x2 paraxial matrix from the first vertex plane to the image plane.

    Returns
    -------
    M : (..., 2, 2) ndarray
        ``(y_image, u_image) = M @ (y_0, u_0)`` (air on both sides).
    """
    shape = np.shape(thickness)[:-1]
    ones, zeros = np.ones(shape + (2,)), np.zeros(shape + (2,))
    a = trace_paraxial(lens, thickness, ones, zeros)
    b = trace_paraxial(lens, thickness, zeros, ones)
    return np.stack([np.stack([a.y_image[..., 0], b.y_image[..., 0]], -1),
                     np.stack([a.u_image[..., 0], b.u_image[..., 0]], -1)], -2)


def effective_focal_length(lens: Prescription, thickness: np.ndarray) -> np.ndarray:
    """(...,) effective focal length, mm: ``-1 / C`` of the system matrix."""
    return -1.0 / system_abcd(lens, thickness)[..., 1, 0]


def surface_matrices(lens: Prescription, thickness: np.ndarray, delta: np.ndarray,
                     tilt: np.ndarray) -> np.ndarray:
    """The 3x3 matrix of every surface (refraction then transfer) in one plane.

    Parameters
    ----------
    thickness : (N,) ndarray
    delta, tilt : (N,) ndarray
        Lateral displacement (mm) and axis tilt (rad) of each surface in this plane.

    Returns
    -------
    M : (N, 3, 3) ndarray
        ``(y, n u, 1)`` after surface k and the gap behind it = ``M[k] @ (y, n u, 1)`` before it.
    """
    n_before, n_after = lens.n_before, lens.n_after
    phi = lens.curvature * (n_after - n_before)
    m = np.zeros((lens.n_surfaces, 3, 3))
    refr = np.broadcast_to(np.eye(3), m.shape).copy()
    refr[:, 1, 0] = -phi
    refr[:, 1, 2] = phi * delta + (n_after - n_before) * tilt
    tran = np.broadcast_to(np.eye(3), m.shape).copy()
    tran[:, 0, 1] = thickness / n_after
    return tran @ refr


def chief_ray_image(lens: Prescription, thickness: np.ndarray,
                    misalignment: Misalignment | None = None,
                    field_slope: np.ndarray | None = None) -> np.ndarray:
    """Paraxial image of a point at infinity: the ray through the centre of the (displaced) stop.

    With ``field_slope = 0`` this is the image of the on-axis object at infinity, i.e. the
    principal point, in lens coordinates on the image plane.

    Parameters
    ----------
    thickness : (..., N) ndarray
    misalignment : Misalignment, optional
    field_slope : (..., 2) ndarray, optional
        Object-space slope of the incoming parallel bundle; default on-axis.

    Returns
    -------
    image : (..., 2) ndarray
        Image position (x, y) on the nominal image plane, mm.
    """
    shape = np.shape(thickness)[:-1]
    if misalignment is not None:
        shape = np.broadcast_shapes(shape, misalignment.batch_shape)
    slope = np.zeros(shape + (2,)) if field_slope is None else np.asarray(field_slope, float)
    # The chief ray is linear in its entrance height h: trace h = 0 (carries the misalignment and
    # field) and the aligned unit-height ray, then pick h so the ray meets the stop centre.
    unit = trace_paraxial(lens, thickness, np.ones(np.shape(thickness)[:-1] + (2,)),
                          np.zeros(np.shape(thickness)[:-1] + (2,)))
    base = trace_paraxial(lens, thickness, np.zeros_like(slope), slope, misalignment)
    h = -base.y_stop / unit.y_stop
    return base.y_image + h * unit.y_image


def exit_pupil_distance(lens: Prescription, thickness: np.ndarray) -> np.ndarray:
    """(...,) distance from the exit pupil to the image plane, mm (positive: the pupil lies in
    front of the image plane): ``y / u`` of a paraxial chief ray (through the stop's centre)
    at the image, ``y`` its height and ``u`` its slope there."""
    shape = np.shape(thickness)[:-1]
    slope = np.zeros(shape + (2,))
    slope[..., 0] = 0.01
    unit = trace_paraxial(lens, thickness, np.ones(shape + (2,)), np.zeros(shape + (2,)))
    base = trace_paraxial(lens, thickness, np.zeros(shape + (2,)), slope)
    h = -base.y_stop[..., 0] / unit.y_stop[..., 0]
    y = base.y_image[..., 0] + h * unit.y_image[..., 0]
    u = base.u_image[..., 0] + h * unit.u_image[..., 0]
    return y / u


def image_shift_sensitivity(lens: Prescription, thickness: np.ndarray,
                            group: str) -> tuple[np.ndarray, np.ndarray]:
    """Principal-point shift per unit decentre and per unit tilt of one group.

    The tilt pivot is the group's first vertex.

    Returns
    -------
    per_decenter : (...,) ndarray
        Image shift / group decentre, mm/mm (same sign convention in x and y).
    per_tilt : (...,) ndarray
        Image shift / group tilt, mm/rad (numerically equal to um/mrad).
    """
    g = lens.group_index(group)
    ng = len(lens.groups)
    unit = np.zeros((ng, 2))
    unit[g] = [1.0, 0.0]
    zero = np.zeros((ng, 2))
    s_d = chief_ray_image(lens, thickness, Misalignment(unit, zero))[..., 0]
    s_t = chief_ray_image(lens, thickness, Misalignment(zero, unit))[..., 0]
    return s_d, s_t
