"""What a real capture adds to the lens, rendered, detected and found (render-sweep's effects).

The frames are rendered (zoomcalib.render: the board's coverage through a pinhole + distortion
camera, Gaussian PSF with pixel integration, read noise, quantisation), then sharpened by an
unsharp mask and JPEG-compressed as a PTZ camera's stream is; the effects hidden in them are
drawn from the render's seed and stay in truth.json, which only the assertions read. The
corners come from the default detector, the calibration and the residual budget from
``zoomcalib calibrate`` as a user runs it: neither shares the renderer's model.
"""

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from zoomcalib.cli import main
from zoomcalib.render.image import BoardSurface, sharpen_image

PATTERN = "chessboard:11x8:20"
# a PTZ stream's frames: the camera's sharpening, then compression
STREAM = ["--sharpen", "0.8,1.2", "--jpeg-quality", "85", "--size", "960x540",
          "--pattern", PATTERN]


def _render(folder, *options):
    res = CliRunner().invoke(main, ["render-sweep", *STREAM, *options, "--out", str(folder)])
    assert res.exit_code == 0, res.output
    return json.loads((folder / "truth.json").read_text())


def _calibrate(images, out, *options):
    res = CliRunner().invoke(main, ["calibrate", str(images), "--pattern", PATTERN,
                                    "--workers", "1", "--no-report", "--out", str(out),
                                    *options])
    assert res.exit_code == 0, res.output
    return json.loads((out / "calibration.json").read_text()), res.output


def _budget(doc: dict, step: str) -> dict:
    return doc["meta"]["residual_budget"]["steps"][step]


@pytest.fixture(scope="module")
def one_step(tmp_path_factory):
    """One wide step (fx 1500 px, tilts to 40 degrees, 16 views): clean, with a zoom that does
    not return between views, and with a rolling shutter read out while the camera turns."""
    root = tmp_path_factory.mktemp("one_step")
    out = {}
    for name, extra in (("jitter", ["--zoom-jitter", "0.015"]), ("clean", []),
                        ("shutter", ["--rolling-shutter", "3e-4"])):
        truth = _render(root / name, "--fx", "1500,1500", "--steps", "1", "--views", "16",
                        "--seed", "3", *extra)
        doc, _ = _calibrate(root / name, root / f"{name}_out", "--backend", "opencv",
                            "--residual-budget")
        out[name] = (truth, doc)
    return out


def test_sharpening_overshoots_both_sides_of_an_edge():
    edge = np.repeat(np.where(np.arange(40) < 20, 60, 200)[None, :], 5, axis=0).astype(np.uint8)
    sharp = sharpen_image(edge, 0.8, 1.2)[2].astype(int)
    assert sharp.max() > 200 and sharp.min() < 60  # overshoot and undershoot
    assert sharp[0] == 60 and sharp[-1] == 200  # flat far from the edge
    with pytest.raises(ValueError, match="amount"):
        sharpen_image(edge, -1.0, 1.2)


def test_a_rolling_shutter_sees_each_point_from_its_rows_pose(rng):
    # OpenCV's projection of each point turned by the part of the readout its row is read at
    # (iterated to its fixed point) against the renderer's mapping, and the way back
    from zoomcalib.camera import CameraModel
    from zoomcalib.render.image import RollingShutterMapping, camera_mapping

    dist = np.array([-0.2, 0.1, 0.001, -0.002, 0.0])
    cam = CameraModel(1500.0, 1500.0, 640.0, 360.0, dist)
    turn = np.append(rng.normal(0, 3e-3, 2), 0.0)
    mapping = RollingShutterMapping(camera_mapping(cam), turn, 720)
    xy = rng.uniform(-0.3, 0.3, (50, 2))
    uv = mapping.project(xy)
    K = np.array([[1500.0, 0, 640.0], [0, 1500.0, 360.0], [0, 0, 1]])
    P = np.column_stack([xy, np.ones(len(xy))])
    ref = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    for _ in range(10):
        turned = [cv2.Rodrigues(turn * (v / 720 - 0.5))[0] @ p for v, p in zip(ref[:, 1], P,
                                                                                  strict=True)]
        ref = cv2.projectPoints(np.array(turned), np.zeros(3), np.zeros(3), K, dist)[0]
        ref = ref.reshape(-1, 2)
    assert np.abs(uv - ref).max() < 1e-9
    assert np.abs(uv - camera_mapping(cam).project(xy)).max() > 0.5  # the effect is there
    assert np.abs(mapping.unproject(uv) - xy).max() < 1e-12


def test_a_zoom_that_does_not_return_is_found_with_its_size(one_step):
    truth, doc = one_step["jitter"]
    step = truth["steps"][0]["step"]
    scales = np.log([v["focal_scale"] for v in truth["steps"][0]["views"]])
    budget = _budget(doc, step)
    causes = {c["name"]: c for c in budget["causes"]}
    focal = causes["focal"]
    # named, or paying and reported as not told apart from a named per-view cause (a shift
    # growing with the row also takes up a scale's vertical part)
    assert focal["pays"], focal
    assert "focal" in budget["named"] or set(focal["ambiguous_with"]) & set(budget["named"])
    for other in ("lens", "board", "points"):
        assert other not in budget["named"], budget["named"]
    assert abs(focal["size"] - scales.std()) < 3 * focal["size_sd"], (focal, scales.std())


def test_a_rolling_shutter_with_a_turning_camera_is_found_with_its_size(one_step):
    # each view's turn over the readout drawn (sd 3e-4 rad about x and y: about 0.2 px at the
    # top and bottom rows at fx 1500), kept in truth.json; the budget fits a shift linear in
    # the row per view and must name it with the turns' size
    truth, doc = one_step["shutter"]
    st = truth["steps"][0]
    turns = np.array([v["readout_turn"] for v in st["views"]])
    true_px = st["camera"]["fx"] * 0.5 * np.sqrt(np.mean(turns[:, :2] ** 2))
    budget = _budget(doc, st["step"])
    readout = {c["name"]: c for c in budget["causes"]}["readout"]
    assert readout["pays"], readout
    assert "readout" in budget["named"] or set(readout["ambiguous_with"]) & set(budget["named"])
    for other in ("lens", "board", "points"):
        assert other not in budget["named"], budget["named"]
    print(f"\nreadout shift {readout['size']:.3f} +- {readout['size_sd']:.3f} px, true "
          f"{true_px:.3f} px; named {budget['named']}")
    assert abs(readout["size"] - true_px) < 3 * readout["size_sd"], (readout, true_px)


def test_sharpened_compressed_frames_of_a_flat_board_name_nothing(one_step):
    truth, doc = one_step["clean"]
    step = truth["steps"][0]["step"]
    budget = _budget(doc, step)
    assert budget["named"] == [], budget
    # the detector's error on these frames stays at a few hundredths of a pixel
    assert doc["steps"][step]["opencv"]["rms_px"] < 0.05


def test_a_board_retaped_between_sessions_gets_each_shape(tmp_path):
    # three steps of one sweep; the board waves (0.6 mm peak) and is re-taped, another wave,
    # from the second step on: steps.csv's session column says when, the shapes are found
    truth = _render(tmp_path / "img", "--fx", "1500,3000", "--steps", "3", "--views", "8",
                    "--wave", "0.6", "--retape-at", "1", "--seed", "5")
    doc, output = _calibrate(tmp_path / "img", tmp_path / "out")
    assert "session" in output
    surfaces = [BoardSurface.from_dict(b) for b in truth["board_surfaces"]]
    boards, misfit, wave = [], [], []
    for st in truth["steps"]:
        X = np.array(doc["steps"][st["step"]]["zoom-wide"]["object_points"])
        true_z = _off_plane(surfaces[st["board_session"]].height(X[:, 0], X[:, 1]), X)
        boards.append(_off_plane(X[:, 2], X))
        misfit.append(float(np.sqrt(np.mean((boards[-1] - true_z) ** 2))))
        wave.append(float(np.sqrt(np.mean(true_z**2))))
    # each step's board within a fifth of the wave's RMS of its own session's truth (found
    # at 3-7 %: the corners' noise over 8 views a step)
    assert all(m < 0.2 * w for m, w in zip(misfit, wave, strict=True)), (misfit, wave)
    # and the sessions' boards are two: they differ by about the waves' own size
    assert np.sqrt(np.mean((boards[0] - boards[1]) ** 2)) > 0.5 * min(wave)
    assert np.sqrt(np.mean((boards[1] - boards[2]) ** 2)) < 0.2 * min(wave)
    # the zoom table carries each step's session, as steps.csv gave it
    from zoomcalib.calibrate.io import read_zoom_table

    rows = read_zoom_table(tmp_path / "out" / "zoom_calibration.csv")
    assert [r["session"] for r in rows] == [f"board{st['board_session'] + 1}"
                                            for st in truth["steps"]]


def _off_plane(z: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Heights ``z`` (n,) of the board points ``X`` (n, 3) less their least-squares plane in
    ``X``'s x, y: the part of a board's shape that no pose takes up."""
    A = np.column_stack([X[:, 0], X[:, 1], np.ones(len(X))])
    return z - A @ np.linalg.lstsq(A, z, rcond=None)[0]
