"""From a lens state (zoom + misalignment) to an OpenCV camera model.

- ``fx = fy = EFL / pitch`` for the paraxial EFL of the focused lens state;
- the principal point is the image of the on-axis object at infinity: the chief ray with zero
  object-space slope, traced exactly, mapped to pixels;
- the distortion coefficients (and fx, fy, cx, cy with them) are fitted by least squares to the
  exact mapping of a grid of field directions that covers the sensor, so a decentred or tilted
  group shows up as the tangential (decentring) distortion it physically produces. The fit's RMS
  and worst residual are reported: they are the part of the lens that the OpenCV model misses.

Frames: the lens frame has x, y along the camera's x (right) and y (down) and z along the light
(from the scene into the camera). A scene direction with normalised camera coordinates (x, y)
arrives as a parallel bundle of object-space slope (-x, -y) and is imaged, to first order, at
``EFL * (-x, -y)`` on the image plane, which the read-out maps to ``c + EFL/pitch * (x, y)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.optimize import least_squares

from ..camera import DEFAULT_SENSOR, CameraModel, Sensor, distort, invert_projection
from .cam import solve_gaps
from .misalignment import Misalignment
from .paraxial import effective_focal_length, exit_pupil_distance
from .prescription import Prescription
from .raytrace import chief_ray_image_real

__all__ = ["LensCamera", "lens_camera", "exact_projection", "fit_camera_model", "ExactMapping",
           "TiltedSensorMapping", "tilted_sensor",
           "exact_mapping"]


@dataclass
class LensCamera:
    """A lens state's camera model and how well the OpenCV model describes it.

    Attributes
    ----------
    camera : CameraModel
        Fitted fx, fy, cx, cy and distortion (OpenCV order, 5 terms).
    zoom : float
    efl_mm : float
        Paraxial effective focal length of the state.
    principal_point_px : (2,) ndarray
        Exact-traced image of the on-axis object at infinity, px.
    fit_rms_px, fit_max_px : float
        RMS and largest residual of the model fit over the field grid, px.
    """

    camera: CameraModel
    zoom: float
    efl_mm: float
    principal_point_px: np.ndarray
    fit_rms_px: float
    fit_max_px: float


def exact_projection(lens: Prescription, thickness: np.ndarray, xy: np.ndarray,
                     misalignment: Misalignment | None = None,
                     sensor: Sensor = DEFAULT_SENSOR) -> np.ndarray:
    """Pixel position of scene directions, by exact chief-ray tracing.

    Parameters
    ----------
    thickness : (N,) ndarray
        One lens state.
    xy : (M, 2) ndarray
        Normalised camera coordinates (X/Z, Y/Z) of scene directions.
    misalignment : Misalignment, optional
        With an empty batch shape (one lens state).

    Returns
    -------
    uv : (M, 2) ndarray
        Pixels, OpenCV convention.
    """
    image = chief_ray_image_real(lens, thickness, misalignment, slope=-np.asarray(xy, float))
    return sensor.image_plane_to_pixels(image)


def fit_camera_model(xy: np.ndarray, uv: np.ndarray, f0: float, c0: np.ndarray,
                     sensor: Sensor = DEFAULT_SENSOR) -> tuple[CameraModel, np.ndarray]:
    """Least-squares fit of fx, fy, cx, cy, k1, k2, p1, p2, k3 to a point mapping.

    Parameters
    ----------
    xy : (M, 2) ndarray
        Normalised coordinates.
    uv : (M, 2) ndarray
        Their pixel positions.
    f0, c0 : float, (2,) ndarray
        Starting focal length and principal point, px.

    Returns
    -------
    camera : CameraModel
    residual : (M, 2) ndarray
        Model minus data, px.
    """

    def model(q):
        xd = distort(xy, q[4:])
        return np.stack([q[0] * xd[:, 0] + q[2], q[1] * xd[:, 1] + q[3]], -1)

    q0 = np.concatenate([[f0, f0], c0, np.zeros(5)])
    sol = least_squares(lambda q: (model(q) - uv).ravel(), q0, method="lm", xtol=1e-14,
                        ftol=1e-14)
    q = sol.x
    cam = CameraModel(q[0], q[1], q[2], q[3], q[4:].copy(), sensor)
    return cam, model(q) - uv


def lens_camera(lens: Prescription, zoom: float, misalignment: Misalignment | None = None,
                sensor: Sensor = DEFAULT_SENSOR, grid: tuple[int, int] = (21, 16)) -> LensCamera:
    """The OpenCV camera model of one lens state.

    Parameters
    ----------
    lens : Prescription
    zoom : float
        Zoom state in [0, 1].
    misalignment : Misalignment, optional
        Group errors of this state (empty batch shape).
    sensor : Sensor
    grid : (int, int)
        Number of field points across and down the sensor used for the distortion fit.

    Returns
    -------
    LensCamera

    Examples
    --------
    >>> from zoomcalib.optics.prescription import load_prescription
    >>> lc = lens_camera(load_prescription("laikin-10x"), 0.0)
    >>> round(lc.efl_mm, 2), bool(lc.fit_rms_px < 0.05)
    (15.0, True)
    """
    thickness = lens.thickness_at(solve_gaps(lens, [zoom]))[0]
    efl = float(effective_focal_length(lens, thickness))
    f_px = efl / sensor.pixel_pitch_mm
    c0 = sensor.centre_px
    u, v = np.meshgrid(np.linspace(0, sensor.width_px - 1, grid[0]),
                       np.linspace(0, sensor.height_px - 1, grid[1]))
    xy = (np.stack([u.ravel(), v.ravel()], -1) - c0) / f_px  # shape (M, 2)
    uv = exact_projection(lens, thickness, xy, misalignment, sensor)
    pp = exact_projection(lens, thickness, np.zeros((1, 2)), misalignment, sensor)[0]
    cam, res = fit_camera_model(xy, uv, f_px, pp, sensor)
    r = np.linalg.norm(res, axis=-1)
    return LensCamera(camera=cam, zoom=float(zoom), efl_mm=efl, principal_point_px=pp,
                      fit_rms_px=float(np.sqrt(np.mean(r**2))), fit_max_px=float(r.max()))


@dataclass
class ExactMapping:
    """The exact ray-traced mapping of a lens state, as the fitted OpenCV model plus a finely
    interpolated residual field.

    ``project(xy) = camera.project_normalized(xy) + (du, dv)(xy)``, where ``(du, dv)`` is the exact
    minus the model on a regular grid of normalised coordinates, interpolated by bicubic splines.
    The residual is small (the model misfit), so its interpolation error is a small part of it.

    Attributes
    ----------
    camera : CameraModel
    lens_camera : LensCamera
    """

    camera: CameraModel
    lens_camera: LensCamera
    _du: RectBivariateSpline
    _dv: RectBivariateSpline

    def project(self, xy: np.ndarray) -> np.ndarray:
        """(M, 2) normalised coordinates -> (M, 2) pixels through the exact lens."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        uv = self.camera.project_normalized(xy)
        uv[:, 0] += self._du.ev(xy[:, 0], xy[:, 1])
        uv[:, 1] += self._dv.ev(xy[:, 0], xy[:, 1])
        return uv

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """(M, 2) pixels -> (M, 2) normalised coordinates (inverse of :meth:`project`)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return invert_projection(self.project, uv, self.camera.unproject_normalized(uv))


def exact_mapping(lens: Prescription, zoom: float, misalignment: Misalignment | None = None,
                  sensor: Sensor = DEFAULT_SENSOR, grid: tuple[int, int] = (41, 31),
                  margin: float = 0.08) -> ExactMapping:
    """Build the exact mapping of one lens state (see :class:`ExactMapping`).

    Parameters
    ----------
    grid : (int, int)
        Exact-traced nodes across x and y.
    margin : float
        Extra field beyond the sensor, as a fraction of its half-size, so the map covers the
        image with room to spare.
    """
    lc = lens_camera(lens, zoom, misalignment, sensor)
    thickness = lens.thickness_at(solve_gaps(lens, [zoom]))[0]
    half = (np.array([sensor.width_px, sensor.height_px]) / 2) * (1 + margin) / lc.camera.fx
    off = (np.array([lc.camera.cx, lc.camera.cy]) - sensor.centre_px) / lc.camera.fx
    xs = np.linspace(-half[0], half[0], grid[0]) - off[0]
    ys = np.linspace(-half[1], half[1], grid[1]) - off[1]
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], -1)
    res = exact_projection(lens, thickness, xy, misalignment, sensor) - \
        lc.camera.project_normalized(xy)
    du = RectBivariateSpline(xs, ys, res[:, 0].reshape(gx.shape), kx=3, ky=3)
    dv = RectBivariateSpline(xs, ys, res[:, 1].reshape(gx.shape), kx=3, ky=3)
    return ExactMapping(lc.camera, lc, du, dv)


@dataclass
class TiltedSensorMapping:
    """An :class:`ExactMapping` seen on a sensor tilted against the lens axis.

    The lens is turned by ``theta = (theta_x, theta_y)`` (rad, small) about its rear nodal
    point. The axis then meets the sensor ``f theta`` from where it met it, and the sensor,
    tilted by ``theta`` against the lens's image plane, cuts every ray at its distance from
    that plane: a ray from the exit pupil (``L`` mm in front of the image plane) that reached
    ``P`` (mm from the axis) meets the sensor at ``P (1 + theta . P / L)`` (first order in
    ``theta``; the defocus across the sensor is not modelled). In pixels::

        uv = c + (uv_0 - c) (1 + pitch theta . (uv_0 - c) / L) + fx theta

    with ``uv_0`` the untilted image and ``c`` the lens's principal point. ``camera`` is the
    untilted camera moved by ``fx theta``; the keystone is left to the residual. The keystone
    has the form of a camera turned by ``theta f / L`` (``f`` the focal length, mm): a
    calibration can take it into every view's pose and then reports the principal point moved
    by up to ``fx theta (1 - f / L)`` rather than ``fx theta``; how much it takes depends on the
    views. ``keystone=False`` gives the image shift alone.
    """

    base: ExactMapping
    theta: np.ndarray  # shape (2,), rad
    exit_pupil_mm: float
    pixel_pitch_mm: float
    keystone: bool = True

    @property
    def camera(self) -> CameraModel:
        cam = self.base.camera
        return replace(cam, cx=cam.cx + cam.fx * self.theta[0],
                       cy=cam.cy + cam.fy * self.theta[1])

    @property
    def lens_camera(self) -> LensCamera:
        return self.base.lens_camera

    def project(self, xy: np.ndarray) -> np.ndarray:
        """(M, 2) normalised coordinates -> (M, 2) pixels on the tilted sensor."""
        uv0 = self.base.project(xy)
        c = np.array([self.base.camera.cx, self.base.camera.cy])
        p = uv0 - c
        stretch = 1.0 + (self.keystone * self.pixel_pitch_mm * (p @ self.theta)
                         / self.exit_pupil_mm)
        shift = np.array([self.base.camera.fx, self.base.camera.fy]) * self.theta
        return c + p * stretch[:, None] + shift

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """(M, 2) pixels -> (M, 2) normalised coordinates (inverse of :meth:`project`)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return invert_projection(self.project, uv, self.camera.unproject_normalized(uv))


def tilted_sensor(mapping: ExactMapping, lens: Prescription, zoom: float,
                  theta_rad: np.ndarray, keystone: bool = True) -> TiltedSensorMapping:
    """``mapping`` (of ``lens`` at ``zoom``) on a sensor tilted by ``theta_rad`` (2,) against
    the lens axis (:class:`TiltedSensorMapping`)."""
    thickness = lens.thickness_at(solve_gaps(lens, [zoom]))[0]
    return TiltedSensorMapping(mapping, np.asarray(theta_rad, float).reshape(2),
                               float(exit_pupil_distance(lens, thickness)),
                               float(mapping.camera.sensor.pixel_pitch_mm), keystone)
