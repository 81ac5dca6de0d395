"""Honest uncertainties: Monte Carlo over calibration sets rendered through the exact lens.

Each set: 8 views rendered through the aligned laikin-10x at zoom 0 (noise 2 DN, blur 0.7 px),
detected with the model fit, calibrated by both backends. Across sets, the empirical spread of
cx, cy and fx must match the backends' own predicted 1-sigma, and the mean must sit on the truth
(the lens state's camera model).

CI runs 24 sets on the default sensor binned 2 x 2 (640 x 480 px, the same field of view: a
quarter of the pixels to render); the full check (reported in docs/calibration.md) runs 100 on
the default sensor itself:
``ZOOMCALIB_MC_SETS=100 ZOOMCALIB_MC_BINNING=1 python -m pytest tests/test_calibration_mc.py``.
``ZOOMCALIB_MC_PSF=airy`` (or ``halo``, ``elliptical``) renders with another PSF shape than the
Gaussian (``zoomcalib.render.image.Optics``); the truth stays the lens state's camera model.
"""

import os

import numpy as np
import pytest

from zoomcalib.study.engine import Task, run_tasks
from zoomcalib.study.paper import detection_task

N_SETS = int(os.environ.get("ZOOMCALIB_MC_SETS", "24"))
PSF = os.environ.get("ZOOMCALIB_MC_PSF", "gaussian")
BINNING = int(os.environ.get("ZOOMCALIB_MC_BINNING", "2"))


@pytest.fixture(scope="module")
def sets():
    kwargs = {"lens": "laikin-10x", "zoom": 0.0, "noise_dn": 2.0, "views": 8,
              "pattern": "chessboard:9x6:25", "blur_px": 0.7, "detectors": ["model"],
              "backends": ["opencv", "bundle"], "psf": PSF, "binning": BINNING}
    tasks = [Task(f"mc{i:03d}", detection_task, kwargs) for i in range(N_SETS)]
    res = run_tasks(tasks, seed=2026, workers=2)
    assert not [r for r in res.values() if "error" in r]
    return list(res.values())


@pytest.mark.parametrize("backend", ["opencv", "bundle"])
def test_predicted_uncertainty_matches_the_spread(sets, backend):
    n = len(sets)
    # The sample sd of n draws has a relative standard error of 1 / sqrt(2 (n - 1)); the mean
    # of n draws sits within 1 / sqrt(n) sd of the truth. Bands of 3 standard errors: with 100
    # sets that is 21 % and 0.3 sigma (the required 15 % and 0.2 sigma are 2.1 and 2 standard
    # errors there); with CI's 24 sets, 44 % and 0.61 sigma.
    band = 3 / np.sqrt(2 * (n - 1))
    bias_band = 3 / np.sqrt(n)
    report = {}
    for name in ("cx", "cy", "fx"):
        est = np.array([s["results"]["model"][backend][name] for s in sets])
        pred = np.array([s["results"]["model"][backend][f"sd_{name}"] for s in sets])
        truth = sets[0]["truth"][name] if name in sets[0]["truth"] else None
        spread, predicted = est.std(ddof=1), np.sqrt(np.mean(pred**2))
        ratio = spread / predicted
        report[name] = ratio
        assert abs(ratio - 1) < band, (name, ratio)
        if truth is not None:
            bias = (est.mean() - truth) / predicted
            report[f"bias_{name}"] = bias
            assert abs(bias) < bias_band, (name, bias)
    print(backend, PSF, BINNING, n, {k: round(float(v), 3) for k, v in report.items()})
