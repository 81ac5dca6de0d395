"""An interrupted calibrate run, rerun, writes the same files as one uninterrupted run."""

import json
import shutil
from pathlib import Path

import pytest

from zoomcalib.calibrate.run import calibrate_folder

SAMPLES = Path(__file__).parent / "data" / "opencv-samples"
SPEC = "chessboard:9x6:25"


def _zoom_set(root: Path) -> Path:
    """Three 'zoom steps' of the real sample images (the same camera: zoom from the names)."""
    images = sorted(SAMPLES.glob("left*.jpg"))
    for k, step in enumerate(("zoom_1", "zoom_2", "zoom_3")):
        (root / step).mkdir(parents=True)
        for f in images[k::3] + images[(k + 1) % 3::3][:2]:
            shutil.copy(f, root / step / f.name)
    return root


class _Interrupt:
    """A progress callback that interrupts the run after ``after`` images."""

    def __init__(self, after: int):
        self.left = after

    def __call__(self, n: int) -> None:
        self.left -= n
        if self.left <= 0:
            raise KeyboardInterrupt


def _contents(out: Path) -> dict[str, bytes]:
    files = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # what legitimately differs: the manifest's command record, and calibration.json's account
    # of which detections were reused; the calibration results themselves must not
    files.pop("manifest.json")
    doc = json.loads(files.pop("calibration.json"))
    files["calibration.json#steps"] = json.dumps(doc["steps"], sort_keys=True).encode()
    return files


def test_interrupted_and_rerun_equals_one_run(tmp_path):
    images = _zoom_set(tmp_path / "set")
    calibrate_folder(images, SPEC, tmp_path / "once", ("opencv",), log=lambda m: None)
    with pytest.raises(KeyboardInterrupt):
        calibrate_folder(images, SPEC, tmp_path / "twice", ("opencv",), log=lambda m: None,
                         progress=_Interrupt(after=9))
    # the first step's detections were kept; the rerun detects the rest
    assert len(list((tmp_path / "twice" / "detections").glob("*.json"))) >= 1
    log: list[str] = []
    calibrate_folder(images, SPEC, tmp_path / "twice", ("opencv",), log=log.append)
    assert any("reused the cached detections" in m for m in log)
    once, twice = _contents(tmp_path / "once"), _contents(tmp_path / "twice")
    assert sorted(once) == sorted(twice)
    for name in once:
        assert once[name] == twice[name], name


def test_detections_linked_from_another_run_are_reused(tmp_path):
    # a user links the detections folder of an earlier run into a new output folder: the
    # run reuses them and lists them in the manifest where they are used
    images = _zoom_set(tmp_path / "set")
    calibrate_folder(images, SPEC, tmp_path / "first", ("opencv",), log=lambda m: None,
                     zoom_wide=False, report=False)
    (tmp_path / "second").mkdir()
    (tmp_path / "second" / "detections").symlink_to(tmp_path / "first" / "detections")
    log: list[str] = []
    calibrate_folder(images, SPEC, tmp_path / "second", ("opencv",), log=log.append,
                     zoom_wide=False, report=False)
    assert any("reused the cached detections" in m for m in log)
    listed = json.loads((tmp_path / "second" / "manifest.json").read_text())["files"]
    assert any(f.startswith("detections/") for f in listed), listed
