import json

import numpy as np
import pytest

from zoomcalib.optics.prescription import PrescriptionError, builtin_lenses, load_prescription


def test_builtins_load():
    assert {"laikin-10x", "nikon-80-200"} <= set(builtin_lenses())
    lens = load_prescription("laikin-10x")
    assert lens.n_surfaces == 24
    assert lens.stop == 15
    assert lens.groups["variator"] == (5, 9)
    np.testing.assert_allclose(lens.gap_after, [4, 9, 14])
    np.testing.assert_allclose(lens.curvature[0], 1 / 255.7704)
    assert lens.curvature[15] == 0.0
    nikon = load_prescription("nikon-80-200")
    assert nikon.stop == 17


def _write(tmp_path, doc, name="lens.json"):
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return p


def _laikin_doc():
    from importlib import resources

    return json.loads((resources.files("zoomcalib.optics") / "lenses" /
                       "laikin-10x.json").read_text())


def test_user_file_by_path(tmp_path):
    p = _write(tmp_path, _laikin_doc())
    lens = load_prescription(p)
    assert lens.path == str(p)
    np.testing.assert_allclose(lens.curvature, load_prescription("laikin-10x").curvature)


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["surfaces"][3].pop("radius_mm"), "surfaces[3].radius_mm"),
    (lambda d: d["surfaces"][2].__setitem__("thickness_mm", "thick"), "surfaces[2].thickness_mm"),
    (lambda d: d["surfaces"][6].__setitem__("nd", 0.5), "surfaces[6].nd"),
    (lambda d: d["surfaces"][0].__setitem__("radius_mm", 0), "surfaces[0].radius_mm"),
    (lambda d: d["surfaces"][0].__setitem__("stop", True), "stop"),
    (lambda d: d["variable_gaps_mm"]["design_positions"][1].__setitem__(0, 99.0),
     "variable_gaps_mm.design_positions"),
    (lambda d: d["variable_gaps_mm"].__setitem__("after_surface", [5, 10]),
     "variable_gaps_mm.after_surface"),
    (lambda d: d["groups"]["variator"].__setitem__("surfaces", [6, 40]), "groups.variator"),
    (lambda d: d["surfaces"][7].__setitem__("group", "nonesuch"), "surfaces[7].group"),
])
def test_bad_prescription_names_file_and_field(tmp_path, mutate, field):
    doc = _laikin_doc()
    mutate(doc)
    p = _write(tmp_path, doc, "broken.json")
    with pytest.raises(PrescriptionError) as info:
        load_prescription(p)
    msg = str(info.value)
    assert str(p) in msg and field in msg
    assert "\n" not in msg


def test_not_json_and_unknown_name(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(PrescriptionError, match="bad.json: not valid JSON"):
        load_prescription(p)
    with pytest.raises(PrescriptionError, match="not a built-in lens"):
        load_prescription("no-such-lens")
