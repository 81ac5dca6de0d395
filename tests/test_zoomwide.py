"""Zoom-wide calibration, its prior, and the honesty checks, on sweeps with hidden truth.

The sweeps here are made by ``sweep_observations``: OpenCV's own projection (cv2.projectPoints)
of a board bent by sine waves (the adjustment models the board with Legendre modes), with
Gaussian detection noise; principal point, distortion and poses drawn from a seeded generator.
"""

import dataclasses

import cv2
import numpy as np
import pytest
import scipy.stats

from zoomcalib.calibrate.checks import (
    Z_LIMIT,
    _basin_flags,
    conditioning_flags,
    cross_validate,
    split_halves,
)
from zoomcalib.calibrate.opencv_backend import calibrate_opencv
from zoomcalib.calibrate.quality import projection_difference, projection_z
from zoomcalib.calibrate.result import Observations
from zoomcalib.calibrate.zoommodel import prior_operator
from zoomcalib.calibrate.zoomwide import (
    DISTORTION_SETS,
    RATIONAL_PRIOR_AT_CORNER,
    TermChoice,
    calibrate_zoom_wide,
    prior_strength,
    second_difference,
    select_distortion,
    zoom_wide_starts,
)
from zoomcalib.render.pp_path import traced_path
from zoomcalib.targets import parse_pattern

SIZE = (1280, 720)


def sweep_observations(rng, steps=7, views=10, noise=0.02, wave_mm=0.3,
                       pattern="chessboard:22x15:20", fx_range=(2300.0, 23000.0),
                       shift_odd_cx=0.0, pp=None, dist=None, dist_centre=(0.0, 0.0),
                       aspect=1.0, retaped_at=None, ripple_mm=0.0, print_mm=(0.0, 0.0)):
    """A zoom sweep's detections and its truth (see the module docstring); ``pp(u)`` (steps, 2)
    px replaces the principal-point path, ``u = log(fx / fx_0)``, and ``dist(u)`` (5,) the
    distortion, centred ``dist_centre`` px from the principal point (OpenCV's model about a
    principal point moved by it, seen along rays shifted by ``-dist_centre / fx``). The views'
    tilt follows the focal length (35 deg at 2300 px, near 3 deg at the long end); the pixels'
    aspect ratio ``fy / fx`` is ``aspect`` at every step. With ``retaped_at`` the steps from
    that index on see a board of another wave (re-taped between two capture sessions); the
    returned wave is then the pair. ``ripple_mm`` adds, on every session's board, ripples of
    3-6 cycles across it (three plane waves of random direction and phase, together of that
    RMS): a shape no low-degree surface follows. ``print_mm`` (a, b) moves every board's points
    in its plane as an inexact print does: x by ``a x y`` (a trapezoid) and y by ``b x^2`` (a
    bow), ``x, y`` normalised to [-1, 1] over the board."""
    target = parse_pattern(pattern)
    X0 = target.object_points.astype(float)
    centre = X0.mean(axis=0)
    span = np.ptp(X0[:, :2], axis=0) / 2
    xn, yn = (X0[:, 0] - centre[0]) / span[0], (X0[:, 1] - centre[1]) / span[1]
    phase = rng.uniform(0, 2 * np.pi, 2)
    def draw_wave():
        phase = rng.uniform(0, 2 * np.pi, 2)
        return wave_mm * np.sin(rng.uniform(1.5, 2.5) * xn + phase[0]) * np.cos(
            rng.uniform(1.2, 2.0) * yn + phase[1])

    wave = wave_mm * np.sin(rng.uniform(1.5, 2.5) * xn + phase[0]) * np.cos(
        rng.uniform(1.2, 2.0) * yn + phase[1])
    if ripple_mm:
        angle, cycles, shift = (rng.uniform(0, np.pi, 3), rng.uniform(3, 6, 3),
                                rng.uniform(0, 2 * np.pi, 3))
        ripple = sum(np.sin(np.pi * c * (np.cos(a) * xn + np.sin(a) * yn) + p)
                     for a, c, p in zip(angle, cycles, shift, strict=True))
        wave = wave + ripple_mm * ripple / np.sqrt(np.mean(ripple**2))
    X0_print = X0.copy()
    X0_print[:, 0] += print_mm[0] * xn * yn
    X0_print[:, 1] += print_mm[1] * xn**2
    X = X0_print.copy()
    X[:, 2] += wave
    if retaped_at is not None:
        wave = (wave, draw_wave())
        X_after = X0_print.copy()
        X_after[:, 2] += wave[1]
    fx = np.geomspace(*fx_range, steps)
    u = np.log(fx / fx[0])
    a, b = rng.uniform(-30, 30, 2)
    path = None if pp is None else pp(u)
    obs, truth = {}, {}
    for s in range(steps):
        if path is None:
            cx = 640 + a * np.sin(0.6 * u[s]) + 5 * u[s]
            cy = 360 + b * (u[s] / u[-1]) ** 2 - 4 * u[s]
        else:
            cx, cy = path[s]
        k1, k2 = -0.25 * np.exp(-1.5 * u[s]), 0.12 * np.exp(-3 * u[s])
        distortion = np.array([k1, k2, 0, 0, 0]) if dist is None else np.asarray(dist(u[s]))
        tilt = 35 * np.exp(-np.log(fx[s] / 2300.0) / 1.2) + 3
        vlist = []
        for v in range(views):
            K = np.array([[fx[s], 0, cx + (shift_odd_cx if v % 2 else 0.0)],
                          [0, fx[s] * aspect, cy], [0, 0, 1]])
            ang = np.deg2rad([*rng.uniform(-tilt, tilt, 2), rng.uniform(-10, 10)])
            R = cv2.Rodrigues(ang)[0]
            t = np.array([*rng.uniform(-15, 15, 2), fx[s] * 0.5 * rng.uniform(1.15, 1.4)])
            board = X if retaped_at is None or s < retaped_at else X_after
            X_cam = (board - centre) @ R.T + t
            e = np.asarray(dist_centre, float) / fx[s]
            X_cam[:, :2] -= e * X_cam[:, 2:]
            K_centre = K + np.array([[0, 0, dist_centre[0]], [0, 0, dist_centre[1]], [0, 0, 0]])
            p, _ = cv2.projectPoints(X_cam, np.zeros(3), np.zeros(3), K_centre, distortion)
            p = p.reshape(-1, 2) + rng.normal(0, noise, (len(X), 2))
            inside = np.all((p > 0) & (p < np.array(SIZE) - 1), axis=1)
            vlist.append((np.flatnonzero(inside), p[inside]))
        name = f"step{s}"
        obs[name] = Observations(X0.copy(), vlist, SIZE, [f"{name}_{v:02d}" for v in range(views)])
        truth[name] = {"fx": fx[s], "cx": cx, "cy": cy,
                       "X": X if retaped_at is None or s < retaped_at else X_after}
    return obs, truth, wave


def test_second_difference_is_exact_on_quadratics(rng):
    u = np.sort(rng.uniform(0, 3, 9))
    a, b, c = rng.normal(size=3)
    np.testing.assert_allclose(second_difference(u) @ (a * u**2 + b * u + c), 2 * a, rtol=1e-9)


def test_prior_strength_recovers_the_roughness(rng):
    # 25 steps, noise small enough that the second differences of the path show through it
    n, sd = 25, 0.05
    u = np.linspace(0, 2.3, n) + rng.uniform(-0.02, 0.02, n)
    fine = np.linspace(-0.05, 2.35, 24001)
    dt = fine[1] - fine[0]
    estimates = []
    for intensity in (30.0, 300.0):
        # an integrated Wiener process on a fine grid (not the estimator's discrete model)
        slope = np.cumsum(intensity * np.sqrt(dt) * rng.normal(size=len(fine)))
        path = np.interp(u, fine, np.cumsum(slope) * dt)
        got, at_bound = prior_strength(path + rng.normal(0, sd, n), np.full(n, sd), u)
        implied = np.sqrt(np.mean((second_difference(u) @ path) ** 2))
        estimates.append((got, implied, at_bound))
    for got, implied, at_bound in estimates:
        assert not at_bound
        # 23 second differences: the estimate scatters by ~15 %; 2x allows 4 sigma
        assert 0.5 < got / implied < 2.0, (got, implied)
    assert estimates[1][0] > 5 * estimates[0][0]


@pytest.fixture(scope="module")
def sweep_and_starts():
    rng = np.random.default_rng(20261124)
    # 0.012 px: the model detector's error on rendered JPEG frames (bench_detect_flags.py)
    obs, truth, wave = sweep_observations(rng, noise=0.012)
    starts = zoom_wide_starts(obs)  # the steps' own fits, shared by the adjustments below
    return obs, truth, wave, calibrate_zoom_wide(obs, starts=starts), starts


@pytest.fixture(scope="module")
def sweep(sweep_and_starts):
    return sweep_and_starts[:4]


@pytest.fixture(scope="module")
def sweep_starts(sweep_and_starts):
    return sweep_and_starts[4]


def test_given_starts_give_the_same_adjustment_and_other_ones_are_refused(rng):
    # the steps' own fits made once serve adjustments that differ in later options: the same
    # result to the bit as making them again; starts made with another term choice, or for
    # other observations, are refused with what differs
    obs, _, _ = sweep_observations(rng, steps=3, views=8, fx_range=(2300.0, 6000.0))
    starts = zoom_wide_starts(obs)
    for options in ({}, {"pp_model": "prior2", "print_shape": False}):
        made, given = (calibrate_zoom_wide(obs, starts=s, **options) for s in (None, starts))
        for name, r in made.results.items():
            np.testing.assert_array_equal(given.results[name].K, r.K)
            np.testing.assert_array_equal(given.results[name].dist, r.dist)
            assert given.results[name].sd == r.sd
            assert given.terms[name] == made.terms[name]
    assert set(starts.init) == set(obs) and not starts.skipped  # unchanged by the adjustments
    with pytest.raises(ValueError, match="other options: select False"):
        calibrate_zoom_wide(obs, starts=starts, select=False)
    moved = dict(obs)
    step = next(iter(obs))
    moved[step] = dataclasses.replace(obs[step], views=[(ids, pts + 0.01)
                                                        for ids, pts in obs[step].views])
    with pytest.raises(ValueError, match="other observations"):
        calibrate_zoom_wide(moved, starts=starts)


@pytest.mark.parametrize("k1", [-0.026, 0.0])
def test_distortion_choice_on_the_board_shape_is_stable(rng, k1):
    # One step at fx 10676 px, 10 near-fronto-parallel views of a board bent by 0.3 mm, noise
    # 0.008 px (the model detector's on rendered frames). k1 = -0.026 moves the corners by
    # 0.09 px. On the board's shape the held-out error of "none" exceeds k1's by 3-5 %, its
    # standard error 0.5-0.8 % (1 % tolerance, 2 standard errors); without distortion every
    # term's gain is within 0.5 %. On the flat board the same draws chose four different sets.
    chosen = []
    for _ in range(6):
        obs, truth, _ = sweep_observations(rng, steps=1, noise=0.008,
                                           fx_range=(10676.0, 10676.0),
                                           dist=lambda u: [k1, 0, 0, 0, 0],
                                           pp=lambda u: np.array([[652.0, 351.0]]))
        start = calibrate_opencv(obs["step0"])
        choice = select_distortion(obs["step0"], board_points=truth["step0"]["X"], start=start)
        assert choice.board == "estimated"
        chosen.append(choice.terms)
    assert chosen == [("k1",) if k1 else ()] * 6, chosen


def test_zoom_wide_recovers_every_step(sweep):
    obs, truth, _, zw = sweep
    assert zw.converged and zw.stop_reason == "tolerance"
    z = []
    for name, t in truth.items():
        r = zw.results[name]
        assert abs(r.fx / t["fx"] - 1) < 0.003, (name, r.fx, t["fx"])
        z.append((r.fx - t["fx"]) / r.sd["fx"])
        for q in ("cx", "cy"):
            # 4 sigma: a 1-in-16000 event per value for honest Gaussian sigmas
            err = getattr(r, q) - t[q]
            assert abs(err) < 4 * r.sd[q], (name, q, err, r.sd[q])
            assert r.sd[q] < 5.0
            z.append(err / r.sd[q])
    # both ways: 21 z of honest sigmas have an RMS in 0.70-1.30 (95 %); 0.5 and 1.6 leave room
    # for the prior's known conservatism and catch sigmas 2x too wide or 1.6x too narrow
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.5 < rms < 1.6, (rms, np.round(z, 2))


@pytest.mark.parametrize("pp_model", ["angle2", "prior2"])
def test_prior_strength_is_not_inflated_by_the_waving_board(sweep, sweep_starts, pp_model):
    # Per-step OpenCV takes the bent board as flat and its principal points scatter by many of
    # their sigmas; a tau estimated from them came out 20-1000x the path's true roughness on
    # such sweeps. From the zoom-wide values it must stay near the truth: with 5 second
    # differences the REML estimate scatters by a factor of ~2 (it may also fall far below).
    # The truth's roughness is measured with the prior's own rows (angle2: in radians).
    obs, truth, _, zw = sweep
    if pp_model != "angle2":
        zw = calibrate_zoom_wide(obs, pp_model=pp_model, starts=sweep_starts)
    fx = np.array([t["fx"] for t in truth.values()])
    R = prior_operator(np.log(fx), 2, 1.0 / fx if pp_model == "angle2" else None)
    for q in ("cx", "cy"):
        assert zw.zoom_models[q]["model"] == pp_model
        roughness = np.sqrt(np.mean((R @ np.array([t[q] for t in truth.values()])) ** 2))
        assert zw.tau[q] < 4 * roughness, (q, zw.tau[q], roughness)
    assert zw.results["step0"].info["tau_source"] == "zoom-wide solve without the prior"


def test_a_term_the_long_end_cannot_measure_is_carried_by_the_prior(sweep):
    # k1 = -0.25 exp(-1.5 u): at the long end it moves the corners by 0.006 px, half the
    # noise, and the held-out views there leave it out; the adjustment takes it from the
    # neighbours through the smoothness prior, with the prior's uncertainty in its sigma
    obs, truth, _, zw = sweep
    carried = [n for n in obs if "k1" not in zw.held_out[n].terms]
    assert carried, {n: zw.held_out[n].terms for n in obs}
    fx0 = truth["step0"]["fx"]
    for name in obs:
        r = zw.results[name]
        assert "k1" in zw.terms[name] and r.sd["k1"] > 0
        k1_true = -0.25 * np.exp(-1.5 * np.log(truth[name]["fx"] / fx0))
        assert abs(r.dist[0] - k1_true) < 4 * r.sd["k1"], (name, r.dist[0], k1_true, r.sd)


def test_zoom_wide_borrows_at_the_long_end(sweep):
    obs, truth, _, zw = sweep
    last = list(obs)[-1]
    try:
        per_step = calibrate_opencv(obs[last])
        sd_per_step = min(per_step.sd["cx"], per_step.sd["cy"])
    except RuntimeError:  # OpenCV cannot even give sigmas there
        sd_per_step = np.inf
    zw_sd = max(zw.results[last].sd["cx"], zw.results[last].sd["cy"])
    assert zw_sd < sd_per_step / 1.5


def test_tau_is_marginalised_and_a_given_tau_is_used(sweep, sweep_starts):
    obs, truth, _, zw = sweep
    last = list(obs)[-1]
    for q in ("cx", "cy"):
        m = zw.zoom_models[q]
        assert m["tau_kind"] == "posterior median"
        assert m["tau_interval_90"][0] <= m["tau"] <= m["tau_interval_90"][1]
    # a prior 100x stronger than the estimated one for cx alone: the long end borrows more
    strong = zw.zoom_models["cx"]["tau"] / 100
    given = calibrate_zoom_wide(obs, prior_strength={"cx": strong}, starts=sweep_starts)
    assert given.zoom_models["cx"]["tau_kind"] == "given"
    assert given.zoom_models["cx"]["tau"] == strong
    noise_model = [r.results[last].info["sd_noise_model"]["cx"] for r in (given, zw)]
    assert noise_model[0] < 0.7 * noise_model[1]
    # the views see a prior too strong for them and widen its sigma, but not back to the other
    assert given.results[last].sd["cx"] < zw.results[last].sd["cx"]
    # and the share of its precision that the prior gives grows accordingly
    share = {r: res.results[last].info["prior_share"]["cx"] for r, res in (("est", zw),
                                                                          ("given", given))}
    assert 0.0 <= share["est"] < share["given"] - 0.3 <= 0.7, share
    assert given.zoom_models["cy"]["tau_kind"] == "posterior median"
    with pytest.raises(ValueError, match="prior_strength: fx"):
        calibrate_zoom_wide(obs, prior_strength={"fx": 1.0})


def test_zoom_wide_recovers_the_board_shape(sweep):
    obs, _, wave, zw = sweep
    board = obs["step0"].object_points
    fitted = zw.results["step0"].object_points[:, 2]
    # compare up to a plane (a piston and a tilt of the board are a change of pose)
    err = _off_plane(board, fitted) - _off_plane(board, wave)
    assert np.sqrt(np.mean(err**2)) < 0.2 * np.sqrt(np.mean(_off_plane(board, wave) ** 2))


def _off_plane(board: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Heights ``z`` less their least-squares plane over the board's x, y."""
    A = np.column_stack([np.ones(len(board)), board[:, :2]])
    return z - A @ np.linalg.lstsq(A, z, rcond=None)[0]


def test_cross_validation_passes_one_camera_and_flags_a_moved_one(rng):
    obs, _, _ = sweep_observations(rng, steps=4, views=8, fx_range=(2300, 6000))
    steady = cross_validate(obs, lambda o: calibrate_zoom_wide(o).results, "zoom-wide")
    assert not steady.failures and not steady.disagreeing()
    moved, _, _ = sweep_observations(rng, steps=4, views=8, fx_range=(2300, 6000),
                                     shift_odd_cx=15.0)
    check = cross_validate(moved, lambda o: calibrate_zoom_wide(o).results, "zoom-wide")
    assert all(abs(check.z[s]["cx"]) > Z_LIMIT for s in moved), check.z
    assert set(check.disagreeing()) == set(moved)
    # the projections over the image in their own sigma: the halves of one camera agree, a
    # 15 px move (about 10 sigmas of cx) is seen there too
    print("\nprojection z_rms, one camera: "
          + ", ".join(f"{p['z_rms']:.2f}" for p in steady.projection.values())
          + "; odd views' cx moved 15 px: "
          + ", ".join(f"{p['z_rms']:.2f}" for p in check.projection.values()))
    assert all(p["z_rms"] < Z_LIMIT for p in steady.projection.values()), steady.projection
    assert sum(p["z_rms"] > Z_LIMIT for p in check.projection.values()) >= 2, check.projection
    assert min(p["z_rms"] for p in check.projection.values()) > \
        np.median([p["z_rms"] for p in steady.projection.values()])
    # the statistic's difference is the report's map
    a, b = check.halves["step1"]
    even, odd = split_halves(moved["step1"])
    xs, ys, _, diff = projection_z(a, even, b, odd)
    np.testing.assert_allclose(diff, projection_difference(a, b, even.image_size)[2])
    even, odd = split_halves(moved["step0"])
    assert even.names == moved["step0"].names[0::2] and odd.names == moved["step0"].names[1::2]


def test_conditioning_flags_name_the_reason(sweep):
    import copy

    _, _, _, zw = sweep
    res = copy.deepcopy(zw.results["step0"])
    assert conditioning_flags(res, SIZE) == []
    res.K[0, 2] = -185.0
    res.sd["cy"] = 40.0
    flags = conditioning_flags(res, SIZE)
    assert any("outside the central region" in f for f in flags)
    assert any(f.startswith("sd cy 40.0 px") for f in flags)


def test_in_and_out_sweeps_are_separate_chains(rng):
    # the same settings reached zooming in and zooming out, the principal point offset by a
    # backlash of 4 px between the two: one chain would tie states 0.1 % apart in fx together
    obs, truth, _ = sweep_observations(rng, steps=4, views=8, fx_range=(2300, 6000))
    both = {f"in_{k}": v for k, v in obs.items()}
    for k, o in obs.items():  # the out sweep: the same views, every point 4 px to the right
        views = [(ids, pts + np.array([4.0, 0.0])) for ids, pts in o.views]
        both[f"out_{k}"] = Observations(o.object_points, views, o.image_size, o.names)
    labels = {s: s.split("_")[0] for s in both}
    zw = calibrate_zoom_wide(both, chains=labels)
    for k in obs:
        d = zw.results[f"out_{k}"].cx - zw.results[f"in_{k}"].cx
        sd = np.hypot(zw.results[f"out_{k}"].sd["cx"], zw.results[f"in_{k}"].sd["cx"])
        assert abs(d - 4.0) < 4 * sd, (k, d, sd)


def test_diagnose_refuses_zoom_wide_rows():
    from zoomcalib.diagnose.table import ZoomTable

    rows = [{"step": f"s{i}", "zoom": float(i), "fx": 1000.0 + i, "fy": 1000.0, "cx": 640.0,
             "cy": 360.0, "mode": "zoom-wide"} for i in range(5)]
    with pytest.raises(ValueError, match="--per-step"):
        ZoomTable.from_rows(rows, "t.csv")


def test_a_step_that_cannot_start_is_left_out_not_fatal(rng):
    obs, truth, _ = sweep_observations(rng, steps=4, views=8, fx_range=(2300, 6000))
    short = obs["step2"]
    obs["step2"] = Observations(short.object_points, short.views[:2], short.image_size,
                                short.names[:2])
    zw = calibrate_zoom_wide(obs)
    assert set(zw.skipped) == {"step2"}
    assert zw.skipped["step2"].startswith("step step2: no starting calibration"), zw.skipped
    assert "; robust start: " in zw.skipped["step2"], zw.skipped  # both reasons said
    assert set(zw.results) == {"step0", "step1", "step3"}
    for name, r in zw.results.items():
        assert abs(r.fx / truth[name]["fx"] - 1) < 0.003


def _recovered_within(zw, truth, limit=4.0, lowest_rms=0.3):
    """Both sides: every cx, cy within ``limit`` of its sigma of the truth (4: a 1-in-16000
    event per value for honest Gaussian sigmas), and their RMS z above ``lowest_rms`` (for 8-14
    honest z, an RMS below 0.3 has a probability under 1e-4: sigmas over 3 times too wide)."""
    z = []
    for name, t in truth.items():
        for q in ("cx", "cy"):
            err = getattr(zw.results[name], q) - t[q]
            assert abs(err) < limit * zw.results[name].sd[q], (name, q, err)
            z.append(err / zw.results[name].sd[q])
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert rms > lowest_rms, (rms, np.round(z, 2))


def test_zoom_model_follows_a_curved_path(rng):
    # a quadratic in log fx whose bow (15 px in cx, in the middle) a line misses
    def quadratic(u):
        t = u / u[-1]
        return np.column_stack([640 + 80 * t - 60 * t**2, 360 - 40 * t + 60 * t**2])

    obs, truth, _ = sweep_observations(rng, views=6, noise=0.012, pp=quadratic)
    zw = calibrate_zoom_wide(obs, select=False, pp_model="select")
    assert not {zw.zoom_models[q]["model"] for q in ("cx", "cy")} & {"poly1"}, zw.zoom_models
    assert zw.results["step0"].info["zoom_model"]["cx"] == zw.zoom_models["cx"]["model"]
    _recovered_within(zw, truth)


def test_zoom_model_keeps_the_prior_on_the_traced_lens(rng):
    # the principal point of the ray-traced zoom lens with mechanical errors, its cam-track
    # run-out turning twice over the range: no polynomial in log fx follows it
    def traced(u):
        return np.array([640.0, 360.0]) + traced_path(u / u[-1], (2300.0, 23000.0), 40.0, 11)[0]

    obs, truth, _ = sweep_observations(rng, noise=0.012, pp=traced)
    zw = calibrate_zoom_wide(obs, select=False, pp_model="select")
    assert not any(zw.zoom_models[q]["model"].startswith("poly") for q in ("cx", "cy")), \
        zw.zoom_models
    _recovered_within(zw, truth)


@pytest.mark.parametrize("seed", [6, 8])
def test_angular_prior_stays_honest_where_the_traced_path_bends(seed):
    # The ray-traced lens with static decentres and tilts of its moving groups: its principal
    # point bends at the long end (second differences in px 5-26x those at the short end, in
    # angle within about 2x). A prior in px learns its tau at the short end and put these two
    # sweeps' long end 17.6 and 8.6 sigma off (benchmarks/bench_zoom_model.py).
    def traced(u):
        return np.array([640.0, 360.0]) + traced_path(u / u[-1], (2300.0, 23000.0), 40.0,
                                                      seed, 0.0)[0]

    obs, truth, _ = sweep_observations(np.random.default_rng(1000 + seed), views=6,
                                       noise=0.012, pp=traced)
    zw = calibrate_zoom_wide(obs, select=False, pp_model="angle2")
    assert {zw.zoom_models[q]["model"] for q in ("cx", "cy")} == {"angle2"}
    _recovered_within(zw, truth)


def _long_end_step(seed: int, k1: float = 14.4) -> tuple[Observations, float]:
    """10 near-fronto-parallel views (at most 3 degrees of tilt) at fx 23000 px through a real
    lens's long-end pincushion (k1 14.4: 1.5 % of the half-diagonal at the corner, the
    Zoom-Nikkor 80-400 at 400 mm in lensfun), 0.01 px of noise."""
    from zoomcalib.camera import CameraModel
    from zoomcalib.render.image import camera_mapping, project_points
    from zoomcalib.render.sweep import SWEEP_SENSOR, sweep_poses

    target = parse_pattern("chessboard:22x15:20")
    cam = CameraModel(23000.0, 23000.0, 652.0, 334.0, np.array([k1, 0, 0, 0, 0]), SWEEP_SENSOR)
    rng = np.random.default_rng(seed)
    views = []
    for R, t in sweep_poses(target, cam, 10, 3.0, rng):
        uv = project_points(target.object_points, camera_mapping(cam), R, t)
        views.append((np.arange(len(uv)), uv + rng.normal(0, 0.01, uv.shape)))
    return Observations(target.object_points, views, SIZE, [f"v{i}" for i in range(10)]), cam.fx


@pytest.mark.parametrize("seed", [0, 3])
def test_the_start_survives_where_opencvs_own_start_fails(seed):
    from zoomcalib.calibrate.stepfits import _distortion_flags, _opencv_start, _robust_start

    obs, fx = _long_end_step(seed)
    # OpenCV from its own (homography) start ends at about twice the focal length with k1, and
    # at no camera without distortion: what the robust start is there for
    assert calibrate_opencv(obs, flags=_distortion_flags(("k1",))).fx > 1.5 * fx
    assert calibrate_opencv(obs, flags=_distortion_flags(())).fx < 0.1 * fx
    robust, failure = _robust_start(obs)
    assert failure is None
    # 1 % is several of the step's own fx sigmas (0.3 % zoom-wide at this step)
    assert abs(robust.fx / fx - 1) < 0.01, robust.fx
    for chosen in (("k1",), ("k1", "k2", "p1", "p2")):
        terms = {"s": chosen}
        start = _opencv_start("s", obs, terms, robust)
        assert abs(start.fx / fx - 1) < 0.01, (chosen, start.fx)
        assert terms["s"] == chosen


def test_a_mirrored_solution_is_flagged(sweep):
    import copy

    _, _, _, zw = sweep
    res = copy.deepcopy(zw.results["step0"])
    res.K[0, 0] = -res.K[0, 0]
    assert any("not positive" in f for f in conditioning_flags(res, SIZE))


def test_per_step_opencv_tries_more_starts_only_on_fronto_parallel_views(rng):
    from zoomcalib.calibrate.opencv_backend import FRONTO_PARALLEL_DEG, calibrate_opencv_robust

    obs, fx = _long_end_step(0)
    res = calibrate_opencv_robust(obs, fronto_parallel_deg=FRONTO_PARALLEL_DEG)
    assert res.info["start"] == "multi-start" and abs(res.fx / fx - 1) < 0.01, res.fx
    # the short end's views are tilted by up to 35 degrees: OpenCV's own start serves
    short, truth, _ = sweep_observations(rng, steps=2, views=8, fx_range=(2300, 3000))
    res = calibrate_opencv_robust(short["step0"], fronto_parallel_deg=FRONTO_PARALLEL_DEG)
    assert res.info["start"] == "opencv" and abs(res.fx / truth["step0"]["fx"] - 1) < 0.003


def test_a_distortion_centre_off_the_principal_point_does_not_pin_it(rng):
    # a real lens's pincushion at the long end (1.5 % of the half-diagonal at the corner),
    # centred 3, 2 px from the principal point: held at p1 = p2 = 0, the long end's principal
    # point landed on the distortion's centre with a sigma of 0.05-0.09 px (28-62 sigma off on
    # a rendered sweep); with p1, p2 free it stays within its sigmas of the truth
    from zoomcalib.calibrate.stepfits import with_decentring

    assert with_decentring(("k1",)) == ("k1", "p1", "p2")
    assert with_decentring(()) == () and with_decentring(("k1", "k2", "k3"))[2:4] == ("p1", "p2")
    half_diagonal = 0.5 * np.hypot(*SIZE)

    def pincushion(u):
        fx = 8000.0 * np.exp(u)
        return np.array([0.015 * (fx / half_diagonal) ** 2, 0, 0, 0, 0])

    obs, truth, _ = sweep_observations(rng, steps=4, views=10, noise=0.01,
                                       fx_range=(8000.0, 23000.0), dist=pincushion,
                                       dist_centre=(3.0, 2.0))
    zw = calibrate_zoom_wide(obs)
    for name in obs:
        assert {"p1", "p2"} <= set(zw.terms[name]), zw.terms[name]
    _recovered_within(zw, truth)


def _wide_views(rng, project, views=16, noise=0.05):
    """A 22 x 15 board seen by a 1280 x 720 camera of fx 480 px (106 degrees across) in seeded
    poses, projected by ``project(X_cam)`` (N, 2) px, with Gaussian noise."""
    X0 = parse_pattern("chessboard:22x15:20").object_points.astype(float)
    centre = X0.mean(axis=0)
    vlist = []
    for _ in range(views):
        R = cv2.Rodrigues(np.deg2rad([*rng.uniform(-40, 40, 2), rng.uniform(-20, 20)]))[0]
        t = np.array([*rng.uniform(-150, 150, 2), rng.uniform(280, 420)])
        p = project((X0 - centre) @ R.T + t) + rng.normal(0, noise, (len(X0), 2))
        inside = np.all((p > 0) & (p < np.array(SIZE) - 1), axis=1)
        vlist.append((np.flatnonzero(inside), p[inside]))
    return Observations(X0.copy(), vlist, SIZE)


def test_the_rational_model_is_chosen_only_where_five_terms_misfit(rng):
    """A wide lens whose image height follows the equidistant fisheye law (``cv2.fisheye``,
    another model than OpenCV's polynomial): five terms leave a systematic error, the held-out
    views choose the rational model and zoom-wide estimates k4..k6 at that step. The same poses
    through a five-term lens: five terms suffice and no rational term is chosen."""
    K = np.array([[480.0, 0, 641.0], [0, 480.0, 357.0], [0, 0, 1]])

    def fisheye(X):
        return cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                         np.array([0.02, -0.01, 0.0, 0.0]))[0].reshape(-1, 2)

    def polynomial(X):
        return cv2.projectPoints(X, np.zeros(3), np.zeros(3), K,
                                 np.array([-0.28, 0.09, 0.0, 0.0, -0.012]))[0].reshape(-1, 2)

    seed = int(rng.integers(1 << 30))
    wide = _wide_views(np.random.default_rng(seed), fisheye)
    plain = _wide_views(np.random.default_rng(seed), polynomial)
    assert "k4" in select_distortion(wide, start=calibrate_opencv(wide)).terms
    assert "k4" not in select_distortion(plain, start=calibrate_opencv(plain)).terms


def test_the_other_models_weight_is_the_chance_it_is_better_by_the_tolerance():
    """``TermChoice.other_model_weight``: the normal probability that the rational model's
    held-out error is below the five terms' by more than 1 %, from the per-view log ratio's
    mean and standard error; its complement where the rational model was chosen."""
    five = DISTORTION_SETS["k1k2p1p2k3"]
    margin = np.log1p(-0.01)
    for mean, se in ((-0.03, 0.01), (0.0, 0.004), (-0.2, 0.05)):
        expected = scipy.stats.norm.cdf((margin - mean) / se)
        assert TermChoice(five, rational_log_ratio=(mean, se)).other_model_weight() == (
            pytest.approx(expected))
        assert TermChoice(DISTORTION_SETS["rational"], rational_log_ratio=(mean, se)
                          ).other_model_weight() == pytest.approx(1.0 - expected)
    assert TermChoice(five).other_model_weight() == 0.0
    assert TermChoice(five, rational_log_ratio=(-0.1, 0.0)).other_model_weight() == 0.0


def test_a_lens_model_choice_that_widens_a_sigma_is_flagged():
    """``conditioning_flags``' reading of ``info["model_choice"]``: a flag where the other
    model's spread widened a pinhole sigma by more than 25 %, none for a small widening, and
    one where the other model is at least as likely but could not be fitted."""
    from zoomcalib.calibrate.checks import _model_choice_flags

    weight, shift = 0.92, {"fx": 2.16, "fy": 2.5, "cx": -0.09, "cy": -1.7}
    sd = {q: float(np.hypot(0.5, np.sqrt(weight) * v)) for q, v in shift.items()}
    (flag,) = _model_choice_flags({"other": "rational", "weight": weight, "shift": shift}, sd)
    grown = np.hypot(0.5, np.sqrt(weight) * 2.5) / 0.5
    assert flag.detail.startswith("lens model uncertain (rational model's weight 0.92): sd fy x"
                                  f"{grown:.1f}")
    assert (flag.kind, flag.severity) == ("model_choice", "note")
    small = {"fx": 0.01, "fy": 0.01, "cx": 0.11, "cy": 0.03}
    sd = {q: float(np.hypot(0.13, np.sqrt(0.06) * v)) for q, v in small.items()}
    assert _model_choice_flags({"other": "rational", "weight": 0.06, "shift": small}, sd) == []
    failed = {"other": "k1k2p1p2k3", "shift": None, "why": "k1+k2: no camera"}
    (flag,) = _model_choice_flags(failed | {"weight": 0.7}, {})
    assert "could not be fitted (k1+k2: no camera)" in flag.detail
    assert flag.severity == "warning"
    assert _model_choice_flags(failed | {"weight": 0.3}, {}) == []
    assert _model_choice_flags(None, {}) == []


def test_one_aspect_ratio_is_estimated_for_every_step():
    # a sensor of non-square pixels, the same at every step (drawn, not told to the fit)
    rng = np.random.default_rng(8)
    aspect = 1.0 + rng.uniform(0.01, 0.04) * rng.choice([-1, 1])
    obs, truth, _ = sweep_observations(rng, steps=6, views=10, aspect=aspect)
    zw = calibrate_zoom_wide(obs)
    z = (zw.aspect - aspect) / zw.aspect_sd
    assert abs(z) < 4, (zw.aspect, aspect, zw.aspect_sd)
    assert 0 < zw.aspect_sd < 2e-4
    for name, r in zw.results.items():
        assert r.fy / r.fx == pytest.approx(zw.aspect, rel=1e-12)
        assert "fy" not in r.info["fixed"] and r.info["aspect_shared"]
        # fy's sigma carries fx's and the aspect's
        assert r.sd["fy"] >= 0.99 * zw.aspect * r.sd["fx"]
        assert abs(r.fy / (truth[name]["fx"] * aspect) - 1) < 0.003


def test_a_board_retaped_between_sessions_gets_a_shape_per_session():
    rng = np.random.default_rng(31)
    cut = int(rng.integers(2, 5))  # the re-taping, hidden from the fit but for the labels
    obs, truth, (wave_a, wave_b) = sweep_observations(rng, steps=7, views=10, wave_mm=0.4,
                                                      retaped_at=cut)
    labels = {n: "a" if i < cut else "b" for i, n in enumerate(obs)}
    starts = zoom_wide_starts(obs)  # the steps' own fits, for both adjustments
    apart = calibrate_zoom_wide(obs, sessions=labels, starts=starts)
    one = calibrate_zoom_wide(obs, starts=starts)
    assert apart.board_sessions == ["a", "b"] and one.board_sessions == [""]
    z_apart, z_one = [], []
    for name, t in truth.items():
        for zw, zs in ((apart, z_apart), (one, z_one)):
            r = zw.results[name]
            zs += [(getattr(r, q) - t[q]) / r.sd[q] for q in ("fx", "cx", "cy")]
        # each step's board is its session's: up to a plane (a change of pose), its heights
        # follow that session's wave as well as one shape does on one board (0.2, above)
        board = apart.results[name].object_points
        true = _off_plane(board, t["X"][:, 2])
        err = _off_plane(board, board[:, 2]) - true
        assert np.sqrt(np.mean(err**2)) < 0.2 * np.sqrt(np.mean(true**2)), name
    rms_apart = np.sqrt(np.mean(np.square(z_apart)))
    assert max(np.abs(z_apart)) < 4 and 0.5 < rms_apart < 1.5, (rms_apart, z_apart)
    # a shape per session leaves the corner noise (0.02 px a coordinate: 0.028 px RMS) at
    # every step; one shape for both boards leaves a misfit at some steps (0.04-0.22 px on
    # the seeds tried) that its widened sigmas then carry
    noise = 0.02 * np.sqrt(2)
    apart_rms = np.array([r.rms_px for r in apart.results.values()])
    one_rms = np.array([r.rms_px for r in one.results.values()])
    assert np.all(apart_rms < 1.2 * noise), apart_rms
    assert one_rms.max() > 1.3 * noise, one_rms


@pytest.mark.parametrize("ripple_mm", [0.0, 0.4])
def test_point_heights_follow_ripples_the_modes_cannot(ripple_mm):
    # a board rippled at 3-6 cycles across (0.4 mm RMS): the degree-4 modes leave it in the
    # residual, the point heights take it out and give it back; on a board without ripples
    # they find none and leave the sigmas honest
    rng = np.random.default_rng(53)
    noise = 0.02
    obs, truth, wave = sweep_observations(rng, steps=4, views=10, noise=noise, wave_mm=0.3,
                                          ripple_mm=ripple_mm)
    starts = zoom_wide_starts(obs)  # the steps' own fits, for both adjustments
    points = calibrate_zoom_wide(obs, starts=starts)
    modes = calibrate_zoom_wide(obs, board_points=False, print_shape=False, starts=starts)
    assert points.board_heights.shape == (1, len(wave))
    z = [(getattr(points.results[n], q) - t[q]) / points.results[n].sd[q]
         for n, t in truth.items() for q in ("fx", "cx", "cy")]
    assert max(np.abs(z)) < 4 and 0.4 < np.sqrt(np.mean(np.square(z))) < 1.6, z
    rms = np.array([r.rms_px for r in points.results.values()])
    assert np.all(rms < 1.2 * noise * np.sqrt(2)), rms      # the corner noise, no more
    name = next(iter(truth))
    board = points.results[name].object_points
    true = _off_plane(board, truth[name]["X"][:, 2])
    err = _off_plane(board, board[:, 2]) - true
    if ripple_mm:
        # the modes alone leave the ripples: several times the corner noise at the short end
        assert modes.results[name].rms_px > 3 * noise * np.sqrt(2)
        assert np.sqrt(np.mean(err**2)) < 0.1 * np.sqrt(np.mean(true**2))
    else:
        # a smooth board: the modes take it, the points add only the corner noise's heights
        # (about 0.01 mm RMS here: 0.02 px corners seen by 40 views; the ripple is 0.4 mm)
        assert np.sqrt(np.mean(points.board_heights**2)) < 0.03


def test_normal_equations_summed_per_view_equal_the_assembled_jacobians(rng, monkeypatch):
    # The solver sums J^T J and J^T r step by step and view by view without forming J; on a
    # sweep with two board sessions and the shared aspect ratio (every kind of global column),
    # each call must equal the products of the assembled sparse Jacobian.
    import zoomcalib.calibrate.zoomproblem as zoomproblem

    obs, _, _ = sweep_observations(rng, steps=4, views=8, retaped_at=2)
    original = zoomproblem._ZoomProblem.normal_equations
    checked = []

    def compared(self, state):
        r, blocks = original(self, state)
        r_ref, J = self.evaluate(state)
        ref = zoomproblem._normal_blocks(self, J, r_ref)
        # rounding only: the same sums in another order, each within 1e-9 of the sum of its
        # terms' magnitudes (the same products of |J| and |r|)
        size = zoomproblem._normal_blocks(self, abs(J), np.abs(r_ref))
        np.testing.assert_allclose(r, r_ref, rtol=1e-12, atol=1e-9)
        for got, want, bound in zip(blocks, ref, size, strict=True):
            assert np.all(np.abs(got - want) <= 1e-9 * bound + 1e-300)
        checked.append(self.n_modes)
        return r, blocks

    monkeypatch.setattr(zoomproblem._ZoomProblem, "normal_equations", compared)
    sessions = {name: ("a" if k < 2 else "b") for k, name in enumerate(obs)}
    calibrate_zoom_wide(obs, sessions=sessions)
    assert len(checked) > 5 and max(checked) > 0


def test_the_steps_own_fits_in_two_processes_give_the_same_adjustment(rng):
    obs, _, _ = sweep_observations(rng, steps=4, views=8)
    one, two = calibrate_zoom_wide(obs), calibrate_zoom_wide(obs, workers=2)
    assert one.terms == two.terms
    for step in obs:
        np.testing.assert_array_equal(one.results[step].K, two.results[step].K)
        np.testing.assert_array_equal(one.results[step].dist, two.results[step].dist)


def test_held_intrinsics_stay_held_and_the_rest_is_recovered():
    # a camera whose principal point is the image centre, with square pixels and no decentring
    # or k3: holding them is then right, and the rest must be found as well as when free
    rng = np.random.default_rng(12)
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    obs, truth, _ = sweep_observations(rng, steps=5, views=9,
                                       pp=lambda u: np.tile(centre, (len(u), 1)))
    held = calibrate_zoom_wide(obs, fixed=("principal-point", "aspect", "tangential", "k3"))
    free = calibrate_zoom_wide(obs)
    for name, r in held.results.items():
        assert (r.cx, r.cy) == tuple(centre) and r.fy == r.fx
        assert not np.any(r.dist[2:]), r.dist
        assert {"cx", "cy", "p1", "p2", "k3"} <= set(r.info["fixed"])
        assert r.info["basin"]["why"] == "the principal point is held"
        z = (r.fx - truth[name]["fx"]) / r.sd["fx"]
        assert abs(z) < 4, (name, r.fx, truth[name]["fx"], r.sd["fx"])
        # fewer unknowns, no wider a sigma than the free adjustment's (small slack: the
        # view-scatter factors are re-estimated)
        assert r.sd["fx"] <= 1.2 * free.results[name].sd["fx"]
    assert held.aspect == 1.0 and held.aspect_sd == 0.0
    with pytest.raises(ValueError, match="cannot fix 'skew'"):
        calibrate_zoom_wide(obs, fixed=("skew",))


def test_the_rational_model_at_every_step_when_asked(rng):
    # a wide lens whose distortion is OpenCV's rational model (drawn); held-out views would
    # choose per step, model="rational" fits all eight terms everywhere
    k = np.array([rng.uniform(-0.4, -0.2), 0.08, 0, 0, 0.0, rng.uniform(-0.3, -0.1), 0.05, 0.0])
    obs, truth, _ = sweep_observations(rng, steps=3, views=10, fx_range=(1400.0, 2800.0),
                                       dist=lambda u: k * np.exp(-u))
    zw = calibrate_zoom_wide(obs, model="rational")
    for name, r in zw.results.items():
        assert zw.terms[name] == ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
        assert len(r.dist) == 8 and r.dist[5] != 0.0
        # the ridge of k1-k3 against k4-k6 is bounded by the prior: every step converges (all
        # three stopped at the iteration cap without it)
        assert r.converged, (name, r.info["stop_reason"])
        # the denominator's terms at the corner stay within a few of their prior sigmas
        corner = 0.5 * np.hypot(*obs[name].image_size) / r.fx
        assert np.all(np.abs(r.dist[5:] * corner ** np.array([2, 4, 6]))
                      < 4 * RATIONAL_PRIOR_AT_CORNER), name
        for q in ("fx", "cx", "cy"):
            z = (getattr(r, q) - truth[name][q]) / r.sd[q]
            assert abs(z) < 4, (name, q, getattr(r, q), truth[name][q], r.sd[q])
    with pytest.raises(ValueError, match="model must be"):
        calibrate_zoom_wide(obs, model="fisheye")


def test_a_term_choice_says_what_failed_and_why_it_chose_nothing(rng, monkeypatch):
    import zoomcalib.calibrate.stepfits as stepfits

    obs, _, _ = sweep_observations(rng, steps=2, views=8, fx_range=(2300.0, 3000.0))
    step = obs["step0"]
    few = select_distortion(Observations(step.object_points, step.views[:5], step.image_size))
    assert few.terms == DISTORTION_SETS["k1k2p1p2k3"] and "fewer than 6" in few.why
    real = stepfits.held_out_errors

    def rational_fails(o, terms, *args):
        if "k4" in terms:
            raise RuntimeError("held-out fit of the rational model diverged")
        return real(o, terms, *args)

    monkeypatch.setattr(stepfits, "held_out_errors", rational_fails)
    choice = select_distortion(step)
    assert choice.why is None and list(choice.failed) == ["rational"]
    assert "diverged" in choice.to_dict()["failed"]["rational"]
    assert not choice.rational
    from zoomcalib.calibrate.zoomset import zoom_wide_step_notes

    assert zoom_wide_step_notes({"distortion_choice": choice.to_dict()}) == [
        "term sets not fitted on held-out views, so not candidates: rational"]

    def k1_places_no_third_view(o, terms, *args):
        squared, count = real(o, terms, *args)
        if terms == ("k1",):
            squared[2], count[2] = 0.0, 0  # a view its intrinsics could not place
        return squared, count

    monkeypatch.setattr(stepfits, "held_out_errors", k1_places_no_third_view)
    choice = select_distortion(step)
    assert choice.unplaced == {"k1": 1}
    # the run's log says so, as it says a set that failed
    notes = zoom_wide_step_notes({"distortion_choice": choice.to_dict()})
    assert notes == ["held-out views a term set could not place, left out of every set's "
                     "comparison: k1 1"], notes
    # every set is judged without that view: its squared errors are in none of them
    squared, count = real(step, DISTORTION_SETS["k1k2"])
    kept = np.arange(len(count)) != 2
    assert choice.mse_px2["k1k2"] == pytest.approx(squared[kept].sum() / count[kept].sum())

    def only_none_fits(o, terms, *args):
        if terms:  # every set with a term diverges on the halves (a narrow step's folds)
            raise RuntimeError("held-out fit diverged: principal point outside the image")
        return real(o, terms, *args)

    monkeypatch.setattr(stepfits, "held_out_errors", only_none_fits)
    choice = select_distortion(step)
    # no evidence for no distortion: all five terms, and why
    assert choice.terms == DISTORTION_SETS["k1k2p1p2k3"], choice
    assert "only the set without distortion" in choice.why
    assert set(choice.failed) == set(DISTORTION_SETS) - {"none"}


@pytest.mark.parametrize("limit", ["iteration cap", "damping limit"])
def test_a_solve_that_stops_short_says_why_and_is_not_converged(rng, monkeypatch, limit):
    import functools

    import zoomcalib.calibrate.zoomwide as zoomwide

    obs, _, _ = sweep_observations(rng, steps=3, views=8, fx_range=(2300.0, 6000.0))
    if limit == "iteration cap":  # one iteration cannot reach the optimum from OpenCV's start
        monkeypatch.setattr(zoomwide, "_levenberg_marquardt", functools.partial(
            zoomwide._levenberg_marquardt, max_iterations=1))
    else:  # no trial step lowers the cost: the damping grows until it gives up
        evaluate = zoomwide._ZoomProblem.evaluate

        def no_trial_is_better(self, state, jacobian=True):
            out = evaluate(self, state, jacobian)
            return out if jacobian else np.full_like(out, np.inf)

        monkeypatch.setattr(zoomwide._ZoomProblem, "evaluate", no_trial_is_better)
    zw = calibrate_zoom_wide(obs, select=False, print_shape=True)
    assert not zw.converged and zw.stop_reason == limit
    assert all(not r.info["converged"] and r.info["stop_reason"] == limit
               for r in zw.results.values())
    # the print's test cannot judge a solve that stopped short: it says so, and the print is
    # taken to be exact
    test = zw.print_test
    assert not test.kept and np.isnan(test.wald) and limit in test.why, test
    assert "could not be judged" in test.summary() and zw.print_modes is None


def test_the_print_shape_is_found_and_keeps_the_principal_point_honest():
    # a print that is a trapezoid and a bow of a few tenths of a mm (drawn, kept from the
    # fit): the print's in-plane modes find it, and the principal point stays within its
    # sigmas; taking the print to be exact moves the narrow steps' principal point by many
    # of theirs (on a real PTZ sweep by 130-190 px, docs/notes/real-camera-print.md)
    rng = np.random.default_rng(71)
    trapezoid = rng.uniform(0.3, 0.6) * rng.choice([-1.0, 1.0])
    bow = rng.uniform(-0.3, 0.3)
    obs, truth, _ = sweep_observations(rng, steps=5, views=10, fx_range=(2300.0, 6000.0),
                                       print_mm=(trapezoid, bow))
    starts = zoom_wide_starts(obs)  # the steps' own fits, for both adjustments
    found = calibrate_zoom_wide(obs, print_shape=True, starts=starts)
    exact = calibrate_zoom_wide(obs, starts=starts)
    assert found.print_test.kept and exact.print_test is None
    # the xy mode of x is the trapezoid itself (P1(x) P1(y)); x^2 = (2 P2(x) + 1) / 3, its
    # constant a shift (a pose)
    assert found.print_modes.shape == (2, found.board_modes.size)
    got = found.print_modes[:, [1, 2]]
    sd = found.print_modes_sd[:, [1, 2]]
    assert abs(got[0, 0] - trapezoid) < 4 * sd[0, 0], (got, sd, trapezoid)
    assert abs(got[1, 1] - 2 * bow / 3) < 4 * sd[1, 1], (got, sd, bow)
    z = {label: [(getattr(zw.results[n], q) - t[q]) / zw.results[n].sd[q]
                 for n, t in truth.items() for q in ("fx", "cx", "cy")]
         for label, zw in (("found", found), ("exact", exact))}
    rms = np.sqrt(np.mean(np.square(z["found"])))
    assert max(np.abs(z["found"])) < 4 and 0.4 < rms < 1.6, z["found"]
    assert max(np.abs(z["exact"])) > 6, z["exact"]


def test_an_exact_print_is_found_exact(sweep, sweep_starts):
    # the shared sweep's board is printed exactly: the print's modes do not pass their test
    # (chi-square of 24 at p = 0.001: 51.2) and are left out: the adjustment is then the one
    # without them (within a tenth of a sigma)
    obs, _, _, points = sweep
    zw = calibrate_zoom_wide(obs, print_shape=True, starts=sweep_starts)
    test = zw.print_test
    assert test is not None and not test.kept and test.wald < test.threshold, test
    assert test.dof == 2 * zw.board_modes.size and zw.print_modes is None
    assert points.print_test is None
    for name, r in points.results.items():
        got = zw.results[name]
        for q in ("fx", "cx", "cy"):  # seen: up to 0.04 sigma, sigmas within 1.1 %
            assert abs(getattr(got, q) - getattr(r, q)) < 0.1 * r.sd[q], (name, q)
            assert got.sd[q] == pytest.approx(r.sd[q], rel=0.03), (name, q)


def test_a_basin_is_judged_with_the_terms_its_chain_lends_it():
    # a pincushion with k2: the wider steps' held-out views choose k2, the narrowest k1
    # alone, and the adjustment ties k2 into them through its zoom model; their principal
    # point's basin is judged with it (a basin that needs k2 must not lose for want of it),
    # and the state they keep has their own terms
    rng = np.random.default_rng(5)
    obs, truth, _ = sweep_observations(rng, steps=7, views=10, fx_range=(2300.0, 9000.0),
                                       dist=lambda u: np.array([-0.2, 8.0, 0.0, 0.0, 0.0]))
    zw = calibrate_zoom_wide(obs)
    own = {n: set(r.info["distortion_choice"]["terms"]) for n, r in zw.results.items()}
    judged = {n: set(r.info["basin"]["terms"]) for n, r in zw.results.items()}
    lent = [n for n in obs if own[n] == {"k1"}]
    assert sum("k2" in t for t in own.values()) >= 3 and lent, own
    for n in obs:  # its own terms with their decentring, and the chain's k2
        assert judged[n] == own[n] | {"k1", "k2", "p1", "p2"}, (n, own[n], judged[n])
    for n in lent:  # the smoothness prior frees k2 there, as the basin check assumed
        assert "k2" in zw.results[n].info["zoom_model"], n
        assert zw.results[n].dist[1] != 0.0, n
    z = [(getattr(zw.results[n], q) - t[q]) / zw.results[n].sd[q]
         for n, t in truth.items() for q in ("fx", "cx", "cy")]
    assert max(np.abs(z)) < 4 and 0.4 < np.sqrt(np.mean(np.square(z))) < 1.6, z


def test_a_step_between_two_basins_takes_both_into_its_sigmas(rng, monkeypatch):
    # the narrowest step's basin check is made to report a second basin (80, -40 px away in
    # cx, cy, p1 0.02 away) that its views do not tell from the chosen one: the adjustment
    # is unchanged, and that step's sigmas of cx, cy, p1 take half the distance in
    # quadrature, no other's
    import copy
    import dataclasses

    import zoomcalib.calibrate.zoomwide as zoomwide

    obs, _, _ = sweep_observations(rng, steps=3, views=8, fx_range=(2300.0, 6000.0))
    plain = calibrate_zoom_wide(obs, select=False)
    real = zoomwide.best_basin

    def two_basins(step_obs, K, dist, flags, noise_px):
        check = real(step_obs, K, dist, flags, noise_px)
        if check.fit is None or K[0, 0] < 5000.0:
            return check
        other = copy.copy(check.fit)
        other.K = check.fit.K + np.array([[0.0, 0, 80], [0, 0, -40], [0, 0, 0]])
        other.dist = np.asarray(check.fit.dist, float).copy()
        other.dist[2] += 0.02  # p1 (a term the step estimates only where it has k1)
        return dataclasses.replace(check, second=other, second_view_t=0.5,
                                   second_view_t_needed=3.6)

    monkeypatch.setattr(zoomwide, "best_basin", two_basins)
    mixed = calibrate_zoom_wide(obs, select=False)
    narrow = max(plain.results, key=lambda n: plain.results[n].fx)
    for name, r in mixed.results.items():
        before = plain.results[name]
        assert r.cx == before.cx and r.fx == before.fx, name
        gap = {"fx": 0.0, "cx": 40.0, "cy": 20.0} if name == narrow else dict.fromkeys(
            ("fx", "cx", "cy"), 0.0)
        for q, g in gap.items():
            assert r.sd[q] == pytest.approx(np.hypot(before.sd[q], g), rel=1e-9), (name, q)
        # the decentring takes its gap too (every term is free: select=False)
        p1_gap = 0.01 if name == narrow else 0.0
        assert r.sd["p1"] == pytest.approx(np.hypot(before.sd["p1"], p1_gap), rel=1e-6), name
        assert r.info["basin"]["ambiguous"] == (name == narrow)
        # the noise model's sigma is without the gap; the rows of the solve without the
        # prior (the held-out checks and a diagnosis read them) carry it as the table does
        for q in ("fx", "cx", "cy"):
            assert r.info["sd_noise_model"][q] == pytest.approx(
                before.info["sd_noise_model"][q], rel=1e-9), (name, q)
            assert mixed.unsmoothed[name][f"sd_{q}"] == pytest.approx(np.hypot(
                plain.unsmoothed[name][f"sd_{q}"], gap[q]), rel=1e-9), (name, q)
    flags = _basin_flags(mixed.results[narrow].info["basin"])
    assert [f.severity for f in flags if "two basins" in f.text] == ["note"], flags


def test_the_basin_check_fits_the_corners_the_adjustment_keeps(rng):
    # a few corners of the narrowest step are 15-30 px off (drawn): the adjustment rejects
    # them, and the basin check's fit of the step alone on its board (info["basin"]["alone"])
    # must see the same corners, landing where the adjustment's solve without the prior is
    obs, _, _ = sweep_observations(rng, steps=3, views=8, fx_range=(2300.0, 6000.0))
    narrow = list(obs)[-1]
    views = []
    for ids, uv in obs[narrow].views:
        uv = uv.copy()
        bad = rng.choice(len(uv), size=3, replace=False)
        uv[bad] += rng.uniform(15.0, 30.0, (3, 2)) * rng.choice([-1.0, 1.0], (3, 2))
        views.append((ids, uv))
    obs = obs | {narrow: Observations(obs[narrow].object_points, views, obs[narrow].image_size)}
    zw = calibrate_zoom_wide(obs, select=False)
    r = zw.results[narrow]
    assert len(r.rejected) >= 3 * len(views)
    basin = r.info["basin"]
    for q, start in zip(("cx", "cy"), basin["start_px"], strict=True):
        assert abs(basin["alone"][q] - start) < 3 * r.info["sd_noise_model"][q], (q, basin)


def test_a_covariance_that_rounding_leaves_indefinite_takes_a_ridge_and_says_so(rng):
    """The posterior covariance's inverse: exact where the information is positive definite;
    where rounding leaves it indefinite (a rank-deficient product plus a perturbation of
    1e-12), the ridge is taken and recorded, and the directions the information determines
    keep their inverse."""
    from types import SimpleNamespace

    from zoomcalib.calibrate.zoomproblem import _inverse_or_ridge

    A = rng.normal(size=(40, 6)) * np.array([1e3, 1.0, 1.0, 1e-2, 10.0, 1.0])
    S = A.T @ A
    prob = SimpleNamespace(covariance_ridge=None)
    assert np.allclose(_inverse_or_ridge(S, prob) @ S, np.eye(6), atol=1e-8)
    assert prob.covariance_ridge == 0.0
    # two equal columns: singular; a symmetric perturbation makes it indefinite
    B = np.column_stack([A, A[:, 0]])
    T = B.T @ B
    T -= 1e-12 * np.abs(T).max() * np.eye(7)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(T)
    cov = _inverse_or_ridge(T, prob)
    assert prob.covariance_ridge == 1e-6 and np.all(np.isfinite(cov))
    # a direction the information determines (column 1 alone) keeps its variance
    assert cov[1, 1] == pytest.approx(np.linalg.inv(S)[1, 1], rel=1e-3)
    # rounding of 2e-5 of the diagonal (as the information's difference of nearly equal terms
    # left it on a real wide-angle half): the smallest ridge that covers it, not a failure
    d = 1.0 / np.sqrt(np.diag(T))
    U = T - 2e-5 * np.diag(1.0 / d**2)
    cov = _inverse_or_ridge(U, prob)
    assert prob.covariance_ridge == 1e-4 and np.all(np.isfinite(cov))
    assert cov[1, 1] == pytest.approx(np.linalg.inv(S)[1, 1], rel=1e-2)
    with pytest.raises(np.linalg.LinAlgError, match="indefinite beyond rounding"):
        _inverse_or_ridge(T - 0.1 * np.diag(np.diag(T)), prob)


def test_a_print_test_that_five_terms_cannot_judge_is_judged_with_the_chosen_terms(
        rng, monkeypatch):
    """Where the print test's solve with k1, k2, p1, p2 and k3 free at every step stops
    short (forced here: it is told it did not converge), the print is judged with each step's
    chosen terms, which says so, and a kept print goes on from that solve; where both stop
    short, it cannot be judged and is taken to be exact."""
    import zoomcalib.calibrate.zoomwide as zoomwide

    trapezoid = rng.uniform(0.3, 0.6)
    obs, _, _ = sweep_observations(rng, steps=4, views=8, fx_range=(2300.0, 6000.0),
                                   print_mm=(trapezoid, 0.0))
    solve_with_noise = zoomwide._solve_with_noise
    free_counts = []

    def five_terms_stop_short(prob, state, free, max_rounds):
        solve, iterations = solve_with_noise(prob, state, free, max_rounds)
        free_counts.append(int(free.sum()))
        if len(free_counts) in stop_short:
            solve = replace(solve, stop_reason="iteration cap")
        return solve, iterations

    from dataclasses import replace

    monkeypatch.setattr(zoomwide, "_solve_with_noise", five_terms_stop_short)
    stop_short = {1}
    starts = zoom_wide_starts(obs)  # the steps' own fits, for both adjustments
    zw = calibrate_zoom_wide(obs, print_shape=True, starts=starts)
    test = zw.print_test
    # the first solve had every step's five terms free, the second the chosen ones (fewer)
    assert free_counts[0] > free_counts[1], free_counts
    assert test.why is None and test.kept and zw.print_modes is not None, test
    assert test.terms.startswith("each step's chosen terms") and "iteration cap" in test.terms
    assert "judged with each step's chosen terms" in test.summary()
    free_counts.clear()
    stop_short = {1, 2}
    zw = calibrate_zoom_wide(obs, print_shape=True, starts=starts)
    assert not zw.print_test.kept and "iteration cap" in zw.print_test.why
    assert zw.print_modes is None
