"""Write the mrcal reference models of tests/test_calibrate_export.py (run once, with a Python
that has mrcal, e.g. Debian's python3-mrcal: ``/usr/bin/python3 make_mrcal_models.py``).

For a 5-term and an 8-term OpenCV lens it writes ``opencv5.cameramodel`` and
``opencv8.cameramodel`` with ``mrcal.cameramodel.write``, and ``projections.json``: seeded
camera-frame points and mrcal's projections of them (px), so that the tests can compare OpenCV's
projection with the distortion vector in OpenCV order against mrcal's without mrcal installed.
"""

import json
from pathlib import Path

import mrcal
import numpy as np

HERE = Path(__file__).resolve().parent
IMAGER = [1920, 1080]
LENSES = {
    "opencv5": ("LENSMODEL_OPENCV5",
                [2400.5, 2401.25, 955.75, 541.5, -0.21, 0.13, 0.0012, -0.0008, -0.04]),
    "opencv8": ("LENSMODEL_OPENCV8",
                [1210.0, 1209.5, 962.25, 538.0, 0.35, -0.12, 0.0021, -0.0015, 0.02,
                 0.61, -0.09, 0.05]),
}


def main() -> None:
    rng = np.random.default_rng(20240611)
    # points in front of the camera, within about 20 degrees of the axis
    xy = rng.uniform(-0.35, 0.35, (12, 2))
    z = rng.uniform(1.0, 3.0, (12, 1))
    points = np.hstack([xy * z, z])
    doc = {"mrcal_lensmodels": {}, "points_cam": points.tolist(), "projections_px": {}}
    for name, (lensmodel, intrinsics) in LENSES.items():
        model = mrcal.cameramodel(intrinsics=(lensmodel, np.array(intrinsics)),
                                  imagersize=np.array(IMAGER),
                                  extrinsics_rt_fromref=np.zeros(6))
        model.write(str(HERE / f"{name}.cameramodel"), note="reference model, "
                    "tests/data/mrcal-models/make_mrcal_models.py")
        doc["mrcal_lensmodels"][name] = lensmodel
        doc["projections_px"][name] = mrcal.project(points, *model.intrinsics()).tolist()
    (HERE / "projections.json").write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
