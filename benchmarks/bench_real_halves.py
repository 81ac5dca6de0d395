"""Real sets split in two: do the halves agree within their sigmas?

``python benchmarks/bench_real_halves.py [--splits 20] [--jackknife 0] [--seed 1] [--own-tests]``

The check mrcal calls its most important, on data nobody on this project made:

- ``figueroa``: mrcal's 186 real views of a 10 x 10 board (6016 x 4016, a wide lens; the
  rational model, mrcal's weights), calibrated by the bundle (default settings) and by the
  bundle with the target held flat (OpenCV's model of the board);
- ``opencv-samples``: OpenCV's 13 real sample images (640 x 480, JPEG, 9 x 6 board), detected
  with the default detector, calibrated by ``calibrate_opencv`` and the bundle.

Each split puts every view at random in one of two halves (the first split of each set: even
and odd views), views of nearly one pose together (figueroa's 186 views are 163 such groups),
calibrates each half and computes ``z_q = (q_a - q_b) / sqrt(sd_a^2 + sd_b^2)``
for fx, fy, cx, cy, once with the noise model's sigmas (``info['sd_noise_model']``) and once with
the reported ones (scaled where the view-scatter check finds the views disagreeing,
:mod:`zoomcalib.calibrate.scatter`, its test pooled over both halves as ``calibrate
--cross-validate`` pools it, :func:`~zoomcalib.calibrate.checks.pooled_halves`;
``--own-tests``: each half's test on its own). Honest sigmas give an RMS z near 1 and |z| > 3
in 0.3 % of values. Splits share views, so their z are not independent; the RMS is still the
right size.

``--jackknife G`` also gives, for each half of the first ``min(splits, 4)`` figueroa splits,
the delete-a-group jackknife sigma (G groups of views, each left out once): a resampling
reference that no linearisation enters, printed as its ratio to the noise model's.
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
from zoomcalib.calibrate.checks import pooled_halves  # noqa: E402
from zoomcalib.calibrate.io import observations_from_npz  # noqa: E402
from zoomcalib.calibrate.opencv_backend import (  # noqa: E402
    calibrate_opencv,
    observations_from_detections,
)
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.scatter import view_groups  # noqa: E402
from zoomcalib.detect.opencv import detect_folder  # noqa: E402

DATA = ROOT / "tests" / "data"
COMPARED = ("fx", "fy", "cx", "cy")


def subset(obs: Observations, idx: np.ndarray) -> Observations:
    return Observations(obs.object_points, [obs.views[i] for i in idx], obs.image_size)


def splits(groups: np.ndarray, count: int, rng: np.random.Generator):
    """Even/odd groups of views first, then random halves of the groups (views of nearly one
    pose, :func:`~zoomcalib.calibrate.scatter.view_groups`, stay in one half)."""
    n_groups = int(groups.max()) + 1
    yield np.flatnonzero(groups % 2 == 0), np.flatnonzero(groups % 2 == 1)
    for _ in range(count - 1):
        first = rng.permutation(n_groups)[: n_groups // 2]
        in_first = np.isin(groups, first)
        yield np.flatnonzero(in_first), np.flatnonzero(~in_first)


def z_values(a, b, key: str | None) -> np.ndarray:
    def sd(r, q):
        return r.info["sd_noise_model"][q] if key else r.sd[q]
    return np.array([(getattr(a, q) - getattr(b, q)) / np.hypot(sd(a, q), sd(b, q))
                     for q in COMPARED])


def jackknife_sd(calibrate, obs: Observations, groups: int, rng: np.random.Generator):
    label = rng.permutation(obs.n_views) % groups
    values = np.array([[getattr(calibrate(subset(obs, np.flatnonzero(label != g))), q)
                        for q in COMPARED] for g in range(groups)])
    return np.sqrt((groups - 1) / groups * ((values - values.mean(0)) ** 2).sum(0))


def run_set(name: str, obs: Observations, fits: dict, count: int, seed: int,
            jackknife: int, pool: bool) -> None:
    rng = np.random.default_rng(seed)
    groups = view_groups(obs.views, obs.image_size)
    print(f"{name}: {obs.n_views} views in {groups.max() + 1} groups of nearly one pose")
    parts = list(splits(groups, count, rng))
    for fit, calibrate in fits.items():
        t0 = time.time()
        z_model, z_used, factors, failed = [], [], [], 0
        for k, (a, b) in enumerate(parts):
            try:
                ra, rb = calibrate(subset(obs, a)), calibrate(subset(obs, b))
            except (ValueError, RuntimeError) as exc:
                failed += 1
                print(f"  {name} {fit} split {k}: failed ({exc})")
                continue
            if not (ra.converged and rb.converged):
                failed += 1
                print(f"  {name} {fit} split {k}: not converged, left out")
                continue
            if pool:
                (ra,), (rb,) = (half.values() for half in pooled_halves({"": ra}, {"": rb}))
            z_model.append(z_values(ra, rb, "model"))
            z_used.append(z_values(ra, rb, None))
            factors += [[r.info["view_scatter"]["factor"].get(q, np.nan) for q in COMPARED]
                        for r in (ra, rb)]
            if jackknife and k < 4:
                jk = [jackknife_sd(calibrate, subset(obs, idx), jackknife, rng) for idx in (a, b)]
                model = [np.array([r.info["sd_noise_model"][q] for q in COMPARED])
                         for r in (ra, rb)]
                print(f"  {name} {fit} split {k}: jackknife/noise-model sigma (halves) "
                      + " ".join(f"{q} {j0:.2f}/{j1:.2f}" for q, j0, j1 in
                                 zip(COMPARED, jk[0] / model[0], jk[1] / model[1],
                                     strict=True)))
        for label, z in (("noise model", z_model), ("reported", z_used)):
            z = np.array(z)
            print(f"{name:15s} {fit:14s} {label:12s} RMS z "
                  + " ".join(f"{q} {v:5.2f}" for q, v in zip(COMPARED, np.sqrt((z**2).mean(0)),
                                                            strict=True))
                  + f"   max |z| {np.abs(z).max():5.2f}, |z| > 3: {(np.abs(z) > 3).sum()}"
                  f" of {z.size}")
        print(f"{name:15s} {fit:14s} view-scatter factor (median over halves) "
              + " ".join(f"{q} {v:.2f}" for q, v in zip(COMPARED, np.nanmedian(factors, 0),
                                                        strict=True))
              + f"; {len(z_model)} splits, {failed} left out, {time.time() - t0:.0f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", type=int, default=20)
    ap.add_argument("--jackknife", type=int, default=0, help="groups (0: none)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--own-tests", action="store_true",
                    help="each half's view-scatter test on its own, not pooled over both")
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    fig, weights = observations_from_npz(DATA / "mrcal-figueroa" / "figueroa_obs.npz")
    w_of = {id(v): w for v, w in zip(fig.views, weights, strict=True)}

    def bundle_rational(o: Observations, **kw):
        return calibrate_bundle(o, model="rational", weights=[w_of[id(v)] for v in o.views], **kw)

    run_set("figueroa", fig, {"bundle": bundle_rational,
                              "bundle, flat": lambda o: bundle_rational(o, refine_target=False)},
            a.splits, a.seed, a.jackknife, not a.own_tests)
    spec = "chessboard:9x6:25"
    samples = observations_from_detections(detect_folder(DATA / "opencv-samples", spec), spec)
    run_set("opencv-samples", samples, {"opencv": calibrate_opencv, "bundle": calibrate_bundle},
            a.splits, a.seed, 0, not a.own_tests)


if __name__ == "__main__":
    main()
