import numpy as np
import pytest

from zoomcalib.camera import DEFAULT_SENSOR
from zoomcalib.optics.cam import solve_gaps
from zoomcalib.optics.lens_camera import exact_projection, lens_camera
from zoomcalib.optics.misalignment import Misalignment


def test_aligned_lens_camera(laikin):
    for zoom in (0.0, 0.5, 1.0):
        lc = lens_camera(laikin, zoom)
        cam = lc.camera
        assert cam.fx == pytest.approx(lc.efl_mm / DEFAULT_SENSOR.pixel_pitch_mm, rel=2e-4)
        assert cam.fy == pytest.approx(cam.fx, rel=1e-6)
        np.testing.assert_allclose([cam.cx, cam.cy], DEFAULT_SENSOR.centre_px, atol=1e-6)
        np.testing.assert_allclose(cam.dist[2:4], 0, atol=1e-9)  # no tangential term
        assert lc.fit_rms_px < 0.01


def test_wide_angle_barrel_distortion(laikin):
    # at the short end the corner of the sensor is pulled in (barrel): k1 < 0
    lc = lens_camera(laikin, 0.0)
    assert lc.camera.dist[0] < -0.1


def test_decentred_group_gives_tangential_distortion(laikin, rng):
    zoom = rng.uniform(0.2, 0.8)
    dx = rng.uniform(0.2, 0.5) * rng.choice([-1, 1])  # mm, large so the effect is clear
    dec = np.zeros((4, 2))
    dec[1] = [dx, 0.0]
    lc = lens_camera(laikin, zoom, Misalignment(dec, np.zeros((4, 2))))
    aligned = lens_camera(laikin, zoom)
    # A decentre along x produces p2 (x-direction decentring distortion), not p1.
    assert abs(lc.camera.dist[3]) > 20 * abs(lc.camera.dist[2])
    assert abs(lc.camera.dist[3]) > 1e-4
    # The image centre moves along x only, and the fitted centre follows the chief ray
    shift = lc.principal_point_px - aligned.principal_point_px
    assert abs(shift[0]) > 5 and abs(shift[1]) < 1e-6
    assert lc.camera.cx == pytest.approx(lc.principal_point_px[0], abs=0.5)


def test_fitted_model_predicts_exact_projection(laikin, rng):
    zoom = rng.uniform(0, 1)
    mis = Misalignment(rng.normal(0, 0.02, (4, 2)), rng.normal(0, 3e-4, (4, 2)))
    lc = lens_camera(laikin, zoom, mis)
    thickness = laikin.thickness_at(solve_gaps(laikin, [zoom]))[0]
    # fresh points, not the fit grid
    uv = rng.uniform([0, 0], [DEFAULT_SENSOR.width_px - 1, DEFAULT_SENSOR.height_px - 1], (40, 2))
    xy = (uv - DEFAULT_SENSOR.centre_px) / lc.camera.fx
    exact = exact_projection(laikin, thickness, xy, mis)
    model = lc.camera.project_normalized(xy)
    err = np.linalg.norm(model - exact, axis=1)
    assert err.max() < 2 * lc.fit_max_px + 1e-3
