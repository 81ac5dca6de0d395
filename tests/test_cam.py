import numpy as np
import pytest

from zoomcalib.optics.cam import design_zooms, efl_at_zoom, focus_error, solve_gaps


def test_laikin_design_focal_lengths(laikin):
    # Published design EFLs (the prescription's note): 15.0 / 32.4 / 69.9 / 150.7 mm.
    efl = efl_at_zoom(laikin, design_zooms(laikin))
    np.testing.assert_allclose(efl, [15.0, 32.4, 69.9, 150.7], atol=0.06)


def test_nikon_design_focal_lengths(nikon):
    # The prescription's note: paraxial EFL 57.2 / 81.7 / 143.1 mm at its scale.
    efl = efl_at_zoom(nikon, design_zooms(nikon))
    np.testing.assert_allclose(efl, [57.2, 81.7, 143.1], atol=0.1)


@pytest.mark.parametrize("name", ["laikin", "nikon"])
def test_compensator_in_focus_and_on_design_branch(name, request, rng):
    lens = request.getfixturevalue(name)
    zoom = np.sort(rng.uniform(0, 1, 25))
    gaps = solve_gaps(lens, zoom)
    assert np.all(np.abs(focus_error(lens, gaps)) < 1e-9)
    np.testing.assert_allclose(gaps.sum(axis=1), lens.gap_total, atol=1e-9)
    assert np.all(gaps >= 0)
    # At the design positions the solved compensator stays within the published focus slack
    # (a few tenths of a mm), i.e. on the design branch, not the other focus solution.
    g = solve_gaps(lens, design_zooms(lens))
    assert np.max(np.abs(g[:, 2] - lens.design_gaps[:, 2])) < 0.35
    # The cam is continuous: no jump to the other branch between neighbouring states.
    fine = solve_gaps(lens, np.linspace(0, 1, 401))
    assert np.max(np.abs(np.diff(fine[:, 2]))) < 0.5


def test_zoom_out_of_range(laikin):
    with pytest.raises(ValueError, match="zoom must lie in"):
        solve_gaps(laikin, [1.2])


@pytest.mark.parametrize("name", ["laikin", "nikon"])
def test_closed_form_compensator_equals_a_root_bracketed_by_brent(name, request, rng):
    # The closed form (the focus error is a quadratic in g3) against scipy's Brent method on
    # the traced error, bracketed 0.5 mm either side of the design cam's guess.
    from scipy.optimize import brentq

    from zoomcalib.optics.cam import _gaps, variator_gap

    lens = request.getfixturevalue(name)
    zoom = rng.uniform(0, 1, 12)
    gaps = solve_gaps(lens, zoom)
    g1 = variator_gap(lens, zoom)
    for z, g, g1_z in zip(zoom, gaps, g1, strict=True):
        def error(g3, g1_z=g1_z):
            return float(focus_error(lens, _gaps(lens, np.array([g1_z]), np.array([g3])))[0])

        lo, hi = max(g[2] - 0.5, 0.0), min(g[2] + 0.5, lens.gap_total - g1_z)
        root = brentq(error, lo, hi, xtol=1e-12, rtol=1e-14)
        assert abs(root - g[2]) < 1e-9, (z, root, g[2])
