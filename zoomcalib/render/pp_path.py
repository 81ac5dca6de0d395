r"""Principal-point paths over a zoom sweep, in px from the sweep's nominal principal point.

``bow``
    ``c(s) = pp_drift_px * s (3 - s) / 2``: a quadratic in the zoom position ``s`` (0 at the
    short end, 1 at the long end, linear in ``log fx``), so any zoom model of degree 2 in
    ``log fx`` fits it exactly.

``traced``
    The principal point of the ray-traced zoom lens ``laikin-10x`` with mechanical errors, lens
    zoom position ``z = s``: the chief ray through the real stop centre
    (:func:`zoomcalib.optics.principal_point.principal_point_image`) with

    * a static assembly decentre and tilt of every moving group (random direction, magnitude
      uniform in 0.5-1 of 100 um and 1 arcmin, then all scaled together so the path's largest
      distance from its short-end point is ``span_px``);
    * the decentre and tilt locked to the barrel (cam-track run-out) of the default tolerance
      file, amplitude uniform in 0.5-1 of the file's, random phase, turning with the barrel
      angle ``4 pi z`` (not scaled).

    The image-plane shift ``x`` (mm) is turned into the sweep's pixels as an angle:
    ``c = -x fx(s) / efl(z)`` (the read-out turns the inverted image upright). Smooth, but not a
    polynomial in ``log fx``: the groups' sensitivities change with zoom, and the run-out turns
    twice over the range. Play and backlash (not repeatable) are left out.

``wiener`` (:func:`wiener_draw`)
    A path whose second derivative is white noise (an integrated Wiener process), drawn on a
    fine grid and seen at a few irregular steps: the generator of the tests and benchmarks of
    the zoom model between the steps, which models the path by a difference prior of its own.
"""

from __future__ import annotations

import numpy as np

from ..optics.cam import barrel_angle, moving_groups, solve_gaps
from ..optics.mechanics import ARCMIN, UM, load_tolerances
from ..optics.misalignment import Misalignment
from ..optics.paraxial import effective_focal_length
from ..optics.prescription import load_prescription
from ..optics.principal_point import principal_point_image

__all__ = ["PP_PATHS", "bowed_path", "traced_path", "wiener_draw"]

PP_PATHS = ("bow", "traced")
TRACED_LENS = "laikin-10x"
_STATIC_DECENTER_UM, _STATIC_TILT_ARCMIN = 100.0, 1.0


def bowed_path(s: np.ndarray, drift_px: tuple[float, float]) -> np.ndarray:
    """``(n, 2)`` px: ``drift_px * s (3 - s) / 2`` (module docstring)."""
    s = np.asarray(s, float)
    return np.outer(s * (3 - s) / 2, drift_px)


def _unit(angle: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def _draw_errors(rng: np.random.Generator, groups: list[int], n_groups: int) -> dict:
    """Static (mm, rad; before scaling) and locked amplitudes (mm, rad) and phases per group."""
    tol = load_tolerances()
    names = load_prescription(TRACED_LENS).group_names
    static_dec, static_tilt = np.zeros((n_groups, 2)), np.zeros((n_groups, 2))
    locked = np.zeros((n_groups, 4))  # decentre amplitude, phase, tilt amplitude, phase
    for g in groups:
        t = tol.for_group(names[g])
        static_dec[g] = (_STATIC_DECENTER_UM * UM * rng.uniform(0.5, 1.0)
                         * _unit(rng.uniform(0, 2 * np.pi)))
        static_tilt[g] = (_STATIC_TILT_ARCMIN * ARCMIN * rng.uniform(0.5, 1.0)
                          * _unit(rng.uniform(0, 2 * np.pi)))
        locked[g] = (t.locked_decenter_um * UM * rng.uniform(0.5, 1.0), rng.uniform(0, 2 * np.pi),
                     t.locked_tilt_arcmin * ARCMIN * rng.uniform(0.5, 1.0),
                     rng.uniform(0, 2 * np.pi))
    return {"static_decenter": static_dec, "static_tilt": static_tilt, "locked": locked}


def _trace(s: np.ndarray, fx_range: tuple[float, float], errors: dict, static_scale: float,
           locked_scale: float) -> np.ndarray:
    """``(n, 2)`` px: the principal point at zoom positions ``s`` (module docstring)."""
    lens = load_prescription(TRACED_LENS)
    z = np.clip(np.asarray(s, float), 0.0, 1.0)
    thickness = lens.thickness_at(solve_gaps(lens, z))
    ratio = fx_range[0] * (fx_range[1] / fx_range[0]) ** z / effective_focal_length(lens, thickness)
    lk = errors["locked"]
    phi = barrel_angle(z)[:, None]  # (n, 1) against the groups' phases (G,)
    dec = (static_scale * errors["static_decenter"]
           + locked_scale * lk[:, 0, None] * _unit(phi + lk[:, 1]))
    tilt = (static_scale * errors["static_tilt"]
            + locked_scale * lk[:, 2, None] * _unit(phi + lk[:, 3]))
    image = principal_point_image(lens, thickness, Misalignment(dec, tilt))
    return -image * ratio[:, None]


def traced_path(s: np.ndarray, fx_range: tuple[float, float], span_px: float,
                seed: int | np.random.SeedSequence, runout: float = 1.0
                ) -> tuple[np.ndarray, dict]:
    """``(n, 2)`` px at zoom positions ``s``, less the path's value at ``s = 0``, and a record
    of the drawn errors (module docstring).

    The static errors are scaled so that ``max_s |c(s) - c(0)|`` over ``s`` in [0, 1] (201
    points) is ``span_px``; the locked run-out is ``runout`` times the size drawn from the
    tolerance file (0: a path of the static errors alone).
    """
    lens = load_prescription(TRACED_LENS)
    groups = [lens.group_index(g) for g in moving_groups(lens)]
    errors = _draw_errors(np.random.default_rng(seed), groups, len(lens.groups))
    fine = _trace(np.linspace(0.0, 1.0, 201), fx_range, errors, 1.0, 0.0)
    scale = span_px / max(float(np.max(np.linalg.norm(fine - fine[0], axis=1))), 1e-12)
    record = {"kind": "traced", "lens": TRACED_LENS, "lens_zoom": "s (0 short end, 1 long end)",
              "static_decenter_um": (scale * errors["static_decenter"] / UM).tolist(),
              "static_tilt_arcmin": (scale * errors["static_tilt"] / ARCMIN).tolist(),
              "locked_decenter_um_phase_rad": (errors["locked"][:, :2] / [UM, 1.0]).tolist(),
              "locked_tilt_arcmin_phase_rad": (errors["locked"][:, 2:] / [ARCMIN, 1.0]).tolist(),
              "runout": runout, "span_px": span_px, "groups": list(lens.group_names)}
    s = np.concatenate([[0.0], np.asarray(s, float)])
    path = _trace(s, fx_range, errors, scale, runout)
    return path[1:] - path[0], record


def wiener_draw(rng: np.random.Generator, steps: int = 10, span: float = 2.3,
                intensity: float = 30.0, noise: float = 1e-3
                ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """One integrated Wiener path: its second derivative white noise of ``intensity`` per
    square root of ``u``, simulated on 4801 points over ``[-0.05, span + 0.05]``; seen at
    ``steps`` abscissae drawn uniformly in ``[0, span]`` (both ends included), each value with
    Gaussian noise of sd ``noise``; and one abscissa drawn between two neighbouring steps
    (0.2-0.8 of their gap). Returns ``u`` (steps,) increasing, the noisy values (steps,),
    ``u_new`` and the path's true value there."""
    fine = np.linspace(-0.05, span + 0.05, 4801)
    dt = fine[1] - fine[0]
    u = np.sort(rng.uniform(0, span, steps))
    u[0], u[-1] = 0.0, span
    path = np.cumsum(np.cumsum(intensity * np.sqrt(dt) * rng.normal(size=len(fine)))) * dt
    values = np.interp(u, fine, path) + rng.normal(0, noise, steps)
    i = rng.integers(0, steps - 1)
    u_new = float(u[i] + rng.uniform(0.2, 0.8) * (u[i + 1] - u[i]))
    return u, values, u_new, float(np.interp(u_new, fine, path))
