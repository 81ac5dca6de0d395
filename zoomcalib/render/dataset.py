"""Multi-view, multi-zoom calibration data sets rendered through the (perturbed) zoom lens.

Poses
-----
For each zoom step the target is scaled so that, at the working distance, it spans ``fill`` of the
image height (the paper uses smaller targets at long focal lengths). Views put the board centre on
a spread of image positions (a jittered 3 x 3 lattice, then random) with tilts of 15-45 degrees
about random in-plane axes, and are kept only when every object point lies inside the image with a
margin, so views cover the whole image.

Layout written by :func:`render_dataset`::

    OUT/steps.csv                 step, zoom, direction, sequence, efl_mm
    OUT/dataset.json              lens, sensor, tolerances, seed, optics, radiometry, and per step:
                                  zoom, efl_mm, camera (fitted), misalignment, target spec,
                                  per view: file, rvec, tvec (board -> camera, mm), points_px
    OUT/zoom_XX/view_YY.png       (view_YY.jpg with a JPEG quality)

With a :class:`~zoomcalib.render.image.BoardSurface` the board waves: the images show it and
``points_px`` are the projections of the object points lifted onto it (``dataset.json`` records
the surface under ``board_surface``). JPEG compression changes the images only, not the truth.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from .. import __version__
from ..camera import DEFAULT_SENSOR, Sensor
from ..io import read_json, write_csv, write_json
from ..optics.lens_camera import exact_mapping, tilted_sensor
from ..optics.mechanics import Tolerances, draw_misalignment
from ..optics.misalignment import Misalignment
from ..optics.prescription import Prescription
from ..targets import Target, parse_pattern
from .image import (
    BoardSurface,
    Optics,
    Radiometry,
    camera_mapping,
    project_points,
    psf_sigma_px,
    render_image,
)

__all__ = ["RenderOptions", "check_render_inputs", "clear_previous_render", "generate_poses",
           "render_dataset", "scaled_target_for_view", "psf_limit_px", "write_image",
           "MAX_PSF_FRACTION", "MIN_PSF_LIMIT_PX"]


def write_image(path: str | Path, image: np.ndarray, jpeg_quality: int | None = None) -> Path:
    """Write ``image`` as PNG (``jpeg_quality`` None) or as JPEG of that quality (1-100).

    ``path`` is taken without its suffix; the written file (``.png`` or ``.jpg``) is returned.

    Raises
    ------
    ValueError
        A quality outside 1-100, or a JPEG of an image that is not 8-bit.
    """
    path = Path(path)
    if jpeg_quality is None:
        out = path.with_suffix(".png")
        ok, data = cv2.imencode(".png", image)
    else:
        check_jpeg_quality(jpeg_quality, image.dtype)
        out = path.with_suffix(".jpg")
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError(f"{out}: the image could not be encoded")
    out.write_bytes(data.tobytes())
    return out


def check_jpeg_quality(jpeg_quality: int | None, dtype=np.uint8) -> None:
    """Raise ``ValueError`` unless ``jpeg_quality`` is None or an integer 1-100 for 8-bit data."""
    if jpeg_quality is None:
        return
    if int(jpeg_quality) != jpeg_quality or not 1 <= jpeg_quality <= 100:
        raise ValueError(f"JPEG quality must be an integer from 1 to 100, got {jpeg_quality!r}")
    if np.dtype(dtype) != np.uint8:
        raise ValueError(f"JPEG holds 8-bit images only, not {np.dtype(dtype)}; use PNG "
                         "(no JPEG quality) for 12 or 16 bits")


def scaled_target_for_view(target: Target, fy_px: float, sensor: Sensor,
                           distance_mm: float, fill: float = 0.55) -> Target:
    """Scale ``target`` so its point grid spans ``fill`` of the image height at ``distance_mm``."""
    span = np.ptp(target.object_points[:, 1]) or np.ptp(target.object_points[:, 0])
    want = fill * sensor.height_px * distance_mm / fy_px
    return target.scaled(want / span)


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, dtype=float).reshape(3, 1))[0]


def generate_poses(target: Target, mapping, sensor: Sensor, n_views: int, distance_mm: float,
                   rng: np.random.Generator, margin_px: float = 12.0,
                   tilt_deg: tuple[float, float] = (15.0, 45.0),
                   max_tries: int = 4000) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses ``Rt_cam_board = (R, t)`` for a calibration set.

    Returns
    -------
    poses : list of ((3, 3) ndarray, (3,) ndarray)
    """
    centre = target.object_points.mean(axis=0)
    lattice = [(a, b) for b in (0.3, 0.5, 0.7) for a in (0.3, 0.5, 0.7)]
    poses = []
    for _ in range(max_tries):
        if len(poses) == n_views:
            break
        k = len(poses)
        if k < len(lattice):
            fu, fv = np.array(lattice[k]) + rng.uniform(-0.08, 0.08, 2)
        else:
            fu, fv = rng.uniform(0.25, 0.75, 2)
        tilt = np.deg2rad(rng.uniform(*tilt_deg))
        phi = rng.uniform(0, 2 * np.pi)
        R = _rotation(tilt * np.array([np.cos(phi), np.sin(phi), 0.0]))
        R = R @ _rotation([0, 0, rng.uniform(-0.3, 0.3)])
        xy = mapping.unproject(np.array([[fu * (sensor.width_px - 1),
                                          fv * (sensor.height_px - 1)]]))[0]
        dist = distance_mm * rng.uniform(0.9, 1.15)
        t = dist * np.array([xy[0], xy[1], 1.0]) / np.sqrt(1 + xy @ xy) - R @ centre
        pts = project_points(target.object_points, mapping, R, t)
        corners = np.array([[target.extent_mm[0], target.extent_mm[1], 0],
                            [target.extent_mm[2], target.extent_mm[3], 0]]) @ R.T + t
        if np.any(corners[:, 2] <= 0):
            continue
        if (np.all(pts > margin_px) and np.all(pts[:, 0] < sensor.width_px - 1 - margin_px)
                and np.all(pts[:, 1] < sensor.height_px - 1 - margin_px)):
            poses.append((R, t))
    if len(poses) < n_views:
        raise RuntimeError(f"found only {len(poses)} of {n_views} poses that keep the target in "
                           f"view with a {margin_px:g} px margin on a {sensor.width_px}x"
                           f"{sensor.height_px} px sensor")
    return poses


MAX_PSF_FRACTION = 0.01
"""Largest PSF sigma, as a fraction of the image's shorter side (but at least
``MIN_PSF_LIMIT_PX``). Beyond it the renderer's time and memory grow with the blur's reach (the
measured cost is in ``docs/notes/commands-examples.md``) while the corners it renders are too
soft to calibrate."""

MIN_PSF_LIMIT_PX = 3.0
"""The PSF sigma limit of small images, px (cheap to render at any image size)."""


def psf_limit_px(sensor: Sensor) -> float:
    """Largest PSF sigma the renderer accepts for ``sensor``, px."""
    return max(MIN_PSF_LIMIT_PX, MAX_PSF_FRACTION * min(sensor.width_px, sensor.height_px))


def check_render_inputs(optics: Optics, sensor: Sensor, n_views: int) -> None:
    """Refuse inputs that cannot give a data set, before any work.

    Raises
    ------
    ValueError
        One line naming the quantity and the limit: a non-finite optics value, an empty sensor,
        no views, or a PSF sigma (blur, diffraction and defocus combined, px) above
        :func:`psf_limit_px`.
    """
    if sensor.width_px < 1 or sensor.height_px < 1:
        raise ValueError(f"sensor {sensor.width_px}x{sensor.height_px} px has no pixels")
    if n_views < 1:
        raise ValueError(f"{n_views} views: at least one is needed")
    values = {"blur_px": optics.blur_px, "defocus_mm": optics.defocus_mm,
              "f_number": optics.f_number, "wavelength_um": optics.wavelength_um}
    for name, value in values.items():
        if not np.isfinite(value):
            raise ValueError(f"optics {name} is {value}, not a finite number")
    sigma = psf_sigma_px(optics, sensor.pixel_pitch_mm)
    limit = psf_limit_px(sensor)
    if sigma > limit:
        raise ValueError(f"PSF sigma {sigma:.1f} px (blur {optics.blur_px:g} px, defocus "
                         f"{optics.defocus_mm:g} mm at f/{optics.f_number:g}) exceeds the "
                         f"limit of {limit:.1f} px for a {sensor.width_px}x{sensor.height_px} "
                         f"image ({MAX_PSF_FRACTION:.0%} of its shorter side, at least "
                         f"{MIN_PSF_LIMIT_PX:g} px)")


def clear_previous_render(out: Path) -> list[Path]:
    """Remove what an earlier ``render`` or ``render-sweep`` wrote in ``out``: the images its
    ``dataset.json`` or ``truth.json`` lists, that file and ``steps.csv``; step folders left
    empty go too. Other files are never touched, so a new render never sits beside an older
    one's extra views.

    Returns
    -------
    list of Path
        The files removed.
    """
    removed = []
    root = out.resolve()
    for name in ("dataset.json", "truth.json"):
        doc_path = out / name
        try:
            doc = read_json(doc_path) if doc_path.is_file() else None
        except ValueError:
            doc = None
        steps = doc.get("steps", []) if isinstance(doc, dict) else []
        files = [out / str(v.get("file", "")) for st in steps if isinstance(st, dict)
                 for v in st.get("views", []) if isinstance(v, dict)]
        for f in [*files, doc_path, out / "steps.csv"]:
            if f.is_file() and f.resolve().is_relative_to(root):
                f.unlink()
                removed.append(f)
        for folder in {f.parent for f in files}:
            if folder != out and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
    return removed


def _axis_tilted(em, lens, zoom, axis_tilt_mrad, keystone: bool):
    """``em`` on a sensor tilted by ``axis_tilt_mrad`` against the lens axis: the image moved
    by ``(fx theta_x, fy theta_y)`` px and, with ``keystone``, the tilted sensor's keystone
    (:class:`~zoomcalib.optics.lens_camera.TiltedSensorMapping`)."""
    if axis_tilt_mrad is None:
        return em
    return tilted_sensor(em, lens, zoom, 1e-3 * np.asarray(axis_tilt_mrad, float), keystone)


@dataclass(frozen=True)
class RenderOptions:
    """How :func:`render_dataset` renders a data set.

    Attributes
    ----------
    optics : Optics, optional
        What sets the blur (default ``Optics()``).
    radiometry : Radiometry, optional
        Signal, noise and quantisation (default ``Radiometry()``).
    seed : int
        Seed of every draw: mechanical errors, poses, board waves and noise.
    sensor : Sensor
        Image size (px) and pixel pitch (mm).
    distance_mm : float
        Working distance of the views, mm (each view's is 0.9-1.15 times it).
    fill : float
        Fraction of the image height the scaled target's point grid spans at ``distance_mm``.
    through : {'exact', 'model'}
        Render through the exact ray-traced mapping, or through the fitted OpenCV model only.
    supersample : int
        Sub-samples per pixel side where the supersampled renderer is used.
    direction : {'random', 'in', 'out'} or sequence of 'in' / 'out', one per step
        Direction of the last zoom move before each step (sets the backlash side); a sequence
        is written to ``steps.csv``.
    board_surface : BoardSurface or float, optional
        The board's waves (board frame of every step's scaled target, mm), or an amplitude (mm):
        each step then draws its own :meth:`BoardSurface.random` over its scaled target,
        recorded in the step's ``board_surface``. None: flat.
    jpeg_quality : int, optional
        Write JPEG files of this quality (1-100, 8-bit images only) instead of PNG.
    axis_tilt_mrad : (float, float), optional
        The lens's optical axis tilted against the sensor normal by ``(theta_x, theta_y)`` mrad
        (the lens turned about its rear nodal point): the image moves by
        ``(fx theta_x, fy theta_y)`` px at every zoom (the step's ``camera`` carries the moved
        principal point) and the tilted sensor adds its keystone, from the exit pupil's
        distance (:class:`~zoomcalib.optics.lens_camera.TiltedSensorMapping`).
    axis_tilt_keystone : bool
        False renders the axis tilt as the image shift alone, without the keystone.
    """

    optics: Optics | None = None
    radiometry: Radiometry | None = None
    seed: int = 0
    sensor: Sensor = DEFAULT_SENSOR
    distance_mm: float = 2000.0
    fill: float = 0.55
    through: str = "exact"
    supersample: int = 4
    direction: str | Sequence[str] = "random"
    board_surface: BoardSurface | float | None = None
    jpeg_quality: int | None = None
    axis_tilt_mrad: tuple[float, float] | None = None
    axis_tilt_keystone: bool = True

    def direction_of(self, step: int) -> str:
        """The direction column of step ``step`` in ``steps.csv`` (empty when random)."""
        if self.direction == "random":
            return ""
        return self.direction if isinstance(self.direction, str) else self.direction[step]


@dataclass(frozen=True)
class _StepPlan:
    """One step's generator, misalignment, exact mapping, the mapping rendered through, the
    target scaled for it and its poses."""

    rng: np.random.Generator
    misalignment: Misalignment
    exact: object
    mapping: object
    target: Target
    poses: list


def _plan_step(lens: Prescription, z: float, mis: Misalignment, rng: np.random.Generator,
               base: Target, n_views: int, opts: RenderOptions) -> _StepPlan:
    """The step's mapping and poses; ValueError naming the zoom when no ``n_views`` poses keep
    the target in view."""
    sensor = opts.sensor
    em = _axis_tilted(exact_mapping(lens, z, mis, sensor), lens, z, opts.axis_tilt_mrad,
                      opts.axis_tilt_keystone)
    mapping = em if opts.through == "exact" else camera_mapping(em.camera)
    target = scaled_target_for_view(base, em.camera.fy, sensor, opts.distance_mm, opts.fill)
    try:
        poses = generate_poses(target, mapping, sensor, n_views, opts.distance_mm, rng)
    except RuntimeError as exc:
        raise ValueError(f"zoom {z:g}: {exc}") from None
    return _StepPlan(rng, mis, em, mapping, target, poses)


def _step_surface(board_surface: BoardSurface | float | None, plan: _StepPlan,
                  seed: np.random.SeedSequence) -> BoardSurface | None:
    """The step's board: the surface given, or one drawn at the given amplitude (mm) over the
    step's scaled target."""
    if isinstance(board_surface, int | float):
        return BoardSurface.random(plan.target.extent_mm, float(board_surface),
                                   np.random.default_rng(seed))
    return board_surface


def _render_step(out: Path, name: str, z: float, plan: _StepPlan, lens: Prescription,
                 surface: BoardSurface | None, opts: RenderOptions,
                 progress: Callable[[int], None] | None) -> dict:
    """Render and write one step's views; its ``dataset.json`` entry. ``opts`` carries the
    optics and radiometry resolved."""
    (out / name).mkdir(exist_ok=True)
    views, view = [], None
    for j, (R, t) in enumerate(plan.poses):
        view = render_image(plan.target, plan.mapping, R, t, opts.sensor, opts.optics,
                            opts.radiometry, plan.rng, opts.supersample, surface=surface)
        fname = write_image(out / name / f"view_{j:02d}", view.image, opts.jpeg_quality).name
        views.append({"file": f"{name}/{fname}", **view.truth_dict()})
        if progress is not None:
            progress(1)
    em, mis = plan.exact, plan.misalignment
    return {
        "step": name, "zoom": float(z), "efl_mm": em.lens_camera.efl_mm,
        "camera": em.camera.to_dict(), "principal_point_px": em.lens_camera.principal_point_px,
        "model_fit_rms_px": em.lens_camera.fit_rms_px,
        "decenter_mm": mis.decenter, "tilt_rad": mis.tilt, "groups": list(lens.group_names),
        "target": plan.target.spec, "psf_sigma_px": views and float(view.sigma_px),
        "board_surface": None if surface is None else surface.to_dict(),
        "views": views,
    }


def _step_misalignments(lens: Prescription, tolerances: Tolerances | None, zoom: list[float],
                        seed: np.random.SeedSequence, direction) -> list[Misalignment]:
    """Each step's draw of the mechanical errors (one per step); all zero without
    ``tolerances``."""
    n_groups = len(lens.groups)
    if tolerances is not None:
        draws = draw_misalignment(lens, tolerances, zoom, 1, seed, direction)
    else:
        draws = Misalignment(np.zeros((len(zoom), 1, n_groups, 2)),
                             np.zeros((len(zoom), 1, n_groups, 2)))
    return [Misalignment(draws.decenter[i, 0], draws.tilt[i, 0]) for i in range(len(zoom))]


def _dataset_doc(lens: Prescription, tolerances: Tolerances | None, pattern: str,
                 opts: RenderOptions, steps: list[dict]) -> dict:
    """What ``dataset.json`` holds (module docstring)."""
    board_surface, tilt = opts.board_surface, opts.axis_tilt_mrad
    return {
        "zoomcalib_version": __version__, "lens": lens.name, "pattern": pattern,
        "sensor": asdict(opts.sensor), "seed": opts.seed, "through": opts.through,
        "axis_tilt_mrad": None if tilt is None else [float(v) for v in tilt],
        "axis_tilt_keystone": bool(opts.axis_tilt_keystone) if tilt is not None else None,
        "tolerances": None if tolerances is None else tolerances.to_dict(),
        "optics": asdict(opts.optics), "radiometry": asdict(opts.radiometry),
        "distance_mm": opts.distance_mm, "fill": opts.fill, "supersample": opts.supersample,
        "board_surface": (board_surface.to_dict() if isinstance(board_surface, BoardSurface)
                          else None if board_surface is None
                          else {"random_amplitude_mm": float(board_surface)}),
        "jpeg_quality": opts.jpeg_quality,
        "convention": "pixels: OpenCV (centre of top-left pixel = (0, 0)); rvec/tvec: board -> "
                      "camera, mm; points_px: true image position of every target object point",
        "steps": steps,
    }


def render_dataset(lens: Prescription, tolerances: Tolerances | None, out: str | Path,
                   zoom: list[float], n_views: int, pattern: str,
                   options: RenderOptions | None = None, *,
                   progress: Callable[[int], None] | None = None, **fields) -> dict:
    """Render a multi-zoom calibration data set (layout in the module docstring).

    Parameters
    ----------
    lens : Prescription
    tolerances : Tolerances or None
        Mechanical errors; each zoom step gets one draw (locked errors, backlash for a random
        approach direction, play). None renders the nominal lens.
    out : path
        Output folder; what an earlier render wrote there is removed first
        (:func:`clear_previous_render`).
    zoom : list of float
        Zoom state of each step, in [0, 1].
    n_views : int
        Views per step.
    pattern : str
        Target spec, e.g. ``chessboard:9x6:25`` (scaled per step to fill the view).
    options : RenderOptions, optional
        How to render (default: its defaults); ``fields``, keywords named as its fields,
        replace them (``seed=3, jpeg_quality=90``).
    progress : callable, optional
        Called with 1 after each written view.

    Returns
    -------
    dataset : dict
        What was written to ``dataset.json``.

    Raises
    ------
    ValueError
        Before any file is written: inputs refused by :func:`check_render_inputs`, or a step
        for which ``n_views`` poses keeping the target in view cannot be found.
    """
    opts = replace(options or RenderOptions(), **fields)
    opts = replace(opts, optics=opts.optics or Optics(),
                   radiometry=opts.radiometry or Radiometry())
    check_jpeg_quality(opts.jpeg_quality, np.uint8 if opts.radiometry.bits <= 8 else np.uint16)
    check_render_inputs(opts.optics, opts.sensor, n_views)
    out = Path(out)
    base = parse_pattern(pattern)
    ss = np.random.SeedSequence(opts.seed)
    mech_seed, *step_seeds = ss.spawn(len(zoom) + 1)
    surface_seeds = ss.spawn(len(zoom))
    misalignments = _step_misalignments(lens, tolerances, zoom, mech_seed, opts.direction)
    # Every step's mapping and poses first: a step whose poses cannot be found stops the run
    # before any file is written. Each step keeps its own generator, so the images do not
    # depend on this order.
    plans = [_plan_step(lens, z, misalignments[i], np.random.default_rng(step_seeds[i]), base,
                        n_views, opts)
             for i, z in enumerate(zoom)]
    clear_previous_render(out)
    out.mkdir(parents=True, exist_ok=True)
    steps, rows = [], []
    for i, (z, plan) in enumerate(zip(zoom, plans, strict=True)):
        name = f"zoom_{i:02d}"
        surface = _step_surface(opts.board_surface, plan, surface_seeds[i])
        steps.append(_render_step(out, name, z, plan, lens, surface, opts, progress))
        rows.append({"step": name, "zoom": float(z), "direction": opts.direction_of(i),
                     "sequence": i, "efl_mm": plan.exact.lens_camera.efl_mm})
    write_csv(out / "steps.csv", rows, ["step", "zoom", "direction", "sequence", "efl_mm"])
    doc = _dataset_doc(lens, tolerances, pattern, opts, steps)
    write_json(out / "dataset.json", doc)
    return doc
