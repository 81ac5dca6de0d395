"""Where one zoom-wide adjustment's time goes, by stage, against another checkout in the same run.

``python benchmarks/bench_zoom_wide_stages.py [--seeds 3] [--steps 7] [--views 10]
[--against PATH]``

Each sweep comes from ``sweep_observations`` of ``tests/test_zoomwide.py`` (seeds ``1 ..
seeds``; fx 2300-23000 px, views tilted 35 degrees at the short end to about 3 at the long end,
a board waving by 0.3 mm, Gaussian noise 0.02 px). One process, one BLAS and OpenCV thread,
``workers=1``: the CPU time (``time.process_time``) of ``calibrate_zoom_wide(obs)`` with its
defaults, and within it of each stage of :data:`STAGES` (the steps' own fits: their robust starts,
held-out term choices (both rounds), OpenCV starts; the basin checks; the Levenberg-Marquardt
engine). Then the adjustment again with the steps' own fits made beforehand
(``zoom_wide_starts``, given as ``starts=``): what an adjustment of the same observations with
other options costs.

With ``--against PATH`` (another checkout, e.g. ``git worktree add /tmp/before HEAD~1``) the same
runs are made with that checkout's library in a second process, one after the other: printed are
both times, their ratio, and the largest difference of any step's fx, cx, cy between the two
in that step's sigmas.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Stages timed: (module, function) of the library.
STAGES = (("zoomcalib.calibrate.stepfits", "_robust_start"),
          ("zoomcalib.calibrate.stepfits", "select_distortion"),
          ("zoomcalib.calibrate.stepfits", "_opencv_start"),
          ("zoomcalib.calibrate.zoomwide", "best_basin"),
          ("zoomcalib.calibrate.zoomwide", "_levenberg_marquardt"))


def _measure(root: Path, seeds: int, steps: int, views: int) -> dict:
    """The stages' CPU times per seed and the steps' fx, cx, cy and sigmas, with the library
    of ``root`` (imported in this process)."""
    sys.path[:0] = [str(root), str(root / "tests")]
    import importlib

    import cv2
    import numpy as np
    from threadpoolctl import threadpool_limits

    sweep_observations = importlib.import_module("test_zoomwide").sweep_observations
    zoomwide = importlib.import_module("zoomcalib.calibrate.zoomwide")
    cv2.setNumThreads(1)
    threadpool_limits(1)
    warnings.simplefilter("ignore")
    spent: dict[str, float] = {}

    def timed(name, function):
        @functools.wraps(function)
        def wrapper(*args, **kwargs):
            start = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                spent[name] = spent.get(name, 0.0) + time.process_time() - start
        return wrapper

    for module, name in STAGES:
        mod = importlib.import_module(module)
        setattr(mod, name, timed(name, getattr(mod, name)))
    out = {"library": str(Path(zoomwide.__file__).parents[2]), "seeds": []}
    for seed in range(1, seeds + 1):
        obs, _, _ = sweep_observations(np.random.default_rng(seed), steps=steps, views=views)
        spent.clear()
        start = time.process_time()
        result = zoomwide.calibrate_zoom_wide(obs)
        row = {"total": time.process_time() - start, "stages": dict(spent),
               "values": {s: {q: [getattr(r, q), r.sd[q]] for q in ("fx", "cx", "cy")}
                          for s, r in result.results.items()}}
        if hasattr(zoomwide, "zoom_wide_starts"):
            starts = zoomwide.zoom_wide_starts(obs)
            start = time.process_time()
            zoomwide.calibrate_zoom_wide(obs, starts=starts)
            row["with_starts"] = time.process_time() - start
        out["seeds"].append(row)
    return out


def _report(run: dict) -> None:
    print(f"library {run['library']}")
    names = [name for _, name in STAGES]
    print("  seed  total s  " + "  ".join(f"{n:>20s}" for n in names) + "  given starts s")
    for seed, row in enumerate(run["seeds"], start=1):
        stages = "  ".join(f"{row['stages'].get(n, 0.0):20.2f}" for n in names)
        given = f"{row['with_starts']:14.2f}" if "with_starts" in row else "             -"
        print(f"  {seed:4d}  {row['total']:7.2f}  {stages}  {given}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=7)
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--against", type=Path, help="another checkout, run second")
    parser.add_argument("--one", type=Path, help=argparse.SUPPRESS)  # a worker's checkout
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(_measure(args.one, args.seeds, args.steps, args.views)))
        return
    runs = []
    for root in [ROOT] + ([args.against.resolve()] if args.against else []):
        command = [sys.executable, __file__, "--one", str(root), "--seeds", str(args.seeds),
                   "--steps", str(args.steps), "--views", str(args.views)]
        env = os.environ | {"PYTHONPATH": str(root)}
        done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        _report(runs[-1])
    if len(runs) == 2:
        this, other = runs
        ratio = (sum(r["total"] for r in this["seeds"]) / sum(r["total"] for r in other["seeds"]))
        worst = max(abs(a[0] - b[0]) / b[1]
                    for ra, rb in zip(this["seeds"], other["seeds"], strict=True)
                    for s in ra["values"] for q in ("fx", "cx", "cy")
                    for a, b in [(ra["values"][s][q], rb["values"][s][q])])
        print(f"total CPU, this checkout over the other: {ratio:.3f}; largest difference of a "
              f"step's fx, cx, cy: {worst:.2e} of its sigma")


if __name__ == "__main__":
    main()
