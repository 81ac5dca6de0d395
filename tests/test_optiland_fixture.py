"""Our tracers against an independent optical design package (optiland), via a committed fixture
made by tests/fixtures/make_optiland_fixture.py."""

import json
from pathlib import Path

import numpy as np
import pytest

from zoomcalib.optics.misalignment import Misalignment
from zoomcalib.optics.paraxial import effective_focal_length
from zoomcalib.optics.raytrace import trace_real

FIXTURE = json.loads((Path(__file__).parent / "data" / "optiland_fixture.json").read_text())


def _misalignment(lens, perturbation):
    dec = np.zeros((len(lens.groups), 2))
    tilt = np.zeros_like(dec)
    for name, p in perturbation.items():
        g = lens.group_index(name)
        dec[g] = p["decenter_mm"]
        tilt[g] = p["tilt_rad"]
    return Misalignment(dec, tilt)


@pytest.mark.parametrize("state", sorted(FIXTURE["states"]))
def test_paraxial_efl_matches_optiland(laikin, state):
    s = FIXTURE["states"][state]
    thickness = laikin.thickness_at(np.array(s["gaps"]))
    assert effective_focal_length(laikin, thickness) == pytest.approx(s["efl_mm"], rel=1e-8)
    # the solved compensator puts the rear focus on the image plane (optiland's BFL)
    assert s["bfl_mm"] == pytest.approx(laikin.thickness[-1], abs=1e-6)


@pytest.mark.parametrize("case", FIXTURE["cases"], ids=lambda c: f"{c['state']}-{c['name']}")
def test_real_rays_match_optiland(laikin, case):
    thickness = laikin.thickness_at(np.array(FIXTURE["states"][case["state"]]["gaps"]))
    p = np.array([r["p"] for r in FIXTURE["rays"]])  # shape (5, 3)
    d = np.array([r["d"] for r in FIXTURE["rays"]])
    rays = trace_real(laikin, thickness, p, d, _misalignment(laikin, case["perturbation"]))
    for i, traced in enumerate(case["traced"]):
        if traced:
            np.testing.assert_allclose(rays.position[i, :2], case["image_xy_mm"][i], atol=1e-9)
            np.testing.assert_allclose(rays.direction[i], case["direction"][i], atol=1e-11)
        else:
            # optiland could not trace it (missed sphere / total reflection): neither can we
            assert np.all(np.isnan(rays.position[i]))
