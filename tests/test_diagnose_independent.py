"""The independent generator: what it hides is in the table, and only in the truth.

:func:`zoomcalib.diagnose.synthetic.independent_zoom_table` departs from the diagnosis's
assumptions (play size and distribution, reported sigmas, several causes, an unlisted effect).
These tests check each departure from the rows and the separately returned truth, with the
columns of :mod:`zoomcalib.diagnose.model` and the play of the tolerance file as the yardsticks.
"""

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import pytest

from zoomcalib.diagnose.model import (
    Context,
    LensResponse,
    axis_tilt_term,
    covariate_term,
    design_matrix,
    direction_offset_term,
    group_term,
    offset_term,
    play_sd_px,
)
from zoomcalib.diagnose.synthetic import independent_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.mechanics import load_tolerances
from zoomcalib.optics.prescription import load_prescription

LENS = load_prescription("laikin-10x")
PITCH = 0.00645
CSV_COLUMNS = {"step", "zoom", "fx", "fy", "cx", "cy", "sd_fx", "sd_fy", "sd_cx", "sd_cy",
               "direction", "sequence", "focus", "temperature"}


def _pp(rows: list[dict]) -> np.ndarray:
    return np.array([[r["cx"], r["cy"]] for r in rows])


def _visible_rms(effect: np.ndarray) -> float:
    return float(np.sqrt(np.mean((effect - effect.mean(axis=0)) ** 2)))


@pytest.fixture(scope="module")
def response():
    # sensitivities are all the projections need; a coarse EFL grid keeps this fast
    return LensResponse.of(LENS, PITCH, n_grid=41)


def test_rows_hold_table_columns_only_and_bad_options_fail():
    rows, truth = independent_zoom_table(LENS, np.random.default_rng(1),
                                         causes=[("backlash", 8.0)], unlisted=3.0,
                                         with_focus=True, with_temperature=True)
    assert set().union(*rows) <= CSV_COLUMNS
    assert truth["causes"][0]["cause"] == "backlash" and truth["unlisted"] is not None
    with pytest.raises(ValueError, match="distinct"):
        independent_zoom_table(LENS, np.random.default_rng(1),
                               causes=[("axis_tilt", 8.0), ("axis_tilt", 9.0)])
    with pytest.raises(ValueError, match="distinct"):
        independent_zoom_table(LENS, np.random.default_rng(1), causes=[("gremlins", 8.0)])
    with pytest.raises(ValueError, match="play_distribution"):
        independent_zoom_table(LENS, np.random.default_rng(1), play_distribution="cauchy")


@pytest.mark.parametrize("factor, play_scale, distribution, growth",
                         [(0.5, 3.0, "uniform", 2.0), (2.0, 0.3, "laplace", 0.0)])
def test_misreported_sigmas_and_unknown_play_are_in_the_table(factor, play_scale, distribution,
                                                              growth):
    rows, truth = independent_zoom_table(
        LENS, np.random.default_rng(int(10 * factor)), n_zoom=12, sd_factor=factor,
        sd_growth=growth, play_scale=play_scale, play_distribution=distribution)
    pp = _pp(rows)
    reported = np.array([[r["sd_cx"], r["sd_cy"]] for r in rows])
    # the noise-only part: the table less the traced lens (locked errors and play)
    meas = pp - truth["locked_px"] - truth["play"]["effect_px"]
    # reported sd / true scatter: 96 draws of a unit normal give an RMS with a relative
    # 1-sigma of 1/sqrt(2 * 96) = 7 %, so 25 % is 3.5 sigma
    ratio = float(np.sqrt(np.mean((meas / reported) ** 2)))
    assert ratio == pytest.approx(1.0 / factor, rel=0.25)
    # the sigma grows with focal length as told: the same ratio at the wide and tele halves
    fx = np.array([r["fx"] for r in rows])
    wide = fx < np.median(fx)
    for half in (wide, ~wide):
        part = float(np.sqrt(np.mean((meas[half] / reported[half]) ** 2)))
        assert part == pytest.approx(1.0 / factor, rel=0.35)  # 48 draws: 10 %, 3.5 sigma
    ratio_sd = reported[:, 0] / reported[:, 0].min()
    assert np.allclose(ratio_sd, (fx / fx.min()) ** growth, rtol=5e-3)  # fx: 5e-4 noise
    # the play's size against the tolerance file's (the diagnosis's assumption): the
    # linearised 1-sigma of model.play_sd_px; 96 draws, as above
    assumed = play_sd_px(LENS, truth["z"], load_tolerances(), PITCH)
    scale = float(np.sqrt(np.mean((truth["play"]["effect_px"] / assumed[:, None]) ** 2)))
    assert scale == pytest.approx(play_scale, rel=0.25)


def test_play_distribution_is_not_gaussian():
    # mean |x| / RMS of unit-variance draws: 0.866 uniform, 0.798 Gaussian, 0.707 Laplace; over
    # 576 draws (2 tables x 36 rows x 2 moving groups x decentre and tilt x 2 axes) its 1-sigma is
    # 0.007, 0.009 and 0.015 (simulated), so 0.83 and 0.76 are >= 3.5 sigma from each neighbour
    tol = load_tolerances()
    ratios = {}
    for dist in ("uniform", "gaussian", "laplace"):
        x = []
        for seed in range(2):
            _, truth = independent_zoom_table(LENS, np.random.default_rng(seed), play_scale=1.7,
                                              play_distribution=dist)
            play = truth["play"]
            for g in ("variator", "compensator"):
                k = LENS.group_index(g)
                sd_dec = tol.for_group(g).play_um * 1e-3 * 1.7
                sd_tilt = tol.for_group(g).play_tilt_arcmin * np.pi / (180 * 60) * 1.7
                x += [play["decenter_mm"][:, k] / sd_dec, play["tilt_rad"][:, k] / sd_tilt]
        x = np.concatenate(x).ravel()
        assert x.size == 576 and np.sqrt(np.mean(x ** 2)) == pytest.approx(1.0, rel=0.15)
        ratios[dist] = float(np.mean(np.abs(x)) / np.sqrt(np.mean(x ** 2)))
    assert ratios["uniform"] > 0.83 and 0.76 < ratios["gaussian"] < 0.83, ratios
    assert ratios["laplace"] < 0.76, ratios


def _cause_columns(ctx: Context) -> dict[str, list[np.ndarray]]:
    groups = ctx.response.groups
    cols = {
        "axis_tilt": [axis_tilt_term()],
        "backlash": [direction_offset_term()]
        + [group_term(g, "decenter", 1, "b", signed_by="direction") for g in groups],
        "thermal_drift": [covariate_term("sequence", "capture", "d")],
        "cam_harmonic": [group_term(g, "decenter", 2, "c") for g in groups],
        "static_decenter": [group_term(g, "decenter", 0, "s") for g in groups],
    }
    if ctx.table.temperature is not None:
        cols["thermal_drift"].append(covariate_term("temperature", "K", "t"))
    if ctx.table.focus is not None:
        cols["focus_shift"] = [covariate_term("focus", "focus_unit", "f")]
    return {c: [design_matrix((t,), ctx) for t in ts] for c, ts in cols.items()}


def _captured(effect: np.ndarray, ctx: Context, sigma: np.ndarray
              ) -> tuple[dict[str, float], float]:
    """Per cause: share of the effect's chi2 beyond the baseline its columns remove; and the
    baseline's share of the whole effect's chi2."""
    w = np.repeat(1.0 / sigma, 2)
    base = design_matrix((offset_term(),) + tuple(
        group_term(g, "decenter", 1, "l") for g in ctx.response.groups), ctx)

    def rest(A: np.ndarray, y: np.ndarray) -> np.ndarray:
        return w * y - (w[:, None] * A) @ np.linalg.lstsq(w[:, None] * A, w * y, rcond=None)[0]

    y = effect.reshape(-1)
    e = rest(base, y) / w
    e2 = np.sum((w * e) ** 2)
    out = {c: max(1 - np.sum(rest(np.hstack([base, A]), e) ** 2) / e2 for A in blocks)
           for c, blocks in _cause_columns(ctx).items()}
    return out, float(1 - e2 / np.sum((w * y) ** 2))


def test_unlisted_effect_is_visible_and_no_cause_captures_it(response):
    rng = np.random.default_rng(21)
    for _ in range(2):
        rows, truth = independent_zoom_table(
            LENS, rng, causes=[("axis_tilt", 8.0)], unlisted=3.0, play_scale=(0.3, 3.0),
            sd_factor=(0.5, 2.0), with_focus=True, with_temperature=True)
        ctx = Context.build(ZoomTable.from_rows(rows), truth["z"], response)
        sigma = np.hypot(truth["sd"]["true_px"], truth["play"]["sd_px"])  # the true noise
        effect = truth["unlisted"]["effect_px"]
        assert _visible_rms(effect) == pytest.approx(3.0 * truth["noise_rms_px"], rel=1e-9)
        captured, by_baseline = _captured(effect, ctx, sigma)
        assert by_baseline < 1e-9  # all of it is beyond the baseline
        assert max(captured.values()) <= 0.5 + 1e-3, captured  # 1e-3: measured vs true fx
        for cause, frac in captured.items():
            assert frac == pytest.approx(truth["unlisted"]["captured"][cause], abs=1e-3)
        assert truth["unlisted"]["captured"]["pair"] >= max(captured.values()) - 1e-9
        # the same yardstick finds a listed cause: the hidden axis tilt is all axis_tilt's
        tilt, _ = _captured(truth["causes"][0]["effect_px"], ctx, sigma)
        assert tilt["axis_tilt"] > 0.99


@pytest.mark.parametrize("pair", [(("cam_harmonic", 10.0), ("static_decenter", 7.0)),
                                  (("backlash", 12.0), ("thermal_drift", 6.0)),
                                  (("axis_tilt", 8.0), ("backlash", 12.0))])
def test_two_cause_tables_hold_both_effects(pair, response):
    rows, truth = independent_zoom_table(LENS, np.random.default_rng(5), causes=list(pair),
                                         play_scale=2.0, sd_factor=0.7, unlisted=2.0)
    rest = (truth["locked_px"] + truth["play"]["effect_px"] + truth["unlisted"]["effect_px"]
            + truth["measurement_noise_px"])
    effects = [c["effect_px"] for c in truth["causes"]]
    assert [c["cause"] for c in truth["causes"]] == [p[0] for p in pair]
    assert np.allclose(_pp(rows) - rest, effects[0] + effects[1], rtol=0, atol=1e-9)
    ctx = Context.build(ZoomTable.from_rows(rows), truth["z"], response)
    sigma = np.hypot(truth["sd"]["true_px"], truth["play"]["sd_px"])
    for (cause, m), effect in zip(pair, effects, strict=True):
        # each at its magnitude; a mechanical cause is scaled by its response to 1 um, and the
        # exact tracer is linear in 10 um to better than 1 %
        assert _visible_rms(effect) / truth["noise_rms_px"] == pytest.approx(m, rel=0.01)
        captured, _ = _captured(effect, ctx, sigma)
        assert captured[cause] > 0.97, (cause, captured)
        other = next(o for o, _ in pair if o != cause)
        assert captured[other] < 0.9, (cause, other, captured)


def test_benchmark_reads_old_and_new_diagnosis_documents():
    """The benchmark's one adapter: the single ``cause`` of today's document (which claims to
    explain the data), and a list of ``causes`` with an ``explained`` verdict."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "diagnose_independent.py"
    spec = importlib.util.spec_from_file_location("diagnose_independent", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.read_diagnosis({"cause": "none"}) == ([], True)
    assert bench.read_diagnosis({"cause": "backlash"}) == (["backlash"], True)
    doc = {"cause": "backlash", "causes": [{"cause": "backlash"}, {"cause": "axis_tilt"}],
           "explained": {"explained": False}}
    assert bench.read_diagnosis(doc) == (["backlash", "axis_tilt"], False)
    assert bench.read_diagnosis({"cause": "none", "causes": [],
                                 "explained": {"explained": True}}) == ([], True)


def test_unlisted_effect_can_be_kept_from_every_pair_of_causes(response):
    """Two causes together capture more of a curve than either; the option bounds that too."""
    rows, truth = independent_zoom_table(LENS, np.random.default_rng(8), unlisted=3.0,
                                         max_captured_pair=0.5, with_temperature=True)
    ctx = Context.build(ZoomTable.from_rows(rows), truth["z"], response)
    sigma = np.hypot(truth["sd"]["true_px"], truth["play"]["sd_px"])
    blocks = _cause_columns(ctx)
    w = np.repeat(1.0 / sigma, 2)
    base = design_matrix((offset_term(),) + tuple(
        group_term(g, "decenter", 1, "l") for g in ctx.response.groups), ctx)
    e = truth["unlisted"]["effect_px"].reshape(-1)
    e2 = np.sum((w * e) ** 2)  # the effect has no baseline part (checked above)
    best = 0.0
    for c1, c2 in itertools.combinations(blocks, 2):
        for a1 in blocks[c1]:
            for a2 in blocks[c2]:
                A = w[:, None] * np.hstack([base, a1, a2])
                r = w * e - A @ np.linalg.lstsq(A, w * e, rcond=None)[0]
                best = max(best, 1 - np.sum(r ** 2) / e2)
    assert best <= 0.5 + 1e-3  # 1e-3: measured vs true fx, as above
    assert best == pytest.approx(truth["unlisted"]["captured"]["pair"], abs=1e-3)
