"""Rendered sweeps that imitate a real PTZ set, calibrated as a user would, against their truth.

``python benchmarks/bench_imitation.py [--seeds 3] [--out DIR] [--views 30] [--steps 10]
[--jitter 0.01] [--no-effects]``

Each seed renders (:func:`zoomcalib.render.sweep.render_zoom_sweep`) a sweep shaped like the
public PTZ set of ``docs/real-camera.md``, from none of its data: 10 steps, fx 1150-11250 px
log-spaced on 1280 x 720 frames, 30 views a step of a 22 x 15-corner chessboard of 25 mm
squares, tilts from 40 degrees at the short end to 3 at the long end; a paper board waving
by 1 mm and re-taped after the second step (two capture sessions, a ``session`` column); the
camera's sharpening (an unsharp mask of 0.8 at 1.2 px) and JPEG compression at quality 85;
a zoom that does not return between views (each view's focal length off by ``--jitter``,
1 % sd); the Zoom-Nikkor 80-400's measured distortion from lensfun (barrel at the short end,
pincushion at the long end) centred 30, -20 px from the principal point (decentring). The
principal point follows the default bowed path. ``--no-effects`` renders the same sweep with
a flat board, no sharpening, PNG and no jitter: the control.

Then ``calibrate_folder`` as ``zoomcalib calibrate FOLDER --pattern chessboard:22x15:25``
(the default zoom-wide adjustment, 2 processes), timed, and per step the zoom-wide row's
``z = (estimate - truth) / sd`` for fx, cx, cy against the rendered camera (the mean focal
length of the step's views is the truth of fx), with the step's status. Honest sigmas give a
pooled RMS z near 1 and few ``|z|`` beyond 3.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.render.sweep import CaptureEffects, render_zoom_sweep  # noqa: E402
from zoomcalib.study.lensfun import sweep_distortion  # noqa: E402

COMPARED = ("fx", "cx", "cy")
PATTERN = "chessboard:22x15:25"
LENS = "Nikkor 80-400"


def render(folder: Path, seed: int, steps: int, views: int, jitter: float,
           effects: bool) -> dict:
    """One imitation sweep (module docstring) into ``folder``; its truth."""
    fx_range, size = (1150.0, 11250.0), (1280, 720)
    dist = sweep_distortion(LENS, np.geomspace(*fx_range, steps), size)
    capture = (CaptureEffects((0.8, 1.2), jitter, 2) if effects else CaptureEffects())
    return render_zoom_sweep(folder, fx_range, steps, views, size, PATTERN,
                             1.0 if effects else None, jpeg_quality=85 if effects else None,
                             seed=seed, effects=capture, dist_centre_px=(30.0, -20.0), **dist)


def compare(truth: dict, run) -> list[tuple[str, dict, str]]:
    """Per rendered step: the z of fx, cx, cy of its table row and its status."""
    rows = []
    for st in truth["steps"]:
        name = st["step"]
        backend = run.table_backend.get(name)
        if backend is None:
            rows.append((name, {}, "lost"))
            continue
        res = run.results[name][backend]
        scale = np.mean([v["focal_scale"] for v in st["views"]])
        true = {"fx": st["camera"]["fx"] * scale, "cx": st["camera"]["cx"],
                "cy": st["camera"]["cy"]}
        z = {q: (getattr(res, q) - true[q]) / res.sd[q] for q in COMPARED}
        rows.append((name, z, run.status[name].status))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench-imitation"))
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--jitter", type=float, default=0.01)
    ap.add_argument("--no-effects", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    allz, statuses = [], {}
    for seed in range(args.seeds):
        folder = args.out / f"seed{seed}"
        t = time.perf_counter()
        truth = render(folder / "images", seed, args.steps, args.views, args.jitter,
                       not args.no_effects)
        rendered = time.perf_counter() - t
        t = time.perf_counter()
        run = calibrate_folder(folder / "images", PATTERN, folder / "calibration", ("opencv",),
                               workers=2, log=lambda m: None, report=False)
        took = time.perf_counter() - t
        print(f"seed {seed}: rendered in {rendered:.0f} s; detection and calibration "
              f"{took:.0f} s")
        for name, z, status in compare(truth, run):
            statuses[status] = statuses.get(status, 0) + 1
            if z:
                allz.append([z[q] for q in COMPARED])
            cells = " ".join(f"z_{q} {z[q]:+6.2f}" for q in COMPARED) if z else "lost"
            print(f"  {name}: {cells}  {status}")
        (folder / "z.json").write_text(json.dumps(compare(truth, run), default=float))
    z = np.array(allz)
    print(f"{args.seeds} seeds, effects {'off' if args.no_effects else 'on'}: RMS z "
          + ", ".join(f"{q} {np.sqrt(np.mean(z[:, i] ** 2)):.2f}" for i, q in enumerate(COMPARED))
          + f"; pooled {np.sqrt(np.mean(z**2)):.2f}; beyond 3: {int((np.abs(z) > 3).sum())} "
          f"of {z.size}; statuses {statuses}")


if __name__ == "__main__":
    main()
