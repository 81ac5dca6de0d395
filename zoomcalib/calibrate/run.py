"""The ``calibrate`` job: detect, calibrate every zoom step with every backend, model the zoom.

For ``DIR`` (a flat image folder, or one subfolder per zoom step, see
:func:`zoomcalib.calibrate.io.zoom_steps`) it writes to ``OUT``:

- ``detections/<step>.json`` — the detections of each step (the detections contract); a rerun
  reuses them when the step's image list is unchanged, so an interrupted run resumes with the
  steps it had finished;
- ``calibration.json`` and ``calibration.yml`` — per step and backend;
- ``zoom_calibration.csv`` — one row per step (the bundle's values where it ran, else OpenCV's);
- ``zoom_model.json`` — smooth fits versus zoom with their held-out interpolation error
  (four or more steps with known zoom);
- figures: ``principal_point_path.png``, ``focal_length.png`` and ``residuals_<step>.png``.

A step whose detection or calibration fails is reported and skipped; the others are kept.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..detect import detect_folder, image_files, read_detections, write_detections
from ..targets import Target, parse_pattern
from .io import write_calibration, write_zoom_table, zoom_steps
from .opencv_backend import calibrate_opencv, observations_from_detections
from .result import DIST_NAMES, CalibrationResult, Observations

__all__ = ["CalibrateRun", "calibrate_folder", "residual_vectors", "BACKENDS"]

BACKENDS = ("opencv", "bundle")


@dataclass
class CalibrateRun:
    """What a calibrate run produced."""

    results: dict[str, dict[str, CalibrationResult]] = field(default_factory=dict)
    observations: dict[str, Observations] = field(default_factory=dict)
    zoom: dict[str, float | None] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    zoom_model: object | None = None
    holdout: dict | None = None


def _safe(step: str) -> str:
    return "root" if step == "." else re.sub(r"[^A-Za-z0-9_.-]", "_", step)


def _cached_detections(cache: Path, files: list[Path], pattern: str):
    """Detections from ``cache`` when it was made for the same pattern and images."""
    if not cache.exists():
        return None
    try:
        spec, dets = read_detections(cache)
    except (ValueError, OSError):
        return None
    if spec != pattern or [d.file for d in dets] != [f.name for f in files]:
        return None
    return dets


def residual_vectors(result: CalibrationResult, obs: Observations) -> list[np.ndarray]:
    """Per view, ``(k, 2)`` reprojection residuals (projected minus observed), px."""
    obj = obs.object_points if result.object_points is None else result.object_points
    out = []
    for (ids, pts), r, t in zip(obs.views, result.rvecs, result.tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj[ids].astype(np.float64), np.asarray(r, float),
                                    np.asarray(t, float), result.K, result.dist)
        out.append(proj.reshape(-1, 2) - pts)
    return out


def _calibrate_once(backend: str, obs: Observations, model: str) -> CalibrationResult:
    if backend == "opencv":
        return calibrate_opencv(obs, model=model)
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
               target: Target | None = None) -> CalibrationResult:
    """Calibrate; for dot targets, iterate the dot-centre correction with the calibration
    (three rounds: the correction changes by far less than the noise after the second)."""
    res = _calibrate_once(backend, obs, model)
    if target is None or not len(target.discs):
        return res
    raw = obs
    for _ in range(3):
        corrected, largest = correct_dot_centres(raw, res, float(target.discs[0, 2]))
        res = _calibrate_once(backend, corrected, model)
    res.info["dot_centre_correction_max_px"] = largest
    return res


def _table_row(step: str, zoom: float | None, extras: dict, res: CalibrationResult) -> dict:
    row = {"step": step, "zoom": np.nan if zoom is None else zoom, "fx": res.fx, "fy": res.fy,
           "cx": res.cx, "cy": res.cy}
    for k in ("fx", "fy", "cx", "cy"):
        row[f"sd_{k}"] = res.sd.get(k, np.nan)
    for i, name in enumerate(DIST_NAMES[:5]):
        row[name] = float(res.dist[i]) if i < len(res.dist) else 0.0
    row["rms_px"] = res.rms_px
    row["n_views"] = len(res.per_view_rms_px)
    for k in ("direction", "sequence", "focus", "temperature"):
        if extras.get(k) not in (None, ""):
            row[k] = extras[k]
    return row


def calibrate_folder(folder: str | Path, pattern: str, out: str | Path,
                     backends: tuple[str, ...] = BACKENDS, model: str = "standard",
                     method: str | None = None, workers: int = 1,
                     progress: Callable[[int], None] | None = None,
                     log: Callable[[str], None] = print) -> CalibrateRun:
    """Run the calibrate job (see the module docstring).

    Parameters
    ----------
    folder : path
        Image folder, or folder of step subfolders.
    pattern : str
        Target spec, e.g. ``chessboard:9x6:25``.
    backends : tuple of {'opencv', 'bundle'}
    model : {'standard', 'rational'}
    method : str, optional
        Detection method (default: the target's usual one).
    workers : int
        Detection processes.
    progress : callable, optional
        Called with 1 per image detected.
    log : callable
        Receives one-line messages (skipped images and steps).

    Returns
    -------
    CalibrateRun
    """
    target: Target = parse_pattern(pattern)
    out = Path(out)
    (out / "detections").mkdir(parents=True, exist_ok=True)
    run = CalibrateRun()
    steps = zoom_steps(folder)
    rows = []
    for step, step_dir, zoom, extras in steps:
        files = image_files(step_dir)
        cache = out / "detections" / f"{_safe(step)}.json"
        dets = _cached_detections(cache, files, pattern)
        if dets is None:
            dets = detect_folder(files, target, method, workers=workers, progress=progress)
            write_detections(cache, dets, pattern)
        elif progress is not None:
            progress(len(files))
        for d in dets:
            if d.error:
                log(f"step {step}: skipped {d.error}")
        good = [d for d in dets if d.error is None]
        if not good:
            run.failures.append(f"step {step}: no image with a detected target")
            log(run.failures[-1])
            continue
        try:
            obs = observations_from_detections(good, target, good[0].image_size)
        except ValueError as exc:
            run.failures.append(f"step {step}: {exc}")
            log(run.failures[-1])
            continue
        run.observations[step] = obs
        run.zoom[step] = zoom
        step_results = {}
        for backend in backends:
            try:
                step_results[backend] = _calibrate(backend, obs, model, target)
            except (ValueError, RuntimeError, np.linalg.LinAlgError, cv2.error) as exc:
                msg = " ".join(str(exc).split())
                run.failures.append(f"step {step}: backend {backend} failed: {msg}")
                log(run.failures[-1])
        if not step_results:
            continue
        run.results[step] = step_results
        best = step_results.get("bundle") or step_results["opencv"]
        rows.append(_table_row(step, zoom, extras, best))

    meta = {"folder": str(folder), "pattern": pattern, "model": model, "backends": list(backends),
            "method": method, "failures": run.failures}
    if run.results:
        run.files += list(write_calibration(out, run.results, meta))
    zoom_set = not (len(steps) == 1 and steps[0][0] == ".")
    if zoom_set and rows:
        run.files.append(write_zoom_table(out / "zoom_calibration.csv", rows))
        known = [r for r in rows if np.isfinite(r["zoom"])]
        if len(known) >= 4:
            from ..zoom import ZoomModel

            try:
                run.zoom_model = ZoomModel.from_table(known)
                run.holdout = run.zoom_model.holdout_error()
                doc = {"model": run.zoom_model.to_dict(),
                       "holdout_rms": {k: float(v) for k, v in run.holdout.items()}}
                path = out / "zoom_model.json"
                path.write_text(json.dumps(doc, indent=1))
                run.files.append(path)
            except (ValueError, np.linalg.LinAlgError) as exc:
                run.failures.append(f"zoom model: {exc}")
                log(run.failures[-1])
    if run.results:
        run.files += _figures(run, out, zoom_set)
    return run


def _figures(run: CalibrateRun, out: Path, zoom_set: bool) -> list[Path]:
    from ..plots import (
        plot_focal_length,
        plot_principal_point_spiral,
        plot_residuals,
    )

    files = []
    steps = list(run.results)
    best = {s: run.results[s].get("bundle") or run.results[s]["opencv"] for s in steps}
    if zoom_set and len(steps) > 1:
        zoom = np.array([run.zoom[s] if run.zoom[s] is not None else i
                         for i, s in enumerate(steps)], dtype=float)
        zmin, zmax = zoom.min(), zoom.max()
        zn = (zoom - zmin) / (zmax - zmin) if zmax > zmin else np.zeros_like(zoom)
        mean = np.array([[best[s].cx, best[s].cy] for s in steps])
        sd = np.array([[best[s].sd.get("cx", 0.0), best[s].sd.get("cy", 0.0)] for s in steps])
        files.append(plot_principal_point_spiral(
            zn, mean, sd, out / "principal_point_path.png",
            title="Calibrated principal point across zoom (1-sigma ellipses)"))
        f = np.array([[best[s].fx, best[s].sd.get("fx", 0.0)] for s in steps])
        files.append(plot_focal_length(zoom, f[:, 0], f[:, 1], out / "focal_length.png",
                                       run.zoom_model))
    for s in steps:
        obs = run.observations[s]
        res = residual_vectors(best[s], obs)
        pts = [p for _, p in obs.views]
        files.append(plot_residuals(pts, res, obs.image_size,
                                    out / f"residuals_{_safe(s)}.png",
                                    title=f"step {s}: {best[s].backend}, rms "
                                          f"{best[s].rms_px:.3f} px"))
    return files
