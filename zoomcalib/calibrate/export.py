"""Calibration results in the formats of other tools (docs/conventions.md, "File contracts").

Conventions: pixels in OpenCV's convention (centre of the top-left pixel = (0, 0)); distortion
in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``, 5 terms (standard model) or 8
(rational); 1-sigma uncertainties. The ``calibrate`` job writes, in ``OUT``:

``opencv/<stem>_<backend>.yml``
    One ``cv::FileStorage`` YAML per step and backend, with the names of OpenCV's calibration
    sample (``image_width``, ``image_height``, ``camera_matrix`` 3x3, ``distortion_coefficients``
    Nx1, ``avg_reprojection_error``, ``nr_of_frames``, ``per_view_reprojection_errors``) and
    ours: ``step``, ``zoom`` (absent when unknown), ``backend``, ``mode``, ``lens_model``,
    ``sigmas`` (1-sigma by parameter name), ``sd_kind``, ``converged`` (0/1) and
    ``quality_flags`` (the reasons the step's zoom-table row is flagged; empty when none);
    the zoom table's backend's file also ``status`` (``ok``, ``imprecise``, ``unusable``:
    :mod:`zoomcalib.calibrate.status`), ``status_reasons`` and ``status_remedies``.
``ros/<stem>.yaml`` and ``ros/camera_info_index.yaml``
    One ROS ``camera_info`` calibration YAML per step (the zoom table's backend), as
    ``camera_calibration_parsers`` reads them: ``camera_name``, ``image_width``,
    ``image_height``, ``camera_matrix`` (K), ``distortion_model`` (``plumb_bob`` for 5 terms,
    ``rational_polynomial`` for 8), ``distortion_coefficients`` (D), ``rectification_matrix``
    (R = I, a monocular camera) and ``projection_matrix`` (P = [K | 0]: the rectified image
    keeps the camera's intrinsics); matrices as ``{rows, cols, data}``, data row-major. The
    index lists the files sorted by zoom (``steps: [{zoom, step, file, status}, ...]``; steps
    of unknown zoom last, with ``zoom: null``). An ``unusable`` step has no file
    (``file: null``) and its ``reasons``; the other files say their status in a comment.
``mrcal/<stem>.cameramodel``
    One mrcal camera model per usable step (the zoom table's backend): a Python-literal dict with
    ``#`` comments, ``lensmodel`` ``LENSMODEL_OPENCV5`` or ``LENSMODEL_OPENCV8``, ``intrinsics``
    ``[fx, fy, cx, cy, k1, k2, p1, p2, k3(, k4, k5, k6)]``, ``extrinsics`` at identity
    (``rt_fromref`` = 0: the camera is the reference frame) and ``imagersize`` ``[w, h]``.
``zoom_model_grid.csv``
    The zoom model (:class:`zoomcalib.zoom.ZoomModel`) evaluated on an even grid over the
    calibrated zoom range: columns ``zoom``, the fitted parameters, then their ``sd_`` 1-sigma.

``<stem>`` is the step's file-name stem (:func:`zoomcalib.calibrate.guards.step_file_stems`).
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import yaml

from .io import _atomic_write, _fmt
from .result import CalibrationResult

if TYPE_CHECKING:
    from ..zoom.model import ZoomModelLike
    from .run import CalibrateRun

__all__ = [
    "ROS_DISTORTION_MODELS",
    "MRCAL_LENS_MODELS",
    "distortion_terms",
    "mrcal_model_text",
    "ros_camera_info",
    "write_exports",
    "write_mrcal_model",
    "write_opencv_yaml",
    "write_ros_camera_info",
    "write_ros_index",
    "write_zoom_model_grid",
]

#: ROS ``distortion_model`` by number of distortion terms.
ROS_DISTORTION_MODELS: dict[int, str] = {5: "plumb_bob", 8: "rational_polynomial"}
#: mrcal ``lensmodel`` by number of distortion terms.
MRCAL_LENS_MODELS: dict[int, str] = {5: "LENSMODEL_OPENCV5", 8: "LENSMODEL_OPENCV8"}
#: Name of the ROS index file in ``OUT/ros``.
ROS_INDEX = "camera_info_index.yaml"


def distortion_terms(dist: Sequence[float] | np.ndarray) -> np.ndarray:
    """The distortion vector as a flat float array of 5 or 8 terms (OpenCV order).

    Raises
    ------
    ValueError
        For any other number of terms, or non-finite values.
    """
    d = np.asarray(dist, np.float64).ravel()
    if len(d) not in ROS_DISTORTION_MODELS:
        raise ValueError(f"{len(d)} distortion terms; the exports know 5 (k1, k2, p1, p2, k3) "
                         "or 8 (k1..k6, p1, p2)")
    if not np.all(np.isfinite(d)):
        raise ValueError("distortion terms must be finite")
    return d


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", text) or "_"


# ----------------------------------------------------------------------------------------------
# OpenCV FileStorage


def write_opencv_yaml(path: str | os.PathLike, res: CalibrationResult,
                      image_size: tuple[int, int], step: str, zoom: float | None = None,
                      quality_flags: Sequence[str] = (), status=None) -> Path:
    """Write one result as an OpenCV FileStorage YAML with the calibration sample's names.

    Parameters
    ----------
    path : path
        Ends in ``.yml`` or ``.yaml``; the folder must exist.
    res : CalibrationResult
    image_size : (int, int)
        (width, height), px.
    step : str
        The zoom step's name.
    zoom : float, optional
        Written as ``zoom`` when known.
    quality_flags : sequence of str
        Why the step's zoom-table row is not to be trusted.
    status : StepStatus, optional
        The step's status (:mod:`zoomcalib.calibrate.status`), written as ``status``,
        ``status_reasons`` and ``status_remedies`` (the zoom table's result only).

    Returns
    -------
    Path
        Written through a temporary name, so never left half written.
    """
    path = Path(path)
    dist = distortion_terms(res.dist)
    tmp = path.with_name(path.name + ".tmp.yml")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise OSError(f"{path}: cannot write")
    try:
        fs.write("image_width", int(image_size[0]))
        fs.write("image_height", int(image_size[1]))
        fs.write("camera_matrix", np.asarray(res.K, np.float64).reshape(3, 3))
        fs.write("distortion_coefficients", dist.reshape(-1, 1))
        fs.write("avg_reprojection_error", float(res.rms_px))
        per_view = np.asarray(res.per_view_rms_px, np.float64).reshape(-1, 1)
        fs.write("nr_of_frames", int(len(per_view)))
        if per_view.size:
            fs.write("per_view_reprojection_errors", per_view)
        _write_opencv_extras(fs, res, step, zoom, quality_flags, len(dist))
        if status is not None:
            _write_status(fs, status)
    finally:
        fs.release()
    os.replace(tmp, path)
    return path


def _write_opencv_extras(fs: cv2.FileStorage, res: CalibrationResult, step: str,
                         zoom: float | None, quality_flags: Sequence[str], n_dist: int) -> None:
    fs.write("step", str(step))
    if zoom is not None and np.isfinite(zoom):
        fs.write("zoom", float(zoom))
    fs.write("backend", str(res.backend))
    fs.write("mode", str(res.info.get("mode", "per-step")))
    fs.write("lens_model", "rational" if n_dist == 8 else "standard")
    fs.startWriteStruct("sigmas", cv2.FileNode_MAP)
    for name, v in res.sd.items():
        fs.write(_safe_name(str(name)), float(v))
    fs.endWriteStruct()
    fs.write("sd_kind", str(res.info.get("sd_kind", "")))
    fs.write("converged", int(res.converged))
    fs.startWriteStruct("quality_flags", cv2.FileNode_SEQ)
    for reason in quality_flags:
        fs.write("", str(reason))
    fs.endWriteStruct()


def _write_status(fs: cv2.FileStorage, status) -> None:
    fs.write("status", str(status.status))
    for key, lines in (("status_reasons", status.reasons), ("status_remedies", status.remedies)):
        fs.startWriteStruct(key, cv2.FileNode_SEQ)
        for line in lines:
            fs.write("", str(line))
        fs.endWriteStruct()


# ----------------------------------------------------------------------------------------------
# ROS camera_info


def _ros_matrix(a: np.ndarray) -> dict:
    a = np.atleast_2d(np.asarray(a, np.float64))
    return {"rows": int(a.shape[0]), "cols": int(a.shape[1]),
            "data": [float(v) for v in a.ravel()]}


def ros_camera_info(K: np.ndarray, dist: Sequence[float] | np.ndarray,
                    image_size: tuple[int, int], camera_name: str) -> dict:
    """The ROS calibration-file dict of a monocular camera (R = I, P = [K | 0]).

    Parameters
    ----------
    K : (3, 3) array_like
        px.
    dist : (5,) or (8,) array_like
        OpenCV order; 5 terms give ``plumb_bob``, 8 ``rational_polynomial``.
    image_size : (int, int)
        (width, height), px.
    camera_name : str

    Returns
    -------
    dict
        Keys in the order ``camera_calibration_parsers`` writes them.
    """
    K = np.asarray(K, np.float64).reshape(3, 3)
    d = distortion_terms(dist)
    return {"image_width": int(image_size[0]), "image_height": int(image_size[1]),
            "camera_name": str(camera_name), "camera_matrix": _ros_matrix(K),
            "distortion_model": ROS_DISTORTION_MODELS[len(d)],
            "distortion_coefficients": _ros_matrix(d.reshape(1, -1)),
            "rectification_matrix": _ros_matrix(np.eye(3)),
            "projection_matrix": _ros_matrix(np.hstack([K, np.zeros((3, 1))]))}


def _comment(lines: Sequence[str]) -> str:
    return "".join(f"# {line}\n" for line in lines)


def write_ros_camera_info(path: str | os.PathLike, info: Mapping,
                          notes: Sequence[str] = ()) -> Path:
    """Write a :func:`ros_camera_info` dict as YAML (flow-style data lists), with ``notes``
    as ``#`` comment lines on top (ROS readers ignore them)."""
    path = Path(path)
    body = yaml.safe_dump(dict(info), sort_keys=False, default_flow_style=None,
                          allow_unicode=True, width=1000)
    _atomic_write(path, _comment(notes) + body)
    return path


def write_ros_index(path: str | os.PathLike, camera_name: str,
                    entries: Sequence[Mapping]) -> Path:
    """Write ``ros/camera_info_index.yaml``: ``camera_name`` and ``steps``, the entries
    (``zoom`` (None when unknown), ``step``, ``file`` relative to the index, None for an
    unusable step, ``status``, and for an unusable step its ``reasons``) sorted by zoom,
    unknown zooms last."""
    ordered = sorted(entries, key=lambda e: (e["zoom"] is None, e["zoom"] or 0.0))
    doc = {"camera_name": str(camera_name),
           "steps": [{"zoom": None if e["zoom"] is None else float(e["zoom"]),
                      "step": str(e["step"]),
                      "file": None if e.get("file") is None else str(e["file"]),
                      "status": str(e.get("status", "ok"))}
                     | ({"reasons": [str(r) for r in e["reasons"]]} if e.get("reasons") else {})
                     for e in ordered]}
    notes = ["ROS camera_info files of one zoom camera, one per calibrated zoom step, sorted",
             "by zoom: for a zoom between two entries, interpolate the parameters of the two",
             "files around it (docs/commands.md, 'Exports'). A step whose status is",
             "'unusable' has no file (file: null); 'imprecise' ones are to be used with care."]
    _atomic_write(Path(path), _comment(notes) + yaml.safe_dump(
        doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=1000))
    return Path(path)


# ----------------------------------------------------------------------------------------------
# mrcal


def mrcal_model_text(K: np.ndarray, dist: Sequence[float] | np.ndarray,
                     image_size: tuple[int, int], notes: Sequence[str] = ()) -> str:
    """An mrcal ``.cameramodel`` (module docstring), ``notes`` as ``#`` lines on top.

    Numbers are written with ``repr``, so reading gives back the same floats.
    """
    K = np.asarray(K, np.float64).reshape(3, 3)
    d = distortion_terms(dist)
    intrinsics = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d]
    numbers = ", ".join(repr(float(v)) for v in intrinsics)
    return (_comment(notes) + "{\n"
            f"    'lensmodel': '{MRCAL_LENS_MODELS[len(d)]}',\n"
            "    # intrinsics are fx, fy, cx, cy (px), then the distortion terms in OpenCV order\n"
            f"    'intrinsics': [{numbers}],\n"
            "    # extrinsics are rt_fromref: the camera is the reference frame\n"
            "    'extrinsics': [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],\n"
            f"    'imagersize': [{int(image_size[0])}, {int(image_size[1])}],\n"
            "}\n")


def write_mrcal_model(path: str | os.PathLike, K: np.ndarray,
                      dist: Sequence[float] | np.ndarray, image_size: tuple[int, int],
                      notes: Sequence[str] = ()) -> Path:
    """Write :func:`mrcal_model_text` to ``path`` (through a temporary name)."""
    path = Path(path)
    _atomic_write(path, mrcal_model_text(K, dist, image_size, notes))
    return path


# ----------------------------------------------------------------------------------------------
# zoom model grid


def write_zoom_model_grid(path: str | os.PathLike, model: ZoomModelLike,
                          n_points: int = 50) -> Path:
    """Write ``zoom_model_grid.csv``: the zoom model at ``n_points`` zooms spread evenly over
    its calibrated range (ends included).

    Columns: ``zoom``, every fitted parameter (fx, fy, cx, cy px; distortion terms), then
    ``sd_<name>``, the 1-sigma of the fitted curve (:meth:`ZoomModel.at`); floats in their
    shortest round-trip form, NaN written empty.

    Raises
    ------
    ValueError
        If ``n_points`` < 2.
    """
    if n_points < 2:
        raise ValueError(f"the zoom model grid needs at least 2 points; got {n_points}")
    zoom = np.linspace(*model.zoom_range, int(n_points))
    pred = model.predict(zoom)
    names = model.names
    columns = ["zoom", *names, *(f"sd_{k}" for k in names)]
    table = np.column_stack([zoom, *(pred[k] for k in names),
                             *(pred[f"sd_{k}"] for k in names)])
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    w.writerows([_fmt(float(v)) for v in row] for row in table)
    _atomic_write(Path(path), buf.getvalue())
    return Path(path)


# ----------------------------------------------------------------------------------------------
# the calibrate job's exports


def _notes(step: str, zoom: float | None, res: CalibrationResult, status=None) -> list[str]:
    sd = ", ".join(f"{k} {v:.4g}" for k, v in res.sd.items() if k in ("fx", "fy", "cx", "cy"))
    notes = [f"zoomcalib calibration of step {json.dumps(step, ensure_ascii=False)}, zoom "
             f"{'unknown' if zoom is None else repr(float(zoom))}, backend {res.backend}, "
             f"rms {res.rms_px:.4g} px",
             f"1-sigma ({res.info.get('sd_kind', 'unstated')}): {sd}"]
    if status is not None:
        notes.append(f"status: {status.summary()}")
    return notes


def _export_step(out: Path, run: CalibrateRun, step: str, camera_name: str,
                 ros_entries: list[dict]) -> list[Path]:
    """The OpenCV files (every backend), the ROS file and the mrcal model of one step; an
    unusable step (:mod:`zoomcalib.calibrate.status`) gets its OpenCV files, which carry the
    status, and an entry without a file in the ROS index, but no ROS or mrcal file."""
    stem, size = run.stems[step], run.observations[step].image_size
    zoom = run.zoom.get(step)
    zoom = None if zoom is None or not np.isfinite(zoom) else float(zoom)
    status = run.status.get(step)
    files = [write_opencv_yaml(out / "opencv" / f"{stem}_{_safe_name(b)}.yml", res, size, step,
                               zoom, run.flags.get(step, []),
                               status if b == run.table_backend[step] else None)
             for b, res in run.results[step].items()]
    entry = {"zoom": zoom, "step": step, "file": None,
             "status": "ok" if status is None else status.status}
    if status is not None and not status.usable:
        ros_entries.append(entry | {"reasons": list(status.reasons)})
        return files
    best = run.results[step][run.table_backend[step]]
    notes = _notes(step, zoom, best, status)
    name = f"{stem}.yaml"  # the index gives its zoom and status
    info = ros_camera_info(best.K, best.dist, size, camera_name)
    files.append(write_ros_camera_info(out / "ros" / name, info, notes))
    ros_entries.append(entry | {"file": name})
    files.append(write_mrcal_model(out / "mrcal" / f"{stem}.cameramodel", best.K, best.dist,
                                   size, notes))
    return files


def write_exports(out: str | os.PathLike, run: CalibrateRun, camera_name: str,
                  grid_points: int = 50, log: Callable[[str], None] = print) -> list[Path]:
    """Write a calibrate run's OpenCV, ROS and mrcal files and, when the run has a zoom model,
    ``zoom_model_grid.csv`` (module docstring).

    A step whose result cannot be exported (a distortion model of another length) is logged
    and recorded in ``run.failures``; the other steps are written.

    Parameters
    ----------
    out : path
        The run's output folder.
    run : CalibrateRun
    camera_name : str
        ``camera_name`` of the ROS files (ROS drivers compare it with their own).
    grid_points : int
        Zoom values of ``zoom_model_grid.csv``.

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out)
    files: list[Path] = []
    ros_entries: list[dict] = []

    def attempt(what: str, write: Callable[[], list[Path]], head: str = "") -> None:
        try:
            files.extend(write())
        except (ValueError, OSError) as exc:
            run.not_written.append(what)
            run.failures.append(f"{head or what + ': not written'}: "
                                f"{' '.join(str(exc).split())}")
            log(run.failures[-1])

    for sub in ("opencv", "ros", "mrcal"):
        attempt(f"{sub}/", lambda sub=sub: (out / sub).mkdir(parents=True, exist_ok=True) or [])
    for step in run.results:
        attempt(f"step {step} exports",
                lambda step=step: _export_step(out, run, step, camera_name, ros_entries),
                f"step {step}: not exported")
    if ros_entries:
        attempt(f"ros/{ROS_INDEX}", lambda: [write_ros_index(out / "ros" / ROS_INDEX,
                                                             camera_name, ros_entries)])
    if run.zoom_model is not None:
        attempt("zoom_model_grid.csv", lambda: [write_zoom_model_grid(
            out / "zoom_model_grid.csv", run.zoom_model, grid_points)])
    return files
