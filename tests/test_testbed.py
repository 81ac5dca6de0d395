"""The realistic test bed: waving boards, non-Gaussian PSFs, JPEG output and the zoom sweep.

Truth is recomputed here independently (cv2.projectPoints, the sine modes written out, Bessel
functions for the Airy pattern), never taken from the renderer.
"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.special import j0, j1

from zoomcalib.calibrate.stepfolders import zoom_steps
from zoomcalib.camera import CameraModel, Sensor
from zoomcalib.cli import main
from zoomcalib.detect import detect_image
from zoomcalib.render.dataset import render_dataset
from zoomcalib.render.image import (
    BoardSurface,
    Optics,
    Radiometry,
    board_coordinates,
    camera_mapping,
    render_coverage,
    render_image,
)
from zoomcalib.render.sweep import render_zoom_sweep
from zoomcalib.targets import circle_grid, parse_pattern

# one mode: 0.6 mm peak, 110 mm wavelength along x, slightly oblique
WAVE = ((0.6, 1 / 110, 0.002, 0.4),)


def _wave_height(x, y, modes):
    return sum(a * np.sin(2 * np.pi * (kx * x + ky * y) + ph) for a, kx, ky, ph in modes)


def _project(points, camera, R, t):
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t, camera.K,
                              camera.dist)
    return uv.reshape(-1, 2)


def _wavy_scene(rng):
    sensor = Sensor(640, 480, 0.00645)
    camera = CameraModel(800.0, 800.0, 320.3, 239.6, np.array([-0.1, 0.0, 0.0, 0.0, 0.0]), sensor)
    target = parse_pattern("chessboard:9x6:20")
    # 35 degrees about y: the waves' height moves corners sideways by ~ w sin(35) * 2.1 px/mm
    R = cv2.Rodrigues(np.array([rng.uniform(-0.1, 0.1), np.deg2rad(35.0), 0.05]))[0]
    t = np.array([0.0, 0.0, 380.0]) - R @ target.object_points.mean(axis=0)
    return sensor, camera, target, R, t


def test_wavy_board_truth_lies_on_the_surface(rng):
    sensor, camera, target, R, t = _wavy_scene(rng)
    view = render_image(target, camera_mapping(camera), R, t, sensor, Optics(),
                        Radiometry(noise_sd=0.0), rng=1, surface=BoardSurface(WAVE))
    p = target.object_points.copy()
    p[:, 2] = _wave_height(p[:, 0], p[:, 1], WAVE)
    wavy = _project(p, camera, R, t)
    flat = _project(target.object_points, camera, R, t)
    # the distortion model is the same, so only the iterative undistortion (< 1e-9 px) differs
    assert np.max(np.abs(view.points_px - wavy)) < 1e-6
    shift = np.linalg.norm(wavy - flat, axis=1)
    assert shift.max() > 0.6 and np.mean(shift) > 0.35  # the wave is visible in px


def test_board_coordinates_meet_the_wavy_surface(rng):
    sensor, camera, target, R, t = _wavy_scene(rng)
    bx, by = board_coordinates(camera_mapping(camera), R, t, sensor,
                               surface=BoardSurface(WAVE))
    u = rng.uniform(20, sensor.width_px - 20, 200)
    v = rng.uniform(20, sensor.height_px - 20, 200)
    b = np.stack([bx.ev(v, u), by.ev(v, u)], -1)
    p = np.concatenate([b, _wave_height(b[:, 0], b[:, 1], WAVE)[:, None]], 1)
    # back through the camera: the spline of 4-px nodes interpolates to ~1e-5 px
    assert np.max(np.abs(_project(p, camera, R, t) - np.stack([u, v], -1))) < 1e-3
    # the plane's intersection misses by the wave's sideways shift
    p[:, 2] = 0.0
    assert np.max(np.abs(_project(p, camera, R, t) - np.stack([u, v], -1))) > 0.3


def test_too_steep_surface_is_refused(rng):
    sensor, camera, target, R, t = _wavy_scene(rng)
    steep = BoardSurface(((15.0, 1 / 20.0, 0.0, 0.0),))  # slope up to 4.7
    with pytest.raises(ValueError, match="did not converge"):
        board_coordinates(camera_mapping(camera), R, t, sensor, surface=steep)


@pytest.mark.parametrize("method", ["classic", "model"])
def test_detector_finds_the_wavy_corners(rng, method):
    sensor, camera, target, R, t = _wavy_scene(rng)
    view = render_image(target, camera_mapping(camera), R, t, sensor, Optics(), Radiometry(),
                        rng=rng, surface=BoardSurface(WAVE))
    flat = _project(target.object_points, camera, R, t)
    det = detect_image(view.image, target, method)
    assert det.error is None and len(det.ids) == target.n_points
    err = det.points - view.points_px[det.ids]
    err_flat = det.points - flat[det.ids]
    # At 2 DN noise, 0.7 px blur, the same view on a flat board gives 0.03 px RMS (classic)
    # and 0.01 px (model) against its truth; the wave moves corners by 0.46 px on average.
    assert np.sqrt(np.mean(np.sum(err**2, 1))) < 0.08
    assert np.sqrt(np.mean(np.sum(err_flat**2, 1))) > 0.35


# --- PSFs: a small dark disc at the image centre is (nearly) a point source.
N = 96
DISC_MM = 0.5  # radius; 1 px per mm at the distance below


def _point_image(optics, supersample=4, method="auto"):
    sensor = Sensor(N, N, 0.00645)
    camera = CameraModel(1000.0, 1000.0, (N - 1) / 2, (N - 1) / 2, np.zeros(5), sensor)
    target = circle_grid(2, 2, 1000.0, radius=DISC_MM)  # the other discs lie far outside
    cov = render_coverage(target, camera_mapping(camera), np.eye(3),
                          np.array([0.0, 0.0, 1000.0]), sensor, 1.0, supersample, method=method,
                          optics=optics)
    vv, uu = np.mgrid[0:N, 0:N]
    return 1.0 - cov, uu - (N - 1) / 2, vv - (N - 1) / 2


@pytest.mark.parametrize("angle", [30.0, -30.0])
def test_elliptical_psf_second_moments(angle):
    optics = Optics(blur_px=1.0, f_number=1e-6, psf="elliptical", ellipse_ratio=0.5,
                    ellipse_angle_deg=angle)
    d, du, dv = _point_image(optics)
    m = d.sum()
    cov = np.array([[np.sum(d * du * du), np.sum(d * du * dv)],
                    [np.sum(d * du * dv), np.sum(d * dv * dv)]]) / m
    a = np.deg2rad(angle)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    # PSF + pixel box (1/12 per axis) + uniform disc (r^2 / 4 per axis)
    want = rot @ np.diag([1.0, 0.25]) @ rot.T + np.eye(2) * (1 / 12 + DISC_MM**2 / 4)
    # measured agreement 0.5 % at supersample 4 (the disc's sub-sample coverage is approximate)
    assert np.allclose(cov, want, atol=0.02)
    assert np.sign(cov[0, 1]) == np.sign(angle)


def test_airy_psf_encircled_energy_and_dark_ring():
    radius = 4.0
    d, du, dv = _point_image(Optics(blur_px=0.0, psf="airy", airy_radius_px=radius))
    rr = np.hypot(du, dv)

    def outside(rho):  # Airy energy beyond rho, of the pattern cut at 6 radii
        ee = [1 - j0(x) ** 2 - j1(x) ** 2 for x in (3.8317 * rho / radius, 3.8317 * 6)]
        return (ee[1] - ee[0]) / ee[1]

    for rho in (radius, 2 * radius, 3 * radius):
        # measured within 3.5 % (the pixel box and the disc spread the core slightly)
        assert d[rr > rho].sum() / d.sum() == pytest.approx(outside(rho), rel=0.06)
    ring = [d[(rr >= r - 0.25) & (rr < r + 0.25)].mean() for r in (4.5, 5.5)]
    assert ring[0] < 0.7 * ring[1]  # the first dark ring, then the first bright one


def test_halo_psf_tail():
    d, du, dv = _point_image(Optics(blur_px=1.0, f_number=1e-6, psf="halo",
                                    halo_fraction=0.05, halo_sigma_px=6.0))
    rr = np.hypot(du, dv)
    for rho in (5.0, 10.0):
        # beyond 5 px the 1-px core has < 1e-5 left; the halo's share is f exp(-rho^2 / 2 s^2)
        want = 0.05 * np.exp(-(rho**2) / 72.0)
        assert d[rr > rho].sum() / d.sum() == pytest.approx(want, rel=0.03)


def test_non_gaussian_psf_cannot_be_analytic():
    for psf in ("airy", "halo"):
        with pytest.raises(ValueError, match="analytic renderer paints a Gaussian PSF only"):
            _point_image(Optics(blur_px=1.0, psf=psf), method="analytic")
    # the elliptical closed form is written for straight edges, not for the dots' rims
    with pytest.raises(ValueError, match="no dots"):
        _point_image(Optics(blur_px=1.0, psf="elliptical"), method="analytic")
    with pytest.raises(ValueError, match="psf must be one of"):
        Optics(psf="lorentzian")


@pytest.mark.parametrize("angle", [30.0, -60.0])
def test_elliptical_psf_closed_form_matches_its_kernel(angle):
    """The closed-form elliptical chessboard against the supersampled one (the PSF's kernel
    convolved on a fine grid, another path), on a tilted view with several corners."""
    sensor = Sensor(160, 120, 0.00645)
    camera = CameraModel(600.0, 600.0, 79.5, 59.5, np.zeros(5), sensor)
    target = parse_pattern("chessboard:6x5:20")
    R = cv2.Rodrigues(np.array([0.35, -0.25, 0.1]))[0]
    t = np.array([-60.0, -50.0, 1000.0])
    optics = Optics(blur_px=0.7, f_number=1e-6, psf="elliptical", ellipse_ratio=0.5,
                    ellipse_angle_deg=angle)
    gauss = Optics(blur_px=0.7, f_number=1e-6)

    def cover(o, method, supersample=8):
        return render_coverage(target, camera_mapping(camera), R, t, sensor, 0.7, supersample,
                               method=method, optics=o)[4:-4, 4:-4]  # off the image border

    closed, fine = cover(optics, "analytic"), cover(optics, "supersample")
    # measured: 4.3e-4 at most (the Gaussian's closed form and its 8x8 supersampling differ
    # by up to 2.7e-4 on this view); 2e-3 of the contrast is half a DN at 8 bits
    assert np.abs(closed - fine).max() < 2e-3
    # and the test sees the shape: the isotropic Gaussian differs by far more
    assert np.abs(cover(gauss, "analytic") - fine).max() > 0.05
    assert np.array_equal(cover(optics, "auto", 4), closed)  # 'auto' takes the closed form


# --- JPEG and the waving board in render_dataset


@pytest.fixture(scope="module")
def jpeg_and_png_sets(tmp_path_factory, laikin):
    root = tmp_path_factory.mktemp("sets")
    sensor = Sensor(320, 240, 0.0258)
    kw = dict(zoom=[0.0, 0.5], n_views=2, pattern="chessboard:9x6:25", seed=3, sensor=sensor)
    docs = {name: render_dataset(laikin, None, root / name, **kw, **extra)
            for name, extra in (("png", {}), ("jpg", {"jpeg_quality": 80}),
                                ("wave", {"board_surface": 0.5}))}
    return root, docs


def test_jpeg_changes_images_not_truth(jpeg_and_png_sets):
    root, docs = jpeg_and_png_sets
    files = [v["file"] for st in docs["jpg"]["steps"] for v in st["views"]]
    assert files and all(f.endswith(".jpg") for f in files)
    assert docs["jpg"]["jpeg_quality"] == 80
    for st_j, st_p in zip(docs["jpg"]["steps"], docs["png"]["steps"], strict=True):
        for vj, vp in zip(st_j["views"], st_p["views"], strict=True):
            assert vj["points_px"] == vp["points_px"]
            jpg = cv2.imread(str(root / "jpg" / vj["file"]), cv2.IMREAD_UNCHANGED)
            png = cv2.imread(str(root / "png" / vp["file"]), cv2.IMREAD_UNCHANGED)
            diff = np.abs(jpg.astype(float) - png)
            assert jpg.shape == png.shape and 0.3 < diff.mean() < 4.0  # 2 DN noise, quality 80
    with pytest.raises(ValueError, match="8-bit"):
        render_dataset(None, None, root / "bad", [0.0], 1, "chessboard:9x6:25",
                       radiometry=Radiometry(bits=16), jpeg_quality=90)


def test_dataset_wave_moves_the_truth(jpeg_and_png_sets):
    _, docs = jpeg_and_png_sets
    for st_w, st_p in zip(docs["wave"]["steps"], docs["png"]["steps"], strict=True):
        modes = st_w["board_surface"]["modes"]
        assert modes and st_p["board_surface"] is None
        for vw, vp in zip(st_w["views"], st_p["views"], strict=True):
            shift = np.linalg.norm(np.subtract(vw["points_px"], vp["points_px"]), axis=1)
            assert shift.max() > 1e-3  # 0.5 mm waves on a 0.2-1 m board, poses of 15-45 deg


def test_cli_render_jpeg(tmp_path):
    res = CliRunner().invoke(main, ["render", "--nominal", "--steps", "1", "--views", "1",
                                    "--size", "320x240", "--jpeg-quality", "70", "--wave", "0.3",
                                    "--psf", "elliptical", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    assert len(list((tmp_path / "r" / "zoom_00").glob("*.jpg"))) == 1
    doc = json.loads((tmp_path / "r" / "dataset.json").read_text())
    assert doc["optics"]["psf"] == "elliptical" and doc["steps"][0]["board_surface"]["modes"]
    res = CliRunner().invoke(main, ["render", "--nominal", "--bits", "16", "--jpeg-quality",
                                    "70", "--out", str(tmp_path / "bad")])
    assert res.exit_code != 0 and "8-bit" in res.output


# --- the zoom sweep

FX = (1150.0, 11500.0)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    doc = render_zoom_sweep(out, fx_range=FX, steps=3, views=3, size=(640, 360),
                            board_surface=0.3, jpeg_quality=92, seed=5)
    return out, doc


def test_sweep_steps_read_back_as_zoom(sweep):
    out, doc = sweep
    steps = zoom_steps(out)
    assert [s[0] for s in steps] == [st["step"] for st in doc["steps"]]
    want = FX[0] * np.sqrt(10.0) ** np.arange(3)  # log-spaced
    assert np.allclose([s[2] for s in steps], want, rtol=1e-9)
    (out / "steps.csv").rename(out / "steps.off")  # without steps.csv: the folder names
    try:
        assert np.allclose([s[2] for s in zoom_steps(out)], want, atol=0.5)
    finally:
        (out / "steps.off").rename(out / "steps.csv")


def test_sweep_camera_and_poses_are_like_a_real_session(sweep):
    _, doc = sweep
    K = np.array([st["K"] for st in doc["steps"]])
    k1 = np.array([st["dist"][0] for st in doc["steps"]])
    drift = np.linalg.norm(K[-1, :2, 2] - K[0, :2, 2])
    assert 10.0 < drift < 100.0
    assert k1[0] < -0.05 and np.all(np.diff(np.abs(k1)) < 0)
    tilts = [[np.degrees(np.arccos(cv2.Rodrigues(np.array(v["rvec"]))[0][2, 2]))
              for v in st["views"]] for st in doc["steps"]]
    assert max(tilts[0]) > 12.0 and max(tilts[0]) <= 40.0 + 1e-9
    assert max(tilts[-1]) <= 3.0 + 1e-9
    for st in doc["steps"]:
        for v in st["views"]:
            p = np.array(v["points_px"])
            assert np.ptp(p[:, 1]) > 0.5 * 360 and v["visible"] and all(v["visible"])


def test_sweep_truth_is_the_projection_of_the_waving_board(sweep):
    out, doc = sweep
    modes = [(m["amplitude_mm"], m["kx_per_mm"], m["ky_per_mm"], m["phase_rad"])
             for m in doc["board_surface"]["modes"]]
    target = parse_pattern(doc["pattern"])
    p = target.object_points.copy()
    p[:, 2] = _wave_height(p[:, 0], p[:, 1], modes)
    assert 0.1 < np.max(np.abs(p[:, 2])) <= 0.3 + 1e-12
    for st in doc["steps"]:
        K, dist = np.array(st["K"]), np.array(st["dist"])
        for v in st["views"]:
            uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.array(v["rvec"]),
                                      np.array(v["tvec"]), K, dist)
            assert np.max(np.abs(uv.reshape(-1, 2) - v["points_px"])) < 1e-6
        # the image agrees: the classic detector on the JPEG of the first view
        image = cv2.imread(str(out / st["views"][0]["file"]), cv2.IMREAD_GRAYSCALE)
        det = detect_image(image, target, "classic")
        err = det.points - np.array(st["views"][0]["points_px"])[det.ids]
        # 2 DN noise, quality 92, 18-px squares: ~0.05 px; a pixel of principal point or
        # distortion error would show as a bias of that size
        assert det.error is None and np.sqrt(np.mean(np.sum(err**2, 1))) < 0.15


def test_sweep_non_gaussian_psf(tmp_path):
    doc = render_zoom_sweep(tmp_path, fx_range=FX, steps=1, views=1, size=(320, 180),
                            psf="airy", supersample=2,
                            optics=Optics(blur_px=0.5, airy_radius_px=2.0))
    assert doc["optics"]["psf"] == "airy" and doc["supersample"] == 2
    assert (tmp_path / doc["steps"][0]["views"][0]["file"]).is_file()


def test_cli_render_sweep(tmp_path):
    res = CliRunner().invoke(main, ["render-sweep", "--fx", "1150,11500", "--steps", "2",
                                    "--views", "1", "--size", "320x180", "--jpeg-quality", "90",
                                    "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    assert "fx_01150" in res.output and (tmp_path / "s" / "fx_11500" / "view_00.jpg").is_file()
    res = CliRunner().invoke(main, ["render-sweep", "--fx", "23000,2300", "--out",
                                    str(tmp_path / "bad")])
    assert res.exit_code != 0 and "MIN <= MAX" in res.output


@pytest.mark.parametrize("keystone", [False, True])
def test_axis_tilt_moves_the_image_by_fx_theta(tmp_path, laikin, keystone):
    from zoomcalib.camera import Sensor
    from zoomcalib.io import read_json
    from zoomcalib.optics.cam import solve_gaps
    from zoomcalib.optics.paraxial import exit_pupil_distance
    from zoomcalib.render.dataset import render_dataset

    sensor = Sensor(160, 120, 0.0516)  # the default field of view, few pixels
    tilt = np.random.default_rng(31).uniform(-1.0, 1.0, 2)  # mrad
    docs = []
    for name, axis in (("flat", None), ("tilted", tuple(tilt))):
        render_dataset(laikin, None, tmp_path / name, [0.3], 1, "chessboard:5x4:25", seed=2,
                       sensor=sensor, axis_tilt_mrad=axis, axis_tilt_keystone=keystone)
        docs.append(read_json(tmp_path / name / "dataset.json"))
    a, b = (d["steps"][0] for d in docs)
    shift = np.array([a["camera"]["fx"] * tilt[0], a["camera"]["fy"] * tilt[1]]) * 1e-3
    np.testing.assert_allclose([b["camera"]["cx"] - a["camera"]["cx"],
                                b["camera"]["cy"] - a["camera"]["cy"]], shift, atol=1e-9)
    # the tilted set's truth is the untilted lens's projection of the same pose, moved by shift
    # and, with the keystone, stretched about the principal point c by
    # (1 + pitch theta . (uv - c) / L), L the exit pupil's distance from the image plane
    from zoomcalib.optics.lens_camera import exact_mapping
    from zoomcalib.render.image import project_points
    from zoomcalib.targets import parse_pattern

    view = b["views"][0]
    R = cv2.Rodrigues(np.asarray(view["rvec"]))[0]
    board = parse_pattern(b["target"]).object_points
    plain = project_points(board, exact_mapping(laikin, 0.3, None, sensor), R,
                           np.asarray(view["tvec"]))
    expected = plain + shift
    if keystone:
        c = np.array([a["camera"]["cx"], a["camera"]["cy"]])
        pupil = exit_pupil_distance(laikin, laikin.thickness_at(solve_gaps(laikin, [0.3]))[0])
        d = plain - c
        expected += d * (sensor.pixel_pitch_mm * (d @ (1e-3 * tilt)) / pupil)[:, None]
        assert np.abs(expected - plain - shift).max() > 1e-3  # the keystone shows at this size
    # 1e-4 px: the mapping rebuilt here (no misalignment object) is fitted anew, 4e-5 px apart
    np.testing.assert_allclose(np.asarray(view["points_px"]), expected, atol=1e-4)
    assert docs[1]["axis_tilt_mrad"] == pytest.approx(list(tilt))


def test_a_new_render_replaces_an_older_one_in_the_same_folder(tmp_path):
    from zoomcalib.render.sweep import render_zoom_sweep

    out = tmp_path / "sweep"
    (tmp_path / "sweep").mkdir()
    (out / "notes.txt").write_text("the user's own file")
    kw = dict(fx_range=(900.0, 1400.0), steps=2, size=(160, 120), pattern="chessboard:5x4:20")
    render_zoom_sweep(out, views=3, **kw)
    render_zoom_sweep(out, views=2, jpeg_quality=90, **kw)
    images = sorted(p.relative_to(out).as_posix() for p in out.rglob("view_*"))
    truth = json.loads((out / "truth.json").read_text())
    assert images == sorted(v["file"] for st in truth["steps"] for v in st["views"])
    assert len(images) == 4 and all(i.endswith(".jpg") for i in images)
    assert (out / "notes.txt").read_text() == "the user's own file"


def test_an_interrupted_sweep_rerun_equals_one_run(tmp_path):
    from zoomcalib.render.sweep import render_zoom_sweep

    kw = dict(fx_range=(900.0, 1400.0), steps=2, views=2, size=(160, 120),
              pattern="chessboard:5x4:20", seed=9)
    render_zoom_sweep(tmp_path / "once", **kw)

    def interrupt(n, left=[3]):  # noqa: B006 (a counter shared across calls)
        left[0] -= n
        if left[0] <= 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_zoom_sweep(tmp_path / "twice", progress=interrupt, **kw)
    render_zoom_sweep(tmp_path / "twice", **kw)

    def contents(root):
        files = {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*")
                 if p.is_file()}
        truth = json.loads(files.pop("truth.json"))
        for key in ("render_s", "render_cpu_s"):  # timings differ between runs
            truth.pop(key)
        files["truth.json"] = json.dumps(truth, sort_keys=True).encode()
        return files

    once, twice = contents(tmp_path / "once"), contents(tmp_path / "twice")
    assert once.keys() == twice.keys()
    assert all(once[k] == twice[k] for k in once)


def test_an_interrupted_lens_render_rerun_equals_one_run(tmp_path, laikin):
    from zoomcalib.render.dataset import render_dataset

    sensor = Sensor(160, 120, 0.0516)
    kw = dict(sensor=sensor, seed=4, direction="in")
    render_dataset(laikin, None, tmp_path / "once", [0.1, 0.6], 2, "chessboard:5x4:25", **kw)

    def interrupt(n, left=[3]):  # noqa: B006 (a counter shared across calls)
        left[0] -= n
        if left[0] <= 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        render_dataset(laikin, None, tmp_path / "twice", [0.1, 0.6], 2, "chessboard:5x4:25",
                       progress=interrupt, **kw)
    render_dataset(laikin, None, tmp_path / "twice", [0.1, 0.6], 2, "chessboard:5x4:25", **kw)
    once, twice = ({p.relative_to(r).as_posix(): p.read_bytes() for p in r.rglob("*")
                    if p.is_file()} for r in (tmp_path / "once", tmp_path / "twice"))
    assert once.keys() == twice.keys()
    assert [k for k in once if once[k] != twice[k]] == []


def test_traced_principal_point_path_is_not_a_low_degree_polynomial():
    from zoomcalib.render.sweep import principal_point_path

    fx, bow, rec = principal_point_path((2300.0, 23000.0), 25, "bow")
    u = np.log(fx)
    cubic = lambda p: p - np.polynomial.polynomial.polyval(  # noqa: E731
        u, np.polynomial.polynomial.polyfit(u, p, 3)).T
    assert rec["kind"] == "bow" and np.abs(cubic(bow)).max() < 1e-6  # a quadratic in u
    for runout in (0.0, 1.0):
        _, path, rec = principal_point_path((2300.0, 23000.0), 25, "traced", span_px=40.0,
                                            runout=runout, seed=7)
        assert rec["kind"] == "traced" and np.allclose(path[0], 0.0)
        # tens of px over the sweep, and a cubic in log fx misses it by more than a long-end
        # sigma of the adjustment (~1 px): the sensitivities change with zoom, the run-out turns
        # (the span is that of the static errors; the run-out adds a few px)
        assert 20.0 < np.linalg.norm(path, axis=1).max() <= (40.0 + 1e-9 if not runout else 50.0)
        assert np.abs(cubic(path)).max() > (1.0 if runout else 0.1), runout


def test_cli_render_sweep_traced_path_in_truth(tmp_path):
    res = CliRunner().invoke(main, ["render-sweep", "--fx", "1150,11500", "--steps", "3",
                                    "--views", "1", "--size", "320x180", "--pp-path", "traced",
                                    "--pp-span", "30", "--seed", "2", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "truth.json").read_text())
    assert doc["pp_path"]["kind"] == "traced" and doc["pp_path"]["lens"] == "laikin-10x"
    c = np.array([np.asarray(st["K"])[:2, 2] for st in doc["steps"]])
    assert 5.0 < np.linalg.norm(c - c[0], axis=1).max() < 40.0


def test_cli_render_sweep_through_a_real_lens(tmp_path):
    data = Path(__file__).parent / "data" / "lensfun"
    res = CliRunner().invoke(main, ["render-sweep", "--fx", "1150,11500", "--steps", "3",
                                    "--views", "1", "--size", "320x180", "--lens", "80-400",
                                    "--lensfun", str(data), "--dist-centre", "3,-2",
                                    "--out", str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "s" / "truth.json").read_text())
    assert doc["distortion"]["kind"] == "lensfun" and "80-400" in doc["distortion"]["lens"]
    assert doc["distortion"]["centre_px"] == [3.0, -2.0]
    assert doc["steps"][-1]["camera"]["dist_centre_px"] == [3.0, -2.0]
    k1 = [st["dist"][0] for st in doc["steps"]]
    assert k1[0] < 0 < k1[-1]  # barrel at the short end, pincushion at the long end
    res = CliRunner().invoke(main, ["render-sweep", "--lens", "Canon", "--lensfun", str(data),
                                    "--out", str(tmp_path / "bad")])
    assert res.exit_code == 2 and "name one lens" in res.output


def test_distortion_centred_off_the_principal_point():
    # a distortion about pp + delta is OpenCV's model about a principal point moved by delta,
    # seen along rays shifted by -delta / f: cv2.projectPoints checks it independently
    from zoomcalib.camera import CameraModel

    rng = np.random.default_rng(11)
    delta = rng.uniform(-8, 8, 2)
    dist = np.array([0.3, -0.5, 0.0, 0.0, 0.0])
    cam = CameraModel(4000.0, 4000.0, 650.0, 350.0, dist, dist_centre_px=delta)
    P = np.column_stack([rng.uniform(-15, 15, (50, 2)), rng.uniform(500, 600, 50)])
    e = delta / 4000.0
    K = np.array([[4000.0, 0, 650.0 + delta[0]], [0, 4000.0, 350.0 + delta[1]], [0, 0, 1]])
    shifted = P - np.column_stack([e[0] * P[:, 2], e[1] * P[:, 2], 0 * P[:, 2]])
    ref = cv2.projectPoints(shifted.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0]
    np.testing.assert_allclose(cam.project(P), ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(cam.unproject_normalized(cam.project(P)), P[:, :2] / P[:, 2:],
                               atol=1e-10)
    # the axis still images at the principal point, to -k1 |e|^2 e
    axis = cam.project(np.array([[0.0, 0.0, 1.0]]))[0]
    assert np.abs(axis - [650.0, 350.0]).max() < 1e-3
