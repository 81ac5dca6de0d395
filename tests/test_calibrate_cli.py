import csv
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from zoomcalib.cli import main


@pytest.fixture(scope="module")
def zoom_set(tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "set"
    res = CliRunner().invoke(main, ["render", "--zoom", "0.1,0.4,0.7", "--views", "6",
                                    "--seed", "11", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def test_calibrate_zoom_set_recovers_rendered_cameras(zoom_set, tmp_path):
    # a broken step: one unreadable image only -> reported and skipped, the rest calibrated
    bad = zoom_set / "zoom_99"
    bad.mkdir()
    (bad / "view_00.png").write_bytes(b"not an image")
    with (zoom_set / "steps.csv").open("a") as fh:
        fh.write("zoom_99,0.9,,3,\n")
    out = tmp_path / "cal"
    # (the report of a zoom set with a dropped step: test_calibrate_faults.py,
    # test_calibrate_exits_3_naming_the_dropped_step)
    res = CliRunner().invoke(main, ["calibrate", str(zoom_set), "--pattern", "chessboard:9x6:25",
                                    "--backend", "opencv", "--method", "model", "--no-report",
                                    "--workers", "1", "--out", str(out)])
    assert res.exit_code == 3, res.output  # partial: one step dropped, the rest written
    assert "zoom_99" in res.output and "cannot read image" in res.output
    assert "partial result: not calibrated or skipped: step zoom_99" in res.output
    truth = json.loads((zoom_set / "dataset.json").read_text())
    cal = json.loads((out / "calibration.json").read_text())
    with (out / "zoom_calibration.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[:17] == ["step", "zoom", "fx", "fy", "cx", "cy", "sd_fx", "sd_fy",
                                  "sd_cx", "sd_cy", "k1", "k2", "p1", "p2", "k3", "rms_px",
                                  "n_views"]
    assert [r["step"] for r in rows] == ["zoom_00", "zoom_01", "zoom_02"]
    for st, row in zip(truth["steps"], rows, strict=True):
        entry = cal["steps"][st["step"]]["opencv"]
        K = np.array(entry["K"])
        cam = st["camera"]
        # the rendered lens is the exact one; its fitted OpenCV model is the reference. The
        # calibration must land within 4 of its noise model's 1-sigma (plus the model misfit,
        # < 0.01 px), and the reported sigma is never below that one.
        noise_sd = entry["info"]["sd_noise_model"]
        # the per-step checks of the view scatter are tested together over the 3 steps
        assert entry["info"]["view_scatter"]["steps_pooled"] == 3
        for k, v in (("cx", K[0, 2]), ("cy", K[1, 2]), ("fx", K[0, 0])):
            assert abs(v - cam[k]) < 4 * noise_sd[k] + 0.05, (st["step"], k, v, cam[k])
            assert entry["sd"][k] >= noise_sd[k]
        assert float(row["rms_px"]) < 0.05
    for name in ("calibration.yml", "principal_point_path.png", "focal_length.png",
                 "residuals_zoom_00.png"):
        assert (out / name).exists()
    fs = cv2.FileStorage(str(out / "calibration.yml"), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    fs.release()
    # the exports: every calibrated step in each tool's format, listed in the manifest; three
    # steps are too few for a zoom model, so no grid
    listed = set(json.loads((out / "manifest.json").read_text())["files"])
    for step in ("zoom_00", "zoom_01", "zoom_02"):
        for rel in (f"opencv/{step}_opencv.yml", f"opencv/{step}_zoom_wide.yml",
                    f"mrcal/{step}.cameramodel"):
            assert rel in listed and (out / rel).is_file(), rel
    index = yaml.safe_load((out / "ros" / "camera_info_index.yaml").read_text())
    assert index["camera_name"] == "set"  # the image folder's name
    assert [e["step"] for e in index["steps"]] == ["zoom_00", "zoom_01", "zoom_02"]
    assert all(f"ros/{e['file']}" in listed for e in index["steps"])
    assert not (out / "zoom_model_grid.csv").exists()
    # a rerun reuses the cached detections
    stamp = (out / "detections" / "zoom_00.json").stat().st_mtime_ns
    res = CliRunner().invoke(main, ["calibrate", str(zoom_set), "--pattern", "chessboard:9x6:25",
                                    "--backend", "opencv", "--method", "model",
                                    "--camera-name", "ptz_cam", "--out", str(out)])
    assert res.exit_code == 3
    assert (out / "detections" / "zoom_00.json").stat().st_mtime_ns == stamp
    # a camera name given reaches the ROS index and every ROS file
    index = yaml.safe_load((out / "ros" / "camera_info_index.yaml").read_text())
    assert index["camera_name"] == "ptz_cam"
    for entry in index["steps"]:
        assert yaml.safe_load((out / "ros" / entry["file"]).read_text())["camera_name"] \
            == "ptz_cam"


def test_the_residual_budget_is_written_and_said(zoom_set, tmp_path):
    # rendered frames of the exact lens, a flat board, no motion: nothing to name
    out = tmp_path / "budget"
    res = CliRunner().invoke(main, ["calibrate", str(zoom_set), "--pattern", "chessboard:9x6:25",
                                    "--method", "model", "--workers", "1", "--residual-budget",
                                    "--out", str(out)])
    assert res.exit_code in (0, 3), res.output
    budget = json.loads((out / "calibration.json").read_text())["meta"]["residual_budget"]
    steps = {"zoom_00", "zoom_01", "zoom_02"}
    assert steps <= set(budget["steps"])
    for name in steps:
        b = budget["steps"][name]
        assert [c["name"] for c in b["causes"]] == ["lens", "board", "points", "focal",
                                                    "readout"]
        assert b["named"] == [], b
        assert f"budget {name}: held-out RMS" in res.output
    assert sum(len(s["steps"]) for s in budget["sessions"].values()) == len(budget["steps"])
    assert "budget of session" in res.output
    page = (out / "report.html").read_text()
    assert "id='residual-budget'" in page and "budget zoom_00" not in page
    assert page.count("zoom_01: held-out RMS") == 1


def _clean_copy(zoom_set, tmp_path):
    """The rendered set copied without the broken step the first test adds to it."""
    import shutil

    folder = tmp_path / "set"
    shutil.copytree(zoom_set, folder, ignore=shutil.ignore_patterns("zoom_99"))
    steps = (folder / "steps.csv").read_text().splitlines()
    (folder / "steps.csv").write_text("\n".join(r for r in steps if "zoom_99" not in r) + "\n")
    return folder


def test_a_byte_identical_copy_is_one_view(zoom_set, tmp_path):
    # the real PTZ set holds such a copy under another name: used twice it would count as a
    # second view of the same pose
    import shutil

    folder = _clean_copy(zoom_set, tmp_path)
    first = sorted((folder / "zoom_00").glob("*.png"))[0]
    shutil.copy(first, folder / "zoom_00" / "zz_copy.png")
    out = tmp_path / "cal"
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", "chessboard:9x6:25",
                                    "--method", "model", "--workers", "1", "--per-step",
                                    "--backend", "opencv", "--no-report", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert f"zz_copy.png is a byte-identical copy of {first.name}: used once" in res.output
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["meta"]["copies"] == {"zoom_00": {"zz_copy.png": first.name}}
    views = {s: e["opencv"]["n_views"] for s, e in cal["steps"].items()}
    assert views["zoom_00"] == views["zoom_01"] == 6, views
    # the progress bar's length is every image file: the copy is counted done, so the bar
    # ends full (the rerun reuses the cached detections)
    from zoomcalib.calibrate.run import calibrate_folder

    done: list[int] = []
    calibrate_folder(folder, "chessboard:9x6:25", out, ("opencv",), method="model",
                     progress=done.append, log=lambda m: None, zoom_wide=False, report=False)
    assert sum(done) == len(list(folder.glob("zoom_*/*.png"))), done


def test_a_spec_that_counts_squares_gets_the_inner_corner_count(zoom_set, tmp_path):
    # the board has 9x6 inner corners (10x7 squares): a user who counts squares finds nothing,
    # and is told which count finds the board (two of the step's images: a board not found
    # costs the detectors' full search in every image)
    import shutil

    images = tmp_path / "images"
    images.mkdir()
    for src in sorted((zoom_set / "zoom_00").glob("*.png"))[:2]:
        shutil.copy(src, images / src.name)
    out = tmp_path / "cal"
    res = CliRunner().invoke(main, ["calibrate", str(images), "--pattern",
                                    "chessboard:10x7:25", "--workers", "1", "--no-report",
                                    "--out", str(out)])
    assert res.exit_code == 4, res.output
    assert ("chessboard:9x6:25 is found in view_00.png: count the inner corners (where four "
            "squares meet), not the squares") in res.output, res.output


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process table from /proc")
def test_ctrl_c_during_detection_ends_at_once_and_keeps_the_finished_images(zoom_set,
                                                                          tmp_path):
    # a real SIGINT to the process group, as a terminal's Ctrl-C sends it, once the two
    # detection workers run, and a second one while the first is handled
    import contextlib
    import signal
    import subprocess
    import sys
    import time

    # 72 images (zoom_00's six, 12 times each with its corner pixel changed: another file,
    # the same board): about 11 s of detection on two idle cores
    folder = tmp_path / "many"
    folder.mkdir()
    for src in sorted((zoom_set / "zoom_00").glob("*.png")):
        image = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        for k in range(12):
            image[0, 0] = 10 * k
            cv2.imwrite(str(folder / f"{src.stem}_{k:02d}.png"), image)
    out = tmp_path / "cal"
    cmd = [sys.executable, "-m", "zoomcalib.cli", "calibrate", str(folder), "--pattern",
           "chessboard:9x6:25", "--workers", "2", "--no-report", "--out", str(out)]
    # a terminal's foreground job has SIGINT at its default; a job started in the background of
    # a non-interactive shell (as a CI script may be) inherits it ignored, and Python then keeps
    # ignoring it: the child restores the default, as the terminal's job would have it
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    workers: list[int] = []
    deadline = time.monotonic() + 60
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
        workers = _children(proc.pid)
    assert len(workers) >= 2, ("the detection workers did not start", proc.poll())
    time.sleep(4.0)  # the workers started (about 1.5 s) and finished some images
    sent = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)
    time.sleep(0.1)  # and again, as an impatient user does: it must not cut the clean-up short
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=30)
    took = time.monotonic() - sent
    assert proc.returncode == 130, (proc.returncode, stdout, stderr)
    assert took < 2.0, (took, stderr)
    assert "Traceback" not in stderr + stdout, stderr
    assert "interrupted: the detections finished so far are kept" in stderr
    # the workers, and multiprocessing's resource tracker, go with the main process
    gone_by = time.monotonic() + 2.0
    while [p for p in workers if _alive(p)] and time.monotonic() < gone_by:
        time.sleep(0.05)
    assert not [p for p in workers if _alive(p)], ("orphans", workers, stderr)
    cached = sum(len(json.loads(f.read_text())["images"])
                 for f in (out / "detections").glob("*.json"))
    assert 1 <= cached < 72, cached
    # the same command resumes: the finished images are not detected again
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"reused the cached detections of {cached} unchanged images" in res.stdout
