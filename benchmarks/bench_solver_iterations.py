"""Where the zoom-wide solves spend their iterations: a digital-zoom sweep of real corners whose
widest steps take the rational model.

``python benchmarks/bench_solver_iterations.py [--split 6] [--seed 1]``

The sweep is ``tests/test_digital_zoom.py``'s: figueroa's real corners (``tests/data``) cut to 7
steps, z 1.5 to 4, 24 views each, and one half of split ``--split`` of its random halves (as
``test_a_steps_sigmas_do_not_hang_on_a_corner_of_another_step``). The default adjustment runs
on it once, every Levenberg-Marquardt solve counted (the rounds of noise re-estimation, the
print test's solve, the basin and term checks).

Printed: the number of solves, how each stopped, the accepted iterations, each rational
step's fx and cy with their sigmas and its radial terms, and for the solves
that reached the iteration cap, over their last 10 iterations, the mean cost decrease an
iteration achieved and the decrease the Gauss-Newton step predicted at the end (both relative
to the cost; the stop rule asks for a predicted decrease below 1e-9). An achieved decrease
larger than the predicted one, iteration after iteration, is a curved valley: the quadratic
model sees only its tangent.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout
sys.path.insert(0, str(ROOT / "tests"))

from test_digital_zoom import _real_sweep  # noqa: E402

from zoomcalib.calibrate import zoomwide  # noqa: E402
from zoomcalib.calibrate.checks import random_halves  # noqa: E402
from zoomcalib.calibrate.solver import GAUSS_NEWTON, predicted_decrease, schur_step  # noqa: E402

SOLVES: list[dict] = []


def _counting(solve_function):
    """``solve_function`` (the engine) recording each solve's stop, iterations and costs."""
    def solve(problem, state, *args, **kwargs):
        costs = []
        linearise = problem.linearise

        def recorded(at):
            cost, blocks = linearise(at)
            costs.append(cost)
            return cost, blocks

        problem.linearise = recorded
        try:
            out = solve_function(problem, state, *args, **kwargs)
        finally:
            del problem.linearise
        predicted = predicted_decrease(out.blocks, schur_step(out.blocks, GAUSS_NEWTON))
        SOLVES.append({"stop": out.stop_reason, "iterations": out.iterations,
                       "costs": np.array(costs), "predicted": predicted / out.cost})
        return out
    return solve


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", type=int, default=6)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    sweep = _real_sweep(rng)
    halves = {s: random_halves(o, 10, rng)[args.split][0]
              for s, o in sweep.observations.items()}
    zoomwide.levenberg_marquardt = _counting(zoomwide.levenberg_marquardt)
    start = time.perf_counter()
    result = zoomwide.calibrate_zoom_wide(halves)
    elapsed = time.perf_counter() - start
    models = {s: len(r.dist) for s, r in result.results.items()}
    print(f"{len(halves)} steps, distortion terms per step {models}; {elapsed:.1f} s")
    print(f"solves {len(SOLVES)}, accepted iterations {sum(s['iterations'] for s in SOLVES)}; "
          f"stops {dict(collections.Counter(s['stop'] for s in SOLVES))}")
    capped = [s for s in SOLVES if s["stop"] == "iteration cap"]
    if capped:
        achieved = [np.mean(-np.diff(s["costs"][-11:]) / s["costs"][-11:-1]) for s in capped]
        predicted = [s["predicted"] for s in capped]
        print(f"at the cap ({len(capped)} solves), last 10 iterations: achieved decrease per "
              f"iteration median {np.median(achieved):.1e} of the cost "
              f"({np.min(achieved):.1e}-{np.max(achieved):.1e}); Gauss-Newton prediction at "
              f"the end median {np.median(predicted):.1e} ({np.min(predicted):.1e}-"
              f"{np.max(predicted):.1e})")
    final = {s: r.info.get("stop_reason") for s, r in result.results.items()}
    print(f"the adjustment's own stop per step: {final}")
    for name, r in result.results.items():
        if len(r.dist) == 8:
            k = ", ".join(f"{v:.2f}" for v in np.asarray(r.dist)[[0, 1, 4, 5, 6, 7]])
            print(f"  {name} (rational): fx {r.fx:.2f} +- {r.sd['fx']:.2f} px, cy {r.cy:.2f} +- "
                  f"{r.sd['cy']:.2f} px; k1 k2 k3 k4 k5 k6 {k}")


if __name__ == "__main__":
    main()
