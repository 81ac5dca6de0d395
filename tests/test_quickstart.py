"""The README's quick start: the bundled sweep (``data/synthetic/sweep``, rendered with its truth
by ``zoomcalib render-sweep``) calibrates to that truth, every step ``ok``."""

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from zoomcalib.cli import main

SWEEP = Path(__file__).resolve().parents[1] / "data" / "synthetic" / "sweep"


def test_the_bundled_sweep_calibrates_to_its_truth(tmp_path):
    out = tmp_path / "example-calibration"
    res = CliRunner().invoke(main, ["calibrate", str(SWEEP), "--pattern", "chessboard:9x6:25",
                                    "--out", str(out), "--workers", "1"])
    assert res.exit_code == 0, res.output
    assert (out / "report.html").stat().st_size > 0
    truth = {s["step"]: s["camera"] for s in json.loads((SWEEP / "truth.json").read_text())
             ["steps"]}
    cal = json.loads((out / "calibration.json").read_text())
    z = []
    for step, camera in truth.items():
        row = cal["steps"][step]["zoom-wide"]
        assert cal["meta"]["status"][step]["status"] == "ok", step
        (fx, _, cx), (_, _, cy) = row["K"][0], row["K"][1]
        z += [(got - camera[q]) / row["sd"][q]
              for q, got in (("fx", fx), ("cx", cx), ("cy", cy))]
    # 3 steps x 3 parameters against the renderer's truth: honest sigmas keep every |z| within
    # 4 (a 1-in-10^4 event per value under the model) and are not ten times too wide
    assert np.max(np.abs(z)) < 4 and np.sqrt(np.mean(np.square(z))) > 0.1, z
