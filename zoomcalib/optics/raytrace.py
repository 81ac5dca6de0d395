"""Exact (real) ray tracing through decentred and tilted spherical surfaces.

Every surface is a sphere (or plane) in its own frame: vertex at the origin, axis +z,

    F(p) = c (x^2 + y^2 + z^2) - 2 z = 0,       c = 1 / radius.

A ray ``p + s d`` (``|d| = 1``) meets it where ``c s^2 + 2 b s + C = 0`` with
``b = c (p . d) - d_z`` and ``C = F(p)``; the root on the vertex side is taken in the
cancellation-free form ``s = -C / (b - sqrt(b^2 - c C))`` (valid for rays travelling +z, b < 0).
The unit normal is ``n = (c x, c y, c z - 1) / |.|`` (pointing back towards the incoming light) and
Snell's law in vector form gives the refracted direction

    d' = mu d + (mu cos_i - sqrt(1 - mu^2 (1 - cos_i^2))) n,   mu = n / n',  cos_i = -n . d.

Group misalignments (see :mod:`zoomcalib.optics.misalignment`) place each surface's frame at
``o_k`` rotated by ``R``; rays are taken into the frame (``R^T (p - o_k)``), refracted and taken
back. Rays that miss a surface or are totally reflected come out as NaN.

The chief ray of a field is the ray through the centre of the real (possibly displaced) stop;
:func:`aim_chief_rays` finds its entrance point by Newton iteration with a finite-difference
Jacobian, starting from the paraxial entrance pupil.

Arrays broadcast: rays of shape ``(..., 3)`` against lens states whose thickness is ``(..., N)`` and
whose misalignment has batch shape ``...``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .misalignment import Misalignment, rotation_from_tilt, vertex_z
from .paraxial import trace_paraxial
from .prescription import Prescription

__all__ = ["RealRays", "trace_real", "aim_chief_rays", "chief_ray_image_real",
           "DEFAULT_Z_START"]

DEFAULT_Z_START = -20.0  # mm: rays are launched on this plane, in air before the first vertex


@dataclass
class RealRays:
    """Rays after tracing.

    Attributes
    ----------
    position : (..., 3) ndarray
        Where each ray ends (on the image plane, or on the last surface traced), lens frame, mm.
    direction : (..., 3) ndarray
        Unit direction there.
    stop_xy : (..., 2) ndarray or None
        Ray position in the stop's own frame (relative to the real stop centre), mm.
    """

    position: np.ndarray
    direction: np.ndarray
    stop_xy: np.ndarray | None


def _rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R @ v`` over broadcast batches; R (..., 3, 3), v (..., 3)."""
    if R.ndim == 2:
        return v @ R.T
    return np.matmul(R, v[..., None])[..., 0]


def _rotate_back(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R^T @ v``."""
    if R.ndim == 2:
        return v @ R
    return np.matmul(np.swapaxes(R, -1, -2), v[..., None])[..., 0]


def trace_real(lens: Prescription, thickness: np.ndarray, position: np.ndarray,
               direction: np.ndarray, misalignment: Misalignment | None = None,
               last_surface: int | None = None) -> RealRays:
    """Trace real rays through the lens.

    Parameters
    ----------
    lens : Prescription
    thickness : (..., N) ndarray
        Axial thicknesses of the lens state(s), mm.
    position : (..., 3) ndarray
        Ray start points in the lens frame (object space, before the first surface), mm.
    direction : (..., 3) ndarray
        Unit ray directions (z component > 0).
    misalignment : Misalignment, optional
        Group decentres/tilts with a batch shape that broadcasts with ``position.shape[:-1]``.
    last_surface : int, optional
        Stop after this surface (0-based) instead of going on to the image plane.

    Returns
    -------
    RealRays
    """
    z = vertex_z(thickness)  # shape (..., N)
    z_image = z[..., -1] + thickness[..., -1]
    n_before, n_after = lens.n_before, lens.n_after
    group_of = lens.surface_group_index()
    p = np.asarray(position, dtype=float)
    d = np.asarray(direction, dtype=float)
    rotations = None
    if misalignment is not None:
        rotations = rotation_from_tilt(misalignment.tilt)  # shape (..., G, 3, 3)
        pivots = misalignment.group_pivot_z(lens, z)  # shape (..., G)
    stop_xy = None
    last = lens.n_surfaces - 1 if last_surface is None else last_surface
    for k in range(last + 1):
        if rotations is None:
            origin = np.zeros(np.shape(z[..., k]) + (3,))
            origin[..., 2] = z[..., k]
            pl, dl = p - origin, d
        else:
            g = group_of[k]
            R = rotations[..., g, :, :]
            axis = R[..., :, 2]
            lever = (z[..., k] - pivots[..., g])[..., None]
            origin = axis * lever
            origin[..., :2] += misalignment.decenter[..., g, :]
            origin[..., 2] += pivots[..., g]
            pl, dl = _rotate_back(R, p - origin), _rotate_back(R, d)
        c = lens.curvature[k]
        b = c * np.sum(pl * dl, axis=-1) - dl[..., 2]
        cc = c * np.sum(pl * pl, axis=-1) - 2.0 * pl[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            s = -cc / (b - np.sqrt(b * b - c * cc))  # NaN when the ray misses the sphere
            pl = pl + s[..., None] * dl
            normal = np.stack([c * pl[..., 0], c * pl[..., 1], c * pl[..., 2] - 1.0], axis=-1)
            normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
            mu = n_before[k] / n_after[k]
            cos_i = -np.sum(normal * dl, axis=-1)
            root = np.sqrt(1.0 - mu * mu * (1.0 - cos_i * cos_i))  # NaN on total reflection
            dl = mu * dl + (mu * cos_i - root)[..., None] * normal
        if k == lens.stop:
            stop_xy = pl[..., :2]
        if rotations is None:
            p, d = pl + origin, dl
        else:
            p, d = _rotate(R, pl) + origin, _rotate(R, dl)
    if last_surface is None:
        s = (z_image - p[..., 2]) / d[..., 2]
        p = p + s[..., None] * d
    return RealRays(position=p, direction=d, stop_xy=stop_xy)


def _directions(slope: np.ndarray) -> np.ndarray:
    d = np.concatenate([slope, np.ones(slope.shape[:-1] + (1,))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def aim_chief_rays(lens: Prescription, thickness: np.ndarray, slope: np.ndarray,
                   misalignment: Misalignment | None = None, z_start: float = DEFAULT_Z_START,
                   tol_mm: float = 1e-10, max_iter: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Start points of the rays, one per field, that pass through the real stop centre.

    Parameters
    ----------
    thickness : (..., N) ndarray
    slope : (..., 2) ndarray
        Object-space slopes (dx/dz, dy/dz) of the incoming parallel bundles.
    misalignment : Misalignment, optional
    z_start : float
        Launch plane, mm (lens frame; the first vertex is at z = 0).

    Returns
    -------
    position : (..., 3) ndarray
        Launch points on the plane ``z = z_start``.
    direction : (..., 3) ndarray
        Unit directions.

    Raises
    ------
    RuntimeError
        If the aiming does not converge to ``tol_mm`` for every ray.
    """
    slope = np.asarray(slope, dtype=float)
    shape = np.broadcast_shapes(slope.shape[:-1], np.shape(thickness)[:-1])
    if misalignment is not None:
        shape = np.broadcast_shapes(shape, misalignment.batch_shape)
    slope = np.broadcast_to(slope, shape + (2,))
    d = _directions(slope)
    # Paraxial entrance pupil of the aligned lens as the first guess.
    th0 = np.asarray(thickness)
    ones, zeros = np.ones(th0.shape[:-1] + (2,)), np.zeros(th0.shape[:-1] + (2,))
    a_s = trace_paraxial(lens, th0, ones, zeros).y_stop
    b_s = trace_paraxial(lens, th0, zeros, ones).y_stop
    h0 = -slope * (b_s / a_s)  # height at the first vertex plane
    xy = h0 + slope * z_start  # back along the ray to the launch plane
    xy = np.broadcast_to(xy, shape + (2,)).copy()
    step = 1e-4

    def miss(xy_):
        p = np.concatenate([xy_, np.full(shape + (1,), z_start)], axis=-1)
        return trace_real(lens, thickness, p, d, misalignment, last_surface=lens.stop).stop_xy

    for _ in range(max_iter):
        m = miss(xy)
        if np.nanmax(np.abs(m), initial=0.0) < tol_mm:
            break
        jx = (miss(xy + [step, 0.0]) - m) / step  # shape (..., 2): column d miss / d x
        jy = (miss(xy + [0.0, step]) - m) / step
        det = jx[..., 0] * jy[..., 1] - jy[..., 0] * jx[..., 1]
        dx = (jy[..., 1] * m[..., 0] - jy[..., 0] * m[..., 1]) / det
        dy = (-jx[..., 1] * m[..., 0] + jx[..., 0] * m[..., 1]) / det
        xy = xy - np.stack([dx, dy], axis=-1)
    else:
        m = miss(xy)
        if not np.nanmax(np.abs(m), initial=0.0) < tol_mm:
            raise RuntimeError(f"chief-ray aiming did not converge (worst miss "
                               f"{np.nanmax(np.abs(m)):.2e} mm)")
    p = np.concatenate([xy, np.full(shape + (1,), z_start)], axis=-1)
    return p, d


def chief_ray_image_real(lens: Prescription, thickness: np.ndarray,
                         misalignment: Misalignment | None = None,
                         slope: np.ndarray | None = None) -> np.ndarray:
    """Real-ray image of a point at infinity (default on axis: the principal point).

    Returns
    -------
    image : (..., 2) ndarray
        Where the chief ray meets the nominal image plane, lens frame, mm.
    """
    shape = np.shape(thickness)[:-1]
    if misalignment is not None:
        shape = np.broadcast_shapes(shape, misalignment.batch_shape)
    if slope is None:
        slope = np.zeros(shape + (2,))
    p, d = aim_chief_rays(lens, thickness, slope, misalignment)
    return trace_real(lens, thickness, p, d, misalignment).position[..., :2]
