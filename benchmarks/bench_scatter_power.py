"""What the view-scatter check cannot see: one calibration set, errors shared within views.

``python benchmarks/bench_scatter_power.py [--sets 100] [--views 20] [--backend opencv|bundle]
[--fields 0 0.05 0.1 0.15 0.2 0.3 0.5 | --misprints 0 0.01 0.02 0.05] [--tested-only]
[--no-board-points] [--target-sigma MM|none|flat]``

The check of :mod:`zoomcalib.calibrate.scatter` flags a sigma only where its test finds the
views disagreeing beyond the corner noise (0.1 % significance), so that a set the noise model
describes is not flagged. A misfit too small for the test to see in one set still makes the
noise model's sigma too small by the misfit's factor; by default every checked sigma is
therefore the larger of the model's and the view-clustered one
(:data:`~zoomcalib.calibrate.scatter.SCALE_UNTESTED`).

``--sets`` seeded single-step sets (``sweep_detections``, 800 x 600, 0.1 px of corner noise,
``--views`` views) get a hidden smooth error field per view of each ``--fields`` size (px at
300 px from the view's centre, :func:`~zoomcalib.calibrate.synthetic.with_view_fields`), and
are calibrated with the backend's defaults. Printed per field size: the RMS over the sets of
the error against the truth of fx, cx, cy in the noise model's sigmas and in the reported ones
(honest sigmas: 1, within about +-10 % for 100 sets and 3 parameters), how many z lie beyond 3,
and in how many sets the whole-solution test fired.

``--misprints``: instead of view fields, boards printed with each corner off by its own
Gaussian error of the given 1-sigma (mm, in the board plane; ``sweep_detections(misprint_mm=)``),
the same in every view, which the views' scatter cannot show and the board points' can
(``--no-board-points`` leaves that check out, ``scatter.CHECK_BOARD_POINTS``). With the bundle,
``--target-sigma`` sets its shape prior (default 0.01 mm; ``none``: the target points free
but for the gauge; ``flat``: the nominal target, not refined).

``--tested-only``: a sigma takes its factor only where a test fired (``SCALE_UNTESTED`` off,
the rule before it became the default), which shows what the test alone misses.
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

from zoomcalib.calibrate import scatter  # noqa: E402
from zoomcalib.calibrate.bundle import calibrate_bundle  # noqa: E402
from zoomcalib.calibrate.opencv_backend import calibrate_opencv  # noqa: E402
from zoomcalib.calibrate.synthetic import sweep_detections, with_view_fields  # noqa: E402

COMPARED = ("fx", "cx", "cy")
BACKENDS = {"opencv": calibrate_opencv, "bundle": calibrate_bundle}


def errors(calibrate, size: float, sets: int, views: int, misprint: bool = False
           ) -> tuple[np.ndarray, np.ndarray, int]:
    """z against the truth with the noise model's and the reported sigmas, (sets, 3) each, and
    the number of sets whose whole-solution test fired (the board points' test with
    ``misprint``). ``size``: the view field (px) or the board's printing error (mm)."""
    z_model, z_reported, fired = [], [], 0
    for seed in range(sets):
        rng = np.random.default_rng(3000 + seed)
        sweep = sweep_detections(rng, steps=1, views=views, noise_px=0.1,
                                 misprint_mm=size if misprint else 0.0)
        (obs,) = sweep.observations.values()
        truth = next(iter(sweep.truth.values()))
        res = calibrate(with_view_fields(obs, rng, size) if size and not misprint else obs)
        error = np.array([getattr(res, q) - truth[q] for q in COMPARED])
        z_model.append(error / [res.info["sd_noise_model"][q] for q in COMPARED])
        z_reported.append(error / [res.sd[q] for q in COMPARED])
        check = res.info["view_scatter"]
        test = check["fit"]
        fired += (bool(set(check.get("board_point", {}).get("flagged", [])) & set(COMPARED))
                  if misprint
                  else bool(test["factor"] > test["threshold"]))
    return np.array(z_model), np.array(z_reported), fired


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=100)
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--backend", choices=list(BACKENDS), default="opencv")
    ap.add_argument("--fields", type=float, nargs="+",
                    default=[0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5])
    ap.add_argument("--tested-only", action="store_true",
                    help="a sigma takes its factor only where a test fired")
    ap.add_argument("--misprints", type=float, nargs="+",
                    help="instead of view fields: boards printed with these corner errors, mm "
                         "(1-sigma in the plane, the same in every view)")
    ap.add_argument("--no-board-points", action="store_true",
                    help="leave the board-point check out (the view check alone)")
    ap.add_argument("--target-sigma", default="0.01",
                    help="bundle: the shape prior's target_sigma_mm ('none': no prior, "
                         "'flat': the target not refined)")
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    scatter.SCALE_UNTESTED = not a.tested_only
    scatter.CHECK_BOARD_POINTS = not a.no_board_points
    misprint = a.misprints is not None
    calibrate = BACKENDS[a.backend]
    if a.backend == "bundle" and a.target_sigma != "0.01":
        options = ({"refine_target": False} if a.target_sigma == "flat" else
                   {"target_sigma_mm": None if a.target_sigma == "none"
                    else float(a.target_sigma)})

        def calibrate(obs, options=options):
            return calibrate_bundle(obs, **options)
    rule = (f", target_sigma {a.target_sigma}" if a.backend == "bundle" else "") + (
        ", factors only where a test fired (--tested-only)" if a.tested_only else "") + (
        ", views only (--no-board-points)" if a.no_board_points else "")
    print(f"# {a.backend}, {a.sets} sets of {a.views} views, 0.1 px corner noise{rule}; "
          f"RMS z of {'/'.join(COMPARED)} against the truth")
    for size in a.misprints if misprint else a.fields:
        t0 = time.time()
        z_model, z_reported, fired = errors(calibrate, size, a.sets, a.views, misprint)
        what = f"misprint {size:5.3f} mm" if misprint else f"field {size:4.2f} px"
        print(f"{what}  noise model RMS z {np.sqrt(np.mean(z_model**2)):5.2f}"
              f"  reported RMS z {np.sqrt(np.mean(z_reported**2)):5.2f} ("
              + "/".join(f"{v:.2f}" for v in np.sqrt(np.mean(z_reported**2, axis=0)))
              + f"), |z| > 3: {(np.abs(z_reported) > 3).sum()} of {z_reported.size}"
              f"  {'points flagged' if misprint else 'test fired'} in {fired} of {a.sets}"
              f"  ({time.time() - t0:.0f} s)")

if __name__ == "__main__":
    main()
