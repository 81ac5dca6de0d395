"""Faults of the calibrate job that used to give a wrong calibration with exit code 0.

Two "cameras" are made from OpenCV's 13 sample views (tests/data/opencv-samples, 640 x 480,
9x6 corners, 25 mm): camera A is the samples as they are, camera B the same views scaled by
3/4 (480 x 360). Scaling the image scales the focal length in pixels by the same factor, so
the truth comes from OpenCV's own published calibration of the samples, not from the code
under test: fx = 532.81 px for A (``test_calibration.py`` of OpenCV, see
tests/test_calibrate_opencv.py) and 399.61 px for B. The calibrations here use OpenCV's
detector and corner refinement (method ``classic``), whose fx agrees with the published one
to within its 1-sigma of about 0.5 px; the tolerance of 2 % (about 10 px for A) is far below
the 25 % that separates the two cameras.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from zoomcalib.calibrate.io import read_zoom_table
from zoomcalib.calibrate.run import calibrate_folder, step_file_stems
from zoomcalib.calibrate.stepfolders import zoom_steps
from zoomcalib.cli import main
from zoomcalib.diagnose.run import load_zoom_table
from zoomcalib.diagnose.table import ZoomTable

DATA = Path(__file__).parent / "data" / "opencv-samples"
SPEC = "chessboard:9x6:25"
FX_A = 532.8099  # OpenCV's modules/python/test/test_calibration.py
SCALE_B = 0.75
FX_B = FX_A * SCALE_B


def _samples(n: int = 13) -> list[Path]:
    files = sorted(DATA.glob("left*.jpg"))[:n]
    assert len(files) == n
    return files


def _camera_a(folder: Path, n: int = 13) -> Path:
    folder.mkdir(parents=True)
    for f in _samples(n):
        shutil.copy(f, folder / f.name)
    return folder


def _scaled(src: Path, dst: Path, scale: float = SCALE_B) -> None:
    img = cv2.imread(str(src))
    small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    assert cv2.imwrite(str(dst), small)


def _camera_b(folder: Path, n: int = 13) -> Path:
    folder.mkdir(parents=True)
    for f in _samples(n):
        _scaled(f, folder / f.name)
    return folder


def _calibrate(folder: Path, out: Path, **kw):
    log: list[str] = []
    kw.setdefault("backends", ("opencv",))
    kw.setdefault("zoom_wide", False)  # these cases concern the per-step job
    kw.setdefault("report", False)  # and its files; the report's own cases: tests/test_report.py
    run = calibrate_folder(folder, SPEC, out, method="classic", log=log.append, **kw)
    return run, log


def _fx(run, step: str = ".", backend: str = "opencv") -> float:
    return run.results[step][backend].fx


# ----------------------------------------------------------------------------------------------
# 1. the detection cache is keyed on the images' content and the detection settings


def test_second_camera_in_the_same_output_folder_is_not_given_the_first_ones_detections(
        tmp_path):
    cam_a = _camera_a(tmp_path / "a")
    cam_b = _camera_b(tmp_path / "b")  # same file names, other images
    out = tmp_path / "out"
    run_a, _ = _calibrate(cam_a, out)
    assert abs(_fx(run_a) - FX_A) < 0.02 * FX_A
    run_b, log = _calibrate(cam_b, out)
    assert abs(_fx(run_b) - FX_B) < 0.02 * FX_B, _fx(run_b)
    assert not run_b.reused and not any("reused" in m for m in log)
    # a rerun on unchanged images reuses them, and says so
    run_b2, log = _calibrate(cam_b, out)
    assert run_b2.reused == {".": 13} and any("reused" in m and "13" in m for m in log)
    meta = json.loads((out / "calibration.json").read_text())["meta"]
    assert meta["detections"]["."]["reused"] == 13 and meta["detections"]["."]["detected"] == 0
    # one image re-encoded (same name, same size, other bytes): only that one is detected again
    img = cv2.imread(str(cam_b / "left03.jpg"))
    assert cv2.imwrite(str(cam_b / "left03.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 60])
    run_b3, _ = _calibrate(cam_b, out)
    meta = json.loads((out / "calibration.json").read_text())["meta"]
    assert meta["detections"]["."]["reused"] == 12 and meta["detections"]["."]["detected"] == 1
    # another detection method is another key
    log = []
    calibrate_folder(cam_b, SPEC, out, ("opencv",), method="sb", log=log.append, report=False)
    assert not any("reused" in m for m in log)


def test_a_failure_from_outside_the_image_is_not_reused_from_the_cache(tmp_path, monkeypatch):
    """A detection that failed for a reason outside the image (here every worker's call
    raising, as when the system kills the pool) is recorded, and the next run detects that
    image again instead of reusing the failure."""
    import zoomcalib.detect.opencv as detect_opencv

    cam = _camera_a(tmp_path / "a")
    out = tmp_path / "out"
    real = detect_opencv.detect_image

    def crashing(path, *args, **kwargs):
        if Path(path).name == "left03.jpg":
            raise MemoryError("worker out of memory")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(detect_opencv, "detect_image", crashing)
    _, log = _calibrate(cam, out)
    assert any("left03.jpg: MemoryError: worker out of memory" in m for m in log), log
    monkeypatch.setattr(detect_opencv, "detect_image", real)
    run, log = _calibrate(cam, out)
    meta = json.loads((out / "calibration.json").read_text())["meta"]
    assert meta["detections"]["."]["detected"] == 1 and run.reused == {".": 12}
    assert not any("left03.jpg" in m for m in log), log
    assert not run.skipped_images


# ----------------------------------------------------------------------------------------------
# 2. step names that differ only outside ASCII get files of their own


def test_step_file_stems_are_distinct():
    names = ["広角", "望遠", "f ü", "f é", "f_ü", "zoom 1", "zoom_1", "Zoom_1", "."]
    stems = step_file_stems(names)
    assert len({s.casefold() for s in stems.values()}) == len(names)
    assert stems["広角"] == "広角" and stems["zoom_1"] != stems["Zoom_1"]
    assert stems["."] == "root"
    assert all("/" not in s and " " not in s for s in stems.values())


def test_non_ascii_steps_keep_their_own_detections_and_figures(tmp_path):
    root = tmp_path / "set"
    _camera_a(root / "f ü", 7)
    _camera_b(root / "f é", 7)
    run, _ = _calibrate(root, tmp_path / "out")
    assert abs(_fx(run, "f ü") - FX_A) < 0.02 * FX_A
    assert abs(_fx(run, "f é") - FX_B) < 0.02 * FX_B, _fx(run, "f é")
    out = tmp_path / "out"
    assert len(list((out / "detections").glob("*.json"))) == 2
    assert len(list(out.glob("residuals_*.png"))) == 2


# ----------------------------------------------------------------------------------------------
# 3. a stray image at the top of a zoom set


def test_stray_top_image_does_not_hide_the_step_subfolders(tmp_path):
    root = tmp_path / "set"
    _camera_a(root / "zoom_1", 7)
    _camera_b(root / "zoom_2", 7)
    cv2.imwrite(str(root / "target.png"), np.full((40, 60), 255, np.uint8))
    assert [s[0] for s in zoom_steps(root)] == ["zoom_1", "zoom_2"]
    run, log = _calibrate(root, tmp_path / "out")
    assert list(run.results) == ["zoom_1", "zoom_2"]
    assert any("target.png" in m and "ignored" in m for m in log)
    assert abs(_fx(run, "zoom_2") - FX_B) < 0.02 * FX_B


# ----------------------------------------------------------------------------------------------
# 4. one image of another size


def test_image_of_another_size_is_left_out_not_the_step(tmp_path):
    cam = _camera_a(tmp_path / "a")
    _scaled(DATA / "left01.jpg", cam / "left01.jpg")  # the first file is the odd one
    run, log = _calibrate(cam, tmp_path / "out")
    assert "." in run.results and not run.dropped
    res = run.results["."]["opencv"]
    assert len(res.per_view_rms_px) == 12 and "left01.jpg" not in run.observations["."].names
    assert abs(res.fx - FX_A) < 0.02 * FX_A
    odd = [m for m in log if "left01.jpg" in m]
    assert odd and "480x360" in odd[0] and "640x480" in odd[0]
    assert not any("left02.jpg" in m for m in log)  # no good image is blamed


def test_image_sizes_without_a_majority_drop_the_step_with_a_reason(tmp_path):
    cam = _camera_a(tmp_path / "a", 6)
    for f in _samples(3):
        _scaled(f, cam / f.name)
    run, log = _calibrate(cam, tmp_path / "out")
    assert run.dropped == ["."] and not run.results
    assert any("640x480" in m and "480x360" in m and "no majority" in m for m in log)


# ----------------------------------------------------------------------------------------------
# 5. each run owns its output folder


def test_rerun_into_a_used_folder_leaves_only_its_own_files(tmp_path):
    root = tmp_path / "set"
    _camera_a(root / "zoom_1", 7)
    _camera_b(root / "zoom_2", 7)
    out = tmp_path / "out"
    _calibrate(root, out, report=True)  # the report too is a file of the run's own
    assert (out / "zoom_calibration.csv").exists() and (out / "residuals_zoom_2.png").exists()
    (out / "notes.txt").write_text("mine")
    flat = _camera_a(tmp_path / "flat", 7)
    run, _ = _calibrate(flat, out, report=True)
    manifest = json.loads((out / "manifest.json").read_text())
    assert "report.html" in manifest["files"]
    present = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert present == set(manifest["files"]) | {"manifest.json", "notes.txt"}
    for stale in ("zoom_calibration.csv", "residuals_zoom_1.png", "residuals_zoom_2.png",
                  "focal_length.png", "principal_point_path.png", "detections/zoom_1.json"):
        assert stale not in present
    assert "residuals_root.png" in present and "calibration.json" in present
    assert manifest["inputs"]["folder"] == str(flat)
    assert [im["file"] for im in manifest["inputs"]["steps"]["."]["images"]] == \
        [f.name for f in _samples(7)]
    assert isinstance(manifest["command"], list)


# ----------------------------------------------------------------------------------------------
# 6. the zoom table says which backend each row is from; diagnose refuses a mixed table


def _fake_bundle(monkeypatch, fail_size):
    import dataclasses

    from zoomcalib.calibrate import bundle
    from zoomcalib.calibrate.opencv_backend import calibrate_opencv

    def fake(obs, model="standard", **kw):
        if tuple(obs.image_size) == fail_size:
            raise ValueError("did not converge")
        return dataclasses.replace(calibrate_opencv(obs, model=model), backend="bundle")

    monkeypatch.setattr(bundle, "calibrate_bundle", fake)


def test_zoom_table_names_its_backend_and_does_not_mix_them(tmp_path, monkeypatch):
    root = tmp_path / "set"
    _camera_a(root / "zoom_1", 7)
    _camera_b(root / "zoom_2", 7)
    _fake_bundle(monkeypatch, (480, 360))
    out = tmp_path / "out"
    run, log = _calibrate(root, out, backends=("opencv", "bundle"))
    rows = read_zoom_table(out / "zoom_calibration.csv")
    # the bundle failed on zoom_2: every row comes from OpenCV, and the table says so
    assert [r["backend"] for r in rows] == ["opencv", "opencv"]
    assert any("zoom_2" in m and "bundle" in m and "opencv" in m for m in log)
    assert run.partial and "zoom_2" in run.partial_message()
    assert load_zoom_table(out / "zoom_calibration.csv").backend == "opencv"


def test_diagnose_refuses_a_table_of_mixed_backends(tmp_path):
    rows = [{"step": f"z{k}", "zoom": k, "fx": 1000.0 + 100 * k, "fy": 1000.0 + 100 * k,
             "cx": 640.0, "cy": 480.0, "backend": b}
            for k, b in enumerate(["bundle", "bundle", "opencv", "bundle"], start=1)]
    with pytest.raises(ValueError, match=r"t.csv: .*backends.*opencv: step z3"):
        ZoomTable.from_rows(rows, "t.csv")
    assert ZoomTable.from_rows([dict(r, backend="bundle") for r in rows], "t.csv").backend \
        == "bundle"
    assert ZoomTable.from_rows([{k: v for k, v in r.items() if k != "backend"} for r in rows],
                               "t.csv").backend is None
    path = tmp_path / "zoom_calibration.csv"
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    res = CliRunner().invoke(main, ["diagnose", str(path), "--out", str(tmp_path / "d")])
    assert res.exit_code == 1 and "mixed" in res.output and "Traceback" not in res.output
    assert len(res.output.strip().splitlines()) == 1


# ----------------------------------------------------------------------------------------------
# 7. every distortion term of the model is in the table


def test_rational_model_writes_k4_to_k6_and_their_sigmas(tmp_path):
    root = tmp_path / "set"
    _camera_a(root / "zoom_1", 13)
    _camera_b(root / "zoom_2", 13)
    out = tmp_path / "out"
    _calibrate(root, out, model="rational")
    cal = json.loads((out / "calibration.json").read_text())["steps"]
    with (out / "zoom_calibration.csv").open() as fh:
        rows = {r["step"]: r for r in csv.DictReader(fh)}
    for step, row in rows.items():
        entry = cal[step]["opencv"]
        assert len(entry["dist"]) == 8
        for k, name in enumerate(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")):
            assert float(row[name]) == entry["dist"][k]
            assert float(row[f"sd_{name}"]) == entry["sd"][name]


# ----------------------------------------------------------------------------------------------
# exit code of a partial result


def test_calibrate_exits_3_naming_the_dropped_step(tmp_path):
    root = tmp_path / "set"
    _camera_a(root / "zoom_1", 7)
    (root / "zoom_2").mkdir()
    (root / "zoom_2" / "view.png").write_bytes(b"not an image")
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["calibrate", str(root), "--pattern", SPEC, "--backend",
                                    "opencv", "--method", "classic", "--workers", "1",
                                    "--out", str(out)])
    assert res.exit_code == 3, res.output
    assert "partial" in res.output and "zoom_2" in res.output.splitlines()[-1]
    assert (out / "calibration.json").exists()
    assert "zoom_2" in (out / "report.html").read_text()  # the report says it too


def test_output_folder_inside_a_flat_image_folder_is_not_a_step(tmp_path):
    # `zoomcalib calibrate .` run from inside the image folder: OUT (with its figures) is a
    # subfolder of the images, and must not turn the folder into a zoom set on the rerun
    cam = _camera_a(tmp_path / "a", 7)
    out = cam / "zoomcalib-calibration"
    _calibrate(cam, out)
    assert list(out.glob("residuals_*.png"))
    run, _ = _calibrate(cam, out)
    assert list(run.results) == ["."] and len(run.observations["."].names) == 7


def test_files_listed_by_the_previous_manifest_are_removed_and_nothing_outside(tmp_path):
    from zoomcalib.calibrate.guards import clear_previous_outputs

    out = tmp_path / "out"
    (out / "detections").mkdir(parents=True)
    # a run's own files go even without a manifest that lists them (an interrupted run)
    for name in ("zoom_joint.json", "calibration.json", "detections/a.json",
                 "zoom_calibration_unsmoothed_correlation.json",
                 "detections/b.json", "residuals_x.png", "keep.txt"):
        (out / name).write_text("x")
    (tmp_path / "outside.txt").write_text("x")
    (out / "manifest.json").write_text(json.dumps(
        {"files": ["zoom_joint.json", "../outside.txt", str(tmp_path / "outside.txt")]}))
    clear_previous_outputs(out, keep=["detections/a.json"], protect=[out / "residuals_x.png"])
    left = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert left == {"detections/a.json", "residuals_x.png", "keep.txt"}
    assert (tmp_path / "outside.txt").exists()
