import json

import numpy as np
import pytest

from zoomcalib.camera import DEFAULT_SENSOR
from zoomcalib.optics.mechanics import (
    ARCMIN,
    GroupTolerance,
    ToleranceError,
    Tolerances,
    draw_misalignment,
    load_tolerances,
    systematic_misalignment,
)
from zoomcalib.optics.principal_point import principal_point_scatter, sensitivity_rows


def test_default_tolerances_are_of_practical_order(laikin):
    tol = load_tolerances(None, laikin)
    for g in ("variator", "compensator"):
        t = tol.for_group(g)
        assert 10 <= t.locked_decenter_um <= 20
        assert 0.5 <= t.locked_tilt_arcmin <= 2
        assert 2 <= t.play_um <= 8
        assert 1 <= t.backlash_um <= 8


def test_locked_error_turns_with_barrel(laikin):
    tol = Tolerances({"variator": GroupTolerance(locked_decenter_um=12.0,
                                                 locked_decenter_phase_deg=30.0)})
    zoom = np.array([0.0, 0.125, 0.25, 0.5, 1.0])
    mis = systematic_misalignment(laikin, tol, zoom)
    d = mis.decenter[:, 1] * 1e3  # um, shape (Z, 2)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 12.0)
    angles = np.rad2deg(np.arctan2(d[:, 1], d[:, 0]))
    # two turns over the range: 45 deg of barrel per 1/16 of zoom; zoom 0.5 and 1 are full turns
    np.testing.assert_allclose(angles, [30, 120, -150, 30, 30], atol=1e-9)
    assert np.all(mis.decenter[:, [0, 2, 3]] == 0)


def test_backlash_flips_with_direction(laikin):
    tol = Tolerances({"compensator": GroupTolerance(backlash_um=6.0)})
    d_in = systematic_misalignment(laikin, tol, [0.3], "in").decenter[0, 2]
    d_out = systematic_misalignment(laikin, tol, [0.3], "out").decenter[0, 2]
    np.testing.assert_allclose(d_in, -d_out)
    assert np.linalg.norm(d_in) == pytest.approx(3e-3)


def test_draws_are_reproducible(laikin):
    tol = load_tolerances(None, laikin)
    zoom = np.linspace(0, 1, 5)
    a = draw_misalignment(laikin, tol, zoom, 100, seed=7)
    np.testing.assert_array_equal(a.decenter, draw_misalignment(laikin, tol, zoom, 100, 7).decenter)
    assert not np.allclose(a.decenter, draw_misalignment(laikin, tol, zoom, 100, 8).decenter)


def test_play_scatter_matches_sensitivity(laikin, rng):
    # Hidden truth: a play sigma drawn at random; the exact-traced Monte Carlo must recover the
    # scatter predicted by the paraxial sensitivity, within the sampling error of a std.
    sigma_um = rng.uniform(2, 20)
    zoom = rng.uniform(0, 1, 3)
    tol = Tolerances({"compensator": GroupTolerance(play_um=sigma_um)})
    n = 4000
    res = principal_point_scatter(laikin, tol, zoom, n, seed=int(rng.integers(1 << 31)))
    s_d = np.array([r["shift_per_decenter"] for r in sensitivity_rows(laikin, zoom)
                    if r["group"] == "compensator"])
    expected = np.abs(s_d) * sigma_um * 1e-3 / DEFAULT_SENSOR.pixel_pitch_mm  # px
    # relative sd of a sample std is 1/sqrt(2(n-1)); allow 4 sigma
    np.testing.assert_allclose(res.std_px, np.repeat(expected[:, None], 2, 1),
                               rtol=4 / np.sqrt(2 * (n - 1)))
    np.testing.assert_allclose(res.mean_px, DEFAULT_SENSOR.centre_px + 0 * res.mean_px,
                               atol=5 * expected.max() / np.sqrt(n))


@pytest.mark.parametrize("tracer", ["paraxial", "exact"])
def test_scatter_scales_linearly_with_tolerance(laikin, tracer):
    tol = load_tolerances(None, laikin)
    zoom = [0.1, 0.6, 0.95]
    base = principal_point_scatter(laikin, tol, zoom, 300, seed=3, tracer=tracer)
    for k in (0.5, 3.0):
        scaled = principal_point_scatter(laikin, tol.scaled(k), zoom, 300, seed=3, tracer=tracer)
        rtol = 1e-9 if tracer == "paraxial" else 2e-3
        np.testing.assert_allclose(scaled.std_px, k * base.std_px, rtol=rtol)
        np.testing.assert_allclose(scaled.mean_px - DEFAULT_SENSOR.centre_px,
                                   k * (base.mean_px - DEFAULT_SENSOR.centre_px),
                                   rtol=rtol, atol=1e-9)


def test_zero_tolerances_give_zero_scatter(laikin):
    res = principal_point_scatter(laikin, Tolerances.zero(), [0.0, 0.5, 1.0], 50, seed=1)
    np.testing.assert_allclose(res.std_px, 0, atol=1e-9)
    np.testing.assert_allclose(res.mean_px, np.tile(DEFAULT_SENSOR.centre_px, (3, 1)), atol=1e-9)


def test_tilt_units(laikin):
    tol = Tolerances({"variator": GroupTolerance(static_tilt_arcmin=(60.0, 0.0))})
    mis = systematic_misalignment(laikin, tol, [0.2])
    assert mis.tilt[0, 1, 0] == pytest.approx(60 * ARCMIN)
    assert mis.tilt[0, 1, 0] == pytest.approx(np.deg2rad(1.0))


@pytest.mark.parametrize("text, name, field", [
    ("groups:\n  variator:\n    play_um: -3\n", "t.yaml", "groups.variator.play_um"),
    ("groups:\n  variator:\n    wobble_um: 3\n", "t.yaml", "groups.variator.wobble_um"),
    ("groups:\n  zoomgroup:\n    play_um: 3\n", "t.yaml", "groups.zoomgroup"),
    ("groups:\n  variator:\n    static_decenter_um: 3\n", "t.yaml",
     "groups.variator.static_decenter_um"),
    (json.dumps({"groups": {"compensator": {"backlash_um": "big"}}}), "t.json",
     "groups.compensator.backlash_um"),
    ("variator: {play_um: 3}\n", "t.yaml", "groups"),
    ("groups: [\n", "t.yaml", "not valid"),
])
def test_bad_tolerance_files(tmp_path, laikin, text, name, field):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(ToleranceError) as info:
        load_tolerances(p, laikin)
    assert str(p) in str(info.value) and field in str(info.value)
    assert "\n" not in str(info.value)
