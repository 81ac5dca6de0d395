"""Hit rate of ``diagnose`` on the default (zoom-wide) calibration's table against the per-step
table, on rendered sweeps with a hidden backlash.

``python benchmarks/diagnose_zoom_wide_hits.py [--seeds 8] [--backlash-um 40] [--workers 2]
[--out DIR]``

Each seed renders the backlash set of ``diagnose_rendered.py`` (5 settings of ``laikin-10x``
swept in then out, 10 views each at 640 x 480, elliptical PSF) with the compensator's backlash
``--backlash-um`` in a direction drawn from the seed, calibrates it per step with OpenCV and
with the default zoom-wide adjustment, and diagnoses both tables (the zoom-wide one through
the rows of its solve without the smoothness prior, ``zoom_calibration_unsmoothed.csv``).
Printed per seed: the cause each names and the half-backlash vector with its sigmas against
the truth; then how often each named ``backlash``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.camera import Sensor  # noqa: E402
from zoomcalib.diagnose.run import diagnose_input  # noqa: E402
from zoomcalib.optics.mechanics import GroupTolerance, Tolerances  # noqa: E402
from zoomcalib.optics.prescription import load_prescription  # noqa: E402
from zoomcalib.render.dataset import render_dataset  # noqa: E402
from zoomcalib.render.image import Optics  # noqa: E402

BOARD = "chessboard:9x6:25"


def one_seed(args: tuple[int, float, str]) -> dict:
    seed, backlash_um, root = args
    out = Path(root) / f"seed{seed}"
    rng = np.random.default_rng(seed)
    phase = float(rng.uniform(0.0, 360.0))
    lens = load_prescription("laikin-10x")
    tol = Tolerances({
        "variator": GroupTolerance(locked_decenter_um=15.0, locked_tilt_arcmin=1.0,
                                   locked_tilt_phase_deg=90.0, play_um=1.0),
        "compensator": GroupTolerance(locked_decenter_um=10.0, locked_decenter_phase_deg=phase,
                                      play_um=1.0, backlash_um=backlash_um)}, "bench")
    settings = list(np.linspace(0.0, 0.4, 5))
    sensor = Sensor(640, 480, 0.0129)
    render_dataset(lens, tol, out / "set", settings + settings[::-1], 10, BOARD, seed=seed,
                   sensor=sensor, direction=["in"] * 5 + ["out"] * 5,
                   optics=Optics(psf="elliptical"))
    ang = np.deg2rad(phase + 90.0)
    truth = 0.5 * backlash_um * np.array([np.cos(ang), np.sin(ang)])
    record = {"seed": seed, "truth": truth.tolist()}
    for name, zoom_wide in (("per-step", False), ("zoom-wide", True)):
        calibrate_folder(out / "set", BOARD, out / name, ("opencv",), workers=1,
                         log=lambda m: None, report=False, zoom_wide=zoom_wide)
        run = diagnose_input(out / name / "zoom_calibration.csv", out / f"diag-{name}", lens,
                             sensor.pixel_pitch_mm, tol, log=lambda m: None)
        d = run.diagnosis
        found = next((s for s in d.causes if s.cause == "backlash"), None)
        record[name] = {"cause": d.cause,
                        "params": None if found is None else list(found.params.values()),
                        "sd": None if found is None else list(found.params_sd.values())}
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--backlash-um", type=float, default=40.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    root = a.out or tempfile.mkdtemp(prefix="zw-hits-")
    jobs = [(s, a.backlash_um, root) for s in range(a.seeds)]
    with ProcessPoolExecutor(a.workers) as pool:
        records = list(pool.map(one_seed, jobs))
    hits = {"per-step": 0, "zoom-wide": 0}
    for r in records:
        line = f"seed {r['seed']}: truth ({r['truth'][0]:.1f}, {r['truth'][1]:.1f}) um"
        for name in hits:
            got = r[name]
            hits[name] += got["cause"] == "backlash"
            if got["params"] is None:
                line += f"; {name} {got['cause']}"
            else:
                z = (np.array(got["params"]) - r["truth"]) / np.array(got["sd"])
                line += (f"; {name} {got['cause']} ({got['params'][0]:.1f}, "
                         f"{got['params'][1]:.1f}) +- {got['sd'][0]:.1f}, z {z[0]:+.1f} "
                         f"{z[1]:+.1f}")
        print(line, flush=True)
    print(f"{a.seeds} seeds, backlash {a.backlash_um:g} um: named backlash per-step "
          f"{hits['per-step']}, zoom-wide {hits['zoom-wide']}; output in {root}")


if __name__ == "__main__":
    main()
