"""Capture advice: a step extended as advised reaches the sigma the advice predicts.

A long-end-like step (nearly fronto-parallel views) is drawn from a seeded generator and
calibrated with OpenCV; the advice names views to add. The test then lays those views out
itself from the advice's words (count, tilt, distance, the quadrants and the centre), with
jitter the advice does not know, redraws the corner noise many times, and calibrates each
extended set: the spread of the estimates about the truth must match the predicted sigma
within 25 %.
"""

import cv2
import numpy as np
import pytest

from zoomcalib.calibrate.advice import advise
from zoomcalib.calibrate.opencv_backend import calibrate_opencv
from zoomcalib.calibrate.result import Observations
from zoomcalib.calibrate.status import PP_SD_LIMIT, step_status
from zoomcalib.targets import parse_pattern

SIZE = (1280, 720)
NOISE = 0.15  # px per coordinate
DRAWS = 60  # the sd of a spread from 60 draws is within 25 % of its truth at about 2.7 sigma


def _views(rng, X, K, poses, noise):
    out = []
    for r, t in poses:
        p = cv2.projectPoints(X, r, t, K, np.zeros(5))[0].reshape(-1, 2)
        p = p + rng.normal(0, noise, p.shape)
        inside = np.all((p >= 0) & (p <= np.array(SIZE) - 1), axis=1)
        out.append((np.flatnonzero(inside), p[inside]))
    return out


def _advised_poses(rng, X, K, advice):
    """The views the advice describes, laid out here from its words, with some jitter."""
    centre = X.mean(axis=0)
    places = [(0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7), (0.5, 0.5)]
    axes = [(1, 0), (0, 1), (-1, 0), (0, -1)]
    poses = []
    for i in range(advice.views):
        ax, ay = axes[i % 4]
        tilt = np.deg2rad(advice.tilt_deg + rng.uniform(-3, 3))
        R = cv2.Rodrigues(np.array([ax * tilt, ay * tilt, np.deg2rad(rng.uniform(-5, 5))]))[0]
        u, v = places[i % 5]
        ray = np.linalg.solve(K, [u * (SIZE[0] - 1) + rng.uniform(-20, 20),
                                  v * (SIZE[1] - 1) + rng.uniform(-20, 20), 1.0])
        t = advice.distance_mm * rng.uniform(0.97, 1.03) * ray / ray[2] - R @ centre
        poses.append((cv2.Rodrigues(R)[0].ravel(), t))
    return poses


@pytest.mark.parametrize("seed", [3, 4])
def test_a_step_extended_as_advised_reaches_the_predicted_sigma(seed):
    rng = np.random.default_rng(seed)
    X = parse_pattern("chessboard:9x6:25").object_points.astype(float)
    fx = rng.uniform(3500, 5000)
    K = np.array([[fx, 0, rng.uniform(600, 680)], [0, fx, rng.uniform(330, 390)], [0, 0, 1]])
    distance = fx * 225 / 500  # the board spans about 500 px
    poses = []
    for _ in range(10):  # nearly fronto-parallel views: a zoom towards its long end
        r = np.deg2rad(rng.uniform(-3, 3, 3))
        ray = np.linalg.solve(K, [rng.uniform(300, 980), rng.uniform(200, 520), 1.0])
        R = cv2.Rodrigues(r)[0]
        poses.append((r, distance * ray / ray[2] - R @ X.mean(axis=0)))
    obs = Observations(X, _views(rng, X, K, poses, NOISE), SIZE)
    res = calibrate_opencv(obs)
    status = step_status(res, SIZE)
    assert status.status != "ok"  # the advice is for this: a principal point not determined
    assert res.sd["cx"] > PP_SD_LIMIT * np.hypot(*SIZE)

    advice = advise(res, obs)
    assert advice is not None
    assert all(advice.predicted_sd[q] < res.sd[q] for q in ("fx", "cx", "cy"))
    added = _advised_poses(rng, X, K, advice)
    estimates = []
    for _ in range(DRAWS):
        views = _views(rng, X, K, poses + added, NOISE)
        r = calibrate_opencv(Observations(X, views, SIZE))
        estimates.append([r.fx - K[0, 0], r.cx - K[0, 2], r.cy - K[1, 2]])
    spread = np.sqrt(np.mean(np.square(estimates), axis=0))  # about the truth
    predicted = np.array([advice.predicted_sd[q] for q in ("fx", "cx", "cy")])
    ratio = spread / predicted
    assert np.all((ratio > 0.75) & (ratio < 1.25)), (ratio, spread, predicted, advice.text())
