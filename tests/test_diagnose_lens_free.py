"""diagnose without a lens model, and the noise scales it estimates.

The tables here come from a generator written for these tests, unlike the diagnosis's models:
the principal-point path is a sum of sinusoids in log zoom (the diagnosis fits Legendre
polynomials), the backlash offset grows with focal length (the diagnosis's lens-free variants
are direction-signed polynomials), the drift is an exponential warm-up in capture order (the
diagnosis fits a line), and the measurement sigmas grow as fx^0.7.
"""

import numpy as np
import pytest
from click.testing import CliRunner

from zoomcalib.cli import main
from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.noise import NoiseShape, estimate_noise
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.io import read_json, write_csv


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=2)
    return v / np.linalg.norm(v)


def _scaled(effect: np.ndarray, magnitude: float, noise_rms: float) -> np.ndarray:
    """``effect`` less its mean, scaled to ``magnitude`` times the RMS noise (RMS over rows)."""
    effect = effect - effect.mean(axis=0)
    return effect * magnitude * noise_rms / np.sqrt(np.mean(np.sum(effect ** 2, axis=1)))


def real_like_table(rng, backlash: bool, drift: bool, n_zoom: int = 10,
                    passes: int = 2) -> list[dict]:
    """A PTZ-like zoom table: sweeps in and out, 1x-10x, causes at 6-16x the noise."""
    zooms = np.linspace(1.0, 10.0, n_zoom)
    zoom = np.tile(np.concatenate([zooms, zooms[::-1]]), passes)
    direction = np.tile(np.repeat([1.0, -1.0], n_zoom), passes)
    fx = 1200.0 * zoom ** 1.05
    u = np.log(zoom) / np.log(10.0)
    amp, phase, freq = rng.uniform(5, 15, 2), rng.uniform(0, 2 * np.pi, 2), rng.uniform(0.5, 1.2, 2)
    path = np.stack([(640.0, 360.0)[i] + amp[i] * np.sin(2 * np.pi * freq[i] * u + phase[i])
                     for i in range(2)], axis=-1)
    sd = 0.4 * (fx / fx.min()) ** 0.7
    noise_rms = float(np.sqrt(np.mean(sd ** 2)))
    sequence = np.arange(len(zoom), dtype=float)
    pp = path + rng.standard_normal(path.shape) * sd[:, None]
    if backlash:
        grows = direction[:, None] * (0.5 + 0.5 * fx / fx.max())[:, None] * _unit(rng)
        pp += _scaled(grows, rng.uniform(6, 16), noise_rms)
    if drift:
        warm = (1.0 - np.exp(-sequence / 15.0))[:, None] * _unit(rng)
        pp += _scaled(warm, rng.uniform(6, 16), noise_rms)
    return [{"step": f"s{k:02d}", "zoom": zoom[k], "fx": fx[k], "fy": fx[k], "cx": pp[k, 0],
             "cy": pp[k, 1], "sd_cx": sd[k], "sd_cy": sd[k],
             "direction": "in" if direction[k] > 0 else "out", "sequence": sequence[k]}
            for k in range(len(zoom))]


@pytest.mark.parametrize("backlash,drift", [(True, False), (False, True), (True, True),
                                            (False, False)])
def test_lens_free_names_backlash_and_drift(backlash, drift):
    rng = np.random.default_rng(40 + 2 * backlash + drift)
    hidden = {name for name, on in (("backlash", backlash), ("thermal_drift", drift)) if on}
    n_draws, right, explained = 6, 0, 0
    for _ in range(n_draws):
        diag = diagnose_table(ZoomTable.from_rows(real_like_table(rng, backlash, drift)), None)
        named = {s.cause for s in diag.causes}
        right += named == hidden
        explained += diag.explained["explained"] is True
        assert diag.cause != "axis_tilt" and "axis_tilt" in diag.skipped
    # the hidden causes, and only they, named in at least 5 of 6 draws: at 6x the noise a
    # cause is rarely missed
    assert right >= 5, right
    # one cause (or none) is explained by the lens-free models, up to the F-tests' 1 % false
    # alarms; two at once at up to 16x the noise can leave a detectable misfit of the
    # lens-free shapes (a polynomial drift for a warm-up exponential), which is reported
    if len(hidden) < 2:
        assert explained >= 5, explained


def test_lens_free_cli(tmp_path):
    rows = real_like_table(np.random.default_rng(3), backlash=True, drift=False)
    write_csv(tmp_path / "t.csv", rows)
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "t.csv"), "--lens", "none",
                                    "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert "cause: backlash" in res.output and "not tested: cam_harmonic" in res.output
    doc = read_json(tmp_path / "o" / "diagnosis.json")
    assert doc["lens"] == "none" and doc["pixel_pitch_mm"] is None
    assert [c["cause"] for c in doc["causes"]] == ["backlash"]
    assert doc["explained"]["explained"] is True
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path / "t.csv"), "--lens", "none",
                                    "--tolerances", str(tmp_path / "t.csv"),
                                    "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "needs a lens model" in res.output


def test_noise_scales_are_recovered():
    """REML finds a hidden sigma scale and play scale from the scatter of a linear model's
    residuals: 60 seeded problems, each 200 rows; the errors of log s and log p over their
    reported 1-sigma must look like standard normals (RMS 0.6-1.5, none beyond 4.5)."""
    rng = np.random.default_rng(8)
    z_errors = []
    for _ in range(60):
        n = 200
        x = np.linspace(-1, 1, n)
        design = np.zeros((2 * n, 4))
        design[0::2, 0] = design[1::2, 1] = 1.0
        design[0::2, 2] = design[1::2, 3] = x
        measured = (0.2 + rng.uniform(0, 1, n)) ** 2  # reported sd^2
        play = (0.3 * np.exp(1.5 * x)) ** 2
        s_true, p_true = np.exp(rng.uniform(-0.7, 0.7, 2))
        sd = np.sqrt(s_true ** 2 * measured + p_true ** 2 * play)
        y = design @ rng.normal(0, 5, 4) + np.repeat(sd, 2) * rng.standard_normal(2 * n)
        fit = estimate_noise(design, y, NoiseShape(measured, play, True, True))
        assert fit.converged
        z_errors += [(np.log(fit.sigma_scale) - np.log(s_true)) / fit.sigma_scale_sd_log,
                     (np.log(fit.play_scale) - np.log(p_true)) / fit.play_scale_sd_log]
    z_errors = np.array(z_errors)
    assert np.all(np.abs(z_errors) < 4.5)
    assert 0.6 < np.sqrt(np.mean(z_errors ** 2)) < 1.5
