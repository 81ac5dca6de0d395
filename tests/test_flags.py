"""Flags a person can act on: each has a severity, a few words and one action, and the most
severe comes first (zoomcalib.calibrate.checks.step_flags, the CLI summary, the report)."""

import copy

import numpy as np

from zoomcalib.calibrate.checks import ACTIONS, SEVERITIES, Flag, by_severity, step_flags
from zoomcalib.calibrate.result import CalibrationResult


def _result(**info) -> CalibrationResult:
    K = np.array([[1000.0, 0, 639.5], [0, 1000.0, 359.5], [0, 0, 1]])
    sd = {"fx": 1.0, "fy": 1.0, "cx": 1.0, "cy": 1.0}
    return CalibrationResult("opencv", K, np.zeros(5), sd, 0.1, np.full(3, 0.1),
                             np.zeros((3, 3)), np.zeros((3, 3)), info={"converged": True, **info})


def test_a_clean_result_has_no_flags_and_every_kind_has_an_action():
    assert step_flags(_result(), (1280, 720)) == []
    assert all(text and not text.endswith(".") for text in ACTIONS.values())


def test_flags_carry_severity_short_text_and_action():
    res = _result()
    res.K[1, 2] = 700.0          # off the central region
    res.sd["cx"] = 40.0          # > 1 % of the diagonal
    res.info.update(converged=False, stop_reason="iteration cap")
    flags = step_flags(res, (1280, 720))
    kinds = {f.kind: f for f in flags}
    assert set(kinds) == {"centre", "sd_pp", "not_converged"}
    assert kinds["not_converged"].severity == "error"
    assert kinds["sd_pp"].severity == "warning" and kinds["sd_pp"].text == "sd cx 40.0 px"
    for f in flags:
        assert f.severity in SEVERITIES and f.action == ACTIONS[f.kind]
        assert len(f.text) < len(f.detail)
        assert f.to_dict()["action"] == f.action
    ordered = by_severity(flags)
    assert ordered[0].kind == "not_converged"
    assert [SEVERITIES.index(f.severity) for f in ordered] == sorted(
        (SEVERITIES.index(f.severity) for f in ordered), reverse=True)


def test_view_scatter_is_a_note_with_its_factor():
    scatter = {"applied": True, "factor": {"fx": 1.0, "cy": 9.7}, "scaled": ["cy"],
               "board_point": {"factor": {"cy": 2.6}, "excess": {"cy": 2.6**2 - 1},
                               "flagged": ["cy"]}}
    flags = step_flags(_result(view_scatter=copy.deepcopy(scatter)), (1280, 720))
    assert [(f.kind, f.severity, f.text) for f in flags] == [
        ("views", "note", "views disagree: sd cy x9.7"),
        ("board", "note", "board not as printed: sd cy x2.6")]
    assert "rigid flat board" in flags[1].action
    # the same message as before, in full, for the files that keep the text
    assert flags[0].detail.startswith("views disagree beyond the corner noise: sd cy x9.7")
    assert isinstance(flags[0], Flag)


def test_a_second_basin_near_in_cost_is_a_warning():
    second = {"cx": 540.0, "cy": 580.0, "fx": 1000.0, "p1": 0.2, "cost_px2": 1.0}
    near = _result(basin={"moved": False, "second": second | {"excess_noise_variances": 4.0}})
    kinds = {f.kind: f for f in step_flags(near, (1280, 720))}
    assert kinds["basin"].severity == "warning" and "(540, 580)" in kinds["basin"].detail
    far = _result(basin={"moved": False, "second": second | {"excess_noise_variances": 300.0}})
    assert step_flags(far, (1280, 720)) == []
    # moved on the total cost where the views' paired test does not support it: said so
    moved = _result(basin={"moved": True, "view_t": 0.6, "view_t_needed": 3.4,
                           "views_disagree": True})
    detail = {f.kind: f for f in step_flags(moved, (1280, 720))}["basin"].detail
    assert "the views do not agree on it (paired t 0.6, 3.4 for 3 sigma)" in detail


def test_flags_are_ordered_most_severe_then_shortest_first():
    rng = np.random.default_rng(7)
    texts = ["".join("x" * n) for n in rng.permutation(np.arange(1, 10))]
    flags = [Flag("correlated", SEVERITIES[i % 3], t, t) for i, t in enumerate(texts)]
    ordered = by_severity(flags)
    ranks = [(-SEVERITIES.index(f.severity), len(f.text)) for f in ordered]
    assert ranks == sorted(ranks) and len(ordered) == len(flags)
    assert ordered[0].severity == "error" and ordered[-1].severity == "note"
