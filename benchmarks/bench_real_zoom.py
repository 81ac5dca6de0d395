"""A zoom sweep of real corners: mrcal's figueroa set cut by a digital zoom.

``python benchmarks/bench_real_zoom.py [--zooms 1.5 4 7] [--views 24] [--drift 30]
[--splits 10] [--seed 1] [--pp-model angle2] [--board-degree 4] [--unpooled]
[--backends zoom-wide opencv bundle]``

:func:`zoomcalib.calibrate.digital_zoom.digital_zoom_sweep` crops the 186 real views (6016 x
4016, a wide lens) to windows of ``1/z`` of the sensor, scaled to 1280 x 854 px, one window per
zoom step, each real view used by one step only. Every step is then a camera whose noise, lens
misfit and board warp are real. Three backends calibrate the sweep with default settings:
zoom-wide, per-step OpenCV, per-step bundle (their view-scatter tests pooled over the steps,
as ``calibrate`` does, and for the halves over both halves' steps, as ``calibrate
--cross-validate`` does; ``--unpooled``: each step's alone). Two checks, neither of which knows
the truth:

- halves: each step's views in two halves (even/odd groups of nearly one pose, then
  ``--splits - 1`` random splits of the groups), both halves calibrated, ``z`` of fx, cx, cy
  over their combined reported sigma (the issue's real-set goal: within 3);
- one camera: each step's fx, cx, cy mapped back to the sensor must be the same camera's,
  so each step is compared with the weighted mean of the others,
  ``z = (b_k - mean_others) / sqrt(sd_k^2 + sd_mean^2)`` (zoom-wide's steps share the board
  and the prior, so its z are conservative).

Last, where the one-camera check fails: each step's fx mapped back, from ``cv2.calibrateCamera``
with the five-term model free and with the distortion held at the bundle's rational fit of
all 186 full views (mrcal's weights; fx, cx, cy free), and from the per-step bundle with the
standard and the rational model. A lens the model fits gives the same fx whatever part of the
field a step sees.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.bundle import calibrate_bundle  # noqa: E402
from zoomcalib.calibrate.checks import (  # noqa: E402
    conditioning_flags,
    pooled_halves,
    random_halves,
)
from zoomcalib.calibrate.digital_zoom import DigitalZoom, digital_zoom_sweep  # noqa: E402
from zoomcalib.calibrate.io import observations_from_npz  # noqa: E402
from zoomcalib.calibrate.opencv_backend import calibrate_opencv_robust  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.scatter import pooled_over_steps  # noqa: E402
from zoomcalib.calibrate.zoomwide import board_height_modes, calibrate_zoom_wide  # noqa: E402

DATA = ROOT / "tests" / "data" / "mrcal-figueroa" / "figueroa_obs.npz"
COMPARED = ("fx", "cx", "cy")
POOLED = True  # per-step backends: the view-scatter test pooled over the steps, as calibrate does


def per_step(calibrate):
    def run(observations: dict[str, Observations]):
        out = {}
        for step, obs in observations.items():
            try:
                out[step] = calibrate(obs)
            except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
                print(f"    {step}: failed ({exc})")
        return out
    return run


BACKENDS = {
    "zoom-wide": lambda obs: calibrate_zoom_wide(obs).results,
    "opencv": per_step(calibrate_opencv_robust),
    "bundle": per_step(calibrate_bundle),
}


def _choice(result) -> str:
    """Zoom-wide: the distortion terms estimated, and the held-out mean squared error of the
    rational model over the five-term one's (``select_distortion``)."""
    mse = result.info.get("distortion_choice", {}).get("mse_px2", {})
    if not mse:
        return ""
    return (f"  {len(result.dist)} terms (held-out rational/five "
            f"{mse['rational'] / mse['k1k2p1p2k3']:.2f})")


def camera_table(sweep: DigitalZoom, name: str, results: dict) -> np.ndarray:
    """Print each step's values mapped to the sensor; return the z against the other steps."""
    steps = [s for s in sweep.observations if s in results]
    value = np.array([sweep.to_sensor(s, *(getattr(results[s], q) for q in COMPARED))
                      for s in steps])
    sd = np.array([[results[s].sd[q] / sweep.scale[s] for q in COMPARED] for s in steps])
    z = np.full_like(value, np.nan)
    for k in range(len(steps)):
        other = np.arange(len(steps)) != k
        w = 1.0 / sd[other] ** 2
        mean = (w * value[other]).sum(0) / w.sum(0)
        z[k] = (value[k] - mean) / np.sqrt(sd[k] ** 2 + 1.0 / w.sum(0))
    for k, s in enumerate(steps):
        r = results[s]
        flags = conditioning_flags(r, sweep.image_size)
        print(f"  {name:9s} {s}  fx {r.fx:7.1f}  sensor "
              + "  ".join(f"{q} {v:7.1f} +- {e:5.1f} (z {zz:+5.1f})"
                          for q, v, e, zz in zip(COMPARED, value[k], sd[k], z[k], strict=True))
              + f"  rms {r.rms_px:.3f}" + _choice(r) + (f"  [{flags[0]}]" if flags else ""))
    return z


def focal_by_distortion(source: Observations, weights: list, sweep: DigitalZoom) -> None:
    """Each step's sensor fx with the distortion free (five terms) and held at the full
    set's rational fit."""
    full = calibrate_bundle(source, model="rational", weights=weights)
    held = (cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_FIX_TANGENT_DIST | cv2.CALIB_FIX_K1
            | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5
            | cv2.CALIB_FIX_K6)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    print(f"  full set, bundle, rational: fx {full.fx:.1f} cx {full.cx:.1f} cy {full.cy:.1f}")
    for label, flags, dist in (("five terms free", 0, np.zeros(5)),
                               ("rational held", held, np.ravel(full.dist))):
        fx = []
        for step, obs in sweep.observations.items():
            s, c, mid = sweep.scale[step], sweep.window_centre[step], sweep.output_centre()
            K = np.array([[s * full.fx, 0.0, s * (full.cx - c[0]) + mid[0]],
                          [0.0, s * full.fy, s * (full.cy - c[1]) + mid[1]], [0.0, 0.0, 1.0]])
            _, K, _, _, _ = cv2.calibrateCamera(
                [obs.object_points[ids].astype(np.float32) for ids, _ in obs.views],
                [uv.astype(np.float32) for _, uv in obs.views], obs.image_size, K,
                dist.copy(), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=criteria)
            fx.append(sweep.to_sensor(step, K[0, 0], K[0, 2], K[1, 2])[0])
        print(f"  sensor fx, {label:15s}: " + " ".join(f"{v:.1f}" for v in fx)
              + f"  (spread {100 * np.ptp(fx) / np.mean(fx):.2f} %)")
    for model in ("standard", "rational"):
        fits = per_step(lambda obs, model=model: calibrate_bundle(obs, model=model))(
            sweep.observations)
        print(f"  per-step bundle, {model:8s}: " + " ".join(
            f"{s} fx {sweep.to_sensor(s, r.fx, r.cx, r.cy)[0]:.1f} rms {r.rms_px:.3f}"
            for s, r in fits.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zooms", type=float, nargs=3, default=(1.5, 4.0, 7),
                    metavar=("FIRST", "LAST", "STEPS"))
    ap.add_argument("--views", type=int, default=24, help="views per step")
    ap.add_argument("--drift", type=float, default=30.0, help="principal point move, px")
    ap.add_argument("--splits", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pp-model", default="angle2", choices=["angle2", "prior2", "select"],
                    help="zoom-wide's prior on cx, cy")
    ap.add_argument("--board-degree", type=int, default=4,
                    help="zoom-wide's board height modes (< 2: a flat board)")
    ap.add_argument("--unpooled", action="store_true",
                    help="per-step backends: each step's view-scatter test on its own")
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    a = ap.parse_args()
    global POOLED
    POOLED = not a.unpooled
    warnings.simplefilter("ignore")
    source, weights = observations_from_npz(DATA)
    rng = np.random.default_rng(a.seed)
    zooms = np.geomspace(a.zooms[0], a.zooms[1], int(a.zooms[2]))
    sweep = digital_zoom_sweep(source, zooms, views_per_step=a.views, drift_px=a.drift, rng=rng)
    print(f"digital zoom of figueroa: {sweep.image_size[0]} x {sweep.image_size[1]} px, "
          + ", ".join(f"{s} {o.n_views} views {o.n_observations} corners fx~"
                      f"{2072 * sweep.scale[s]:.0f}" for s, o in sweep.observations.items()))
    parts = {s: random_halves(o, a.splits, rng) for s, o in sweep.observations.items()}
    zoom_wide_fits: list = []

    def zoom_wide(obs: dict[str, Observations]) -> dict:
        result = calibrate_zoom_wide(obs, pp_model=a.pp_model, board_degree=a.board_degree)
        zoom_wide_fits.append(result)
        return result.results

    BACKENDS["zoom-wide"] = zoom_wide
    for name in a.backends:
        calibrate, t0 = BACKENDS[name], time.time()
        results = calibrate(sweep.observations)
        if name != "zoom-wide" and POOLED:
            results = pooled_over_steps(results)
        z_camera = camera_table(sweep, name, results)
        if name == "zoom-wide" and a.board_degree >= 2:
            height = (board_height_modes(source.object_points, a.board_degree)
                      @ zoom_wide_fits[0].board_modes)
            print(f"  zoom-wide board: heights {height.min():+.2f} to {height.max():+.2f} mm, "
                  f"RMS {np.std(height):.2f} mm (largest mode sigma "
                  f"{zoom_wide_fits[0].board_modes_sd.max():.3f} mm)")
        print(f"  {name:9s} one camera: RMS z " + " ".join(
            f"{q} {v:.2f}" for q, v in zip(COMPARED, np.sqrt(np.nanmean(z_camera**2, 0)),
                                           strict=True))
              + f", max |z| {np.nanmax(np.abs(z_camera)):.1f}  ({time.time() - t0:.0f} s)")
        z_half = {s: [] for s in sweep.observations}
        for k in range(a.splits):
            half_a = calibrate({s: p[k][0] for s, p in parts.items()})
            half_b = calibrate({s: p[k][1] for s, p in parts.items()})
            if name != "zoom-wide" and POOLED:
                half_a, half_b = pooled_halves(half_a, half_b)
            for s in sweep.observations:
                if s in half_a and s in half_b:
                    ra, rb = half_a[s], half_b[s]
                    z_half[s].append([(getattr(ra, q) - getattr(rb, q))
                                      / np.hypot(ra.sd[q], rb.sd[q]) for q in COMPARED])
        every = np.concatenate([np.reshape(v, (-1, 3)) for v in z_half.values()])
        print(f"  {name:9s} halves ({a.splits} splits): per step RMS z fx/cx/cy "
              + ", ".join(f"{s} " + "/".join(f"{v:.1f}" for v in np.sqrt(np.mean(
                  np.square(z), 0))) for s, z in z_half.items() if len(z))
              + f"; max |z| {np.abs(every).max():.1f}, |z| > 3: {(np.abs(every) > 3).sum()}"
              f" of {every.size}  ({time.time() - t0:.0f} s)")

    focal_by_distortion(source, weights, sweep)


if __name__ == "__main__":
    main()
