"""A zoom sweep cut from one real calibration set: a testbed whose noise nobody modelled.

A digital zoom crops the sensor to a window of ``1/z`` of its width centred on ``c`` (sensor
px) and scales the window to the output size, ``s = z W_out / W`` output px per sensor px.
A corner seen at ``u`` (sensor px, OpenCV's convention: pixel centres at integers) lands at

    u' = s (u - c) + (W_out - 1) / 2,

so a pinhole with distortion ``(fx, cx, cy, k1 ...)`` becomes exactly

    fx' = s fx,   cx' = s (cx - c_x) + (W_out - 1) / 2,   cy' likewise,

with the distortion coefficients unchanged (they act on normalised coordinates). Each step
keeps only the corners inside its window, and each real view goes to at most one step, so the
steps share no corner errors. Their intrinsics, mapped back to the sensor
(:meth:`DigitalZoom.to_sensor`), are one camera's: they must agree across the steps within
their sigmas, whatever the camera's true values are. That is a check of accuracy and of the
sigmas' honesty on real corner errors (a real lens's misfit to the model, a real board's
warp, real detector noise), which no renderer of ours made.

What it does not reproduce: the real zoom's change of distortion with focal length (here
constant in normalised coordinates) and the long end's near-fronto-parallel views (here the
tilts of the real set at every step); noise grows with ``s`` instead of staying constant in
output px. Moving the window's centre along the zoom (``drift_px``) moves the output
principal point as a real zoom's wobble would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .result import Observations
from .scatter import view_groups

__all__ = ["DigitalZoom", "digital_zoom_sweep"]


@dataclass
class DigitalZoom:
    """A digital-zoom sweep (module docstring).

    Attributes
    ----------
    observations : dict of str to Observations
        Per step, the corners inside its window in output px.
    zoom : dict of str to float
        ``z`` per step (1: the full sensor width).
    scale : dict of str to float
        ``s`` per step, output px per sensor px.
    window_centre : dict of str to (2,) ndarray
        ``c`` per step, sensor px.
    source_views : dict of str to (n,) ndarray
        Per step, the indices of the source set's views it uses (disjoint between steps).
    image_size : (int, int)
        Output (width, height), px.
    """

    observations: dict[str, Observations]
    zoom: dict[str, float]
    scale: dict[str, float]
    window_centre: dict[str, np.ndarray]
    source_views: dict[str, np.ndarray]
    image_size: tuple[int, int]

    def output_centre(self) -> np.ndarray:
        """``((W_out - 1) / 2, (H_out - 1) / 2)``, px."""
        return (np.asarray(self.image_size, float) - 1.0) / 2.0

    def to_sensor(self, step: str, fx: float, cx: float, cy: float) -> tuple[float, ...]:
        """A step's ``fx, cx, cy`` (output px) as the source camera's (sensor px): the
        inverse of the module docstring's map."""
        s, c = self.scale[step], self.window_centre[step]
        mid = self.output_centre()
        return fx / s, (cx - mid[0]) / s + c[0], (cy - mid[1]) / s + c[1]


def _window_points(obs: Observations, z: float, centre: np.ndarray,
                   out_size: tuple[int, int]) -> tuple[float, list]:
    """Scale ``s`` and, per source view, the corners inside the window (output px)."""
    s = z * out_size[0] / obs.image_size[0]
    mid = (np.asarray(out_size, float) - 1.0) / 2.0
    views = []
    for ids, uv in obs.views:
        moved = s * (np.asarray(uv, float) - centre) + mid
        inside = np.all((moved >= 0.0) & (moved <= np.asarray(out_size) - 1.0), axis=1)
        views.append((np.asarray(ids)[inside], moved[inside]))
    return s, views


def digital_zoom_sweep(obs: Observations, zooms: np.ndarray, *, width: int = 1280,
                       views_per_step: int = 24, min_points: int = 24, drift_px: float = 0.0,
                       rng: np.random.Generator | None = None) -> DigitalZoom:
    """Cut ``obs`` (one real set, sensor px) into a digital-zoom sweep (module docstring).

    Parameters
    ----------
    zooms : (S,) array_like
        ``z`` of each step, each >= 1.
    width : int
        Output width, px; the height keeps the sensor's aspect ratio.
    views_per_step : int
        Views per step (fewer where the set runs out). Steps take views from the longest zoom
        down, each from the views not yet used whose whole group of nearly one pose
        (:func:`~zoomcalib.calibrate.scatter.view_groups`) has ``min_points`` corners in the
        window, drawn at random with ``rng``.
    drift_px : float
        Output principal point's move from the shortest to the longest step, px: ``x`` by
        ``drift_px sin(2.5 t)``, ``y`` by ``-drift_px t`` with ``t`` from 0 to 1 in ``log z``.

    Raises
    ------
    ValueError
        If a zoom is below 1 or a step finds fewer than 3 views.
    """
    zooms = np.sort(np.asarray(zooms, float))
    if zooms.size < 2 or zooms[0] < 1.0:
        raise ValueError(f"digital zoom needs 2 or more zooms >= 1, got {zooms.tolist()}")
    rng = rng or np.random.default_rng(0)
    w, h = obs.image_size
    out_size = (int(width), int(round(width * h / w)))
    groups = view_groups(obs.views, obs.image_size)
    used = np.zeros(obs.n_views, bool)
    span = np.log(zooms[-1] / zooms[0])
    sweep = DigitalZoom({}, {}, {}, {}, {}, out_size)
    for z in zooms[::-1]:
        t = np.log(z / zooms[0]) / span
        s = z * out_size[0] / w
        shift = np.array([drift_px * np.sin(2.5 * t), -drift_px * t])
        centre = (np.array([w, h], float) - 1.0) / 2.0 - shift / s
        s, views = _window_points(obs, z, centre, out_size)
        enough = np.array([len(ids) >= min_points for ids, _ in views]) & ~used
        eligible = [g for g in np.unique(groups) if enough[groups == g].all()]
        chosen: list[int] = []
        for g in rng.permutation(eligible):
            if len(chosen) >= views_per_step:
                break
            chosen += np.flatnonzero(groups == g).tolist()
        name = f"z{z:.2f}"
        if len(chosen) < 3:
            raise ValueError(f"digital zoom: step {name} finds {len(chosen)} views with "
                             f"{min_points} corners in its window (need 3)")
        chosen = sorted(chosen)
        used[chosen] = True
        sweep.observations[name] = Observations(
            obs.object_points, [views[i] for i in chosen], out_size,
            [obs.names[i] if obs.names else f"view{i:03d}" for i in chosen])
        sweep.zoom[name], sweep.scale[name] = float(z), float(s)
        sweep.window_centre[name], sweep.source_views[name] = centre, np.array(chosen)
    order = sorted(sweep.zoom, key=sweep.zoom.get)
    sweep.observations = {n: sweep.observations[n] for n in order}
    return sweep
