"""The zoom cams: from the zoom state to the positions of the moving groups.

- The variator gap ``g1`` (first variable gap) is linear in ``zoom`` between its first and last
  design values: ``g1 = g1_first + zoom * (g1_last - g1_first)``; zoom 0 is the first design
  position (shortest focal length for the built-in lenses).
- The compensator gap ``g3`` (third variable gap) is solved so that an object at infinity is in
  paraxial focus on the fixed image plane; the middle gap takes up the rest,
  ``g2 = total - g1 - g3``, because the front group and the relay do not move.
- Of the focus solutions, the one nearest the design cam (``g3`` interpolated between the design
  positions) is followed, so the compensator stays on the branch through the design positions.
- The barrel turns two full turns over the range: ``phi = 4 pi zoom`` (rad).
"""

from __future__ import annotations

import numpy as np

from .misalignment import vertex_z
from .paraxial import effective_focal_length, trace_paraxial
from .prescription import Prescription

__all__ = ["variator_gap", "zoom_of_variator_gap", "solve_gaps", "focus_error",
           "design_zooms", "barrel_angle", "efl_at_zoom", "moving_groups"]

BARREL_TURNS = 2.0


def barrel_angle(zoom: np.ndarray) -> np.ndarray:
    """Barrel rotation angle, rad: ``phi = 2 pi * BARREL_TURNS * zoom``."""
    return 2.0 * np.pi * BARREL_TURNS * np.asarray(zoom, dtype=float)


def variator_gap(lens: Prescription, zoom: np.ndarray) -> np.ndarray:
    """Variator gap (mm) at ``zoom`` in [0, 1]."""
    g_first, g_last = lens.design_gaps[0, 0], lens.design_gaps[-1, 0]
    return g_first + np.asarray(zoom, dtype=float) * (g_last - g_first)


def zoom_of_variator_gap(lens: Prescription, g1: np.ndarray) -> np.ndarray:
    """Inverse of :func:`variator_gap`."""
    g_first, g_last = lens.design_gaps[0, 0], lens.design_gaps[-1, 0]
    return (np.asarray(g1, dtype=float) - g_first) / (g_last - g_first)


def design_zooms(lens: Prescription) -> np.ndarray:
    """(P,) zoom values of the published design positions."""
    return zoom_of_variator_gap(lens, lens.design_gaps[:, 0])


def focus_error(lens: Prescription, gaps: np.ndarray) -> np.ndarray:
    """Height on the image plane of the paraxial ray entering parallel at unit height.

    Zero when an object at infinity is focused on the image plane. Shape ``gaps.shape[:-1]``.
    """
    thickness = lens.thickness_at(gaps)
    shape = gaps.shape[:-1] + (2,)
    rays = trace_paraxial(lens, thickness, np.ones(shape), np.zeros(shape))
    return rays.y_image[..., 0]


def _gaps(lens: Prescription, g1: np.ndarray, g3: np.ndarray) -> np.ndarray:
    return np.stack([g1, lens.gap_total - g1 - g3, g3], axis=-1)


def solve_gaps(lens: Prescription, zoom: np.ndarray) -> np.ndarray:
    """The three variable gaps at each zoom state, with the compensator solved for focus.

    A paraxial ray's height on the image plane is linear in each gap on its own (a transfer
    ``y' = y + t u`` per gap), and with ``g1`` held both ``g3`` and ``g2 = total - g1 - g3``
    are linear in ``g3``: the focus error is a quadratic in ``g3``, exactly. Its three
    coefficients come from three traces (``g3`` at 0, half and all of ``total - g1``), its
    roots in closed form (the cancellation-free form of the quadratic formula), and the root in
    ``[0, total - g1]`` nearest the design cam is polished by one Newton step on the traced
    error.

    Parameters
    ----------
    zoom : (Z,) array_like
        Zoom states in [0, 1].

    Returns
    -------
    gaps : (Z, 3) ndarray
        ``(g1, g2, g3)`` in mm.

    Raises
    ------
    ValueError
        If a zoom is outside [0, 1] or no focus solution exists there.
    """
    zoom = np.atleast_1d(np.asarray(zoom, dtype=float))
    if np.any((zoom < 0) | (zoom > 1)) or not np.all(np.isfinite(zoom)):
        raise ValueError(f"zoom must lie in [0, 1], got {zoom[(zoom < 0) | (zoom > 1)]}")
    g1 = variator_gap(lens, zoom)
    order = np.argsort(lens.design_gaps[:, 0])
    guess = np.interp(g1, lens.design_gaps[order, 0], lens.design_gaps[order, 2])
    g3_max = lens.gap_total - g1  # g2 >= 0
    # the focus error at x = g3 / g3_max = 0, 1/2, 1: e(x) = a x^2 + b x + c
    trial = np.array([0.0, 0.5, 1.0])[None, :] * g3_max[:, None]
    e0, e_half, e1 = focus_error(
        lens, _gaps(lens, np.broadcast_to(g1[:, None], trial.shape), trial)).T
    a = 2.0 * e1 - 4.0 * e_half + 2.0 * e0
    b = 4.0 * e_half - 3.0 * e0 - e1
    c = e0
    roots = _quadratic_roots(a, b, c)                                   # (Z, 2), in x
    inside = (roots >= -1e-12) & (roots <= 1.0 + 1e-12)
    dist = np.where(inside, np.abs(roots - (guess / g3_max)[:, None]), np.inf)
    pick = np.argmin(dist, axis=1)
    found = np.isfinite(dist[np.arange(len(zoom)), pick])
    if not np.all(found):
        raise ValueError(f"lens {lens.name!r}: no compensator position focuses infinity at "
                         f"zoom {zoom[~found]}")
    x = np.clip(roots[np.arange(len(zoom)), pick], 0.0, 1.0)
    # one Newton step on the traced error: the coefficients' rounding, not the model, is left
    slope = 2.0 * a * x + b
    e_x = focus_error(lens, _gaps(lens, g1, x * g3_max))
    step = np.where(slope != 0.0, e_x / np.where(slope != 0.0, slope, 1.0), 0.0)
    x = np.clip(x - step, 0.0, 1.0)
    return _gaps(lens, g1, x * g3_max)


def _quadratic_roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Both real roots of ``a x^2 + b x + c`` per row, (Z, 2); NaN where there are none (a
    linear row, ``a`` negligible, has its one root twice). ``q = -(b + sign(b) sqrt(b^2 -
    4ac)) / 2`` gives ``q / a`` and ``c / q`` without cancellation."""
    scale = np.maximum(np.abs(b), np.abs(c)) + 1e-300
    linear = np.abs(a) <= 1e-12 * scale
    disc = b * b - 4.0 * a * c
    sqrt_disc = np.sqrt(np.where(disc >= 0.0, disc, np.nan))
    q = -0.5 * (b + np.where(b >= 0.0, 1.0, -1.0) * sqrt_disc)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(linear, -c / b, q / a)
        r2 = np.where(linear, -c / b, c / q)
    return np.stack([r1, r2], axis=1)


def efl_at_zoom(lens: Prescription, zoom: np.ndarray) -> np.ndarray:
    """(Z,) effective focal length (mm) of the focused lens at each zoom state."""
    return effective_focal_length(lens, lens.thickness_at(solve_gaps(lens, zoom)))


def moving_groups(lens: Prescription) -> tuple[str, ...]:
    """Names of the groups whose axial position changes with zoom (the barrel moves them)."""
    thickness = lens.thickness_at(solve_gaps(lens, np.array([0.0, 0.5, 1.0])))
    z = vertex_z(thickness)  # shape (3, N)
    firsts = [first for first, _ in lens.groups.values()]
    return tuple(name for name, s in zip(lens.group_names, firsts, strict=True)
                 if np.ptp(z[:, s]) > 1e-6)
