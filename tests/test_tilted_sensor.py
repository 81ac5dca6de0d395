"""The tilted-sensor mapping against rays cut by a tilted plane in 3-D (written here)."""

import numpy as np

from zoomcalib.camera import Sensor
from zoomcalib.optics.lens_camera import exact_mapping, tilted_sensor
from zoomcalib.optics.prescription import load_prescription


def _cut_by_tilted_plane(p_mm, theta, pupil_mm):
    """Rays from the exit pupil centre (0, 0, -L) through image-plane points (x, y, 0), cut by
    the plane through the origin whose normal is the lens axis turned by ``theta``; returned in
    that plane's own orthonormal axes (mm)."""
    normal = np.array([-theta[0], -theta[1], 1.0])
    normal /= np.linalg.norm(normal)
    ex = np.cross([0.0, 1.0, 0.0], normal)
    ex /= np.linalg.norm(ex)
    ey = np.cross(normal, ex)
    start = np.array([0.0, 0.0, -pupil_mm])
    d = np.column_stack([p_mm, np.zeros(len(p_mm))]) - start
    t = -(start @ normal) / (d @ normal)
    hit = start + t[:, None] * d
    return np.column_stack([hit @ ex, hit @ ey])


def test_keystone_matches_rays_cut_by_the_tilted_sensor(rng):
    lens = load_prescription("laikin-10x")
    sensor = Sensor(640, 480, 0.0129)
    z = float(rng.uniform(0, 1))
    theta = rng.uniform(-2e-3, 2e-3, 2)
    em = exact_mapping(lens, z, None, sensor)
    tm = tilted_sensor(em, lens, z, theta)
    uv = rng.uniform([0, 0], [639, 479], (50, 2))
    xy = em.unproject(uv)
    c = np.array([em.camera.cx, em.camera.cy])
    f = np.array([em.camera.fx, em.camera.fy])
    got = tm.project(xy) - f * theta - c
    want = _cut_by_tilted_plane((em.project(xy) - c) * sensor.pixel_pitch_mm, theta,
                                tm.exit_pupil_mm) / sensor.pixel_pitch_mm
    # the mapping is first order in theta: what is left is ~ |P| theta^2 ~ 1e-3 px at 2 mrad
    np.testing.assert_allclose(got, want, atol=2e-3)
    keystone = np.abs(got - (em.project(xy) - c)).max()
    assert keystone > 10 * np.abs(got - want).max()  # the test sees the keystone itself
    np.testing.assert_allclose(tm.unproject(tm.project(xy)), xy, atol=1e-10)
