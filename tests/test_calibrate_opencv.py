"""OpenCV calibration backend and the calibration files, checked against OpenCV's own published
results on its sample images (tests/data/opencv-samples, 13 views, 9x6 corners, 25 mm squares).

Reference 1 is ``left_intrinsics.yml``, the output of OpenCV's ``samples/cpp/calibration.cpp``
(findChessboardCorners, cornerSubPix with an 11x11 ``winSize``, CALIB_FIX_ASPECT_RATIO); reference 2
is OpenCV's Python unit test ``test_calibration.py`` (cornerSubPix ``winSize`` 5x5, flags 0). The
references were made by older OpenCV versions whose detection differs slightly, so they are matched
to within a fraction of their own 1-sigma (0.44 px for fx), not exactly.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from zoomcalib.calibrate.checks import conditioning_flags
from zoomcalib.calibrate.io import read_calibration, write_calibration, yaml_prefix
from zoomcalib.calibrate.opencv_backend import (
    CRITERIA,
    START_CRITERIA,
    STATIONARY_SIGMA,
    _camera_covariance,
    _normal_matrix_at_solution,
    _stationarity,
    calibrate_opencv,
    calibrate_opencv_camera,
    calibrate_opencv_ro,
    calibrate_opencv_robust,
    default_fixed_point,
    not_a_camera,
    observations_from_detections,
)
from zoomcalib.calibrate.result import Observations
from zoomcalib.detect.opencv import Detection, detect_folder
from zoomcalib.targets import parse_pattern

DATA = Path(__file__).parent / "data" / "opencv-samples"
SPEC = "chessboard:9x6:25"

# Reference 1: left_intrinsics.yml (OpenCV's calibration sample output).
REF1_F, REF1_C, REF1_RMS = 535.91573396163199, (342.28315473308373, 235.57082909788173), 0.39259
REF1_DIST = [-0.26637260909660682, -0.038588898922304653, 1.7831947042852964e-03,
             -2.8122100441115472e-04, 0.23839153080878486]
# Reference 2: OpenCV's modules/python/test/test_calibration.py.
REF2_RMS = 0.196335
REF2_K = (532.8099, 532.9335, 342.4952, 233.8879)  # fx, fy, cx, cy
REF2_DIST = [-0.2813256, 0.0291130, 0.0012123, -0.00014083, 0.1548658]


def _images() -> list[Path]:
    files = sorted(DATA.glob("left*.jpg"))
    assert len(files) == 13, "tests/data/opencv-samples should hold left01..left14 (no left10)"
    return files


def _opencv_sample_detections(win: int, criteria, cb_flags: int) -> list[Detection]:
    """Corners found as OpenCV's reference programs find them (not zoomcalib's detector)."""
    out = []
    for f in _images():
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, corners = cv2.findChessboardCorners(img, (9, 6), flags=cb_flags)
        assert ok, f.name
        corners = cv2.cornerSubPix(img, corners, (win, win), (-1, -1), criteria)
        # OpenCV's own labelling (either end of the board): fine for calibration, as every view
        # is a rigid pose of the same flat grid.
        out.append(Detection(f.name, corners.reshape(-1, 2), np.arange(54), None, "classic",
                             (img.shape[1], img.shape[0])))
    return out


def _mapping_difference(K1, d1, K2, d2, pts: np.ndarray) -> np.ndarray:
    """(n,) px: where camera 2 puts the rays that camera 1 sees at ``pts``."""
    rays = cv2.undistortPoints(pts.reshape(-1, 1, 2).astype(np.float64), np.asarray(K1, float),
                               np.asarray(d1, float)).reshape(-1, 2)
    proj, _ = cv2.projectPoints(np.c_[rays, np.ones(len(rays))], np.zeros(3), np.zeros(3),
                                np.asarray(K2, float), np.asarray(d2, float))
    return np.linalg.norm(proj.reshape(-1, 2) - pts, axis=1)


@pytest.fixture(scope="module")
def ref1_obs() -> Observations:
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-4)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK | cv2.CALIB_CB_NORMALIZE_IMAGE
    return observations_from_detections(_opencv_sample_detections(11, crit, flags), SPEC)


@pytest.fixture(scope="module")
def ref2_obs() -> Observations:
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    return observations_from_detections(_opencv_sample_detections(5, crit, flags), SPEC)


@pytest.fixture(scope="module")
def zc_obs() -> Observations:
    """zoomcalib's own detector (classic, cornerSubPix half-window 5 = 11x11 pixels)."""
    dets = detect_folder(DATA, SPEC, method="classic", win=5)
    return observations_from_detections(dets, SPEC)


@pytest.fixture(scope="module")
def zc_result(zc_obs) -> object:
    return calibrate_opencv(zc_obs)


# ----------------------------------------------------------------------------------------------
# references


def test_reference1_opencv_sample_fix_aspect(ref1_obs):
    # Measured (OpenCV 5.0): f 536.109, c (342.374, 235.595), rms 0.4088 px; the reference has
    # f 535.916, c (342.283, 235.571), rms 0.3926. The gap is the reference's older detector
    # (left13 alone moves from 0.38 to 0.46 px); 1 px on f and 1.5 px on c are about 2 and 3 of
    # the noise model's 1-sigma (the views' scatter makes the reported cx sigma about 4x that).
    r = calibrate_opencv(ref1_obs, fix_aspect=True)
    assert r.backend == "opencv" and r.fx == pytest.approx(r.fy, abs=1e-9)
    assert abs(r.fx - REF1_F) < 1.0
    assert abs(r.cx - REF1_C[0]) < 1.5 and abs(r.cy - REF1_C[1]) < 1.5
    assert abs(r.rms_px - REF1_RMS) < 0.03
    # Same lens mapping inside the area the board covered (measured max 0.20 px).
    pts = np.concatenate([p for _, p in ref1_obs.views])
    K1 = [[REF1_F, 0, REF1_C[0]], [0, REF1_F, REF1_C[1]], [0, 0, 1]]
    assert _mapping_difference(K1, REF1_DIST, r.K, r.dist, pts).max() < 0.5
    # The tied focal length reports fy's uncertainty.
    assert r.sd["fx"] == pytest.approx(r.sd["fy"]) and r.sd["fy"] > 0
    assert "CALIB_FIX_ASPECT_RATIO" in r.info["flag_names"]
    # left02 is the reference's worst view too (1.18 px there, 1.22 here).
    assert int(np.argmax(r.per_view_rms_px)) == r.info["views"].index("left02.jpg")


def test_reference2_opencv_unit_test(ref2_obs):
    # Measured: rms 0.196235, fx 532.789, fy 532.914, cx 342.481, cy 233.913, i.e. within
    # 0.025 px of the reference (its 1-sigma on fx is 0.44 px). Distortion compared through the
    # mapping, as k3 moves by ~0.004 between OpenCV versions (measured max 0.036 px).
    r = calibrate_opencv(ref2_obs)
    assert abs(r.rms_px - REF2_RMS) < 0.002
    np.testing.assert_allclose([r.fx, r.fy, r.cx, r.cy], REF2_K, atol=0.05)
    pts = np.concatenate([p for _, p in ref2_obs.views])
    K2 = [[REF2_K[0], 0, REF2_K[2]], [0, REF2_K[1], REF2_K[3]], [0, 0, 1]]
    assert _mapping_difference(K2, REF2_DIST, r.K, r.dist, pts).max() < 0.1


def test_zoomcalib_detector_reproduces_reference2(zc_result):
    # zoomcalib's classic detector (same 11x11 window, own criteria and corner ordering).
    # Measured: rms 0.19543, fx 532.827, fy 532.946, cx 342.487, cy 233.856 (max 0.032 px off).
    r = zc_result
    assert abs(r.rms_px - REF2_RMS) < 0.005
    np.testing.assert_allclose([r.fx, r.fy, r.cx, r.cy], REF2_K, atol=0.1)


# ----------------------------------------------------------------------------------------------
# result content


def test_result_fields_match_opencv(zc_obs, zc_result):
    r = zc_result
    assert r.K.shape == (3, 3) and r.dist.shape == (5,)
    assert set(r.sd) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert all(v > 0 for v in r.sd.values())
    assert r.rvecs.shape == (13, 3) and r.tvecs.shape == (13, 3)
    assert r.info["views"] == zc_obs.names and r.info["n_points"] == 13 * 54
    # rms over all points (OpenCV's definition) and per view, recomputed = OpenCV's.
    assert r.rms_px == pytest.approx(r.info["opencv_rms_px"], rel=1e-6)
    np.testing.assert_allclose(r.per_view_rms_px, r.info["opencv_per_view_rms_px"], rtol=1e-5)
    assert r.rms_px == pytest.approx(np.sqrt(np.mean(r.per_view_rms_px**2)), rel=1e-9)
    # Poses are Rt_cam_board: the board is in front of the camera, 25 mm squares.
    assert np.all(r.tvecs[:, 2] > 0)
    assert r.info["sd_rvecs"].shape == (13, 3)


def test_a_camera_only_fit_is_the_same_camera_without_the_checks(zc_obs, zc_result):
    # the held-out folds and the starts use the camera alone: the same solve, the checks
    # that only the reported sigmas and the diagnosis use skipped, and said so
    light = calibrate_opencv(zc_obs, camera_only=True)
    np.testing.assert_array_equal(light.K, zc_result.K)
    np.testing.assert_array_equal(light.dist, zc_result.dist)
    np.testing.assert_array_equal(light.rvecs, zc_result.rvecs)
    assert light.info["camera_only"] and "camera_only" not in zc_result.info
    assert "view_scatter" not in light.info and "keystone_response" not in light.info
    assert zc_result.info["view_scatter"]["applied"]
    # its sigmas are the noise model's, which the full fit keeps beside its scaled ones
    assert light.sd == pytest.approx(zc_result.info["sd_noise_model"], rel=1e-12)


def test_a_fit_without_the_keystone_response_keeps_everything_else(zc_obs, zc_result):
    # the starts and the basins' fits read the camera, its sigmas and the poses, never the
    # response to a keystone that only the per-step table's diagnosis reads
    plain = calibrate_opencv(zc_obs, keystone=False)
    assert "keystone_response" in zc_result.info and "keystone_response" not in plain.info
    np.testing.assert_array_equal(plain.K, zc_result.K)
    np.testing.assert_array_equal(plain.rvecs, zc_result.rvecs)
    assert plain.sd == zc_result.sd
    assert plain.info["view_scatter"] == zc_result.info["view_scatter"]


def test_the_camera_alone_is_the_full_fits_camera(zc_obs, zc_result):
    # the held-out folds need the camera matrix and distortion only: the same solve to the bit,
    # from OpenCV's start and from a guess, with the same refusals
    K, dist = calibrate_opencv_camera(zc_obs)
    np.testing.assert_array_equal(K, zc_result.K)
    np.testing.assert_array_equal(dist, zc_result.dist)
    flags = cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_K3
    guess = {"K_guess": zc_result.K * [[1.02], [1.02], [1.0]], "dist_guess": zc_result.dist}
    full = calibrate_opencv(zc_obs, flags=flags, **guess)
    K, dist = calibrate_opencv_camera(zc_obs, flags, **guess)
    assert dist.shape == (8,) and dist[4] == zc_result.dist[4]  # held at its guess
    np.testing.assert_array_equal(K, full.K)
    np.testing.assert_array_equal(dist, full.dist)
    two = Observations(zc_obs.object_points, zc_obs.views[:2], zc_obs.image_size,
                       zc_obs.names[:2])
    with pytest.raises(ValueError, match="calibrate_opencv_camera: 2 usable views"):
        calibrate_opencv_camera(two)
    assert not_a_camera(zc_result.K, zc_obs.image_size) is None
    assert "outside the image" in not_a_camera(zc_result.K + [[0, 0, 2000], [0, 0, 0], [0, 0, 0]],
                                               zc_obs.image_size)


def test_rational_model_and_schur_bit(zc_obs, zc_result):
    r8 = calibrate_opencv(zc_obs, model="rational")
    assert r8.dist.shape == (8,) and {"k4", "k5", "k6"} <= set(r8.sd)
    assert r8.rms_px < zc_result.rms_px  # nested model: never worse (0.1940 vs 0.1954)
    # Bit 1 << 18 is both DISABLE_SCHUR_COMPLEMENT and TILTED_MODEL in OpenCV 5.0: the backend
    # keeps the sensor untilted, so the Bouguet engine gives the default engine's answer
    # (without the fix, cx moves by 17 px).
    rb = calibrate_opencv(zc_obs, flags=cv2.CALIB_DISABLE_SCHUR_COMPLEMENT)
    assert rb.dist.shape == (5,) and "CALIB_FIX_TAUX_TAUY" in rb.info["flag_names"]
    np.testing.assert_allclose(rb.K, zc_result.K, atol=1e-3)


# ----------------------------------------------------------------------------------------------
# convergence and uncertainties


def test_convergence_is_checked_at_the_solution(zc_obs, zc_result):
    """OpenCV does not say why it stopped; the backend re-evaluates the Gauss-Newton step at the
    solution. The default run is at the minimum; one iteration from OpenCV's initial guess is
    not, and must say so (measured: fx 552.4 against 532.8, rms 1.18 px, a step of 36 sigma
    left; the default run's step is 1e-7 sigma)."""
    assert zc_result.converged and zc_result.info["stop_reason"] == "tolerance"
    assert zc_result.info["convergence_check"]["step_sigma"] < 0.05
    assert zc_result.info["sd_kind"] == "repeatability"
    one = calibrate_opencv(zc_obs, criteria=(cv2.TERM_CRITERIA_COUNT, 1, 0))
    assert not one.converged and one.info["stop_reason"] == "not stationary"
    assert one.info["convergence_check"]["step_sigma"] > 1.0
    assert one.info["convergence_check"]["criteria"]["max_count"] == 1
    assert json.loads(json.dumps(one.to_dict()))["converged"] is False


def test_stationarity_measures_the_distance_to_the_minimum(zc_obs, zc_result):
    """fx moved by 5 of its 1-sigma from OpenCV's minimum, everything else kept: the step back
    is at least 5 sigma long (5 sd / the conditional sigma of fx, which is <= sd)."""
    r = zc_result
    obj = [np.asarray(zc_obs.object_points[ids], np.float32) for ids, _ in zc_obs.views]
    img = [np.asarray(p, np.float32) for _, p in zc_obs.views]
    at_min = _stationarity(obj, img, r.K, r.dist, r.rvecs, r.tvecs, 0, 5)
    K = r.K.copy()
    K[0, 0] += 5 * r.sd["fx"]
    moved = _stationarity(obj, img, K, r.dist, r.rvecs, r.tvecs, 0, 5)
    assert at_min < 0.05 and 4.5 < moved, (at_min, moved)


def test_invalid_opencv_sd_is_flagged_or_replaced(zc_obs, zc_result, monkeypatch):
    """OpenCV's 1-sigmas are square roots of its covariance's diagonal; a NaN (negative
    variance, made so here on purpose) is never passed on silently: a pose's is listed in
    ``info['sd_invalid']`` with a warning, a camera parameter's is replaced by the full inverse
    of the normal matrix and recorded in ``info['sd_check']``, with a conditioning flag."""
    original = cv2.calibrateCameraExtended

    def broken(where):
        def run(*args, **kwargs):
            rms, K, dist, rv, tv, sdi, sde, per_view = original(*args, **kwargs)
            if where == "camera":
                sdi[2] = np.nan
            else:
                sde[6 * 2 + 3] = np.nan                 # third view, tx
            return rms, K, dist, rv, tv, sdi, sde, per_view
        return run

    monkeypatch.setattr(cv2, "calibrateCameraExtended", broken("pose"))
    with pytest.warns(RuntimeWarning, match="no valid 1-sigma"):
        res = calibrate_opencv(zc_obs)
    assert res.info["sd_invalid"] == ["left03.jpg.tx"]
    monkeypatch.setattr(cv2, "calibrateCameraExtended", broken("camera"))
    res = calibrate_opencv(zc_obs)
    check = res.info["sd_check"]
    assert check["reason"] == "truncated" and check["ratio"] == {"cx": None}
    assert np.isnan(check["opencv_sd"]["cx"])
    # well conditioned here: the full inverse is OpenCV's own 1-sigma of the unbroken run
    assert res.sd["cx"] == pytest.approx(zc_result.sd["cx"], rel=1e-3)
    # the poses' sigmas come from the full inverse too: OpenCV's own, where it is sound
    for key in ("sd_rvecs", "sd_tvecs"):
        np.testing.assert_allclose(res.info[key], zc_result.info[key], rtol=0.01)
    assert any("OpenCV's sd cx not a number" in f for f in conditioning_flags(res, (640, 480)))
    json.dumps(res.to_dict())


def test_full_inverse_matches_opencv_where_well_conditioned(zc_obs, zc_result):
    """On OpenCV's sample views (13 views, tilted up to 40 degrees) the scaled full inverse
    (another implementation: our Jacobian, our Schur complement) gives OpenCV's own 1-sigmas,
    and nothing is replaced or flagged."""
    r = zc_result
    obj = [np.asarray(zc_obs.object_points[ids], np.float32) for ids, _ in zc_obs.views]
    img = [np.asarray(p, np.float32) for _, p in zc_obs.views]
    cov, pose_sd, _ = _camera_covariance(_normal_matrix_at_solution(obj, img, r.K, r.dist,
                                                                 r.rvecs, r.tvecs, 0, 5))
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    full = np.sqrt(np.diag(cov))[:9]
    np.testing.assert_allclose(full, [r.info["sd_noise_model"][n] for n in names], rtol=0.01)
    np.testing.assert_allclose(pose_sd, np.hstack([r.info["sd_rvecs"], r.info["sd_tvecs"]]),
                               rtol=0.01)
    assert "sd_check" not in r.info
    assert not any("near-singular" in f for f in conditioning_flags(r, (640, 480)))


def _long_end_draws(draws: int):
    """The observations of one set of 10 views within 3 degrees of fronto-parallel at fx 23000
    px through a 1.5 % pincushion (k1 14.4), exact image points from the renderer's camera
    model, each draw with fresh noise of 0.01 px."""
    from zoomcalib.camera import CameraModel
    from zoomcalib.render.image import camera_mapping, project_points
    from zoomcalib.render.sweep import SWEEP_SENSOR, sweep_poses

    target = parse_pattern("chessboard:22x15:20")
    cam = CameraModel(23000.0, 23000.0, 652.0, 334.0, np.array([14.4, 0, 0, 0, 0]),
                      SWEEP_SENSOR)
    clean = [project_points(target.object_points, camera_mapping(cam), R, t)
             for R, t in sweep_poses(target, cam, 10, 3.0, np.random.default_rng(2))]
    for d in range(draws):
        rng = np.random.default_rng(100 + d)
        views = [(np.arange(len(uv)), uv + rng.normal(0, 0.01, uv.shape)) for uv in clean]
        yield Observations(target.object_points, views, (1280, 720),
                           [f"v{i}" for i in range(10)])


def test_truncated_opencv_sd_at_the_long_end_is_found_and_replaced():
    """At the long end OpenCV's pseudo-inverse drops fx's direction: its 1-sigma is far below
    the scatter over noise draws. The reported one (the full inverse) is of that scatter's size,
    and the step is flagged."""
    results = [calibrate_opencv_robust(obs, fronto_parallel_deg=15.0)
               for obs in _long_end_draws(12)]
    fx = np.array([r.fx for r in results])
    spread = fx.std(ddof=1)
    own = np.median([r.info["sd_check"]["opencv_sd"]["fx"] for r in results])
    reported = np.median([r.sd["fx"] for r in results])
    assert np.all(np.abs(fx / 23000 - 1) < 0.02), fx     # 2 %: 4-5 of fx's sigmas
    assert own < spread / 20, (own, spread)              # measured: 1/1700 of it
    # 12 draws: the sample deviation scatters by 21 % (1 sigma); the linearised sigma of this
    # ill-conditioned step is measured 1.1x below the scatter over 25 draws
    assert 0.5 < spread / reported < 2.0, (spread, reported)
    # the board's distance trades against fx the same way: its sigma is replaced too
    tz = np.array([r.tvecs[0, 2] for r in results])
    tz_sd = np.median([r.info["sd_tvecs"][0][2] for r in results])
    assert 0.5 < tz.std(ddof=1) / tz_sd < 2.0, (tz.std(ddof=1), tz_sd)
    for r in results:
        assert r.info["sd_check"]["reason"] == "truncated" and "fx" in r.info["sd_check"]["ratio"]
        assert any("near-singular normal matrix: OpenCV's sd" in f
                   for f in conditioning_flags(r, (1280, 720)))


def test_observations_skip_failures_and_check_sizes():
    t = parse_pattern(SPEC)
    pts = np.random.default_rng(0).uniform(0, 600, (54, 2))
    dets = [Detection("a.jpg", pts, np.arange(54), None, "sb", (640, 480)),
            Detection("b.jpg", error="b.jpg: no chessboard 9x6 found", image_size=(640, 480)),
            Detection("c.jpg", pts[:3], np.arange(3), None, "sb", (640, 480)),
            Detection("d.jpg", pts[:10], np.arange(10, 20), None, "sb", (640, 480))]
    obs = observations_from_detections(dets, t)
    assert obs.names == ["a.jpg", "d.jpg"] and obs.image_size == (640, 480)
    np.testing.assert_array_equal(obs.views[1][0], np.arange(10, 20))
    dets.append(Detection("e.jpg", pts, np.arange(54), None, "sb", (1280, 960)))
    with pytest.raises(ValueError, match="e.jpg: image size 1280x960"):
        observations_from_detections(dets, t)
    bad = [Detection("f.jpg", pts[:5], [0, 1, 2, 3, 99], None, "sb", (640, 480))]
    with pytest.raises(ValueError, match="f.jpg: point id 99"):
        observations_from_detections(bad, t)


def test_clear_errors(zc_obs):
    two = Observations(zc_obs.object_points, zc_obs.views[:2], zc_obs.image_size,
                       zc_obs.names[:2])
    with pytest.raises(ValueError, match="2 usable views; need at least 3"):
        calibrate_opencv(two)
    few = Observations(zc_obs.object_points,
                       zc_obs.views[:3] + [(zc_obs.views[3][0][:3], zc_obs.views[3][1][:3])],
                       zc_obs.image_size, zc_obs.names[:4])
    with pytest.raises(ValueError, match="view left04.jpg has 3 points"):
        calibrate_opencv(few)
    with pytest.raises(ValueError, match="unknown distortion model"):
        calibrate_opencv(zc_obs, model="fisheye")
    with pytest.raises(ValueError, match="THIN_PRISM"):
        calibrate_opencv(zc_obs, flags=cv2.CALIB_THIN_PRISM_MODEL)
    # 4-point views: 3 views x 4 points = 24 equations for 4 + 5 + 18 unknowns.
    tiny = Observations(zc_obs.object_points, [(i[:4], p[:4]) for i, p in zc_obs.views[:3]],
                        zc_obs.image_size, zc_obs.names[:3])
    with pytest.raises(ValueError, match="24 equations for 27 unknowns"):
        calibrate_opencv(tiny)


# ----------------------------------------------------------------------------------------------
# object releasing


def test_calibrate_ro_refines_target(zc_obs, zc_result):
    # Measured: rms 0.1284 px (0.1954 with the nominal board), largest point move 0.47 mm,
    # fx 534.21. Releasing 155 target coordinates lowers the rms; the gauge points stay put.
    r = calibrate_opencv_ro(zc_obs)
    n = len(zc_obs.object_points)
    assert r.backend == "opencv-ro" and r.object_points.shape == (n, 3)
    assert r.object_points_sd.shape == (n, 3)
    i = r.info["i_fixed_point"]
    assert i == default_fixed_point(zc_obs.object_points) == 8  # top-right corner of 9x6
    np.testing.assert_allclose(r.object_points[[0, i]], zc_obs.object_points[[0, i]], atol=1e-6)
    assert r.object_points[-1, 2] == pytest.approx(zc_obs.object_points[-1, 2], abs=1e-6)
    assert 0 < r.info["max_point_shift"] < 1.0  # mm: a printed board, not a warped one
    assert r.rms_px < zc_result.rms_px
    assert r.info["dropped_views"] == [] and len(r.per_view_rms_px) == 13
    assert r.rms_px == pytest.approx(r.info["opencv_rms_px"], rel=1e-5)
    assert r.converged and r.info["convergence_check"]["step_sigma"] < 0.05


def test_calibrate_ro_guess_and_partial_views(zc_obs):
    # A partial view is dropped (RO needs every point in every view); with an intrinsic guess
    # OpenCV 5.0's Schur engine would assert, so the backend switches engine.
    views = list(zc_obs.views)
    views[4] = (views[4][0][:40], views[4][1][:40])
    obs = Observations(zc_obs.object_points, views, zc_obs.image_size, zc_obs.names)
    K0 = np.array([[530.0, 0, 320], [0, 530, 240], [0, 0, 1]])
    r = calibrate_opencv_ro(obs, K_guess=K0)
    assert r.info["dropped_views"] == [zc_obs.names[4]]
    assert "12 of 13" in r.info["full_views_only"] and len(r.per_view_rms_px) == 12
    assert "engine_note" in r.info and r.info["engine"] == "bouguet"
    assert 530 < r.fx < 540 and r.dist.shape == (5,)
    with pytest.raises(ValueError, match="i_fixed_point 53 outside"):
        calibrate_opencv_ro(zc_obs, i_fixed_point=53)


# ----------------------------------------------------------------------------------------------
# calibration.json / calibration.yml


def test_write_calibration_round_trip(tmp_path, zc_obs, zc_result):
    r = dataclasses.replace(zc_result, rejected=[(2, 17)])
    other = calibrate_opencv(zc_obs, fix_aspect=True)
    results = {"zoom 3x": {"opencv": r}, "zoom_3x": {"opencv": other}}
    meta = {"pattern": SPEC, "image_size": [640, 480], "seed": 1}
    jpath, ypath = write_calibration(tmp_path / "out", results, meta)
    assert jpath.name == "calibration.json" and ypath.name == "calibration.yml"

    doc = json.loads(jpath.read_text())
    e = doc["steps"]["zoom 3x"]["opencv"]
    assert {"K", "dist", "sd", "rms_px", "per_view_rms_px", "rejected", "rvecs"} <= set(e)
    back, meta_back = read_calibration(jpath)
    assert meta_back == meta
    b = back["zoom 3x"]["opencv"]
    np.testing.assert_array_equal(b.K, r.K)
    np.testing.assert_array_equal(b.dist, r.dist)
    np.testing.assert_array_equal(b.rvecs, r.rvecs)
    assert b.sd == r.sd and b.rms_px == r.rms_px and b.rejected == [(2, 17)]
    assert b.info["views"] == zc_obs.names

    fs = cv2.FileStorage(str(ypath), cv2.FILE_STORAGE_READ)
    try:
        assert fs.getNode("format").string() == "zoomcalib-calibration"
        entries = fs.getNode("entries")
        prefixes = [entries.at(k).string() for k in range(entries.size())]
        # Both names sanitise to step_zoom_3x_opencv: the second gets a suffix.
        assert prefixes == ["step_zoom_3x_opencv", "step_zoom_3x_opencv_2"]
        p = prefixes[0]
        assert fs.getNode(f"{p}_step").string() == "zoom 3x"
        np.testing.assert_allclose(fs.getNode(f"{p}_K").mat(), r.K, rtol=1e-15)
        np.testing.assert_allclose(fs.getNode(f"{p}_dist").mat().ravel(), r.dist, rtol=1e-15)
        assert fs.getNode(f"{p}_sd").getNode("cx").real() == pytest.approx(r.sd["cx"],
                                                                          rel=1e-15)
        assert fs.getNode(f"{p}_rms_px").real() == pytest.approx(r.rms_px, rel=1e-15)
        np.testing.assert_allclose(fs.getNode(f"{p}_per_view_rms_px").mat().ravel(),
                                   r.per_view_rms_px, rtol=1e-15)
        np.testing.assert_array_equal(fs.getNode(f"{p}_rejected").mat(), [[2, 17]])
        assert fs.getNode(f"{p}_views").at(0).string() == "left01.jpg"
        assert fs.getNode(f"{prefixes[1]}_n_rejected").real() == 0
        assert json.loads(fs.getNode("meta_json").string()) == meta
        assert fs.getNode("camera_matrix").empty()  # only for a flat folder
    finally:
        fs.release()


def test_a_meta_entry_too_long_for_the_yaml_stays_in_the_json_only(tmp_path, zc_result):
    # OpenCV writes a YAML string of at most 4096 characters: a long entry of the run's meta
    # (one not yet listed as JSON-only) is left out of meta_json, named, not a failure
    rng = np.random.default_rng(5)
    meta = {"pattern": SPEC, "long_report": {f"k{i}": rng.normal(size=40).tolist()
                                             for i in range(20)}}
    jpath, ypath = write_calibration(tmp_path, {"a": {"opencv": zc_result}}, meta)
    assert json.loads(jpath.read_text())["meta"] == meta
    fs = cv2.FileStorage(str(ypath), cv2.FILE_STORAGE_READ)
    try:
        brief = json.loads(fs.getNode("meta_json").string())
    finally:
        fs.release()
    assert brief == {"pattern": SPEC, "in_calibration_json_only": ["long_report"]}


def test_write_calibration_flat_folder_opencv_names(tmp_path, zc_result):
    _, ypath = write_calibration(tmp_path, {".": {"opencv": zc_result}},
                                 {"image_size": [640, 480]})
    fs = cv2.FileStorage(str(ypath), cv2.FILE_STORAGE_READ)
    try:
        assert yaml_prefix(".", "opencv") == "step_root_opencv"
        np.testing.assert_allclose(fs.getNode("step_root_opencv_K").mat(), zc_result.K)
        # OpenCV calibration sample's names, for tools that read those.
        np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), zc_result.K)
        assert fs.getNode("image_width").real() == 640
        assert fs.getNode("distortion_coefficients").mat().shape == (5, 1)
    finally:
        fs.release()


def test_scaled_inverse_survives_units_that_a_pseudo_inverse_does_not():
    """A well-conditioned matrix seen in units 10^14 apart: the scaled inverse is exact, the
    unscaled pseudo-inverse loses it; a singular matrix is reported as not of full rank."""
    from zoomcalib.calibrate.bundleproblem import scaled_inverse

    rng = np.random.default_rng(7)
    X = rng.normal(size=(40, 6))
    B = X.T @ X                                         # condition of order 10
    D = np.geomspace(1e-7, 1e7, 6)
    A = B * np.outer(D, D)
    exact = np.linalg.inv(B) / np.outer(D, D)
    inv, full = scaled_inverse(A)
    assert full
    np.testing.assert_allclose(np.diag(inv), np.diag(exact), rtol=1e-8)
    pinv = np.linalg.pinv(A, hermitian=True)
    assert np.max(np.abs(np.diag(pinv) / np.diag(exact) - 1)) > 0.5
    X[:, 5] = X[:, 0] - 2 * X[:, 1]                  # a column that the others make
    _, full = scaled_inverse((X.T @ X) * np.outer(D, D))
    assert not full


def test_only_a_truncated_pinhole_sigma_flags_the_step(zc_result):
    """A truncated k3 alone (a narrow field's collinear radial terms) is recorded, not flagged;
    a truncated fx is flagged by name, whatever the distortion terms' ratios."""
    res = dataclasses.replace(zc_result, info=dict(zc_result.info))
    sd = dict(res.sd)
    res.info["sd_check"] = {"reason": "truncated", "opencv_sd": sd, "sd": sd,
                            "ratio": {"k3": 1e-4}}
    assert not any("near-singular" in f for f in conditioning_flags(res, (640, 480)))
    res.info["sd_check"]["ratio"] = {"fx": 1e-3, "k3": 1e-5}
    (flag,) = [f for f in conditioning_flags(res, (640, 480)) if "near-singular" in f]
    assert "OpenCV's sd fx" in flag and "1/1000 of" in flag


def test_only_the_pose_sigma_warning_is_silenced_where_poses_are_unused():
    import warnings

    import pytest

    from zoomcalib.calibrate.opencv_backend import _NO_POSE_SIGMA, pose_sigmas_unused

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with pose_sigmas_unused():
            warnings.warn(f"opencv: {_NO_POSE_SIGMA} (negative variance) for 2 parameters",
                          RuntimeWarning, stacklevel=1)
    assert seen == []
    with pytest.warns(RuntimeWarning, match="overflow"), pose_sigmas_unused():
        warnings.warn("overflow in exp", RuntimeWarning, stacklevel=1)


def test_a_start_at_the_looser_stop_is_the_reported_fit_within_its_sigma(zc_obs, zc_result):
    """A fit that only starts another solve stops at ``START_CRITERIA`` (a relative step of
    1e-6 instead of 1e-12). Its camera stays within a tenth of the stationarity threshold
    (``STATIONARY_SIGMA``) of the reported fit's, in the reported sigmas: on the OpenCV sample
    and on the long end's ridge, where OpenCV's own steps are smallest."""
    def apart(a, b) -> float:
        return max(abs(getattr(a, q) - getattr(b, q)) / a.sd[q] for q in ("fx", "cx", "cy"))

    start = calibrate_opencv(zc_obs, criteria=START_CRITERIA)
    assert apart(zc_result, start) < 0.1 * STATIONARY_SIGMA
    assert START_CRITERIA[2] > CRITERIA[2]
    for obs in _long_end_draws(2):
        reported = calibrate_opencv_robust(obs, fronto_parallel_deg=15.0)
        start = calibrate_opencv_robust(obs, fronto_parallel_deg=15.0, criteria=START_CRITERIA)
        assert apart(reported, start) < 0.1 * STATIONARY_SIGMA
