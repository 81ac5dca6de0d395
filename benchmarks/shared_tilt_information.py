"""What the images alone say about one sensor tilt shared by every zoom step: the keystone
that each step's calibration cannot take into its poses, principal point and distortion.

A sensor tilted by ``theta`` against the lens's image plane moves every image point ``uv`` by
``p (p . kappa)``, ``p = uv - c`` px, ``kappa = pitch theta / L`` (1/px, ``L`` the exit pupil's
distance; ``zoomcalib.calibrate.opencv_backend.keystone_response``). A zoom-wide adjustment that
fits one ``kappa`` for all steps, each step keeping its own poses, principal point and
distortion, learns about it only from the part of each step's keystone field that those
parameters cannot reproduce. Linearised at each step's solution, with ``d_i`` the field of a
unit ``kappa_i`` and ``J`` the step's Jacobian over what OpenCV adjusts (poses included), that
part has the Gram matrix

    G_ij = d_i . d_j - d_i^T J (J^T J)^-1 J^T d_j        (px^2 per (1/px)^2),

and at a corner noise of ``sigma`` px per coordinate the steps together give ``kappa`` the
covariance ``sigma^2 (sum_s G_s)^-1``: the best a shared tilt fitted in the adjustment can do
from the images, before any prior on the principal points' path over zoom (which carries the
tilt's image shift ``fx theta`` beside the mechanics' own path, and is not data about the
keystone).

The axis-tilt set of ``benchmarks/diagnose_rendered.py`` (8 lens states 0-1 of
``laikin-10x``, 10 views of a 9x6 board each at 640 x 480, 12.9 um pixels; the poses of
``benchmarks/keystone_absorption.py``) is projected through the exact aligned lens without
noise and calibrated by OpenCV with its default five terms. Printed per state: ``f``, ``L``,
the share of a unit keystone's field that the step's parameters leave (``sqrt(G_xx / d_x .
d_x)``, same in y), and that step's own sd of the tilt at ``--noise-px``; last, the sd of one
tilt shared by all states and the hidden tilt's size in it.

``--check`` tests the linearisation against OpenCV itself: the step's own solution reprojected
(so its model fits exactly), moved by a keystone of 0.3 px at the farthest corner along x, then
y, and calibrated again from that solution; printed per state is the squared error the refit
leaves over the ``kappa^2 G`` predicted (1: the linear picture holds; below 1: the refit takes
in more than the linearised step, and ``G`` overstates what the images say).

``python benchmarks/shared_tilt_information.py [--noise-px 0.02] [--tilt 0.9,-0.4] [--check]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]  # benchmark this checkout

from keystone_absorption import SENSOR, _observations, milli_pair, set_views  # noqa: E402

from zoomcalib.calibrate.opencv_backend import (  # noqa: E402
    _gauss_newton_step,
    _problem_at_solution,
    calibrate_opencv,
    solution_points,
)
from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.optics.lens_camera import exact_mapping, tilted_sensor  # noqa: E402
from zoomcalib.optics.misalignment import Misalignment  # noqa: E402
from zoomcalib.optics.prescription import load_prescription  # noqa: E402

#: The keystone the fields are made at (1/px): small, though the problem is linear in it.
KAPPA = 1e-7


def unabsorbed_gram(obj: list[np.ndarray], res, flags: int = 0) -> np.ndarray:
    """(2, 2) ``G`` of the module docstring at calibration ``res`` (per (1/px)^2)."""
    proj, _ = solution_points(obj, res.K, res.dist, res.rvecs, res.tvecs)
    centre = res.K[[0, 1], [2, 2]]
    fields = [[(p - centre) * ((p - centre) @ (KAPPA * kappa))[:, None] for p in proj]
              for kappa in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0]))]
    left = []
    for field in fields:
        moved = [p + d for p, d in zip(proj, field, strict=True)]
        prob, state = _problem_at_solution(obj, moved, res.K, res.dist, res.rvecs, res.tvecs,
                                           flags, len(res.dist))
        step = _gauss_newton_step(*prob.normal_equations(state)[:5])
        if step is None:
            raise RuntimeError("the step's normal equations are singular")
        total = sum(float(np.sum(d * d)) for d in field)
        left.append(max(total - step[1], 0.0) / KAPPA**2)
    g_xx, g_yy, g_sum = left
    g_xy = 0.5 * (g_sum - g_xx - g_yy)
    return np.array([[g_xx, g_xy], [g_xy, g_yy]])


def refit_over_linear(target, res, gram: np.ndarray) -> list[float]:
    """Per axis, the squared error OpenCV's refit leaves after a keystone of 0.3 px at the
    farthest corner, over ``kappa^2 G`` (the ``--check`` of the module docstring)."""
    pts = target.object_points
    obj = [pts] * len(res.rvecs)
    proj, _ = solution_points(obj, res.K, res.dist, res.rvecs, res.tvecs)
    centre = res.K[[0, 1], [2, 2]]
    kappa = 0.3 / max(float(np.max(np.abs(p - centre))) for p in proj) ** 2
    out = []
    for axis in (0, 1):
        k = np.zeros(2)
        k[axis] = kappa
        moved = [p + (p - centre) * ((p - centre) @ k)[:, None] for p in proj]
        refit = calibrate_opencv(Observations(pts, [(np.arange(len(pts)), m) for m in moved],
                                              (SENSOR.width_px, SENSOR.height_px)),
                                 K_guess=res.K, dist_guess=res.dist)
        left = refit.rms_px**2 * refit.info["n_points"]
        out.append(left / (kappa**2 * gram[axis, axis]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise-px", type=float, default=0.02,
                    help="corner noise, px per coordinate")
    ap.add_argument("--tilt", type=milli_pair, default="0.9,-0.4", help="TX,TY mrad (hidden)")
    ap.add_argument("--check", action="store_true",
                    help="the refit's squared error over the linear prediction, per state")
    args = ap.parse_args()
    lens = load_prescription("laikin-10x")
    still = Misalignment(np.zeros((len(lens.groups), 2)), np.zeros((len(lens.groups), 2)))
    pitch = SENSOR.pixel_pitch_mm
    print(f"{'z':>5s} {'f mm':>6s} {'L mm':>6s} {'left x':>7s} {'left y':>7s} "
          f"{'sd tilt x, y alone (mrad)':>28s}" + ("  refit / linear x, y" if args.check else ""))
    total = np.zeros((2, 2))
    exit_pupils = []
    for z in np.linspace(0.0, 1.0, 8):
        aligned = exact_mapping(lens, float(z), still, SENSOR)
        L = tilted_sensor(aligned, lens, float(z), np.zeros(2)).exit_pupil_mm
        target, poses = set_views(aligned, float(z))
        res = calibrate_opencv(_observations(aligned, target, poses))
        obj = [target.object_points] * len(poses)
        gram = unabsorbed_gram(obj, res)
        proj, _ = solution_points(obj, res.K, res.dist, res.rvecs, res.tvecs)
        energy = [sum(float(np.sum(((p - res.K[[0, 1], [2, 2]]) * (p - res.K[[0, 1], [2, 2]])
                                    [:, [j]]) ** 2)) for p in proj) for j in (0, 1)]
        # kappa = pitch theta / L: the tilt's information is G (pitch / L)^2 per rad^2
        info_theta = gram * (pitch / L) ** 2 / args.noise_px**2
        total += info_theta
        exit_pupils.append(L)
        with np.errstate(divide="ignore"):
            alone = 1e3 / np.sqrt(np.diag(info_theta))
        print(f"{z:5.2f} {aligned.camera.fx * pitch:6.1f} {L:6.1f} "
              f"{np.sqrt(gram[0, 0] / energy[0]):7.4f} {np.sqrt(gram[1, 1] / energy[1]):7.4f} "
              f"{alone[0]:13.2f} {alone[1]:13.2f}"
              + ("  {:6.2f} {:6.2f}".format(*refit_over_linear(target, res, gram))
                 if args.check else ""))
    cov = np.linalg.inv(total)
    sd = 1e3 * np.sqrt(np.diag(cov))
    hidden = 1e3 * args.tilt
    print(f"one tilt shared by all {len(exit_pupils)} states, at {args.noise_px:g} px: sd "
          f"{sd[0]:.2f}, {sd[1]:.2f} mrad; the hidden tilt {hidden[0]:.2f}, {hidden[1]:.2f} "
          f"mrad is {abs(hidden[0]) / sd[0]:.2f}, {abs(hidden[1]) / sd[1]:.2f} sd")


if __name__ == "__main__":
    main()
