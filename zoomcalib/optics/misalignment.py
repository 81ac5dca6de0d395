"""Rigid-body misalignment of lens groups: decentre and tilt about a pivot.

A group moved by a decentre ``d = (dx, dy)`` (mm) and a tilt ``t = (tx, ty)`` (rad) about a pivot
on the nominal axis at ``z_p`` has its own optical axis along the unit vector
``a = R @ (0, 0, 1) ~ (tx, ty, 1)`` and every vertex ``k`` of the group at

    o_k = (dx, dy, z_p) + (z_k - z_p) * a

so, to first order, surface ``k`` is decentred laterally by ``d + t * (z_k - z_p)`` and its axis is
tilted by ``t``. The pivot defaults to the group's first vertex (``pivot_offset = 0``).
The rotation is ``R = Ry(tx) @ Rx(-ty)``, which maps +z onto ``(cos ty sin tx, sin ty,
cos ty cos tx)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .prescription import Prescription

__all__ = ["Misalignment", "vertex_z", "rotation_from_tilt"]


def vertex_z(thickness: np.ndarray) -> np.ndarray:
    """Vertex positions along the axis, mm, with the first surface at z = 0.

    Parameters
    ----------
    thickness : (..., N) ndarray

    Returns
    -------
    z : (..., N) ndarray
        ``z[..., k] = sum(thickness[..., :k])``.
    """
    z = np.cumsum(thickness, axis=-1)
    return np.concatenate([np.zeros_like(z[..., :1]), z[..., :-1]], axis=-1)


def rotation_from_tilt(tilt: np.ndarray) -> np.ndarray:
    """Rotation matrices for axis tilts.

    Parameters
    ----------
    tilt : (..., 2) ndarray
        ``(tx, ty)`` in radians: the tilted axis leans towards +x by tx and towards +y by ty.

    Returns
    -------
    R : (..., 3, 3) ndarray
        ``R = Ry(tx) @ Rx(-ty)``; ``R @ v`` maps group coordinates to lens coordinates.
    """
    tx, ty = tilt[..., 0], tilt[..., 1]
    cx, sx, cy, sy = np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty)
    zero = np.zeros_like(tx)
    # Ry(tx) = [[cx,0,sx],[0,1,0],[-sx,0,cx]];  Rx(-ty) = [[1,0,0],[0,cy,sy],[0,-sy,cy]]
    return np.stack([
        np.stack([cx, -sx * sy, sx * cy], axis=-1),
        np.stack([zero, cy, sy], axis=-1),
        np.stack([-sx, -cx * sy, cx * cy], axis=-1),
    ], axis=-2)


@dataclass
class Misalignment:
    """Decentre and tilt of every group of a lens, for a batch of lens states.

    Attributes
    ----------
    decenter : (..., G, 2) ndarray
        Lateral displacement (x, y) of each group, mm.
    tilt : (..., G, 2) ndarray
        Axis tilt (tx, ty) of each group, rad.
    pivot_offset : (G,) ndarray
        Axial position of each group's tilt pivot, mm, measured from its first vertex.
    """

    decenter: np.ndarray
    tilt: np.ndarray
    pivot_offset: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.decenter = np.asarray(self.decenter, dtype=float)
        self.tilt = np.asarray(self.tilt, dtype=float)
        if self.decenter.shape[-1:] != (2,) or self.tilt.shape[-1:] != (2,):
            raise ValueError("decenter and tilt must have shape (..., G, 2)")
        if self.pivot_offset is None:
            self.pivot_offset = np.zeros(self.decenter.shape[-2])

    @classmethod
    def none(cls, lens: Prescription) -> Misalignment:
        """The aligned lens."""
        g = len(lens.groups)
        return cls(np.zeros((g, 2)), np.zeros((g, 2)))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return np.broadcast_shapes(self.decenter.shape[:-2], self.tilt.shape[:-2])

    def group_pivot_z(self, lens: Prescription, z: np.ndarray) -> np.ndarray:
        """(..., G) pivot positions along the axis, mm, given vertex positions ``z (..., N)``."""
        first = np.array([lens.groups[g][0] for g in lens.group_names])
        return z[..., first] + self.pivot_offset

    def surface(self, lens: Prescription, z: np.ndarray, k: int,
                group_of: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First-order lateral displacement and tilt of surface ``k``.

        Parameters
        ----------
        z : (..., N) ndarray
            Nominal vertex positions.
        group_of : (N,) ndarray of int
            ``lens.surface_group_index()``, passed in so loops do not recompute it.

        Returns
        -------
        delta : (..., 2) ndarray
            ``d + t * (z_k - z_p)``, mm.
        tilt : (..., 2) ndarray
            ``t``, rad.
        """
        g = group_of[k]
        z_p = z[..., lens.groups[lens.group_names[g]][0]] + self.pivot_offset[g]
        lever = (z[..., k] - z_p)[..., None]
        t = self.tilt[..., g, :]
        return self.decenter[..., g, :] + t * lever, t

    def scaled(self, factor: float) -> Misalignment:
        return Misalignment(self.decenter * factor, self.tilt * factor, self.pivot_offset)
