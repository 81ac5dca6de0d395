"""Target detection with OpenCV's detectors: images in, detected target points out.

Pixel convention (OpenCV's, used for every point here): the centre of the top-left pixel is
(0, 0), x grows to the right, y grows downwards.

Methods (``METHODS``) and the target kinds they fit:

``"model"``
    OpenCV's detector finds the points, a fit of the blurred, pixel-integrated pattern places
    them (:mod:`zoomcalib.detect.refine`; at the Cramér-Rao bound on rendered boards). Every
    target kind. Default for chessboards. A point whose fit fails keeps the detector's position
    and is flagged in ``Detection.fallback``.
``"sb"``
    ``cv2.findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``, retried with
    ``CALIB_CB_EXHAUSTIVE``. Chessboards. ``CALIB_CB_NORMALIZE_IMAGE`` is not used: on rendered
    boards it makes the corners several times worse (measured by ``python
    benchmarks/bench_detect_flags.py``; results in ``docs/performance.md``).
``"classic"``
    ``cv2.findChessboardCorners`` (adaptive threshold, normalised image) and
    ``cv2.cornerSubPix`` (half-window ``win``, default 5, i.e. an 11 x 11 window). Chessboards.
``"circles"``
    ``cv2.findCirclesGrid`` with a ``SimpleBlobDetector`` tuned for dots from about 8 px across
    to as large as a grid cell; symmetric or asymmetric grid from ``target.kind``, retried with
    ``CALIB_CB_CLUSTERING``. Circle grids (``circles``, ``acircles``).
``"charuco"``
    ``cv2.aruco.CharucoDetector`` on the board ``targets.charuco`` builds. Partial views give
    the corners seen, with OpenCV's corner ids. ChArUco boards.

Point order
-----------
ChArUco ids come from the markers and are exact. A chessboard or a circle grid can only be
labelled up to the symmetries of its point lattice, and OpenCV's detectors return any of them
(a 9x6 chessboard from either end; a symmetric circle grid even mirrored, or turned by 90 degrees
when square). Detections are therefore normalised, among the labellings the lattice allows
(``ids`` always index ``target.object_points`` row-major, ``i = r * cols + c``), by three rules
applied in turn, each only where it still leaves a choice:

1. *Front view*: the board's x (columns) and y (rows) axes appear in the image with the same
   handedness as in the board frame, as they do for any board seen from its printed side.
   This fixes the mirrored labellings OpenCV's symmetric circle-grid finder can return.
2. *Colour* (chessboards): the inner squares with ``(c + r)`` even (the square between corners
   ``0, 1, cols, cols + 1`` and every one in its colour class) are the dark ones, as in
   ``targets.chessboard``, whose square diagonally outside corner 0 is dark. This decides the
   180-degree ambiguity whenever ``cols + rows`` is odd (e.g. 9x6), so such boards are
   labelled as the physical board, the same in every view and the same as rendered ground truth.
3. *Image position*: of what remains (chessboards with ``cols + rows`` even, symmetric circle
   grids), point 0 is the candidate first point nearest the image's top-left corner, i.e. with
   the smallest ``x + y`` (then the smallest ``y``). Such boards look the same turned by 180
   degrees, so nothing in the image can tell the two labellings apart: this rule only makes the
   choice deterministic. The asymmetric circle grid needs no rule: rule 1 fixes it.

Depth
-----
Colour images are converted to grey. ``uint16`` and floating-point images are stretched to
8 bits for OpenCV's detectors that need 8 bits (chessboard search, blob detection, marker
detection); ``cornerSubPix`` (``classic``, and ``charuco`` for non-8-bit input) then refines on
the full-depth grey image. ``sb`` refines internally on the 8-bit image; circle centres are the
blob detector's (moments of thresholded blobs, on the 8-bit image).
"""

from __future__ import annotations

import concurrent.futures
import inspect
import json
import multiprocessing
import os
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from zoomcalib.io import read_json
from zoomcalib.pool import ignore_interrupt, stop_pool
from zoomcalib.targets import Target, parse_pattern

__all__ = [
    "DEFAULT_METHODS",
    "Detection",
    "IMAGE_EXTENSIONS",
    "METHODS",
    "default_method",
    "detect_folder",
    "detect_image",
    "detection_pool",
    "image_files",
    "read_detections",
    "write_detections",
]

#: Method name -> the target kinds it can detect.
METHODS: dict[str, tuple[str, ...]] = {
    "sb": ("chessboard",),
    "classic": ("chessboard",),
    "circles": ("circles", "acircles"),
    "charuco": ("charuco",),
    "model": ("chessboard", "circles", "acircles", "charuco"),
}

#: Target kind -> the method used when none is given.
DEFAULT_METHODS: dict[str, str] = {
    "chessboard": "model",
    "circles": "circles",
    "acircles": "circles",
    "charuco": "charuco",
}

#: File name extensions taken as images (compared in lower case).
IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)


@dataclass
class Detection:
    """The target points found in one image.

    Attributes
    ----------
    file : str
        Image name (base name for files; ``"<array>"`` or the given name for arrays).
    points : (K, 2) ndarray of float64
        Detected points, pixels, OpenCV convention (centre of the top-left pixel is (0, 0),
        x right, y down). Empty, shape (0, 2), when the image failed.
    ids : (K,) ndarray of int64
        Index of each point in ``target.object_points``.
    error : str or None
        One-line message naming the file when the image failed, else None.
    method : str
        Detection method used (a key of ``METHODS``).
    image_size : (int, int)
        Image width and height, pixels; (0, 0) when the image could not be read.
    fallback : (K,) ndarray of bool
        True where the method's own refinement failed for that point and it holds the initial
        detector's position instead (``model`` only); calibration leaves such points out.
    transient : bool
        The image failed for a reason outside it (an unexpected exception, a worker killed by
        the system): another run may succeed, so a cache must not reuse the failure. Not
        written to a detections file.
    steep_edges : bool
        The image's edges are steeper than any Gaussian blur makes (a camera that sharpens):
        the ``model`` refiner fitted its corners at a fixed 0.5 px blur
        (:attr:`~zoomcalib.detect.refine.RefineResult.steep_edges`).
    no_target : bool
        The image was read and searched, and no whole target was found in it: a frame whose
        board runs off the image or is hidden, normal in a real set (an unreadable image, a
        failed detector, are errors without it).
    sharpening : (float, float, float) or None
        The camera's sharpening the ``model`` refiner fitted its corners with: the PSF
        ``(sigma, amount, radius)`` (px, 1, px) of
        :class:`~zoomcalib.detect.cornermodel.SharpenedPSF`; None when a Gaussian blur was used.
    """

    file: str
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    error: str | None = None
    method: str = ""
    image_size: tuple[int, int] = (0, 0)
    fallback: np.ndarray | None = None
    transient: bool = False
    steep_edges: bool = False
    sharpening: tuple[float, float, float] | None = None
    no_target: bool = False

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 2)
        self.ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        if len(self.ids) != len(self.points):
            raise ValueError(f"{self.file}: {len(self.points)} points but {len(self.ids)} ids")
        if self.fallback is None:
            self.fallback = np.zeros(len(self.points), dtype=bool)
        self.fallback = np.asarray(self.fallback, dtype=bool).reshape(-1)
        if len(self.fallback) != len(self.points):
            raise ValueError(f"{self.file}: {len(self.points)} points but "
                             f"{len(self.fallback)} fallback flags")
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    @property
    def ok(self) -> bool:
        """True when the image gave points and no error."""
        return self.error is None and len(self.points) > 0

    @property
    def n_fallback(self) -> int:
        """Points whose refinement failed (see ``fallback``)."""
        return int(np.count_nonzero(self.fallback))

    def to_dict(self) -> dict:
        """The detections-file entry ``{"file", "points", "ids", "error"[, "fallback",
        "steep_edges", "sharpening", "no_target"]}``, plain Python types; ``fallback`` (one
        bool per point) only when a point fell back, ``steep_edges`` and ``no_target`` only
        when true, ``sharpening`` (``[sigma, amount, radius]``) only when fitted."""
        entry = {"file": self.file, "points": self.points.tolist(),
                 "ids": [int(i) for i in self.ids], "error": self.error}
        if self.n_fallback:
            entry["fallback"] = [bool(b) for b in self.fallback]
        if self.steep_edges:
            entry["steep_edges"] = True
        if self.sharpening is not None:
            entry["sharpening"] = [float(v) for v in self.sharpening]
        if self.no_target:
            entry["no_target"] = True
        return entry

    @classmethod
    def from_dict(cls, entry: dict, method: str = "",
                  image_size: tuple[int, int] = (0, 0)) -> Detection:
        """Inverse of :meth:`to_dict`; ``method`` and ``image_size`` are taken from ``entry``
        when it has them."""
        return cls(str(entry["file"]), np.asarray(entry.get("points") or [], float),
                   np.asarray(entry.get("ids") or [], np.int64), entry.get("error"),
                   str(entry.get("method", method)), tuple(entry.get("image_size", image_size)),
                   entry.get("fallback"), steep_edges=bool(entry.get("steep_edges", False)),
                   sharpening=tuple(entry["sharpening"]) if entry.get("sharpening") else None,
                   no_target=bool(entry.get("no_target", False)))


def default_method(target: Target) -> str:
    """The method used for ``target`` when none is given (``DEFAULT_METHODS[target.kind]``)."""
    return DEFAULT_METHODS[target.kind]


def _check_method(target: Target, method: str | None) -> str:
    method = default_method(target) if method is None else method
    if method not in METHODS:
        raise ValueError(f"unknown detection method {method!r}; choose one of "
                         + ", ".join(repr(m) for m in METHODS))
    if target.kind not in METHODS[method]:
        fits = [m for m, kinds in METHODS.items() if target.kind in kinds]
        raise ValueError(f"detection method {method!r} does not fit a {target.kind} target "
                         f"({target.spec}); it detects {' or '.join(METHODS[method])} targets. "
                         f"For this target use " + " or ".join(repr(m) for m in fits))
    return method


def _check_options(method: str, options: dict) -> None:
    allowed = list(inspect.signature(_DETECTORS[method]).parameters)[3:]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(f"detection method {method!r} has no option "
                        + ", ".join(repr(u) for u in unknown) + "; its options: "
                        + (", ".join(allowed) or "none"))


def _as_target(target: Target | str) -> Target:
    return parse_pattern(target) if isinstance(target, str) else target


# ----------------------------------------------------------------------------------------------
# images


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_problem(data: bytes) -> str | None:
    """What is wrong with a PNG file's chunk structure (a chunk running past the end, a CRC
    that does not match its chunk, no ``IEND``), or None when it is whole. Checked before
    decoding, so that a damaged frame is named here instead of libpng printing its own error
    line to the process's stderr.

    Examples
    --------
    >>> import cv2, numpy as np
    >>> whole = cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes()
    >>> png_problem(whole) is None, png_problem(whole[:50])
    (True, 'truncated PNG: chunk IDAT runs past the end of the file')
    """
    pos = len(_PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        name = kind.decode("latin-1")
        end = pos + 12 + length
        if end > len(data):
            return f"truncated PNG: chunk {name} runs past the end of the file"
        if zlib.crc32(data[pos + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            return f"corrupt PNG: CRC error in chunk {name}"
        if kind == b"IEND":
            return None
        pos = end
    return "truncated PNG: no IEND chunk"


def _read_image(path: Path) -> tuple[np.ndarray | None, str | None]:
    """Decode an image file unchanged (depth, channels); (None, reason) when it cannot."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, exc.strerror.lower() if exc.strerror else type(exc).__name__
    if not data:
        return None, "empty file"
    if data.startswith(_PNG_SIGNATURE) and (problem := png_problem(data)):
        return None, problem
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        return None, "not an image file OpenCV can decode"
    return img, None


def _grey_levels(img: np.ndarray) -> tuple[np.ndarray, np.ndarray] | str:
    """Grey 8-bit image for the detectors and the best grey image for subpixel refinement.

    Parameters
    ----------
    img : (h, w) or (h, w, c) ndarray
        Grey, BGR or BGRA; uint8, uint16 or floating point.

    Returns
    -------
    grey8 : (h, w) uint8 ndarray
    best : (h, w) ndarray
        ``grey8`` itself for 8-bit input, else the grey image as float32 (full depth).
    Or a string saying why the array is not a usable image.
    """
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)) \
            or min(img.shape[:2]) < 1:
        return f"unsupported image array of shape {img.shape}"
    if img.dtype == np.bool_ or not np.issubdtype(img.dtype, np.number) \
            or np.issubdtype(img.dtype, np.complexfloating):
        return f"unsupported image dtype {img.dtype}"
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    if img.ndim == 3:
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        img = cv2.cvtColor(np.ascontiguousarray(img), code)
    if img.dtype == np.uint8:
        return img, img
    best = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    lo, hi = np.percentile(best, (0.05, 99.95))
    if not hi > lo:
        lo, hi = float(best.min()), float(best.max())
    scale = 255.0 / (hi - lo) if hi > lo else 0.0
    grey8 = np.clip((best - lo) * scale + 0.5, 0, 255).astype(np.uint8)
    return grey8, best


# ----------------------------------------------------------------------------------------------
# point order


_SYMMETRY_CACHE: dict[tuple[tuple[int, ...], bytes], list[tuple[np.ndarray, int]]] = {}


def _lattice_symmetries(object_xy: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """Relabellings of a planar point set that map it onto itself (cached per point set).

    Parameters
    ----------
    object_xy : (n, 2) ndarray
        Object points in the board plane.

    Returns
    -------
    list of ((n,) int ndarray, int)
        For each of the 8 axis-aligned rotations and reflections S about the centroid that maps
        the set onto itself: ``perm`` with ``S(P[i]) = P[perm[i]]``, and ``det S`` (+1 or -1).
        The identity is first.
    """
    key = (object_xy.shape, np.ascontiguousarray(object_xy, np.float64).tobytes())
    if key in _SYMMETRY_CACHE:
        return _SYMMETRY_CACHE[key]
    centred = object_xy - object_xy.mean(axis=0)
    scale = np.abs(centred).max() or 1.0
    tol = 1e-6 * scale
    out = []
    for det in (1, -1):
        for k in range(4):
            c, s = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
            m = np.array([[c, -s], [s, c]]) @ np.diag([1.0, float(det)])
            mapped = centred @ m.T
            d2 = np.sum((mapped[:, None, :] - centred[None, :, :]) ** 2, axis=-1)
            perm = np.argmin(d2, axis=1)
            if np.all(d2[np.arange(len(perm)), perm] < tol ** 2) \
                    and len(np.unique(perm)) == len(perm):
                out.append((perm, det))
    if len(_SYMMETRY_CACHE) > 32:
        _SYMMETRY_CACHE.clear()
    _SYMMETRY_CACHE[key] = out
    return out


def _handedness(object_xy: np.ndarray, points: np.ndarray) -> float:
    """Sign of the determinant of the affine map that best takes ``object_xy`` to ``points``."""
    a = np.column_stack([object_xy - object_xy.mean(0), np.ones(len(object_xy))])
    coef = np.linalg.lstsq(a, points - points.mean(0), rcond=None)[0]
    return float(np.sign(np.linalg.det(coef[:2])))


def _square_contrast(points: np.ndarray, cols: int, rows: int, smooth: np.ndarray) -> float:
    """Mean grey of the inner squares with ``(c + r)`` odd minus those with it even.

    Positive when the squares of the class of the square between corners 0, 1, cols, cols + 1
    are dark. ``points`` : (cols * rows, 2) corners in row-major order; ``smooth`` : (h, w)
    grey image, lightly smoothed (each square is sampled at one pixel, its centre).
    """
    g = points.reshape(rows, cols, 2)
    centres = 0.25 * (g[:-1, :-1] + g[:-1, 1:] + g[1:, :-1] + g[1:, 1:])
    h, w = smooth.shape
    x = np.clip(np.rint(centres[..., 0]).astype(int), 0, w - 1)
    y = np.clip(np.rint(centres[..., 1]).astype(int), 0, h - 1)
    values = smooth[y, x]
    rr, cc = np.indices(values.shape)
    odd = (rr + cc) % 2 == 1
    return float(values[odd].mean() - values[~odd].mean())


def _normalise_order(points: np.ndarray, target: Target, grey: np.ndarray) -> np.ndarray:
    """Relabel a full grid detection by the rules in the module docstring.

    Parameters
    ----------
    points : (n, 2) ndarray
        Detected points for ``target.object_points`` in the detector's order, pixels.
    target : Target
        Chessboard or circle grid.
    grey : (h, w) ndarray
        The grey image (for the chessboard colour rule).

    Returns
    -------
    (n, 2) ndarray
        The same points, reordered.
    """
    obj = target.object_points[:, :2]
    hand = _handedness(obj, points)
    cands = [(points[perm], hand * det) for perm, det in _lattice_symmetries(obj)]
    if len(cands) > 1:
        front = [c for c in cands if c[1] > 0]
        cands = front or cands
    if len(cands) > 1 and target.kind == "chessboard" and min(target.pattern_size) >= 2:
        cols, rows = target.pattern_size
        smooth = cv2.blur(grey.astype(np.float32), (3, 3))
        dark_even = [c for c in cands if _square_contrast(c[0], cols, rows, smooth) > 0]
        cands = dark_even or cands
    first = np.array([c[0][0] for c in cands])
    best = np.lexsort((first[:, 1], first[:, 0] + first[:, 1]))[0]
    return cands[best][0]


# ----------------------------------------------------------------------------------------------
# detectors: each returns (points (K, 2), ids (K,)) or a string saying what was not found


def _detect_sb(grey8: np.ndarray, best: np.ndarray, target: Target,
               exhaustive_retry: bool = True):
    size = tuple(target.pattern_size)
    flags = cv2.CALIB_CB_ACCURACY  # NORMALIZE_IMAGE costs accuracy (module docstring)
    ok, corners = cv2.findChessboardCornersSB(grey8, size, flags=flags)
    if not ok and exhaustive_retry:
        ok, corners = cv2.findChessboardCornersSB(grey8, size,
                                                  flags=flags | cv2.CALIB_CB_EXHAUSTIVE)
    if not ok:
        return f"no chessboard {size[0]}x{size[1]} found"
    pts = _normalise_order(np.asarray(corners, np.float64).reshape(-1, 2), target, grey8)
    # SB too occasionally returns a corner several pixels off, inside the board
    return _repair_grid(pts, size, best), np.arange(len(pts))


def _corner_spacing(g: np.ndarray) -> float:
    """Smallest distance between grid neighbours of a (rows, cols, 2) corner grid, px."""
    return float(min(np.linalg.norm(np.diff(g, axis=0), axis=-1).min(),
                     np.linalg.norm(np.diff(g, axis=1), axis=-1).min()))


def _repair_grid(pts: np.ndarray, size: tuple[int, int], image: np.ndarray,
                 win: int = 5) -> np.ndarray:
    """Restart corners that disagree with their grid neighbours from the neighbours' prediction
    (cornerSubPix, half-window ``win`` shrunk to 0.45 x the spacing); the others are kept."""
    spacing = _corner_spacing(pts.reshape(size[1], size[0], 2))
    tol = max(1.5, 0.03 * spacing)  # linear prediction is good to ~0.6 % of the spacing
    w = int(max(2, min(win, np.floor(0.45 * spacing))))
    out = pts.copy()
    # Worst first: a bad corner spoils its neighbours' predictions, so fix one at a time.
    for _ in range(len(pts) // 4):
        pred = _grid_prediction(out.reshape(size[1], size[0], 2)).reshape(-1, 2)
        dev = np.linalg.norm(out - pred, axis=1)
        j = int(np.argmax(dev))
        if dev[j] <= tol:
            break
        fixed = cv2.cornerSubPix(image, pred[j:j + 1].astype(np.float32).reshape(-1, 1, 2),
                                 (w, w), (-1, -1), _SUBPIX_CRITERIA)
        out[j] = np.asarray(fixed, np.float64).reshape(2)
    return out


def _detect_classic(grey8: np.ndarray, best: np.ndarray, target: Target, win: int = 5):
    size = tuple(target.pattern_size)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(grey8, size, flags=flags)
    if not ok:
        return f"no chessboard {size[0]}x{size[1]} found"
    pts = np.asarray(corners, np.float64).reshape(-1, 2)
    pts = _normalise_order(pts, target, grey8)
    # Keep the window off the neighbouring corners on small views of the board.
    w = int(max(2, min(win, np.floor(0.45 * _corner_spacing(pts.reshape(size[1], size[0], 2))))))
    refined = cv2.cornerSubPix(best, pts.astype(np.float32).reshape(-1, 1, 2), (w, w), (-1, -1),
                               _SUBPIX_CRITERIA)
    refined = np.asarray(refined, np.float64).reshape(-1, 2)
    # findChessboardCorners sometimes places a border corner several pixels off, beyond the
    # reach of cornerSubPix.
    return _repair_grid(refined, size, best, win), np.arange(len(pts))


def _grid_prediction(g: np.ndarray) -> np.ndarray:
    """Predict every corner of a (rows, cols, 2) grid from its neighbours along rows and columns
    (mean of the two neighbours inside the grid, linear extrapolation at the border); the median
    of the available predictions is returned, so one bad neighbour does not spoil it."""
    rows, cols = g.shape[:2]
    cands = np.full((4, rows, cols, 2), np.nan)
    for axis, k in ((0, 0), (1, 2)):
        a = np.moveaxis(g, axis, 0)
        n = a.shape[0]
        c1 = np.full_like(a, np.nan)
        c2 = np.full_like(a, np.nan)
        c1[1:-1] = 0.5 * (a[:-2] + a[2:])
        if n >= 3:
            c1[0] = 2 * a[1] - a[2]
            c1[-1] = 2 * a[-2] - a[-3]
            c2[2:] = 2 * a[1:-1] - a[:-2]
            c2[:-2] = np.where(np.isnan(c2[:-2]), 2 * a[1:-1] - a[2:], c2[:-2])
        cands[k] = np.moveaxis(c1, 0, axis)
        cands[k + 1] = np.moveaxis(c2, 0, axis)
    return np.nanmedian(cands, axis=0)


def _blob_detector(image_shape: tuple[int, ...], n_points: int, min_diameter: float,
                   max_diameter: float | None, dark: bool):
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = 10, 245, 10
    p.minRepeatability = 2
    p.minDistBetweenBlobs = max(1.0, 0.5 * min_diameter)
    p.filterByColor, p.blobColor = True, 0 if dark else 255
    p.filterByArea = True
    p.minArea = 0.5 * np.pi * (0.5 * min_diameter) ** 2
    cell = image_shape[0] * image_shape[1] / max(n_points, 1)  # a dot is smaller than its cell
    p.maxArea = cell if max_diameter is None else np.pi * (0.5 * max_diameter) ** 2 * 1.5
    p.maxArea = max(p.maxArea, 4 * p.minArea)
    p.filterByCircularity = False
    p.filterByInertia, p.minInertiaRatio = True, 0.05  # oblique views: ellipses
    p.filterByConvexity, p.minConvexity = True, 0.8
    return cv2.SimpleBlobDetector_create(p)


def _detect_circles(grey8: np.ndarray, best: np.ndarray, target: Target,
                    min_diameter: float = 8.0, max_diameter: float | None = None,
                    dark: bool = True):
    size = tuple(target.pattern_size)
    asym = target.kind == "acircles"
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if asym else cv2.CALIB_CB_SYMMETRIC_GRID
    blobs = _blob_detector(grey8.shape, target.n_points, min_diameter, max_diameter, dark)
    ok, centres = cv2.findCirclesGrid(grey8, size, flags=flags, blobDetector=blobs)
    if not ok:
        ok, centres = cv2.findCirclesGrid(grey8, size, flags=flags | cv2.CALIB_CB_CLUSTERING,
                                          blobDetector=blobs)
    if not ok:
        kind = "asymmetric circle grid" if asym else "circle grid"
        return f"no {kind} {size[0]}x{size[1]} found"
    pts = np.asarray(centres, np.float64).reshape(-1, 2)
    return _normalise_order(pts, target, grey8), np.arange(len(pts))


def _charuco_detector(target: Target):
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.dictionary))
    board = cv2.aruco.CharucoBoard(tuple(target.squares), float(target.pitch_mm),
                                   float(target.marker_mm), dictionary)
    return cv2.aruco.CharucoDetector(board)


def _detect_charuco(grey8: np.ndarray, best: np.ndarray, target: Target, win: int = 5):
    corners, ids, _marker_corners, marker_ids = _charuco_detector(target).detectBoard(grey8)
    if ids is None or len(ids) == 0:
        n_markers = 0 if marker_ids is None else len(marker_ids)
        sx, sy = target.squares
        return (f"no ChArUco corners found ({sx}x{sy} squares, {target.dictionary}; "
                f"{n_markers} marker{'s' if n_markers != 1 else ''} seen)")
    pts = np.asarray(corners, np.float64).reshape(-1, 2)
    ids = np.asarray(ids, np.int64).ravel()
    if best.dtype != np.uint8:  # refine again on the full-depth image
        pts = np.asarray(cv2.cornerSubPix(best, pts.astype(np.float32).reshape(-1, 1, 2),
                                          (win, win), (-1, -1), _SUBPIX_CRITERIA),
                         np.float64).reshape(-1, 2)
    order = np.argsort(ids, kind="stable")
    return pts[order], ids[order]


def _min_spacing(points: np.ndarray, statistic=np.min) -> float:
    """Smallest (or another statistic of the) nearest-neighbour distance between points."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    return float(statistic(d[:, 1]))


def _detect_model(grey8: np.ndarray, best: np.ndarray, target: Target, window: int = 5,
                  sigma: float | str | None = "shared"):
    """OpenCV finds the points; our model fit (:mod:`zoomcalib.detect.refine`) places them.

    Chessboards start from findChessboardCorners + cornerSubPix (the SB detector when that
    fails), ChArUco from the ChArUco detector, dots from findCirclesGrid.

    Chessboard and ChArUco corners: blurred X-junction fit in a ``(2 window + 1)^2`` window
    (shrunk to 0.45 x the corner spacing) with one blur shared by the image, isotropic or, when
    the corners ask for it (motion blur, astigmatism), anisotropic; the window grows with the
    shared blur to ``ceil(3 sigma_major) + 2`` px, at most ``_MAX_WINDOW`` and 0.45 x the
    spacing. Dots: blurred-ellipse fit; the result is the
    centre of the imaged ellipse (its perspective/distortion bias is corrected at calibration,
    see :func:`zoomcalib.detect.dots.dot_centre_bias`). Points whose fit did not converge keep
    OpenCV's position and are returned flagged (the third element, True where a point fell back);
    the fourth says whether the corners' edges were steeper than any blur makes
    (:attr:`~zoomcalib.detect.refine.RefineResult.steep_edges`), the fifth the sharpened PSF
    ``(sigma, amount, radius)`` they were fitted with, or None
    (:attr:`~zoomcalib.detect.refine.RefineResult.sharpening`).
    """
    from .refine import refine_corners, refine_dots

    if target.kind == "chessboard":
        # findChessboardCorners is much faster than the SB detector (docs/performance.md,
        # benchmarks/bench_detect_flags.py); SB is the fallback
        found = _detect_classic(grey8, best, target)
        if isinstance(found, str):
            found = _detect_sb(grey8, best, target)
    else:
        base = {"charuco": _detect_charuco, "circles": _detect_circles,
                "acircles": _detect_circles}[target.kind]
        found = base(grey8, best, target)
    if isinstance(found, str):
        return found
    pts, ids = found
    if len(pts) < 2:
        return pts, ids, np.ones(len(pts), bool)  # nothing to fix the window size: not refined
    img = best.astype(np.float64)
    spacing = _min_spacing(pts)
    if target.kind in ("circles", "acircles"):
        # dot radius in px from the grid spacing and the target's radius/pitch ratio
        ratio = target.discs[0, 2] / _min_spacing(target.object_points[:, :2])
        res = refine_dots(img, pts, ratio * _min_spacing(pts, np.median), sigma=None)
        refined = res.centres
    else:
        cap = int(max(2, np.floor(0.45 * spacing)))
        res = refine_corners(img, pts, window=min(window, cap), sigma=sigma,
                             max_window=min(_MAX_WINDOW, cap))
        refined = res.points
    out = np.where(res.converged[:, None], refined, pts)
    psf = getattr(res, "sharpening", None)
    return (out, ids, ~res.converged, bool(getattr(res, "steep_edges", False)),
            None if psf is None else (psf.sigma, psf.amount, psf.radius))


_MAX_WINDOW = 12  # px; the model fit's half-window grows with the blur up to this

_DETECTORS = {"sb": _detect_sb, "classic": _detect_classic, "circles": _detect_circles,
              "charuco": _detect_charuco, "model": _detect_model}


# ----------------------------------------------------------------------------------------------
# public API


def detect_image(image_or_path: str | os.PathLike | np.ndarray, target: Target | str,
                 method: str | None = None, *, name: str | None = None,
                 **options) -> Detection:
    """Detect the target in one image.

    Parameters
    ----------
    image_or_path : str, path or (h, w) / (h, w, 3) / (h, w, 4) ndarray
        Image file, or image array (grey, BGR or BGRA; uint8, uint16 or float).
    target : Target or str
        The target, or its pattern spec.
    method : str, optional
        A key of ``METHODS``; default ``DEFAULT_METHODS[target.kind]``.
    name : str, optional
        Name used in ``Detection.file`` and messages; default the file's base name, or
        ``"<array>"`` for arrays.
    **options
        Method options: ``sb``: ``exhaustive_retry=True``; ``classic``: ``win=5`` (cornerSubPix
        half-window; shrunk to 0.45 x the corner spacing on small views); ``circles``:
        ``min_diameter=8.0``, ``max_diameter=None`` (px; default: up to a grid cell),
        ``dark=True`` (dark dots on a light board); ``charuco``: ``win=5`` (half-window of the
        re-refinement done for non-8-bit images).

    Returns
    -------
    Detection
        Points in OpenCV's pixel convention (centre of the top-left pixel is (0, 0), x right,
        y down), ordered as described in the module docstring. A bad image or a pattern not
        found gives ``error`` set and empty arrays; this function does not raise for those.

    Raises
    ------
    ValueError
        If ``method`` is unknown or does not fit ``target.kind``.
    TypeError
        If an option is not one of the method's.
    """
    target = _as_target(target)
    method = _check_method(target, method)
    _check_options(method, options)
    detector = _DETECTORS[method]
    if isinstance(image_or_path, np.ndarray):
        label = name or "<array>"
        img, why = image_or_path, None
    else:
        path = Path(image_or_path)
        label = name or path.name
        img, why = _read_image(path)
    if img is None:
        return Detection(label, error=f"{label}: cannot read image ({why})", method=method)
    levels = _grey_levels(img)
    if isinstance(levels, str):
        return Detection(label, error=f"{label}: cannot use image ({levels})", method=method)
    grey8, best = levels
    size = (grey8.shape[1], grey8.shape[0])
    try:
        found = detector(grey8, best, target, **options)
    except cv2.error as exc:
        msg = " ".join(str(exc).split())
        return Detection(label, error=f"{label}: OpenCV failed in method {method}: {msg}",
                         method=method, image_size=size)
    if isinstance(found, str):
        return Detection(label, error=f"{label}: {found}", method=method, image_size=size,
                         no_target=True)
    points, ids, *extra = found
    return Detection(label, points, ids, None, method, size, extra[0] if extra else None,
                     steep_edges=len(extra) > 1 and bool(extra[1]),
                     sharpening=extra[2] if len(extra) > 2 else None)


def image_files(folder: str | os.PathLike) -> list[Path]:
    """The image files directly in ``folder`` (``IMAGE_EXTENSIONS``, any case), sorted by name."""
    folder = Path(folder)
    return sorted((p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS),
                  key=lambda p: p.name)


def _detect_safely(path: Path, target: Target, method: str, options: dict) -> Detection:
    """One image, never raising: any unexpected failure becomes the Detection's error."""
    try:
        return detect_image(path, target, method, **options)
    except Exception as exc:  # noqa: BLE001 - one image must never stop the others
        msg = " ".join(str(exc).split())
        return Detection(path.name, error=f"{path.name}: {type(exc).__name__}: {msg}",
                         method=method, transient=True)


def _worker_init() -> None:
    cv2.setNumThreads(1)  # the pool supplies the parallelism
    ignore_interrupt()  # Ctrl-C: the main process stops the pool (zoomcalib.pool)


class DetectionInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`detect_folder`: ``finished`` holds, per input image, its
    detection or None where it was not finished."""

    def __init__(self, finished: list[Detection | None]):
        super().__init__("detection interrupted")
        self.finished = finished


def detection_pool(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """A pool of ``workers`` spawned detection processes (one OpenCV thread each, Ctrl-C left
    to the main process) for several :func:`detect_folder` calls (``pool=``): a zoom set's
    steps then pay the workers' start once, not once per step. The caller shuts it down
    (:func:`zoomcalib.pool.stop_pool` on an interrupt)."""
    return concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init)


def detect_folder(folder_or_files: str | os.PathLike | Iterable[str | os.PathLike],
                  target: Target | str, method: str | None = None, workers: int = 1,
                  progress: Callable[[int], object] | None = None,
                  pool: concurrent.futures.ProcessPoolExecutor | None = None,
                  **options) -> list[Detection]:
    """Detect the target in every image of a folder, or in a list of image files.

    Parameters
    ----------
    folder_or_files : folder, or iterable of image paths
        A folder: its image files (``IMAGE_EXTENSIONS``, any case, not recursive), sorted by
        name. An iterable: those files, in the order given.
    target : Target or str
        The target, or its pattern spec.
    method : str, optional
        As in :func:`detect_image`.
    workers : int
        Processes; ``> 1`` uses a ``ProcessPoolExecutor`` (spawned workers, one OpenCV thread
        each). Results are in input order and do not depend on ``workers``.
    progress : callable, optional
        Called with 1 each time an image is finished.
    pool : ProcessPoolExecutor, optional
        Workers to use instead of starting ``workers`` new ones (:func:`detection_pool`);
        left running, except on Ctrl-C, which stops it.
    **options
        Method options, as in :func:`detect_image`.

    Returns
    -------
    list of Detection
        One per image, ``file`` the base name. A failing image gets its ``error`` and never
        stops the others.

    Raises
    ------
    ValueError
        If ``method`` is unknown or does not fit the target.
    TypeError
        If an option is not one of the method's.
    FileNotFoundError
        If ``folder_or_files`` is a path that does not exist.

    Notes
    -----
    Workers are started with the ``spawn`` method (OpenCV's thread pool does not survive
    ``fork`` reliably), so a script that calls this with ``workers > 1`` needs the usual
    ``if __name__ == "__main__":`` guard.
    """
    target = _as_target(target)
    method = _check_method(target, method)
    _check_options(method, options)
    if isinstance(folder_or_files, str | os.PathLike):
        root = Path(folder_or_files)
        if not root.exists():
            raise FileNotFoundError(f"{root}: no such folder or file")
        files = image_files(root) if root.is_dir() else [root]
    else:
        files = [Path(f) for f in folder_or_files]
    if workers <= 1 or len(files) <= 1:
        out = []
        for f in files:
            out.append(_detect_safely(f, target, method, options))
            if progress is not None:
                progress(1)
        return out
    results: list[Detection | None] = [None] * len(files)
    own_pool = pool is None
    if own_pool:
        pool = detection_pool(min(workers, len(files)))
    try:
        futures = {pool.submit(_detect_safely, f, target, method, options): i
                   for i, f in enumerate(files)}
        for fut in concurrent.futures.as_completed(futures):
            i = futures[fut]
            try:
                results[i] = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. a worker killed by the system
                name = files[i].name
                msg = " ".join(str(exc).split()) or "worker failed"
                results[i] = Detection(name, error=f"{name}: {type(exc).__name__}: {msg}",
                                       method=method, transient=True)
            if progress is not None:
                progress(1)
    except KeyboardInterrupt:
        stop_pool(pool)
        raise DetectionInterrupted(results) from None
    if own_pool:
        pool.shutdown()
    return [r for r in results if r is not None]


def write_detections(path: str | os.PathLike, detections: Iterable[Detection],
                     spec: str | Target, provenance: dict | None = None) -> Path:
    """Write a detections file (the contract in docs/conventions.md).

    ``{"pattern": SPEC, "images": [{"file", "points", "ids", "error"}, ...]}``, one entry per
    image, points in pixels (OpenCV convention), one image per line. Each entry also carries
    ``method`` and ``image_size`` ([w, h]), and ``fallback`` (one bool per point) when a point's
    refinement failed and it kept the initial detector's position; readers that do not know
    these keys can ignore them (a reader that ignores ``fallback`` uses less accurate points).
    ``provenance`` (JSON-serialisable), when given, is written as a top-level
    ``"provenance"`` key: what the detections were made from (the calibrate job keys its
    detection cache on it). The file is written to a temporary name and renamed, so it is
    never left half written.
    """
    path = Path(path)
    spec = spec.spec if isinstance(spec, Target) else str(spec)
    lines = []
    for d in detections:
        entry = d.to_dict()
        entry["method"] = d.method
        entry["image_size"] = list(d.image_size)
        lines.append(json.dumps(entry))
    head = '{"pattern": ' + json.dumps(spec)
    if provenance is not None:
        head += ', "provenance": ' + json.dumps(provenance)
    text = head + ', "images": [\n' + ",\n".join(lines) + "\n]}\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def read_detections(path: str | os.PathLike) -> tuple[str, list[Detection]]:
    """Read a detections file written by :func:`write_detections` (or by any writer of the
    contract).

    Returns
    -------
    spec : str
        The pattern spec (``parse_pattern(spec)`` gives the target).
    detections : list of Detection

    Raises
    ------
    ValueError
        One-line message naming the file when it is not a detections file.
    """
    path = Path(path)
    data = read_json(path, path.name)
    if not isinstance(data, dict) or "pattern" not in data \
            or not isinstance(data.get("images"), list):
        raise ValueError(f"{path.name}: not a detections file (needs 'pattern' and 'images')")
    out = []
    for k, entry in enumerate(data["images"]):
        try:
            out.append(Detection.from_dict(entry))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path.name}: image entry {k} is malformed ({exc})") from None
    return str(data["pattern"]), out
