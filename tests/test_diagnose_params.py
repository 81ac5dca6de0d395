"""Each selected cause reports its own parameters, also when two causes of one group share
parameter names (a static decentre and a cam harmonic of the variator both have
``variator_x_um``, ``variator_y_um``).

Both are hidden in one table of the independent generator
(:func:`zoomcalib.diagnose.synthetic.independent_zoom_table`), each at 8-16 times the noise
in its own random direction; the test draws tables from a seeded generator until both causes
fell on the variator, and keeps their truth apart from the diagnosis."""

import numpy as np

from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import independent_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription


def _both_on_the_variator(lens, rng):
    for _ in range(60):
        rows, truth = independent_zoom_table(
            lens, rng, causes=[("static_decenter", (8.0, 16.0)), ("cam_harmonic", (8.0, 16.0))])
        if all(c["group"] == "variator" for c in truth["causes"]):
            return rows, {c["cause"]: c["params"] for c in truth["causes"]}
    raise AssertionError("no draw put both causes on the variator")


def test_causes_sharing_parameter_names_keep_their_own_values():
    lens = load_prescription("laikin-10x")
    rows, truth = _both_on_the_variator(lens, np.random.default_rng(20261127))
    d = diagnose_table(ZoomTable.from_rows(rows, "draw"), LensResponse.of(lens))
    by_cause = {s.cause: s for s in d.causes}
    # both named, with the same parameter names
    assert set(by_cause) == {"static_decenter", "cam_harmonic"}, list(by_cause)
    assert set(by_cause["static_decenter"].params) == set(by_cause["cam_harmonic"].params)
    for cause, params in truth.items():
        own = by_cause[cause]
        for name, value in params.items():
            # decentres of tens to hundreds of um; 4 sd: 1 in 16000 for an honest Gaussian sd
            assert abs(own.params[name] - value) < 4 * own.params_sd[name], (
                cause, name, own.params, value)
    # the extended model's flat dict keeps both, each qualified by its term
    params, _ = d.extended.fit.param_dict(d.extended.n_baseline)
    shared = [k for k in params if k.startswith("variator_x_um")]
    assert len(shared) == 2 and all("(" in k for k in shared), list(params)
