"""A zoom sweep like a real calibration session, rendered through pinhole + distortion cameras.

Camera per step
---------------
``steps`` focal lengths ``fx`` log-spaced over ``fx_range`` (px, square pixels: ``fy = fx``).
With ``s = log(fx / fx_0) / log(fx_1 / fx_0)`` (0 at the short end, 1 at the long end):

* principal point ``c(s) = centre + pp_offset_px + p(s)`` (the centre is
  ``((W - 1) / 2, (H - 1) / 2)``), the path ``p`` one of :mod:`zoomcalib.render.pp_path`:
  ``bow`` (default), ``p(s) = pp_drift_px * s (3 - s) / 2``, a quadratic in ``log fx``; or
  ``traced``, the principal point of the ray-traced zoom lens with drawn mechanical errors,
  ``pp_span_px`` from its short-end point at most, not a polynomial in ``log fx``;
* distortion ``(k1, 0, 0, 0, 0)`` with ``k1 = k1_short * fx_0 / fx``: barrel at the short end,
  nearly none at the long end; or given terms per step (``dist``), e.g. a real lens's measured
  distortion, which at the long end of most zoom lenses is a pincushion of 1-3 % of the
  half-diagonal (lensfun).

Poses
-----
One physical board (the pattern in mm, optionally waving: :class:`BoardSurface`) at a distance
scaled with ``fx`` so its point grid spans ``fill`` of the image height, times 0.95-1.25 per
view. Tilts about random in-plane axes are drawn from 0.2-1 times a maximum that goes
geometrically from ``tilt_short_deg`` at the short end to ``tilt_long_deg`` at the long end (near
fronto-parallel, as long-focus sets are); rolls of up to 10 degrees; the board centre lands in the
middle fifth of the image; a view is kept when every point lies 10 px inside the image.

Layout written by :func:`render_zoom_sweep`::

    OUT/steps.csv            step, zoom (= fx, px), sequence (and session, with a re-taping)
    OUT/truth.json           settings, board surface, the principal-point path
                             (``pp_path``: kind and its drawn errors), and per step:
                             zoom, K, dist, camera,
                             psf_sigma_px, board_session, per view: file, rvec, tvec (board ->
                             camera, mm), points_px (true, OpenCV convention), visible,
                             focal_scale (e^{s_v}), readout_turn (w_v, rad);
                             effects; render_s
                             (wall clock) and render_cpu_s (CPU time of the process)
    OUT/fx_NNNNN/view_YY.png (or .jpg)   NNNNN = fx rounded to px

Capture effects
---------------
:class:`CaptureEffects` imitates what a real PTZ camera's set carries beside the lens: the
camera's sharpening (an unsharp mask on the quantised frame, :func:`~zoomcalib.render.image.
sharpen_image`), a zoom that does not return to the same focal length between views (each
view's ``fx``, ``fy`` scaled by ``e^{s_v}``, ``s_v ~ N(0, zoom_jitter)``), a paper board
re-taped between capture sessions (the steps from ``retape_at`` on see a second board surface,
drawn like the first; ``steps.csv`` then has a ``session`` column), and a rolling shutter read
out while the camera turns (each view's turn over the readout ``w_v = (w_x, w_y, 0)``,
``w ~ N(0, rolling_shutter)`` rad, row ``v`` seen from the pose turned by ``(v / height - 1/2)
w_v``: :class:`~zoomcalib.render.image.RollingShutterMapping`; poses and true points are the
mid-readout ones). Their draws come from seeds
of their own, so a render without them is the same as before they existed.

The folder names hold one number each (the rounded fx), so
:func:`zoomcalib.calibrate.stepfolders.zoom_steps` reads the zoom from ``steps.csv`` (exact fx)
or, without it, from the names.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path

import cv2
import numpy as np

from .. import __version__
from ..camera import CameraModel, Sensor
from ..io import write_csv, write_json
from ..targets import Target, parse_pattern
from .dataset import check_jpeg_quality, clear_previous_render, write_image
from .image import (
    BoardSurface,
    Optics,
    Radiometry,
    RollingShutterMapping,
    camera_mapping,
    project_points,
    render_image,
    sharpen_image,
)
from .pp_path import PP_PATHS, bowed_path, traced_path

__all__ = ["SWEEP_SENSOR", "CaptureEffects", "SweepCameraOptions", "SweepOptions",
           "sweep_cameras", "principal_point_path", "sweep_poses", "render_zoom_sweep"]

SWEEP_SENSOR = Sensor(1280, 720, 0.003)  # a video camera's frame, 3 um pixels
MARGIN_PX = 10.0


def _zoom_position(fx: np.ndarray, fx_range: tuple[float, float]) -> np.ndarray:
    """0 at the short end of the sweep, 1 at the long end, linear in log fx."""
    return np.log(np.asarray(fx) / fx_range[0]) / np.log(fx_range[1] / fx_range[0])


@dataclass(frozen=True)
class SweepCameraOptions:
    """The principal-point path and the distortion of a sweep's cameras (module docstring,
    section Camera per step).

    Attributes
    ----------
    pp_offset_px : (float, float)
        The principal point's offset from the image centre at the short end, px (before the
        path).
    pp_drift_px : (float, float)
        'bow' path: its drift from the short to the long end, px.
    k1_short : float
        The fading barrel's ``k1`` at the short end (``k1 = k1_short * fx_0 / fx``).
    pp_path : {'bow', 'traced'}
        The path's kind (:data:`zoomcalib.render.pp_path.PP_PATHS`).
    pp_span_px : float
        'traced' path: its largest distance from its short-end point, px.
    pp_runout : float
        'traced' path: cam-track run-out, times the default tolerance file's.
    pp_seed : int or numpy.random.SeedSequence, optional
        'traced' path: seed of its mechanical errors
        (:func:`zoomcalib.render.pp_path.traced_path`); None: 0 in :func:`sweep_cameras`,
        drawn from the sweep's seed in :func:`render_zoom_sweep`.
    dist : (steps, 5) ndarray, optional
        OpenCV terms per step instead of the fading barrel of ``k1_short`` (e.g. a real
        lens's, :meth:`zoomcalib.study.lensfun.ZoomLensDistortion.opencv_distortion`).
    dist_centre_px : (float, float)
        The distortion's centre relative to the principal point at every step, px
        (:class:`~zoomcalib.camera.CameraModel`; OpenCV's model, which the calibration fits,
        has 0).
    """

    pp_offset_px: tuple[float, float] = (6.0, -4.0)
    pp_drift_px: tuple[float, float] = (30.0, -18.0)
    k1_short: float = -0.12
    pp_path: str = "bow"
    pp_span_px: float = 40.0
    pp_runout: float = 1.0
    pp_seed: int | np.random.SeedSequence | None = None
    dist: np.ndarray | None = None
    dist_centre_px: tuple[float, float] = (0.0, 0.0)

    def path(self, fx_range: tuple[float, float], steps: int
             ) -> tuple[np.ndarray, np.ndarray, dict]:
        """:func:`principal_point_path` of these options."""
        return principal_point_path(fx_range, steps, self.pp_path, self.pp_drift_px,
                                    self.pp_span_px, self.pp_runout,
                                    0 if self.pp_seed is None else self.pp_seed)

    def distortion_record(self, source: dict | None = None) -> dict:
        """The ``distortion`` of ``truth.json``: ``source`` (where ``dist`` comes from) or the
        kind of distortion, and its centre."""
        kind = source or ({"kind": "fading", "k1_short": self.k1_short} if self.dist is None
                          else {"kind": "given"})
        return {**kind, "centre_px": [float(v) for v in self.dist_centre_px]}


def sweep_cameras(fx_range: tuple[float, float] = (2300.0, 23000.0), steps: int = 7,
                  sensor: Sensor = SWEEP_SENSOR, options: SweepCameraOptions | None = None,
                  **fields) -> list[CameraModel]:
    """The cameras of the sweep, short end first (module docstring, section Camera per step).

    ``options`` (default: its defaults) sets the principal-point path and the distortion;
    ``fields``, keywords named as its fields, replace them (``pp_path="traced"``).
    """
    opts = replace(options or SweepCameraOptions(), **fields)
    if opts.dist is not None and np.shape(opts.dist) != (steps, 5):
        raise ValueError(f"dist must be (steps, 5) = ({steps}, 5), got {np.shape(opts.dist)}")
    fx, path, _ = opts.path(fx_range, steps)
    centre = np.array([(sensor.width_px - 1) / 2, (sensor.height_px - 1) / 2])
    cams = []
    for i, (f, p) in enumerate(zip(fx, path, strict=True)):
        cx, cy = centre + np.asarray(opts.pp_offset_px) + p
        terms = (np.array([opts.k1_short * fx_range[0] / f, 0.0, 0.0, 0.0, 0.0])
                 if opts.dist is None else np.asarray(opts.dist[i], float))
        cams.append(CameraModel(float(f), float(f), float(cx), float(cy), terms, sensor,
                                np.asarray(opts.dist_centre_px, float)))
    return cams


def principal_point_path(fx_range: tuple[float, float], steps: int, kind: str = "bow",
                         drift_px: tuple[float, float] = (30.0, -18.0), span_px: float = 40.0,
                         runout: float = 1.0, seed: int | np.random.SeedSequence = 0
                         ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The steps' fx (px), the path ``p`` (steps, 2) px of the principal point from
    ``centre + pp_offset_px`` and its record for ``truth.json`` (module docstring)."""
    if steps < 1 or not 0 < fx_range[0] <= fx_range[1]:
        raise ValueError(f"need steps >= 1 and 0 < fx_min <= fx_max, got {steps} and {fx_range}")
    if kind not in PP_PATHS:
        raise ValueError(f"pp_path must be one of {PP_PATHS}, got {kind!r}")
    fx = np.geomspace(fx_range[0], fx_range[1], steps)
    s = _zoom_position(fx, fx_range) if fx_range[1] > fx_range[0] else np.zeros(steps)
    if kind == "bow":
        return fx, bowed_path(s, drift_px), {"kind": "bow", "drift_px": list(drift_px)}
    path, record = traced_path(s, fx_range, span_px, seed, runout)
    return fx, path, record


@dataclass(frozen=True)
class CaptureEffects:
    """What a real capture adds to the lens (module docstring, Capture effects).

    ``sharpen``: ``(amount, sigma_px)`` of the camera's unsharp mask, or None; ``zoom_jitter``:
    sd of each view's log focal scale ``s_v`` (0: none); ``retape_at``: index of the first step
    that sees the re-taped board (None: one board for the sweep); ``rolling_shutter``: sd
    (rad) of each view's turn about the camera's x and y axes over the frame's readout (0:
    a global shutter or a camera at rest)."""

    sharpen: tuple[float, float] | None = None
    zoom_jitter: float = 0.0
    retape_at: int | None = None
    rolling_shutter: float = 0.0

    def __post_init__(self):
        if self.sharpen is not None and not (self.sharpen[0] >= 0 and self.sharpen[1] > 0):
            raise ValueError(f"sharpen {self.sharpen}: give AMOUNT >= 0 and SIGMA_PX > 0")
        if not self.zoom_jitter >= 0:
            raise ValueError(f"zoom_jitter {self.zoom_jitter}: give an sd >= 0")
        if not self.rolling_shutter >= 0:
            raise ValueError(f"rolling_shutter {self.rolling_shutter}: give an sd >= 0 (rad)")
        if self.retape_at is not None and self.retape_at < 1:
            raise ValueError(f"retape_at {self.retape_at}: the first re-taped step's index, "
                             ">= 1")


def _rotation(axis_angle) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, dtype=float).reshape(3, 1))[0]


def sweep_poses(target: Target, camera: CameraModel, n_views: int, max_tilt_deg: float,
                rng: np.random.Generator, fill: float = 0.7,
                max_tries: int = 2000) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses ``Rt_cam_board = (R, t)`` (mm) for one step (module docstring, Poses).

    Raises
    ------
    RuntimeError
        When fewer than ``n_views`` poses keep the board inside the image.
    """
    sensor = camera.sensor
    mapping = camera_mapping(camera)
    pts = target.object_points
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    span = np.ptp(pts[:, 1]) or np.ptp(pts[:, 0])
    distance = camera.fy * span / (fill * sensor.height_px)
    size = np.array([sensor.width_px - 1, sensor.height_px - 1])
    ext = target.extent_mm
    outline = np.array([[ext[0], ext[1], 0], [ext[2], ext[1], 0], [ext[0], ext[3], 0],
                        [ext[2], ext[3], 0]])
    poses = []
    for _ in range(max_tries):
        if len(poses) == n_views:
            break
        tilt = np.deg2rad(max_tilt_deg * rng.uniform(0.2, 1.0))
        phi = rng.uniform(0, 2 * np.pi)
        R = (_rotation(tilt * np.array([np.cos(phi), np.sin(phi), 0.0]))
             @ _rotation([0.0, 0.0, np.deg2rad(rng.uniform(-10, 10))]))
        aim = mapping.unproject((rng.uniform(0.4, 0.6, 2) * size)[None])[0]
        dist = distance * rng.uniform(0.95, 1.25)
        t = dist * np.array([aim[0], aim[1], 1.0]) / np.sqrt(1 + aim @ aim) - R @ centre
        if np.any((outline @ R.T + t)[:, 2] <= 0):
            continue
        uv = project_points(pts, mapping, R, t)
        if np.all(uv > MARGIN_PX) and np.all(uv < size - MARGIN_PX):
            poses.append((R, t))
    if len(poses) < n_views:
        raise RuntimeError(f"found only {len(poses)} of {n_views} poses that keep the board "
                           f"{MARGIN_PX:g} px inside the image at fx {camera.fx:.0f}; lower fill")
    return poses


def _board_surfaces(board_surface: BoardSurface | float | None, extent_mm,
                    retaped: bool, surface_seed, retape_seed) -> list[BoardSurface | None]:
    """The board's surface of each session: the one given (or drawn at the given amplitude,
    mm) and, when the board is re-taped, a second of the same kind, waving otherwise."""
    surface = board_surface
    if isinstance(board_surface, int | float):
        surface = BoardSurface.random(extent_mm, float(board_surface),
                                      np.random.default_rng(surface_seed))
    if not retaped:
        return [surface]
    amplitude = (float(board_surface) if isinstance(board_surface, int | float)
                 else max((abs(m[0]) for m in getattr(surface, "modes", ())), default=0.5))
    return [surface, BoardSurface.random(extent_mm, amplitude or 0.5,
                                         np.random.default_rng(retape_seed))]


@dataclass(frozen=True)
class SweepOptions:
    """What :func:`render_zoom_sweep` renders (layout and conventions in the module docstring).

    Attributes
    ----------
    fx_range : (float, float)
        Focal length at the short and long end, px.
    steps : int
        Zoom steps, ``fx`` log-spaced over ``fx_range``.
    views : int
        Views per step.
    size : (int, int)
        Image width, height, px.
    pattern : str
        The board's spec (one physical size for every step).
    board_surface : BoardSurface or float, optional
        The board's waves (board mm), or an amplitude (mm) for :meth:`BoardSurface.random`
        drawn from ``seed`` over the board; the same board serves every step. None: flat.
    psf : str, optional
        Overrides ``optics.psf`` ('gaussian', 'airy', 'halo', 'elliptical'). A Gaussian or
        elliptical PSF is rendered analytically (when it applies); the others supersampled
        ``supersample`` times per pixel side.
    jpeg_quality : int, optional
        JPEG files of this quality (1-100) instead of PNG; the truth is unchanged.
    seed : int
        Seed of every draw: board, poses, noise, a traced path and the capture effects.
    optics, radiometry
        Default: ``Optics(blur_px=0.8, f_number=2.8)`` and ``Radiometry()`` (2 DN read noise).
    fill : float
        Fraction of the image height the board's point grid spans (module docstring, Poses).
    tilt_deg : (float, float)
        Largest tilt at the short and at the long end, degrees.
    supersample : int
        Sub-samples per pixel side where the supersampled renderer is used.
    pixel_pitch_mm : float
        Pixel pitch, mm.
    distortion_source : dict, optional
        Where a ``dist`` given in ``camera`` comes from (e.g. a lensfun lens), written to
        ``truth.json`` as ``distortion``.
    effects : CaptureEffects, optional
        Sharpening, zoom jitter per view, a re-taped board and a rolling shutter (module
        docstring).
    camera : SweepCameraOptions
        The principal-point path and the distortion of :func:`sweep_cameras`; a traced path
        without ``pp_seed`` is drawn from ``seed``.
    """

    fx_range: tuple[float, float] = (2300.0, 23000.0)
    steps: int = 7
    views: int = 10
    size: tuple[int, int] = (1280, 720)
    pattern: str = "chessboard:22x15:20"
    board_surface: BoardSurface | float | None = None
    psf: str | None = None
    jpeg_quality: int | None = None
    seed: int = 0
    optics: Optics | None = None
    radiometry: Radiometry | None = None
    fill: float = 0.7
    tilt_deg: tuple[float, float] = (40.0, 3.0)
    supersample: int = 3
    pixel_pitch_mm: float = 0.003
    distortion_source: dict | None = None
    effects: CaptureEffects | None = None
    camera: SweepCameraOptions = field(default_factory=SweepCameraOptions)


_CAMERA_FIELDS = frozenset(f.name for f in dataclass_fields(SweepCameraOptions))


def _sweep_options(options: SweepOptions | None, overrides: dict) -> SweepOptions:
    """``options`` with ``overrides`` (fields of :class:`SweepOptions` or of its ``camera``)
    and its optics, radiometry and effects resolved (``psf`` applied)."""
    opts = options or SweepOptions()
    camera = {k: v for k, v in overrides.items() if k in _CAMERA_FIELDS}
    rest = {k: v for k, v in overrides.items() if k not in _CAMERA_FIELDS}
    opts = replace(opts, **rest)
    opts = replace(opts, camera=replace(opts.camera, **camera))
    optics = opts.optics or Optics(blur_px=0.8, f_number=2.8)
    if opts.psf is not None:
        optics = replace(optics, psf=opts.psf)
    return replace(opts, optics=optics, radiometry=opts.radiometry or Radiometry(),
                   effects=opts.effects or CaptureEffects())


@dataclass(frozen=True)
class _SweepSeeds:
    """The sweep's seeds: board, each step's poses and noise, the traced path, the re-taped
    board, the zoom jitter and the rolling shutter. The path's seed is one child more than
    the board's and the steps' and the effects' come after it, so that a render without them
    is the same as before they existed."""

    surface: np.random.SeedSequence
    steps: list[np.random.SeedSequence]
    path: np.random.SeedSequence
    retape: np.random.SeedSequence
    jitter: np.random.SeedSequence
    shutter: np.random.SeedSequence

    @classmethod
    def of(cls, seed: int, steps: int) -> _SweepSeeds:
        children = np.random.SeedSequence(seed).spawn(steps + 5)
        surface, *step_seeds, path = children[:steps + 2]
        retape, jitter, shutter = children[steps + 2:]
        return cls(surface, step_seeds, path, retape, jitter, shutter)


@dataclass(frozen=True)
class _SweepJob:
    """What every step of a sweep renders with: the resolved options, the output folder, the
    board, the sensor, the generators of the zoom jitter and the rolling shutter shared by all
    views, and the progress callback."""

    opts: SweepOptions
    out: Path
    target: Target
    sensor: Sensor
    jitter: np.random.Generator
    shutter: np.random.Generator
    progress: Callable[[int], None] | None


def _render_sweep_view(job: _SweepJob, name: str, j: int, cam: CameraModel, pose: tuple,
                       rng: np.random.Generator, surface: BoardSurface | None
                       ) -> tuple[dict, float]:
    """Render and write one view of a step; its ``truth.json`` entry and its PSF sigma (px)."""
    effects, (R, t) = job.opts.effects, pose
    scale = float(np.exp(job.jitter.normal(0.0, effects.zoom_jitter)))
    seen = cam if scale == 1.0 else replace(cam, fx=cam.fx * scale, fy=cam.fy * scale)
    mapping, turn = camera_mapping(seen), np.zeros(3)
    if effects.rolling_shutter:
        turn[:2] = job.shutter.normal(0.0, effects.rolling_shutter, 2)
        mapping = RollingShutterMapping(mapping, turn, job.sensor.height_px)
    view = render_image(job.target, mapping, R, t, job.sensor, job.opts.optics,
                        job.opts.radiometry, rng, job.opts.supersample, surface=surface)
    image = view.image if effects.sharpen is None else sharpen_image(view.image,
                                                                     *effects.sharpen)
    file = write_image(job.out / name / f"view_{j:02d}", image, job.opts.jpeg_quality)
    if job.progress is not None:
        job.progress(1)
    return ({"file": f"{name}/{file.name}", **view.truth_dict(), "focal_scale": scale,
             "readout_turn": turn.tolist()}, float(view.sigma_px))


def _render_sweep_step(job: _SweepJob, i: int, cam: CameraModel, max_tilt: float,
                       surfaces: list[BoardSurface | None], seed: np.random.SeedSequence
                       ) -> dict:
    """Render and write step ``i``'s views; its ``truth.json`` entry."""
    rng = np.random.default_rng(seed)
    name = f"fx_{round(cam.fx):05d}"
    (job.out / name).mkdir(exist_ok=True)
    retape_at = job.opts.effects.retape_at
    session = int(retape_at is not None and i >= retape_at)
    view_docs = []
    poses = sweep_poses(job.target, cam, job.opts.views, max_tilt, rng, job.opts.fill)
    for j, pose in enumerate(poses):
        view_doc, sigma_px = _render_sweep_view(job, name, j, cam, pose, rng, surfaces[session])
        view_docs.append(view_doc)
    return {"step": name, "zoom": cam.fx, "K": cam.K.tolist(), "dist": cam.dist.tolist(),
            "camera": cam.to_dict(), "max_tilt_deg": float(max_tilt),
            "board_session": session, "psf_sigma_px": sigma_px, "views": view_docs}


def _sweep_truth(opts: SweepOptions, sensor: Sensor, surfaces: list[BoardSurface | None],
                 path_record: dict, steps: list[dict]) -> dict:
    """What ``truth.json`` holds but the timings (module docstring)."""
    surface = surfaces[0]
    return {
        "format": "zoomcalib-sweep-truth", "zoomcalib_version": __version__,
        "pattern": opts.pattern, "sensor": asdict(sensor), "seed": opts.seed,
        "fx_range": [float(v) for v in opts.fx_range], "fill": opts.fill,
        "tilt_deg": list(opts.tilt_deg),
        "optics": asdict(opts.optics), "radiometry": asdict(opts.radiometry),
        "supersample": opts.supersample, "jpeg_quality": opts.jpeg_quality,
        "board_surface": None if surface is None else surface.to_dict(),
        "board_surfaces": [None if b is None else b.to_dict() for b in surfaces],
        "effects": asdict(opts.effects),
        "pp_path": path_record,
        "distortion": opts.camera.distortion_record(opts.distortion_source),
        "convention": "pixels: OpenCV (centre of top-left pixel = (0, 0)); zoom = fx, px; "
                      "rvec/tvec: board -> camera, mm; points_px: true image position of every "
                      "object point on the (waving) board",
        "steps": steps,
    }


def render_zoom_sweep(out: str | Path, options: SweepOptions | None = None, *,
                      progress: Callable[[int], None] | None = None, **fields) -> dict:
    """Render a zoom sweep (layout and conventions in the module docstring).

    Parameters
    ----------
    out : path
        Output folder; what an earlier render wrote there is removed first
        (:func:`~zoomcalib.render.dataset.clear_previous_render`).
    options : SweepOptions, optional
        What to render (default: its defaults); ``fields``, keywords named as its fields or as
        those of its ``camera`` (:class:`SweepCameraOptions`), replace them
        (``steps=3, pp_path="traced"``).
    progress : callable, optional
        Called with 1 after each written view.

    Returns
    -------
    truth : dict
        What was written to ``truth.json``.
    """
    t_start, cpu_start = time.perf_counter(), time.process_time()
    opts = _sweep_options(options, fields)
    sensor = Sensor(int(opts.size[0]), int(opts.size[1]), opts.pixel_pitch_mm)
    check_jpeg_quality(opts.jpeg_quality, np.uint8 if opts.radiometry.bits <= 8 else np.uint16)
    target = parse_pattern(opts.pattern)
    seeds = _SweepSeeds.of(opts.seed, opts.steps)
    retape_at = opts.effects.retape_at
    if retape_at is not None and retape_at >= opts.steps:
        raise ValueError(f"retape_at {retape_at}: the sweep has {opts.steps} steps")
    jitter = np.random.default_rng(seeds.jitter)
    shutter = np.random.default_rng(seeds.shutter)
    if opts.camera.pp_seed is None:
        opts = replace(opts, camera=replace(opts.camera, pp_seed=seeds.path))
    cameras = sweep_cameras(opts.fx_range, opts.steps, sensor, opts.camera)
    *_, path_record = opts.camera.path(opts.fx_range, opts.steps)
    surfaces = _board_surfaces(opts.board_surface, target.extent_mm, retape_at is not None,
                               seeds.surface, seeds.retape)
    out = Path(out)
    clear_previous_render(out)
    out.mkdir(parents=True, exist_ok=True)
    job = _SweepJob(opts, out, target, sensor, jitter, shutter, progress)
    max_tilt = np.geomspace(opts.tilt_deg[0], opts.tilt_deg[1], opts.steps)
    doc_steps = [_render_sweep_step(job, i, cam, max_tilt[i], surfaces, seeds.steps[i])
                 for i, cam in enumerate(cameras)]
    session_column = len(surfaces) > 1
    rows = [{"step": st["step"], "zoom": st["zoom"], "sequence": i}
            | ({"session": f"board{st['board_session'] + 1}"} if session_column else {})
            for i, st in enumerate(doc_steps)]
    write_csv(out / "steps.csv", rows, ["step", "zoom", "sequence"]
              + (["session"] if session_column else []))
    doc = _sweep_truth(opts, sensor, surfaces, path_record, doc_steps)
    doc["render_s"] = time.perf_counter() - t_start
    doc["render_cpu_s"] = time.process_time() - cpu_start
    write_json(out / "truth.json", doc)
    return doc
