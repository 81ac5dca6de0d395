"""``diagnose`` on rows whose measurement errors a capture session shares.

The rows of a zoom-wide adjustment's solve without its prior share the adjustment's aspect
ratio and each session's board, so one session's principal points err together. Each draw
builds a table with :func:`zoomcalib.diagnose.synthetic.independent_zoom_table` (exact ray
tracer, ``laikin-10x``): ``--sessions`` capture sessions over the capture order, each with a
common share (uniform in ``--share``) of its rows' measurement noise; the measurement noise
dominant (``--sd-wide`` px at the wide end, growing as ``f / f_min``); the play 0.3-1 times the
tolerance file's; the sigmas misreported by 0.7-1.4. Half the draws are nulls, half hide one
cause (each in turn, 6-16 times the noise). Every table is diagnosed twice: as independent rows,
and with the correlation the session structure gives (its share misreported by 0.8-1.2, as a
calibration's own estimate would be). Printed: what each names, and for the named hidden cause
the Mahalanobis distance of its fitted parameters from the truth (chi2 with 2 degrees of
freedom, mean 2, when the sigmas are right).

Usage::

    python benchmarks/diagnose_correlated.py --draws 60 --workers 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import HIDDEN_CAUSES, independent_zoom_table, session_correlation
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription

sys.path.insert(0, str(Path(__file__).resolve().parent))
from draws import run_draws  # noqa: E402  (the benchmarks folder's shared helper)

LENS = "laikin-10x"
_RESPONSE = {}


def _mahalanobis2(diag, truth_params: dict) -> float | None:
    fit, k0 = diag.extended.fit, diag.extended.n_baseline
    names = fit.names[k0:]
    if set(names) != set(truth_params):
        return None
    d = fit.params[k0:] - np.array([truth_params[n] for n in names])
    return float(d @ np.linalg.solve(fit.cov[k0:, k0:], d))


def one_draw(job: tuple) -> dict:
    seed, cause, sessions, share, sd_wide = job
    lens = load_prescription(LENS)
    response = _RESPONSE.setdefault(LENS, LensResponse.of(lens))
    rng = np.random.default_rng(seed)
    rows, truth = independent_zoom_table(
        lens, rng, causes=[(cause, (6.0, 16.0))] if cause else [], play_scale=(0.3, 1.0),
        sd_factor=(0.7, 1.4), sd_wide_px=sd_wide, sessions=sessions, session_share=share,
        with_focus=bool(rng.integers(2)), with_temperature=bool(rng.integers(2)))
    table = ZoomTable.from_rows(rows, f"draw {seed}")
    record = {"seed": seed, "hidden": cause, "share": truth["sd"]["session_share"]}
    labels = np.unique([r["session"] for r in rows], return_inverse=True)[1]
    reported = min(truth["sd"]["session_share"] * rng.uniform(0.8, 1.2), 0.95)
    for how in ("independent", "correlated"):
        if how == "correlated":
            table.pp_correlation = session_correlation(labels, reported)
        diag = diagnose_table(table, response)
        record[how] = {"cause": diag.cause, "named": [s.cause for s in diag.causes],
                       "d2": (_mahalanobis2(diag, truth["causes"][0]["params"])
                              if cause and diag.extended is not None else None)}
    return record


def summary(recs: list[dict], how: str) -> list[str]:
    nulls = [r[how] for r in recs if r["hidden"] is None]
    hidden = [(r["hidden"], r[how]) for r in recs if r["hidden"] is not None]
    clean = sum(not r["named"] and r["cause"] != "unexplained" for r in nulls)
    alone = sum(r["named"] == [c] for c, r in hidden)
    extra = sum(c in r["named"] and len(r["named"]) > 1 for c, r in hidden)
    d2 = [r["d2"] for c, r in hidden if r["named"] == [c] and r["d2"] is not None]
    return [f"{how}: nulls with nothing named and no structure {clean}/{len(nulls)}; "
            f"hidden cause named alone {alone}/{len(hidden)}, with another beside it "
            f"{extra}/{len(hidden)}; d2 of the named cause's parameters: mean "
            f"{np.mean(d2) if d2 else float('nan'):.2f}, max "
            f"{max(d2) if d2 else float('nan'):.2f} over {len(d2)}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=60, help="tables; half nulls")
    ap.add_argument("--sessions", type=int, default=3)
    ap.add_argument("--share", type=float, nargs=2, default=(0.5, 0.9))
    ap.add_argument("--sd-wide", type=float, default=1.0, help="px at the wide end")
    ap.add_argument("--seed", type=int, default=9000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default="", help="write the per-draw records here")
    a = ap.parse_args()
    jobs = [(a.seed + i, HIDDEN_CAUSES[(i // 2) % len(HIDDEN_CAUSES)] if i % 2 else None,
             a.sessions, tuple(a.share), a.sd_wide) for i in range(a.draws)]
    recs, header = run_draws(one_draw, jobs, a.workers, a.json, chunksize=2)
    print(header)
    for how in ("independent", "correlated"):
        print("\n".join(summary(recs, how)))


if __name__ == "__main__":
    main()
