"""Tests of zoomcalib.study.lensfun on an extract of the lensfun database (tests/data/lensfun)."""

import csv
import io
import math
from pathlib import Path

import numpy as np
import pytest

from zoomcalib.study.lensfun import (
    ZoomLensDistortion,
    distortion_measure,
    distortion_trend,
    half_diagonal_px,
    lens_trend,
    lensfun_forward,
    read_lensfun,
    read_lensfun_xml,
    trend_table,
)

DATA = Path(__file__).parent / "data" / "lensfun"
G3 = "Canon PowerShot G3 & compatibles (Standard)"
NIKKOR = "Nikon AF Zoom-Nikkor 24-50mm f/3.3-4.5D"


@pytest.fixture(scope="module")
def lenses():
    return read_lensfun(DATA)


def by_model(lenses, model):
    (lens,) = [x for x in lenses if x.model == model]
    return lens


# ---------------------------------------------------------------------------------------------
# Parsing


def test_extract_counts(lenses):
    # 51 systematic picks + G3 + Nikkor (README.md); the fisheye zoom only without the filter;
    # the prime and the 3-focal compact never.
    assert len(lenses) == 53
    assert all(lens.n_focal >= 4 for lens in lenses)
    assert all(lens.focal_range_mm[0] < lens.focal_range_mm[1] for lens in lenses)
    assert all(np.all(np.diff(lens.focal_mm) > 0) for lens in lenses)
    everything = read_lensfun(DATA, rectilinear_only=False)
    assert len(everything) == 54
    assert "smc Pentax-DA Fish-Eye 10-17mm f/3.5-4.5 ED IF" in {x.model for x in everything}
    models = {x.model for x in read_lensfun(DATA, min_focals=1, rectilinear_only=False)}
    assert "Fujifilm FinePix A370" in models  # a zoom with fewer than 4 calibrated focals
    assert "Mamiya 35mm f/3.5" not in models  # a prime is never a zoom


def test_parse_ptlens_lens(lenses):
    # From the XML text (compact-canon.xml): 11 ptlens entries, 4:3, crop 4.843.
    lens = by_model(lenses, G3)
    assert lens.maker == "Canon"
    assert lens.mounts == ("canonG3",)
    assert lens.crop_factor == 4.843
    assert lens.aspect_ratio == pytest.approx(4.0 / 3.0)
    assert lens.r_corner == pytest.approx(5.0 / 3.0)
    assert lens.n_focal == 11
    assert lens.dist_models == ("ptlens",) * 11
    assert lens.focal_mm[[0, 1, 5, -1]].tolist() == [7.188, 8.0, 14.406, 28.813]
    assert lens.coeffs.shape == (11, 3)
    assert lens.coeffs[0].tolist() == [0.013088, -0.036387, 0.0]  # focal 7.188
    assert lens.coeffs[5].tolist() == [0.001788, 0.00205, 0.0]  # focal 14.406
    assert lens.coeffs[-1].tolist() == [-8.6e-05, 0.005193, 0.0]  # focal 28.813
    # No focal range in the name: taken from the calibration.
    assert lens.focal_range_mm == (7.188, 28.813)


def test_parse_poly3_lens(lenses):
    # From the XML text (slr-nikon.xml): 4 poly3 entries, crop 1.528, no aspect ratio (3:2).
    lens = by_model(lenses, NIKKOR)
    assert lens.maker == "Nikon"
    assert lens.crop_factor == 1.528
    assert lens.aspect_ratio == 1.5
    assert lens.focal_mm.tolist() == [24.0, 29.0, 38.0, 50.0]
    assert lens.dist_models == ("poly3",) * 4
    assert lens.coeffs[:, 0].tolist() == [-0.010413, -0.006777, -0.003447, -0.003329]
    assert np.all(lens.coeffs[:, 1:] == 0.0)
    assert lens.focal_range_mm == (24.0, 50.0)  # from the model name


def test_parse_rules_inline():
    def xml(model, focals, extra="", dist='model="poly3" k1="-0.01"'):
        entries = "".join(f'<distortion {dist} focal="{f}"/>' for f in focals)
        return io.StringIO(
            f"<lensdatabase><lens><maker>M</maker><model>{model}</model>"
            f'<model lang="en">other</model><cropfactor>1.5</cropfactor>{extra}'
            f"<calibration>{entries}</calibration></lens></lensdatabase>"
        )

    (lens,) = read_lensfun_xml(xml("Z 2.8-4/12-40", (12, 18, 25, 40)))
    assert lens.model == "Z 2.8-4/12-40" and lens.focal_range_mm == (12.0, 40.0)
    # A named prime is skipped even with several calibrated focal lengths.
    assert read_lensfun_xml(xml("P 50mm f/1.8", (49, 50, 51, 52))) == []
    # <focal min max> is used when the name has no range.
    (lens,) = read_lensfun_xml(xml("Z", (10, 12, 15, 20), '<focal min="10" max="20"/>'))
    assert lens.focal_range_mm == (10.0, 20.0)
    # Repeated focal length: the first entry is kept, so only 3 distinct focals here.
    assert read_lensfun_xml(xml("Z 10-20mm", (10, 10, 15, 20))) == []
    (lens,) = read_lensfun_xml(xml("Z 10-20mm", (10, 10, 15, 20)), min_focals=3)
    assert lens.n_focal == 3
    # Aspect ratio given as a number; poly5 coefficients.
    (lens,) = read_lensfun_xml(
        xml(
            "Z 10-20mm",
            (10, 12, 15, 20),
            "<aspect-ratio>1.7778</aspect-ratio>",
            dist='model="poly5" k1="-0.02" k2="0.003"',
        )
    )
    assert lens.aspect_ratio == 1.7778
    assert lens.coeffs[0].tolist() == [-0.02, 0.003, 0.0]


# ---------------------------------------------------------------------------------------------
# Distortion measure, against closed forms worked out by hand


def test_forward_models():
    r = np.array([0.5, 1.0, 1.5])
    a, b, c = 0.01, -0.03, 0.002
    expect = r * (a * r**3 + b * r**2 + c * r + 1 - a - b - c)
    assert np.allclose(lensfun_forward(r, "ptlens", [a, b, c])[0], expect)
    assert np.allclose(lensfun_forward(r, "poly3", [-0.02, 0, 0])[0], r * (1.02 - 0.02 * r**2))
    assert np.allclose(
        lensfun_forward(r, "poly5", [-0.02, 0.004, 0])[0], r * (1 - 0.02 * r**2 + 0.004 * r**4)
    )
    # Hugin's models are pinned at r = 1.
    assert lensfun_forward(np.array([1.0]), "ptlens", [a, b, c])[0, 0] == pytest.approx(1.0)


def test_measure_ptlens_by_hand(lenses):
    # G3 at 7.188 mm: a = 0.013088, b = -0.036387, c = 0, 4:3 frame, corner r_c = 5/3.
    # Paraxial scale d = 1 - a - b = 1.023299; relative to it the displacement at radius r is
    # (a r^4 + b r^3) / (d r_c) of the half-diagonal; a r^4 + b r^3 peaks at r = -3b / 4a = 2.085,
    # outside the frame, so the largest magnitude is at the corner:
    # (a (5/3)^3 + b (5/3)^2) / d = (0.0605926 - 0.1010750) / 1.023299 = -0.0395607 (barrel).
    a, b = 0.013088, -0.036387
    corner = (a * (125 / 27) + b * (25 / 9)) / (1 - a - b)
    assert corner == pytest.approx(-0.0395607, abs=1e-7)
    m = by_model(lenses, G3).measure("paraxial")
    assert m.corner[0] == pytest.approx(corner, rel=1e-9)
    assert m.peak[0] == pytest.approx(corner, rel=1e-9)
    assert m.r_peak[0] == 1.0
    assert m.scale[0] == pytest.approx(1.023299)
    # Lensfun's raw model (s = 1): (r_d - r_c) / r_c = a (r_c^3 - 1) + b (r_c^2 - 1) = -0.0171834.
    raw = by_model(lenses, G3).measure("lensfun")
    assert raw.corner[0] == pytest.approx(a * (125 / 27 - 1) + b * (25 / 9 - 1), rel=1e-9)
    assert raw.corner[0] == pytest.approx(-0.0171834, abs=1e-7)


def test_measure_ptlens_moustache_by_hand():
    # a = 0.027509, b = -0.054383, c = 0 (a 28 mm entry in slr-canon.xml), 3:2 frame.
    # a r^4 + b r^3 peaks inside the frame at r* = -3b / 4a = 1.482687 (r_c = 1.802776):
    # peak = (a r*^4 + b r*^3) / (d r_c) = -0.0239383;
    # corner = (a r_c^3 + b r_c^2) / d = -0.0151615.
    a, b = 0.027509, -0.054383
    m = distortion_measure("ptlens", [a, b, 0.0], aspect_ratio=1.5)
    assert m.peak[0] == pytest.approx(-0.0239383, abs=2e-7)
    assert m.max_abs[0] == pytest.approx(0.0239383, abs=2e-7)
    assert m.corner[0] == pytest.approx(-0.0151615, abs=2e-7)
    assert m.r_peak[0] == pytest.approx(1.482687 / 1.802776, abs=3e-3)


def test_measure_poly3_by_hand(lenses):
    # Nikkor 24-50 at 24 mm: k1 = -0.010413, 3:2 frame (r_c^2 = 3.25). Paraxial distortion of
    # poly3 is k1 r^2 / (1 - k1), monotone in r: at the corner -0.033842 / 1.010413 = -0.0334935,
    # i.e. -26.79 px on a 1280 x 960 sensor (half-diagonal 800 px).
    k1 = -0.010413
    m = by_model(lenses, NIKKOR).measure()
    assert m.corner[0] == pytest.approx(k1 * 3.25 / (1 - k1), rel=1e-9)
    assert m.corner[0] == pytest.approx(-0.0334935, abs=1e-7)
    assert m.peak[0] == m.corner[0]
    assert half_diagonal_px(1280, 960) == 800.0
    assert m.max_abs[0] * half_diagonal_px() == pytest.approx(26.7948, abs=1e-3)
    # Lensfun's raw model: k1 (r_c^2 - 1) = -0.0234293.
    assert by_model(lenses, NIKKOR).measure("lensfun").corner[0] == pytest.approx(
        k1 * 2.25, rel=1e-9
    )


def test_measure_best_scale_poly3():
    # For r_d = (1 - k1) r + k1 r^3 the least-squares scale over the frame [0, A] x [0, 1] is
    # s = 1 - k1 + k1 <r^4> / <r^2>, with (continuum) <r^2> = A^3/3 + A/3 and
    # <r^4> = A^5/5 + 2 A^3/9 + A/5 (both times 1/A). The code samples a 64 x 64 grid.
    k1, aspect = -0.02, 1.5
    r2 = aspect**3 / 3 + aspect / 3
    r4 = aspect**5 / 5 + 2 * aspect**3 / 9 + aspect / 5
    s = 1 - k1 + k1 * r4 / r2
    m = distortion_measure("poly3", [k1, 0, 0], aspect, reference="best_scale")
    assert m.scale[0] == pytest.approx(s, abs=2e-5)
    rc = math.hypot(1, aspect)
    corner = ((1 - k1) * rc + k1 * rc**3 - s * rc) / (s * rc)
    assert m.corner[0] == pytest.approx(corner, abs=5e-5)
    # Barrel bends the image edge inward relative to the best scale, outward near the centre:
    # the largest residual is at the corner and smaller than the paraxial one.
    assert m.corner[0] < 0
    assert m.max_abs[0] < abs(distortion_measure("poly3", [k1, 0, 0], aspect).corner[0])


def test_measure_vectorised_and_errors():
    m = distortion_measure(["poly3", "ptlens"], np.array([[-0.02, 0, 0], [0, -0.02, 0]]))
    # ptlens with b only is poly3 with k1 = b.
    assert m.corner[0] == pytest.approx(m.corner[1])
    with pytest.raises(ValueError):
        distortion_measure("poly3", [0, 0, 0], reference="nope")
    with pytest.raises(ValueError):
        distortion_measure("fov1", [0, 0, 0])


# ---------------------------------------------------------------------------------------------
# Trend with focal length


def test_trend_real_lenses(lenses):
    # Nikkor 24-50: all barrel, |k1| falls at every step: the paper's assumption holds.
    t = lens_trend(by_model(lenses, NIKKOR))
    assert t.monotone_decreasing and t.tele_below_wide
    assert t.min_location == "tele" and t.spearman == pytest.approx(-1.0)
    assert (t.sign_wide, t.sign_tele, t.sign_change) == (-1, -1, False)
    assert t.tele_rise_px == 0.0
    # G3: b goes from -0.036 to +0.005: barrel at the wide end, pincushion at the tele end.
    t = lens_trend(by_model(lenses, G3))
    assert t.sign_change and t.barrel_to_pincushion
    assert (t.sign_wide, t.sign_tele) == (-1, 1)
    assert t.min_location == "interior" and not t.monotone_decreasing


def test_trend_summary_extract(lenses):
    s = distortion_trend(lenses)
    assert s.n_lenses == len(lenses) == len(s.lenses) == 53
    fracs = {k: v for k, v in s.as_dict().items() if k.startswith("frac_")}
    assert len(fracs) >= 10
    for name, v in fracs.items():
        assert 0.0 <= v <= 1.0, name
        assert (v * 53) == pytest.approx(round(v * 53)), name  # a count over 53 lenses
    assert s.frac_assumption_holds == s.frac_monotone_decreasing
    assert s.frac_monotone_decreasing <= s.frac_tele_below_wide
    assert s.frac_barrel_to_pincushion <= s.frac_sign_change
    assert sum(s.min_location_frac.values()) == pytest.approx(1.0)
    for q in (s.abs_wide_quartiles, s.abs_tele_quartiles, s.spearman_quartiles):
        assert q[0] <= q[1] <= q[2]
    assert np.allclose(np.array(s.abs_tele_px_quartiles), 800.0 * np.array(s.abs_tele_quartiles))
    # What the extract shows (the full database agrees): most zooms go from barrel to
    # pincushion, so |distortion| bottoms out inside the range; it is rarely monotone.
    assert s.frac_sign_change > 0.5
    assert s.min_location_frac["interior"] > 0.5
    assert s.frac_monotone_decreasing < 0.3
    assert s.abs_tele_px_quartiles[1] > 1.0  # far from sub-pixel at the tele end

    rows = trend_table(s)
    assert len(rows) == 53
    assert rows[0]["reference"] == "paraxial"
    assert {"maker", "model", "abs_wide", "abs_tele_px", "spearman", "min_location"} <= set(rows[0])
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    assert buf.getvalue().count("\n") == 54
    with pytest.raises(ValueError):
        distortion_trend([])


def _fake(model_name, focal, k1, aspect=1.5):
    """A fake lens with poly3 k1 (or ptlens b) at the given focal lengths."""
    k = np.asarray(k1, dtype=float)
    coeffs = np.zeros((k.size, 3))
    coeffs[:, 0 if model_name == "poly3" else 1] = k
    return ZoomLensDistortion(
        maker="Fake",
        model=f"Fake {focal[0]:.0f}-{focal[-1]:.0f}mm",
        mounts=(),
        crop_factor=1.0,
        aspect_ratio=aspect,
        focal_mm=np.asarray(focal, dtype=float),
        dist_models=(model_name,) * k.size,
        coeffs=coeffs,
        focal_range_mm=(float(focal[0]), float(focal[-1])),
        source="synthetic",
    )


def test_trend_synthetic(rng):
    monotone, crossing, rising = [], [], []
    for _ in range(7):  # barrel that fades: |k1| = k0 (f_min / f)^p
        n = int(rng.integers(4, 11))
        f = rng.uniform(10, 30) * np.geomspace(1, rng.uniform(2, 10), n)
        k0, p = rng.uniform(0.005, 0.05), rng.uniform(0.5, 2.0)
        monotone.append(_fake("poly3", f, -k0 * (f[0] / f) ** p))
    for _ in range(5):  # barrel to pincushion, crossing zero at 30-70 % of the log range
        n = int(rng.integers(5, 11))
        f = 18.0 * np.geomspace(1, rng.uniform(3, 12), n)
        x = np.log(f / f[0]) / np.log(f[-1] / f[0])
        x0, slope = rng.uniform(0.3, 0.7), rng.uniform(0.01, 0.06)
        crossing.append(_fake("ptlens", f, slope * (x - x0)))
    for _ in range(3):  # pincushion that grows towards tele
        f = np.geomspace(28, 300, 6)
        rising.append(_fake("poly3", f, rng.uniform(0.001, 0.004) * np.log(f / 20)))

    for lens in monotone:
        t = lens_trend(lens)
        assert t.monotone_decreasing and t.min_location == "tele"
        assert t.spearman == pytest.approx(-1.0)
        assert not t.sign_change and t.sign_wide == t.sign_tele == -1
    for lens in crossing:
        t = lens_trend(lens)
        assert t.sign_change and t.barrel_to_pincushion
        assert t.min_location == "interior" and not t.monotone_decreasing
    for lens in rising:
        t = lens_trend(lens)
        assert t.min_location == "wide" and t.spearman == pytest.approx(1.0)
        assert not t.monotone_decreasing and not t.tele_below_wide
        assert t.sign_wide == t.sign_tele == 1

    s = distortion_trend(monotone + crossing + rising)
    assert s.n_lenses == 15
    assert s.frac_monotone_decreasing == pytest.approx(7 / 15)
    assert s.frac_sign_change == pytest.approx(5 / 15)
    assert s.frac_barrel_to_pincushion == pytest.approx(5 / 15)
    assert s.min_location_frac == pytest.approx(
        {"wide": 3 / 15, "interior": 5 / 15, "tele": 7 / 15}
    )
    # Crossing lenses have a V-shaped |distortion|: their rank correlation can take either sign.
    assert 7 / 15 <= s.frac_spearman_negative <= 12 / 15


def test_trend_tolerance():
    # A tiny rise (0.5e-4 of the half-diagonal) in an otherwise falling lens breaks strict
    # monotonicity but not a 1e-4 tolerance.
    k = np.array([-0.02, -0.01, -0.005, -0.005 * 1.001, -0.002])
    lens = _fake("poly3", np.array([10.0, 15, 20, 25, 30]), k)
    assert not lens_trend(lens).monotone_decreasing
    assert lens_trend(lens, tol=1e-4).monotone_decreasing


# ---------------------------------------------------------------------------------------------
# A real lens's distortion for rendered zoom sweeps


def _corner(terms: np.ndarray, fx: np.ndarray, size) -> np.ndarray:
    """OpenCV's radial displacement at the image corner, fraction of the half-diagonal."""
    r2 = (0.5 * math.hypot(*size) / fx) ** 2
    return terms[:, 0] * r2 + terms[:, 1] * r2 ** 2 + terms[:, 4] * r2 ** 3


def test_opencv_distortion_renders_the_measured_corner(lenses):
    # poly3 is even in r, so OpenCV's terms hold it exactly: on steps that land on the lens's
    # calibrated focal lengths the corner is lensfun's own measure (another code path), and
    # half way (in log f) between two of them it is their mean (linear interpolation)
    lens = by_model(lenses, "Nikon AF Zoom-Nikkor 80-400mm f/4.5-5.6D ED VR 183")
    size = (1280, 720)
    fx = 29.0 * lens.focal_mm
    terms, residual = lens.opencv_distortion(fx, size)
    assert residual < 1e-9 and np.all(terms[:, 2:4] == 0)
    np.testing.assert_allclose(_corner(terms, fx, size), lens.measure().corner, atol=1e-12)
    mid = np.sqrt(fx[1] * fx[2])
    steps = np.array([fx[0], mid, fx[-1]])
    terms, _ = lens.opencv_distortion(steps, size)
    assert _corner(terms, steps, size)[1] == pytest.approx(lens.measure().corner[1:3].mean())


def test_opencv_distortion_of_ptlens_within_its_residual(lenses):
    # ptlens has odd powers of r: the fit's largest error over the frame is reported, and the
    # corner it renders is within it of the measured corner
    lens = by_model(lenses, G3)
    size = (1280, 720)
    fx = 100.0 * lens.focal_mm
    terms, residual = lens.opencv_distortion(fx, size)
    d = 0.5 * math.hypot(*size)
    corner = lens.measure().corner
    assert np.all(np.abs(_corner(terms, fx, size) - corner) * d <= residual + 1e-9)
    assert residual < 0.1 * np.abs(corner).max() * d


def test_find_lens_names_one_lens_or_says_which():
    from zoomcalib.study.lensfun import find_lens, sweep_distortion

    assert find_lens("zoom-nikkor 80-400", DATA).model.startswith("Nikon AF Zoom-Nikkor 80-400")
    with pytest.raises(ValueError, match=r"match 'Canon' .*name one lens"):
        find_lens("Canon", DATA)
    with pytest.raises(ValueError, match="0 zoom lenses"):
        find_lens("no such lens", DATA)
    options = sweep_distortion("80-400", np.geomspace(2300, 23000, 4), (1280, 720), DATA)
    assert options["dist"].shape == (4, 5)
    assert options["distortion_source"]["lens"].endswith("80-400mm f/4.5-5.6D ED VR 183")
