"""End to end: a rendered zoom sweep with a wavy board, an Airy PSF and JPEG frames, through
``zoomcalib calibrate`` with default settings (and ``--cross-validate``); truth hidden in
``truth.json``, which only this test reads."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from zoomcalib.calibrate.io import read_zoom_table
from zoomcalib.cli import main
from zoomcalib.render.sweep import render_zoom_sweep


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    seed = int(np.random.default_rng(11).integers(1 << 16))
    render_zoom_sweep(root / "images", fx_range=(1800.0, 9000.0), steps=4, views=8,
                      size=(960, 540), pattern="chessboard:16x10:20", board_surface=0.3,
                      psf="airy", supersample=2, jpeg_quality=90, seed=seed)
    out = root / "out"
    res = CliRunner().invoke(main, ["calibrate", str(root / "images"), "--pattern",
                                    "chessboard:16x10:20", "--cross-validate", "--workers", "1",
                                    "--out", str(out)])
    truth = json.loads((root / "images" / "truth.json").read_text())
    return res, out, truth


def test_default_calibration_of_a_rendered_sweep_is_within_its_sigmas(rendered):
    res, out, truth = rendered
    assert res.exit_code == 0, res.output
    rows = {r["step"]: r for r in read_zoom_table(out / "zoom_calibration.csv")}
    assert {r["backend"] for r in rows.values()} == {"zoom-wide"}
    assert {r["mode"] for r in rows.values()} == {"zoom-wide"}
    z = []
    for step in truth["steps"]:
        K = np.asarray(step["K"])
        row = rows[step["step"]]
        assert abs(row["fx"] / K[0, 0] - 1) < 0.003, (step["step"], row["fx"], K[0, 0])
        for q, true in (("cx", K[0, 2]), ("cy", K[1, 2])):
            # 4 combined sigma; the sigma itself must be small enough to be useful
            assert abs(row[q] - true) < 4 * row[f"sd_{q}"], (step["step"], q, row[q], true)
            assert row[f"sd_{q}"] < 5.0
            z.append((row[q] - true) / row[f"sd_{q}"])
    # and not too wide: for honest sigmas an RMS z below 0.3 has a probability under 1e-3
    assert np.sqrt(np.mean(np.square(z))) > 0.3, np.round(z, 2)


def test_cross_validation_is_reported_everywhere(rendered):
    res, out, truth = rendered
    doc = json.loads((out / "calibration.json").read_text())
    cv = doc["meta"]["cross_validation"]
    assert cv["backend"] == "zoom-wide"
    assert set(cv["steps"]) == {s["step"] for s in truth["steps"]}
    z = [v for step in cv["steps"].values() for v in step["z"].values()]
    assert all(abs(v) < 4.0 for v in z), z
    assert np.sqrt(np.mean(np.square(z))) > 0.3, z  # both ways, as above
    assert "cross-validation (zoom-wide" in res.output
    # the report's even/odd map carries a verdict for every step, that of the z above
    html = (out / "report.html").read_text()
    assert html.count("Verdict: the halves agree.") == len(truth["steps"]), html.count("Verdict")

    assert (out / "cross_validation.png").stat().st_size > 10_000


def test_zoom_model_of_the_principal_point_is_reported(rendered):
    _, out, _ = rendered
    models = json.loads((out / "calibration.json").read_text())["meta"]["zoom_wide"]["zoom_model"]
    for q in ("cx", "cy"):  # the default: the angular second-difference prior, REML tau
        assert models[q]["model"] == "angle2" and models[q]["order"] == 2
        assert models[q]["tau"] > 0


def test_the_zoom_model_is_the_adjustments_own_posterior(rendered):
    # at each step's zoom the model written to zoom_model.json gives that step's row: the
    # rows are not refitted as if the prior had not smoothed them
    from zoomcalib.calibrate.zoompath import PosteriorZoomModel

    _, out, _ = rendered
    doc = json.loads((out / "zoom_model.json").read_text())
    model = PosteriorZoomModel.from_dict(doc["model"])
    rows = read_zoom_table(out / "zoom_calibration.csv")
    for row in rows:
        lens = model.at(row["zoom"])
        for q in ("fx", "fy", "cx", "cy"):
            assert abs(lens.values[q] - row[q]) < 1e-6 * row[f"sd_{q}"], (row["step"], q)
    assert set(doc["holdout_rms"]) >= {"fx", "cx", "cy"}
    grid = (out / "zoom_model_grid.csv").read_text().splitlines()
    assert grid[0].startswith("zoom,fx,fy,cx,cy") and len(grid) == 51


def test_the_halves_verdict_says_which_side_of_the_limit():
    from zoomcalib.calibrate.report import halves_verdict

    assert "agree" in halves_verdict(2.9, "10") and "disagree" in halves_verdict(3.1, "10")
    assert "3.10 of their sigmas" in halves_verdict(3.1, "10")
    assert halves_verdict(None, "10") == "" and halves_verdict(float("nan"), "10") == ""


def test_the_solve_without_the_prior_is_written_beside_the_table(rendered):
    # its rows are the steps' own (no prior): within 4 of their sigmas of the rendered truth,
    # their sigmas no smaller than the adjustment's (the prior only adds information), and
    # their correlation with other steps reported
    import json

    res, out, truth = rendered
    rows = {r["step"]: r for r in read_zoom_table(out / "zoom_calibration_unsmoothed.csv")}
    smoothed = {r["step"]: r for r in read_zoom_table(out / "zoom_calibration.csv")}
    free = json.loads((out / "calibration.json").read_text())["meta"]["zoom_wide"]["unsmoothed"]
    assert set(rows) == {s["step"] for s in truth["steps"]} == set(free)
    for step in truth["steps"]:
        K, row = np.asarray(step["K"]), rows[step["step"]]
        assert row["mode"] == "zoom-wide, no prior"
        for q, true in (("cx", K[0, 2]), ("cy", K[1, 2])):
            assert abs(row[q] - true) < 4 * row[f"sd_{q}"], (step["step"], q, row[q], true)
            assert row[f"sd_{q}"] >= 0.99 * smoothed[step["step"]][f"sd_{q}"]
        assert 0.0 <= free[step["step"]]["step_correlation"]["cy"] < 1.0
    # the correlation of those rows' principal points, beside them: a correlation matrix
    # whose largest cy entry between two steps is the one calibration.json gives
    from zoomcalib.calibrate.io import read_principal_point_correlation
    from zoomcalib.diagnose.run import load_zoom_table

    steps = [s["step"] for s in truth["steps"]]
    corr = read_principal_point_correlation(out / "zoom_calibration_unsmoothed_correlation.json",
                                            steps)
    for i, step in enumerate(steps):
        others = [2 * j + 1 for j in range(len(steps)) if j != i]
        assert np.max(np.abs(corr[2 * i + 1, others])) == pytest.approx(
            free[step]["step_correlation"]["cy"], rel=1e-9, abs=1e-12)
    loaded = load_zoom_table(out / "zoom_calibration_unsmoothed.csv")
    np.testing.assert_array_equal(loaded.pp_correlation, read_principal_point_correlation(
        out / "zoom_calibration_unsmoothed_correlation.json", loaded.step))
