"""The calibrate job's exports: OpenCV FileStorage, ROS camera_info, mrcal .cameramodel.

The results are made up (seeded) and kept here as the truth; each file is read back with the
other tool's reader (cv2.FileStorage, a YAML parser checked against the CameraInfo message
definition, mrcal's grammar and mrcal's own files) and compared with that truth.
"""

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from zoomcalib.calibrate.export import mrcal_model_text, write_exports
from zoomcalib.calibrate.guards import step_file_stems
from zoomcalib.calibrate.result import DIST_NAMES, CalibrationResult, Observations
from zoomcalib.calibrate.run import CalibrateRun

MRCAL_DATA = Path(__file__).parent / "data" / "mrcal-models"

# sensor_msgs/CameraInfo, as the message definition declares it (ROS 1; ROS 2 spells the
# arrays d, k, r, p): the independent reference for the ROS files' layout.
CAMERA_INFO_MSG = """
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] D
float64[9] K
float64[9] R
float64[12] P
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
"""
# camera_calibration_parsers' YAML names of the calibrated fields (the others, header,
# binning and roi, are filled by the driver)
ROS_YAML_OF_FIELD = {"height": "image_height", "width": "image_width",
                     "distortion_model": "distortion_model", "D": "distortion_coefficients",
                     "K": "camera_matrix", "R": "rectification_matrix", "P": "projection_matrix"}
ROS_MATRIX_SHAPE = {"K": (3, 3), "R": (3, 3), "P": (3, 4)}


def _message_fields(text: str) -> dict[str, tuple[str, int | None]]:
    """name -> (element type, fixed length or None for a variable array / scalar)."""
    fields = {}
    for line in text.strip().splitlines():
        kind, name = line.split()
        m = re.fullmatch(r"(\w+)\[(\d*)\]", kind)
        fields[name] = (m.group(1), int(m.group(2)) if m.group(2) else None) if m else (kind,
                                                                                       None)
    return fields


SIZE = (1920, 1080)
# step -> (zoom, backends and their distortion lengths, table backend, flags)
STEPS = {
    "wide": (1.5, {"opencv": 5, "bundle": 5}, "bundle", []),
    "tele 4x": (4.0, {"opencv": 8}, "opencv", ["principal point outside the central region"]),
    "no zoom": (None, {"opencv": 5}, "opencv", []),
}


def _made_up_result(rng: np.random.Generator, backend: str, n_dist: int) -> CalibrationResult:
    fx = rng.uniform(1000, 5000)
    K = np.array([[fx, 0, rng.uniform(900, 1000)], [0, fx * rng.uniform(0.99, 1.01),
                                                    rng.uniform(500, 580)], [0, 0, 1.0]])
    dist = rng.normal(0, 0.1, n_dist)
    sd = {k: float(rng.uniform(0.01, 2)) for k in ("fx", "fy", "cx", "cy", *DIST_NAMES[:n_dist])}
    m = 7
    return CalibrationResult(backend, K, dist, sd, float(rng.uniform(0.05, 0.5)),
                             rng.uniform(0.05, 0.5, m), np.zeros((m, 3)), np.zeros((m, 3)),
                             info={"converged": bool(rng.integers(2)),
                                   "sd_kind": "repeatability"})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    rng = np.random.default_rng(7)
    run = CalibrateRun(stems=step_file_stems(STEPS))
    for step, (zoom, backends, table, flags) in STEPS.items():
        run.results[step] = {b: _made_up_result(rng, b, n) for b, n in backends.items()}
        run.observations[step] = Observations(np.zeros((1, 3)), [], SIZE)
        run.zoom[step] = zoom
        run.table_backend[step] = table
        if flags:
            run.flags[step] = flags
    out = tmp_path_factory.mktemp("exports")
    files = write_exports(out, run, "zoom_cam", log=lambda m: None)
    return out, run, files


def _stem(run, step):
    return run.stems[step]


def test_opencv_files_read_back_with_filestorage(exported):
    out, run, files = exported
    n_files = 0
    for step, (zoom, backends, _, flags) in STEPS.items():
        for backend in backends:
            res = run.results[step][backend]
            path = out / "opencv" / f"{_stem(run, step)}_{backend}.yml"
            assert path in files
            n_files += 1
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
            assert fs.isOpened()
            try:
                assert (fs.getNode("image_width").real(), fs.getNode("image_height").real()) \
                    == SIZE
                # FileStorage writes 17 significant digits: the numbers come back exactly
                assert np.array_equal(fs.getNode("camera_matrix").mat(), res.K)
                assert np.array_equal(fs.getNode("distortion_coefficients").mat().ravel(),
                                      res.dist)
                assert fs.getNode("avg_reprojection_error").real() == res.rms_px
                assert fs.getNode("nr_of_frames").real() == len(res.per_view_rms_px)
                assert np.array_equal(fs.getNode("per_view_reprojection_errors").mat().ravel(),
                                      res.per_view_rms_px)
                assert fs.getNode("step").string() == step
                assert fs.getNode("backend").string() == backend
                assert fs.getNode("zoom").empty() if zoom is None \
                    else fs.getNode("zoom").real() == zoom
                assert fs.getNode("lens_model").string() == ("rational" if backends[backend] == 8
                                                             else "standard")
                sig = fs.getNode("sigmas")
                assert {k: sig.getNode(k).real() for k in sig.keys()} == res.sd
                assert fs.getNode("converged").real() == int(res.info["converged"])
                node = fs.getNode("quality_flags")
                assert [node.at(i).string() for i in range(node.size())] == flags
            finally:
                fs.release()
    assert n_files == 4


def _ros_files(out):
    index = yaml.safe_load((out / "ros" / "camera_info_index.yaml").read_text())
    return index, {e["step"]: yaml.safe_load((out / "ros" / e["file"]).read_text())
                   for e in index["steps"]}


def test_ros_files_match_the_camera_info_message(exported):
    out, run, _ = exported
    fields = _message_fields(CAMERA_INFO_MSG)
    _, docs = _ros_files(out)
    assert set(docs) == set(STEPS)
    for step, doc in docs.items():
        res = run.results[step][STEPS[step][2]]
        assert set(doc) == {"camera_name", *ROS_YAML_OF_FIELD.values()}
        assert doc["camera_name"] == "zoom_cam"
        msg = {}
        for field, key in ROS_YAML_OF_FIELD.items():
            kind, length = fields[field]
            value = doc[key]
            if kind == "uint32":
                assert isinstance(value, int) and 0 <= value < 2**32, (step, field)
            elif kind == "string":
                assert isinstance(value, str), (step, field)
            else:
                assert kind == "float64"
                rows, cols, data = value["rows"], value["cols"], value["data"]
                assert rows * cols == len(data) and all(isinstance(v, float) for v in data)
                if length is not None:
                    assert len(data) == length and (rows, cols) == ROS_MATRIX_SHAPE[field]
                else:
                    assert rows == 1
                value = np.array(data).reshape(rows, cols)
            msg[field] = value
        assert (msg["width"], msg["height"]) == SIZE
        n = len(res.dist)
        assert msg["distortion_model"] == {5: "plumb_bob", 8: "rational_polynomial"}[n]
        assert np.array_equal(msg["D"].ravel(), res.dist)
        assert np.array_equal(msg["K"], res.K)
        assert np.array_equal(msg["R"], np.eye(3))  # monocular: no rectifying rotation
        assert np.array_equal(msg["P"], np.hstack([res.K, np.zeros((3, 1))]))


def test_ros_index_lists_every_step_by_zoom(exported):
    out, run, files = exported
    index, _ = _ros_files(out)
    assert index["camera_name"] == "zoom_cam"
    # sorted by zoom, the step of unknown zoom last
    assert [(e["step"], e["zoom"]) for e in index["steps"]] == [
        ("wide", 1.5), ("tele 4x", 4.0), ("no zoom", None)]
    for e in index["steps"]:
        assert out / "ros" / e["file"] in files
        # named by the step alone: the index carries its zoom and status
        assert e["file"] == f"{_stem(run, e['step'])}.yaml"
        assert e["status"] in ("ok", "imprecise")


def _parse_cameramodel(text: str) -> dict:
    """mrcal's documented grammar: a Python literal dict, ``#`` starting a comment."""
    body = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    return ast.literal_eval(body)


def test_mrcal_models_follow_the_grammar_and_count_rule(exported):
    out, run, _ = exported
    for step, (_, _, table, _) in STEPS.items():
        res = run.results[step][table]
        text = (out / "mrcal" / f"{_stem(run, step)}.cameramodel").read_text()
        model = _parse_cameramodel(text)
        assert set(model) == {"lensmodel", "intrinsics", "extrinsics", "imagersize"}
        n_dist = int(re.fullmatch(r"LENSMODEL_OPENCV(\d+)", model["lensmodel"]).group(1))
        assert n_dist == len(res.dist)
        assert len(model["intrinsics"]) == 4 + n_dist
        K = res.K
        assert model["intrinsics"] == [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *res.dist]
        assert model["extrinsics"] == [0.0] * 6
        assert model["imagersize"] == list(SIZE)


@pytest.mark.parametrize("name", ["opencv5", "opencv8"])
def test_mrcal_models_match_mrcal_and_opencv_order(name):
    """Our file for the reference lens equals mrcal's own, and OpenCV's projection with our
    distortion vector equals mrcal's projection (so the term order is OpenCV's)."""
    ref = _parse_cameramodel((MRCAL_DATA / f"{name}.cameramodel").read_text())
    proj = json.loads((MRCAL_DATA / "projections.json").read_text())
    fx, fy, cx, cy, *dist = ref["intrinsics"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    ours = _parse_cameramodel(mrcal_model_text(K, dist, tuple(ref["imagersize"])))
    for key in ("lensmodel", "intrinsics", "extrinsics", "imagersize"):
        assert ours[key] == ref[key], key
    px, _ = cv2.projectPoints(np.array(proj["points_cam"]), np.zeros(3), np.zeros(3), K,
                              np.array(ours["intrinsics"][4:]))
    # two double-precision evaluations of the same polynomial: 1e-6 px is far above rounding
    # and far below any swapped term (the terms move points by > 1 px here)
    assert np.abs(px.reshape(-1, 2) - np.array(proj["projections_px"][name])).max() < 1e-6


def _python_with_mrcal() -> str | None:
    for exe in (sys.executable, "/usr/bin/python3"):
        if not Path(exe).exists():
            continue
        ok = subprocess.run([exe, "-c", "import mrcal"], capture_output=True).returncode == 0
        if ok:
            return exe
    return None


def test_mrcal_reads_our_models(exported):
    exe = _python_with_mrcal()
    if exe is None:
        pytest.skip("mrcal not installed")
    out, run, _ = exported
    paths = [str(out / "mrcal" / f"{_stem(run, s)}.cameramodel") for s in STEPS]
    script = ("import json, sys, mrcal\n"
              "out = []\n"
              "for p in sys.argv[1:]:\n"
              "    m = mrcal.cameramodel(p)\n"
              "    lens, intr = m.intrinsics()\n"
              "    out.append([lens, intr.tolist(), m.imagersize().tolist(),\n"
              "                m.extrinsics_rt_fromref().tolist()])\n"
              "print(json.dumps(out))\n")
    done = subprocess.run([exe, "-c", script, *paths], capture_output=True, text=True,
                          check=True)
    for step, (lens, intr, size, rt) in zip(STEPS, json.loads(done.stdout), strict=True):
        res = run.results[step][STEPS[step][2]]
        assert lens == f"LENSMODEL_OPENCV{len(res.dist)}"
        K = res.K
        assert intr == [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *res.dist]
        assert size == list(SIZE) and rt == [0.0] * 6


def test_a_distortion_model_without_an_export_is_reported(tmp_path):
    rng = np.random.default_rng(3)
    run = CalibrateRun(stems=step_file_stems(["a", "b"]))
    for step, n in (("a", 5), ("b", 4)):
        res = _made_up_result(rng, "opencv", 5)
        res.dist = res.dist[:n]
        run.results[step] = {"opencv": res}
        run.observations[step] = Observations(np.zeros((1, 3)), [], SIZE)
        run.zoom[step] = float(len(step))
        run.table_backend[step] = "opencv"
    logged = []
    files = write_exports(tmp_path, run, "cam", log=logged.append)
    assert logged == ["step b: not exported: 4 distortion terms; the exports know 5 (k1, k2, "
                      "p1, p2, k3) or 8 (k1..k6, p1, p2)"]
    assert run.failures == logged
    assert tmp_path / "mrcal" / "a.cameramodel" in files
    assert not (tmp_path / "mrcal" / "b.cameramodel").exists()


def test_calibrate_refuses_a_camera_name_ros_would_not_accept(tmp_path):
    from click.testing import CliRunner

    from zoomcalib.cli import main

    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "view.png"), np.zeros((8, 8), np.uint8))
    res = CliRunner().invoke(main, ["calibrate", str(images), "--pattern", "chessboard:9x6:25",
                                    "--camera-name", "zoom cam", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "'zoom cam': ROS camera names are letters, digits and _" in res.output
    assert not (tmp_path / "o").exists()


def test_an_unusable_step_is_listed_but_not_exported_as_a_camera(tmp_path):
    from zoomcalib.calibrate.status import sensor_aspect, step_status

    rng = np.random.default_rng(13)
    run = CalibrateRun(stems=step_file_stems(["1x", "5x", "9x"]))
    for i, step in enumerate(("1x", "5x", "9x")):
        res = _made_up_result(rng, "zoom-wide", 5)
        res.dist[:] = 0.0
        res.info["converged"] = True
        run.results[step] = {"zoom-wide": res}
        run.observations[step] = Observations(np.zeros((1, 3)), [], SIZE)
        run.zoom[step] = float(1 + 4 * i)
        run.table_backend[step] = "zoom-wide"
    hidden = str(rng.choice(["5x", "9x"]))  # which step leaves the image: not told below
    run.results[hidden]["zoom-wide"].K[1, 2] = -float(rng.uniform(100, 600))
    table = {s: r["zoom-wide"] for s, r in run.results.items()}
    aspect = sensor_aspect(table)
    run.status = {s: step_status(r, SIZE, aspect) for s, r in table.items()}
    files = write_exports(tmp_path, run, "cam", log=lambda m: None)
    index = yaml.safe_load((tmp_path / "ros" / "camera_info_index.yaml").read_text())
    by_step = {e["step"]: e for e in index["steps"]}
    assert set(by_step) == {"1x", "5x", "9x"}
    for step, e in by_step.items():
        stem = run.stems[step]
        mrcal = tmp_path / "mrcal" / f"{stem}.cameramodel"
        if step == hidden:
            assert e["status"] == "unusable" and e["file"] is None
            assert any("outside the" in r for r in e["reasons"])
            assert not mrcal.exists() and not (tmp_path / "ros" / f"{stem}.yaml").exists()
        else:
            assert e["status"] == "ok" and (tmp_path / "ros" / e["file"]) in files
            assert "# status: ok" in (tmp_path / "ros" / e["file"]).read_text()
            assert "# status: ok" in mrcal.read_text()
        fs = cv2.FileStorage(str(tmp_path / "opencv" / f"{stem}_zoom_wide.yml"),
                             cv2.FILE_STORAGE_READ)
        try:
            assert fs.getNode("status").string() == e["status"]
            node = fs.getNode("status_reasons")
            reasons = [node.at(i).string() for i in range(node.size())]
            assert bool(reasons) == (step == hidden)
        finally:
            fs.release()
