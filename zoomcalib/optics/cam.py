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

from .paraxial import effective_focal_length, trace_paraxial
from .prescription import Prescription

__all__ = ["variator_gap", "zoom_of_variator_gap", "solve_gaps", "focus_error",
           "design_zooms", "barrel_angle", "efl_at_zoom"]

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


def solve_gaps(lens: Prescription, zoom: np.ndarray, *, grid: int = 4001,
               tol_mm: float = 1e-10) -> np.ndarray:
    """The three variable gaps at each zoom state, with the compensator solved for focus.

    Parameters
    ----------
    zoom : (Z,) array_like
        Zoom states in [0, 1].
    grid : int
        Number of trial compensator gaps used to bracket every focus solution.

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
    # Bracket every root on a fine grid of g3, vectorised over zoom x trial.
    frac = np.linspace(0.0, 1.0, grid)
    trial = frac[None, :] * g3_max[:, None]  # shape (Z, grid)
    err = focus_error(lens, _gaps(lens, np.broadcast_to(g1[:, None], trial.shape), trial))
    change = np.sign(err[:, :-1]) * np.sign(err[:, 1:]) <= 0
    mid = 0.5 * (trial[:, :-1] + trial[:, 1:])
    dist = np.where(change, np.abs(mid - guess[:, None]), np.inf)
    cell = np.argmin(dist, axis=1)
    if np.any(~np.isfinite(dist[np.arange(len(zoom)), cell])):
        bad = zoom[~np.isfinite(dist[np.arange(len(zoom)), cell])]
        raise ValueError(f"lens {lens.name!r}: no compensator position focuses infinity at "
                         f"zoom {bad}")
    lo = trial[np.arange(len(zoom)), cell]
    hi = trial[np.arange(len(zoom)), cell + 1]
    f_lo = err[np.arange(len(zoom)), cell]
    # Bisection inside the bracketing cell (vectorised, robust, ~45 halvings to 1e-10 mm).
    while np.max(hi - lo) > tol_mm:
        m = 0.5 * (lo + hi)
        f_m = focus_error(lens, _gaps(lens, g1, m))
        left = np.sign(f_m) * np.sign(f_lo) <= 0
        hi = np.where(left, m, hi)
        lo = np.where(left, lo, m)
        f_lo = np.where(left, f_lo, f_m)
    return _gaps(lens, g1, 0.5 * (lo + hi))


def efl_at_zoom(lens: Prescription, zoom: np.ndarray) -> np.ndarray:
    """(Z,) effective focal length (mm) of the focused lens at each zoom state."""
    return effective_focal_length(lens, lens.thickness_at(solve_gaps(lens, zoom)))
