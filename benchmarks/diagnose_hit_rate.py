"""Hit rate of ``diagnose`` on synthetic per-zoom tables with one hidden cause.

Every draw builds a table with :func:`zoomcalib.diagnose.synthetic.synthetic_zoom_table` (exact
ray tracer, play, measurement noise growing with focal length, 2 passes of in and out sweeps over
9 settings), hides one cause of random direction and of a magnitude drawn uniformly in
``--magnitude`` (RMS effect / RMS noise), diagnoses it and records what was named, the recovered
parameters' z-scores ``(estimate - truth) / sd``, and the extended model's cv_rms over the noise.
Null draws (no hidden cause) give the false-alarm rate. A ``focus`` and a ``temperature`` column are
each added to half the draws, so those causes are also tested where they are absent.

Usage::

    python benchmarks/diagnose_hit_rate.py --draws 200 --null 500 --workers 2
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import HIDDEN_CAUSES, synthetic_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription

sys.path.insert(0, str(Path(__file__).resolve().parent))
from draws import run_draws  # noqa: E402  (the benchmarks folder's shared helper)

_RESPONSE: LensResponse | None = None


def one_draw(args: tuple[str | None, int, tuple[float, float]]) -> dict:
    global _RESPONSE
    cause, seed, magnitude = args
    lens = load_prescription("laikin-10x")
    if _RESPONSE is None:
        _RESPONSE = LensResponse.of(lens)
    rng = np.random.default_rng(seed)
    rows, truth = synthetic_zoom_table(lens, cause, rng, magnitude=magnitude,
                                       with_focus=bool(rng.integers(2)),
                                       with_temperature=bool(rng.integers(2)))
    d = diagnose_table(ZoomTable.from_rows(rows, f"draw {seed}"), _RESPONSE)
    out = {"cause": truth["cause"], "named": d.cause, "magnitude": truth.get("magnitude", 0.0),
           "noise": truth["noise_rms_px"], "cv_base": d.baseline.cv_rms_px, "z": []}
    if d.extended is not None:
        out["cv_ext"] = d.extended.fit.cv_rms_px
        own = [s for s in d.causes if s.cause == truth["cause"]]
        if d.cause == truth["cause"] and own:
            # the hidden cause's own parameters (another selected cause may share their names)
            params, sds = own[0].params, own[0].params_sd
            out["z"] = [(params[k] - v) / sds[k] for k, v in truth["params"].items()
                        if k in params]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=100, help="draws per cause")
    ap.add_argument("--null", type=int, default=300, help="draws without a hidden cause")
    ap.add_argument("--magnitude", type=float, nargs=2, default=(1.0, 8.0))
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--causes", nargs="*", default=list(HIDDEN_CAUSES), choices=HIDDEN_CAUSES)
    ap.add_argument("--json", default="", help="also write the per-draw records here")
    a = ap.parse_args()
    jobs = [(None, a.seed * 100000 + k, tuple(a.magnitude)) for k in range(a.null)]
    for c, cause in enumerate(HIDDEN_CAUSES):
        if cause not in a.causes:
            continue
        jobs += [(cause, a.seed * 100000 + 10000 * (c + 1) + k, tuple(a.magnitude))
                 for k in range(a.draws)]
    recs, header = run_draws(one_draw, jobs, a.workers, a.json, chunksize=8)
    print(header)
    null = [r for r in recs if r["cause"] == "none"]
    fa = Counter(r["named"] for r in null)
    null = null or [{"named": "none"}]
    print(f"null: 'none' in {fa['none']}/{len(null)} = {fa['none'] / len(null):.1%}; "
          f"false alarms: {dict((k, v) for k, v in fa.items() if k != 'none')}")
    lo_m, hi_m = a.magnitude
    edges = np.geomspace(lo_m, hi_m, 4)
    bins = list(zip(edges[:-1], edges[1:] + 1e-9, strict=True))
    head = " | ".join(f"hit {lo:.1f}-{hi:.1f}x" for lo, hi in bins)
    print(f"| cause | draws | {head} | hit all | |z|<2 | z rms | cv/noise | named instead |")
    print("|---|---|" + "---|" * (len(bins) + 5))
    for cause in a.causes:
        rs = [r for r in recs if r["cause"] == cause]
        cells = []
        for lo, hi in bins:
            b = [r for r in rs if lo <= r["magnitude"] < hi]
            hits = sum(r["named"] == cause for r in b)
            cells.append(f"{hits}/{len(b)}")
        hits = [r for r in rs if r["named"] == cause]
        z = np.array([v for r in hits for v in r["z"]])
        cvr = np.array([r["cv_ext"] / r["noise"] for r in hits])
        wrong = defaultdict(int)
        for r in rs:
            if r["named"] != cause:
                wrong[r["named"]] += 1
        print(f"| {cause} | {len(rs)} | " + " | ".join(cells)
              + f" | {len(hits) / len(rs):.0%} | {np.mean(np.abs(z) < 2):.0%} | "
              f"{np.sqrt(np.mean(z ** 2)):.2f} | {np.median(cvr):.2f} | "
              + (", ".join(f"{k} {v}" for k, v in sorted(wrong.items())) or "-") + " |")


if __name__ == "__main__":
    main()
