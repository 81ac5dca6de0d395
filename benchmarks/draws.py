"""Seeded Monte Carlo draws over a process pool, shared by the diagnosis benchmarks.

``run_draws(one_draw, jobs, workers)`` maps ``one_draw`` over ``jobs`` (each job carries its own
seed, so the records do not depend on the number of workers), optionally writes the per-draw
records as JSON, and returns them with a header line naming the draws, the wall time and the
machine.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor


def run_draws(one_draw: Callable, jobs: Sequence, workers: int, json_path: str = "",
              chunksize: int = 4) -> tuple[list, str]:
    """Records of ``one_draw(job)`` for every job, in job order, and the header line."""
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        recs = list(pool.map(one_draw, jobs, chunksize=chunksize))
    wall = time.perf_counter() - t0
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(recs, fh)
    header = (f"# {len(recs)} draws in {wall:.0f} s on {workers} workers, "
              f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    return recs, header
