"""The print's trapezoid or a tilted sensor? Each step alone, on each board, with and without a
sensor tilt.

``python benchmarks/bench_print_or_tilt.py FOLDER [--out DIR] [--pattern chessboard:22x15:25]``

``FOLDER`` is a zoom set (step subfolders), e.g. the real PTZ set's ``calibration_images``
(``bench_real_ptz.py``; nothing of it is kept here); detections are made or reused from
``OUT/detections``. The zoom-wide adjustment runs twice, with the board ``points`` (each
session's heights, the print exact) and ``print`` (besides, the print's in-plane shape where
its test keeps it). Then every step is fitted alone by ``cv2.calibrateCamera`` (k1, k2, p1,
p2; k3 held at 0; started from the ``points`` adjustment's camera, 200 iterations) on three
boards: the nominal flat one, the ``points`` adjustment's and the ``print`` one's (each
step's session), each without and with OpenCV's tilted-sensor model
(``CALIB_TILTED_MODEL``: the sensor's tilts ``tau_x``, ``tau_y`` free, k4-k6 held).

What it tells: a sensor tilt makes a keystone in the image, the nearest error of the camera to
a print's trapezoid. If the trapezoid the ``print`` board carries were the camera's, the tilted
model on the ``points`` board would take up what the ``print`` board does (its RMS as low, its
principal point as plausible, and one tilt for every step, since a sensor's tilt does not
change with the zoom). Printed per step: RMS, fx, cx, cy, and the fitted tilts in degrees.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.stepfolders import capture_date  # noqa: E402
from zoomcalib.calibrate.zoomwide import board_options, calibrate_zoom_wide  # noqa: E402

CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)


def fit_alone(obs, board: np.ndarray, K0: np.ndarray, tilted: bool):
    """``cv2.calibrateCamera`` of one step's views on ``board`` (n, 3) mm from ``K0``: RMS px,
    K and the distortion vector (14 terms with ``tilted``, else 5)."""
    objects = [board[ids].astype(np.float32) for ids, _ in obs.views]
    images = [uv.astype(np.float32).reshape(-1, 1, 2) for _, uv in obs.views]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    dist0 = np.zeros(5)
    if tilted:
        flags |= (cv2.CALIB_TILTED_MODEL | cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5
                  | cv2.CALIB_FIX_K6)
        dist0 = np.zeros(14)
    rms, K, dist, _, _ = cv2.calibrateCamera(objects, images, obs.image_size, K0.copy(), dist0,
                                             flags=flags, criteria=CRITERIA)
    return rms, K, np.ravel(dist)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench-print-or-tilt"))
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    args = ap.parse_args()
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=lambda m: None, report=False, zoom_wide=False)
    obs = dict(run.observations)
    sessions = {s: capture_date(list(o.names))[0] for s, o in obs.items()}
    sessions = None if None in sessions.values() else sessions
    adjusted = {shape: calibrate_zoom_wide(obs, sessions=sessions, workers=2,
                                           **board_options(shape))
                for shape in ("points", "print")}
    test = adjusted["print"].print_test
    print(f"{len(obs)} steps; the print's test: {test.summary()}")
    tilts = []
    for step, o in obs.items():
        start = adjusted["points"].results[step]
        K0 = np.array([[start.fx, 0.0, start.cx], [0.0, start.fy, start.cy], [0.0, 0.0, 1.0]])
        cells = []
        for board_name in ("flat", "points", "print"):
            board = (o.object_points if board_name == "flat"
                     else adjusted[board_name].results[step].object_points)
            for tilted in (False, True):
                rms, K, dist = fit_alone(o, board, K0, tilted)
                cell = (f"{board_name}{'+tilt' if tilted else ''} {rms:.3f} px, fx {K[0, 0]:.0f}"
                        f", c ({K[0, 2]:.0f}, {K[1, 2]:.0f})")
                if tilted:
                    tau = np.degrees(dist[12:14])
                    cell += f", tau ({tau[0]:+.2f}, {tau[1]:+.2f}) deg"
                    if board_name == "points":
                        tilts.append(tau)
                cells.append(cell)
        print(f"{step}: " + "; ".join(cells))
    tilts = np.array(tilts)
    print(f"sensor tilt on the points board over the steps: tau_x {tilts[:, 0].mean():+.2f} "
          f"(sd {tilts[:, 0].std(ddof=1):.2f}), tau_y {tilts[:, 1].mean():+.2f} (sd "
          f"{tilts[:, 1].std(ddof=1):.2f}) deg")


if __name__ == "__main__":
    main()
