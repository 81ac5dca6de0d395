"""ZoomModel.at (intrinsics at any zoom) and zoom_model_grid.csv, on seeded synthetic tables
whose truth is a known smooth function of zoom, kept here away from the model."""

import csv

import numpy as np
import pytest

from zoomcalib.calibrate.export import write_zoom_model_grid
from zoomcalib.zoom import ZoomModel

STEP_ZOOM = np.linspace(0.0, 1.0, 9)
# the hidden lens: focal length exponential in zoom, a curved principal-point path, k1 quadratic
TRUTH = {
    "fx": lambda z: 1500.0 * np.exp(1.2 * z),
    "fy": lambda z: 1502.0 * np.exp(1.2 * z),
    "cx": lambda z: 640.0 + 25.0 * z - 15.0 * z**2,
    "cy": lambda z: 360.0 - 10.0 * z,
    "k1": lambda z: -0.2 + 0.1 * z**2,
}
# per-step 1-sigma of the made-up calibrations (relative for the focal lengths)
STEP_SD = {"fx": lambda v: 0.003 * v, "fy": lambda v: 0.003 * v, "cx": lambda v: 0.5 + 0 * v,
           "cy": lambda v: 0.4 + 0 * v, "k1": lambda v: 0.005 + 0 * v}


def _noisy_model(seed: int) -> ZoomModel:
    rng = np.random.default_rng(seed)
    values, sd = {}, {}
    for name, f in TRUTH.items():
        true = f(STEP_ZOOM)
        sd[name] = STEP_SD[name](true)
        values[name] = true + rng.normal(0.0, sd[name])
    return ZoomModel.fit(STEP_ZOOM, values, sd)


def test_at_finds_the_hidden_curves_within_its_sigmas():
    # 12 seeded tables, each looked up at 5 zooms between and on the steps: the errors against
    # the truth, in units of at()'s 1-sigma, must look like unit-variance errors (the module's
    # own calibration study finds 0.84-0.87, its misfit term making it a little conservative;
    # 60 correlated draws per parameter allow 0.6-1.5) and never exceed 4.5 (p < 1e-5 for one
    # normal draw).
    lookups = np.array([0.05, 0.3, 0.5, 0.77, 1.0])
    z_scores = {name: [] for name in TRUTH}
    sd_ratio = {name: [] for name in TRUTH}
    for seed in range(12):
        model = _noisy_model(seed)
        for z in lookups:
            lens = model.at(z)
            assert not lens.extrapolated
            for name, f in TRUTH.items():
                z_scores[name].append((lens.values[name] - f(z)) / lens.sd[name])
                sd_ratio[name].append(lens.sd[name] / STEP_SD[name](f(z)))
    for name, zs in z_scores.items():
        zs = np.asarray(zs)
        assert np.abs(zs).max() < 4.5, name
        assert 0.6 < np.sqrt(np.mean(zs**2)) < 1.5, (name, np.sqrt(np.mean(zs**2)))
        # 9 steps make the curve better known, on average, than one step's calibration at
        # every lookup zoom (ends included), else the sigmas would be too loose for the
        # checks above to mean anything
        assert np.all(np.mean(np.reshape(sd_ratio[name], (12, -1)), axis=0) < 1.0), name


def test_at_gives_the_camera_matrix_and_opencv_distortion():
    model = _noisy_model(1)
    lens = model.at(0.4)
    K = lens.K
    assert K.shape == (3, 3)
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (lens.values["fx"], lens.values["fy"],
                                                    lens.values["cx"], lens.values["cy"])
    assert K[2].tolist() == [0.0, 0.0, 1.0] and K[0, 1] == K[1, 0] == 0.0
    # k1 fitted, the other four terms of the standard model not fitted: zero
    assert lens.dist.tolist() == [lens.values["k1"], 0.0, 0.0, 0.0, 0.0]


def test_at_refuses_a_zoom_outside_the_calibrated_range():
    model = _noisy_model(2)
    with pytest.raises(ValueError, match=r"zoom 1\.2 is outside the calibrated range \[0, 1\]; "
                                         "pass extrapolate=True"):
        model.at(1.2)
    with pytest.raises(ValueError, match="zoom nan is not finite"):
        model.at(float("nan"))
    lens = model.at(1.2, extrapolate=True)
    assert lens.extrapolated
    # extrapolated, the curve is known worse than at its end
    assert lens.sd["cx"] > model.at(1.0).sd["cx"]


def _read_grid(path):
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_grid_csv_holds_at_on_an_even_grid(tmp_path):
    model = _noisy_model(3)
    path = write_zoom_model_grid(tmp_path / "zoom_model_grid.csv", model, n_points=7)
    rows = _read_grid(path)
    names = list(TRUTH)
    assert list(rows[0]) == ["zoom", *names, *(f"sd_{k}" for k in names)]
    zoom = [float(r["zoom"]) for r in rows]
    assert zoom == pytest.approx(np.linspace(0.0, 1.0, 7), abs=1e-15)
    for r in rows:
        lens = model.at(float(r["zoom"]))
        for k in names:
            # written with repr: the same numbers up to the last bit of a vectorised evaluation
            assert float(r[k]) == pytest.approx(lens.values[k], rel=1e-12, abs=1e-15), k
            assert float(r[f"sd_{k}"]) == pytest.approx(lens.sd[k], rel=1e-9, abs=1e-15), k


def test_grid_csv_default_and_minimum_points(tmp_path):
    model = _noisy_model(4)
    assert len(_read_grid(write_zoom_model_grid(tmp_path / "g.csv", model))) == 50
    with pytest.raises(ValueError, match="at least 2 points; got 1"):
        write_zoom_model_grid(tmp_path / "g1.csv", model, n_points=1)
