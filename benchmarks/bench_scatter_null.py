"""Under the noise model, does the view-scatter test's statistic average to 1?

``python benchmarks/bench_scatter_null.py [--draws 200] [--sweeps 12]``

The test of :mod:`zoomcalib.calibrate.scatter` divides the view-clustered sum by its
expectation under the noise model: ``null_share`` times the model variance (the views'
leverage, :func:`~zoomcalib.calibrate.scatter.noise_share`). Here the corners carry nothing but
independent Gaussian noise, so the squared test factor should average 1 (it spreads like
``chi2_d / d``). Printed beside it, what the old correction ``(d - 1) / d`` would have given,
the spread of the estimates over the draws against the reported noise-model sigma, and the
residual variance against the true one (beside it, what ``2 N - n`` in its denominator gave).

1. One seeded geometry (10 views of an 88-corner board, ``sweep_detections`` seed 401) with
   ``--draws`` redraws of 0.2 px corner noise, calibrated by the bundle three ways: the target
   held flat, refined without a shape prior, and refined with its default shape prior.
2. ``--sweeps`` seeded synthetic sweeps (5 steps of 12 views, 0.2 px), calibrated zoom-wide;
   every checked fx, fy, cx, cy counted.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.bundle import calibrate_bundle  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.synthetic import sweep_detections  # noqa: E402
from zoomcalib.calibrate.zoomwide import calibrate_zoom_wide  # noqa: E402

PINHOLE = ("fx", "fy", "cx", "cy")
BUNDLE_SETTINGS = {
    "flat target": {"refine_target": False},
    "refined, no prior": {"target_sigma_mm": None, "warp_sigma_mm": None},
    "refined, shape prior": {},
}


def statistic(check: dict) -> np.ndarray:
    """(q, 3): per checked pinhole term the squared test factor, ``null_share``, ``(d-1)/d``."""
    rows = []
    for q in PINHOLE:
        if q in check["test_factor"]:
            d = check["views"][q]
            rows.append((check["test_factor"][q] ** 2, check["null_share"][q], (d - 1) / d))
    return np.array(rows).reshape(-1, 3)


def report(label: str, stats: np.ndarray, seconds: float) -> None:
    """Means over all counted terms: F^2 with the leverage (its standard error) and with
    ``(d - 1) / d`` in its place."""
    f2, share, approx = stats.T
    print(f"{label:30s} mean F^2 {f2.mean():.3f} +- {f2.std() / np.sqrt(len(f2)):.3f}"
          f" (with (d-1)/d: {np.mean(f2 * share / approx):.3f}); null_share {share.mean():.3f},"
          f" (d-1)/d {approx.mean():.3f}; {len(f2)} terms, {seconds:.0f} s")


def bundle_draws(draws: int) -> None:
    sweep = sweep_detections(np.random.default_rng(401), steps=1, views=10, noise_px=0.0)
    (exact,) = sweep.observations.values()
    truth = next(iter(sweep.truth.values()))
    for label, settings in BUNDLE_SETTINGS.items():
        rng, start = np.random.default_rng(5), time.perf_counter()
        stats, estimates, sigmas, noise = [], [], [], []
        for _ in range(draws):
            noisy = Observations(exact.object_points,
                                 [(ids, pts + 0.2 * rng.normal(size=pts.shape))
                                  for ids, pts in exact.views], exact.image_size)
            res = calibrate_bundle(noisy, **settings)
            stats.append(statistic(res.info["view_scatter"]))
            estimates.append([getattr(res, q) for q in PINHOLE])
            sigmas.append([res.info["sd_noise_model"][q] for q in PINHOLE])
            info = res.info
            s2 = info["sigma_px"] ** 2 / 0.2**2
            noise.append((s2, s2 * info["residual_dof"]
                          / (2 * info["n_observations"] - info["n_unknowns"])))
        report(f"bundle, {label}", np.concatenate(stats), time.perf_counter() - start)
        spread = np.std(estimates, axis=0) / np.sqrt(np.mean(np.square(sigmas), axis=0))
        true = [truth.get(q, truth["fx"]) for q in PINHOLE]      # square pixels: fy = fx
        bias = (np.mean(estimates, axis=0) - true) / np.std(estimates, axis=0)
        print(f"{'':30s} spread / noise-model sigma " + " ".join(
            f"{q} {s:.2f}" for q, s in zip(PINHOLE, spread, strict=True))
            + f" (+-{1 / np.sqrt(2 * draws):.2f}); mean error / spread "
            + " ".join(f"{b:+.2f}" for b in bias))
        s2, naive = np.mean(noise, axis=0)
        print(f"{'':30s} residual variance / true {s2:.3f} (dividing by 2N - n: {naive:.3f})")


def zoom_wide_sweeps(sweeps: int) -> None:
    stats, scaled, start = [], 0, time.perf_counter()
    for seed in range(sweeps):
        sweep = sweep_detections(np.random.default_rng(700 + seed), steps=5, views=12,
                                 noise_px=0.2)
        for res in calibrate_zoom_wide(sweep.observations).results.values():
            stats.append(statistic(res.info["view_scatter"]))
            scaled += bool(res.info["view_scatter"]["scaled"])
    report("zoom-wide", np.concatenate(stats), time.perf_counter() - start)
    print(f"{'':30s} steps with a scaled sigma: {scaled} of {5 * sweeps}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--draws", type=int, default=200, help="noise draws of the bundle's set")
    ap.add_argument("--sweeps", type=int, default=12, help="synthetic zoom-wide sweeps")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    if args.draws:
        bundle_draws(args.draws)
    if args.sweeps:
        zoom_wide_sweeps(args.sweeps)


if __name__ == "__main__":
    main()
