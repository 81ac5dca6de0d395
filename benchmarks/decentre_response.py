"""How far a calibration's principal point follows a decentred group: the paraxial image shift
the diagnosis models, against what calibrations make of the whole traced image.

For each of 8 lens states (0-1) of ``laikin-10x``, the axis-tilt set's views (10 views of a 9x6
board at 640 x 480, 12.9 um pixels) are projected without noise through the exact lens, aligned
and with the variator statically decentred by ``--decenter`` um, and each is calibrated with
OpenCV (5 terms; k3 fixed at the long end when OpenCV gives k3 no sigma). Printed per state:

* ``paraxial``: the chief ray's image shift ``-S_g d / pitch`` (what the renderer records as the
  moved principal point, and the diagnosis's column per decentre), px;
* ``dense fit``: the move of the principal point of :func:`zoomcalib.optics.lens_camera.lens_camera`
  (a camera model fitted to the traced image over the whole field), px;
* ``calibrated``: the move of the calibrated principal point, px, and its ratio to the paraxial
  shift;
* ``predicted``: the move :func:`zoomcalib.diagnose.response.calibration_response` predicts from
  the aligned lens's calibration (its views and solution) and the traced image of the error, px.

``python benchmarks/decentre_response.py [--decenter 94,-41]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from keystone_absorption import (  # noqa: E402
    SENSOR,
    _observations,
    calibrate_or_none,
    milli_pair,
    set_views,
)

from zoomcalib.diagnose.model import LensResponse  # noqa: E402
from zoomcalib.diagnose.response import RowCalibration, calibration_response  # noqa: E402
from zoomcalib.optics.lens_camera import exact_mapping, lens_camera  # noqa: E402
from zoomcalib.optics.misalignment import Misalignment  # noqa: E402
from zoomcalib.optics.prescription import load_prescription  # noqa: E402

GROUP = "variator"


def _calibrated_move(lens, z: float, still: Misalignment, moved: Misalignment):
    aligned = exact_mapping(lens, z, still, SENSOR)
    decentred = exact_mapping(lens, z, moved, SENSOR)
    target, poses = set_views(aligned, z)
    for flags in (0, cv2.CALIB_FIX_K3):
        obs = _observations(aligned, target, poses)
        plain = calibrate_or_none(obs, flags)
        shifted = calibrate_or_none(_observations(decentred, target, poses), flags)
        if plain is not None and shifted is not None:
            G = calibration_response(lens, z, SENSOR.pixel_pitch_mm, RowCalibration(plain, obs),
                                     GROUP, "decenter")
            d_mm = moved.decenter[list(lens.group_names).index(GROUP)]
            return np.array([shifted.cx - plain.cx, shifted.cy - plain.cy]), G[:2] @ d_mm, flags
    return None, None, None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--decenter", type=milli_pair, default="94,-41",
                    help="X,Y um of the variator")
    d_mm = ap.parse_args().decenter
    lens = load_prescription("laikin-10x")
    response = LensResponse.of(lens, SENSOR.pixel_pitch_mm, n_grid=201)
    names = list(lens.group_names)
    zero = np.zeros((len(names), 2))
    offset = zero.copy()
    offset[names.index(GROUP)] = d_mm
    still, moved = Misalignment(zero, zero), Misalignment(offset, zero)
    print(f"{'z':>5s} {'f mm':>6s} | {'paraxial':>15s} | {'dense fit':>15s} | "
          f"{'calibrated':>15s} {'/ paraxial':>10s} | {'predicted':>15s}")
    for z in np.linspace(0.0, 1.0, 8):
        s_d, _ = response.sensitivities(np.array([z]))[GROUP]
        paraxial = -s_d[0] * d_mm / SENSOR.pixel_pitch_mm
        c1, c0 = (lens_camera(lens, float(z), m).camera for m in (moved, still))
        # lens_camera's own sensor: its pixels scaled to this set's
        to_set_px = c0.sensor.pixel_pitch_mm / SENSOR.pixel_pitch_mm
        dense = np.array([c1.cx - c0.cx, c1.cy - c0.cy]) * to_set_px
        calibrated, predicted, flags = _calibrated_move(lens, float(z), still, moved)
        f_mm = c0.fx * c0.sensor.pixel_pitch_mm
        cal = ("(OpenCV gives no sigma)" if calibrated is None else
               f"{calibrated[0]:7.2f} {calibrated[1]:7.2f} "
               f"{np.linalg.norm(calibrated) / np.linalg.norm(paraxial):10.2f} | "
               f"{predicted[0]:7.2f} {predicted[1]:7.2f}" + (" (k3 fixed)" if flags else ""))
        print(f"{z:5.2f} {f_mm:6.1f} | {paraxial[0]:7.2f} {paraxial[1]:7.2f} | "
              f"{dense[0]:7.2f} {dense[1]:7.2f} | {cal}")


if __name__ == "__main__":
    main()
