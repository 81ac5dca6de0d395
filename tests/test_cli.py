import csv

import numpy as np
from click.testing import CliRunner

from zoomcalib.cli import main
from zoomcalib.optics.mechanics import load_tolerances
from zoomcalib.optics.principal_point import principal_point_scatter


def test_simulate_writes_contract_files(tmp_path, laikin):
    out = tmp_path / "sim"
    res = CliRunner().invoke(main, ["simulate", "--steps", "4", "--samples", "40", "--seed", "5",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    with (out / "principal_point.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["zoom", "efl_mm", "fx_px", "cx_mean", "cy_mean", "cx_std", "cy_std"]
    assert len(rows) == 4
    with (out / "sensitivity.csv").open() as fh:
        sens = list(csv.DictReader(fh))
    assert list(sens[0]) == ["zoom", "efl_mm", "group", "shift_per_decenter",
                             "shift_per_tilt_um_per_mrad"]
    assert {r["group"] for r in sens} == {"G1", "variator", "compensator", "relay"}
    assert (out / "spiral.png").stat().st_size > 10_000
    # the file holds what the library computes for the same seed
    ref = principal_point_scatter(laikin, load_tolerances(None, laikin), np.linspace(0, 1, 4), 40,
                                  seed=5)
    np.testing.assert_allclose([float(r["cx_std"]) for r in rows], ref.std_px[:, 0], rtol=1e-8)
    assert "wrote" in res.output


def test_simulate_bad_inputs_give_one_line_errors(tmp_path):
    bad = tmp_path / "broken.json"
    bad.write_text('{"surfaces": 3}')
    res = CliRunner().invoke(main, ["simulate", "--lens", str(bad), "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "broken.json: field 'surfaces'" in res.output
    assert "Traceback" not in res.output
    tol = tmp_path / "tol.yaml"
    tol.write_text("groups:\n  variator:\n    play_um: lots\n")
    res = CliRunner().invoke(main, ["simulate", "--tolerances", str(tol), "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "tol.yaml: field 'groups.variator.play_um'" in res.output


def test_target_and_render_commands(tmp_path):
    import json

    import cv2

    res = CliRunner().invoke(main, ["target", "acircles:4x5:20", "--dpi", "100",
                                    "--out", str(tmp_path / "t")])
    assert res.exit_code == 0, res.output
    geo = json.loads((tmp_path / "t.json").read_text())
    assert len(geo["object_points"]) == 20
    h, w = cv2.imread(str(tmp_path / "t.png")).shape[:2]
    assert w == 709 and h > 473  # the 180 x 120 mm board at 100 dpi, its legend below
    res = CliRunner().invoke(main, ["target", "hexagons:3x3:1", "--out", str(tmp_path / "u")])
    assert res.exit_code == 2 and "not understood" in res.output

    out = tmp_path / "set"
    res = CliRunner().invoke(main, ["render", "--zoom", "0.2", "--views", "1", "--seed", "4",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "dataset.json").read_text())
    view = doc["steps"][0]["views"][0]
    img = cv2.imread(str(out / view["file"]), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (960, 1280)
    pts = np.array(view["points_px"])
    # truth lies on X-junctions: dark and bright quadrants around each point
    i, j = np.round(pts[len(pts) // 2]).astype(int)
    patch = img[j - 6:j + 7, i - 6:i + 7].astype(float)
    assert patch.max() - patch.min() > 100
    with (out / "steps.csv").open() as fh:
        assert fh.readline().strip().split(",")[:3] == ["step", "zoom", "direction"]


def test_detect_command_reports_error_against_truth(tmp_path):
    import json
    from pathlib import Path

    example = Path(__file__).parents[1] / "data" / "synthetic" / "example"
    out = tmp_path / "det.json"
    res = CliRunner().invoke(main, ["detect", str(example), "--pattern", "chessboard:9x6:25",
                                    "--method", "sb", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["pattern"] == "chessboard:9x6:25"
    assert [im["file"] for im in doc["images"]][0] == "zoom_00/view_00.png"
    assert all(im["error"] is None and len(im["ids"]) == 54 for im in doc["images"])
    rms = float(res.output.split("RMS ")[1].split(" px")[0])
    assert rms < 0.3  # a misordered board or a half-pixel slip would be far larger
