"""Two hidden causes at once, on tables of the independent generator, are both named.

:func:`zoomcalib.diagnose.synthetic.independent_zoom_table` hides two causes, each at 6-16
times the noise with its own random direction and group, in tables whose play (0.3-3 times the
tolerance file's, Gaussian, uniform or Laplace) and reported sigmas (0.5-2 times the true ones)
are not what the diagnosis assumes; the truth stays with the test. The pairs are the ones the
diagnosis can tell apart (``docs/diagnose.md``, "Two causes at once"): every pair of the six
but axis tilt with static decentre, whose signatures are nearly one on this lens.
"""

import itertools

import numpy as np
import pytest

from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import HIDDEN_CAUSES, PLAY_DISTRIBUTIONS, independent_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription

LENS = load_prescription("laikin-10x")
NOT_TOLD_APART = {("axis_tilt", "static_decenter")}


@pytest.fixture(scope="module")
def response():
    return LensResponse.of(LENS)


def _draw(rng, pair, response):
    rows, truth = independent_zoom_table(
        LENS, rng, causes=[(c, (6.0, 16.0)) for c in pair], play_scale=(0.3, 3.0),
        play_distribution=str(rng.choice(sorted(PLAY_DISTRIBUTIONS))), sd_growth=(0.0, 2.0),
        sd_factor=(0.5, 2.0), with_focus=bool(rng.integers(2)),
        with_temperature=bool(rng.integers(2)))
    diag = diagnose_table(ZoomTable.from_rows(rows, "pair draw"), response)
    return {s.cause for s in diag.causes}, truth


def test_both_causes_of_a_pair_are_named(response):
    rng = np.random.default_rng(20261126)
    pairs = [p for p in itertools.combinations(HIDDEN_CAUSES, 2) if p not in NOT_TOLD_APART]
    # the pair the diagnosis once missed (a compensator backlash beside a thermal drift), and
    # seven drawn from the rest
    chosen = [("backlash", "thermal_drift")] + [
        pairs[i] for i in rng.choice(len(pairs), size=7, replace=False)]
    both, named_of = 0, []
    for pair in chosen:
        named, truth = _draw(rng, pair, response)
        assert [c["cause"] for c in truth["causes"]] == list(pair)
        both += set(pair) <= named
        named_of.append((pair, sorted(named)))
    # the benchmark names both in 98-100 % of such draws: 7 of 8 allows one miss (two or more
    # happen with probability about 1 % at a 98 % rate)
    assert both >= 7, named_of
