"""Each selected cause reports its own parameters, also when two causes of one group share
parameter names (a static decentre and a cam harmonic of the variator both have
``variator_x_um``, ``variator_y_um``)."""

import numpy as np

from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import synthetic_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription

# a draw of benchmarks/diagnose_hit_rate.py (static_decenter, magnitude 1-16x) whose selection
# adds a cam harmonic of the same group to the hidden static decentre
SEED = 2026 * 100000 + 10000 * 5 + 34


def test_causes_sharing_parameter_names_keep_their_own_values():
    lens = load_prescription("laikin-10x")
    rng = np.random.default_rng(SEED)
    rows, truth = synthetic_zoom_table(lens, "static_decenter", rng, magnitude=(1.0, 16.0),
                                       with_focus=bool(rng.integers(2)),
                                       with_temperature=bool(rng.integers(2)))
    d = diagnose_table(ZoomTable.from_rows(rows, "draw"), LensResponse.of(lens))
    by_cause = {s.cause: s for s in d.causes}
    # the situation under test: two selected causes with the same parameter names
    assert {"static_decenter", "cam_harmonic"} <= set(by_cause)
    assert set(by_cause["static_decenter"].params) == set(by_cause["cam_harmonic"].params)
    own = by_cause["static_decenter"]
    for name, value in truth["params"].items():
        # hidden decentre of some hundred um; 4 sd: 1 in 16000 for an honest Gaussian sd
        assert abs(own.params[name] - value) < 4 * own.params_sd[name], (name, own.params, value)
    # the extended model's flat dict keeps both, each qualified by its term
    params, _ = d.extended.fit.param_dict(d.extended.n_baseline)
    shared = [k for k in params if k.startswith("variator_x_um")]
    assert len(shared) == 2 and all("(" in k for k in shared), list(params)
