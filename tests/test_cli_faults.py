"""Fault handling of the commands: bad input and unwritable output end in one line and a
documented exit code, before any work; partial results exit 3, nothing usable exits 4."""

import csv
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import zoomcalib.calibrate.run
import zoomcalib.detect
import zoomcalib.diagnose.run
import zoomcalib.render.dataset
import zoomcalib.simulate
import zoomcalib.study.run
import zoomcalib.targets
from zoomcalib import cli
from zoomcalib.cli import main

SAMPLES = Path(__file__).parent / "data" / "opencv-samples"
CHESS = "chessboard:9x6:25"

# The function each command's work starts with: a check that runs after it is too late.
WORK = {"simulate": (zoomcalib.simulate, "simulate"),
        "target": (zoomcalib.targets, "write_printable"),
        "render": (zoomcalib.render.dataset, "render_dataset"),
        "detect": (zoomcalib.detect, "detect_folder"),
        "calibrate": (zoomcalib.calibrate.run, "calibrate_folder"),
        "study": (zoomcalib.study.run, "run_study"),
        "diagnose": (zoomcalib.diagnose.run, "diagnose_table")}


@pytest.fixture
def no_work(monkeypatch):
    """Make every command's work fail loudly if it starts."""
    def refuse(*args, **kwargs):
        raise AssertionError("the command started its work")

    for module, name in WORK.values():
        monkeypatch.setattr(module, name, refuse)


def zoom_table(path: Path, fx: list[float]) -> Path:
    """A per-zoom table with one row per focal length (zoom = row number)."""
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "zoom", "fx", "fy", "cx", "cy"])
        for k, f in enumerate(fx):
            w.writerow([f"s{k}", k, f, f, 640 + k, 480 - k])
    return path


def one_line_error(res, code: int, *fragments: str) -> str:
    """The single ``Error:`` line of a refused command, after checking the exit code."""
    assert res.exit_code == code, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert "Traceback" not in res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, res.output
    for f in fragments:
        assert f in errors[0], errors[0]
    return errors[0]


def command_args(command: str, out: str) -> list[str]:
    """Valid arguments for ``command`` writing to ``out``."""
    return {"simulate": ["simulate", "--steps", "2", "--samples", "2"],
            "target": ["target", CHESS],
            "render": ["render", "--zoom", "0.2", "--views", "1"],
            "detect": ["detect", str(SAMPLES), "--pattern", CHESS],
            "calibrate": ["calibrate", str(SAMPLES), "--pattern", CHESS],
            "study": ["study", "--quick"],
            "diagnose": ["diagnose", str(SAMPLES), "--pattern", CHESS]}[command] + ["--out", out]


@pytest.mark.parametrize("command", list(WORK))
def test_output_through_a_file_is_refused_before_work(command, tmp_path, no_work):
    (tmp_path / "somefile.txt").write_text("x")
    out = str(tmp_path / "somefile.txt" / "sub" / "result.json")
    res = CliRunner().invoke(main, command_args(command, out))
    one_line_error(res, 2, "--out", out, f"{tmp_path / 'somefile.txt'} is a file, not a folder")


@pytest.mark.parametrize("command", list(WORK))
def test_read_only_output_folder_is_refused_before_work(command, tmp_path, no_work,
                                                        monkeypatch):
    # Tests run as root, for whom a chmod'ed folder stays writable: the permission answer is
    # injected, the real case is in test_read_only_folder_for_a_user.
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access

    def access(path, mode):
        if Path(path) == locked and mode & os.W_OK:
            return False
        return real_access(path, mode)

    monkeypatch.setattr(cli.os, "access", access)
    out = str(locked / "new" / "result.json")
    res = CliRunner().invoke(main, command_args(command, out))
    one_line_error(res, 2, "--out", out, f"no permission to write in {locked}")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root writes into read-only folders; the injected case above covers it")
def test_read_only_folder_for_a_user(tmp_path, no_work):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        res = CliRunner().invoke(main, command_args("simulate", str(locked / "sim")))
    finally:
        locked.chmod(0o700)
    one_line_error(res, 2, f"no permission to write in {locked}")


MINIMUM = "needs 3 or more settings and 4 rows outside any one setting (so 5 rows"

# (arguments, exit code, what the error line must say), per command; OUT, TMP, EMPTY and the
# tables THREE, FOUR, ONE_STATE are replaced by paths in the test's folder.
BAD_INPUT = [
    (["simulate", "--seed", "-1"], 2, "--seed"),
    (["simulate", "--lens", "TMP/nolens.json"], 2, "nolens.json"),
    (["target", CHESS, "--dpi", "nan"], 2, "not a finite number"),
    (["target", "hexagons:3x3:1"], 2, "not understood"),
    (["render", "--size", "0x0"], 2, "each side must be 1 to"),
    (["render", "--size", "64by48"], 2, "is not WIDTHxHEIGHT"),
    (["render", "--defocus", "-5"], 2, "PSF sigma 80.8 px"),
    (["render", "--blur", "50"], 2, "reduce --blur or --defocus"),
    (["render", "--noise", "nan"], 2, "not a finite number"),
    (["render", "--seed", "-1"], 2, "--seed"),
    (["render", "--zoom", "0.2,1.5"], 2, "[0, 1]"),
    (["render", "--nominal", "--tolerances", "THREE"], 2, "not both"),
    (["detect", "EMPTY", "--pattern", CHESS], 2, "no images found"),
    (["detect", str(SAMPLES), "--pattern", "chessboard:9x6"], 2, "PATTERN"),
    (["calibrate", "EMPTY", "--pattern", CHESS], 2, "FOLDER"),
    (["study", "--noise=-1"], 2, "[0, 255]"),
    (["study", "--noise", "1,nan"], 2, "[0, 255]"),
    (["study", "--seed", "-1"], 2, "--seed"),
    (["diagnose", "THREE"], 1, f"3 rows at 3 zoom settings are too few; the diagnosis {MINIMUM}"),
    (["diagnose", "FOUR", "--pixel-pitch", "auto"], 1,
     f"4 rows at 4 zoom settings are too few; the diagnosis {MINIMUM}"),
    (["diagnose", "ONE_STATE"], 1, "all 6 rows are one lens state"),
    (["diagnose", "THREE", "--pixel-pitch", "-1"], 2, "must be positive"),
]


@pytest.mark.parametrize("args, code, fragment", BAD_INPUT,
                         ids=[f"{a[0]}-{i}" for i, (a, _, _) in enumerate(BAD_INPUT)])
def test_bad_input_gives_one_line_and_exit_code_before_work(args, code, fragment, tmp_path,
                                                           no_work):
    tables = tmp_path / "tables"
    tables.mkdir()
    (tmp_path / "empty").mkdir()
    paths = {"TMP": str(tmp_path), "EMPTY": str(tmp_path / "empty"),
             "THREE": zoom_table(tables / "three.csv", [2400.0, 4000.0, 7000.0]),
             "FOUR": zoom_table(tables / "four.csv", [2400.0, 3500.0, 5000.0, 7000.0]),
             "ONE_STATE": zoom_table(tables / "one_state.csv", [3000.0] * 6)}
    out = tmp_path / "out"
    args = [a.replace("TMP", paths["TMP"]) if a.startswith("TMP") else str(paths.get(a, a))
            for a in args]
    res = CliRunner().invoke(main, args + ["--out", str(out)])
    one_line_error(res, code, fragment)
    assert not out.exists()


def test_detect_output_that_is_a_folder_is_refused(tmp_path, no_work):
    res = CliRunner().invoke(main, ["detect", str(SAMPLES), "--pattern", CHESS,
                                    "--out", str(tmp_path)])
    one_line_error(res, 2, "is a directory")


def test_render_finds_every_pose_before_writing(tmp_path):
    # the renderer's own pose search is the check: it runs before any file is written, and the
    # message names render's options (it used to name --fill, an option render does not have)
    out = tmp_path / "set"
    res = CliRunner().invoke(main, ["render", "--zoom", "0.2,0.9", "--views", "2", "--size",
                                    "64x48", "--out", str(out)])
    line = one_line_error(res, 2, "64x48 px sensor; use a larger --size or fewer --views")
    assert "--fill" not in line
    assert not out.exists()


def test_diagnose_minimum_is_the_true_one(tmp_path):
    # 4 rows at 4 settings are refused (above); 5 rows, one per setting, are diagnosed.
    table = zoom_table(tmp_path / "five.csv", [2400.0, 3500.0, 5000.0, 7000.0, 9000.0])
    res = CliRunner().invoke(main, ["diagnose", str(table), "--out", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "d" / "diagnosis.json").exists()


def test_diagnose_folder_too_small_is_refused_before_calibration(tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("calibrated before the size check")

    monkeypatch.setattr(zoomcalib.calibrate.run, "calibrate_folder", refuse)
    for k in range(3):
        step = tmp_path / "set" / f"zoom_{k}"
        step.mkdir(parents=True)
        (step / "left01.jpg").symlink_to(SAMPLES / f"left0{k + 1}.jpg")
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "set"), "--pattern", CHESS,
                                    "--out", str(tmp_path / "d")])
    one_line_error(res, 1, "3 rows at 3 zoom settings are too few")


def linked_folder(tmp_path: Path, names: list[str], junk: int = 0) -> Path:
    """A folder of symbolic links to sample images elsewhere, and ``junk`` unreadable ones."""
    folder = tmp_path / "links"
    folder.mkdir()
    for name in names:
        (folder / name).symlink_to(SAMPLES / name)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    for k in range(junk):
        (elsewhere / f"bad{k}.jpg").write_bytes(b"not an image")
        (folder / f"zz_bad{k}.jpg").symlink_to(elsewhere / f"bad{k}.jpg")
    return folder


def test_detect_on_a_folder_of_symlinks(tmp_path):
    import json

    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg", "left03.jpg"])
    out = tmp_path / "det.json"
    res = CliRunner().invoke(main, ["detect", str(folder), "--pattern", CHESS, "--method", "sb",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert [im["file"] for im in doc["images"]] == ["left01.jpg", "left02.jpg", "left03.jpg"]
    assert all(len(im["ids"]) == 54 for im in doc["images"])


def test_detect_exit_codes_partial_and_nothing(tmp_path):
    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg"], junk=1)
    out = tmp_path / "det.json"
    res = CliRunner().invoke(main, ["detect", str(folder), "--pattern", CHESS, "--method", "sb",
                                    "--out", str(out)])
    assert res.exit_code == 3, res.output
    assert "partial result: 1 of 3 images failed: zz_bad0.jpg" in res.output
    assert out.exists()
    res = CliRunner().invoke(main, ["detect", str(folder), "--pattern", "chessboard:7x7:25",
                                    "--method", "sb", "--out", str(out)])
    assert res.exit_code == 4, res.output
    assert "nothing usable" in res.output


def test_calibrate_exit_codes_partial_and_nothing(tmp_path):
    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg"],
                           junk=1)
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", CHESS, "--backend",
                                    "opencv", "--workers", "1", "--out", str(tmp_path / "c")])
    assert res.exit_code == 3, res.output
    assert "partial result: not calibrated or skipped: image zz_bad0.jpg" in res.output
    assert (tmp_path / "c" / "calibration.json").exists()
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", "chessboard:7x7:25",
                                    "--backend", "opencv", "--workers", "1",
                                    "--out", str(tmp_path / "c2")])
    assert res.exit_code == 4, res.output
    assert "nothing usable: no step could be calibrated" in res.output


def test_a_frame_whose_board_runs_off_the_image_is_left_aside_with_a_note(tmp_path):
    """A frame with the board half out of view is normal in a real set: left aside with a
    note, the run complete (exit 0); an unreadable image beside it still makes it partial."""
    import cv2

    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg"])
    grey = cv2.imread(str(SAMPLES / "left05.jpg"), cv2.IMREAD_GRAYSCALE)
    shifted = np.full_like(grey, int(np.median(grey)))
    shifted[:, 320:] = grey[:, :320]  # the same size, the board's left half out of the frame
    cv2.imwrite(str(folder / "left05.jpg"), shifted)
    args = ["calibrate", str(folder), "--pattern", CHESS, "--backend", "opencv", "--workers",
            "1", "--no-report"]
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    assert "left aside left05.jpg: no chessboard 9x6 found (no whole target in view" \
        in res.output
    assert "partial result" not in res.output
    (elsewhere := tmp_path / "elsewhere").mkdir(exist_ok=True)
    (elsewhere / "bad.jpg").write_bytes(b"not an image")
    (folder / "zz_bad.jpg").symlink_to(elsewhere / "bad.jpg")
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "c2")])
    assert res.exit_code == 3, res.output
    assert "not calibrated or skipped: image zz_bad.jpg" in res.output
    assert "left05" not in res.output.split("partial result")[1]


def test_an_image_of_another_size_is_named_in_the_partial_result(tmp_path):
    """An image left out because its size is not the step's is a partial result, named."""
    import cv2

    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg"])
    small = cv2.imread(str(SAMPLES / "left05.jpg"))
    cv2.imwrite(str(folder / "left05.jpg"), cv2.resize(small, (320, 240)))
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", CHESS, "--backend",
                                    "opencv", "--workers", "1", "--out", str(tmp_path / "c")])
    assert res.exit_code == 3, res.output
    assert "left out left05.jpg (320x240): not the step's image size 640x480" in res.output
    assert "partial result: not calibrated or skipped: image left05.jpg" in res.output


def test_help_documents_exit_codes():
    for command in WORK:
        res = CliRunner().invoke(main, [command, "--help"])
        assert "3 partial" in res.output and "4 nothing usable" in res.output, command


def test_a_write_failing_during_the_work_is_one_line(tmp_path, monkeypatch):
    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "sim" / "spiral.png"))

    monkeypatch.setattr(zoomcalib.simulate, "simulate", disk_full)
    res = CliRunner().invoke(main, ["simulate", "--out", str(tmp_path / "sim")])
    one_line_error(res, 1, f"{tmp_path / 'sim' / 'spiral.png'}: No space left on device")


@pytest.mark.parametrize("command, args", [("simulate", []), ("detect", ["--pattern", CHESS]),
                                           ("study", ["--quick"])])
def test_ctrl_c_in_any_command_is_one_line_and_exit_130(tmp_path, monkeypatch, command, args):
    # calibrate's own handling (detections kept, a real signal) is tested in
    # test_calibrate_cli.py; every other command ends the same way through the group
    def pressed(*a, **kw):
        raise KeyboardInterrupt

    import signal

    module, name = WORK[command]
    monkeypatch.setattr(module, name, pressed)
    folder = linked_folder(tmp_path, ["left01.jpg"]) if command == "detect" else None
    handler = signal.getsignal(signal.SIGINT)
    try:
        res = CliRunner().invoke(main, [command, *([str(folder)] if folder else []), *args,
                                        "--out", str(tmp_path / "o")])
        # the ending process ignores a second press (a real one: test_calibrate_cli.py)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, handler)
    assert res.exit_code == 130, res.output
    assert res.output.strip().splitlines()[-1] == "interrupted (exit code 130)"
    assert "Aborted" not in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("failed, code", [(1, 3), ("all", 4)])
def test_study_exit_codes_name_failed_sets(tmp_path, monkeypatch, failed, code):
    import zoomcalib.study.run as study_run

    real_tasks = study_run.detection_tasks

    def fake_run(config, out, **kw):  # the CLI's handling of failed sets, not the study
        n = len(real_tasks(config)) if failed == "all" else failed
        return {"failures": [f"set{i}: detection failed" for i in range(n)], "comparison": [],
                "timing": {"render_s": 0, "detect_s": 0, "calibrate_s": 0, "mechanics_s": 0,
                           "wall_s": 0}}

    monkeypatch.setattr(study_run, "run_study", fake_run)
    res = CliRunner().invoke(main, ["study", "--quick", "--out", str(tmp_path / "st")])
    assert res.exit_code == code, res.output
    last = res.output.strip().splitlines()[-1]
    assert ("partial result" if code == 3 else "nothing usable") in last
    assert "set0" in res.output and "Traceback" not in res.output


def test_calibrate_warns_of_a_solve_that_did_not_converge(tmp_path, monkeypatch):
    import shutil

    from zoomcalib.calibrate import opencv_backend

    samples = Path(__file__).parent / "data" / "opencv-samples"
    folder = tmp_path / "imgs"
    folder.mkdir()
    for f in sorted(samples.glob("left*.jpg"))[:8]:
        shutil.copy(f, folder / f.name)
    real = opencv_backend.calibrate_opencv

    def capped(obs, *a, **kw):  # OpenCV stopped after 2 iterations: far from its minimum
        kw["criteria"] = (3, 2, 1e-12)
        return real(obs, *a, **kw)

    monkeypatch.setattr(opencv_backend, "calibrate_opencv", capped)  # under calibrate_opencv_robust
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", "chessboard:9x6:25",
                                    "--backend", "both", "--workers", "1",
                                    "--out", str(tmp_path / "out")])
    assert "step . (opencv) did not converge" in res.output, res.output


def test_diagnose_passes_no_report_to_the_calibration(tmp_path, monkeypatch):
    seen = {}

    def record(*args, **kwargs):
        seen.update(kwargs)
        raise ValueError("recorded")

    monkeypatch.setattr(zoomcalib.diagnose.run, "diagnose_input", record)
    table = zoom_table(tmp_path / "t.csv", [1000.0, 2000.0, 3000.0, 4000.0, 5000.0])
    for extra, report in (([], True), (["--no-report"], False)):
        res = CliRunner().invoke(main, ["diagnose", str(table), "--out", str(tmp_path / "d"),
                                        *extra])
        assert res.exit_code == 1 and "recorded" in res.output, res.output
        assert seen["report"] is report


def test_a_requested_output_that_cannot_be_written_makes_the_run_partial(tmp_path):
    """The report and the ROS files are asked for (the default); where they cannot be written
    (a folder in the report's place, a file in the ros folder's) the rest is written and the run
    ends partial (exit 3), naming them."""
    folder = linked_folder(tmp_path, ["left01.jpg", "left02.jpg", "left03.jpg", "left04.jpg"])
    out = tmp_path / "c"
    (out / "report.html").mkdir(parents=True)
    (out / "ros").write_text("in the way\n")
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", CHESS, "--backend",
                                    "opencv", "--workers", "1", "--out", str(out)])
    assert res.exit_code == 3, res.output
    assert "report.html: not written" in res.output
    assert "ros/: not written" in res.output
    assert "partial result: not calibrated, skipped or not written: " in res.output
    named = res.output.split("partial result")[1]
    assert "ros/ not written" in named and "report.html not written" in named
    assert (out / "calibration.json").is_file() and any((out / "opencv").glob("*.yml"))
    res = CliRunner().invoke(main, ["calibrate", str(folder), "--pattern", CHESS, "--backend",
                                    "opencv", "--workers", "1", "--out", str(tmp_path / "c2")])
    assert res.exit_code == 0, res.output
    assert "not written" not in res.output
