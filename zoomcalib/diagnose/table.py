"""Measured per-zoom principal points, as read from a ``zoom_calibration.csv``.

A :class:`ZoomTable` holds one row per calibrated zoom step: the measured focal length and
principal point (px, OpenCV convention), their 1-sigma when known, and the capture conditions
that the discrepancy causes need (direction of the last zoom move, capture order, focus,
temperature).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..calibrate.io import KEYSTONE_COLUMNS

__all__ = ["ZoomTable", "direction_sign"]

_IN = {"in", "+", "+1", "1", "up", "tele"}
_OUT = {"out", "-", "-1", "down", "wide"}


def direction_sign(value, where: str) -> float:
    """+1 for a last zoom move ``in`` (towards tele), -1 for ``out``, 0 when unknown (empty)."""
    if value is None:
        return 0.0
    text = str(value).strip().lower()
    if text in ("", "nan", "none"):
        return 0.0
    if text in _IN:
        return 1.0
    if text in _OUT:
        return -1.0
    raise ValueError(f"{where}: direction must be 'in' or 'out', got {value!r}")


def _column(rows: Sequence[Mapping], key: str) -> np.ndarray | None:
    """(N,) float column, or None when the column is absent or entirely empty."""
    vals = [r.get(key) for r in rows]
    if all(v is None or v == "" for v in vals):
        return None
    return np.array([np.nan if v is None or v == "" else float(v) for v in vals])


def _single_backend(rows: Sequence[Mapping], steps: list[str], source: str) -> str | None:
    """The one backend named in the rows' ``backend`` column (None when no row names one).

    Raises
    ------
    ValueError
        One line naming ``source`` and the steps of each backend when the rows name several:
        two backends' principal points differ by their own biases, which would read as a
        zoom-dependent discrepancy.
    """
    by_backend: dict[str, list[str]] = {}
    for step, r in zip(steps, rows, strict=True):
        name = str(r.get("backend") or "").strip()
        if name and name.lower() not in ("nan", "none"):
            by_backend.setdefault(name, []).append(step)
    if len(by_backend) > 1:
        parts = "; ".join(f"{b}: step{'s' if len(s) > 1 else ''} {', '.join(s)}"
                          for b, s in by_backend.items())
        raise ValueError(f"{source}: mixed calibration backends ({parts}); keep one "
                         "backend's rows (e.g. calibrate with --backend opencv)")
    return next(iter(by_backend), None)


def _keystone(rows: Sequence[Mapping]) -> np.ndarray | None:
    """(N, 4, 2) keystone response of every row, None unless all rows have it finite (a
    per-step OpenCV calibration and the zoom-wide adjustment write it; the bundle does not)."""
    cols = [_column(rows, key) for key in KEYSTONE_COLUMNS]
    if any(c is None or not np.all(np.isfinite(c)) for c in cols):
        return None
    return np.stack(cols, axis=-1).reshape(len(rows), 4, 2)


@dataclass
class ZoomTable:
    """Per-zoom calibration results.

    Attributes
    ----------
    zoom : (N,) ndarray
        The zoom setting in the user's unit (any monotone setting).
    fx, fy, cx, cy : (N,) ndarray
        Focal lengths and principal point, px.
    sd_cx, sd_cy : (N,) ndarray
        1-sigma of the principal point, px (zeros when the table has none).
    direction : (N,) ndarray or None
        +1 after a move in, -1 after a move out, 0 unknown.
    sequence, focus, temperature : (N,) ndarray or None
        Capture order, focus setting, temperature, when the table has them.
    session : list of str or None
        Each row's capture session (``calibrate`` writes it where the steps were captured in
        more than one), when every row has one.
    step : list of str
    source : str
        Where the table came from (named in error messages).
    backend : str or None
        The calibration backend of every row (the table's ``backend`` column), None when the
        table does not say. A table whose rows come from different backends is refused.
    keystone : (N, 4, 2) ndarray or None
        Each row's calibration response to a keystone of the image (the ``keystone_*``
        columns): rows ``A`` (cx, cy) and ``B`` (p1, p2) of
        :func:`zoomcalib.calibrate.opencv_backend.keystone_response`; None unless every row
        has all of them.
    pp_correlation : (2N, 2N) ndarray or None
        The correlation of the rows' measured principal points, ordered
        ``(cx_0, cy_0, cx_1, ...)``: the rows of one adjustment without its smoothness
        prior share its aspect ratio and boards (``zoom_calibration_unsmoothed_correlation.json``
        beside its table, :func:`zoomcalib.diagnose.run.load_zoom_table`); None for
        independent rows.
    calibrations : list of RowCalibration or None
        Each row's per-step calibration (observations and solution), when the diagnosis made
        them itself (an image folder): its group terms then use each calibration's own response
        (:mod:`zoomcalib.diagnose.response`). Not read from a table file.
    response_cache : dict
        Those responses, once computed, by (group, kind, pitch, lens states).
    """

    zoom: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    sd_cx: np.ndarray
    sd_cy: np.ndarray
    direction: np.ndarray | None = None
    sequence: np.ndarray | None = None
    focus: np.ndarray | None = None
    temperature: np.ndarray | None = None
    session: list[str] | None = None
    step: list[str] = field(default_factory=list)
    source: str = "table"
    backend: str | None = None
    keystone: np.ndarray | None = None
    pp_correlation: np.ndarray | None = field(default=None, repr=False, compare=False)
    calibrations: list | None = field(default=None, repr=False, compare=False)
    response_cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n(self) -> int:
        return len(self.zoom)

    @property
    def has_sd(self) -> bool:
        return bool(np.any(self.sd_cx > 0) or np.any(self.sd_cy > 0))

    @property
    def principal_point(self) -> np.ndarray:
        """(N, 2) measured (cx, cy), px."""
        return np.stack([self.cx, self.cy], axis=-1)

    @classmethod
    def from_rows(cls, rows: Sequence[Mapping], source: str = "table") -> ZoomTable:
        """Build from dict rows (as :func:`zoomcalib.calibrate.io.read_zoom_table` returns).

        Raises
        ------
        ValueError
            Naming ``source`` and the row when a value cannot be used.
        """
        if len(rows) == 0:
            raise ValueError(f"{source}: the table has no rows")
        if any(str(r.get("mode") or "").strip() == "zoom-wide" for r in rows):
            raise ValueError(f"{source}: rows of the zoom-wide adjustment are tied by its "
                             "smoothness prior, and the diagnosis needs independent rows: "
                             "diagnose the table with zoom_calibration_unsmoothed.csv beside "
                             "it (calibrate writes it), calibrate with --per-step, or diagnose "
                             "the image folder")
        req = {}
        for key in ("zoom", "fx", "fy", "cx", "cy"):
            col = _column(rows, key)
            if col is None:
                raise ValueError(f"{source}: column {key} is missing or empty")
            bad = np.flatnonzero(~np.isfinite(col))
            if bad.size:
                raise ValueError(f"{source} row {bad[0] + 1}: {key} is not a finite number")
            req[key] = col
        for key in ("fx", "fy"):
            bad = np.flatnonzero(req[key] <= 0)
            if bad.size:
                raise ValueError(f"{source} row {bad[0] + 1}: {key} must be positive")
        sds = {}
        for key in ("sd_cx", "sd_cy"):
            col = _column(rows, key)
            col = np.zeros(len(rows)) if col is None else np.nan_to_num(col, nan=0.0)
            if np.any(col < 0):
                raise ValueError(f"{source} row {int(np.argmax(col < 0)) + 1}: {key} is negative")
            sds[key] = col
        direction = None
        if any(r.get("direction") not in (None, "") for r in rows):
            direction = np.array([direction_sign(r.get("direction"), f"{source} row {k + 1}")
                                  for k, r in enumerate(rows)])
        extras = {}
        for key in ("sequence", "focus", "temperature"):
            col = _column(rows, key)
            if col is not None and np.any(~np.isfinite(col)):
                k = int(np.argmax(~np.isfinite(col)))
                raise ValueError(f"{source} row {k + 1}: {key} is empty or not a number while "
                                 f"other rows have it")
            extras[key] = col
        steps = [str(r.get("step", k)) for k, r in enumerate(rows)]
        backend = _single_backend(rows, steps, source)
        session = [str(r.get("session") or "") for r in rows]
        return cls(**req, **sds, direction=direction, step=steps, source=source,
                   backend=backend, keystone=_keystone(rows), **extras,
                   session=session if all(session) else None)

    def zoom_groups(self) -> np.ndarray:
        """(N,) int label of the distinct zoom setting of each row (for held-out-step CV)."""
        _, inverse = np.unique(np.round(self.zoom, 9), return_inverse=True)
        return inverse
