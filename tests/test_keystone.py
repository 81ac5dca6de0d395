"""A calibration's response to a tilted sensor's keystone and to a decentred group, and the
diagnosis made with them.

A keystone ``uv -> uv + p (p . kappa)`` (``p`` from the principal point) is to first order a
camera turned by ``f kappa`` with its principal point moved by ``-f^2 kappa``: a pinhole
calibration takes all of it into the poses and the principal point (``A = I``).
:func:`keystone_response` predicts, from the solution alone, how far a calibration with
distortion terms does; the tests compare that with what OpenCV's own fit does with and without
the keystone, and diagnose a table whose points were projected through the exact lens on a
tilted sensor (the renderer's mapping, not the diagnosis's model). Likewise a decentred group:
the calibrated principal point follows it by more than its paraxial image shift, as
:func:`zoomcalib.diagnose.response.calibration_response` predicts.
"""

from __future__ import annotations

import copy
import functools

import cv2
import numpy as np
import pytest

from zoomcalib.calibrate.io import KEYSTONE_COLUMNS, read_zoom_table, write_zoom_table
from zoomcalib.calibrate.opencv_backend import calibrate_opencv, keystone_response
from zoomcalib.calibrate.outputs import table_row
from zoomcalib.calibrate.result import Observations
from zoomcalib.camera import Sensor
from zoomcalib.diagnose.discrepancy import Fitter, diagnose_table, noise_shape
from zoomcalib.diagnose.model import Context, LensResponse, group_term, offset_term
from zoomcalib.diagnose.response import RowCalibration, calibration_response
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.diagnose.tangential import resolve_with_distortion
from zoomcalib.optics.lens_camera import exact_mapping, tilted_sensor
from zoomcalib.optics.mechanics import Tolerances
from zoomcalib.optics.misalignment import Misalignment
from zoomcalib.optics.prescription import load_prescription
from zoomcalib.render.dataset import generate_poses, scaled_target_for_view
from zoomcalib.render.image import project_points
from zoomcalib.targets import parse_pattern

BOARD = parse_pattern("chessboard:9x6:25")
SIZE = (640, 480)


def _views(rng, fx: float, n_views: int = 10):
    """Board points and seeded poses filling a 640x480 image at focal length ``fx``."""
    obj = BOARD.object_points.astype(float)
    obj = obj - obj.mean(axis=0)
    scale = 0.6 * SIZE[1] * 1000.0 / fx / np.ptp(obj[:, 1])
    poses = []
    for _ in range(n_views):
        axis = rng.normal(size=3) * np.array([1.0, 1.0, 0.2])
        rvec = axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(15, 40))
        tvec = np.array([*rng.uniform(-0.1, 0.1, 2) * 1000.0 * SIZE[0] / fx, 1000.0])
        poses.append((rvec, tvec))
    return obj * scale, poses


def _keystoned(points: np.ndarray, centre: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    p = points - centre
    return points + p * (p @ kappa)[:, None]


def _calibrate(obj, poses, K, dist, kappa, flags):
    views = []
    for rvec, tvec in poses:
        uv = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        views.append((np.arange(len(obj)), _keystoned(uv, K[:2, 2], kappa)))
    return calibrate_opencv(Observations(obj, views, SIZE), flags=flags)


@pytest.mark.parametrize("fx, k1, flags", [
    (900.0, 0.0, cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
     | cv2.CALIB_ZERO_TANGENT_DIST),
    (900.0, -0.2, 0),
    (6000.0, 0.3, cv2.CALIB_FIX_K3),
])
def test_keystone_response_predicts_the_calibrated_principal_point(fx, k1, flags):
    rng = np.random.default_rng(int(fx) + 7)
    obj, poses = _views(rng, fx)
    K = np.array([[fx, 0, 321.3], [0, fx, 238.1], [0, 0, 1.0]])
    dist = np.array([k1, 0.0, 0.0, 0.0, 0.0])
    eps = rng.uniform(1.0, 2.0, 2) * rng.choice([-1, 1], 2) * 1e-3  # camera-turn equivalent
    plain = _calibrate(obj, poses, K, dist, np.zeros(2), flags)
    tilted = _calibrate(obj, poses, K, dist, eps / fx, flags)
    moved = np.array([tilted.cx - plain.cx, tilted.cy - plain.cy])
    response = keystone_response([obj] * len(poses), plain.K, plain.dist, plain.rvecs,
                                 plain.tvecs, flags, 5)
    predicted = -fx * response["absorption"] @ eps
    # first order in eps: the neglected terms are ~ fx eps^2 ~ 0.02 px of shifts of 1-12 px
    assert np.allclose(moved, predicted, atol=0.03 + 0.01 * np.abs(predicted).max())
    if flags & cv2.CALIB_ZERO_TANGENT_DIST:  # a pinhole fit takes the keystone whole
        assert np.allclose(response["absorption"], np.eye(2), atol=0.01)
        assert np.allclose(response["tangential"], 0.0)
    else:
        tangential = np.array([tilted.dist[2] - plain.dist[2], tilted.dist[3] - plain.dist[3]])
        assert np.allclose(tangential, response["tangential"] @ eps,
                           atol=0.05 * np.abs(tangential).max() + 1e-7)


def test_keystone_columns_round_trip_through_the_zoom_table(tmp_path):
    rng = np.random.default_rng(3)
    rows = [{"step": f"s{i}", "zoom": float(i), "fx": 1000.0 + i, "fy": 1000.0 + i, "cx": 320.0,
             "cy": 240.0, **dict(zip(KEYSTONE_COLUMNS, rng.normal(size=8), strict=True))}
            for i in range(4)]
    table = ZoomTable.from_rows(read_zoom_table(write_zoom_table(tmp_path / "t.csv", rows)))
    expected = np.array([[r[c] for c in KEYSTONE_COLUMNS] for r in rows]).reshape(4, 4, 2)
    assert np.array_equal(table.keystone, expected)
    rows[2].pop("keystone_p1_y")  # one row without: the table has no keystone response
    table = ZoomTable.from_rows(read_zoom_table(write_zoom_table(tmp_path / "u.csv", rows)))
    assert table.keystone is None


def _tilted_lens_table(theta_mrad: np.ndarray, noise_px: float, seed: int) -> list[dict]:
    """Per-setting OpenCV calibrations of points projected through the exact ``laikin-10x``
    on a sensor tilted by ``theta_mrad`` (keystone included), with Gaussian detection noise."""
    return [dict(r) for r in _tilted_lens_rows(tuple(theta_mrad), noise_px, seed)]


@functools.cache
def _tilted_lens_rows(theta_mrad: tuple[float, float], noise_px: float, seed: int
                      ) -> tuple[dict, ...]:
    theta_mrad = np.asarray(theta_mrad, dtype=float)
    lens = load_prescription("laikin-10x")
    sensor = Sensor(*SIZE, 0.0129)
    still = Misalignment(np.zeros((len(lens.groups), 2)), np.zeros((len(lens.groups), 2)))
    rng = np.random.default_rng(seed)
    rows = []
    for i, z in enumerate(np.linspace(0.0, 1.0, 8)):
        mapping = tilted_sensor(exact_mapping(lens, z, still, sensor), lens, z,
                                1e-3 * theta_mrad)
        target = scaled_target_for_view(BOARD, mapping.camera.fy, sensor, 2000.0, 0.6)
        poses = generate_poses(target, mapping, sensor, 12, 2000.0, rng)
        pts = target.object_points
        views = [(np.arange(len(pts)), project_points(pts, mapping, R, t)
                  + rng.normal(0.0, noise_px, (len(pts), 2))) for R, t in poses]
        res = calibrate_opencv(Observations(pts, views, SIZE), flags=cv2.CALIB_FIX_K3)
        rows.append(table_row(f"z{i}", float(z), {}, res))
    return tuple(rows)


@functools.cache
def _response() -> LensResponse:
    return LensResponse.of(load_prescription("laikin-10x"), 0.0129, n_grid=201)


def _diagnose(rows: list[dict]):
    """The diagnosis as ``diagnose`` makes it: the principal points, then the tangential
    distortion (no mechanical errors in these tables: zero tolerances)."""
    return resolve_with_distortion(*_on_points(rows))


def _on_points(rows: list[dict]):
    """The principal points' diagnosis of ``rows``, the rows and its ``refit``."""
    response = _response()
    table = ZoomTable.from_rows(rows)

    def refit(**changes):
        return diagnose_table(table, response, Tolerances.zero(), **changes)

    return refit(), rows, refit


@functools.cache
def _aligned_on_points():
    return _on_points(_tilted_lens_table(np.zeros(2), 0.02, seed=12))


@functools.cache
def _aligned_diagnosis():
    """The aligned lens's table diagnosed as ``diagnose`` does it (shared: its scores are the
    start of the rule's test)."""
    base, rows, refit = _aligned_on_points()
    return resolve_with_distortion(copy.copy(base), rows, refit)


def test_axis_tilt_with_its_keystone_is_named_by_the_tangential_distortion():
    rng = np.random.default_rng(2024)
    angle = rng.uniform(0, 2 * np.pi)
    theta = rng.uniform(0.9, 1.2) * np.array([np.cos(angle), np.sin(angle)])  # mrad
    rows = _tilted_lens_table(theta, 0.02, seed=11)
    assert ZoomTable.from_rows(rows).keystone is not None
    diag = _diagnose(rows)
    assert "axis_tilt" in {s.cause for s in diag.causes}
    assert diag.distortion["required"] == "axis_tilt"
    joint = diag.distortion["causes"]["axis_tilt"]
    got = np.array([joint["params"]["tilt_x_mrad"], joint["params"]["tilt_y_mrad"]])
    sd = np.array([joint["params_sd"]["tilt_x_mrad"], joint["params_sd"]["tilt_y_mrad"]])
    assert np.all(sd < 0.3), sd  # a tilt of about 1 mrad is measured, not just bounded
    assert np.all(np.abs(got - theta) <= 3 * sd), (got, sd, theta)


def test_no_axis_tilt_is_named_on_an_aligned_lens():
    diag = _aligned_diagnosis()
    assert "axis_tilt" not in {s.cause for s in diag.causes}
    assert diag.distortion is None or diag.distortion["required"] is None


@pytest.mark.parametrize("tilt_bic, decentre_bic, required, ambiguous", [
    (-40.0, -32.0, "axis_tilt", ["static_decenter"]),  # both supported, 8 apart: not told apart
    (-40.0, -28.0, "axis_tilt", []),  # 12 apart: the decentre is behind by the margin
    (-12.0, -5.0, "axis_tilt", []),  # 7 apart, but the decentre does not pay
    (-9.0, 3.0, None, []),  # the tilt not supported
])
def test_a_tilt_the_distortion_puts_in_names_a_decentre_it_cannot_part_from_it(
        monkeypatch, tilt_bic, decentre_bic, required, ambiguous):
    # The rule of the keystone route, on scores set here: the tilt is required where it
    # lowers the BIC of the principal points and p1, p2 by more than BIC_MARGIN and leads the
    # static decentre; a decentre that lowers it by as much too and trails by less than the
    # margin is not told apart, and said so.
    from zoomcalib.diagnose import tangential

    base, rows, refit = _aligned_on_points()
    scored = _aligned_diagnosis().distortion  # the real scores of this table, to be set

    def fixed_scores(diag, p, sd_p, causes=tangential.EVIDENCE_CAUSES):
        ev = copy.deepcopy(scored)
        ev["causes"]["axis_tilt"]["delta_bic"] = tilt_bic
        ev["causes"]["static_decenter"]["delta_bic"] = decentre_bic
        ev["best"] = "axis_tilt"
        ev["pair_delta_bic"] = tilt_bic - 20.0  # both together pay: neither is dropped for it
        return ev

    monkeypatch.setattr(tangential, "distortion_evidence", fixed_scores)
    diag = resolve_with_distortion(copy.copy(base), rows, refit)
    assert diag.distortion["required"] == required
    assert diag.distortion["margin"] == pytest.approx(decentre_bic - tilt_bic)
    assert ("axis_tilt" in {s.cause for s in diag.causes}) == (required is not None)
    assert diag.ambiguous_with == ambiguous
    assert diag.distortion["ambiguous"] == (ambiguous[0] if ambiguous else None)
    doc = diag.to_dict()
    assert doc["ambiguous_with"] == ambiguous
    if ambiguous:
        from zoomcalib.diagnose.report import report_markdown

        assert ("Not told apart from: static_decenter (static_decenter: within 10 of the tilt "
                "on the principal points and p1, p2)") in report_markdown(diag, doc)


def _decentred_lens_table(decenter_um: np.ndarray, noise_px: float, seed: int):
    """Per-setting OpenCV calibrations (rows and the calibrations themselves) of points
    projected through the exact ``laikin-10x`` with its variator statically decentred."""
    lens = load_prescription("laikin-10x")
    sensor = Sensor(*SIZE, 0.0129)
    names = list(lens.group_names)
    offset = np.zeros((len(names), 2))
    offset[names.index("variator")] = 1e-3 * decenter_um
    moved = Misalignment(offset, np.zeros_like(offset))
    rng = np.random.default_rng(seed)
    rows, cals = [], []
    for i, z in enumerate(np.linspace(0.0, 0.86, 7)):
        mapping = exact_mapping(lens, z, moved, sensor)
        target = scaled_target_for_view(BOARD, mapping.camera.fy, sensor, 2000.0, 0.6)
        poses = generate_poses(target, mapping, sensor, 10, 2000.0, rng)
        pts = target.object_points
        obs = Observations(pts, [(np.arange(len(pts)), project_points(pts, mapping, R, t)
                                  + rng.normal(0.0, noise_px, (len(pts), 2)))
                                 for R, t in poses], SIZE)
        res = calibrate_opencv(obs, flags=cv2.CALIB_FIX_K3)
        rows.append(table_row(f"z{i}", float(z), {}, res))
        cals.append(RowCalibration(res, obs))
    return rows, cals


def test_a_decentre_is_recovered_at_its_size_through_the_calibrations_response():
    """The calibrated principal points follow a decentred group by 1.3-1.9 times its paraxial
    image shift (they take part of its decentring distortion too): fitted with the paraxial
    shift the decentre comes out too large; with each calibration's own response, right."""
    rng = np.random.default_rng(77)
    angle = rng.uniform(0, 2 * np.pi)
    hidden = rng.uniform(250.0, 350.0) * np.array([np.cos(angle), np.sin(angle)])  # um
    rows, cals = _decentred_lens_table(hidden, 0.02, seed=5)
    fits = {}
    for label, calibrations in (("response", cals), ("paraxial", None)):
        table = ZoomTable.from_rows(rows)
        table.calibrations = calibrations
        ctx = Context.build(table, _response().state_of_focal(table.fx), _response())
        fitter = Fitter(ctx, noise_shape(table, np.zeros(table.n)), table.zoom_groups())
        terms = (offset_term(), group_term("variator", "decenter", 0, "static decentre"))
        fits[label] = fitter(terms)
    got, sd = fits["response"].params[2:], fits["response"].sd[2:]
    assert np.all(np.abs(got - hidden) <= 3 * sd), (got, sd, hidden)
    paraxial = fits["paraxial"].params[2:]
    assert np.linalg.norm(paraxial) > 1.2 * np.linalg.norm(hidden), (paraxial, hidden)


@pytest.mark.parametrize("z", [0.1, 0.6])
def test_calibration_response_predicts_a_decentred_groups_principal_point(z):
    """Same views through the aligned and the decentred lens, no noise: the move of the
    calibrated principal point is what the aligned calibration's response predicts, and not
    the paraxial image shift."""
    lens = load_prescription("laikin-10x")
    sensor = Sensor(*SIZE, 0.0129)
    rng = np.random.default_rng(int(100 * z))
    decenter_mm = 1e-3 * rng.uniform(60.0, 120.0) * rng.choice([-1, 1], 2)
    names = list(lens.group_names)
    offset = np.zeros((len(names), 2))
    offset[names.index("variator")] = decenter_mm
    zero = np.zeros_like(offset)
    aligned = exact_mapping(lens, z, Misalignment(zero, zero), sensor)
    moved = exact_mapping(lens, z, Misalignment(offset, zero), sensor)
    target = scaled_target_for_view(BOARD, aligned.camera.fy, sensor, 2000.0, 0.6)
    poses = generate_poses(target, aligned, sensor, 10, 2000.0, rng)
    pts = target.object_points

    def calibrate(mapping):
        obs = Observations(pts, [(np.arange(len(pts)), project_points(pts, mapping, R, t))
                                 for R, t in poses], SIZE)
        return calibrate_opencv(obs), obs

    plain, obs = calibrate(aligned)
    shifted, _ = calibrate(moved)
    actual = np.array([shifted.cx - plain.cx, shifted.cy - plain.cy])
    G = calibration_response(lens, z, 0.0129, RowCalibration(plain, obs), "variator",
                             "decenter")
    predicted = G[:2] @ decenter_mm
    assert np.allclose(actual, predicted, atol=0.02 * np.abs(actual).max() + 0.01)
    s_d, _ = _response().sensitivities(np.array([z]))["variator"]
    paraxial = -s_d[0] * decenter_mm / 0.0129  # what the renderer records as the move
    assert np.linalg.norm(actual) > 1.2 * np.linalg.norm(paraxial)


def test_a_failed_calibration_response_is_said(monkeypatch):
    """Where a calibration's response cannot be had (a singular normal matrix), the group terms
    fall back to the paraxial shift and diagnosis.json says so."""
    import zoomcalib.diagnose.model as model

    rows, cals = _decentred_lens_table(np.array([100.0, -40.0]), 0.02, seed=6)
    table = ZoomTable.from_rows(rows)
    table.calibrations = cals
    monkeypatch.setattr(model, "calibration_response", lambda *args, **kwargs: None)
    doc = diagnose_table(table, _response(), Tolerances.zero()).to_dict()
    assert "paraxial image shift for the decenter of" in doc["group_columns"]
    assert "singular normal matrix" in doc["group_columns"]
    table.calibrations = None
    assert diagnose_table(table, _response(), Tolerances.zero()).to_dict()[
        "group_columns"] == "paraxial image shift"
