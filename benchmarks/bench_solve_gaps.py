"""The compensator's closed form against a bracket-and-bisect solve of the same focus error.

``python benchmarks/bench_solve_gaps.py [--states 801]``

:func:`zoomcalib.optics.cam.solve_gaps` solves the focus error, a quadratic in the
compensator gap, in closed form. The peer here is the way it was solved before: every root
bracketed on a 4001-point grid of the gap, the bracket nearest the design cam kept, bisection
to 1e-10 mm. Per built-in lens: both times over ``--states`` zoom states from 0 to 1, their
ratio, the largest difference of the gaps (mm) and the largest focus error left.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmark this checkout

from zoomcalib.optics import cam  # noqa: E402
from zoomcalib.optics.prescription import builtin_lenses, load_prescription  # noqa: E402


def bracket_and_bisect(lens, zoom: np.ndarray, grid: int = 4001, tol_mm: float = 1e-10
                       ) -> np.ndarray:
    """The gaps by bracketing every root of the focus error on a grid of ``g3`` and bisecting
    the bracket nearest the design cam."""
    g1 = cam.variator_gap(lens, zoom)
    order = np.argsort(lens.design_gaps[:, 0])
    guess = np.interp(g1, lens.design_gaps[order, 0], lens.design_gaps[order, 2])
    trial = np.linspace(0.0, 1.0, grid)[None, :] * (lens.gap_total - g1)[:, None]
    err = cam.focus_error(lens, cam._gaps(lens, np.broadcast_to(g1[:, None], trial.shape),
                                          trial))
    change = np.sign(err[:, :-1]) * np.sign(err[:, 1:]) <= 0
    mid = 0.5 * (trial[:, :-1] + trial[:, 1:])
    cell = np.argmin(np.where(change, np.abs(mid - guess[:, None]), np.inf), axis=1)
    rows = np.arange(len(zoom))
    lo, hi, f_lo = trial[rows, cell], trial[rows, cell + 1], err[rows, cell]
    while np.max(hi - lo) > tol_mm:
        m = 0.5 * (lo + hi)
        f_m = cam.focus_error(lens, cam._gaps(lens, g1, m))
        left = np.sign(f_m) * np.sign(f_lo) <= 0
        hi, lo, f_lo = np.where(left, m, hi), np.where(left, lo, m), np.where(left, f_lo, f_m)
    return cam._gaps(lens, g1, 0.5 * (lo + hi))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=801)
    args = ap.parse_args()
    zoom = np.linspace(0.0, 1.0, args.states)
    print(f"{'lens':>14} {'closed form s':>13} {'bisection s':>11} {'ratio':>7} "
          f"{'max |diff| mm':>13} {'max focus error':>15}")
    for name in builtin_lenses():
        lens = load_prescription(name)
        t0 = time.perf_counter()
        closed = cam.solve_gaps(lens, zoom)
        t1 = time.perf_counter()
        peer = bracket_and_bisect(lens, zoom)
        t2 = time.perf_counter()
        print(f"{name:>14} {t1 - t0:13.4f} {t2 - t1:11.2f} {(t2 - t1) / (t1 - t0):7.0f} "
              f"{np.abs(closed - peer).max():13.2e} "
              f"{np.abs(cam.focus_error(lens, closed)).max():15.2e}")


if __name__ == "__main__":
    main()
