"""What keeps the calibrate job from returning a wrong calibration without saying so.

- :func:`step_file_stems`: file names for the zoom steps that no two steps share;
- :func:`detect_with_cache`: detections reused only for images whose content (size and
  BLAKE2b hash) and detection settings (pattern, method, options, zoomcalib and OpenCV
  versions, digest of the detection code) are unchanged;
- :func:`keep_majority_size`: an image of another size than most of its step is left out,
  named, instead of dropping the step;
- :func:`clear_previous_outputs` and :func:`write_manifest`: each run owns its output folder;
  ``OUT/manifest.json`` lists the files it wrote, with the command and the inputs.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import unicodedata
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import cv2

from .. import __version__
from .. import detect as detect_package
from ..detect import detect_folder, read_detections, write_detections
from ..detect.opencv import Detection, DetectionInterrupted, default_method
from ..io import read_json
from ..targets import Target

__all__ = [
    "MANIFEST",
    "OWN_FILE_PATTERNS",
    "clear_previous_outputs",
    "detect_with_cache",
    "detection_settings",
    "image_fingerprints",
    "keep_majority_size",
    "step_file_stems",
    "write_manifest",
]

#: The manifest of a calibrate run, in ``OUT``.
MANIFEST = "manifest.json"

#: Files the calibrate job writes in ``OUT`` (glob patterns relative to it); a run removes the
#: ones it does not write itself.
_OWN_FILES: tuple[str, ...] = (
    "calibration.json", "calibration.yml", "zoom_calibration.csv",
    "zoom_calibration_unsmoothed.csv", "zoom_calibration_unsmoothed_correlation.json",
    "zoom_model.json",
    "principal_point_path.png", "focal_length.png", "residuals_*.png", "cross_validation.png",
    "report.html",
    MANIFEST,
    "detections/*.json", "opencv/*.yml", "ros/*.yaml", "mrcal/*.cameramodel",
    "zoom_model_grid.csv")
OWN_FILE_PATTERNS: tuple[str, ...] = _OWN_FILES + tuple(f"{p}.tmp" for p in _OWN_FILES)

_UNSAFE = re.compile(r"[^\w.-]")  # \w: Unicode letters, digits and "_"
_MAX_STEM_BYTES = 120


def _short_hash(text: str) -> str:
    return hashlib.blake2b(text.encode("utf-8"), digest_size=4).hexdigest()


def _stem(step: str) -> str:
    """``step`` with characters that are unsafe in file names replaced by ``_`` and, when
    anything had to change, a short hash of the exact name appended."""
    if step == ".":
        return "root"
    stem = _UNSAFE.sub("_", unicodedata.normalize("NFC", step))
    if stem.startswith("."):
        stem = "_" + stem[1:]
    if stem == step and len(stem.encode("utf-8")) <= _MAX_STEM_BYTES:
        return stem
    while len(stem.encode("utf-8")) > _MAX_STEM_BYTES:
        stem = stem[:-1]
    return f"{stem}-{_short_hash(step)}"


def step_file_stems(steps: Iterable[str]) -> dict[str, str]:
    """File-name stems for zoom steps (``detections/<stem>.json``, ``residuals_<stem>.png``).

    A name made only of Unicode letters, digits, ``_``, ``.`` and ``-`` is kept as it is
    (``広角`` stays ``広角``); any other is made safe and gets the first 8 hex digits of the
    BLAKE2b hash of the exact name (``f ü`` -> ``f_ü-<hash>``, distinct from ``f é`` and
    from a step folder literally named ``f_ü``). Stems that would still coincide when case
    is ignored (``Zoom_1`` and ``zoom_1`` on a case-insensitive file system) all get the hash.
    The flat folder's step ``"."`` is ``root``.

    Returns
    -------
    dict of str to str
        Step name -> stem; no two stems are equal ignoring case.
    """
    steps = list(steps)
    stems = {s: _stem(s) for s in steps}
    counts = Counter(v.casefold() for v in stems.values())
    for s in steps:
        if counts[stems[s].casefold()] > 1:
            stems[s] = f"{_UNSAFE.sub('_', s)[:_MAX_STEM_BYTES // 4]}-{_short_hash(s)}"
    if len({v.casefold() for v in stems.values()}) != len(steps):  # pragma: no cover
        raise ValueError("zoom step names give clashing file names: "
                         + ", ".join(repr(s) for s in steps))
    return stems


# ----------------------------------------------------------------------------------------------
# detection cache


def _file_digest(path: Path) -> str:
    h = hashlib.blake2b(digest_size=16)
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def image_fingerprints(files: Iterable[Path]) -> list[dict]:
    """Per image ``{"file": base name, "bytes": size, "blake2b": 128-bit hex digest}``."""
    return [{"file": f.name, "bytes": f.stat().st_size, "blake2b": _file_digest(f)}
            for f in files]


def byte_identical(files: list[Path]) -> dict[Path, Path]:
    """Each image whose bytes equal an earlier one's (in ``files``' order), mapped to that
    first one: a copy under another name is one view, not two."""
    first: dict[tuple[int, str], Path] = {}
    copies = {}
    for f in files:
        key = (f.stat().st_size, _file_digest(f))
        if key in first:
            copies[f] = first[key]
        else:
            first[key] = f
    return copies


def _detector_code_digest() -> str:
    """BLAKE2b (64-bit, hex) of the source files of ``zoomcalib.detect``: a change of the
    detection code between releases also invalidates cached detections."""
    h = hashlib.blake2b(digest_size=8)
    for f in sorted(Path(detect_package.__file__).parent.glob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def detection_settings(target: Target, method: str | None, options: Mapping | None = None
                       ) -> dict:
    """Everything besides the images that changes the detections: pattern, method (the
    target's default resolved), method options, zoomcalib and OpenCV versions and the
    detection code's digest."""
    return {"pattern": target.spec, "method": method or default_method(target),
            "options": dict(options or {}), "zoomcalib": __version__,
            "detector_code": _detector_code_digest(), "opencv": cv2.__version__}


def _fingerprint_key(fp: Mapping) -> tuple:
    return fp["file"], int(fp["bytes"]), fp["blake2b"]


def _cached(cache: Path, settings: dict) -> tuple[dict[tuple, Detection], list[str]]:
    """Reusable detections of ``cache`` by image fingerprint, and the image names it holds
    (empty when it is missing, unreadable, older than the fingerprints, or made otherwise)."""
    if not cache.is_file():
        return {}, []
    try:
        prov = read_json(cache).get("provenance")
        _, dets = read_detections(cache)
    except (ValueError, OSError, AttributeError):
        return {}, []
    if not isinstance(prov, dict) or prov.get("settings") != settings:
        return {}, []
    images = prov.get("images")
    if not isinstance(images, list) or len(images) != len(dets):
        return {}, []
    try:
        keyed = {_fingerprint_key(fp): d for fp, d in zip(images, dets, strict=True)
                 if fp.get("file") == d.file and fp.get("reuse", True)}
    except (KeyError, TypeError, ValueError, AttributeError):
        return {}, []
    return keyed, [d.file for d in dets]


def detect_with_cache(cache: Path, files: list[Path], target: Target, settings: dict,
                      workers: int = 1, progress: Callable[[int], object] | None = None,
                      pool=None) -> tuple[list[Detection], int, list[dict]]:
    """Detections of ``files``, reusing those of ``cache`` made from the same image content
    with the same ``settings`` (:func:`detection_settings`); the others are detected, and the
    cache is rewritten when anything changed. A failure from outside the image (``transient``:
    a worker killed, an unexpected exception) is written with ``"reuse": false`` in its
    fingerprint and detected again next time. ``pool``: detection workers to use
    (:func:`~zoomcalib.detect.opencv.detection_pool`), else ``workers`` new ones.

    Returns
    -------
    detections : list of Detection
        In the order of ``files``.
    reused : int
        How many came from the cache.
    fingerprints : list of dict
        :func:`image_fingerprints` of ``files``.
    """
    prints = image_fingerprints(files)
    cached, cached_names = _cached(cache, settings)
    found = [cached.get(_fingerprint_key(fp)) for fp in prints]
    todo = [f for f, d in zip(files, found, strict=True) if d is None]
    reused = len(files) - len(todo)
    if reused and progress is not None:
        progress(reused)
    try:
        fresh = iter(detect_folder(todo, target, settings["method"], workers=workers,
                                   progress=progress, pool=pool, **settings["options"])
                     if todo else [])
    except DetectionInterrupted as stop:  # keep what was finished: a rerun resumes there
        done = iter(stop.finished)
        kept = [(fp, d if d is not None else next(done))
                for fp, d in zip(prints, found, strict=True)]
        kept = [(fp, d) for fp, d in kept if d is not None and not d.transient]
        if kept:
            write_detections(cache, [d for _, d in kept], settings["pattern"],
                             provenance={"settings": settings,
                                         "images": [fp for fp, _ in kept]})
        raise
    dets = [d if d is not None else next(fresh) for d in found]
    if todo or cached_names != [f.name for f in files]:
        images = [fp | {"reuse": False} if d.transient else fp
                  for fp, d in zip(prints, dets, strict=True)]
        write_detections(cache, dets, settings["pattern"],
                         provenance={"settings": settings, "images": images})
    return dets, reused, prints


# ----------------------------------------------------------------------------------------------
# image sizes


def keep_majority_size(dets: list[Detection]
                       ) -> tuple[list[Detection], list[Detection], tuple[int, int] | None]:
    """Split the detections of one step by image size: the size most images have wins.

    Images that could not be read (size 0 x 0) are kept (they carry their own error).

    Returns
    -------
    kept, odd : list of Detection
    size : (int, int) or None
        The step's (width, height), px; None when no image could be read.

    Raises
    ------
    ValueError
        When two sizes are equally common: nothing tells which is the camera's. The message
        lists the sizes and how many images have each.
    """
    counts = Counter(d.image_size for d in dets if d.image_size != (0, 0))
    if not counts:
        return list(dets), [], None
    ranked = counts.most_common()
    if len(ranked) > 1 and ranked[0][1] == ranked[1][1]:
        sizes = ", ".join(f"{w}x{h}: {n} image{'s' if n > 1 else ''}" for (w, h), n in ranked)
        raise ValueError(f"images of different sizes and no majority ({sizes}); put each "
                         "camera's images in a folder of their own")
    size = ranked[0][0]
    kept = [d for d in dets if d.image_size in ((0, 0), size)]
    odd = [d for d in dets if d.image_size not in ((0, 0), size)]
    return kept, odd, size


# ----------------------------------------------------------------------------------------------
# output folder


def _inside(out: Path, rel: str) -> Path | None:
    """``out / rel`` when ``rel`` is a relative path that stays inside ``out``, else None."""
    p = Path(rel)
    if p.is_absolute() or ".." in p.parts:
        return None
    return out / p


def clear_previous_outputs(out: Path, keep: Iterable[str] = (),
                           protect: Iterable[Path] = ()) -> list[Path]:
    """Remove the files an earlier run left in ``out``: those its manifest lists and those
    matching :data:`OWN_FILE_PATTERNS`, except ``keep`` (paths relative to ``out``, e.g. this
    run's detection caches) and ``protect`` (e.g. the input images, should ``out`` hold them).
    Other files are never touched.

    Returns
    -------
    list of Path
        The files removed.
    """
    if not out.is_dir():
        return []
    keep_set = {Path(k).as_posix() for k in keep}
    protected = {os.path.realpath(p) for p in protect}
    candidates = {p for pattern in OWN_FILE_PATTERNS for p in out.glob(pattern)}
    try:
        listed = read_json(out / MANIFEST).get("files", []) if (out / MANIFEST).is_file() else []
    except (ValueError, OSError, AttributeError):
        listed = []
    for rel in listed if isinstance(listed, list) else []:
        p = _inside(out, str(rel))
        if p is not None:
            candidates.add(p)
    removed = []
    for p in sorted(candidates):
        if not p.is_file() or p.relative_to(out).as_posix() in keep_set \
                or os.path.realpath(p) in protected:
            continue
        p.unlink()
        removed.append(p)
    return removed


def write_manifest(out: Path, files: Iterable[Path], inputs: Mapping, call: Mapping) -> Path:
    """Write ``OUT/manifest.json``: ``{"format": "zoomcalib-calibrate-manifest", "version": 1,
    "command": sys.argv, "call": call, "zoomcalib": version, "inputs": inputs, "files": [...]}``
    with ``files`` relative to ``out`` (POSIX separators), sorted; the manifest is not in it."""
    # absolute, symbolic links kept: a detections folder linked from another run is listed
    # where it is used
    root = Path(os.path.abspath(out))
    rel = sorted({Path(os.path.abspath(f)).relative_to(root).as_posix() for f in files}
                 - {MANIFEST})
    doc = {"format": "zoomcalib-calibrate-manifest", "version": 1, "command": list(sys.argv),
           "call": dict(call), "zoomcalib": __version__, "inputs": dict(inputs), "files": rel}
    path = out / MANIFEST
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)
    return path
