import cv2
import numpy as np

from zoomcalib.camera import DEFAULT_SENSOR, CameraModel
from zoomcalib.detect import detect_image
from zoomcalib.detect.dots import dot_centre_bias
from zoomcalib.render.image import Optics, Radiometry, camera_mapping, render_image
from zoomcalib.targets import parse_pattern


def test_dot_centres_at_45_degrees_under_distortion(rng):
    # The reference case: 45 degree tilt, k1 = -0.2. Goal: <= 0.01 px RMS after correction.
    cam = CameraModel(1400.0, 1400.0, 641.3, 478.2, np.array([-0.2, 0, 0, 0, 0]))
    target = parse_pattern("acircles:4x11:20")
    axis = np.array([*rng.normal(size=2), 0.0])
    R = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.deg2rad(45))[0]
    t = np.array([*rng.uniform(-30, 30, 2), 520.0]) - R @ target.object_points.mean(0)
    mapping = camera_mapping(cam)
    view = render_image(target, mapping, R, t, DEFAULT_SENSOR, Optics(blur_px=0.7),
                        Radiometry(noise_sd=2 / 255), rng=int(rng.integers(1000)))
    det = detect_image(view.image, target, "model")
    assert det.error is None and len(det.ids) == 44
    err = det.points - view.points_px[det.ids]
    bias = dot_centre_bias(mapping.project, R, t, target.object_points, target.discs[0, 2])
    pinhole = camera_mapping(CameraModel(cam.fx, cam.fy, cam.cx, cam.cy, np.zeros(5)))
    conic = dot_centre_bias(pinhole.project, R, t, target.object_points, target.discs[0, 2])

    def rms(e):
        return np.sqrt(np.mean(np.sum(e**2, axis=1)))

    assert rms(err) > 0.05  # the ellipse centres are biased ...
    assert rms(err - conic[det.ids]) > 0.01  # ... perspective alone does not explain it ...
    assert rms(err - bias[det.ids]) < 0.01  # ... perspective and distortion together do


def test_calibration_iterates_the_dot_centre_correction(tmp_path):
    import json

    from click.testing import CliRunner

    from zoomcalib.cli import main

    out = tmp_path / "dots"
    res = CliRunner().invoke(main, ["render", "--zoom", "0.0", "--views", "8", "--pattern",
                                    "acircles:4x11:20", "--nominal", "--seed", "5",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    cal = tmp_path / "cal"
    res = CliRunner().invoke(main, ["calibrate", str(out), "--pattern", "acircles:4x11:20",
                                    "--method", "model", "--workers", "1", "--out", str(cal)])
    assert res.exit_code == 0, res.output
    truth = json.loads((out / "dataset.json").read_text())["steps"][0]["camera"]
    doc = json.loads((cal / "calibration.json").read_text())["steps"]["zoom_00"]
    for backend in ("opencv", "bundle"):
        entry = doc[backend]
        assert entry["info"]["dot_centre_correction_max_px"] > 0.02  # the bias was there
        K = np.array(entry["K"])
        for name, value in (("fx", K[0, 0]), ("cx", K[0, 2]), ("cy", K[1, 2])):
            assert abs(value - truth[name]) < 4 * entry["sd"][name], (backend, name)
