"""The calibration report: its numbers against hidden truth and Monte Carlo, and the page itself
loaded in a headless browser (Debian's chromium, when installed; the page's structure and
every embedded image are checked either way)."""

import base64
import html
import re
import shutil
import subprocess
from html.parser import HTMLParser

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from zoomcalib.calibrate import quality
from zoomcalib.calibrate.opencv_backend import calibrate_opencv
from zoomcalib.calibrate.report import write_report
from zoomcalib.calibrate.result import CalibrationResult, Observations
from zoomcalib.calibrate.synthetic import calibrated_run, sweep_detections
from zoomcalib.cli import main

SIZE = (640, 480)
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync"]


# ----------------------------------------------------------------------------------------------
# numbers


def _camera(fx=700.0, cx=330.0, cy=235.0, dist=(-0.2, 0.08, 0.0, 0.0, 0.0)):
    K = np.array([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]])
    return K, np.array(dist, float)


def _result(K, dist, rvecs=None, tvecs=None) -> CalibrationResult:
    n = 0 if rvecs is None else len(rvecs)
    return CalibrationResult("opencv", K, dist, {}, 0.0, np.zeros(n),
                             np.zeros((n, 3)) if rvecs is None else np.asarray(rvecs),
                             np.zeros((n, 3)) if tvecs is None else np.asarray(tvecs))


def test_view_geometry_recovers_tilt_and_distance(rng):
    board = np.array([[x, y, 0.0] for x in (0.0, 100.0) for y in (0.0, 60.0)])
    angles = rng.uniform(5, 40, 4)
    rvecs = [cv2.Rodrigues(cv2.Rodrigues(np.radians([a, 0, 0]))[0]
                           @ cv2.Rodrigues(np.radians([0, 0, 30]))[0])[0].ravel()
             for a in angles]  # tilt about x after a spin about the optical axis
    ranges = rng.uniform(400, 900, 4)
    tvecs = []
    for r, d in zip(rvecs, ranges, strict=True):
        R = cv2.Rodrigues(r)[0]
        tvecs.append(np.array([0.0, 0.0, d]) - R @ board.mean(axis=0))
    obs = Observations(board, [], SIZE)
    got = quality.view_geometry(_result(*_camera(), rvecs, tvecs), obs)
    np.testing.assert_allclose(got.tilt_deg, angles, atol=1e-9)
    np.testing.assert_allclose(got.distance, ranges, rtol=1e-12)


def _full_field(rng, n=400):
    return rng.uniform([0, 0], [SIZE[0] - 1, SIZE[1] - 1], (n, 2))


def test_coverage_verdict_names_fronto_parallel_views_and_a_centred_board(rng):
    distances = np.array([500.0, 650.0, 800.0])
    tilted = quality.ViewGeometry(np.array([5.0, 25.0, 35.0]), distances)
    flat = quality.ViewGeometry(np.full(3, quality.MIN_TILT_DEG - 2), distances)
    # full field, tilted views at three distances: no problem
    problems, summary = quality.coverage_verdict(_full_field(rng), SIZE, tilted)
    assert problems == [] and "largest tilt 35.0 deg" in summary
    problems, _ = quality.coverage_verdict(_full_field(rng), SIZE, flat)
    assert len(problems) == 1 and "fronto-parallel" in problems[0]
    # a board in the middle third of the image: outer region and corners not reached
    centre = rng.uniform([SIZE[0] / 3, SIZE[1] / 3], [2 * SIZE[0] / 3, 2 * SIZE[1] / 3],
                         (400, 2))
    problems, _ = quality.coverage_verdict(centre, SIZE, tilted)
    assert any("outer region" in p for p in problems)
    assert any("a corner of the image has no point" in p for p in problems)
    one_distance = quality.ViewGeometry(tilted.tilt_deg, np.array([600.0, 610.0, 620.0]))
    problems, _ = quality.coverage_verdict(_full_field(rng), SIZE, one_distance)
    assert len(problems) == 1 and "one distance" in problems[0]


def test_projection_difference_of_a_principal_point_shift_is_the_shift():
    K, dist = _camera(dist=(0, 0, 0, 0, 0))
    K2 = K.copy()
    K2[0, 2] += 3.0
    K2[1, 2] -= 4.0
    _, _, diff = quality.projection_difference(_result(K, dist), _result(K2, dist), SIZE, columns=9)
    np.testing.assert_allclose(diff, 5.0, atol=1e-6)  # undistortPoints: float32 input


def test_observed_region_is_the_hull_of_the_points():
    square = np.array([[100.0, 100.0], [300.0, 100.0], [300.0, 300.0], [100.0, 300.0],
                       [200.0, 200.0]])
    xs, ys = np.array([50.0, 150.0, 250.0, 350.0]), np.array([50.0, 150.0, 250.0])
    hull, inside = quality.observed_region(square, xs, ys)
    assert len(hull) == 4
    np.testing.assert_array_equal(inside, [[0, 0, 0, 0], [0, 1, 1, 0], [0, 1, 1, 0]])


def test_projection_uncertainty_matches_monte_carlo_of_refits(rng):
    """The predicted 1-sigma against the spread of mrcal's mean-frame reprojection over 60
    refits of fresh noise, from the truth (not from the code under test). At the boards'
    distance the pose terms cancel most of the intrinsics' error and at 5x it does not, so an
    intrinsics-only propagation fails one of the two."""
    board = np.array([[25.0 * i, 25.0 * j, 0.0] for j in range(6) for i in range(9)])
    centre = board.mean(axis=0)
    K, dist = _camera()
    poses = []
    for _ in range(8):
        R = cv2.Rodrigues(np.radians([*rng.uniform(-30, 30, 2), rng.uniform(-10, 10)]))[0]
        t = np.array([*rng.uniform(-40, 40, 2), rng.uniform(500, 700)]) - R @ centre
        poses.append((cv2.Rodrigues(R)[0].ravel(), t))
    clean = [cv2.projectPoints(board, r, t, K, dist)[0].reshape(-1, 2) for r, t in poses]
    noise = 0.3

    def draw():
        return Observations(board, [(np.arange(len(board)), c + rng.normal(0, noise, c.shape))
                                    for c in clean], SIZE)

    fit = calibrate_opencv(draw())
    refits = [calibrate_opencv(draw()) for _ in range(60)]
    for distance in (600.0, 3000.0):
        xs, ys, sigma = quality.projection_uncertainty(fit, draw(), distance, columns=12)
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        ray = cv2.undistortPoints(grid.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
        ray = np.column_stack([ray, np.ones(len(ray))])
        p = distance * ray / np.linalg.norm(ray, axis=1, keepdims=True)
        boards = [(p - t) @ cv2.Rodrigues(r)[0] for r, t in poses]  # truth: camera -> board
        q = []
        for res in refits:
            mean = np.mean([x @ cv2.Rodrigues(r)[0].T + t for x, r, t in
                            zip(boards, res.rvecs, res.tvecs, strict=True)], axis=0)
            q.append(cv2.projectPoints(mean, np.zeros(3), np.zeros(3), res.K,
                                       res.dist)[0].reshape(-1, 2))
        q = np.array(q)
        d = q - q.mean(axis=0)
        cov = np.einsum("kni,knj->nij", d, d) / (len(q) - 1)
        mc = np.sqrt(np.linalg.eigvalsh(cov)[:, 1]).reshape(sigma.shape)
        # where the boards were seen (outside, the model is extrapolated and far from
        # linear); 60 draws give a sigma to ~9 % (1-sigma), 0.7-1.4 allows > 3.5 of them
        inside = quality.observed_region(np.concatenate(clean), xs, ys)[1]
        assert inside.sum() >= 10
        ratio = sigma[inside] / mc[inside]
        assert np.all((ratio > 0.7) & (ratio < 1.4)), (distance, ratio)


# ----------------------------------------------------------------------------------------------
# the page


class _Page(HTMLParser):
    """Tag balance, sections and images of an HTML page."""

    VOID = {"img", "meta", "br", "hr", "link", "input"}

    def __init__(self):
        super().__init__()
        self.stack, self.errors, self.ids, self.images = [], [], [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.append(attrs["id"])
        if tag == "img":
            self.images.append(attrs.get("src", ""))
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1] if self.stack else 'nothing'}")
        else:
            self.stack.pop()


def _check_structure(text: str, steps: list[str]) -> _Page:
    page = _Page()
    page.feed(text)
    page.close()
    assert page.errors == [] and page.stack == [], (page.errors, page.stack)
    assert [i for i in page.ids if i.startswith("step-")] == [f"step-{s}" for s in steps]
    assert "zoom-range" in page.ids
    for src in page.images:  # every figure is in the page and is a PNG that decodes
        assert src.startswith("data:image/png;base64,")
        png = np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8)
        image = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
        assert image is not None and min(image.shape[:2]) > 100
    return page


def _chromium_dom(path, profile) -> str | None:
    """The page's DOM after load, dumped by headless chromium; None when it is not installed."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        return None
    out = subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                          "--virtual-time-budget=10000", "--dump-dom", path.as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """A 3-step synthetic set with 3 gross outliers in one image, calibrated by the bundle (which
    rejects them), with one image whose detection failed."""
    sweep = sweep_detections(np.random.default_rng(20261124), steps=3, views=8,
                             outliers={(1, 2): 15.0})
    run = calibrated_run(sweep, "bundle")
    run.skipped_images["zoom_02"] = ["zoom_02_view08.png: no chessboard found"]
    out = tmp_path_factory.mktemp("report")
    return write_report(run, out), list(sweep.observations)


def test_report_loads_in_a_browser_with_every_figure(report, tmp_path):
    path, steps = report
    text = path.read_text(encoding="utf-8")
    page = _check_structure(text, steps)
    assert len(page.images) == 5 * len(steps) + 1
    dom = _chromium_dom(path, tmp_path / "profile")
    if dom is not None:
        assert re.search(r'<body[^>]*data-images-loaded="all"', dom), dom[:500]
        assert f'data-image-count="{len(page.images)}"' in dom
        for s in steps:
            assert f'id="step-{s}"' in dom
        text = dom
    assert "Step zoom_01" in text and "The zoom range" in text
    # every step says how its three confidence signals fit together
    assert text.count("Reading the signals together") == len(steps)
    # a run without its image folders says it cannot draw the worst image's corners
    assert text.count("could not be read to draw its corners") == len(steps)


def test_report_names_the_rejected_and_the_left_out_images(report):
    text = report[0].read_text(encoding="utf-8")
    assert "zoom_01_view02.png: 3 points rejected" in text
    assert "zoom_02_view08.png: not in the fit (no chessboard found)" in text
    # the other steps' images are not marked
    assert "zoom_00_view02.png: " not in text


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "set"
    res = CliRunner().invoke(main, ["render", "--zoom", "0.1,0.5", "--views", "5",
                                    "--size", "640x480", "--through", "model", "--seed", "3",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def test_calibrate_writes_the_report_unless_told_not_to(rendered, tmp_path):
    args = ["calibrate", str(rendered), "--pattern", "chessboard:9x6:25", "--per-step",
            "--backend", "opencv", "--workers", "1"]
    res = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    text = (tmp_path / "a" / "report.html").read_text(encoding="utf-8")
    page = _check_structure(text, ["zoom_00", "zoom_01"])
    # the images are at hand: each step draws its worst one's corners (one figure more)
    assert text.count("<h3>The image of the largest error</h3>") == 2
    assert len(page.images) == 6 * 2 + 1
    assert "report.html" in (tmp_path / "a" / "manifest.json").read_text()
    # images chosen by the user are drawn too: all of zoom_01's, one of which is its worst
    chosen = [f"--report-image=zoom_01/view_{i:02d}.png" for i in range(5)]
    res = CliRunner().invoke(main, [*args, *chosen, "--out", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    path = tmp_path / "c" / "report.html"
    text = path.read_text(encoding="utf-8")
    assert text.count("<h3>A chosen image</h3>") == 4
    assert all(f"corners of view_{i:02d}.png" in text for i in range(5))
    page = _check_structure(text, ["zoom_00", "zoom_01"])
    assert len(page.images) == 6 * 2 + 1 + 4
    dom = _chromium_dom(path, tmp_path / "profile")
    if dom is not None:
        assert re.search(r'<body[^>]*data-images-loaded="all"', dom), dom[:500]
        assert f'data-image-count="{len(page.images)}"' in dom
    res = CliRunner().invoke(main, [*args, "--report-image", "zoom_01/nope.png",
                                    "--out", str(tmp_path / "d")])
    assert res.exit_code == 2 and "zoom_01/nope.png: no such image in step zoom_01" \
        in res.output, res.output
    res = CliRunner().invoke(main, [*args, "--report-distance", "250", "--no-report",
                                    "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "b" / "report.html").exists()
    assert (tmp_path / "b" / "calibration.json").exists()


def test_every_step_status_reaches_the_summary_the_files_and_the_report(rendered, tmp_path):
    import csv
    import json

    import yaml

    out = tmp_path / "s"
    res = CliRunner().invoke(main, ["calibrate", str(rendered), "--pattern", "chessboard:9x6:25",
                                    "--per-step", "--backend", "opencv", "--workers", "1",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "calibration.json").read_text())["meta"]
    status = {s: v["status"] for s, v in meta["status"].items()}
    assert set(status) == {"zoom_00", "zoom_01"}
    assert all(v in ("ok", "imprecise", "unusable") for v in status.values())
    line = next(t for t in res.output.splitlines() if t.startswith("status: "))
    assert all(f"{s} {v}" in line for s, v in status.items())
    with open(out / "zoom_calibration.csv", newline="") as f:
        assert {r["step"]: r["status"] for r in csv.DictReader(f)} == status
    index = yaml.safe_load((out / "ros" / "camera_info_index.yaml").read_text())
    assert {e["step"]: e["status"] for e in index["steps"]} == status
    text = (out / "report.html").read_text(encoding="utf-8")
    assert "<th>status</th>" in text
    assert all(f"<b>{v}</b>" in text for v in status.values())
    # the summary table's fx and fy with their sigmas, as calibration.json has them
    assert "<th>fx [px]</th><th>fy [px]</th>" in text
    for step, entry in json.loads((out / "calibration.json").read_text())["steps"].items():
        best = entry[meta["table_backend"][step]]
        K, sd = np.array(best["K"]), best["sd"]
        assert f"<td>{K[0, 0]:.2f} &plusmn; {sd['fx']:.2f}</td>" in text, step
        assert f"<td>{K[1, 1]:.2f} &plusmn; {sd['fy']:.2f}</td>" in text, step


def test_flags_reach_the_summary_with_severity_and_action_and_the_report_with_details(
        rendered, tmp_path):
    import json

    out = tmp_path / "f"
    res = CliRunner().invoke(main, ["calibrate", str(rendered), "--pattern", "chessboard:9x6:25",
                                    "--per-step", "--backend", "opencv", "--workers", "1",
                                    "--out", str(out)])
    assert res.exit_code == 0, res.output
    records = json.loads((out / "calibration.json").read_text())["meta"]["flag_records"]
    assert records, "the 5-view steps are expected to be flagged"
    text = (out / "report.html").read_text(encoding="utf-8")
    lines = res.output.splitlines()
    todo = [t for t in lines if t.startswith("  to do (")]
    for step, flags in records.items():
        head = next(t for t in lines if t.startswith(f"FLAGGED step {step} "))
        assert head.startswith(f"FLAGGED step {step} ({flags[0]['severity']}): ")
        for f in flags:
            assert f"{f['text']} [{f['severity']}]" in head
            # each action once, naming every step that needs it
            (line,) = [t for t in todo if t.endswith(f"): {f['action']}")]
            assert step in line.split("): ")[0]
            assert html.escape(f["text"], quote=True) in text
            assert html.escape(f["action"], quote=True) in text
    assert "<summary>details, what to do</summary>" in text


def test_the_residual_cloud_is_named_by_what_a_test_finds_in_it():
    # hidden: the same corner noise alone, with a radial error of the size of the noise (a
    # k1 the model missed), with a smooth field that is not radial, and stretched along y
    rng = np.random.default_rng(11)
    centre = np.array([640.0, 360.0])
    points = rng.uniform([0, 0], [1280, 720], (800, 2))
    noise = rng.normal(0, 0.2, (800, 2))
    d = points - centre
    r = np.linalg.norm(d, axis=1, keepdims=True) / 734.0
    radial = 0.3 * r**2 * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    smooth = np.column_stack([0.25 * np.sin(points[:, 1] / 300.0), 0 * points[:, 0]])
    words = {}
    for name, e in (("noise", noise), ("radial", noise + radial), ("smooth", noise + smooth),
                    ("elongated", noise * [1.0, 2.5])):
        words[name], numbers = quality.residual_pattern(points, e, centre)
    assert words["noise"].startswith("a round cloud, no pattern"), words
    assert words["radial"].startswith("a radial pattern"), words
    assert words["smooth"].startswith("a smooth field"), words
    assert words["elongated"].startswith("an elongated cloud: sd 2."), words
    assert quality.residual_pattern(points[:5], noise[:5], centre)[0].startswith("too few")
    # an error smooth within each of 8 views but of a random sign per view: pooled, nothing;
    # view by view, a smooth field
    view = np.arange(800) % 8
    sign = rng.choice([-1.0, 1.0], 8)[view][:, None]
    shifted = noise + sign * np.column_stack([0.2 * (points[:, 0] / 640 - 1), 0 * view])
    assert quality.residual_pattern(points, shifted, centre)[0].startswith("a round cloud")
    word = quality.residual_pattern(points, shifted, centre, view)[0]
    assert word.startswith("a smooth field") and "within each view" in word, word


def test_image_labels_keep_what_tells_them_apart():
    from zoomcalib.report_plots import per_view_figure, short_labels

    names = [f"live_ch0_2025080509{m:02d}{s:02d}.png" for m, s in ((22, 46), (23, 1), (37, 55))]
    labels, prefix = short_labels(names)
    assert prefix == "live_ch0_2025080509" and labels == ["2246.png", "2301.png", "3755.png"]
    assert [prefix + t for t in labels] == names
    # a prefix that is a whole name, or too short to matter, is kept
    assert short_labels(["a.png", "a.png.bak"]) == (["a.png", "a.png.bak"], "")
    assert short_labels(["view1.png", "view2.png"]) == (["1.png", "2.png"], "view")
    assert short_labels(["im1", "im2"])[1] == ""
    png = per_view_figure(names, np.array([0.5, 0.7, 0.4]), {}, ["live_ch0_20250805093000.png"])
    assert cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED) is not None


def test_distortion_map_and_board_outlines():
    # a pure k1: a pixel at normalised radius r images at r (1 + k1 r^2), so the map at the
    # image corner is f k1 r^3 (r of the undistorted ray, solved here by fixed point)
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    res = CalibrationResult("opencv", K, np.array([-0.2, 0, 0, 0, 0]), {}, 0.1, np.zeros(1),
                            np.zeros((1, 3)), np.array([[0.0, 0.0, 500.0]]))
    xs, ys, shift = quality.distortion_map(res, (640, 480), columns=41)
    rd = np.hypot(319.5, 239.5) / 800.0
    r = rd
    for _ in range(50):
        r = rd / (1 - 0.2 * r**2)
    assert shift[0, 0] == pytest.approx(800.0 * (r - rd), rel=1e-3)
    assert shift[len(ys) // 2, len(xs) // 2] < 1e-3 * shift[0, 0]
    board = np.array([[0.0, 0, 0], [100, 0, 0], [100, 50, 0], [0, 50, 0]])
    outline = quality.board_outlines(res, board)
    assert outline.shape == (1, 5, 3)
    np.testing.assert_allclose(outline[0, :4], board + [0, 0, 500])
    np.testing.assert_allclose(outline[0, 4], outline[0, 0])


def test_fix_holds_intrinsics_per_step_and_zoom_wide(rendered, tmp_path):
    import json

    out = tmp_path / "fix"
    res = CliRunner().invoke(main, ["calibrate", str(rendered), "--pattern", "chessboard:9x6:25",
                                    "--per-step", "--fix", "principal-point", "--fix", "k3",
                                    "--fix", "aspect", "--workers", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["meta"]["fixed"] == ["principal-point", "k3", "aspect"]
    for by_backend in doc["steps"].values():
        assert list(by_backend) == ["opencv"]  # --fix: the OpenCV backend alone
        e = by_backend["opencv"]
        K = np.array(e["K"])
        assert (K[0, 2], K[1, 2]) == (319.5, 239.5)  # the 640 x 480 image's centre
        assert K[0, 0] == K[1, 1] and e["dist"][4] == 0.0
        assert e["sd"]["cx"] == 0.0 and e["sd"]["k3"] == 0.0
    # the zoom-wide adjustment holds them too
    out = tmp_path / "fix_zoom_wide"
    res = CliRunner().invoke(main, ["calibrate", str(rendered), "--pattern", "chessboard:9x6:25",
                                    "--fix", "principal-point", "--fix", "tangential",
                                    "--workers", "1", "--out", str(out)])
    assert res.exit_code in (0, 3), res.output
    doc = json.loads((out / "calibration.json").read_text())
    rows = [by_backend["zoom-wide"] for by_backend in doc["steps"].values()]
    assert len(rows) == len(doc["steps"]) >= 2
    for e in rows:
        K = np.array(e["K"])
        assert (K[0, 2], K[1, 2]) == (319.5, 239.5) and e["dist"][2:4] == [0.0, 0.0]
        assert {"cx", "cy", "p1", "p2"} <= set(e["info"]["fixed"])
    # not where it cannot hold: the bundle
    res = CliRunner().invoke(main, ["calibrate", str(rendered), "--pattern",
                                    "chessboard:9x6:25", "--fix", "k3", "--per-step",
                                    "--backend", "bundle", "--out", str(tmp_path / "no")])
    assert res.exit_code == 2 and "--fix" in res.output, res.output


def test_a_chosen_image_is_found_by_name_or_step_and_name():
    from zoomcalib.calibrate.report import chosen_views
    from zoomcalib.calibrate.result import Observations
    from zoomcalib.calibrate.run import CalibrateRun

    board = np.zeros((4, 3))
    views = [(np.arange(4), np.zeros((4, 2)))] * 3
    run = CalibrateRun(results={"a": {}, "b": {}}, observations={
        "a": Observations(board, views, (64, 48), ["x.png", "y.png", "z.png"]),
        "b": Observations(board, views, (64, 48), ["y.png", "w.png", "x.png"])})
    chosen, unknown = chosen_views(run, ("y.png", "b/x.png", "a/w.png", "q.png"))
    assert chosen == {"a": [1], "b": [0, 2]}
    assert unknown == ["a/w.png", "q.png"]
