"""The principal point across the zoom range: its drift, its scatter and its sensitivities.

The principal point of a lens state is the image of the on-axis object at infinity (the chief ray
through the real stop centre). Under the mechanical error model of
:mod:`zoomcalib.optics.mechanics` it follows a spiral as the barrel turns (the locked errors), and
scatters about it (play and backlash): the paper's Fig. 5.

References
----------
A. Gardel, J. L. Lázaro, J. M. Lavest, "Influence of mechanical errors in a zoom camera",
Image Anal. Stereol. 21 (2002).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..camera import DEFAULT_SENSOR, Sensor
from .cam import solve_gaps
from .mechanics import Tolerances, draw_misalignment
from .misalignment import Misalignment
from .paraxial import chief_ray_image, effective_focal_length, image_shift_sensitivity
from .prescription import Prescription
from .raytrace import chief_ray_image_real

__all__ = ["PrincipalPointScatter", "principal_point_scatter", "principal_point_image",
           "sensitivity_rows", "neutral_pivot_offset", "TRACERS"]

TRACERS = ("exact", "paraxial")


def principal_point_image(lens: Prescription, thickness: np.ndarray,
                          misalignment: Misalignment | None, tracer: str = "exact") -> np.ndarray:
    """(..., 2) principal point on the image plane, lens frame, mm, with the chosen tracer."""
    if tracer == "exact":
        return chief_ray_image_real(lens, thickness, misalignment)
    if tracer == "paraxial":
        return chief_ray_image(lens, thickness, misalignment)
    raise ValueError(f"tracer must be one of {TRACERS}, got {tracer!r}")


@dataclass
class PrincipalPointScatter:
    """Monte Carlo principal point per zoom state.

    Attributes
    ----------
    zoom, efl_mm, fx_px : (Z,) ndarray
    mean_px, std_px : (Z, 2) ndarray
        Mean and 1-sigma (per axis, ddof=1) of (cx, cy) over the draws, px.
    sd_mean_px : (Z, 2) ndarray
        1-sigma of the mean itself (``std / sqrt(S)``).
    samples_px : (Z, S, 2) ndarray
        Every draw's principal point, px.
    seed : int
    tracer : str
    """

    zoom: np.ndarray
    efl_mm: np.ndarray
    fx_px: np.ndarray
    mean_px: np.ndarray
    std_px: np.ndarray
    sd_mean_px: np.ndarray
    samples_px: np.ndarray
    seed: int
    tracer: str

    def rows(self) -> list[dict]:
        """One dict per zoom state with the ``principal_point.csv`` columns."""
        return [{"zoom": z, "efl_mm": e, "fx_px": f, "cx_mean": m[0], "cy_mean": m[1],
                 "cx_std": s[0], "cy_std": s[1]}
                for z, e, f, m, s in zip(self.zoom, self.efl_mm, self.fx_px, self.mean_px,
                                         self.std_px, strict=True)]


def principal_point_scatter(lens: Prescription, tolerances: Tolerances, zoom: Iterable[float],
                            n_samples: int = 1000, seed: int = 0, tracer: str = "exact",
                            sensor: Sensor = DEFAULT_SENSOR, direction: str = "random",
                            progress: Callable[[int], None] | None = None
                            ) -> PrincipalPointScatter:
    """Monte Carlo of the principal point over the mechanical error draws.

    Parameters
    ----------
    lens : Prescription
    tolerances : Tolerances
    zoom : (Z,) array_like
        Zoom states in [0, 1].
    n_samples : int
        Draws per zoom state.
    seed : int
        Seed of the draws (each zoom step has its own child stream, see
        :func:`~zoomcalib.optics.mechanics.draw_misalignment`).
    tracer : {'exact', 'paraxial'}
    sensor : Sensor
    direction : {'random', 'in', 'out'}
        Direction of the last zoom move before each draw (sets the backlash side).
    progress : callable, optional
        Called with 1 after each zoom step.

    Returns
    -------
    PrincipalPointScatter
    """
    if n_samples < 2:
        raise ValueError("n_samples must be at least 2 to estimate a scatter")
    zoom = np.atleast_1d(np.asarray(list(zoom), dtype=float))
    thickness = lens.thickness_at(solve_gaps(lens, zoom))  # shape (Z, N)
    efl = effective_focal_length(lens, thickness)
    draws = draw_misalignment(lens, tolerances, zoom, n_samples, seed, direction)
    samples = np.empty((len(zoom), n_samples, 2))
    for i in range(len(zoom)):
        mis = Misalignment(draws.decenter[i], draws.tilt[i])  # shape (S, G, 2)
        image = principal_point_image(lens, thickness[i], mis, tracer)
        samples[i] = sensor.image_plane_to_pixels(image)
        if progress is not None:
            progress(1)
    std = samples.std(axis=1, ddof=1)
    return PrincipalPointScatter(zoom=zoom, efl_mm=efl, fx_px=efl / sensor.pixel_pitch_mm,
                                 mean_px=samples.mean(axis=1), std_px=std,
                                 sd_mean_px=std / np.sqrt(n_samples), samples_px=samples,
                                 seed=seed, tracer=tracer)


def sensitivity_rows(lens: Prescription, zoom: Iterable[float]) -> list[dict]:
    """Paraxial image shift per unit decentre and tilt of every group, per zoom state.

    Returns
    -------
    rows : list of dict
        Keys ``zoom, efl_mm, group, shift_per_decenter`` (um/um) and
        ``shift_per_tilt_um_per_mrad`` (tilt pivot at the group's first vertex). Shifts are on the
        image plane in the lens frame (a positive value moves the image the same way as the group).
    """
    zoom = np.atleast_1d(np.asarray(list(zoom), dtype=float))
    thickness = lens.thickness_at(solve_gaps(lens, zoom))
    efl = effective_focal_length(lens, thickness)
    per = {g: image_shift_sensitivity(lens, thickness, g) for g in lens.group_names}
    return [{"zoom": z, "efl_mm": efl[i], "group": g, "shift_per_decenter": per[g][0][i],
             "shift_per_tilt_um_per_mrad": per[g][1][i]}
            for i, z in enumerate(zoom) for g in lens.group_names]


def neutral_pivot_offset(lens: Prescription, zoom: float, group: str) -> float:
    """Axial position (mm from the group's first vertex) of the tilt pivot that leaves the
    principal point in place to first order.

    A tilt ``t`` about a pivot ``a`` mm behind the first vertex equals a tilt about the vertex
    plus a decentre ``-a t``, so the image shift ``t (S_t - a S_d)`` vanishes for ``a = S_t / S_d``.
    """
    thickness = lens.thickness_at(solve_gaps(lens, [zoom]))[0]
    s_d, s_t = image_shift_sensitivity(lens, thickness, group)
    return float(s_t / s_d)
