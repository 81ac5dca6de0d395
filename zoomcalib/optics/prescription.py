"""Lens prescriptions: reading, validating and holding a multi-group zoom lens.

A prescription is the JSON form used in ``zoomcalib/optics/lenses/*.json``: a list of spherical
(or flat) surfaces with the thickness that follows each one, the refractive index after it,
the group it belongs to, the aperture stop, and the three variable gaps that the zoom cams move.

Conventions
-----------
- Lengths in millimetres. The optical axis is +z, light travels towards +z.
- ``curvature = 1 / radius`` (0 for a flat surface); a positive radius has its centre of
  curvature on the +z side of the vertex.
- Surface indices in this module are 0-based; the JSON files number surfaces from 1.
- Surface ``k``'s vertex lies at ``z[k] = sum(thickness[:k])``; surface 0 at z = 0.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = ["Prescription", "PrescriptionError", "load_prescription", "builtin_lenses"]


class PrescriptionError(ValueError):
    """A lens file that cannot be used, with the file and the offending field in the message."""


@dataclass(frozen=True)
class Prescription:
    """A zoom lens as a sequence of surfaces grouped into rigid groups.

    Attributes
    ----------
    name : str
    curvature : (N,) ndarray
        Surface curvatures, 1/mm (0 = flat).
    thickness : (N,) ndarray
        Axial distance from each surface to the next, mm, at the first design position;
        the last entry is the distance from the last surface to the image plane.
    n_after : (N,) ndarray
        Refractive index (d line) of the medium after each surface; the object space is air.
    semi_diameter : (N,) ndarray
        Clear semi-aperture, mm (NaN where the file gives none).
    surface_group : tuple of str
        Name of the group each surface belongs to.
    groups : dict of str to (int, int)
        First and last surface index (0-based, inclusive) of each group, in lens order.
    stop : int
        Index of the aperture stop surface.
    gap_after : (3,) ndarray of int
        Surfaces after which the three variable gaps lie: the variator gap (moved linearly with
        zoom), the middle gap (takes up the rest) and the compensator gap (solved for focus).
    design_gaps : (P, 3) ndarray
        The variable gaps at the P published design positions, mm.
    f_number : float
    source : str
    """

    name: str
    curvature: np.ndarray
    thickness: np.ndarray
    n_after: np.ndarray
    semi_diameter: np.ndarray
    surface_group: tuple[str, ...]
    groups: dict[str, tuple[int, int]]
    stop: int
    gap_after: np.ndarray
    design_gaps: np.ndarray
    f_number: float
    source: str = ""
    path: str = field(default="", compare=False)

    @property
    def n_surfaces(self) -> int:
        return len(self.curvature)

    @property
    def group_names(self) -> tuple[str, ...]:
        return tuple(self.groups)

    @property
    def gap_total(self) -> float:
        """Sum of the three variable gaps, mm (constant: front group and relay are fixed)."""
        return float(self.design_gaps[0].sum())

    @property
    def n_before(self) -> np.ndarray:
        """(N,) refractive index of the medium before each surface."""
        return np.concatenate([[1.0], self.n_after[:-1]])

    def group_index(self, name: str) -> int:
        """Position of group ``name`` in :attr:`group_names`."""
        try:
            return self.group_names.index(name)
        except ValueError:
            raise KeyError(f"lens {self.name!r} has no group {name!r}; groups: "
                           f"{', '.join(self.group_names)}") from None

    def surface_group_index(self) -> np.ndarray:
        """(N,) int: the index into :attr:`group_names` of each surface's group."""
        return np.array([self.group_names.index(g) for g in self.surface_group])

    def thickness_at(self, gaps: np.ndarray) -> np.ndarray:
        """Thicknesses with the variable gaps replaced.

        Parameters
        ----------
        gaps : (..., 3) ndarray
            Variable gaps, mm.

        Returns
        -------
        thickness : (..., N) ndarray
        """
        gaps = np.asarray(gaps, dtype=float)
        t = np.broadcast_to(self.thickness, gaps.shape[:-1] + (self.n_surfaces,)).copy()
        t[..., self.gap_after] = gaps
        return t


def builtin_lenses() -> list[str]:
    """Names of the prescriptions shipped with the package."""
    folder = resources.files("zoomcalib.optics") / "lenses"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json"))


def _fail(path: str, what: str) -> PrescriptionError:
    return PrescriptionError(f"{path}: {what}")


def _number(path: str, where: str, value, *, allow_null: bool = False,
            positive: bool = False) -> float:
    if value is None and allow_null:
        return float("nan")
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise _fail(path, f"field '{where}' must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise _fail(path, f"field '{where}' must be positive, got {value!r}")
    return float(value)


def load_prescription(name_or_path: str | Path = "laikin-10x") -> Prescription:
    """Read and validate a lens prescription.

    Parameters
    ----------
    name_or_path : str or Path
        A built-in lens name (see :func:`builtin_lenses`) or the path of a JSON file.

    Returns
    -------
    Prescription

    Raises
    ------
    PrescriptionError
        One line naming the file and the field that is wrong.

    Examples
    --------
    >>> lens = load_prescription("laikin-10x")
    >>> lens.n_surfaces, lens.group_names
    (24, ('G1', 'variator', 'compensator', 'relay'))
    """
    name_or_path = str(name_or_path)
    candidate = Path(name_or_path)
    if candidate.suffix.lower() == ".json" or candidate.exists():
        path = str(candidate)
        try:
            text = candidate.read_text()
        except OSError as exc:
            raise _fail(path, f"cannot read lens file ({exc.strerror})") from None
    else:
        if name_or_path not in builtin_lenses():
            raise PrescriptionError(
                f"{name_or_path}: no such lens file, and not a built-in lens "
                f"(built-in: {', '.join(builtin_lenses())})")
        res = resources.files("zoomcalib.optics") / "lenses" / f"{name_or_path}.json"
        path = f"{name_or_path} (built-in)"
        text = res.read_text()
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise _fail(path, f"not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(doc, dict):
        raise _fail(path, "top level must be a JSON object")
    return _parse(doc, path)


def _parse(doc: dict, path: str) -> Prescription:
    surfaces = _parse_surfaces(doc, path)
    groups = _parse_groups(doc, path, surfaces["group_of"])
    after, design_arr = _parse_gaps(doc, path, len(surfaces["group_of"]))
    f_number = _number(path, "f_number", doc.get("f_number", 4.0), positive=True)
    thickness = np.array(surfaces["thick"])
    gap_after = np.array(after) - 1
    thickness[gap_after] = design_arr[0]
    return Prescription(
        name=str(doc.get("name", Path(path).stem)),
        curvature=np.array(surfaces["curv"]),
        thickness=thickness,
        n_after=np.array(surfaces["n_after"]),
        semi_diameter=np.array(surfaces["semi"]),
        surface_group=tuple(surfaces["group_of"]),
        groups=groups,
        stop=surfaces["stop"],
        gap_after=gap_after,
        design_gaps=design_arr,
        f_number=f_number,
        source=str(doc.get("source", "")),
        path=path,
    )


def _parse_surfaces(doc: dict, path: str) -> dict:
    """The ``surfaces`` list, checked: per surface its curvature (1/mm, 0 flat), thickness
    (mm), index after it, semi-diameter (mm, NaN unknown) and group; the stop's index."""
    surfaces = doc.get("surfaces")
    if not isinstance(surfaces, list) or len(surfaces) < 2:
        raise _fail(path, "field 'surfaces' must be a list of at least two surfaces")
    curv, thick, n_after, semi, group_of, stops = [], [], [], [], [], []
    for k, s in enumerate(surfaces):
        where = f"surfaces[{k}]"
        if not isinstance(s, dict):
            raise _fail(path, f"field '{where}' must be an object")
        for key in ("radius_mm", "thickness_mm", "nd", "group"):
            if key not in s:
                raise _fail(path, f"field '{where}.{key}' is missing")
        radius = _number(path, f"{where}.radius_mm", s["radius_mm"], allow_null=True)
        if radius == 0:
            raise _fail(path, f"field '{where}.radius_mm' is 0; use null for a flat surface")
        curv.append(0.0 if np.isnan(radius) else 1.0 / radius)
        thick.append(_number(path, f"{where}.thickness_mm", s["thickness_mm"]))
        n = _number(path, f"{where}.nd", s["nd"], positive=True)
        if n < 1.0:
            raise _fail(path, f"field '{where}.nd' must be >= 1, got {n}")
        n_after.append(n)
        semi.append(_number(path, f"{where}.semi_diameter_mm", s.get("semi_diameter_mm"),
                            allow_null=True))
        if not isinstance(s["group"], str):
            raise _fail(path, f"field '{where}.group' must be a group name")
        group_of.append(s["group"])
        if s.get("stop", False):
            stops.append(k)
    if len(stops) != 1:
        raise _fail(path, f"field 'surfaces[].stop' must be true on exactly one surface, "
                          f"found {len(stops)}")
    if n_after[-1] != 1.0:
        raise _fail(path, f"field 'surfaces[{len(surfaces) - 1}].nd' must be 1 (image in air)")
    return {"curv": curv, "thick": thick, "n_after": n_after, "semi": semi,
            "group_of": group_of, "stop": stops[0]}


def _parse_groups(doc: dict, path: str, group_of: list[str]) -> dict[str, tuple[int, int]]:
    """The ``groups`` object, checked against each surface's group: name -> (first, last)
    surface index."""
    groups_doc = doc.get("groups")
    if not isinstance(groups_doc, dict) or not groups_doc:
        raise _fail(path, "field 'groups' must be an object of group name -> {surfaces: [a, b]}")
    n_surfaces = len(group_of)
    groups: dict[str, tuple[int, int]] = {}
    for gname, g in groups_doc.items():
        rng = g.get("surfaces") if isinstance(g, dict) else None
        if (not isinstance(rng, list) or len(rng) != 2
                or not all(isinstance(i, int) for i in rng)
                or not 1 <= rng[0] <= rng[1] <= n_surfaces):
            raise _fail(path, f"field 'groups.{gname}.surfaces' must be [first, last] surface "
                              f"numbers within 1..{n_surfaces}")
        groups[gname] = (rng[0] - 1, rng[1] - 1)
        for k in range(rng[0] - 1, rng[1]):
            if group_of[k] != gname:
                raise _fail(path, f"field 'surfaces[{k}].group' is {group_of[k]!r} but "
                                  f"'groups.{gname}' claims it")
    unknown = sorted(set(group_of) - set(groups))
    if unknown:
        raise _fail(path, f"field 'surfaces[].group' names undeclared group(s) {unknown}")
    return groups


def _parse_gaps(doc: dict, path: str, n_surfaces: int) -> tuple[list[int], np.ndarray]:
    """The ``variable_gaps_mm`` object, checked: the three surface numbers the variable gaps
    follow, and the design positions (P, 3), mm."""
    gaps_doc = doc.get("variable_gaps_mm")
    if not isinstance(gaps_doc, dict):
        raise _fail(path, "field 'variable_gaps_mm' is missing")
    after = gaps_doc.get("after_surface")
    if (not isinstance(after, list) or len(after) != 3
            or not all(isinstance(i, int) and 1 <= i < n_surfaces for i in after)
            or sorted(after) != after):
        raise _fail(path, "field 'variable_gaps_mm.after_surface' must list three increasing "
                          "surface numbers (variator gap, middle gap, compensator gap)")
    design = gaps_doc.get("design_positions")
    try:
        design_arr = np.array(design, dtype=float)
    except (TypeError, ValueError):
        design_arr = np.empty(0)
    if design_arr.ndim != 2 or design_arr.shape[1] != 3 or len(design_arr) < 2:
        raise _fail(path, "field 'variable_gaps_mm.design_positions' must be a list of at "
                          "least two [g1, g2, g3] rows")
    if not np.all(np.isfinite(design_arr)) or np.any(design_arr < 0):
        raise _fail(path, "field 'variable_gaps_mm.design_positions' must hold finite "
                          "non-negative gaps")
    sums = design_arr.sum(axis=1)
    if np.ptp(sums) > 0.01:
        raise _fail(path, "field 'variable_gaps_mm.design_positions': the three gaps must sum "
                          f"to the same length at every position (sums {np.round(sums, 4)})")
    if design_arr[0, 0] == design_arr[-1, 0]:
        raise _fail(path, "field 'variable_gaps_mm.design_positions': the variator gap must "
                          "differ between the first and last positions")
    return after, design_arr
