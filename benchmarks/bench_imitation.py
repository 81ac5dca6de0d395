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
``z = (estimate - truth) / sd`` for fx, cx, cy, with the step's status. Two truths: the
rendered camera (the mean focal length of the step's views for fx), and its *OpenCV
equivalent*, the camera OpenCV's model (the step's chosen terms) fits to the true image points
of the same poses projected without jitter or noise (:func:`opencv_equivalent`). A distortion
centred off the principal point is not in OpenCV's model family: at a narrow field, where the
principal point is nearly undetermined, a misfit of thousandths of a pixel moves the
equivalent's principal point by px, so renders with hundredths of a pixel of noise are graded
against the equivalent (what the estimator converges to with unlimited data), and the
distance between the two is printed. Honest sigmas give a pooled RMS z near 1 and few ``|z|``
beyond 3. ``--compare-only`` grades the outputs of an earlier run in ``--out``.
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

import cv2  # noqa: E402

from zoomcalib.calibrate.opencv_backend import calibrate_opencv  # noqa: E402
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.stepfits import _distortion_flags  # noqa: E402
from zoomcalib.camera import CameraModel, Sensor  # noqa: E402
from zoomcalib.render.image import BoardSurface, camera_mapping, project_points  # noqa: E402
from zoomcalib.render.sweep import CaptureEffects, render_zoom_sweep  # noqa: E402
from zoomcalib.study.lensfun import sweep_distortion  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402

COMPARED = ("fx", "cx", "cy")
PATTERN = "chessboard:22x15:25"
LENS = "Nikkor 80-400"


def render(folder: Path, seed: int, steps: int, views: int, jitter: float,
           effects: bool) -> dict:
    """One imitation sweep (module docstring) into ``folder``; its truth."""
    fx_range, size = (1150.0, 11250.0), (1280, 720)
    dist = sweep_distortion(LENS, np.geomspace(*fx_range, steps), size)
    capture = (CaptureEffects((0.8, 1.2), jitter, 2) if effects else CaptureEffects())
    return render_zoom_sweep(folder, fx_range=fx_range, steps=steps, views=views, size=size,
                             pattern=PATTERN, board_surface=1.0 if effects else None,
                             jpeg_quality=85 if effects else None, seed=seed, effects=capture,
                             dist_centre_px=(30.0, -20.0), **dist)


def opencv_equivalent(truth: dict, step: dict, terms: list[str]) -> dict:
    """fx, cx, cy of OpenCV's model with ``terms`` fitted to the true image points of the
    step's poses, projected through its rendered camera without jitter or noise."""
    target = parse_pattern(truth["pattern"])
    surface = BoardSurface.from_dict(truth["board_surfaces"][step["board_session"]])
    X = surface.lift(target.object_points)
    c = step["camera"]
    sensor = Sensor(**c["sensor"])
    cam = CameraModel(c["fx"], c["fy"], c["cx"], c["cy"], np.array(c["dist"]), sensor,
                      np.array(c["dist_centre_px"]))
    views = []
    for v in step["views"]:
        uv = project_points(X, camera_mapping(cam), cv2.Rodrigues(np.array(v["rvec"]))[0],
                            np.array(v["tvec"]))
        seen = np.array(v["visible"])
        views.append((np.flatnonzero(seen), uv[seen]))
    fit = calibrate_opencv(Observations(X, views, (sensor.width_px, sensor.height_px)),
                           flags=_distortion_flags(tuple(terms)), K_guess=cam.K,
                           dist_guess=np.array(c["dist"]))
    return {"fx": fit.fx, "cx": fit.cx, "cy": fit.cy}


def compare(truth: dict, doc: dict) -> list[dict]:
    """Per rendered step of ``truth.json`` and the run's ``calibration.json``: the z of fx, cx,
    cy of its table row against the camera and against its OpenCV equivalent, and its
    status."""
    rows = []
    for st in truth["steps"]:
        name = st["step"]
        backend = doc["meta"]["table_backend"].get(name)
        if backend is None:
            rows.append({"step": name, "status": "lost"})
            continue
        res = doc["steps"][name][backend]
        K, sd = np.array(res["K"]), res["sd"]
        got = {"fx": K[0, 0], "cx": K[0, 2], "cy": K[1, 2]}
        scale = np.mean([v["focal_scale"] for v in st["views"]])
        camera = {"fx": st["camera"]["fx"] * scale, "cx": st["camera"]["cx"],
                  "cy": st["camera"]["cy"]}
        equivalent = opencv_equivalent(truth, st, res["info"]["distortion_terms"])
        equivalent["fx"] *= scale
        rows.append({"step": name, "status": doc["meta"]["status"][name]["status"],
                     "z_camera": {q: (got[q] - camera[q]) / sd[q] for q in COMPARED},
                     "z": {q: (got[q] - equivalent[q]) / sd[q] for q in COMPARED},
                     "equivalent_off_px": float(np.hypot(equivalent["cx"] - camera["cx"],
                                                         equivalent["cy"] - camera["cy"]))})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("bench-imitation"))
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--jitter", type=float, default=0.01)
    ap.add_argument("--no-effects", action="store_true")
    ap.add_argument("--compare-only", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    allz, camz, statuses = [], [], {}
    for seed in range(args.seeds):
        folder = args.out / f"seed{seed}"
        if not args.compare_only:
            t = time.perf_counter()
            render(folder / "images", seed, args.steps, args.views, args.jitter,
                   not args.no_effects)
            rendered = time.perf_counter() - t
            t = time.perf_counter()
            calibrate_folder(folder / "images", PATTERN, folder / "calibration", ("opencv",),
                             workers=2, log=lambda m: None, report=False)
            print(f"seed {seed}: rendered in {rendered:.0f} s; detection and calibration "
                  f"{time.perf_counter() - t:.0f} s")
        truth = json.loads((folder / "images" / "truth.json").read_text())
        doc = json.loads((folder / "calibration" / "calibration.json").read_text())
        rows = compare(truth, doc)
        for row in rows:
            statuses[row["status"]] = statuses.get(row["status"], 0) + 1
            if "z" not in row:
                print(f"  {row['step']}: lost")
                continue
            allz.append([row["z"][q] for q in COMPARED])
            camz.append([row["z_camera"][q] for q in COMPARED])
            print(f"  {row['step']}: " + " ".join(f"z_{q} {row['z'][q]:+6.2f}" for q in COMPARED)
                  + "  (camera: " + " ".join(f"{row['z_camera'][q]:+6.2f}" for q in COMPARED)
                  + f"; equivalent {row['equivalent_off_px']:.1f} px off)  {row['status']}")
        (folder / "z.json").write_text(json.dumps(rows, default=float, indent=1))
    for label, z in (("OpenCV equivalent", np.array(allz)), ("camera", np.array(camz))):
        print(f"{args.seeds} seeds, effects {'off' if args.no_effects else 'on'}, against the "
              f"{label}: RMS z " + ", ".join(f"{q} {np.sqrt(np.mean(z[:, i] ** 2)):.2f}"
                                             for i, q in enumerate(COMPARED))
              + f"; pooled {np.sqrt(np.mean(z**2)):.2f}; beyond 3: "
              f"{int((np.abs(z) > 3).sum())} of {z.size}")
    print(f"statuses {statuses}")


if __name__ == "__main__":
    main()
