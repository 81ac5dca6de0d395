"""Synthetic per-zoom calibration tables with one hidden cause, to test a diagnosis.

The generator is independent of the diagnosis's linear model: principal points come from the exact
ray tracer (:func:`zoomcalib.optics.principal_point.principal_point_image`) through the perturbed
lens, so any error in the paraxial sensitivities or in the sign conventions of
:mod:`zoomcalib.diagnose.model` shows up as a failed recovery.

A table is a zoom schedule of ``passes`` x (a sweep in, then a sweep out) over ``n_zoom`` settings,
the last move's direction and the capture order recorded per row. The truth is

- a sensor offset and, for every moving group, a decentre and tilt locked to the barrel (random
  amplitude up to the tolerance's, random phase), plus Gaussian play at every visit (the
  tolerances' ``play_um`` and ``play_tilt_arcmin``);
- measurement noise of the calibration, 1-sigma ``sd_wide_px * (f / f_min) ** sd_growth``;
- optionally one hidden cause, of a random direction and of a magnitude given as the RMS of its
  effect over the rows (less its mean) in units of the RMS noise.
"""

from __future__ import annotations

import numpy as np

from ..camera import Sensor
from ..optics.cam import barrel_angle, solve_gaps
from ..optics.mechanics import ARCMIN, UM, Tolerances, load_tolerances
from ..optics.misalignment import Misalignment
from ..optics.paraxial import effective_focal_length
from ..optics.prescription import Prescription
from ..optics.principal_point import principal_point_image
from .model import moving_groups, play_sd_px

__all__ = ["synthetic_zoom_table", "HIDDEN_CAUSES"]

HIDDEN_CAUSES = ("axis_tilt", "backlash", "thermal_drift", "cam_harmonic", "static_decenter",
                 "focus_shift")


def _rot(angle: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """(N, 2) rotation of the fixed 2-vector ``vec`` by each angle."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vec[0] - s * vec[1], s * vec[0] + c * vec[1]], axis=-1)


def _visible_rms(effect: np.ndarray) -> float:
    """RMS of an (N, 2) effect without its mean: a constant shift is the sensor offset's."""
    return float(np.sqrt(np.mean((effect - effect.mean(axis=0)) ** 2)))


def synthetic_zoom_table(lens: Prescription, cause: str | None, rng: np.random.Generator, *,
                         n_zoom: int = 9, passes: int = 2, pitch_mm: float = 0.00645,
                         tolerances: Tolerances | None = None,
                         magnitude: float | tuple[float, float] = (3.0, 8.0),
                         sd_wide_px: float = 0.05, sd_growth: float = 1.0,
                         with_focus: bool = False, with_temperature: bool = False
                         ) -> tuple[list[dict], dict]:
    """A measured ``zoom_calibration.csv`` table with one hidden cause.

    Parameters
    ----------
    lens : Prescription
    cause : str or None
        One of :data:`HIDDEN_CAUSES`, or None for the simulation's model alone.
    rng : numpy.random.Generator
    n_zoom, passes : int
        Zoom settings per sweep; repetitions of (in sweep, out sweep).
    pitch_mm : float
    tolerances : Tolerances, optional
        Locked-error amplitudes and play (default: the built-in tolerances).
    magnitude : float or (float, float)
        RMS over the rows of the hidden effect less its mean (a constant shift cannot be told
        from the sensor offset), in units of the RMS noise; a range draws it uniformly.
    sd_wide_px, sd_growth : float
        Measurement 1-sigma of cx and cy at the shortest focal length and its growth exponent.
    with_focus, with_temperature : bool
        Add a ``focus`` / ``temperature`` column (forced on for ``focus_shift``).

    Returns
    -------
    rows : list of dict
        The table (``zoom_calibration.csv`` columns; ``zoom`` is an encoder count).
    truth : dict
        ``cause``, ``group`` (for mechanical causes), ``params`` named as the diagnosis names
        them, ``magnitude`` (noise units), ``z`` (lens state per row) and ``noise_rms_px``.
    """
    if cause is not None and cause not in HIDDEN_CAUSES:
        raise ValueError(f"cause must be one of {HIDDEN_CAUSES} or None, got {cause!r}")
    tolerances = tolerances if tolerances is not None else load_tolerances()
    with_focus = with_focus or cause == "focus_shift"
    groups = moving_groups(lens)
    gi = {g: lens.group_index(g) for g in groups}

    # schedule: passes x (in sweep, out sweep)
    settings = np.linspace(0.0, 1.0, n_zoom)
    z = np.concatenate([np.concatenate([settings, settings[::-1]]) for _ in range(passes)])
    direction = np.tile(np.repeat([1.0, -1.0], n_zoom), passes)
    n = len(z)
    seq = np.arange(n, dtype=float)
    phi = barrel_angle(z)
    efl = effective_focal_length(lens, lens.thickness_at(solve_gaps(lens, z)))
    fx = efl / pitch_mm
    sensor = Sensor(width_px=1280, height_px=960, pixel_pitch_mm=pitch_mm)

    # truth of the simulation's model
    decenter = np.zeros((n, len(lens.groups), 2))  # shape (N, G, 2), mm
    tilt = np.zeros_like(decenter)  # rad
    for g in groups:
        tol = tolerances.for_group(g)
        a_dec = tol.locked_decenter_um * UM * rng.uniform(0.5, 1.0)
        a_tilt = tol.locked_tilt_arcmin * ARCMIN * rng.uniform(0.5, 1.0)
        decenter[:, gi[g]] = _rot(phi + rng.uniform(0, 2 * np.pi), np.array([a_dec, 0.0]))
        tilt[:, gi[g]] = _rot(phi + rng.uniform(0, 2 * np.pi), np.array([a_tilt, 0.0]))
        decenter[:, gi[g]] += rng.standard_normal((n, 2)) * tol.play_um * UM
        tilt[:, gi[g]] += rng.standard_normal((n, 2)) * tol.play_tilt_arcmin * ARCMIN
    offset = sensor.centre_px + rng.normal(0.0, 15.0, 2)
    thickness = lens.thickness_at(solve_gaps(lens, z))

    def principal_points(dec: np.ndarray) -> np.ndarray:
        image = principal_point_image(lens, thickness, Misalignment(dec, tilt))  # shape (N, 2)
        return sensor.image_plane_to_pixels(image) + (offset - sensor.centre_px)

    pp_model = principal_points(decenter)  # shape (N, 2)
    sd_meas = sd_wide_px * (efl / efl.min()) ** sd_growth
    # the noise the diagnosis is told about: measurement and play scatter (reported in truth)
    play = play_sd_px(lens, z, tolerances, pitch_mm)
    noise_rms = float(np.sqrt(np.mean(sd_meas ** 2 + play ** 2)))

    focus = rng.choice([0.0, 0.5, 1.0, 2.0], size=n) if with_focus else None
    temperature = None
    if with_temperature:
        warm = 8.0 * (1.0 - np.exp(-seq / (0.4 * n))) + rng.normal(0.0, 0.1, n)
        temperature = 20.0 + warm
    truth: dict = {"cause": cause or "none", "params": {}, "z": z, "noise_rms_px": noise_rms}
    pp = pp_model
    if cause is not None:
        m = float(rng.uniform(*magnitude)) if isinstance(magnitude, tuple) else float(magnitude)
        truth["magnitude"] = m
        ang = rng.uniform(0, 2 * np.pi)
        unit = np.array([np.cos(ang), np.sin(ang)])
        if cause in ("backlash", "cam_harmonic", "static_decenter"):
            g = groups[rng.integers(len(groups))]
            truth["group"] = g
            if cause == "backlash":
                # the group sits +-b/2 along a barrel-fixed direction, sign by the last move
                shift = direction[:, None] * _rot(phi, unit)
            elif cause == "cam_harmonic":
                shift = _rot(2.0 * phi, unit)
            else:
                shift = np.broadcast_to(unit, (n, 2))

            def with_amplitude(a_um: float) -> np.ndarray:
                dec = decenter.copy()
                dec[:, gi[g]] += a_um * UM * shift
                return principal_points(dec)

            effect = with_amplitude(1.0) - pp_model  # per um
            a_um = m * noise_rms / _visible_rms(effect)
            pp = with_amplitude(a_um)
            truth["params"] = {f"{g}_x_um": a_um * unit[0], f"{g}_y_um": a_um * unit[1]}
        else:
            if cause == "axis_tilt":
                per_unit = 1e-3 * fx[:, None] * unit
                names = ("tilt_x_mrad", "tilt_y_mrad")
            elif cause == "thermal_drift":
                v = temperature if temperature is not None else seq
                per_unit = (v - v.mean())[:, None] * unit
                names = (("rate_x_px_per_K", "rate_y_px_per_K") if temperature is not None
                         else ("rate_x_px_per_capture", "rate_y_px_per_capture"))
            else:  # focus_shift
                per_unit = (focus - focus.mean())[:, None] * unit
                names = ("rate_x_px_per_focus_unit", "rate_y_px_per_focus_unit")
            a = m * noise_rms / _visible_rms(per_unit)
            pp = pp_model + a * per_unit
            truth["params"] = {names[0]: a * unit[0], names[1]: a * unit[1]}

    cx = pp[:, 0] + rng.standard_normal(n) * sd_meas
    cy = pp[:, 1] + rng.standard_normal(n) * sd_meas
    fx_meas = fx * (1.0 + rng.normal(0.0, 5e-4, n))
    counts = np.round(9000.0 * z ** 0.8)  # a monotone encoder scale
    rows = []
    for i in range(n):
        row = {"step": f"s{i:03d}", "zoom": float(counts[i]), "fx": fx_meas[i],
               "fy": fx_meas[i] * (1.0 + rng.normal(0.0, 2e-4)), "cx": cx[i], "cy": cy[i],
               "sd_fx": 5e-4 * fx[i], "sd_fy": 5e-4 * fx[i], "sd_cx": sd_meas[i],
               "sd_cy": sd_meas[i], "direction": "in" if direction[i] > 0 else "out",
               "sequence": i}
        if focus is not None:
            row["focus"] = float(focus[i])
        if temperature is not None:
            row["temperature"] = float(temperature[i])
        rows.append(row)
    return rows, truth
