"""Calibration files (docs/conventions.md, "File contracts"): ``calibration.json`` and
``calibration.yml``, the per-zoom table ``zoom_calibration.csv`` and the correlation of its
unsmoothed rows' principal points (the zoom steps of an image folder:
:mod:`zoomcalib.calibrate.stepfolders`).

Conventions: pixels in OpenCV's convention (centre of the top-left pixel = (0, 0)); distortion in
OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``; poses ``rvecs, tvecs`` are ``Rt_cam_board``
in the target's units (mm for parsed pattern specs); uncertainties are 1-sigma.

``calibration.json``
--------------------
::

    {"format": "zoomcalib-calibration", "version": 1, "meta": {...},
     "steps": {STEP: {BACKEND: ENTRY, ...}, ...}}

``STEP`` is the zoom step's name (``"."`` for a flat folder), ``BACKEND`` the backend that ran
(``opencv``, ``opencv-ro``, ``bundle``), and ``ENTRY`` is :meth:`CalibrationResult.to_dict`
(``K`` 3x3 list, ``dist``, ``sd`` by parameter name, ``rms_px``, ``per_view_rms_px``,
``rejected`` as ``[view, point id]`` pairs, ``n_views``, ``info`` with ``info["views"]`` the
image names when the backend gives them, and for target-releasing backends ``object_points``
and ``object_points_sd``) plus ``rvecs`` and ``tvecs`` (m x 3 lists).

``calibration.yml`` (OpenCV FileStorage)
----------------------------------------
The same numbers, readable with ``cv2.FileStorage``. Top-level nodes::

    format: zoomcalib-calibration
    version: 1
    meta_json: "<meta as a JSON string>"
    entries: [ PREFIX, ... ]           # one per (step, backend), in file order
    PREFIX_step: "<step name>"         # original names (any characters)
    PREFIX_backend: "<backend>"
    PREFIX_K: !!opencv-matrix 3x3, px
    PREFIX_dist: !!opencv-matrix 1xN, OpenCV order
    PREFIX_sd: {fx: .., fy: .., cx: .., cy: .., k1: .., ...}   # 1-sigma, by name
    PREFIX_rms_px: real
    PREFIX_n_views: int
    PREFIX_per_view_rms_px: !!opencv-matrix 1xM (absent when M = 0)
    PREFIX_views: [ "<image name>", ... ]   (when known)
    PREFIX_n_rejected: int
    PREFIX_rejected: !!opencv-matrix Rx2 int, (view, point id) (absent when R = 0)
    PREFIX_rvecs, PREFIX_tvecs: !!opencv-matrix Mx3 (Rt_cam_board)
    PREFIX_object_points, PREFIX_object_points_sd: !!opencv-matrix Nx3 (releasing backends)

``PREFIX`` is ``step_<S>_<B>`` with ``S`` the step name and ``B`` the backend, each with every
character outside ``[A-Za-z0-9_]`` replaced by ``_`` (``"."`` becomes ``root``); when two
entries would get the same prefix, ``_2``, ``_3``, ... is appended. E.g. the ``opencv`` result of
step ``zoom_3x`` is ``step_zoom_3x_opencv_K``. A flat folder (the single step ``"."``) with an
``opencv`` result also gets OpenCV's sample names ``image_width``, ``image_height``,
``camera_matrix``, ``distortion_coefficients`` and ``avg_reprojection_error`` when ``meta`` has
``image_size``, so tools reading OpenCV's calibration sample output read it too.

``zoom_calibration.csv``
------------------------
One row per step, columns :data:`ZOOM_TABLE_COLUMNS`, then those of
:data:`ZOOM_TABLE_OPTIONAL` that any row knows. :func:`read_zoom_table` needs only
:data:`ZOOM_TABLE_REQUIRED`. The optional columns include ``backend`` (the backend whose
result the row holds), the rational model's ``k4, k5, k6`` and the 1-sigma ``sd_k1 ...
sd_k6`` of the distortion terms.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from zoomcalib.calibrate.result import CalibrationResult
from zoomcalib.io import read_json

from .stepfolders import csv_reader

__all__ = [
    "KEYSTONE_COLUMNS",
    "ZOOM_TABLE_COLUMNS",
    "ZOOM_TABLE_OPTIONAL",
    "ZOOM_TABLE_REQUIRED",
    "read_calibration",
    "read_principal_point_correlation",
    "read_zoom_table",
    "write_calibration",
    "write_principal_point_correlation",
    "write_zoom_table",
    "yaml_prefix",
]

#: A calibration's response to a keystone of the image, as the rows (cx, cy) of the absorption
#: ``A`` and (p1, p2) of ``B``, columns per camera-turn equivalent ``eps_x``, ``eps_y``
#: (:func:`zoomcalib.calibrate.opencv_backend.keystone_response`).
KEYSTONE_COLUMNS: tuple[str, ...] = tuple(f"keystone_{q}_{axis}" for q in ("cx", "cy", "p1", "p2")
                                          for axis in "xy")
#: Columns of ``zoom_calibration.csv``, always written, in this order.
ZOOM_TABLE_COLUMNS: tuple[str, ...] = (
    "step", "zoom", "fx", "fy", "cx", "cy", "sd_fx", "sd_fy", "sd_cx", "sd_cy",
    "k1", "k2", "p1", "p2", "k3", "rms_px", "n_views")
#: Columns written after those when any row knows them.
ZOOM_TABLE_OPTIONAL: tuple[str, ...] = (
    "direction", "sequence", "focus", "temperature", "session", "backend", "mode", "converged",
    "flags", "status", "status_reasons",
    "k4", "k5", "k6",
    "sd_k1", "sd_k2", "sd_p1", "sd_p2", "sd_k3", "sd_k4", "sd_k5", "sd_k6",
    *KEYSTONE_COLUMNS)
#: Columns :func:`read_zoom_table` cannot do without.
ZOOM_TABLE_REQUIRED: tuple[str, ...] = ("zoom", "fx", "fy", "cx", "cy")

_TEXT_COLUMNS = ("step", "direction", "session", "backend", "mode", "converged", "flags",
                 "status", "status_reasons")
_INT_COLUMNS = ("n_views", "sequence")


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON-serialisable: {type(v).__name__}")


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------------------
# calibration.json / calibration.yml


def yaml_prefix(step: str, backend: str) -> str:
    """The FileStorage node prefix of one (step, backend) entry, before de-duplication.

    Examples
    --------
    >>> yaml_prefix(".", "opencv"), yaml_prefix("zoom 3x", "opencv-ro")
    ('step_root_opencv', 'step_zoom_3x_opencv_ro')
    """
    s = "root" if step == "." else re.sub(r"[^A-Za-z0-9_]", "_", str(step))
    b = re.sub(r"[^A-Za-z0-9_]", "_", str(backend))
    return f"step_{s}_{b}"


def _entry(res: CalibrationResult) -> dict:
    d = res.to_dict()
    d["rvecs"] = np.asarray(res.rvecs, float).reshape(-1, 3).tolist()
    d["tvecs"] = np.asarray(res.tvecs, float).reshape(-1, 3).tolist()
    return d


#: ``meta`` entries too long for one YAML string (OpenCV's limit); calibration.json has them
#: (of ``status`` the YAML keeps each step's status word).
_JSON_ONLY_META = ("cross_validation", "zoom_wide", "detections", "flags", "flag_records",
                   "residual_budget")
#: OpenCV writes a YAML string of at most 4096 characters; ``meta_json`` stays below with room
#: for the escapes of its quotes.
_YAML_STRING_MAX = 4000


def _brief_json(brief: dict) -> str:
    """``brief`` as JSON within OpenCV's YAML string limit: the longest entries are left out
    (named under ``"in_calibration_json_only"``) until it fits."""
    brief, left_out = dict(brief), []
    while True:
        text = json.dumps(brief | ({"in_calibration_json_only": left_out} if left_out else {}),
                          default=_plain)
        if len(text) + text.count('"') <= _YAML_STRING_MAX or not brief:
            return text
        longest = max(brief, key=lambda k: len(json.dumps(brief[k], default=_plain)))
        left_out.append(longest)
        del brief[longest]


def _write_yaml(path: Path, results: Mapping[str, Mapping[str, CalibrationResult]],
                meta: Mapping) -> None:
    tmp = path.with_name(path.name + ".tmp.yml")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise OSError(f"{path}: cannot write")
    try:
        fs.write("format", "zoomcalib-calibration")
        fs.write("version", 1)
        # the YAML keeps the run's settings; the long reports live in calibration.json
        brief = {k: v for k, v in meta.items() if k not in _JSON_ONLY_META}
        if isinstance(meta.get("status"), Mapping):  # the statuses; reasons and advice: JSON
            brief["status"] = {s: v.get("status") if isinstance(v, Mapping) else v
                               for s, v in meta["status"].items()}
        fs.write("meta_json", _brief_json(brief))
        prefixes = _yaml_prefixes(results)
        fs.startWriteStruct("entries", cv2.FileNode_SEQ)
        for prefix, *_ in prefixes:
            fs.write("", prefix)
        fs.endWriteStruct()
        for prefix, step, backend, res in prefixes:
            _write_yaml_entry(fs, prefix, step, backend, res)
        flat = results.get(".") if len(results) == 1 else None
        size = meta.get("image_size")
        if flat is not None and "opencv" in flat and size is not None:
            res = flat["opencv"]
            fs.write("image_width", int(size[0]))
            fs.write("image_height", int(size[1]))
            fs.write("camera_matrix", np.asarray(res.K, np.float64).reshape(3, 3))
            fs.write("distortion_coefficients", np.asarray(res.dist, np.float64).reshape(-1, 1))
            fs.write("avg_reprojection_error", float(res.rms_px))
    finally:
        fs.release()
    os.replace(tmp, path)


def _yaml_prefixes(results: Mapping[str, Mapping[str, CalibrationResult]]
                   ) -> list[tuple[str, str, str, CalibrationResult]]:
    """``(prefix, step, backend, result)`` per entry, each prefix (:func:`yaml_prefix`) made
    unique by a ``_2``, ``_3`` ... suffix."""
    prefixes: list[tuple[str, str, str, CalibrationResult]] = []
    used: set[str] = set()
    for step, by_backend in results.items():
        for backend, res in by_backend.items():
            base = yaml_prefix(step, backend)
            prefix, k = base, 1
            while prefix in used:
                k += 1
                prefix = f"{base}_{k}"
            used.add(prefix)
            prefixes.append((prefix, str(step), str(backend), res))
    return prefixes


def _write_yaml_entry(fs: cv2.FileStorage, prefix: str, step: str, backend: str,
                      res: CalibrationResult) -> None:
    """One step's and backend's keys, all starting with ``prefix``."""
    fs.write(f"{prefix}_step", step)
    fs.write(f"{prefix}_backend", backend)
    fs.write(f"{prefix}_K", np.asarray(res.K, np.float64).reshape(3, 3))
    fs.write(f"{prefix}_dist", np.asarray(res.dist, np.float64).reshape(1, -1))
    fs.startWriteStruct(f"{prefix}_sd", cv2.FileNode_MAP)
    for name, v in res.sd.items():
        fs.write(re.sub(r"[^A-Za-z0-9_]", "_", str(name)), float(v))
    fs.endWriteStruct()
    fs.write(f"{prefix}_rms_px", float(res.rms_px))
    per_view = np.asarray(res.per_view_rms_px, np.float64).reshape(1, -1)
    fs.write(f"{prefix}_n_views", int(per_view.shape[1]))
    if per_view.size:
        fs.write(f"{prefix}_per_view_rms_px", per_view)
    views = res.info.get("views")
    if views:
        fs.startWriteStruct(f"{prefix}_views", cv2.FileNode_SEQ)
        for v in views:
            fs.write("", str(v))
        fs.endWriteStruct()
    fs.write(f"{prefix}_n_rejected", len(res.rejected))
    if res.rejected:
        fs.write(f"{prefix}_rejected", np.asarray(res.rejected, np.int32).reshape(-1, 2))
    for name in ("rvecs", "tvecs"):
        arr = np.asarray(getattr(res, name), np.float64).reshape(-1, 3)
        if arr.size:
            fs.write(f"{prefix}_{name}", arr)
    for name in ("object_points", "object_points_sd"):
        arr = getattr(res, name)
        if arr is not None:
            fs.write(f"{prefix}_{name}", np.asarray(arr, np.float64).reshape(-1, 3))


def write_calibration(out_dir: str | os.PathLike,
                      results: Mapping[str, Mapping[str, CalibrationResult]],
                      meta: Mapping | None = None) -> list[Path]:
    """Write ``OUT/calibration.json`` and ``OUT/calibration.yml`` (module docstring).

    Parameters
    ----------
    out_dir : path
        Output folder; created when missing.
    results : dict of str to (dict of str to CalibrationResult)
        ``results[step][backend]``; ``"."`` is the step of a flat folder.
    meta : dict, optional
        JSON-able facts about the run (pattern, image_size [w, h], seed, versions, ...), stored
        as ``meta`` (JSON) and ``meta_json`` (YAML).

    Returns
    -------
    list of Path
        ``[calibration.json, calibration.yml]``. Each file is written to a temporary name and
        renamed, so it is never left half written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(meta or {})
    doc = {"format": "zoomcalib-calibration", "version": 1, "meta": meta,
           "steps": {str(step): {str(b): _entry(r) for b, r in by_backend.items()}
                     for step, by_backend in results.items()}}
    jpath = out / "calibration.json"
    _atomic_write(jpath, json.dumps(doc, indent=1, default=_plain) + "\n")
    ypath = out / "calibration.yml"
    _write_yaml(ypath, results, meta)
    return [jpath, ypath]


def _result_from_entry(backend: str, d: dict) -> CalibrationResult:
    def arr(key, shape=(-1, 3)):
        v = d.get(key)
        return None if v is None else np.asarray(v, np.float64).reshape(shape)

    rv = arr("rvecs")
    tv = arr("tvecs")
    return CalibrationResult(
        backend, np.asarray(d["K"], np.float64).reshape(3, 3),
        np.asarray(d["dist"], np.float64).ravel(), {k: float(v) for k, v in d["sd"].items()},
        float(d["rms_px"]), np.asarray(d.get("per_view_rms_px", []), np.float64).ravel(),
        np.zeros((0, 3)) if rv is None else rv, np.zeros((0, 3)) if tv is None else tv,
        [(int(a), int(b)) for a, b in d.get("rejected", [])], arr("object_points"),
        arr("object_points_sd"), dict(d.get("info", {})))


def read_calibration(path: str | os.PathLike
                     ) -> tuple[dict[str, dict[str, CalibrationResult]], dict]:
    """Read a ``calibration.json`` written by :func:`write_calibration`.

    Returns
    -------
    results : dict of str to (dict of str to CalibrationResult)
        ``results[step][backend]``; arrays as written (``info`` values stay JSON lists).
    meta : dict

    Raises
    ------
    ValueError
        One-line message naming the file when it is not a calibration file.
    """
    path = Path(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("steps"), dict):
        raise ValueError(f"{path}: not a calibration file (needs 'steps')")
    out: dict[str, dict[str, CalibrationResult]] = {}
    for step, by_backend in doc["steps"].items():
        out[step] = {}
        for backend, entry in by_backend.items():
            try:
                out[step][backend] = _result_from_entry(backend, entry)
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{path}: step {step!r} backend {backend!r} is malformed "
                                 f"({type(exc).__name__}: {exc})") from None
    return out, dict(doc.get("meta", {}))


# ----------------------------------------------------------------------------------------------
# zoom_calibration.csv


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool | np.bool_):
        return str(bool(v)).lower()
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        v = float(v)
        return "" if math.isnan(v) else repr(v)
    return str(v)


#: Beside ``zoom_calibration_unsmoothed.csv``: the correlation of its rows' principal points
#: (:func:`write_principal_point_correlation`).
PP_CORRELATION_FILE = "zoom_calibration_unsmoothed_correlation.json"


def write_principal_point_correlation(path: str | os.PathLike, steps: Sequence[str],
                                      correlation: np.ndarray) -> Path:
    """Write the (2S, 2S) correlation of the steps' principal points, ordered
    ``(cx, cy)`` step by step, as JSON: ``{"steps": [...], "order": "cx, cy per step",
    "correlation": [[...], ...]}`` (floats in shortest round-trip form)."""
    corr = np.asarray(correlation, float)
    if corr.shape != (2 * len(steps), 2 * len(steps)):
        raise ValueError(f"{path}: a correlation of {len(steps)} steps' principal points is "
                         f"({2 * len(steps)}, {2 * len(steps)}), got {corr.shape}")
    doc = {"steps": [str(s) for s in steps], "order": "cx, cy per step",
           "correlation": corr.tolist()}
    _atomic_write(Path(path), json.dumps(doc, indent=1) + "\n")
    return Path(path)


def read_principal_point_correlation(path: str | os.PathLike, steps: Sequence[str]
                                     ) -> np.ndarray:
    """The (2N, 2N) correlation of the principal points of ``steps`` (a subset of the file's,
    in any order), ordered ``(cx, cy)`` step by step, from a file of
    :func:`write_principal_point_correlation`.

    Raises
    ------
    ValueError
        Naming the file: not such a file, a step it does not hold, or a matrix that is not a
        correlation (not symmetric, a diagonal other than 1, not positive definite).
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        names = [str(v) for v in doc["steps"]]
        corr = np.asarray(doc["correlation"], float)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a principal-point correlation file ({exc})") from None
    if corr.shape != (2 * len(names), 2 * len(names)):
        raise ValueError(f"{path}: {len(names)} steps need a ({2 * len(names)}, "
                         f"{2 * len(names)}) correlation, got {corr.shape}")
    missing = [s for s in steps if s not in names]
    if missing:
        raise ValueError(f"{path}: no correlation for step {missing[0]}")
    at = np.ravel([[2 * names.index(s), 2 * names.index(s) + 1] for s in steps]).astype(int)
    corr = corr[np.ix_(at, at)]
    if not (np.all(np.isfinite(corr)) and np.allclose(corr, corr.T, atol=1e-9)
            and np.allclose(np.diag(corr), 1.0, atol=1e-9)):
        raise ValueError(f"{path}: not a correlation matrix (symmetric, unit diagonal)")
    if np.linalg.eigvalsh(corr)[0] <= 0:
        raise ValueError(f"{path}: the correlation is not positive definite")
    return corr


def write_zoom_table(path: str | os.PathLike, rows: Iterable[Mapping]) -> Path:
    """Write ``zoom_calibration.csv``: one row per zoom step.

    Parameters
    ----------
    path : path
    rows : iterable of dict
        Keys from :data:`ZOOM_TABLE_COLUMNS` (px for fx..cy and their ``sd_``; distortion in
        OpenCV's normalised units; ``rms_px``; ``n_views``) and optionally
        :data:`ZOOM_TABLE_OPTIONAL`. Missing or None values (and NaN) are written empty. Other
        keys are ignored.

    Returns
    -------
    Path
        The file, written through a temporary name. Floats are written with ``repr`` (shortest
        round-trip form), so reading gives back the same numbers.
    """
    path = Path(path)
    rows = [dict(r) for r in rows]
    optional = [c for c in ZOOM_TABLE_OPTIONAL
                if any(r.get(c) is not None and _fmt(r.get(c)) != "" for r in rows)]
    columns = list(ZOOM_TABLE_COLUMNS) + optional
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_fmt(r.get(c)) for c in columns])
    _atomic_write(path, buf.getvalue())
    return path


def _parse_cell(value: str, column: str, where: str):
    value = value.strip()
    if column in _TEXT_COLUMNS:
        return value
    if value == "":
        return None
    try:
        f = float(value)
    except ValueError:
        if column in ZOOM_TABLE_COLUMNS or column in ZOOM_TABLE_OPTIONAL:
            raise ValueError(f"{where}: {column} {value!r} is not a number") from None
        return value
    if column in _INT_COLUMNS and f.is_integer():
        return int(f)
    return f


def read_zoom_table(path: str | os.PathLike) -> list[dict]:
    """Read a ``zoom_calibration.csv`` (any writer of the contract).

    Only :data:`ZOOM_TABLE_REQUIRED` (``zoom, fx, fy, cx, cy``) must be present and filled;
    other columns are read when present.

    Parameters
    ----------
    path : path

    Returns
    -------
    list of dict
        One dict per row, in file order, with every column of the file: ``step``,
        ``direction``, ``session`` and ``backend`` as str, ``n_views`` and ``sequence`` as
        int, other known columns as float (None when empty), unknown columns as float when
        numeric, else str.

    Raises
    ------
    ValueError
        One line naming the file (and the row, counted from 1 after the header) when a required
        column is missing or a value is not a number.
    """
    path = Path(path)
    reader, header = csv_reader(path)
    missing = [c for c in ZOOM_TABLE_REQUIRED if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column{'s' if len(missing) > 1 else ''} "
                         f"{', '.join(missing)} (needs {', '.join(ZOOM_TABLE_REQUIRED)})")
    reader.fieldnames = header
    out = []
    for k, raw in enumerate(reader, start=1):
        where = f"{path} row {k}"
        if None in raw:
            raise ValueError(f"{where}: more cells than columns")
        row = {}
        for c in header:
            cell = raw.get(c)
            row[c] = _parse_cell("" if cell is None else cell, c, where)
        for c in ZOOM_TABLE_REQUIRED:
            if row[c] is None:
                raise ValueError(f"{where}: {c} is empty")
            if not math.isfinite(row[c]):
                raise ValueError(f"{where}: {c} is not finite")
        out.append(row)
    return out


# ----------------------------------------------------------------------------------------------
# zoom steps of an image folder


def observations_from_npz(path: str | os.PathLike, scale: float = 1000.0):
    """Observations exported from mrcal (``obs`` (m, H, W, 3): x, y, weight; ``obj`` (H, W, 3);
    ``imagersize``), with corners of weight <= 0 dropped.

    Parameters
    ----------
    scale : float
        Multiplies the object points (1000: metres to mm).

    Returns
    -------
    obs : Observations
    weights : list of (k,) ndarray
        The kept corners' weights, per view.
    """
    from .result import Observations

    d = np.load(path)
    views, weights = [], []
    for o in d["obs"]:
        o = o.reshape(-1, 3)
        keep = o[:, 2] > 0
        views.append((np.flatnonzero(keep), o[keep, :2]))
        weights.append(o[keep, 2])
    obj = d["obj"].reshape(-1, 3) * scale
    return Observations(obj, views, tuple(int(v) for v in d["imagersize"])), weights
