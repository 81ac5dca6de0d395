"""End to end: render a zoom sweep through a lens with hidden backlash, calibrate it, diagnose it.

The compensator's backlash puts it +-b/2 along the barrel's tangential direction, the side set by
the direction of the last zoom move (zoomcalib.optics.mechanics). Sweeping in and then out over
the same settings, the calibrated principal points must show it: the diagnosis names
``backlash`` and recovers the compensator's half-backlash vector in the barrel frame.

The images are rendered with an elliptical PSF (the renderer's default shape: minor sd half the
major one, major axis at 30 deg), which the default ``model`` detector, assuming a round Gaussian
blur, does not model.
"""

import numpy as np

from zoomcalib.camera import Sensor
from zoomcalib.diagnose.run import diagnose_input
from zoomcalib.io import read_json
from zoomcalib.optics.mechanics import GroupTolerance, Tolerances
from zoomcalib.optics.prescription import load_prescription
from zoomcalib.render.dataset import render_dataset
from zoomcalib.render.image import Optics

BACKLASH_UM = 100.0
PHASE_DEG = 120.0


def _table_error_scale2(dataset, table) -> float:
    """Mean square of (calibrated - true principal point) / reported sigma over the table."""
    from zoomcalib.calibrate.io import read_zoom_table

    truth = {st["step"]: st["camera"] for st in read_json(dataset)["steps"]}
    z = [(r[q] - truth[r["step"]][q]) / r[f"sd_{q}"] for r in read_zoom_table(table)
         for q in ("cx", "cy")]
    return float(np.mean(np.square(z)))


def test_rendered_backlash_is_diagnosed(tmp_path):
    lens = load_prescription("laikin-10x")
    tol = Tolerances({
        "variator": GroupTolerance(locked_decenter_um=15.0, locked_tilt_arcmin=1.0,
                                   locked_tilt_phase_deg=90.0, play_um=1.0),
        "compensator": GroupTolerance(locked_decenter_um=10.0,
                                      locked_decenter_phase_deg=PHASE_DEG, play_um=1.0,
                                      backlash_um=BACKLASH_UM)}, "test")
    settings = list(np.linspace(0.0, 0.4, 5))  # 15-30 mm, where 10 views pin the centre best
    zoom = settings + settings[::-1]
    direction = ["in"] * 5 + ["out"] * 5
    # a small sensor with the default one's field of view keeps rendering fast
    sensor = Sensor(640, 480, 0.0129)
    render_dataset(lens, tol, tmp_path / "set", zoom, 10, "chessboard:9x6:25", seed=3,
                   sensor=sensor, direction=direction, optics=Optics(psf="elliptical"))
    assert (tmp_path / "set" / "steps.csv").read_text().count(",out,") == 5

    run = diagnose_input(tmp_path / "set", tmp_path / "diag", lens, sensor.pixel_pitch_mm, tol,
                         "chessboard:9x6:25", ("opencv",), workers=1, log=lambda m: None,
                   report=False)
    doc = read_json(tmp_path / "diag" / "diagnosis.json")
    assert doc["cause"] == "backlash", doc["candidates"]
    ext = run.diagnosis.extended
    assert "compensator" in ext.variant
    # truth in the barrel frame: half the backlash along the tangent, phase + 90 deg
    ang = np.deg2rad(PHASE_DEG + 90.0)
    truth = 0.5 * BACKLASH_UM * np.array([np.cos(ang), np.sin(ang)])
    k0 = ext.n_baseline
    d = ext.fit.params[k0:] - truth
    # The table's principal points miss the rendered truth by more than their own sigmas: the
    # standard model against the exact lens (and the model detector makes those sigmas small).
    # Scale the fit's covariance by that factor, measured here against the truth.
    scale2 = _table_error_scale2(tmp_path / "set" / "dataset.json",
                                 tmp_path / "diag" / "calibration" / "zoom_calibration.csv")
    cov = ext.fit.cov[k0:, k0:] * max(scale2, 1.0)
    assert d @ np.linalg.solve(cov, d) < 13.8, (ext.fit.params[k0:], truth, scale2)
    assert doc["gain"]["cv_rms_ratio"] > 1.0
    assert doc["extended"]["chi2_dof"] < doc["baseline"]["chi2_dof"]

    # the table alone, in its calibrate output folder: the same calibrations are read back
    # (calibration.json, detections/), so the same diagnosis
    assert doc["group_columns"].startswith("each row's calibration response")
    messages = []
    again = diagnose_input(tmp_path / "diag" / "calibration" / "zoom_calibration.csv",
                           tmp_path / "diag2", lens, sensor.pixel_pitch_mm, tol,
                           log=messages.append)
    assert read_json(tmp_path / "diag2" / "diagnosis.json")["group_columns"] == \
        doc["group_columns"], messages
    np.testing.assert_allclose(again.diagnosis.extended.fit.params, ext.fit.params,
                               rtol=1e-6, atol=1e-9)

    # the default calibration (the zoom-wide adjustment): its table is diagnosed through the
    # rows of its solve without the smoothness prior, written beside it, and names the same
    import shutil

    from zoomcalib.calibrate.run import calibrate_folder

    # the first run's detections are reused (the cache checks the images and the detector)
    shutil.copytree(tmp_path / "diag" / "calibration" / "detections",
                    tmp_path / "zw" / "detections")
    zw = calibrate_folder(tmp_path / "set", "chessboard:9x6:25", tmp_path / "zw", ("opencv",),
                          workers=1, log=lambda m: None, report=False)
    assert sum(zw.reused.values()) == 100
    messages = []
    diagnose_input(tmp_path / "zw" / "zoom_calibration.csv", tmp_path / "diag3", lens,
                   sensor.pixel_pitch_mm, tol, log=messages.append)
    assert any("zoom_calibration_unsmoothed.csv" in m and "correlation" in m
               for m in messages), messages
    zoom_wide = read_json(tmp_path / "diag3" / "diagnosis.json")
    assert zoom_wide["cause"] == "backlash", zoom_wide["candidates"]
    # weighed with the correlation of those rows' principal points, written beside them
    assert zoom_wide["noise"]["row_correlation"]["used"] is True
    assert 0.0 < zoom_wide["noise"]["row_correlation"]["largest"] < 1.0


def test_rendered_axis_tilt_is_diagnosed(tmp_path):
    """A hidden axis tilt of 0.9-1.0 mrad in a random direction, rendered over the whole zoom
    range (the axis-tilt set of benchmarks/diagnose_rendered.py, seed 12, not one used to
    design it) with the elliptical PSF and the tilted sensor's keystone: named with default
    settings.

    Each calibration takes most of the keystone into its poses, which leaves the tilt a faint
    trace in the principal points (``fx theta (1 - (f / L) A)``) and a clear one in the
    tangential distortion; the diagnosis reads both with the table's keystone response
    (docs/diagnose.md, "The diagnosis with the keystone"). The default calibration's table (the
    zoom-wide adjustment's) is diagnosed alike."""
    rng = np.random.default_rng(20261124)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    truth = rng.uniform(0.9, 1.0) * np.array([np.cos(angle), np.sin(angle)])
    lens = load_prescription("laikin-10x")
    tol = Tolerances({
        "variator": GroupTolerance(locked_decenter_um=15.0, locked_tilt_arcmin=1.0,
                                   locked_tilt_phase_deg=90.0, play_um=1.0),
        "compensator": GroupTolerance(locked_decenter_um=10.0,
                                      locked_decenter_phase_deg=PHASE_DEG, play_um=1.0)},
        "test")
    settings = list(np.random.default_rng(12).permutation(np.linspace(0.0, 1.0, 8)))
    sensor = Sensor(640, 480, 0.0129)
    render_dataset(lens, tol, tmp_path / "set", settings, 10, "chessboard:9x6:25", seed=12,
                   sensor=sensor, direction="in", axis_tilt_mrad=tuple(truth),
                   optics=Optics(psf="elliptical"))
    diagnose_input(tmp_path / "set", tmp_path / "diag", lens, sensor.pixel_pitch_mm, tol,
                   "chessboard:9x6:25", ("opencv",), workers=1, log=lambda m: None,
                   report=False)
    doc = read_json(tmp_path / "diag" / "diagnosis.json")
    assert not (tmp_path / "diag" / "calibration" / "report.html").exists()  # report=False
    assert doc["cause"] == "axis_tilt", (doc["candidates"], doc["distortion_evidence"])
    assert [c["cause"] for c in doc["causes"]] == ["axis_tilt"]
    evidence = doc["distortion_evidence"]
    assert evidence["best"] == "axis_tilt" and evidence["margin"] > 10.0, evidence
    joint = evidence["causes"]["axis_tilt"]
    got = np.array([joint["params"]["tilt_x_mrad"], joint["params"]["tilt_y_mrad"]])
    sd = np.array([joint["params_sd"]["tilt_x_mrad"], joint["params_sd"]["tilt_y_mrad"]])
    assert np.all(np.abs(got - truth) < 3.0 * sd), (got, sd, truth)

    # the default calibration (the zoom-wide adjustment) of the same images: its rows carry a
    # keystone response of their own, so its table is diagnosed alike
    import shutil

    from zoomcalib.calibrate.run import calibrate_folder

    shutil.copytree(tmp_path / "diag" / "calibration" / "detections",
                    tmp_path / "zw" / "detections")
    calibrate_folder(tmp_path / "set", "chessboard:9x6:25", tmp_path / "zw", ("opencv",),
                     workers=1, log=lambda m: None, report=False)
    diagnose_input(tmp_path / "zw" / "zoom_calibration.csv", tmp_path / "diag_zw", lens,
                   sensor.pixel_pitch_mm, tol, log=lambda m: None, report=False)
    zoom_wide = read_json(tmp_path / "diag_zw" / "diagnosis.json")
    assert zoom_wide["cause"] == "axis_tilt", (zoom_wide["candidates"],
                                               zoom_wide["distortion_evidence"])
    joint = zoom_wide["distortion_evidence"]["causes"]["axis_tilt"]
    got = np.array([joint["params"]["tilt_x_mrad"], joint["params"]["tilt_y_mrad"]])
    sd = np.array([joint["params_sd"]["tilt_x_mrad"], joint["params_sd"]["tilt_y_mrad"]])
    assert np.all(np.abs(got - truth) < 3.0 * sd), (got, sd, truth)
