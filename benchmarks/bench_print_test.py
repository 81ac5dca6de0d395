"""How often the print test keeps an in-plane print shape where the truth has none, and why.

``python benchmarks/bench_print_test.py [--seeds 10] [--first 100] [--wave 0.3] [--workers 2]
[--fx-range 2300 23000] [--versions wave flat truth] [--no-noiseless]``

Each sweep comes from ``sweep_observations`` of ``tests/test_zoomwide.py`` (6 steps x 8 views, fx
2300-23000 px or ``--fx-range``, Gaussian detection noise 0.02 px; the board exact in its plane,
bent by a sine wave of ``--wave`` mm) with seeds ``first .. first + seeds - 1``. The zoom-wide
adjustment with ``print_shape=True`` runs on three versions of the same detections (same noise draw;
those of ``--versions``):

- ``wave``: the board as generated, fitted as a user would (the default board model);
- ``flat``: the same sweep with no wave (``wave_mm=0``);
- ``truth``: the ``wave`` detections with the true bent board given as the object points.

Printed per seed and version: the print test's Wald statistic (24 degrees of freedom, its threshold
at p = 0.001) and whether it kept the print; then per version how many kept it and the mean, median
and sd of the Wald statistic (chi-square on 24 under the null). Without a print in the truth, every
keep is a false alarm. Then one seed again with the noise at 1e-5 px: the largest print amplitude
fitted where the board's shape is fitted (``wave``, ``--wave`` and twice it) and the per-step RMS
with the print left out: a misfit that grows as the square of the wave is second order in the
board's slope, which a height model at the nominal in-plane positions does not follow.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout
sys.path.insert(0, str(ROOT / "tests"))

from test_zoomwide import sweep_observations  # noqa: E402

from zoomcalib.calibrate.zoomwide import calibrate_zoom_wide  # noqa: E402
from zoomcalib.pool import map_in_processes  # noqa: E402

VERSIONS = ("wave", "flat", "truth")


def _one(seed: int, version: str, wave_mm: float, fx_range: tuple[float, float]
         ) -> tuple[float, float, bool]:
    warnings.simplefilter("ignore")
    rng = np.random.default_rng(seed)
    obs, truth, _ = sweep_observations(rng, steps=6, views=8, fx_range=fx_range,
                                       wave_mm=0.0 if version == "flat" else wave_mm)
    if version == "truth":
        obs = {n: dataclasses.replace(o, object_points=truth[n]["X"]) for n, o in obs.items()}
    test = calibrate_zoom_wide(obs, print_shape=True).print_test
    return test.wald, test.threshold, test.kept


def _noiseless(seed: int, wave_mm: float, print_shape: bool) -> tuple[float, list[float]]:
    warnings.simplefilter("ignore")
    obs, _, _ = sweep_observations(np.random.default_rng(seed), steps=6, views=8,
                                   wave_mm=wave_mm, noise=1e-5)
    res = calibrate_zoom_wide(obs, print_shape=print_shape)
    largest = np.nan if res.print_modes is None else float(np.abs(res.print_modes).max())
    return largest, [r.rms_px for r in res.results.values()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first", type=int, default=100)
    parser.add_argument("--wave", type=float, default=0.3, help="mm")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--fx-range", type=float, nargs=2, default=(2300.0, 23000.0),
                        metavar=("LO", "HI"), help="focal lengths of the 6 steps, px")
    parser.add_argument("--versions", nargs="+", choices=VERSIONS, default=list(VERSIONS))
    parser.add_argument("--no-noiseless", action="store_true",
                        help="leave out the runs at 1e-5 px of noise")
    args = parser.parse_args()
    seeds = range(args.first, args.first + args.seeds)
    versions = [v for v in VERSIONS if v in args.versions]
    fx_range = tuple(args.fx_range)
    items = [(s, v, args.wave, fx_range) for s in seeds for v in versions]
    out = dict(zip(((s, v) for s, v, *_ in items), map_in_processes(_one, items, args.workers),
                   strict=True))
    threshold = next(iter(out.values()))[1]
    print(f"print test: Wald on 24 degrees of freedom, threshold {threshold:.1f} (p = 0.001); "
          f"fx {fx_range[0]:.0f}-{fx_range[1]:.0f} px")
    print("seed  " + "  ".join(f"{v:>14}" for v in versions))
    for s in seeds:
        print(f"{s:4d}  " + "  ".join(f"{out[s, v][0]:8.1f} {'kept' if out[s, v][2] else '    '}"
                                      for v in versions))
    for v in versions:
        walds = np.array([out[s, v][0] for s in seeds])
        kept = sum(out[s, v][2] for s in seeds)
        print(f"{v:>5}: kept {kept} of {len(seeds)}, mean Wald {np.nanmean(walds):.1f}, "
              f"median {np.nanmedian(walds):.1f}, sd {np.nanstd(walds, ddof=1):.1f} "
              "(chi-square on 24: 24, 23.3, 6.9)")
    if args.no_noiseless:
        return
    print(f"noise 1e-5 px, seed {args.first}:")
    for wave in (0.0, args.wave, 2 * args.wave):
        largest, _ = _noiseless(args.first, wave, True)
        _, rms = _noiseless(args.first, wave, False)
        print(f"  wave {wave:.2f} mm: largest print mode {largest * 1e3:.3f} um with the print; "
              f"without it, RMS {min(rms):.2e}-{max(rms):.2e} px")


if __name__ == "__main__":
    main()
