"""An interrupted diagnosis of an image folder, rerun, writes the same files as one run."""

import json
import shutil

import numpy as np
import pytest

from zoomcalib.camera import Sensor
from zoomcalib.diagnose.run import diagnose_input
from zoomcalib.render.dataset import render_dataset


def _contents(root):
    files = {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*")
             if p.is_file()}
    # what legitimately differs: the calibrate manifest's command record and its account of
    # reused detections; the calibration results and the diagnosis must not
    files.pop("calibration/manifest.json")
    doc = json.loads(files.pop("calibration/calibration.json"))
    files["calibration/calibration.json#steps"] = json.dumps(doc["steps"], sort_keys=True).encode()
    return files


def test_interrupted_diagnosis_rerun_equals_one_run(tmp_path, laikin):
    sensor = Sensor(320, 240, 0.0258)
    render_dataset(laikin, None, tmp_path / "set", list(np.linspace(0.0, 0.5, 5)), 4,
                   "chessboard:9x6:25", seed=6, sensor=sensor, direction="in")
    args = (laikin, sensor.pixel_pitch_mm, None, "chessboard:9x6:25", ("opencv",))
    out = tmp_path / "diag"  # one folder for both runs: the report names its table's path
    diagnose_input(tmp_path / "set", out, *args, workers=1, log=lambda m: None)
    once = _contents(out)
    shutil.rmtree(out)

    def interrupt(n, left=[9]):  # noqa: B006 (a counter shared across calls)
        left[0] -= n
        if left[0] <= 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        diagnose_input(tmp_path / "set", out, *args, workers=1, progress=interrupt,
                       log=lambda m: None)
    diagnose_input(tmp_path / "set", out, *args, workers=1, log=lambda m: None)
    twice = _contents(out)
    assert once.keys() == twice.keys()
    assert [k for k in once if once[k] != twice[k]] == []
