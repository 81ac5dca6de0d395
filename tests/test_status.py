"""Step statuses: a result that is not a camera, or not determined, is called so, with why.

Cameras are drawn from a seeded generator; a hidden fault is put into some of them, and the
record of which is kept here, away from the code under test. Every fault must be named by its
reason and every clean camera must come out ``ok``.
"""

import numpy as np
import pytest

from zoomcalib.calibrate.result import CalibrationResult
from zoomcalib.calibrate.status import (
    ASPECT_TOLERANCE,
    MOVE_LIMIT,
    distortion_fold_radius,
    sensor_aspect,
    step_status,
)

SIZE = (1280, 720)
FAULTS = ("none", "pp_outside", "aspect", "fold", "pp_undetermined", "pp_imprecise",
          "fx_imprecise")
# the reason's words each fault must be named by, and the status it must give
NAMED = {"pp_outside": ("outside the", "unusable"), "aspect": ("aspect ratio", "unusable"),
         "fold": ("folds", "unusable"), "pp_undetermined": ("not determined", "unusable"),
         "pp_imprecise": ("% of the image diagonal", "imprecise"),
         "fx_imprecise": ("sd fx", "imprecise")}


def _camera(rng, fault: str) -> CalibrationResult:
    fx = float(np.exp(rng.uniform(np.log(800), np.log(12000))))
    fy = fx * (1 + rng.normal(0, 1e-4))
    cx, cy = rng.uniform(540, 740), rng.uniform(300, 420)
    corner = np.hypot(700, 420) / fx  # normalised radius of the farthest corner, about
    # a barrel or pincushion of at most 3 % at the corner: no fold
    dist = np.array([rng.uniform(-0.03, 0.03) / corner**2, 0.0, rng.normal(0, 1e-4),
                     rng.normal(0, 1e-4), 0.0])
    sd = {"fx": fx * rng.uniform(1e-4, 3e-3), "cx": rng.uniform(0.3, 5),
          "cy": rng.uniform(0.3, 5)}
    sd["fy"] = sd["fx"]
    if fault == "pp_outside":
        if rng.random() < 0.5:
            cy = -rng.uniform(50, 700)
        else:
            cx = SIZE[0] + rng.uniform(50, 700)
    elif fault == "aspect":
        fy = fx * (1 + rng.choice([-1, 1]) * rng.uniform(0.03, 0.2))
    elif fault == "fold":  # r_d = r + k1 r^3 turns over at r^2 = -1/(3 k1): put that inside
        r_fold = corner * rng.uniform(0.4, 0.9)
        dist[0] = -1.0 / (3 * r_fold**2)
    elif fault == "pp_undetermined":
        sd["cy"] = rng.uniform(200, 900)
    elif fault == "pp_imprecise":
        sd["cx"] = rng.uniform(20, 150)
    elif fault == "fx_imprecise":
        sd["fx"] = sd["fy"] = fx * rng.uniform(0.015, 0.05)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return CalibrationResult("zoom-wide", K, dist, sd, 0.3, np.full(20, 0.3),
                             np.zeros((20, 3)), np.zeros((20, 3)), info={"converged": True})


def test_every_hidden_fault_is_named_and_clean_cameras_are_ok():
    rng = np.random.default_rng(20261126)
    truth = rng.choice(FAULTS, size=140)
    cams = {f"s{i}": _camera(rng, str(f)) for i, f in enumerate(truth)}
    aspect = sensor_aspect(cams)
    # the sensor's ratio comes from the clean majority, not the faulty steps
    assert aspect is not None and abs(aspect[0] - 1.0) < 2e-4
    missed, false = [], []
    for (name, res), fault in zip(cams.items(), truth, strict=True):
        st = step_status(res, SIZE, aspect)
        if fault == "none":
            if st.status != "ok":
                false.append((name, st.summary()))
            continue
        words, status = NAMED[str(fault)]
        if st.status != status or not any(words in r for r in st.reasons):
            missed.append((name, fault, st.summary()))
        assert len(st.remedies) >= 1 and all(st.remedies)
    assert (truth == "none").sum() > 10 and len(set(truth)) == len(FAULTS)
    assert not missed, missed
    assert not false, false


def test_a_step_moved_by_the_joint_adjustment_beyond_its_own_sigmas_is_flagged():
    rng = np.random.default_rng(5)
    moved, kept = 0, 0
    for _ in range(40):
        own = _camera(rng, "none")
        shift = rng.uniform(0, 2 * MOVE_LIMIT)
        joint = CalibrationResult("zoom-wide", own.K.copy(), own.dist.copy(), dict(own.sd),
                                  0.3, own.per_view_rms_px, own.rvecs, own.tvecs,
                                  info={"converged": True})
        joint.K[0, 2] += shift * own.sd["cx"]
        st = step_status(joint, SIZE, None, own)
        flagged = any("moved cx" in r for r in st.reasons)
        assert flagged == (shift > MOVE_LIMIT), (shift, st.summary())
        assert st.status == ("imprecise" if shift > MOVE_LIMIT else "ok")
        moved, kept = moved + flagged, kept + (not flagged)
    assert moved > 5 and kept > 5
    # a step that is not well determined alone gives no reference to be moved from
    own = _camera(rng, "pp_imprecise")
    joint = CalibrationResult("zoom-wide", own.K.copy(), own.dist, {**own.sd, "cx": 2.0}, 0.3,
                              own.per_view_rms_px, own.rvecs, own.tvecs,
                              info={"converged": True})
    joint.K[0, 2] += 10 * own.sd["cx"]
    assert not any("moved" in r for r in step_status(joint, SIZE, None, own).reasons)


def test_a_move_says_whether_the_board_or_the_other_steps_made_it():
    # the step alone on the adjustment's board (the basin check's fit) lands either near the
    # adjustment (the board's shape moved the step) or near the per-step fit (the other steps
    # did); which one is drawn and kept here
    rng = np.random.default_rng(11)
    board_cases = 0
    for _ in range(30):
        own = _camera(rng, "none")
        shift = rng.uniform(1.5, 3) * MOVE_LIMIT * own.sd["cy"]
        by_board = bool(rng.random() < 0.5)
        board_cases += by_board
        alone_cy = own.cy + shift + (rng.uniform(-2, 2) * own.sd["cy"] if by_board
                                     else rng.uniform(-0.5, 0.5) * own.sd["cy"] - shift)
        joint = CalibrationResult("zoom-wide", own.K.copy(), own.dist.copy(), dict(own.sd),
                                  0.3, own.per_view_rms_px, own.rvecs, own.tvecs,
                                  info={"converged": True, "basin": {"alone": {
                                      "fx": own.fx, "cx": own.cx, "cy": alone_cy}}})
        joint.K[1, 2] += shift
        st = step_status(joint, SIZE, None, own)
        reason = next(r for r in st.reasons if "moved cy" in r)
        assert ("board's estimated shape moved it" in reason) == by_board, reason
        assert ("the other steps moved it" in reason) == (not by_board), reason
        assert any(("session of its own" in r) == by_board for r in st.remedies)
    assert 5 < board_cases < 25


@pytest.mark.parametrize("k1", [-0.5, -2.0, -8.0])
def test_the_fold_radius_is_where_the_radial_map_turns(k1):
    # r_d = r + k1 r^3 has d r_d / d r = 0 at r = 1 / sqrt(-3 k1), r_d = 2 r / 3 there
    r, rd = distortion_fold_radius(np.array([k1, 0, 0, 0, 0]), r_max=2.0, samples=200000)
    r_true = 1.0 / np.sqrt(-3 * k1)
    assert r == pytest.approx(r_true, abs=2e-5)
    assert rd == pytest.approx(2 * r_true / 3, abs=2e-5)


def test_a_shared_aspect_ratio_is_read_through_faulty_steps():
    rng = np.random.default_rng(11)
    true_aspect = 1.0 + rng.uniform(-0.05, 0.05)  # a non-square pixel, the same at every step
    cams = {}
    for i in range(9):
        c = _camera(rng, "aspect" if i in (6, 8) else "none")
        c.K[1, 1] *= true_aspect
        cams[f"s{i}"] = c
    a, sd = sensor_aspect(cams)
    assert abs(a - true_aspect) < 5e-4 and 0 < sd < 5e-3
    statuses = [step_status(c, SIZE, (a, sd)).status for c in cams.values()]
    assert statuses[6] == statuses[8] == "unusable"
    assert statuses.count("ok") == 7
    assert ASPECT_TOLERANCE <= 0.02


def test_diagnose_leaves_out_an_unusable_row(tmp_path):
    from zoomcalib.calibrate.io import write_zoom_table
    from zoomcalib.diagnose.run import load_zoom_table

    rng = np.random.default_rng(2)
    rows = []
    for i, zoom in enumerate(np.linspace(0, 1, 6)):
        fx = 1200 * (1 + 9 * zoom)
        rows.append({"step": f"s{i}", "zoom": zoom, "fx": fx, "fy": fx,
                     "cx": 640 + rng.normal(0, 2), "cy": 360 + rng.normal(0, 2),
                     "sd_fx": 1.0, "sd_fy": 1.0, "sd_cx": 1.0, "sd_cy": 1.0, "rms_px": 0.2,
                     "n_views": 20, "backend": "opencv", "mode": "per-step", "status": "ok"})
    bad = int(rng.integers(1, 5))
    rows[bad] |= {"cy": -663.0, "status": "unusable",
                  "status_reasons": "principal point (650, -663) outside the 1280x720 image"}
    path = write_zoom_table(tmp_path / "zoom_calibration.csv", rows)
    table = load_zoom_table(path)
    assert table.step == [r["step"] for r in rows if r["status"] == "ok"]
    assert np.all(table.cy > 0)


def test_long_statuses_and_advice_do_not_stop_calibration_yml(tmp_path):
    import json

    import cv2

    from zoomcalib.calibrate.io import write_calibration

    rng = np.random.default_rng(9)
    results = {f"zoom_{k}x": {"zoom-wide": _camera(rng, "pp_imprecise")} for k in range(1, 11)}
    long = "add 24 views with the board tilted 45 degrees " * 6
    meta = {"status": {s: {"status": "imprecise", "reasons": ["sd cy 30.0 px > 1 %"] * 3,
                           "remedies": [long], "advice": {"text": long}} for s in results}}
    json_path, yml_path = write_calibration(tmp_path, results, meta)
    assert json.loads(json_path.read_text())["meta"]["status"]["zoom_3x"]["advice"]["text"]
    fs = cv2.FileStorage(str(yml_path), cv2.FILE_STORAGE_READ)
    try:
        brief = json.loads(fs.getNode("meta_json").string())
    finally:
        fs.release()
    assert brief["status"] == {s: "imprecise" for s in results}


def test_a_result_without_sigmas_is_called_so_and_gets_no_advice():
    from zoomcalib.calibrate.advice import advise
    from zoomcalib.calibrate.result import Observations

    rng = np.random.default_rng(17)
    res = _camera(rng, "none")
    res.sd = {k: float("nan") for k in res.sd}
    st = step_status(res, SIZE)
    assert st.status == "unusable"
    assert any("sd cx not known" in r for r in st.reasons)
    assert any("sd fx not known" in r for r in st.reasons)
    # no views to build the information on: no advice, and no error
    assert advise(res, Observations(np.zeros((4, 3)), [], SIZE)) is None
