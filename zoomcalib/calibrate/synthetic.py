"""Synthetic zoom sweeps without images: detections made by projecting a board, and a
:class:`~zoomcalib.calibrate.run.CalibrateRun` made from them, for tests, benchmarks and the
report's examples.

A sweep (:func:`sweep_detections`) has ``steps`` zoom steps with ``fx`` spaced evenly in log
from ``fx_range[0]`` to ``fx_range[1]`` (px), a principal point drifting by up to ``drift_px``
from the image centre and ``k1`` shrinking as ``fx`` grows; each view is a pose drawn from the
seeded generator (tilts up to ``max_tilt_deg`` about x and y, distance such that the board
fills about half the image) and projected with ``cv2.projectPoints``, with Gaussian noise of
``noise_px`` per coordinate. With ``misprint_mm`` the board projected is not the nominal one
the observations carry: each corner is displaced in the board plane by its own Gaussian error
of that 1-sigma, the same in every view and step (a board printed a little off). Pixels in
OpenCV's convention; board in mm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..targets import parse_pattern
from .result import Observations

__all__ = ["Sweep", "SweepSettings", "sweep_detections", "with_view_fields", "calibrated_run"]


@dataclass
class Sweep:
    """Detections per step (``observations``), the step's zoom, and the truth per step
    (``fx, cx, cy, k1`` and the ``(rvec, tvec)`` poses), kept apart from the detections."""

    observations: dict[str, Observations]
    zoom: dict[str, float]
    truth: dict[str, dict]


@dataclass(frozen=True)
class SweepSettings:
    """What :func:`sweep_detections` draws (module docstring).

    Attributes
    ----------
    steps, views : int
        Zoom steps, and views per step.
    image_size : (int, int)
        Width and height, px.
    noise_px : float
        Corner noise, 1-sigma per coordinate, px.
    fx_range : (float, float)
        Focal lengths of the first and the last step, px (log-spaced between).
    max_tilt_deg : float
        The board's tilts about the two image axes are drawn within this, degrees.
    drift_px : float
        Size of the principal point's drift over the sweep, px.
    pattern : str
        Target spec.
    outliers : mapping of (step index, view index) to float, optional
        A displacement (px) added to three of that view's points, which a robust fit should
        reject.
    misprint_mm : float
        The 1-sigma of the board's printing error (drawn first, and only when positive).
    """

    steps: int = 3
    views: int = 10
    image_size: tuple[int, int] = (800, 600)
    noise_px: float = 0.1
    fx_range: tuple[float, float] = (700.0, 2800.0)
    max_tilt_deg: float = 35.0
    drift_px: float = 12.0
    pattern: str = "chessboard:11x8:20"
    outliers: Mapping[tuple[int, int], float] | None = None
    misprint_mm: float = 0.0


def sweep_detections(rng: np.random.Generator, settings: SweepSettings | None = None,
                     **fields) -> Sweep:
    """A seeded synthetic sweep (module docstring) of ``settings`` (default: its defaults);
    ``fields``, keywords named as its fields, replace them (``steps=1, views=20``)."""
    opts = replace(settings or SweepSettings(), **fields)
    steps, views, image_size = opts.steps, opts.views, opts.image_size
    noise_px, fx_range, max_tilt_deg = opts.noise_px, opts.fx_range, opts.max_tilt_deg
    drift_px, outliers, misprint_mm = opts.drift_px, opts.outliers, opts.misprint_mm
    board = parse_pattern(opts.pattern).object_points.astype(float)
    printed = board.copy()
    if misprint_mm > 0:
        printed[:, :2] += rng.normal(0.0, misprint_mm, (len(board), 2))
    centre = board.mean(axis=0)
    extent = float(np.ptp(board[:, 0]))
    w, h = image_size
    fx = np.geomspace(*fx_range, steps)
    obs, zoom, truth = {}, {}, {}
    for s in range(steps):
        u = s / max(steps - 1, 1)
        cx = (w - 1) / 2 + drift_px * np.sin(2.5 * u)
        cy = (h - 1) / 2 - drift_px * u
        k1 = -0.2 * (fx[0] / fx[s])
        K = np.array([[fx[s], 0.0, cx], [0.0, fx[s], cy], [0.0, 0.0, 1.0]])
        dist = np.array([k1, 0.0, 0.0, 0.0, 0.0])
        distance = 2.0 * fx[s] * extent / w
        name = f"zoom_{s:02d}"
        view_list, poses = [], []
        for v in range(views):
            R = cv2.Rodrigues(np.radians([*rng.uniform(-max_tilt_deg, max_tilt_deg, 2),
                                          rng.uniform(-10, 10)]))[0]
            t = np.array([*rng.uniform(-0.1, 0.1, 2) * extent,
                          distance * rng.uniform(0.9, 1.2)]) - R @ centre
            rvec = cv2.Rodrigues(R)[0].ravel()
            pts = cv2.projectPoints(printed, rvec, t, K, dist)[0].reshape(-1, 2)
            pts = pts + rng.normal(0.0, noise_px, pts.shape)
            shift = (outliers or {}).get((s, v))
            if shift:
                pts[:3] += shift
            inside = np.all((pts >= 0) & (pts <= np.array([w - 1, h - 1])), axis=1)
            view_list.append((np.flatnonzero(inside), pts[inside]))
            poses.append((rvec, t))
        obs[name] = Observations(board.copy(), view_list, image_size,
                                 [f"{name}_view{v:02d}.png" for v in range(views)])
        zoom[name] = float(s + 1)
        truth[name] = {"fx": fx[s], "cx": cx, "cy": cy, "k1": k1, "poses": poses}
    return Sweep(obs, zoom, truth)


def with_view_fields(obs: Observations, rng: np.random.Generator, size_px: float
                     ) -> Observations:
    """Each view's corners moved by its own random smooth field (quadratic and cubic in the
    image position, ``size_px`` at 300 px from the view's centre): a lens misfit or a board
    that bends differently in every view, which no pose or camera parameter absorbs."""
    views = []
    for ids, pts in obs.views:
        q = (pts - pts.mean(axis=0)) / 300.0
        basis = np.stack([q[:, 0]**2, q[:, 0] * q[:, 1], q[:, 1]**2, q[:, 0]**3, q[:, 1]**3], 1)
        views.append((ids, pts + size_px * basis @ rng.normal(size=(5, 2))))
    return Observations(obs.object_points, views, obs.image_size, obs.names)


def calibrated_run(sweep: Sweep, backend: str = "opencv", cross_validate: bool = False):
    """A :class:`~zoomcalib.calibrate.run.CalibrateRun` of ``sweep``'s detections as the
    calibrate job makes it without images: each step calibrated with ``backend``
    (``"opencv"``, ``"bundle"`` or ``"zoom-wide"``), flags, optional two-halves check, and the
    zoom model when there are four or more steps."""
    from .run import (
        CalibrateRun,
        _calibrate_once,
        _cross_validate,
        set_step_flags,
        step_file_stems,
    )

    steps = list(sweep.observations)
    run = CalibrateRun(stems=step_file_stems(steps))
    run.observations = dict(sweep.observations)
    run.zoom = dict(sweep.zoom)
    run.zoom_source = {s: "steps.csv" for s in steps}
    if backend == "zoom-wide":
        from .zoomwide import calibrate_zoom_wide

        run.zoom_wide = calibrate_zoom_wide(run.observations, select=False)
        run.results = {s: {"zoom-wide": r} for s, r in run.zoom_wide.results.items()}
    else:
        run.results = {s: {backend: _calibrate_once(backend, o, "standard")}
                       for s, o in run.observations.items()}
    run.table_backend = {s: backend for s in steps}
    if cross_validate:
        run.cross_validation = _cross_validate(run, "standard", None)
    set_step_flags(run)
    if len(steps) >= 4:
        from ..zoom import ZoomModel

        rows = [{"zoom": run.zoom[s], "fx": r.fx, "fy": r.fy, "cx": r.cx, "cy": r.cy,
                 "k1": float(r.dist[0]), **{f"sd_{k}": r.sd[k] for k in ("fx", "fy", "cx", "cy")}}
                for s in steps for r in [run.results[s][backend]]]
        run.zoom_model = ZoomModel.from_table(rows)
        run.holdout = run.zoom_model.holdout_error()
    return run
