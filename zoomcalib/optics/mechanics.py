"""Mechanical errors of the moving groups of a zoom lens.

Each group's decentre ``d`` (mm) and tilt ``t`` (rad) at zoom state ``zoom`` with barrel angle
``phi = 4 pi zoom`` is the sum of

- a locked error that turns with the barrel (cam-track run-out):
  ``d_locked = A (cos(phi + psi), sin(phi + psi))``, likewise for the tilt with its own
  amplitude and phase; the same on every visit to that zoom, so it draws the paper's spiral;
- backlash: ``d_backlash = s b / 2 (-sin(phi + psi), cos(phi + psi))`` along the barrel's tangential
  direction, with ``s = +1`` after a move in (towards zoom 1) and ``-1`` after a move out;
- non-repeatable play: Gaussian, 1-sigma ``sigma_play`` per axis, new at every visit;
- a static assembly decentre and tilt.

Tolerance files (JSON or YAML) give these per group in micrometres and arcminutes; see
``zoomcalib/optics/tolerances/default.yaml``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from .cam import barrel_angle
from .misalignment import Misalignment
from .prescription import Prescription

__all__ = ["GroupTolerance", "Tolerances", "ToleranceError", "load_tolerances",
           "systematic_misalignment", "draw_misalignment", "ARCMIN"]

ARCMIN = np.pi / (180.0 * 60.0)  # rad per arcminute
UM = 1e-3  # mm per micrometre


class ToleranceError(ValueError):
    """A tolerance file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class GroupTolerance:
    """Mechanical tolerances of one group (file units: um, arcmin, degrees)."""

    locked_decenter_um: float = 0.0
    locked_decenter_phase_deg: float = 0.0
    locked_tilt_arcmin: float = 0.0
    locked_tilt_phase_deg: float = 0.0
    play_um: float = 0.0
    play_tilt_arcmin: float = 0.0
    backlash_um: float = 0.0
    static_decenter_um: tuple[float, float] = (0.0, 0.0)
    static_tilt_arcmin: tuple[float, float] = (0.0, 0.0)

    def scaled(self, factor: float) -> GroupTolerance:
        """Every error magnitude multiplied by ``factor`` (phases kept)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name.endswith("phase_deg"):
                out[f.name] = v
            elif isinstance(v, tuple):
                out[f.name] = tuple(factor * x for x in v)
            else:
                out[f.name] = factor * v
        return replace(self, **out)


@dataclass(frozen=True)
class Tolerances:
    """Tolerances of the groups of a lens; groups not listed are perfect."""

    groups: dict[str, GroupTolerance] = field(default_factory=dict)
    source: str = ""

    def scaled(self, factor: float) -> Tolerances:
        return Tolerances({k: g.scaled(factor) for k, g in self.groups.items()},
                          f"{self.source} x {factor:g}")

    def for_group(self, name: str) -> GroupTolerance:
        return self.groups.get(name, GroupTolerance())

    @classmethod
    def zero(cls) -> Tolerances:
        return cls({}, "zero")

    def to_dict(self) -> dict:
        return {"groups": {k: {f.name: (list(getattr(g, f.name))
                                        if isinstance(getattr(g, f.name), tuple)
                                        else getattr(g, f.name)) for f in fields(g)}
                           for k, g in self.groups.items()}}


def load_tolerances(path: str | Path | None = None,
                    lens: Prescription | None = None) -> Tolerances:
    """Read a tolerance file (JSON or YAML); ``None`` gives the documented defaults.

    Raises
    ------
    ToleranceError
        One line naming the file and the offending field.
    """
    if path is None:
        res = resources.files("zoomcalib.optics") / "tolerances" / "default.yaml"
        text, where = res.read_text(), "default tolerances (built-in)"
    else:
        where = str(path)
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ToleranceError(f"{where}: cannot read tolerance file ({exc.strerror})") from None
    try:
        if str(where).lower().endswith(".json"):
            doc = json.loads(text)
        else:
            doc = yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        msg = str(exc).splitlines()[0]
        raise ToleranceError(f"{where}: not valid JSON/YAML ({msg})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("groups"), dict):
        raise ToleranceError(f"{where}: field 'groups' must map group names to tolerances")
    names = {f.name: f for f in fields(GroupTolerance)}
    groups: dict[str, GroupTolerance] = {}
    for gname, spec in doc["groups"].items():
        if lens is not None and gname not in lens.groups:
            raise ToleranceError(f"{where}: field 'groups.{gname}': lens {lens.name!r} has no "
                                 f"such group (groups: {', '.join(lens.group_names)})")
        if not isinstance(spec, dict):
            raise ToleranceError(f"{where}: field 'groups.{gname}' must be a mapping")
        kwargs = {}
        for key, value in spec.items():
            if key not in names:
                raise ToleranceError(f"{where}: field 'groups.{gname}.{key}' is unknown "
                                     f"(known: {', '.join(names)})")
            vector = key.startswith("static_")
            vals = value if vector else [value]
            if (not isinstance(vals, list) or len(vals) != (2 if vector else 1)
                    or not all(isinstance(x, int | float) and not isinstance(x, bool)
                               and np.isfinite(x) for x in vals)):
                want = "a list [x, y] of numbers" if vector else "a number"
                raise ToleranceError(f"{where}: field 'groups.{gname}.{key}' must be {want}, "
                                     f"got {value!r}")
            if not vector and not key.endswith("phase_deg") and value < 0:
                raise ToleranceError(f"{where}: field 'groups.{gname}.{key}' must be >= 0, "
                                     f"got {value!r}")
            kwargs[key] = tuple(float(x) for x in vals) if vector else float(value)
        groups[gname] = GroupTolerance(**kwargs)
    return Tolerances(groups, where)


def _direction_sign(direction, shape, rng) -> np.ndarray:
    if isinstance(direction, str):
        if direction == "in":
            return np.ones(shape)
        if direction == "out":
            return -np.ones(shape)
        if direction == "random":
            if rng is None:
                raise ValueError("direction 'random' needs a random generator")
            return rng.choice([-1.0, 1.0], size=shape)
        raise ValueError(f"direction must be 'in', 'out' or 'random', got {direction!r}")
    return np.broadcast_to(np.asarray(direction, dtype=float), shape)


def _unit(angle: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def systematic_misalignment(lens: Prescription, tolerances: Tolerances, zoom: np.ndarray,
                            direction: str | np.ndarray = "none") -> Misalignment:
    """The repeatable part of the group errors: locked + static (+ backlash for a direction).

    Parameters
    ----------
    zoom : (Z,) array_like
    direction : {'none', 'in', 'out'} or (Z,) array of +1/-1
        Direction of the last zoom move; 'none' leaves backlash out (the mid position).

    Returns
    -------
    Misalignment
        ``decenter`` and ``tilt`` of shape (Z, G, 2).
    """
    zoom = np.atleast_1d(np.asarray(zoom, dtype=float))
    phi = barrel_angle(zoom)  # shape (Z,)
    sign = (np.zeros(zoom.shape) if isinstance(direction, str) and direction == "none"
            else _direction_sign(direction, zoom.shape, None))
    dec = np.zeros(zoom.shape + (len(lens.groups), 2))
    tilt = np.zeros_like(dec)
    for g, name in enumerate(lens.group_names):
        tol = tolerances.for_group(name)
        psi = np.deg2rad(tol.locked_decenter_phase_deg)
        psi_t = np.deg2rad(tol.locked_tilt_phase_deg)
        dec[:, g] = (tol.locked_decenter_um * _unit(phi + psi)
                     + sign[:, None] * 0.5 * tol.backlash_um * _unit(phi + psi + np.pi / 2)
                     + np.asarray(tol.static_decenter_um)) * UM
        tilt[:, g] = (tol.locked_tilt_arcmin * _unit(phi + psi_t)
                      + np.asarray(tol.static_tilt_arcmin)) * ARCMIN
    return Misalignment(dec, tilt)


def draw_misalignment(lens: Prescription, tolerances: Tolerances, zoom: np.ndarray,
                      n_samples: int, seed: int | np.random.SeedSequence = 0,
                      direction: str | Sequence[str] = "random") -> Misalignment:
    """Monte Carlo draws of the group errors at each zoom state.

    Every zoom step gets its own child of ``SeedSequence(seed)``, so a step's draws do not depend
    on how the work is split.

    Parameters
    ----------
    zoom : (Z,) array_like
    n_samples : int
        Draws per zoom state (S).
    seed : int or SeedSequence
    direction : {'random', 'in', 'out'} or (Z,) sequence of them
        Direction of the last zoom move before each draw (one for all steps, or one per step).

    Returns
    -------
    Misalignment
        ``decenter`` and ``tilt`` of shape (Z, S, G, 2).
    """
    zoom = np.atleast_1d(np.asarray(zoom, dtype=float))
    per_step = [direction] * len(zoom) if isinstance(direction, str) else list(direction)
    if len(per_step) != len(zoom):
        raise ValueError(f"direction: {len(per_step)} values for {len(zoom)} zoom steps")
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    n_groups = len(lens.groups)
    dec = np.empty((len(zoom), n_samples, n_groups, 2))
    tilt = np.empty_like(dec)
    play = np.array([tolerances.for_group(g).play_um for g in lens.group_names]) * UM
    play_t = np.array([tolerances.for_group(g).play_tilt_arcmin
                       for g in lens.group_names]) * ARCMIN
    for i, child in enumerate(ss.spawn(len(zoom))):
        rng = np.random.default_rng(child)
        sign = _direction_sign(per_step[i], (n_samples,), rng)  # shape (S,)
        plus = systematic_misalignment(lens, tolerances, np.full(1, zoom[i]), "in")
        minus = systematic_misalignment(lens, tolerances, np.full(1, zoom[i]), "out")
        pick = (sign > 0)[:, None, None]
        dec[i] = np.where(pick, plus.decenter, minus.decenter)
        tilt[i] = np.where(pick, plus.tilt, minus.tilt)
        dec[i] += rng.standard_normal((n_samples, n_groups, 2)) * play[:, None]
        tilt[i] += rng.standard_normal((n_samples, n_groups, 2)) * play_t[:, None]
    return Misalignment(dec, tilt)
