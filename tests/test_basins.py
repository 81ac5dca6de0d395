"""The principal point's basin at the long end of a zoom (zoomcalib.calibrate.basins).

A narrow-field step (fx 8800 px on 1280 x 720, views tilted at most 8 degrees) through a lens
with the decentring and pincushion a real PTZ camera's 9x step showed, projected by the
renderer's camera mapping (not OpenCV's), with 0.3 px of corner noise. Its cost over the
principal point has a second minimum, p1 of the other sign: OpenCV started there stays there.
"""

import cv2
import numpy as np
import pytest

from zoomcalib.calibrate.basins import best_basin
from zoomcalib.calibrate.opencv_backend import calibrate_opencv
from zoomcalib.calibrate.result import Observations
from zoomcalib.camera import CameraModel
from zoomcalib.render.image import camera_mapping, project_points
from zoomcalib.render.sweep import SWEEP_SENSOR, sweep_poses
from zoomcalib.targets import parse_pattern

NOISE_PX = 0.3
FLAGS = cv2.CALIB_FIX_K3


def _narrow_step(rng: np.random.Generator):
    truth = {"cx": rng.uniform(620, 700), "cy": rng.uniform(180, 260),
             "p1": -rng.uniform(0.08, 0.12), "p2": rng.uniform(0.0, 0.03)}
    cam = CameraModel(8800.0, 8800.0, truth["cx"], truth["cy"],
                      np.array([5.5, 0.0, truth["p1"], truth["p2"], 0.0]), SWEEP_SENSOR)
    target = parse_pattern("chessboard:22x15:25")
    views = []
    for R, t in sweep_poses(target, cam, 20, 8.0, rng):
        uv = project_points(target.object_points, camera_mapping(cam), R, t)
        views.append((np.arange(len(uv)), uv + rng.normal(0, NOISE_PX, uv.shape)))
    size = (SWEEP_SENSOR.width_px, SWEEP_SENSOR.height_px)
    return Observations(target.object_points, views, size), truth


def _fit_from(obs, cx, cy, p1):
    K = np.array([[8800.0, 0, cx], [0, 8800.0, cy], [0, 0, 1]])
    return calibrate_opencv(obs, flags=FLAGS, fix_aspect=True, K_guess=K,
                            dist_guess=np.array([5.5, 0, p1, 0, 0]))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_start_in_the_other_basin_is_moved_to_the_right_one(seed):
    obs, truth = _narrow_step(np.random.default_rng(seed))
    wrong = _fit_from(obs, 620.0, 500.0, 0.1)
    # the setting is as met: OpenCV converges in the other basin with a sigma that does not
    # cover the distance to the truth
    assert abs(wrong.cy - truth["cy"]) > 30 * wrong.sd["cy"], (wrong.cy, wrong.sd["cy"])
    check = best_basin(obs, wrong.K, wrong.dist, FLAGS, NOISE_PX)
    assert check.moved and check.other_cost_px2 < check.cost_px2
    # white noise: the views prefer the right basin together; no flag
    assert check.view_t > check.view_t_needed and not check.views_disagree
    for q in ("cx", "cy"):  # 4 sigmas: the fit's own, at 0.3 px of noise about 1.3 px
        assert abs(getattr(check.fit, q) - truth[q]) < 4 * check.fit.sd[q], (q, check.fit)
    assert np.sign(check.fit.dist[2]) == np.sign(truth["p1"])


def test_a_start_in_the_right_basin_stays():
    obs, truth = _narrow_step(np.random.default_rng(2))
    right = _fit_from(obs, truth["cx"] + 20, truth["cy"] - 20, 0.0)
    assert abs(right.cy - truth["cy"]) < 4 * right.sd["cy"]
    check = best_basin(obs, right.K, right.dist, FLAGS, NOISE_PX)
    assert not check.moved and check.why is None
    assert check.fit.cy == pytest.approx(right.cy, abs=0.1 * right.sd["cy"])
    assert len(check.profile) == 14 and min(c for _, _, c in check.profile) > 0



@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_other_basin_is_found_from_either_side(seed):
    obs, truth = _narrow_step(np.random.default_rng(seed))
    wrong = _fit_from(obs, 620.0, 500.0, 0.1)
    right = _fit_from(obs, truth["cx"] + 20, truth["cy"] - 20, 0.0)
    from_right = best_basin(obs, right.K, right.dist, FLAGS, NOISE_PX)
    from_wrong = best_basin(obs, wrong.K, wrong.dist, FLAGS, NOISE_PX)
    assert not from_right.moved and from_wrong.moved
    for check, other in ((from_right, wrong), (from_wrong, wrong)):
        # the basin not chosen is the one OpenCV reaches from the wrong start, p1 of the
        # other sign, and costs more (over 100 noise variances at this noise)
        assert check.second is not None
        assert abs(check.second.cy - other.cy) < 3 * other.sd["cy"], (check.second.cy, other.cy)
        assert np.sign(check.second.dist[2]) != np.sign(truth["p1"])
        assert check.second_excess > 100
        assert check.to_dict()["second"]["cy"] == pytest.approx(check.second.cy)
        # white noise: every view prefers the chosen basin; no mixture of the two
        assert check.second_view_t > check.second_view_t_needed
        assert not check.ambiguous and check.half_gap() == {}
    # both sides end at the same camera
    assert from_right.fit.cy == pytest.approx(from_wrong.fit.cy, abs=0.1 * right.sd["cy"])


@pytest.mark.parametrize("seed", [0, 2])
def test_a_move_that_two_views_alone_make_is_flagged(seed):
    # Views 0 and 1 get ten times the difference between the two basins' projections of
    # them added: the other basin's total cost is then lower by over 100 noise variances,
    # all of it from those two views, as a real step's views with errors of their own make.
    obs, truth = _narrow_step(np.random.default_rng(seed))
    wrong = _fit_from(obs, 620.0, 500.0, 0.1)
    right = _fit_from(obs, truth["cx"] + 20, truth["cy"] - 20, 0.0)
    views = list(obs.views)
    for v in (0, 1):
        ids, uv = views[v]
        moved_by = [cv2.projectPoints(obs.object_points[ids], fit.rvecs[v], fit.tvecs[v], fit.K,
                                      fit.dist)[0].reshape(-1, 2) for fit in (wrong, right)]
        views[v] = (ids, uv + 10.0 * (moved_by[0] - moved_by[1]))
    bent = Observations(obs.object_points, views, obs.image_size)
    start = _fit_from(bent, truth["cx"] + 20, truth["cy"] - 20, 0.0)
    check = best_basin(bent, start.K, start.dist, FLAGS, NOISE_PX)
    # the total cost moves it (the views' paired test is reported, not required) ...
    assert check.cost_px2 - check.other_cost_px2 > 100 * NOISE_PX**2 and check.moved
    # ... and the record says that the views do not agree on the move
    assert check.view_t < check.view_t_needed and check.views_disagree
    assert check.to_dict()["views_disagree"] is True
    assert check.to_dict()["view_t"] == pytest.approx(check.view_t)
    # nor do they agree that the chosen basin is lower than the one left: the step is a
    # mixture of the two, half their distance its sd's share
    assert check.second is not None and check.ambiguous
    gap = check.half_gap()
    for q in ("fx", "cx", "cy"):
        assert gap[q] == pytest.approx(0.5 * abs(getattr(check.fit, q) - getattr(check.second, q)))
    assert gap["cy"] > 10 * check.fit.sd["cy"]
    # the decentring too: the second basin's p1 has the other sign
    assert gap["p1"] == pytest.approx(0.5 * abs(check.fit.dist[2] - check.second.dist[2]))
    assert gap["p1"] > 0.5 * abs(check.fit.dist[2])
    assert check.to_dict()["half_gap"] == gap


def test_a_move_without_a_paired_test_is_not_called_disagreed():
    from zoomcalib.calibrate.basins import BasinCheck

    assert BasinCheck(None, True, view_t=0.5, view_t_needed=3.4).views_disagree
    assert not BasinCheck(None, True, view_t=5.0, view_t_needed=3.4).views_disagree
    assert not BasinCheck(None, True).views_disagree  # one view: no test, nothing said
    assert not BasinCheck(None, False, view_t=0.5, view_t_needed=3.4).views_disagree
