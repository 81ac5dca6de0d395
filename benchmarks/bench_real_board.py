"""The board of a real set, point by point: every board point released by the bundle adjustment
on one step's views, and what shape the released points take.

    python benchmarks/bench_real_board.py OUT zoom_1x zoom_5x

``OUT`` is a ``zoomcalib calibrate`` output folder (its cached ``detections/<step>.json``);
``--pattern`` the board. Per step: the released points against the nominal board after the
best 3D affine map (in-plane and out-of-plane RMS, mm; the affine's in-plane scale ratio, a
print scaled differently along its two axes), then the out-of-plane part after smooth surfaces
of degree 2, 4, 6, 8 in the board's coordinates (the zoom-wide adjustment's board modes go to
degree 4), mm RMS.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from zoomcalib.calibrate.budget import _flags, _guess_dist, _terms, _train_board
from zoomcalib.calibrate.opencv_backend import calibrate_opencv, observations_from_detections
from zoomcalib.detect.opencv import read_detections
from zoomcalib.targets import parse_pattern


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("steps", nargs="+")
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    args = ap.parse_args()
    target = parse_pattern(args.pattern)
    for step in args.steps:
        _, dets = read_detections(args.out / "detections" / f"{step}.json")
        good = [d for d in dets if d.error is None]
        obs = observations_from_detections(good, target, good[0].image_size)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            start = calibrate_opencv(obs)
        terms = _terms(start)
        X = _train_board(obs, start.K, _guess_dist(start, terms, False),
                         _flags(terms, False), None)[2]
        N = np.asarray(obs.object_points, float)
        design = np.column_stack([N, np.ones(len(N))])
        coef = np.linalg.lstsq(design, X, rcond=None)[0]
        resid = X - design @ coef
        s = np.linalg.svd(coef[:3].T[:2, :2], compute_uv=False)
        print(f"{step}: {len(obs.views)} views; after an affine map: in-plane "
              f"{np.sqrt(np.mean(np.sum(resid[:, :2] ** 2, axis=1))):.3f} mm, out-of-plane "
              f"{np.sqrt(np.mean(resid[:, 2] ** 2)):.3f} mm RMS; scale ratio of the axes "
              f"{s[0] / s[1]:.5f}")
        x = 2 * (N[:, 0] - N[:, 0].mean()) / np.ptp(N[:, 0])
        y = 2 * (N[:, 1] - N[:, 1].mean()) / np.ptp(N[:, 1])
        cells = []
        for degree in (2, 4, 6, 8):
            basis = np.column_stack([x**i * y**j for i in range(degree + 1)
                                     for j in range(degree + 1 - i)])
            left = resid[:, 2] - basis @ np.linalg.lstsq(basis, resid[:, 2], rcond=None)[0]
            cells.append(f"degree {degree}: {np.sqrt(np.mean(left**2)):.3f}")
        print("  out-of-plane after a surface of " + ", ".join(cells) + " mm RMS")


if __name__ == "__main__":
    main()
