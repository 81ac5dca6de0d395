"""Edge accuracy of the analytic renderer against a fine brute-force reference.

``python benchmarks/render_accuracy.py [--samples 128] [--seeds 2]``: renders a small chessboard
view (64 x 48 px, blur 0.7 px, k1 = -0.15) with the analytic renderer and with the independent
point-sampled reference of ``tests/test_render.py`` (``samples`` x ``samples`` points per pixel,
blur on the fine grid), and prints the edge-position differences along pixel rows. The reference's
own scatter is about ``(1 / samples) / sqrt(12) / sqrt(samples)`` px per row.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_render import _brute_blurred, _edge_shifts  # noqa: E402

from zoomcalib.camera import CameraModel, Sensor  # noqa: E402
from zoomcalib.render.image import camera_mapping, render_coverage  # noqa: E402
from zoomcalib.targets import parse_pattern  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    sensor = Sensor(64, 48, 0.00645)
    camera = CameraModel(200.0, 200.0, 31.3, 23.6, np.array([-0.15, 0.03, 1e-3, -5e-4, 0.0]),
                         sensor)
    target = parse_pattern("chessboard:3x3:10")
    print(f"reference: {args.samples} x {args.samples} samples per pixel; own scatter about "
          f"{1 / args.samples / np.sqrt(12) / np.sqrt(args.samples):.1e} px per row")
    print("seed  renderer           edges  RMS px     mean px    max px")
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        R = cv2.Rodrigues(rng.uniform(-0.4, 0.4, 3))[0]
        t = np.array([-10 + rng.uniform(-3, 3), -10 + rng.uniform(-3, 3), 170.0])
        ref = _brute_blurred(target, camera, R, t, sensor, 0.7, args.samples)
        for label, kw in (("analytic", {"method": "analytic"}),
                          ("supersampled x8", {"method": "supersample", "supersample": 8})):
            img = render_coverage(target, camera_mapping(camera), R, t, sensor, 0.7, **kw)
            e = _edge_shifts(img, ref)
            print(f"{seed:4d}  {label:16s} {len(e):6d}  {np.sqrt(np.mean(e**2)):.2e}  "
                  f"{e.mean():+.2e}  {np.abs(e).max():.2e}")


if __name__ == "__main__":
    main()
