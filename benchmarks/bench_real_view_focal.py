"""Does each view of a real zoom step have a focal length of its own?

``python benchmarks/bench_real_view_focal.py FOLDER --out DIR [--pattern chessboard:22x15:25]
[--null-draws 1] [--seed 0]``

``FOLDER`` and ``--out`` as for ``bench_real_ptz.py`` (the real PTZ set of
``e-cagan/camera-calibration``, read where it lies; detections cached in ``DIR/detections``).

The default ``calibrate`` run gives every step's zoom-wide camera, its board (each capture
session's modes and point heights) and each view's pose. Each view is then fitted alone by
OpenCV (``calibrateCameraExtended``) with the principal point, the aspect ratio, the
distortion and the board held at the adjustment's: its own focal length ``f_v`` and pose. Its
sigma is OpenCV's, rescaled from the view's own residual to the step's corner noise (the
adjustment's ``noise_sigma_px``), so a view whose corners fit worse is not given a wider one.
Per step it prints the spread of ``f_v`` (sd, percent of fx), the median sigma, the mean of
``z_v^2 = ((f_v - f) / sd_v)^2`` (1 for views that share one focal length), the correlation
of ``f_v`` with the board's tilt, and a runs test over the capture order (frames sorted by
name, which holds the capture time): ``z_runs`` below -2 says that consecutive frames share
the sign of their departure, a focal length that changes in steps between groups of frames
(a refocus, a zoom that does not return) rather than frame by frame.

``--null-draws N`` repeats the measurement on N synthetic sweeps of ``bench_real_mc.py``'s
``imitated`` errors (the same views, poses, cameras, boards and corner noise, one focal length
per step), each calibrated zoom-wide first: the spread that the method itself gives where no
view has a focal length of its own.
The data have no licence: nothing of them is kept in this repository.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from bench_real_mc import draw_sweep  # noqa: E402
from bench_real_ptz import real_set_parser  # noqa: E402

from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.zoomwide import calibrate_zoom_wide  # noqa: E402

HELD = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
        | cv2.CALIB_FIX_TANGENT_DIST)


def view_focal_lengths(obs, r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per view of ``obs``: its own focal length (px) and sigma with everything else of the
    zoom-wide step result ``r`` held (module docstring), and the board's tilt (degrees)."""
    noise = float(r.info.get("noise_sigma_px", r.rms_px / np.sqrt(2)))
    board = r.object_points.astype(np.float32)
    f, sd, tilt = [], [], []
    for ids, pts in obs.views:
        out = cv2.calibrateCameraExtended(
            [board[ids]], [pts.astype(np.float32).reshape(-1, 1, 2)], tuple(obs.image_size),
            r.K.copy(), np.asarray(r.dist[:5], float).copy(), flags=HELD)
        rms, K, _, rvecs, _, sd_intrinsics = out[:6]
        own = rms * np.sqrt(2 * len(ids) / max(2 * len(ids) - 7, 1))  # per coordinate
        f.append(K[0, 0])
        sd.append(float(np.max(sd_intrinsics[:2])) * noise / max(own, 1e-12))
        tilt.append(np.degrees(np.arccos(abs(cv2.Rodrigues(rvecs[0])[0][2, 2]))))
    return np.array(f), np.array(sd), np.array(tilt)


def runs_z(signs: np.ndarray) -> float:
    """Wald-Wolfowitz runs test of a sequence of signs: (runs - expected) / sd."""
    n_plus, n_minus = int(np.sum(signs > 0)), int(np.sum(signs <= 0))
    n = n_plus + n_minus
    if n_plus == 0 or n_minus == 0:
        return float("nan")
    runs = 1 + int(np.sum((signs[1:] > 0) != (signs[:-1] > 0)))
    expected = 1 + 2 * n_plus * n_minus / n
    var = 2 * n_plus * n_minus * (2 * n_plus * n_minus - n) / (n * n * (n - 1))
    return float((runs - expected) / np.sqrt(var))


def report(label: str, observations, zw) -> None:
    print(f"{label}:")
    print(f"{'step':>9} {'fx':>8} {'sd f_v %':>8} {'own sd %':>8} {'mean z^2':>8} "
          f"{'r(tilt)':>7} {'z_runs':>6}")
    for step, r in zw.results.items():
        obs = observations[step]
        f, sd, tilt = view_focal_lengths(obs, r)
        order = np.argsort(obs.names) if len(obs.names) == len(f) else np.arange(len(f))
        z = (f - r.fx) / sd
        print(f"{step:>9} {r.fx:8.1f} {100 * f.std() / r.fx:8.2f} "
              f"{100 * np.median(sd) / r.fx:8.3f} {np.mean(z**2):8.1f} "
              f"{np.corrcoef(f, tilt)[0, 1]:7.2f} {runs_z(np.sign(z[order])):6.2f}")


def main() -> None:
    ap = real_set_parser(__doc__)
    ap.add_argument("--null-draws", type=int, default=1)
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=lambda m: None, report=False)
    zw = run.zoom_wide
    report("real views", run.observations, zw)
    sessions = {s: r.info["board_session"] for s, r in zw.results.items()}
    rng = np.random.default_rng(args.seed)
    for d in range(args.null_draws):
        sweep, _ = draw_sweep(run, zw, 0.3, rng)
        report(f"null draw {d} (imitated errors, one focal length per step)", sweep,
               calibrate_zoom_wide(sweep, sessions=sessions, workers=2))


if __name__ == "__main__":
    main()
