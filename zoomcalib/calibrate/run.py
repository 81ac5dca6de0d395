"""The ``calibrate`` job: detect, calibrate every zoom step with every backend, model the zoom.

For ``DIR`` (a flat image folder, or one subfolder per zoom step, see
:func:`zoomcalib.calibrate.stepfolders.zoom_steps`) it writes to ``OUT``:

- ``detections/<stem>.json`` — the detections of each step (the detections contract), with
  the images' sizes and BLAKE2b hashes and the detection settings; a rerun reuses the
  detections of the images whose content and settings are unchanged (and says so), so an
  interrupted run resumes with the images it had finished. ``<stem>`` is the step name, made
  safe and given a hash of the exact name when it had to be changed
  (:func:`zoomcalib.calibrate.guards.step_file_stems`);
- ``calibration.json`` and ``calibration.yml`` — per step and backend;
- ``zoom_calibration.csv`` — one row per step, all from one backend, named in its ``backend``
  and ``mode`` columns: the zoom-wide adjustment (:mod:`zoomcalib.calibrate.zoomwide`, the
  default for a zoom set), else the bundle when it calibrated every step, else OpenCV;
- ``zoom_model.json`` — the intrinsics versus zoom (for the zoom-wide table: its own posterior
  carried between the steps by its prior, :mod:`zoomcalib.calibrate.zoompath`; else curves
  fitted to the table) with their held-out interpolation error
  (four or more steps with known zoom);
- ``opencv/``, ``ros/``, ``mrcal/`` and ``zoom_model_grid.csv`` — the results in the formats
  of other tools (:mod:`zoomcalib.calibrate.export`);
- figures: ``principal_point_path.png``, ``focal_length.png`` and ``residuals_<stem>.png``;
- ``report.html`` — every step's and the zoom range's figures in one page
  (:mod:`zoomcalib.calibrate.report`), unless ``report=False``;
- ``manifest.json`` — the files this run wrote, the command and the inputs. A run first
  removes the files an earlier run left (listed in its manifest, or named as this job names
  its files), so the folder never mixes two runs.

The table, ``meta``, the zoom model, the figures and the manifest are written by
:mod:`zoomcalib.calibrate.outputs`; the capture sessions and the residual budget come from
:mod:`zoomcalib.calibrate.zoomset`.

A step whose detection or calibration fails is reported and skipped (:attr:`CalibrateRun.dropped`);
the others are kept. An image of another size than most of its step is left out and named.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..detect import detection_pool, image_files
from ..pool import stop_pool
from ..targets import Target, parse_pattern
from ..zoom.model import ZoomModelLike
from .advice import advise
from .export import write_exports
from .guards import (
    byte_identical,
    clear_previous_outputs,
    detect_with_cache,
    detection_settings,
    keep_majority_size,
    step_file_stems,
)
from .opencv_backend import (
    FRONTO_PARALLEL_DEG,
    calibrate_opencv_robust,
    fix_flags,
    observations_from_detections,
)
from .outputs import run_meta, table_rows, write_figures, write_results, write_run_manifest
from .result import CalibrationResult, Observations, residual_vectors
from .scatter import pooled_over_steps
from .status import StepStatus, sensor_aspect, step_status
from .stepfolders import ignored_top_images, zoom_steps
from .zoomset import capture_sessions, log_sittings, residual_budgets, zoom_wide_step_notes

__all__ = ["CalibrateOptions", "CalibrateRun", "calibrate_folder", "residual_vectors",
           "step_file_stems", "BACKENDS"]

BACKENDS = ("opencv", "bundle")


@dataclass
class CalibrateRun:
    """What a calibrate run produced.

    ``dropped`` lists the steps that gave no calibration, ``backend_failures`` the backends
    that failed on a step that another backend calibrated; either makes the run
    :attr:`partial`. ``reused`` counts, per step, the images whose cached detections were
    reused; ``left_out`` names, per step, the images of another size than the step's;
    ``copies`` maps, per step, each byte-identical copy of an earlier image to that image
    (used once);
    ``ignored`` the images next to step subfolders; ``table_backend`` the backend of each
    step's row in ``zoom_calibration.csv`` and figures; ``stems`` the steps' file-name stems;
    ``skipped_images`` the one-line errors of the images whose detection failed or found no
    whole target, per step (only the first make the run partial);
    ``zoom_source`` where each step's zoom came from (``zoom_steps``' ``zoom_source``);
    ``status`` each step's :class:`~zoomcalib.calibrate.status.StepStatus` (``ok``,
    ``imprecise``, ``unusable``, with reasons and remedies); ``budget`` and
    ``budget_sessions`` the residual budget per step and per capture session (when asked);
    ``flags`` per step the full texts of its flags, ``flag_records`` the same as
    :class:`~zoomcalib.calibrate.checks.Flag` records (severity, few words, one action), the
    most severe first (:func:`set_step_flags`); ``step_dirs`` each step's image folder;
    ``fixed`` the intrinsics held (names of :data:`~zoomcalib.calibrate.opencv_backend.
    FIXABLE`) and ``fix_flags`` OpenCV's flags for them in the per-step fits;
    ``not_written`` the requested outputs that could not be written (``report.html``,
    ``step S exports``, ...; the reason is in ``failures`` or the log), which make the run
    :attr:`partial`.
    """

    results: dict[str, dict[str, CalibrationResult]] = field(default_factory=dict)
    observations: dict[str, Observations] = field(default_factory=dict)
    zoom: dict[str, float | None] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    zoom_model: ZoomModelLike | None = None
    holdout: dict | None = None
    dropped: list[str] = field(default_factory=list)
    backend_failures: dict[str, list[str]] = field(default_factory=dict)
    reused: dict[str, int] = field(default_factory=dict)
    left_out: dict[str, list[str]] = field(default_factory=dict)
    copies: dict[str, dict[str, str]] = field(default_factory=dict)
    ignored: list[str] = field(default_factory=list)
    table_backend: dict[str, str] = field(default_factory=dict)
    stems: dict[str, str] = field(default_factory=dict)
    zoom_wide: object | None = None
    cross_validation: object | None = None
    flags: dict[str, list[str]] = field(default_factory=dict)
    flag_records: dict[str, list] = field(default_factory=dict)
    step_dirs: dict[str, Path] = field(default_factory=dict)
    fixed: tuple[str, ...] = ()
    fix_flags: int = 0
    skipped_images: dict[str, list[str]] = field(default_factory=dict)
    zoom_source: dict[str, str | None] = field(default_factory=dict)
    status: dict[str, StepStatus] = field(default_factory=dict)
    budget: dict = field(default_factory=dict)
    budget_sessions: dict = field(default_factory=dict)
    not_written: list[str] = field(default_factory=list)

    @property
    def partial(self) -> bool:
        """True when a step was dropped, a backend failed on a step or an output was not
        written."""
        return bool(self.dropped or self.backend_failures or self.not_written)

    def partial_message(self) -> str:
        """One line saying what is missing ('' when the run is complete)."""
        parts = []
        if self.dropped:
            parts.append("steps dropped: " + ", ".join(self.dropped))
        if self.backend_failures:
            parts.append("backends failed: " + "; ".join(
                f"{', '.join(b)} on {s}" for s, b in self.backend_failures.items()))
        if self.not_written:
            parts.append("not written: " + ", ".join(self.not_written))
        return "partial result (" + "; ".join(parts) + ")" if parts else ""


def _calibrate_once(backend: str, obs: Observations, model: str, flags: int = 0
                    ) -> CalibrationResult:
    if backend == "opencv":  # near-fronto-parallel views (a zoom's long end): several starts
        return calibrate_opencv_robust(obs, model=model, flags=flags,
                                       fronto_parallel_deg=FRONTO_PARALLEL_DEG)
    if flags:
        raise ValueError(f"the {backend} backend estimates every intrinsic; --fix is for "
                         "--backend opencv")
    if backend == "bundle":
        from .bundle import calibrate_bundle

        return calibrate_bundle(obs, model=model)
    raise ValueError(f"unknown backend {backend!r}; use one of {BACKENDS}")


def correct_dot_centres(obs: Observations, result: CalibrationResult, radius: float
                        ) -> tuple[Observations, float]:
    """Dot detections moved from the imaged ellipses' centres to the images of the circles'
    centres, with the camera and poses of ``result``
    (:func:`zoomcalib.detect.dots.dot_centre_bias`: perspective and distortion together).

    Returns
    -------
    obs : Observations
    largest : float
        Largest correction, px.
    """
    from ..camera import CameraModel
    from ..detect.dots import dot_centre_bias

    cam = CameraModel(result.fx, result.fy, result.cx, result.cy, np.asarray(result.dist))
    obj = obs.object_points if result.object_points is None else result.object_points
    views, largest = [], 0.0
    for (ids, pts), r, t in zip(obs.views, result.rvecs, result.tvecs, strict=True):
        R = cv2.Rodrigues(np.asarray(r, float).reshape(3, 1))[0]
        bias = dot_centre_bias(cam.project_normalized, R, np.asarray(t, float), obj[ids],
                               radius)
        largest = max(largest, float(np.abs(bias).max(initial=0.0)))
        views.append((ids, pts - bias))
    return Observations(obs.object_points, views, obs.image_size, obs.names), largest


def _calibrate(backend: str, obs: Observations, model: str,
               target: Target | None = None, flags: int = 0) -> CalibrationResult:
    """Calibrate (OpenCV ``flags`` holding intrinsics fixed, :data:`~zoomcalib.calibrate.
    opencv_backend.FIXABLE`); for dot targets, iterate the dot-centre correction with the
    calibration (three rounds: the correction changes by far less than the noise after the
    second)."""
    res = _calibrate_once(backend, obs, model, flags)
    if target is None or not len(target.discs):
        return res
    raw = obs
    for _ in range(3):
        corrected, largest = correct_dot_centres(raw, res, float(target.discs[0, 2]))
        res = _calibrate_once(backend, corrected, model, flags)
    res.info["dot_centre_correction_max_px"] = largest
    return res


@dataclass(frozen=True)
class CalibrateOptions:
    """What the calibrate job does beyond detecting and calibrating each step
    (:func:`calibrate_folder`); every field's default is the CLI's.

    Attributes
    ----------
    model : {'standard', 'rational'}
    method : str, optional
        Detection method (default: the target's usual one).
    zoom_wide : bool
        For a zoom set of 2 or more steps, also calibrate all steps together
        (:func:`zoomcalib.calibrate.zoomwide.calibrate_zoom_wide`; with ``model`` standard the
        rational model only where a step's held-out views choose it, with rational at every
        step); its
        results (backend ``"zoom-wide"``) make the zoom table. ``backends`` still run per step.
    cross_validate : bool
        Calibrate the even and the odd images of every step apart, as the table's backend did,
        and compare (:func:`zoomcalib.calibrate.checks.cross_validate`).
    pp_model : {'angle2', 'prior2', 'select'}
        How the zoom-wide adjustment ties cx, cy across zoom (``pp_model`` of
        :func:`zoomcalib.calibrate.zoomwide.calibrate_zoom_wide`).
    grid_points : int
        Zoom values of ``zoom_model_grid.csv`` (:mod:`zoomcalib.calibrate.export`).
    camera_name : str, optional
        ``camera_name`` of the ROS files; default the image folder's name, with characters
        other than ``[A-Za-z0-9_]`` replaced by ``_``.
    report : bool
        Write ``report.html`` (:func:`zoomcalib.calibrate.report.write_report`).
    report_distance : float, optional
        Distance (mm) of the report's projection-uncertainty maps; default each step's median
        board distance.
    report_images : tuple of str
        Images whose corners the report draws beside each step's image of the largest error
        (``NAME`` or ``STEP/NAME``; :func:`~zoomcalib.calibrate.report.write_report`).
    residual_budget : bool
        Also the residual budget of every usable step and capture session
        (:mod:`zoomcalib.calibrate.budget`; ``run.budget``, ``run.budget_sessions`` and
        ``calibration.json``'s ``meta.residual_budget``).
    board_shape : {'print', 'points', 'modes'}
        The zoom-wide adjustment's board: height modes to degree 4 per capture session, a
        height for every point and the print's in-plane modes where their test says they pay
        (``print``, the default); without the print's (``points``); or the height modes alone
        (``modes``; ``board_points`` and ``print_shape`` of
        :func:`zoomcalib.calibrate.zoomwide.calibrate_zoom_wide`).
    fixed : tuple of str
        Intrinsics the per-step OpenCV fits and the zoom-wide adjustment hold (keys of
        :data:`~zoomcalib.calibrate.opencv_backend.FIXABLE`: the principal point at the image
        centre, the aspect ratio at 1, k1, k2, k3 or the tangential terms at 0). Not with the
        bundle backend (ValueError).
    """

    model: str = "standard"
    method: str | None = None
    zoom_wide: bool = True
    cross_validate: bool = False
    pp_model: str = "angle2"
    grid_points: int = 50
    camera_name: str | None = None
    report: bool = True
    report_distance: float | None = None
    report_images: tuple[str, ...] = ()
    residual_budget: bool = False
    board_shape: str = "print"
    fixed: tuple[str, ...] = ()


def calibrate_folder(folder: str | Path, pattern: str, out: str | Path,
                     backends: tuple[str, ...] = BACKENDS,
                     options: CalibrateOptions | None = None, *, workers: int = 1,
                     progress: Callable[[int], None] | None = None,
                     log: Callable[[str], None] = print, **fields) -> CalibrateRun:
    """Run the calibrate job (see the module docstring).

    Parameters
    ----------
    folder : path
        Image folder, or folder of step subfolders.
    pattern : str
        Target spec, e.g. ``chessboard:9x6:25``.
    backends : tuple of {'opencv', 'bundle'}
    options : CalibrateOptions, optional
        What else the job does (default: the CLI's defaults); ``fields``, keywords named as
        its fields, replace them (``zoom_wide=False, report=False``).
    workers : int
        Processes for detection and for the zoom-wide adjustment's per-step OpenCV fits.
    progress : callable, optional
        Called with the number of images done: each detected or reused, and the byte-identical
        copies left out.
    log : callable
        Receives one-line messages (skipped images and steps).

    Returns
    -------
    CalibrateRun
    """
    opts = replace(options or CalibrateOptions(), **fields)
    target: Target = parse_pattern(pattern)
    from .zoomwide import board_options

    board_options(opts.board_shape)  # an unknown board model is refused before any detection
    out = Path(out)
    steps = zoom_steps(folder)
    run = CalibrateRun(stems=step_file_stems(s[0] for s in steps), fixed=tuple(opts.fixed),
                       fix_flags=fix_flags(opts.fixed))
    if opts.fixed and set(backends) - {"opencv"}:
        raise ValueError(f"fixed {', '.join(opts.fixed)}: the bundle estimates every intrinsic; "
                         "the OpenCV backend and the zoom-wide adjustment hold them "
                         "(--backend opencv)")
    every_file = {step: image_files(step_dir) for step, step_dir, _, _ in steps}
    run.step_dirs = {step: Path(step_dir) for step, step_dir, _, _ in steps}
    _start_output_folder(out, run, every_file)
    step_files = {step: _without_copies(step, files, run, log)
                  for step, files in every_file.items()}
    copies = sum(len(every_file[s]) - len(f) for s, f in step_files.items())
    if copies and progress is not None:  # counted as done: the bar's length is every file
        progress(copies)
    _report_ignored(folder, run, log)
    settings = detection_settings(target, opts.method)
    provenance: dict[str, dict] = {}
    how = _Detecting(out, target, settings, workers, progress, log, provenance)
    extras_of = _each_step(run, steps, step_files, how, backends, opts)
    _pool_view_scatter(run, backends)
    log_sittings(run, log)
    # the capture sessions go to the table's session column either way; the zoom-wide
    # adjustment also gives each its own board shape
    capture = capture_sessions(run, extras_of, log if opts.zoom_wide else (lambda message: None))
    sessions = capture if opts.zoom_wide else {}
    if opts.zoom_wide and len(run.observations) >= 2:
        directions = {s: e.get("direction") or "" for s, e in extras_of.items()}
        _zoom_wide(run, opts.model, target, log, directions, opts.pp_model, sessions, workers,
                   opts.board_shape)
    _drop_uncalibrated(run)
    run.table_backend = _table_backends(run, log)
    if opts.cross_validate and run.results:
        run.cross_validation = _cross_validate(run, opts.model, target, opts.pp_model,
                                               sessions, workers, opts.board_shape)
    set_step_flags(run)
    run.status = _step_statuses(run)
    _log_unusable(run, log)
    if opts.residual_budget and run.results:
        residual_budgets(run, sessions, workers, log)
    rows = table_rows(run, extras_of, capture)

    call = {"pattern": pattern, "backends": list(backends), "model": opts.model,
            "method": opts.method, "fixed": list(opts.fixed), "detection_settings": settings}
    zoom_set = not (len(steps) == 1 and steps[0][0] == ".")
    write_results(run, out, run_meta(run, {"folder": str(folder)} | call, provenance),
                  rows if zoom_set else [], log)
    if run.results:
        run.files += write_exports(out, run, opts.camera_name or _camera_name(folder),
                                   opts.grid_points, log)
        run.files += write_figures(run, out, zoom_set, workers)
    if opts.report and run.results:
        _report(run, out, opts.report_distance, opts.report_images, log)
    run.files.append(write_run_manifest(out, run, folder, steps, provenance, call))
    return run


def _each_step(run: CalibrateRun, steps: list, step_files: dict[str, list[Path]],
               how: _Detecting, backends: tuple[str, ...], opts: CalibrateOptions
               ) -> dict[str, dict]:
    """Detect (or reuse the detections of) each step's images and calibrate the step on its
    own, filling ``run``; returns each kept step's extras (``zoom_steps``). A step without
    observations is skipped; one no backend calibrated is dropped unless the zoom-wide
    adjustment is to calibrate it. One pool of detection workers serves every step (started
    at the first image to detect), stopped at once on any exception (Ctrl-C)."""
    extras_of: dict[str, dict] = {}
    target, log, workers = how.target, how.log, how.workers
    pool = detection_pool(workers) if workers > 1 and len(steps) > 1 else None
    how.pool = pool
    try:
        for step, _, zoom, extras in steps:
            dets = _step_detections(how, step, step_files[step], run)
            obs = _step_observations(step, dets, target, run, log, step_files[step],
                                     opts.method)
            if obs is None:
                continue
            run.observations[step] = obs
            run.zoom[step] = zoom
            run.zoom_source[step] = extras.get("zoom_source")
            if extras.get("zoom_note"):
                log(f"step {step}: {extras['zoom_note']}"
                    + ("; its zoom is unknown" if zoom is None else ""))
            step_results = _calibrate_step(step, obs, backends, opts.model, target, run, log)
            if not step_results and not opts.zoom_wide:
                run.backend_failures.pop(step, None)
                run.dropped.append(step)
                continue
            run.results[step] = step_results  # empty: left to the zoom-wide adjustment
            extras_of[step] = extras
    except BaseException:
        if pool is not None:
            stop_pool(pool)
        raise
    if pool is not None:
        pool.shutdown()
    return extras_of


# ----------------------------------------------------------------------------------------------
# helpers of calibrate_folder: detection cache, image sizes, output folder, table backend


def _step_observations(step: str, dets: list, target: Target, run: CalibrateRun,
                       log: Callable[[str], None], files: Sequence[Path] = (),
                       method: str | None = None) -> Observations | None:
    """The step's detections as observations: images of another size left out, failed images
    named in ``run.skipped_images``; None (the step dropped, with the reason and, for a
    chessboard found in none of its images, a count that does find it) when nothing is
    left."""
    dets = _same_size_images(step, dets, run, log)
    if dets is None:
        return None
    for d in dets:
        if d.error and getattr(d, "no_target", False):
            # a frame whose board runs off the image is normal: said, not a failure
            log(f"step {step}: left aside {d.error} (no whole target in view: a frame whose "
                "board runs off the image or is hidden)")
            run.skipped_images.setdefault(step, []).append(d.error)
        elif d.error:
            log(f"step {step}: skipped {d.error}")
            run.skipped_images.setdefault(step, []).append(d.error)
    good = [d for d in dets if d.error is None]
    if not good:
        hint = _corner_count_hint(target, files, method)
        _drop(run, step, "no image with a detected target" + (f"; {hint}" if hint else ""),
              log)
        return None
    try:
        return observations_from_detections(good, target, good[0].image_size)
    except ValueError as exc:
        _drop(run, step, str(exc), log)
        return None


def _corner_count_hint(target: Target, files: Sequence[Path], method: str | None,
                       tries: int = 3) -> str | None:
    """For a chessboard found in no image: the first of ``(cols-1, rows-1)``, ``(cols-1,
    rows)``, ``(cols, rows-1)`` found in one of the first ``tries`` images (a spec that counted
    squares instead of inner corners), said as a suggestion; None when none is found."""
    if target.kind != "chessboard" or not files:
        return None
    from ..detect.opencv import detect_image
    from ..targets import chessboard

    cols, rows = target.pattern_size
    for c, r in ((cols - 1, rows - 1), (cols - 1, rows), (cols, rows - 1)):
        if min(c, r) < 2:
            continue
        other = chessboard(c, r, target.pitch_mm)
        for f in list(files)[:tries]:
            if detect_image(f, other, method).error is None:
                return (f"chessboard:{c}x{r}:{target.pitch_mm:g} is found in {f.name}: count "
                        "the inner corners (where four squares meet), not the squares")
    return None


def _calibrate_step(step: str, obs: Observations, backends: Sequence[str], model: str,
                    target: Target, run: CalibrateRun, log: Callable[[str], None]
                    ) -> dict[str, CalibrationResult]:
    """Every per-step backend's calibration of one step; a backend that fails is logged and
    recorded in ``run`` (the others' results stay)."""
    results = {}
    for backend in backends:
        try:
            results[backend] = _calibrate(backend, obs, model, target, run.fix_flags)
        except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error) as exc:
            msg = " ".join(str(exc).split())
            run.failures.append(f"step {step}: backend {backend} failed: {msg}")
            log(run.failures[-1])
            run.backend_failures.setdefault(step, []).append(backend)
    return results


def _camera_name(folder: str | Path) -> str:
    """The image folder's name made a ROS camera name (``[A-Za-z0-9_]``)."""
    return re.sub(r"[^A-Za-z0-9_]", "_", Path(folder).resolve().name) or "camera"


def _drop(run: CalibrateRun, step: str, why: str, log: Callable[[str], None]) -> None:
    run.failures.append(f"step {step}: {why}")
    run.dropped.append(step)
    log(run.failures[-1])


def _start_output_folder(out: Path, run: CalibrateRun, step_files: dict[str, list[Path]]
                         ) -> None:
    """Remove an earlier run's files from ``out`` (keeping this run's steps' detection
    caches, which are keyed on the images), and make ``out/detections``."""
    keep = [f"detections/{run.stems[s]}.json" for s in step_files]
    inputs = [f for files in step_files.values() for f in files]
    clear_previous_outputs(out, keep, inputs)
    (out / "detections").mkdir(parents=True, exist_ok=True)


def _report_ignored(folder: str | Path, run: CalibrateRun, log: Callable[[str], None]) -> None:
    stray = ignored_top_images(folder)
    if stray:
        run.ignored = [p.name for p in stray]
        log(f"{folder}: ignored {len(stray)} image{'s' if len(stray) > 1 else ''} next to the "
            f"step subfolders ({', '.join(run.ignored)}); only the subfolders are calibrated")


def _without_copies(step: str, files: list[Path], run: CalibrateRun,
                    log: Callable[[str], None]) -> list[Path]:
    """``files`` without the byte-identical copies of an earlier image (one view, not two);
    each copy is logged and recorded in ``run.copies``."""
    copies = byte_identical(files)
    if copies:
        run.copies[step] = {f.name: kept.name for f, kept in copies.items()}
        log(f"step {step}: " + "; ".join(f"{f.name} is a byte-identical copy of {kept.name}"
                                         for f, kept in copies.items())
            + ": used once")
    return [f for f in files if f not in copies]


@dataclass
class _Detecting:
    """How a run detects: its output folder (``out/detections`` caches them), the target and
    its detection settings, the processes (``pool``, else ``workers`` new ones), the progress
    callback, the log, and per step where its detections came from (``provenance``)."""

    out: Path
    target: Target
    settings: dict
    workers: int
    progress: Callable[[int], None] | None
    log: Callable[[str], None]
    provenance: dict = field(default_factory=dict)
    pool: object | None = None


def _step_detections(how: _Detecting, step: str, files: list[Path], run: CalibrateRun):
    """The step's detections, from the cache for unchanged images (the others detected by
    ``how.pool``, else ``how.workers`` new processes); records and logs reuse."""
    out, log = how.out, how.log
    cache = out / "detections" / f"{run.stems[step]}.json"
    dets, reused, prints = detect_with_cache(cache, files, how.target, how.settings,
                                             how.workers, how.progress, how.pool)
    how.provenance[step] = {"file": cache.relative_to(out).as_posix(), "reused": reused,
                            "detected": len(files) - reused, "images": prints}
    if reused:
        run.reused[step] = reused
        fresh = len(files) - reused
        log(f"step {step}: reused the cached detections of {reused} unchanged image"
            f"{'s' if reused > 1 else ''} ({cache})"
            + (f"; detected {fresh} new or changed" if fresh else ""))
    steep = sum(d.steep_edges for d in dets)
    if steep:
        log(f"step {step}: {steep} of {len(dets)} images have edges steeper than any blur makes "
            "(a camera that sharpens): their corners were fitted at a 0.5 px blur")
    sharpened = [d.sharpening for d in dets if getattr(d, "sharpening", None) is not None]
    if sharpened:
        amount, radius = np.median([s[1] for s in sharpened]), np.median([s[2] for s in sharpened])
        log(f"step {step}: {len(sharpened)} of {len(dets)} images are sharpened by the camera "
            f"(an unsharp mask of amount {amount:.2f} at {radius:.2f} px, median): their "
            "corners were fitted with it")
    return dets


def _same_size_images(step: str, dets: list, run: CalibrateRun, log: Callable[[str], None]):
    """The detections of the images of the step's majority size; the others are named and
    left out. None (the step dropped) when no size has a majority."""
    try:
        kept, odd, size = keep_majority_size(dets)
    except ValueError as exc:
        _drop(run, step, str(exc), log)
        return None
    if odd:
        run.left_out[step] = [d.file for d in odd]
        names = ", ".join(f"{d.file} ({d.image_size[0]}x{d.image_size[1]})" for d in odd)
        log(f"step {step}: left out {names}: not the step's image size {size[0]}x{size[1]} "
            f"({len(kept)} of {len(dets)} images)")
    return kept


def _pool_view_scatter(run: CalibrateRun, backends: Sequence[str]) -> None:
    """Each per-step backend's view-scatter checks, tested together over the steps
    (:func:`~zoomcalib.calibrate.scatter.pooled_over_steps`)."""
    for backend in backends:
        pooled = pooled_over_steps({s: r[backend] for s, r in run.results.items()
                                    if backend in r})
        for step, res in pooled.items():
            run.results[step][backend] = res


def _zoom_wide(run: CalibrateRun, model: str, target: Target, log: Callable[[str], None],
               directions: dict[str, str], pp_model: str = "angle2",
               sessions: dict[str, str] | None = None, workers: int = 1,
               board_shape: str = "print") -> None:
    """The zoom-wide adjustment of every calibrated step, added to ``run.results`` as backend
    ``"zoom-wide"`` (the steps reached zooming in and out are separate chains of its prior);
    a failure is logged and recorded (the per-step results stay)."""
    from .zoomwide import board_options, calibrate_zoom_wide

    obs = dict(run.observations)
    if len(target.discs):  # dot centres: corrected with each step's own calibration first
        radius = float(target.discs[0, 2])
        obs = {s: correct_dot_centres(o, next(iter(run.results[s].values())), radius)[0]
               if run.results.get(s) else o for s, o in obs.items()}
    try:
        zw = calibrate_zoom_wide(obs, chains=directions, pp_model=pp_model, sessions=sessions,
                                 workers=workers, fixed=run.fixed, model=model,
                                 **board_options(board_shape))
    except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error) as exc:
        msg = " ".join(str(exc).split())
        run.failures.append(f"zoom-wide adjustment failed: {msg}")
        run.backend_failures.setdefault("all steps", []).append("zoom-wide")
        log(run.failures[-1])
        return
    if not zw.converged:
        log(f"zoom-wide adjustment did not converge ({zw.stop_reason}); its rows are marked")
    if zw.print_test is not None:
        log(f"zoom-wide: {zw.print_test.summary()}")
    for step, why in zw.skipped.items():
        run.failures.append(f"step {step}: left out of the zoom-wide adjustment: {why}")
        log(run.failures[-1])
    for step, res in zw.results.items():
        for note in zoom_wide_step_notes(res.info):
            log(f"zoom-wide: step {step}: {note}")
        run.results[step]["zoom-wide"] = res
        # a per-step backend that failed here is reported, but the step's result is complete
        run.backend_failures.pop(step, None)
    run.zoom_wide = zw


def _cross_validate(run: CalibrateRun, model: str, target: Target, pp_model: str = "angle2",
                    sessions: dict[str, str] | None = None, workers: int = 1,
                    board_shape: str = "print"):
    """Two-halves check with the backend (and mode) of the zoom table (zoom-wide: with the
    board sessions of the full set)."""
    from .checks import cross_validate

    backend = next(iter(run.table_backend.values()))
    if backend == "zoom-wide":
        from .zoomwide import board_options, calibrate_zoom_wide

        return cross_validate(run.observations,
                              lambda o: calibrate_zoom_wide(o, pp_model=pp_model,
                                                            sessions=sessions,
                                                            fixed=run.fixed, model=model,
                                                            workers=workers,
                                                            **board_options(board_shape)
                                                            ).results,
                              backend)

    def per_step(obs: dict[str, Observations]) -> dict[str, CalibrationResult]:
        out = {}
        for step, o in obs.items():
            try:
                out[step] = _calibrate(run.table_backend[step], o, model, target,
                                       run.fix_flags)
            except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error):
                continue
        return out
    return cross_validate({s: run.observations[s] for s in run.results}, per_step, backend,
                          pool=True)


def set_step_flags(run: CalibrateRun) -> None:
    """Per step, why its table row is not to be trusted (conditioning and cross-validation):
    ``run.flag_records`` (:class:`~zoomcalib.calibrate.checks.Flag`, the most severe first) and
    ``run.flags`` (their full texts)."""
    from .checks import Z_LIMIT, Flag, by_severity, step_flags

    records = {}
    for step in run.results:
        res = run.results[step][run.table_backend[step]]
        reasons = step_flags(res, run.observations[step].image_size)
        cv = run.cross_validation
        if cv is not None and step in cv.z:
            bad = [f"{q} {z:+.1f}" for q, z in cv.z[step].items() if not abs(z) <= Z_LIMIT]
            proj = cv.projection.get(step, {}).get("z_rms", 0.0)
            if proj > Z_LIMIT:
                bad.append(f"projection {proj:.1f}")
            if bad:
                reasons.append(Flag("halves", "warning", f"halves disagree: z {bad[0]}",
                                    "halves disagree (z: " + ", ".join(bad) + ")"))
        if cv is not None and step in cv.failures:
            reasons.append(Flag("halves_failed", "note", "halves not calibrated",
                                f"halves not calibrated: {cv.failures[step]}"))
        if reasons:
            records[step] = by_severity(reasons)
    run.flag_records = records
    run.flags = {s: [f.detail for f in fl] for s, fl in records.items()}


def _step_statuses(run: CalibrateRun) -> dict[str, StepStatus]:
    """Each calibrated step's status (:func:`~zoomcalib.calibrate.status.step_status`): the
    sensor's aspect ratio from every table row, and for zoom-wide rows the step's own per-step
    OpenCV result as the reference a joint shift is measured against; a step that is not
    ``ok`` gets its capture advice (:func:`~zoomcalib.calibrate.advice.advise`)."""
    table = {s: run.results[s][run.table_backend[s]] for s in run.results}
    aspect = sensor_aspect(table) if len(table) > 1 else None
    cv = run.cross_validation
    out = {}
    for step, res in table.items():
        own = run.results[step].get("opencv") if res.backend == "zoom-wide" else None
        halves = None
        if cv is not None and step in cv.z:
            halves = dict(cv.z[step])
            if "z_rms" in cv.projection.get(step, {}):
                halves["projection"] = cv.projection[step]["z_rms"]
        out[step] = step_status(res, run.observations[step].image_size, aspect, own, halves)
        if out[step].status != "ok" and res.fx > 0:
            advice = advise(res, run.observations[step])
            out[step].advice = None if advice is None else advice.to_dict()
    return out


def _table_backends(run: CalibrateRun, log: Callable[[str], None]) -> dict[str, str]:
    """The backend of each step's table row and figures: one backend for every step, the
    zoom-wide adjustment when it ran, else the bundle when it calibrated every step, else
    OpenCV when it did; only when none did do the rows mix (each step's bundle result, else
    OpenCV's), which is logged."""
    steps = list(run.results)
    if steps and all("zoom-wide" in run.results[s] for s in steps):
        return {s: "zoom-wide" for s in steps}
    for backend in ("bundle", "opencv"):
        if steps and all(backend in run.results[s] for s in steps):
            if backend == "opencv" and any("bundle" in run.results[s] for s in steps):
                failed = [s for s in steps if "bundle" not in run.results[s]]
                log(f"the bundle failed on step{'s' if len(failed) > 1 else ''} "
                    f"{', '.join(failed)}: the zoom table and figures use opencv for every "
                    "step (the bundle's results stay in calibration.json)")
            return {s: backend for s in steps}
    chosen = {s: "bundle" if "bundle" in run.results[s] else next(iter(run.results[s]))
              for s in steps}
    if len(set(chosen.values())) > 1:
        log("the zoom table mixes backends (no backend calibrated every step): "
            + ", ".join(f"{s} {b}" for s, b in chosen.items()))
    return chosen


def _report(run: CalibrateRun, out: Path, distance: float | None, images: tuple[str, ...],
            log: Callable[[str], None]) -> None:
    """Write ``report.html``; a failure is logged in one line (the other outputs stand), and
    so is a chosen image no step has."""
    from .report import chosen_views, write_report

    for name in chosen_views(run, images)[1]:
        run.not_written.append(f"report image {name}")
        log(f"report image {name}: no calibrated step has a view of that name")
    try:
        run.files.append(write_report(run, out, distance, images))
    except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error, OSError) as exc:
        run.not_written.append("report.html")
        log(f"{out / 'report.html'}: not written: {' '.join(str(exc).split())}")


def _drop_uncalibrated(run: CalibrateRun) -> None:
    """Steps that neither a backend nor the zoom-wide adjustment calibrated leave the results
    and are listed as dropped."""
    for step in [s for s, r in run.results.items() if not r]:
        del run.results[step]
        run.backend_failures.pop(step, None)
        run.dropped.append(step)


def _log_unusable(run: CalibrateRun, log: Callable[[str], None]) -> None:
    for step, st in run.status.items():
        if not st.usable:
            log(f"step {step}: unusable ({'; '.join(st.reasons)}): kept in the table and "
                "calibration.json with its status, not exported and not in the zoom model")



