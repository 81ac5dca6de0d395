"""Is the zoom model's 1-sigma calibrated? ``python benchmarks/zoom_model_coverage.py [--sets N]``.

Draws N synthetic zoom calibrations (15 steps of a 10x zoom with a wandering principal point and
a linear k1, known per-step noise), fits :class:`zoomcalib.zoom.ZoomModel` to each, and compares
its predictions half-way between the steps with the hidden truth in units of the model's own
1-sigma. A calibrated 1-sigma gives standardised errors with an RMS of 1. Prints, per model
kind, the RMS over all sets and the 5-95 % range of the per-set RMS.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zoomcalib.zoom import ZoomModel

STEPS = 15
NOISE = {"fx": 3.0, "fy": 3.0, "cx": 0.8, "cy": 0.8, "k1": 0.004}  # 1-sigma per step


def hidden_truth(z: np.ndarray, f0: float, growth: float) -> dict[str, np.ndarray]:
    """Intrinsics of the synthetic zoom lens at lens states ``z`` in [0, 1] (px, k1 unitless)."""
    return {"fx": f0 * np.exp(growth * z), "fy": 1.002 * f0 * np.exp(growth * z),
            "cx": 640.0 + 4.0 * np.sin(2.5 * z) - 3.0 * z, "cy": 480.0 - 2.0 * z + 1.5 * z**2,
            "k1": -0.2 + 0.15 * z}


def standardised_errors(rng: np.random.Generator, kind: str) -> np.ndarray:
    """Errors of one fitted model half-way between the steps, over its own 1-sigma."""
    f0, growth = rng.uniform(800.0, 1500.0), np.log(10.0) * rng.uniform(0.9, 1.1)
    z = np.linspace(0.0, 1.0, STEPS)
    truth = hidden_truth(z, f0, growth)
    values = {k: v + rng.normal(0.0, NOISE[k], STEPS) for k, v in truth.items()}
    model = ZoomModel.fit(z, values, {k: np.full(STEPS, s) for k, s in NOISE.items()}, kind=kind)
    mid = (np.arange(STEPS - 1) + 0.5) / (STEPS - 1)
    pred, exact = model.predict(mid), hidden_truth(mid, f0, growth)
    return np.concatenate([(pred[k] - exact[k]) / pred[f"sd_{k}"] for k in NOISE])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=300, help="synthetic data sets per kind")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"{args.sets} synthetic zoom calibrations of {STEPS} steps per kind, seed {args.seed}")
    print("kind    RMS of standardised errors   per-set RMS 5-95 %   time [s]")
    for kind in ("poly", "spline"):
        rng = np.random.default_rng(args.seed)
        start = time.perf_counter()
        per_set = [standardised_errors(rng, kind) for _ in range(args.sets)]
        rms = np.sqrt([np.mean(e**2) for e in per_set])
        lo, hi = np.percentile(rms, [5, 95])
        overall = np.sqrt(np.mean(np.concatenate(per_set) ** 2))
        seconds = time.perf_counter() - start
        print(f"{kind:7s} {overall:26.3f}   {lo:8.2f}-{hi:.2f}   {seconds:12.1f}")


if __name__ == "__main__":
    main()
