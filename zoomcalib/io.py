"""File formats: CSV tables and JSON written by the commands."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["write_csv", "read_csv", "write_json", "read_json"]


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def write_csv(path: str | Path, rows: Sequence[dict], columns: Sequence[str] | None = None,
              float_format: str = "{:.10g}") -> Path:
    """Write dict rows as CSV; floats with ``float_format`` (10 significant digits)."""
    path = Path(path)
    columns = list(columns or (rows[0].keys() if rows else []))
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        for r in rows:
            w.writerow([float_format.format(v) if isinstance(v, float | np.floating) else _plain(v)
                        for v in (r.get(c, "") for c in columns)])
    return path


def read_csv(path: str | Path) -> list[dict]:
    """Read a CSV into dict rows, turning numeric fields into floats."""
    out = []
    with Path(path).open(newline="") as fh:
        for r in csv.DictReader(fh):
            row = {}
            for k, v in r.items():
                try:
                    row[k] = float(v)
                except (TypeError, ValueError):
                    row[k] = v
            out.append(row)
    return out


def write_json(path: str | Path, doc: dict) -> Path:
    path = Path(path)
    path.write_text(json.dumps(doc, indent=1, default=_plain) + "\n")
    return path


def read_json(path: str | Path, name: str | None = None):
    """Parse a JSON file; a file that is not JSON raises ``ValueError`` with one line naming it
    (``name``, default the path) and where the parse failed."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{name or path}: not JSON ({exc.msg} at line {exc.lineno})") from None
