"""The pinhole + Brown-Conrady camera model, in OpenCV's conventions.

Pixels: the centre of the top-left pixel is (0, 0), x to the right, y down. Camera frame: x right,
y down, z forward (towards the scene). A point ``(X, Y, Z)`` in the camera frame has normalised
coordinates ``x = X / Z, y = Y / Z``; with ``r^2 = x^2 + y^2``,

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
          + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
          + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,   v = fy y_d + cy

with the coefficients in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``. The paper's symbols:
u0 = cx, v0 = cy, f/dx = fx, f/dy = fy, (a1, a2, a3) = (k1, k2, k3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Sensor", "CameraModel", "distort", "invert_projection", "DEFAULT_SENSOR"]


@dataclass(frozen=True)
class Sensor:
    """An image sensor.

    Attributes
    ----------
    width_px, height_px : int
        Image size in pixels.
    pixel_pitch_mm : float
        Pixel pitch (square pixels), mm.
    """

    width_px: int = 1280
    height_px: int = 960
    pixel_pitch_mm: float = 0.00645

    @property
    def centre_px(self) -> np.ndarray:
        """(2,) the geometric centre of the pixel grid, OpenCV convention: ((W-1)/2, (H-1)/2)."""
        return np.array([(self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0])

    def image_plane_to_pixels(self, xy_mm: np.ndarray) -> np.ndarray:
        """Map positions on the image plane (lens frame, mm) to pixels.

        The lens forms an inverted image; the sensor read-out turns it upright, so
        ``u = (W-1)/2 - x / pitch`` and ``v = (H-1)/2 - y / pitch``, with the sensor centred on the
        nominal optical axis.

        Parameters
        ----------
        xy_mm : (..., 2) ndarray
        """
        return self.centre_px - np.asarray(xy_mm) / self.pixel_pitch_mm


DEFAULT_SENSOR = Sensor()


def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV's distortion to normalised coordinates.

    Parameters
    ----------
    xy : (..., 2) ndarray
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.
    dist : (K,) ndarray
        Coefficients in OpenCV order, K in {4, 5, 8}; missing terms are zero.

    Returns
    -------
    xy_d : (..., 2) ndarray

    Examples
    --------
    >>> distort(np.array([0.1, 0.0]), np.array([-0.2, 0, 0, 0, 0]))
    array([0.0998, 0.    ])
    """
    k = np.zeros(8)
    dist = np.ravel(dist)
    k[: len(dist)] = dist
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


#: Points per block of :func:`invert_projection`.
INVERT_BLOCK = 65536


def invert_projection(project, uv: np.ndarray, xy0: np.ndarray, iterations: int = 30,
                      tol_px: float = 1e-9) -> np.ndarray:
    """Solve ``project(xy) = uv`` for normalised coordinates by Newton iteration.

    The Jacobian is taken by central differences, so any smooth mapping works (the OpenCV model,
    or the exact lens mapping).

    Parameters
    ----------
    project : callable
        (M, 2) normalised coordinates -> (M, 2) pixels.
    uv : (M, 2) ndarray
        Pixels.
    xy0 : (M, 2) ndarray
        Starting point (e.g. the pinhole inverse).

    Returns
    -------
    xy : (M, 2) ndarray

    Points are solved in blocks of :data:`INVERT_BLOCK` (each block iterates until its own
    points converge): on millions of points that is about twice as fast as one pass, the
    arrays of a block staying in the processor's cache.
    """
    uv = np.asarray(uv, dtype=float)
    if len(uv) > INVERT_BLOCK:
        pieces = -(-len(uv) // INVERT_BLOCK)
        return np.concatenate([invert_projection(project, u, x, iterations, tol_px)
                               for u, x in zip(np.array_split(uv, pieces),
                                               np.array_split(np.asarray(xy0), pieces),
                                               strict=True)])
    xy = np.array(xy0, dtype=float)
    h = 1e-7
    for _ in range(iterations):
        r = project(xy) - uv
        if np.max(np.abs(r), initial=0.0) < tol_px:
            break
        ju = (project(xy + [h, 0]) - project(xy - [h, 0])) / (2 * h)  # column d uv / d x
        jv = (project(xy + [0, h]) - project(xy - [0, h])) / (2 * h)
        det = ju[:, 0] * jv[:, 1] - jv[:, 0] * ju[:, 1]
        dx = (jv[:, 1] * r[:, 0] - jv[:, 0] * r[:, 1]) / det
        dy = (-ju[:, 1] * r[:, 0] + ju[:, 0] * r[:, 1]) / det
        xy -= np.stack([dx, dy], -1)
    return xy


@dataclass
class CameraModel:
    """Intrinsics of one camera (one zoom state).

    Attributes
    ----------
    fx, fy : float
        Focal lengths, px.
    cx, cy : float
        Principal point, px (OpenCV convention).
    dist : (5,) or (8,) ndarray
        Distortion coefficients, OpenCV order.
    sensor : Sensor
    dist_centre_px : (2,) ndarray
        Where the distortion is centred, relative to the principal point, px (OpenCV's model:
        0). Non-zero, the distortion acts about ``e = dist_centre_px / (fx, fy)`` in normalised
        coordinates: ``x_d = e + distort(x - e)``; the image of the axis stays near ``(cx,
        cy)`` (off by ``-k1 |e|^2 e``).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    sensor: Sensor = DEFAULT_SENSOR
    dist_centre_px: np.ndarray = field(default_factory=lambda: np.zeros(2))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project_normalized(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) normalised undistorted coordinates -> (..., 2) pixels."""
        xy = np.asarray(xy, dtype=float)
        if np.any(self.dist_centre_px):
            e = np.asarray(self.dist_centre_px, float) / [self.fx, self.fy]
            xd = e + distort(xy - e, self.dist)
        else:
            xd = distort(xy, self.dist)
        return np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], -1)

    def unproject_normalized(self, uv: np.ndarray) -> np.ndarray:
        """(M, 2) pixels -> (M, 2) normalised undistorted coordinates (inverse of
        :meth:`project_normalized`)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        xy0 = (uv - [self.cx, self.cy]) / [self.fx, self.fy]
        return invert_projection(self.project_normalized, uv, xy0)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(..., 3) points in the camera frame -> (..., 2) pixels."""
        p = np.asarray(points_cam, dtype=float)
        return self.project_normalized(p[..., :2] / p[..., 2:3])

    def to_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "dist": [float(v) for v in self.dist],
                "dist_centre_px": [float(v) for v in self.dist_centre_px],
                "sensor": {"width_px": self.sensor.width_px, "height_px": self.sensor.height_px,
                           "pixel_pitch_mm": self.sensor.pixel_pitch_mm}}
