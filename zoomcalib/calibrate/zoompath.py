r"""The zoom model of a zoom-wide adjustment: the intrinsics at any zoom, from its own posterior.

The zoom-wide adjustment (:mod:`zoomcalib.calibrate.zoomwide`) ties each smoothed parameter
(cx, cy and the distortion terms) across the steps by a difference prior in ``u = log fx``
(:mod:`zoomcalib.calibrate.zoommodel`). Its posterior at the steps, mean ``m`` and joint
covariance ``P`` (``ZoomWideResult.covariance``), already holds what the steps and the prior
say. Curves fitted to those rows as if they were independent count the prior twice: the rows
are smoothed by it and their sigmas shrunk by it. This model carries the same prior between
the steps instead.

Between the steps
-----------------
The prior reads a parameter ``q`` through its form as ``v = w q``: ``w = 1`` (``prior2``),
``w = 1 / fx`` with a free offset along ``w`` (``angle2``: the angular principal point), or
``w = (d / fx)^p`` (``corner2``: a distortion term's displacement at the image corner,
``d`` the half-diagonal in px). At a new abscissa ``u*`` the prior gives ``v* | v ~ N(lam^T v,
V)`` (:func:`~zoomcalib.calibrate.zoommodel.path_between`), so over the posterior

.. math::

    E\,q^* = \lambda^T (w \circ m) / w^*,\qquad
    \mathrm{var}\,q^* = (\lambda^T W P W \lambda + V) / w^{*2},\qquad W = \mathrm{diag}(w).

``V`` is 0 at a step and grows with the gap: the path's freedom between the steps, at the
prior's own ``tau``.

The zoom axis
-------------
``u* = log fx(z*)`` needs fx between the steps. The adjustment does not smooth fx, so its
posterior at the steps is what the steps say, and ``log fx`` is carried against the zoom value
``z`` the same way: the second-difference prior in ``z`` with its ``tau`` by restricted
maximum likelihood from those values and their joint covariance
(:func:`~zoomcalib.calibrate.zoommodel.prior_strength`). Its 1-sigma reaches every other
parameter through ``dq*/du*`` (a central difference). ``fy = a fx``, ``a`` the shared aspect
ratio. The prior's abscissa ``u`` is ``log fx`` at the adjustment's start; its small
difference from the final ``log fx`` is interpolated linearly in zoom. At a step's own zoom
the model gives the step's row.

Held-out check
--------------
Every interior step (an end step held out is an extrapolation) of a smoothed parameter is
predicted from the other steps' values of the solve without the prior (the values and joint
covariance the adjustment chose its models from, scaled by the views' scatter as the table's
sigmas are; a REML ``tau`` estimated again without the step), ``z = error / sd`` with the
step's own noise in ``sd`` (``ZoomWideResult.zoom_models[name]["held_out"]``); fx alike from
the posterior fx. A parameter is flagged when its largest ``|z|`` or its ``sum z^2`` has a
chance below :data:`FLAG_P` under honest sigmas (the largest of ``n`` with Bonferroni's
bound, ``|z| > Phi^{-1}(1 - FLAG_P / 2n)``: 3.8 for 8 steps; ``sum z^2`` above the chi-square
quantile with ``n`` degrees of freedom): one test per parameter, so a clean set of nine
parameters is flagged about once in 50 runs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

from ..camera import CameraModel
from ..zoom.model import ZoomIntrinsics, ZoomModel, ZoomModelLike, intrinsics_at
from .zoommodel import held_out_residuals, path_between, prior_strength

__all__ = ["PosteriorZoomModel", "FLAG_P", "zoom_model_from_dict"]

#: Chance, under honest sigmas, below which a parameter's held-out steps flag it.
FLAG_P = 1e-3
_DIST = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
_DU = 1e-4  # step of the central difference in u


@dataclass
class _Path:
    """One smoothed parameter's posterior at the steps where it is free, and its prior."""

    steps: list[str]
    u: np.ndarray  # (n,) prior abscissae, increasing
    mean: np.ndarray  # (n,) posterior mean
    cov: np.ndarray  # (n, n) posterior covariance
    order: int
    tau: float
    power: int = 0
    scale: float = 1.0
    offset: bool = False

    def weight(self, u: np.ndarray | float) -> np.ndarray:
        """``w = (scale / fx)^power`` at abscissae ``u = log fx``."""
        return (self.scale * np.exp(-np.asarray(u, float))) ** self.power

    def at(self, u_new: float) -> tuple[float, float]:
        """Value and variance at ``u_new`` (module docstring, "Between the steps")."""
        w, w_new = self.weight(self.u), float(self.weight(u_new))
        lam, var_path = path_between(self.u, u_new, self.order, self.tau,
                                     w if self.offset else None, w_new)
        lw = lam * w
        return (float(lw @ self.mean) / w_new,
                max(float(lw @ self.cov @ lw) + var_path, 0.0) / w_new**2)

    def to_dict(self) -> dict:
        return {"steps": list(self.steps), "u": self.u.tolist(), "mean": self.mean.tolist(),
                "cov": self.cov.tolist(), "order": self.order, "tau": self.tau,
                "power": self.power, "scale": self.scale, "offset": self.offset}

    @classmethod
    def from_dict(cls, d: Mapping) -> _Path:
        return cls(list(d["steps"]), np.asarray(d["u"], float), np.asarray(d["mean"], float),
                   np.asarray(d["cov"], float), int(d["order"]), float(d["tau"]),
                   int(d["power"]), float(d["scale"]), bool(d["offset"]))


def _param(result, name: str) -> float:
    """A parameter of a :class:`~zoomcalib.calibrate.result.CalibrationResult` (0 for a
    distortion term it does not hold)."""
    if name in ("fx", "fy", "cx", "cy"):
        return float(getattr(result, name))
    i = _DIST.index(name)
    return float(result.dist[i]) if i < len(result.dist) else 0.0


@dataclass
class PosteriorZoomModel:
    """The intrinsics of a zoom-wide adjustment at any zoom (module docstring).

    Build with :meth:`from_zoom_wide`; evaluate with :meth:`predict`, :meth:`at` and
    :meth:`camera` (the interface of :class:`zoomcalib.zoom.model.ZoomModelLike`); check with
    :meth:`holdout_error` and :meth:`flags`.

    Attributes
    ----------
    zoom : (S,) ndarray
        The steps' zoom values, increasing.
    steps : list of str
    focal : _Path
        ``log fx`` against zoom (abscissa: the zoom values).
    aspect, aspect_sd : float
        ``fy / fx`` and its 1-sigma.
    u_shift : (S,) ndarray
        The prior's abscissa minus ``log fx`` at each step.
    paths : dict of str to _Path
        The smoothed parameters carried between the steps.
    held_out : dict of str to dict
        Per parameter: ``steps``, ``error``, ``sd`` of the held-out check.
    notes : list of str
        Parameters a step holds that the model does not carry, and why.
    """

    zoom: np.ndarray
    steps: list[str]
    focal: _Path
    aspect: float
    aspect_sd: float
    u_shift: np.ndarray
    paths: dict[str, _Path]
    held_out: dict[str, dict] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    kind = "posterior"

    @classmethod
    def from_zoom_wide(cls, result, zoom: Mapping[str, float],
                       exclude: Sequence[str] = ()) -> PosteriorZoomModel:
        """The model of a :class:`~zoomcalib.calibrate.zoomwide.ZoomWideResult` over its
        steps of finite ``zoom`` (step name -> zoom value), leaving out ``exclude`` (e.g. the
        unusable steps).

        Raises
        ------
        ValueError
            With fewer than 4 such steps, or steps of several chains of the prior (the
            model carries one path per parameter).
        """
        steps = [s for s in result.results if s not in exclude
                 and zoom.get(s) is not None and math.isfinite(zoom[s])]
        if len(steps) < 4:
            raise ValueError(f"a zoom model needs 4 or more steps of known zoom; got "
                             f"{len(steps)}")
        steps.sort(key=lambda s: zoom[s])
        z = np.array([zoom[s] for s in steps], float)
        if np.any(np.diff(z) <= 0):
            raise ValueError("two steps share a zoom value: "
                             + ", ".join(f"{a} and {b}" for a, b, d in zip(
                                 steps, steps[1:], np.diff(z), strict=False) if d <= 0))
        res = [result.results[s] for s in steps]
        fx = np.array([r.fx for r in res])
        column = {c: i for i, c in enumerate(result.columns)}
        focal, focal_held = _focal_path(result, steps, z, fx, column)
        u = np.array([result.u[s] for s in steps])
        paths, notes = {}, []
        for name, doc in result.zoom_models.items():
            free = [s for s in steps if (s, name) in column]
            if not free:
                continue
            form = doc.get("form") or {}
            idx = [column[s, name] for s in free]
            path = _Path(free, u[[steps.index(s) for s in free]],
                         np.array([_param(result.results[s], name) for s in free]),
                         result.covariance[np.ix_(idx, idx)], int(doc["order"]),
                         float(doc["tau"]) if doc.get("tau") is not None else 0.0,
                         int(form.get("power", 0)), float(form.get("scale", 1.0)),
                         bool(form.get("offset", False)))
            if np.any(np.diff(path.u) <= 0) or len(free) <= path.order + path.offset:
                notes.append(f"{name}: free at {len(free)} steps ({', '.join(free)}); too few "
                             "for its prior between the steps, not carried")
                continue
            paths[name] = path
        held = {k: d["held_out"] for k, d in result.zoom_models.items()
                if k in paths and d.get("held_out")}
        if focal_held is not None:
            held["fx"] = focal_held
        for name in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"):
            holding = [s for s, r in zip(steps, res, strict=True) if _param(r, name) != 0.0]
            if holding and name not in paths and not any(name in n for n in notes):
                notes.append(f"{name}: held by {', '.join(holding)} with no zoom model of the "
                             "adjustment; not carried between the steps")
        return cls(z, steps, focal, float(result.aspect), float(result.aspect_sd),
                   u - np.log(fx), paths, held, notes)

    # -- evaluation ----------------------------------------------------------------------

    @property
    def zoom_range(self) -> tuple[float, float]:
        return float(self.zoom[0]), float(self.zoom[-1])

    @property
    def names(self) -> list[str]:
        """The parameters carried: fx, fy, then the smoothed ones."""
        return ["fx", "fy", *self.paths]

    def predict(self, zoom: float | Sequence[float] | np.ndarray) -> dict:
        """The parameters at zoom value(s): ``name`` -> value and ``"sd_" + name`` ->
        1-sigma (of the model there, not of a new calibration); floats for a scalar zoom,
        (k,) arrays otherwise. fx, fy, cx, cy in px."""
        scalar = np.ndim(zoom) == 0
        z = np.atleast_1d(np.asarray(zoom, float))
        log_fx = np.array([self.focal.at(v) for v in z])
        fx = np.exp(log_fx[:, 0])
        sd_fx = fx * np.sqrt(log_fx[:, 1])
        a, sd_a = self.aspect, self.aspect_sd if math.isfinite(self.aspect_sd) else 0.0
        out = {"fx": fx, "sd_fx": sd_fx, "fy": a * fx,
               "sd_fy": np.sqrt((a * sd_fx) ** 2 + (fx * sd_a) ** 2)}
        u = np.log(fx) + np.interp(z, self.zoom, self.u_shift)
        sd_u = sd_fx / fx
        for name, path in self.paths.items():
            vals = np.empty(len(z))
            sds = np.empty(len(z))
            for i, (ui, si) in enumerate(zip(u, sd_u, strict=True)):
                value, var = path.at(ui)
                slope = (path.at(ui + _DU)[0] - path.at(ui - _DU)[0]) / (2 * _DU)
                vals[i], sds[i] = value, math.sqrt(var + (slope * si) ** 2)
            out[name], out[f"sd_{name}"] = vals, sds
        if scalar:
            return {k: float(v[0]) for k, v in out.items()}
        return out

    def at(self, zoom: float, *, extrapolate: bool = False) -> ZoomIntrinsics:
        """The intrinsics and their 1-sigma at one zoom value, with the errors of
        :meth:`zoomcalib.zoom.ZoomModel.at` (a zoom not finite or outside the calibrated range
        without ``extrapolate``; cx or cy not carried).

        Examples
        --------
        See ``tests/test_zoompath.py``: a model needs a zoom-wide adjustment of 4 or more
        steps.
        """
        return intrinsics_at(self, zoom, extrapolate)

    def camera(self, zoom: float) -> CameraModel:
        """The camera at one zoom value (extrapolated outside the calibrated range)."""
        lens = self.at(zoom, extrapolate=True)
        return CameraModel(lens.fx, lens.fy, lens.cx, lens.cy, lens.dist)

    # -- checks --------------------------------------------------------------------------

    def _held_out_z(self) -> dict[str, dict]:
        """Per parameter: the held-out steps (of this model's), errors, sds and z."""
        out = {}
        for name in self.names:
            if name in ("fx", "fy") and "fx" in self.held_out:
                rec = self.held_out["fx"]
                inner = set(self.steps[1:-1])
                keep = [i for i, s in enumerate(rec["steps"]) if s in inner]
                scale = 1.0 if name == "fx" else self.aspect
                steps = [rec["steps"][i] for i in keep]
                err = scale * np.array([rec["error"][i] for i in keep], float)
                sd = scale * np.array([rec["sd"][i] for i in keep], float)
            elif name in self.held_out:
                rec = self.held_out[name]
                inner = set(self.steps[1:-1])  # an end step held out is an extrapolation
                keep = [i for i, s in enumerate(rec["steps"]) if s in inner]
                steps = [rec["steps"][i] for i in keep]
                err = np.array([rec["error"][i] for i in keep], float)
                sd = np.array([rec["sd"][i] for i in keep], float)
            else:
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                z = np.where(sd > 0, err / sd, np.nan)
            out[name] = {"steps": steps, "error": err, "sd": sd, "z": z}
        return out

    def holdout_error(self, details: bool = False) -> dict:
        """RMS of each parameter's held-out errors (module docstring; parameter units), or
        with ``details`` the per-step ``steps``, ``error``, ``sd`` and ``z`` beside ``rms``."""
        out = {}
        for name, d in self._held_out_z().items():
            rms = float(np.sqrt(np.mean(d["error"] ** 2))) if len(d["error"]) else math.nan
            out[name] = d | {"rms": rms} if details else rms
        return out

    def flags(self) -> list[str]:
        """One line per parameter whose held-out steps miss the model beyond their sigmas,
        then the parameters not carried."""
        out = []
        for name, d in self._held_out_z().items():
            z = d["z"][np.isfinite(d["z"])]
            if not len(z):
                continue
            chi2 = float(np.sum(z**2))
            worst = int(np.nanargmax(np.abs(d["z"])))
            z_limit = scipy.stats.norm.isf(FLAG_P / (2 * len(z)))
            if np.abs(z).max() > z_limit or chi2 > scipy.stats.chi2.isf(FLAG_P, len(z)):
                unit = " px" if name in ("fx", "fy", "cx", "cy") else ""
                rms = float(np.sqrt(np.mean(d["error"] ** 2)))
                out.append(f"{name}: held-out steps miss the zoom model (chi2 {chi2:.1f} for "
                           f"{len(z)} steps; worst {d['steps'][worst]} at z "
                           f"{d['z'][worst]:+.1f}): between the steps it is good to about "
                           f"{rms:.3g}{unit}, not to its 1-sigma")
        return out + list(self.notes)

    def summary(self) -> str:
        """One line per parameter: its prior between the steps and its held-out RMS z."""
        held = self._held_out_z()
        lines = []
        for name in self.names:
            what = (f"log fx: prior of order 2 in zoom, tau {self.focal.tau:.3g}"
                    if name in ("fx", "fy") else
                    f"prior of order {self.paths[name].order}, tau {self.paths[name].tau:.3g}")
            z = held.get(name, {}).get("z", np.zeros(0))
            z = z[np.isfinite(z)]
            rms_z = f", held-out RMS z {np.sqrt(np.mean(z**2)):.2f}" if len(z) else ""
            lines.append(f"{name}: {what}{rms_z}")
        return "\n".join(lines)

    # -- saving --------------------------------------------------------------------------

    def to_dict(self) -> dict:
        """JSON-ready; :meth:`from_dict` reads it back."""
        return {"format": "zoomcalib-zoom-model", "version": 2, "kind": self.kind,
                "zoom_range": list(self.zoom_range), "steps": list(self.steps),
                "zoom": self.zoom.tolist(), "focal": self.focal.to_dict(),
                "aspect": self.aspect,
                "aspect_sd": self.aspect_sd if math.isfinite(self.aspect_sd) else None,
                "u_shift": self.u_shift.tolist(),
                "paths": {k: p.to_dict() for k, p in self.paths.items()},
                "held_out": self.held_out, "notes": list(self.notes)}

    @classmethod
    def from_dict(cls, d: Mapping) -> PosteriorZoomModel:
        """Inverse of :meth:`to_dict`."""
        if d.get("format") != "zoomcalib-zoom-model" or d.get("kind") != "posterior":
            raise ValueError("not a posterior zoom model (format 'zoomcalib-zoom-model', "
                             "kind 'posterior')")
        sd = d.get("aspect_sd")
        return cls(np.asarray(d["zoom"], float), list(d["steps"]),
                   _Path.from_dict(d["focal"]), float(d["aspect"]),
                   math.nan if sd is None else float(sd), np.asarray(d["u_shift"], float),
                   {k: _Path.from_dict(p) for k, p in d["paths"].items()},
                   dict(d.get("held_out", {})), list(d.get("notes", [])))


def _focal_path(result, steps: list[str], zoom: np.ndarray, fx: np.ndarray,
                column: Mapping) -> tuple[_Path, dict | None]:
    """``log fx`` against zoom (module docstring, "The zoom axis") and its held-out check
    (None with fewer than 4 steps)."""
    idx = [column.get((s, "fx")) for s in steps]
    if all(i is not None for i in idx):
        cov = result.covariance[np.ix_(idx, idx)] / np.outer(fx, fx)
    else:  # fx not free somewhere: the steps' own sigmas
        cov = np.diag([(result.results[s].sd["fx"] / f) ** 2 for s, f in zip(steps, fx,
                                                                              strict=True)])
    values = np.log(fx)
    tau = prior_strength(values, cov, zoom, 2)[0]
    path = _Path(list(steps), zoom.copy(), values, cov, 2, float(tau) if np.isfinite(tau)
                 else 0.0)
    got = held_out_residuals((values, cov, zoom), 2, path.tau, True, marginal=True)
    if got is None:
        return path, None
    return path, {"steps": list(steps), "error": [float(v) for v in got[0] * fx],
                  "sd": [float(v) for v in got[1] * fx]}


def zoom_model_from_dict(d: Mapping) -> ZoomModelLike:
    """The zoom model of a ``zoom_model.json``'s ``"model"``: this module's for a zoom-wide
    table (``kind: posterior``), else :meth:`zoomcalib.zoom.ZoomModel.from_dict`'s curves."""
    if d.get("kind") == "posterior":
        return PosteriorZoomModel.from_dict(d)
    return ZoomModel.from_dict(d)
