"""How well the zoom model (``zoom_model.json``, ``zoom_model_grid.csv``) follows a real zoom
lens between its steps. ``python benchmarks/bench_zoom_curve.py [--paths N] [--draws K]``.

The truth is not drawn from any curve the model can take: each path is the principal point of
the ray-traced ``laikin-10x`` zoom lens with drawn mechanical errors
(:func:`zoomcalib.render.pp_path.traced_path`, 40 px span), over fx 2300-23000 px. A zoom table
of ``--steps`` steps is keyed either by focal length (``fx``: equal focal ratios, as EXIF focal
lengths or zoom ratios are) or by a lens position linear in the cam (``position`` 100-1000).
Each step's cx, cy get noise of a stated 1-sigma that grows with fx, as per-step sigmas do:
``zoom-wide`` 0.05-2.5 px, ``per-step`` 2-20 px; fx 0.02 %.

For each rule the model is fitted and compared with the truth at 4 zooms between each pair of
steps: RMS error (px), RMS of the errors over the model's own 1-sigma, the RMS of the
held-out error :meth:`ZoomModel.holdout_error` reports (what ``calibrate`` prints), how often
the chosen degree of cx, cy is 4 or more, and how often a curve is flagged. Rules:

``old``
    the curves in zoom only, no misfit term;
``no misfit``
    ``log zoom`` tried as well (one abscissa for all curves), no misfit term;
``per curve``
    the abscissa chosen per curve (``POOL_ABSCISSA = False``), the misfit added;
``one-SE``
    as the default, the degree by the one-standard-error rule (the simplest candidate whose
    held-out mean square is within one standard error of the paired per-step differences from
    the best's; Hastie, Tibshirani & Friedman 2009, section 7.10);
``gate P``
    the misfit added where its held-out test has p < P (``MISFIT_GATE``; 1: always);
``default``
    as the package ships.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zoomcalib.render.pp_path import traced_path
from zoomcalib.zoom import ZoomModel
from zoomcalib.zoom import model as zoom_model

FX_RANGE = (2300.0, 23000.0)
NOISE_PX = {"zoom-wide": (0.05, 2.5), "per-step": (2.0, 20.0)}
FX_REL_SD = 2e-4
BETWEEN = 4


def keyed(s: np.ndarray, key: str) -> np.ndarray:
    return FX_RANGE[0] * (FX_RANGE[1] / FX_RANGE[0]) ** s if key == "fx" else 100.0 + 900.0 * s


def one_standard_error(tried):
    """The simplest candidate within one standard error of the best held-out mean square."""
    best = min(tried, key=lambda t: (t.mse, t.complexity))
    if not np.isfinite(best.mse) or len(best.loo_sq) < 3:
        return best

    def within(t) -> bool:
        diff = t.loo_sq - best.loo_sq
        return bool(np.all(np.isfinite(diff))
                    and np.mean(diff) <= np.std(diff, ddof=1) / np.sqrt(len(diff)))

    return min((t for t in tried if t is best or within(t)), key=lambda t: (t.complexity, t.mse))


RULES = {"old": {"log_zoom": False, "MIN_HELD_OUT": 10**9},
         "no misfit": {"MIN_HELD_OUT": 10**9},
         "per curve": {"POOL_ABSCISSA": False},
         "one-SE": {"_choose": None},
         "gate 1": {"MISFIT_GATE": 1.0}, "gate 0.05": {"MISFIT_GATE": 0.05},
         "gate 0.001": {"MISFIT_GATE": 0.001}, "default": {}}


def one_fit(rule: str, zoom: np.ndarray, values: dict, sd: dict, zoom_between: np.ndarray,
            truth_between: dict) -> dict:
    settings = dict(RULES[rule])
    log_zoom = settings.pop("log_zoom", None)
    if "_choose" in settings:
        settings["_choose"] = one_standard_error
    saved = {k: getattr(zoom_model, k) for k in settings}
    for k, v in settings.items():
        setattr(zoom_model, k, v)
    try:
        m = ZoomModel.fit(zoom, values, sd, log_zoom=log_zoom)
        held = m.holdout_error()
    finally:
        for k, v in saved.items():
            setattr(zoom_model, k, v)
    pred = m.predict(zoom_between)
    err = {k: pred[k] - truth_between[k] for k in ("cx", "cy")}
    return {"err": np.concatenate([err["cx"], err["cy"]]),
            "z": np.concatenate([err[k] / pred[f"sd_{k}"] for k in ("cx", "cy")]),
            "held": np.array([held["cx"], held["cy"]]),
            "high": sum(m.fits[k].degree >= 4 for k in ("cx", "cy")),
            "flagged": sum(m.fits[k].misfit_flagged for k in ("cx", "cy"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=20, help="traced lenses (seeds 0..N-1)")
    parser.add_argument("--draws", type=int, default=10, help="noise draws per path")
    parser.add_argument("--steps", type=int, default=7)
    parser.add_argument("--runout", type=float, default=1.0,
                        help="the cam-track run-out's size (0: static errors only, a smooth path)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    start = time.perf_counter()
    s_steps = np.linspace(0.0, 1.0, args.steps)
    frac = (np.arange(BETWEEN) + 1.0) / (BETWEEN + 1.0)
    s_between = (s_steps[:-1, None] + frac / (args.steps - 1)).ravel()
    paths = []
    for seed in range(args.paths):
        path, _ = traced_path(np.concatenate([s_steps, s_between]), FX_RANGE, 40.0, seed,
                              args.runout)
        paths.append(path + [640.0, 360.0])
    rules = tuple(RULES)
    print(f"run-out {args.runout:g}: {args.paths} traced paths x {args.draws} noise draws, "
          f"{args.steps} steps, fx {FX_RANGE[0]:g}-{FX_RANGE[1]:g} px; "
          f"cx, cy at {BETWEEN} zooms between steps")
    print(f"{'key':9s} {'noise':10s} {'rule':10s} {'RMS err px':>10s} {'RMS z':>6s} "
          f"{'held-out px':>11s} {'deg>=4':>7s} {'flagged':>7s}")
    rng = np.random.default_rng(args.seed)
    for key in ("fx", "position"):
        for noise, (sd_lo, sd_hi) in NOISE_PX.items():
            sd_pp = sd_lo * (sd_hi / sd_lo) ** s_steps
            out = {r: [] for r in rules}
            for path in paths:
                fx = keyed(s_steps, "fx")
                truth_between = {"cx": path[args.steps:, 0], "cy": path[args.steps:, 1]}
                for _ in range(args.draws):
                    values = {"fx": fx * (1.0 + FX_REL_SD * rng.standard_normal(args.steps)),
                              "cx": path[:args.steps, 0] + sd_pp * rng.standard_normal(args.steps),
                              "cy": path[:args.steps, 1] + sd_pp * rng.standard_normal(args.steps)}
                    sd = {"fx": FX_REL_SD * fx, "cx": sd_pp, "cy": sd_pp}
                    for r in rules:
                        out[r].append(one_fit(r, keyed(s_steps, key), values, sd,
                                              keyed(s_between, key), truth_between))
            for r in rules:
                rows = out[r]
                err = np.concatenate([o["err"] for o in rows])
                z = np.concatenate([o["z"] for o in rows])
                held = np.concatenate([o["held"] for o in rows])
                high = sum(o["high"] for o in rows) / (2 * len(rows))
                flagged = sum(o["flagged"] for o in rows) / (2 * len(rows))
                print(f"{key:9s} {noise:10s} {r:10s} {np.sqrt(np.mean(err**2)):10.2f} "
                      f"{np.sqrt(np.mean(z**2)):6.2f} {np.sqrt(np.mean(held**2)):11.2f} "
                      f"{100 * high:6.0f}% {100 * flagged:6.0f}%")
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
