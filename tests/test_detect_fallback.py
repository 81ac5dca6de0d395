"""Points whose model fit fails are flagged, written, read back and left out of calibration."""

import cv2
import numpy as np

from zoomcalib.calibrate.opencv_backend import observations_from_detections
from zoomcalib.camera import CameraModel, Sensor
from zoomcalib.detect import DEFAULT_METHODS, detect_image, read_detections, write_detections
from zoomcalib.render.image import Optics, Radiometry, camera_mapping, render_image
from zoomcalib.targets import parse_pattern


def _view(rng, target, sensor):
    cam = CameraModel(900.0, 900.0, 322.0, 236.0, np.array([-0.05, 0, 0, 0, 0]), sensor)
    R = cv2.Rodrigues(np.deg2rad(rng.uniform(-15, 15, 3)))[0]
    t = np.array([0.0, 0.0, 520.0]) - R @ target.object_points.mean(axis=0)
    return render_image(target, camera_mapping(cam), R, t, sensor, Optics(blur_px=0.7),
                        Radiometry(), rng=int(rng.integers(1 << 30)))


def test_glare_on_hidden_corners_is_flagged_and_dropped(rng, tmp_path):
    target = parse_pattern("chessboard:9x6:25")
    assert DEFAULT_METHODS["chessboard"] == "model"
    view = _view(rng, target, Sensor(640, 480, 0.005))
    hidden = np.sort(rng.choice(np.arange(10, 44), size=3, replace=False))
    image = view.image.copy()
    for j in hidden:  # a saturated spot of 3 px radius hides the X-junction
        cv2.circle(image, tuple(int(round(v)) for v in view.points_px[j]), 3, 255, -1)
    det = detect_image(image, target)  # the default method
    assert det.ok, det.error
    np.testing.assert_array_equal(np.flatnonzero(det.fallback), hidden)
    # the others are at the truth (noise 2 DN: the bound is ~0.01 px; 0.05 px is 5 sigma)
    good = ~det.fallback
    err = np.linalg.norm(det.points[good] - view.points_px[det.ids[good]], axis=1)
    assert err.max() < 0.05
    # the flags survive the detections file
    path = write_detections(tmp_path / "d.json", [det], target)
    _, (back,) = read_detections(path)
    np.testing.assert_array_equal(back.fallback, det.fallback)
    obs = observations_from_detections([back], target)
    ids, pts = obs.views[0]
    assert obs.n_fallback == len(hidden)
    assert not set(hidden) & set(ids.tolist())
    assert len(ids) == target.n_points - len(hidden)


def test_detections_without_flags_read_as_refined(tmp_path):
    target = parse_pattern("chessboard:3x3:10")
    path = tmp_path / "old.json"
    path.write_text('{"pattern": "chessboard:3x3:10", "images": [\n'
                    '{"file": "a.png", "points": [[1, 2], [3, 4]], "ids": [0, 1], "error": null}\n'
                    ']}\n')
    _, (det,) = read_detections(path)
    assert det.fallback.tolist() == [False, False]
    assert "fallback" not in det.to_dict()
    assert target.n_points == 9
