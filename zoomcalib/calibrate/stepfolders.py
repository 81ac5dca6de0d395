"""A folder of zoom steps: each step's images and its zoom, and when its frames were taken.

:func:`zoom_steps` reads a folder as one step per subfolder (or one flat step, ``"."``). Each
step's zoom comes from ``steps.csv`` (``step,zoom`` and optional ``direction``, ``sequence``,
``focus``, ``temperature``, ``session`` columns), else the number in the step's name
(:func:`zoom_from_name`), else the images' EXIF focal length (:func:`exif_focal_length`), and
``zoom_source`` says which. :func:`capture_date` and :func:`capture_sittings` read the capture
times that camera and recorder names carry (``...20250818084126...``): the capture day of a
step, and the sittings of its frames. :func:`csv_reader` opens the project's CSV files with
their header checked (``steps.csv`` here, ``zoom_calibration.csv`` in
:mod:`zoomcalib.calibrate.io`).
"""

from __future__ import annotations

import csv
import datetime
import math
import os
import re
from pathlib import Path

import numpy as np

from zoomcalib.detect.opencv import IMAGE_EXTENSIONS, image_files

__all__ = ["capture_date", "capture_sittings", "csv_reader", "exif_focal_length",
           "ignored_top_images", "zoom_from_name", "zoom_steps"]


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def zoom_from_name(name: str) -> float | None:
    """The zoom value written in a step folder's name, or None.

    The name must hold exactly one number (digits, optionally with a decimal point); with
    none, or several (e.g. ``f2.8_zoom3``), the name does not say the zoom.

    Examples
    --------
    >>> zoom_from_name("zoom_3x"), zoom_from_name("zoom_07"), zoom_from_name("z2.5")
    (3.0, 7.0, 2.5)
    >>> zoom_from_name("wide") is None, zoom_from_name("f2.8_zoom3") is None
    (True, True)
    """
    found = _NUMBER.findall(name)
    return float(found[0]) if len(found) == 1 else None


def exif_focal_length(path: str | os.PathLike, errors: list[str] | None = None
                      ) -> float | None:
    """The EXIF FocalLength (tag 0x920A, mm) of an image, or None when absent, unreadable or
    not a positive finite number; why a present value could not be used is appended to
    ``errors`` (``"<file>: <reason>"``) when given.

    Uses Pillow when it is installed; without Pillow, returns None.
    """
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return None
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(0x8769).get(0x920A)  # Exif sub-IFD, FocalLength
            if value is None:
                value = exif.get(0x920A)
    except Exception as exc:  # noqa: BLE001 - Pillow raises many kinds; said in ``errors``
        if errors is not None:
            errors.append(f"{Path(path).name}: {' '.join(str(exc).split()) or type(exc).__name__}")
        return None
    if value is None:
        return None
    try:
        if isinstance(value, tuple) and len(value) == 2:
            f = float(value[0]) / float(value[1])
        else:
            f = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        f = math.nan
    if math.isfinite(f) and f > 0:
        return f
    if errors is not None:
        errors.append(f"{Path(path).name}: EXIF FocalLength {value!r} is not a length in mm")
    return None


def _exif_zoom(folder: Path) -> tuple[float | None, dict]:
    """The median EXIF focal length of the folder's images (None without one) and the step's
    extras: ``zoom_source`` and, when some images' EXIF could not be read, ``zoom_note``."""
    files, errors = image_files(folder), []
    values = [f for f in (exif_focal_length(p, errors) for p in files) if f is not None]
    zoom = float(np.median(values)) if values else None
    extras: dict = {"zoom_source": "exif" if zoom is not None else None}
    if errors:
        extras["zoom_note"] = (f"EXIF unreadable in {len(errors)} of {len(files)} images "
                               f"(first: {errors[0]})")
    return zoom, extras


def _natural_key(name: str):
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower())
            for t in re.split(r"(\d+)", name) if t]


_STEPS_OPTIONAL = {"direction": str, "sequence": int, "focus": float, "temperature": float,
                   "session": str}


#: A capture date in a file name: ``YYYYMMDD`` (2000-2099), not inside a longer number
#: (``live_ch0_20250805092246.png``, ``IMG_20250805_092246.jpg``).
_NAME_DATE = re.compile(r"(?<!\d)(20\d{2})(0[1-9]|1[0-2])(0[1-9]|[12]\d|3[01])"
                        r"(?=\d{6}(?!\d)|(?!\d))")


def csv_reader(path: Path) -> tuple[csv.DictReader, list[str]]:
    """A dict reader over a CSV file (BOM tolerated) and its stripped header; a file that
    cannot be read gives a one-line ``ValueError`` naming it."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or type(exc).__name__})") from None
    reader = csv.DictReader(text.splitlines())
    return reader, [h.strip() for h in (reader.fieldnames or [])]


def _read_steps_csv(path: Path) -> dict[str, tuple[float, dict]]:
    reader, header = csv_reader(path)
    missing = [c for c in ("step", "zoom") if c not in header]
    if missing:
        raise ValueError(f"{path}: missing column{'s' if len(missing) > 1 else ''} "
                         f"{', '.join(missing)} (needs step, zoom; optional direction, sequence, "
                         "focus, temperature, session)")
    reader.fieldnames = header
    out: dict[str, tuple[float, dict]] = {}
    for k, raw in enumerate(reader, start=1):
        where = f"{path} row {k}"
        if None in raw:
            raise ValueError(f"{where}: more cells than columns")
        step = (raw.get("step") or "").strip()
        if not step:
            raise ValueError(f"{where}: step is empty")
        if step in out:
            raise ValueError(f"{where}: step {step!r} listed twice")
        ztext = (raw.get("zoom") or "").strip()
        try:
            zoom = float(ztext)
        except ValueError:
            raise ValueError(f"{where}: zoom {ztext!r} is not a number") from None
        if not math.isfinite(zoom):
            raise ValueError(f"{where}: zoom {ztext!r} is not finite")
        extras: dict = {"zoom_source": "steps.csv"}
        for col, kind in _STEPS_OPTIONAL.items():
            cell = (raw.get(col) or "").strip()
            if not cell:
                continue
            if col == "direction":
                if cell.lower() not in ("in", "out"):
                    raise ValueError(f"{where}: direction {cell!r} must be 'in' or 'out'")
                extras[col] = cell.lower()
                continue
            if col == "session":
                extras[col] = cell
                continue
            try:
                v = float(cell)
            except ValueError:
                raise ValueError(f"{where}: {col} {cell!r} is not a number") from None
            if kind is int:
                if not v.is_integer():
                    raise ValueError(f"{where}: sequence {cell!r} is not an integer")
                v = int(v)
            extras[col] = v
        out[step] = (zoom, extras)
    return out


def capture_date(names: list[str]) -> tuple[str | None, int]:
    """The capture date most of ``names`` (image file names) carry, ``YYYY-MM-DD``, and how
    many names carry another date or none; ``(None, len(names))`` when no name has one.

    Examples
    --------
    >>> capture_date(["live_ch0_20250805092246.png", "live_ch0_20250805102314.png",
    ...               "1x_zoom_1.png"])
    ('2025-08-05', 1)
    >>> capture_date(["frame_00012345.png"])
    (None, 1)
    """
    dates = [m.group(1) + "-" + m.group(2) + "-" + m.group(3) if m else None
             for m in (_NAME_DATE.search(n) for n in names)]
    known = [d for d in dates if d]
    if not known:
        return None, len(names)
    best = max(dict.fromkeys(known), key=known.count)
    return best, len(names) - known.count(best)


_NAME_TIME = re.compile(r"(?<!\d)(20\d{2}(?:0[1-9]|1[0-2])(?:0[1-9]|[12]\d|3[01])"
                        r"(?:[01]\d|2[0-3])[0-5]\d[0-5]\d)(?!\d)")


def capture_sittings(names: list[str], gap_hours: float = 1.0
                     ) -> list[tuple[datetime.datetime, datetime.datetime, int]]:
    """The sittings of ``names`` (image file names carrying a capture time
    ``YYYYMMDDhhmmss``): in time order, a new sitting after a gap of more than ``gap_hours``.
    Per sitting its first and last capture time and its number of names; names without a
    time are left out (``[]`` when none has one).

    Examples
    --------
    >>> [(a.strftime("%H:%M"), b.strftime("%H:%M"), n) for a, b, n in capture_sittings(
    ...     ["live_ch0_20250805120423.png", "live_ch0_20250805121945.png",
    ...      "live_ch0_20250805150754.png", "1x_zoom_1.png"])]
    [('12:04', '12:19', 2), ('15:07', '15:07', 1)]
    """
    times = sorted(datetime.datetime.strptime(m.group(1), "%Y%m%d%H%M%S")
                   for m in (_NAME_TIME.search(n) for n in names) if m)
    gap = datetime.timedelta(hours=gap_hours)
    sittings: list[list[datetime.datetime]] = []
    for t in times:
        if not sittings or t - sittings[-1][-1] > gap:
            sittings.append([])
        sittings[-1].append(t)
    return [(group[0], group[-1], len(group)) for group in sittings]


def _is_output_folder(folder: Path) -> bool:
    """True for a calibrate job's output folder (its figures are images, not a zoom step)."""
    return (folder / "calibration.json").is_file() or (folder / "manifest.json").is_file()


def _step_subfolders(root: Path) -> list[Path]:
    """The subfolders of ``root`` that hold images, in natural order; hidden folders and the
    calibrate job's output folders (holding ``calibration.json`` or ``manifest.json``, e.g.
    ``zoomcalib-calibration`` when the job is run from inside the image folder) are skipped."""
    return sorted((p for p in root.iterdir()
                   if p.is_dir() and not p.name.startswith(".") and not _is_output_folder(p)
                   and image_files(p)),
                  key=lambda p: _natural_key(p.name))


def ignored_top_images(folder: str | os.PathLike) -> list[Path]:
    """The images directly in ``folder`` that :func:`zoom_steps` leaves out, because
    ``folder`` has step subfolders (empty for a flat folder)."""
    root = Path(folder)
    return image_files(root) if _step_subfolders(root) else []


def zoom_steps(folder: str | os.PathLike) -> list[tuple[str, Path, float | None, dict]]:
    """The zoom steps of an image folder (docs/conventions.md, "File contracts").

    * ``DIR`` has subfolders that hold images (hidden ones and the calibrate job's own output
      folders skipped): every such subfolder is a step, named after
      the subfolder, in natural name order (``zoom_2`` before ``zoom_10``). Its zoom comes from
      ``DIR/steps.csv`` (columns ``step`` = subfolder name, ``zoom``; optional ``direction``
      ``in``/``out``, ``sequence``, ``focus``, ``temperature``, ``session``), else from the one
      number in the
      folder name (``zoom_3x`` -> 3, ``zoom_07`` -> 7), else from the median EXIF FocalLength
      (mm) of its images, else None. Images directly in ``DIR`` are then not calibrated (a
      printed target or a preview next to the steps); :func:`ignored_top_images` lists them.
    * Otherwise ``DIR`` holds images directly: one step named ``"."``. Its zoom is the ``"."``
      row of ``DIR/steps.csv`` when there is one, else the images' EXIF FocalLength, else None.

    When ``steps.csv`` exists it must list every step subfolder, and only those: a name that
    does not match is far more often a typo than an intended gap, and mixing zoom sources
    (steps.csv units for some steps, folder-name numbers for others) would corrupt the table.

    Parameters
    ----------
    folder : path

    Returns
    -------
    list of (str, Path, float or None, dict)
        ``(step name, image folder, zoom, extras)``; ``extras`` has ``zoom_source``
        (``"steps.csv"``, ``"name"``, ``"exif"`` or None) and the optional steps.csv columns
        given for that step.

    Raises
    ------
    FileNotFoundError
        If ``folder`` does not exist.
    ValueError
        One line naming the file (and row) when ``steps.csv`` is malformed or does not match
        the subfolders, or when the folder holds no images at all.
    """
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder")
    csv_path = root / "steps.csv"
    table = _read_steps_csv(csv_path) if csv_path.is_file() else None
    subdirs = _step_subfolders(root)
    if not subdirs and image_files(root):
        zoom, extras = None, {"zoom_source": None}
        if table is not None and "." in table:
            zoom, extras = table["."]
            extras = dict(extras)
        else:
            zoom, extras = _exif_zoom(root)
        return [(".", root, zoom, extras)]
    if not subdirs:
        exts = ", ".join(IMAGE_EXTENSIONS)
        raise ValueError(f"{root}: no images ({exts}) in the folder or its subfolders")
    steps = []
    if table is not None:
        names = {p.name for p in subdirs}
        unknown = [s for s in table if s not in names]
        if unknown:
            raise ValueError(f"{csv_path}: step {unknown[0]!r} is not an image subfolder of "
                             f"{root}")
        absent = [p.name for p in subdirs if p.name not in table]
        if absent:
            raise ValueError(f"{csv_path}: no row for step subfolder {absent[0]!r}")
    for p in subdirs:
        if table is not None:
            zoom, extras = table[p.name]
            steps.append((p.name, p, zoom, dict(extras)))
            continue
        zoom = zoom_from_name(p.name)
        if zoom is not None:
            steps.append((p.name, p, zoom, {"zoom_source": "name"}))
            continue
        zoom, extras = _exif_zoom(p)
        steps.append((p.name, p, zoom, extras))
    return steps
