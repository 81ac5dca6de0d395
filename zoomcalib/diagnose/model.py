"""The simulation's principal-point model, linearised, and its physical extensions.

For small mechanical errors the principal point moves linearly with every group's decentre and
tilt (:func:`zoomcalib.optics.paraxial.image_shift_sensitivity`). A decentre ``d`` (mm) of group
``g`` at lens state ``z`` moves the principal point by

    Delta c(z) = -S_g(z) d / pitch                          (px; the read-out flips the image)

and a tilt ``t`` (rad) by ``-T_g(z) t / pitch``. An error that turns with the barrel at ``m`` times
its angle ``phi = 4 pi z`` is ``d = R(m phi) a`` with a fixed vector ``a`` in the barrel frame,
so each such term is two linear columns, ``-S_g R(m phi) e_x / pitch`` and
``-S_g R(m phi) e_y / pitch``:

- ``m = 1``: the paper's rotation-locked decentre and tilt (the spiral);
- ``m = 2``: a cam error at twice the barrel rotation (``cam_harmonic``);
- ``m = 0``: a decentre that does not turn with the barrel (``static_decenter``).

Every model here is therefore linear in its parameters: a :class:`Term` gives a block of columns
of shape (N, 2, k) (row, axis (cx, cy), parameter).

An axis tilt ``theta`` (rad) of the lens against the sensor moves the image by ``f theta`` and
tilts the sensor against the lens's image plane: a keystone ``kappa = pitch theta / L`` (1/px,
``L`` the exit pupil's distance, mm), which a calibration takes partly into its poses and its
principal point. When the table carries each row's keystone response (``A``, ``B`` of
:func:`zoomcalib.calibrate.opencv_backend.keystone_response`), the calibrated values move by

    Delta c = diag(f) (theta - A eps),    Delta (p1, p2) = B eps,    eps = diag(f) kappa

(``f = (fx, fy)`` px); without it by ``f theta`` alone.

Likewise a group's decentre or tilt: when the table holds each row's calibration (a diagnosis of
an image folder), the columns are that calibration's own response to the error's traced image
(:mod:`zoomcalib.diagnose.response`), ``G(z) R(m phi)``, instead of the paraxial
``-S_g(z) / pitch R(m phi)``.

The lens state of each measured row is found from its focal length: ``efl(z) = fx * pitch``,
inverted on the lens's EFL curve, so the table's own zoom unit never matters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..optics.cam import barrel_angle, moving_groups, solve_gaps
from ..optics.lens_camera import lens_camera
from ..optics.mechanics import ARCMIN, UM, Tolerances
from ..optics.misalignment import Misalignment
from ..optics.paraxial import effective_focal_length, exit_pupil_distance, image_shift_sensitivity
from ..optics.prescription import Prescription
from .response import calibration_response
from .table import ZoomTable

__all__ = ["LensResponse", "Context", "Term", "moving_groups", "play_sd_px", "FocalRangeError",
           "offset_term", "group_term", "axis_tilt_term", "direction_offset_term",
           "covariate_term", "covariate_curve_term", "design_matrix", "DEFAULT_PITCH_MM",
           "smooth_path_term", "decentring_distortion",
           "setting_term", "log_focal_coordinate"]

DEFAULT_PITCH_MM = 0.00645


class FocalRangeError(ValueError):
    """The measured focal lengths do not fit the lens's EFL range at the given pixel pitch."""


@dataclass
class LensResponse:
    """EFL curve and principal-point sensitivities of a lens, on a dense zoom grid.

    Attributes
    ----------
    lens : Prescription
    pitch_mm : float
        Pixel pitch, mm.
    zoom_grid, efl_grid : (G,) ndarray
        Lens state in [0, 1] and its EFL, mm (monotone in zoom).
    groups : tuple of str
        The moving groups.
    """

    lens: Prescription
    pitch_mm: float
    zoom_grid: np.ndarray
    efl_grid: np.ndarray
    groups: tuple[str, ...]

    @classmethod
    def of(cls, lens: Prescription, pitch_mm: float = DEFAULT_PITCH_MM,
           n_grid: int = 801) -> LensResponse:
        if not pitch_mm > 0:
            raise ValueError(f"pixel pitch must be positive, got {pitch_mm!r}")
        zg = np.linspace(0.0, 1.0, n_grid)
        efl = effective_focal_length(lens, lens.thickness_at(solve_gaps(lens, zg)))
        if not np.all(np.diff(efl) > 0):
            raise ValueError(f"lens {lens.name!r}: EFL is not increasing with zoom, so a focal "
                             f"length does not name one lens state")
        return cls(lens, float(pitch_mm), zg, efl, moving_groups(lens))

    def with_pitch(self, pitch_mm: float) -> LensResponse:
        return LensResponse(self.lens, float(pitch_mm), self.zoom_grid, self.efl_grid,
                            self.groups)

    def state_of_focal(self, fx_px: np.ndarray, source: str = "table",
                       tolerance: float = 0.03) -> np.ndarray:
        """(N,) lens state ``z`` whose EFL equals ``fx_px * pitch``.

        Values up to ``tolerance`` (relative) outside the lens's range are clamped to its ends.

        Raises
        ------
        FocalRangeError
            When the measured range does not fit the lens at this pitch.
        """
        efl = np.asarray(fx_px, dtype=float) * self.pitch_mm
        lo, hi = self.efl_grid[0], self.efl_grid[-1]
        if efl.min() < lo * (1 - tolerance) or efl.max() > hi * (1 + tolerance):
            raise FocalRangeError(
                f"{source}: measured focal lengths {fx_px.min():.1f}-{fx_px.max():.1f} px are "
                f"{efl.min():.2f}-{efl.max():.2f} mm at pixel pitch {self.pitch_mm:g} mm, outside "
                f"lens {self.lens.name!r} ({lo:.2f}-{hi:.2f} mm). Give the sensor's pitch with "
                f"--pixel-pitch, or fit it with --pixel-pitch auto")
        return np.interp(np.clip(efl, lo, hi), self.efl_grid, self.zoom_grid)

    def pitch_range(self, fx_px: np.ndarray, source: str = "table") -> tuple[float, float]:
        """Pixel pitches (mm) at which every measured focal length lies in the lens's range."""
        fx = np.asarray(fx_px, dtype=float)
        lo, hi = self.efl_grid[0] / fx.min(), self.efl_grid[-1] / fx.max()
        if lo > hi:
            raise FocalRangeError(
                f"{source}: measured zoom ratio {fx.max() / fx.min():.2f} exceeds lens "
                f"{self.lens.name!r}'s {self.efl_grid[-1] / self.efl_grid[0]:.2f}: no pixel "
                f"pitch fits; is it the right lens?")
        return float(lo), float(hi)

    def sensitivities(self, z: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per group: (N,) image shift per decentre (mm/mm) and per tilt (mm/rad) at states z."""
        thickness = self.lens.thickness_at(solve_gaps(self.lens, np.asarray(z, dtype=float)))
        return {g: image_shift_sensitivity(self.lens, thickness, g)
                for g in self.lens.group_names}

    def exit_pupil_mm(self, z: np.ndarray) -> np.ndarray:
        """(N,) distance from the exit pupil to the image plane at states z, mm."""
        thickness = self.lens.thickness_at(solve_gaps(self.lens, np.asarray(z, dtype=float)))
        return exit_pupil_distance(self.lens, thickness)

    def play_sd_px(self, z: np.ndarray, tolerances: Tolerances) -> np.ndarray:
        """(N,) 1-sigma per axis of the principal point from the random play, px."""
        return play_sd_px(self.lens, z, tolerances, self.pitch_mm)


def play_sd_px(lens: Prescription, z: np.ndarray, tolerances: Tolerances,
               pitch_mm: float) -> np.ndarray:
    """(N,) 1-sigma per axis of the principal point from the groups' random play, px.

    ``sigma^2 = sum_g (S_g play_g)^2 + (T_g play_tilt_g)^2``, over every group of the lens.
    """
    thickness = lens.thickness_at(solve_gaps(lens, np.asarray(z, dtype=float)))
    var = np.zeros(thickness.shape[0])
    for g in lens.group_names:
        s_d, s_t = image_shift_sensitivity(lens, thickness, g)
        tol = tolerances.for_group(g)
        var += (s_d * tol.play_um * UM) ** 2 + (s_t * tol.play_tilt_arcmin * ARCMIN) ** 2
    return np.sqrt(var) / pitch_mm


def decentring_distortion(lens: Prescription, z: np.ndarray, group: str,
                          decenter_mm: np.ndarray) -> np.ndarray:
    """(N, 2) change of the tangential distortion (OpenCV ``p1``, ``p2``, dimensionless) of
    the camera model fitted at lens states ``z`` when ``group`` is decentred by
    ``decenter_mm`` ((2,) x, y in the lens frame, mm), from the exact tracer.

    A decentred group bends the image (decentring distortion) as well as moving it; a lens
    axis tilted against the sensor moves it and adds a keystone, whose share in ``p1``, ``p2``
    depends on the calibration (:func:`axis_tilt_term`). So a static decentre large enough to
    imitate an axis tilt in the principal points shows in ``p1``, ``p2``, which the
    calibration table holds beside them.
    """
    names = list(lens.group_names)
    if group not in names:
        raise ValueError(f"lens {lens.name!r} has no group {group!r} (groups: "
                         f"{', '.join(names)})")
    moved = np.zeros((len(names), 2))
    moved[names.index(group)] = decenter_mm
    still = Misalignment(np.zeros_like(moved), np.zeros_like(moved))
    shifted = Misalignment(moved, np.zeros_like(moved))
    return np.array([lens_camera(lens, float(zz), shifted).camera.dist[2:4]
                     - lens_camera(lens, float(zz), still).camera.dist[2:4]
                     for zz in np.atleast_1d(z)])


@dataclass
class Context:
    """What the terms need about the rows: lens state, barrel angle, sensitivities, table."""

    table: ZoomTable
    z: np.ndarray  # shape (N,)
    response: LensResponse | None
    sens: dict[str, tuple[np.ndarray, np.ndarray]]
    exit_pupil_mm: np.ndarray | None = None  # shape (N,)

    @classmethod
    def build(cls, table: ZoomTable, z: np.ndarray, response: LensResponse | None) -> Context:
        """``response`` None: no lens model (only terms that need no optics can be used)."""
        if response is None:
            return cls(table, np.asarray(z, dtype=float), None, {})
        return cls(table, np.asarray(z, dtype=float), response, response.sensitivities(z),
                   response.exit_pupil_mm(z))

    def group_response(self, group: str, kind: str) -> np.ndarray | None:
        """(N, 4, 2) each row's calibration response to a unit decentre (mm) or tilt (rad) of
        ``group`` (:func:`zoomcalib.diagnose.response.calibration_response`), None when the
        table has no calibrations (the paraxial shift is used then)."""
        cals = self.table.calibrations
        if cals is None or self.response is None:
            return None
        key = (group, kind, self.response.pitch_mm, self.z.tobytes())
        cache = self.table.response_cache
        if key not in cache:
            rows = [calibration_response(self.response.lens, float(z), self.response.pitch_mm,
                                         cal, group, kind) for z, cal in zip(self.z, cals,
                                                                             strict=True)]
            failed = [step for step, r in zip(self.table.step, rows, strict=True) if r is None]
            if failed:  # said in diagnosis.json (group_columns): the paraxial shift instead
                cache.setdefault("failed", []).append(
                    f"{kind} of {group}: the calibration of step {failed[0]} has a singular "
                    f"normal matrix")
            cache[key] = None if failed else np.array(rows)
        return cache[key]

    @property
    def keystone_per_mrad(self) -> np.ndarray | None:
        """(N, 2, 2) camera-turn equivalent ``eps`` of the tilted sensor's keystone per mrad
        of axis tilt (diagonal: ``f pitch / L``), None without the table's keystone response
        or a lens model."""
        if self.table.keystone is None or self.exit_pupil_mm is None:
            return None
        f = np.stack([self.table.fx, self.table.fy], -1)  # shape (N, 2)
        ratio = 1e-3 * f * self.response.pitch_mm / self.exit_pupil_mm[:, None]
        return ratio[:, :, None] * np.eye(2)[None]

    @property
    def phi(self) -> np.ndarray:
        return barrel_angle(self.z)


@dataclass(frozen=True)
class Term:
    """A block of linear columns with named parameters.

    Attributes
    ----------
    name : str
        Short description, e.g. ``"locked decentre, variator"``.
    params : tuple of str
        Parameter names with their unit in the name (``variator_x_um``).
    columns : callable
        ``columns(ctx) -> (N, 2, k)``: the change of (cx, cy) per unit of each parameter, px.
    tangential : callable, optional
        ``tangential(ctx) -> (N, 2, k)``: the change of the calibrated (p1, p2) per unit of
        each parameter, for a term that is not a group's decentre or tilt (those come from
        the tracer, :mod:`zoomcalib.diagnose.tangential`).
    """

    name: str
    params: tuple[str, ...]
    columns: Callable[[Context], np.ndarray]
    tangential: Callable[[Context], np.ndarray] | None = None


def _rotating(weight: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(N, 2, 2) columns ``weight * R(angle) e_x`` and ``weight * R(angle) e_y``."""
    c, s = np.cos(angle), np.sin(angle)
    return weight[:, None, None] * np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], 1)


def offset_term() -> Term:
    """A constant principal point (sensor offset), px."""
    return Term("sensor offset", ("cx0_px", "cy0_px"),
                lambda ctx: np.broadcast_to(np.eye(2), (len(ctx.z), 2, 2)).copy())


def group_term(group: str, kind: str, harmonic: int, label: str, signed_by: str = "") -> Term:
    """Decentre (``kind='decenter'``, um) or tilt (``'tilt'``, arcmin) of ``group`` turning at
    ``harmonic`` times the barrel angle, optionally multiplied by the approach direction."""
    unit = "um" if kind == "decenter" else "arcmin"
    scale = UM if kind == "decenter" else ARCMIN

    def columns(ctx: Context) -> np.ndarray:
        measured = ctx.group_response(group, kind)
        if measured is None:  # the paraxial image shift
            s_d, s_t = ctx.sens[group]
            weight = -(s_d if kind == "decenter" else s_t) * scale / ctx.response.pitch_mm
            cols = _rotating(weight, harmonic * ctx.phi)
        else:  # as each row's calibration takes it
            cols = scale * measured[:, :2] @ _rotating(np.ones(len(ctx.z)), harmonic * ctx.phi)
        if signed_by == "direction":
            cols = cols * ctx.table.direction[:, None, None]
        return cols

    return Term(f"{label}, {group}", (f"{group}_x_{unit}", f"{group}_y_{unit}"), columns)


def axis_tilt_term() -> Term:
    """Optical axis tilted against the sensor normal by theta (mrad): ``Delta c = f theta``,
    less what the calibration took of the tilted sensor's keystone when the table says
    (module docstring)."""

    def columns(ctx: Context) -> np.ndarray:
        f = np.stack([ctx.table.fx, ctx.table.fy], -1)[:, :, None]  # shape (N, 2, 1)
        shift = 1e-3 * f * np.eye(2)[None]
        eps = ctx.keystone_per_mrad
        if eps is None:
            return shift
        return shift - f * (ctx.table.keystone[:, :2] @ eps)

    def tangential(ctx: Context) -> np.ndarray:
        eps = ctx.keystone_per_mrad
        if eps is None:
            return np.zeros((len(ctx.z), 2, 2))
        return ctx.table.keystone[:, 2:] @ eps

    return Term("axis tilt", ("tilt_x_mrad", "tilt_y_mrad"), columns, tangential)


def direction_offset_term() -> Term:
    """An offset whose sign follows the last zoom move: ``Delta c = s b`` (px, s = +1 in)."""
    return Term("direction-signed offset", ("half_shift_x_px", "half_shift_y_px"),
                lambda ctx: ctx.table.direction[:, None, None] * np.eye(2)[None])


def covariate_term(column: str, unit: str, label: str) -> Term:
    """A linear drift with a table column (centred): ``Delta c = (v - mean v) * rate``."""

    def columns(ctx: Context) -> np.ndarray:
        v = getattr(ctx.table, column)
        return (v - v.mean())[:, None, None] * np.eye(2)[None]

    return Term(label, (f"rate_x_px_per_{unit}", f"rate_y_px_per_{unit}"), columns)


def covariate_curve_term(column: str, degree: int, label: str) -> Term:
    """A drift smooth in a table column: ``Delta c = sum_{d=1..degree} P_d(t) b_d`` (px per
    axis; Legendre ``P_d`` of the column mapped to ``t`` on [-1, 1]), e.g. a warm-up that
    levels off."""
    names = tuple(f"{column}_{axis}_p{d}_px" for d in range(1, degree + 1) for axis in "xy")

    def columns(ctx: Context) -> np.ndarray:
        v = getattr(ctx.table, column)
        t = 2.0 * (v - v.min()) / np.ptp(v) - 1.0
        vander = np.polynomial.legendre.legvander(t, degree)[:, 1:]  # shape (N, degree)
        return np.einsum("nd,ak->nadk", vander, np.eye(2)).reshape(len(t), 2, 2 * degree)

    return Term(f"{label}, degree {degree}", names, columns)


def log_focal_coordinate(fx: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(N,) ``u = 2 (ln fx - ln lo) / (ln hi - ln lo) - 1``: the focal range on [-1, 1]."""
    return 2.0 * (np.log(fx) - np.log(lo)) / (np.log(hi) - np.log(lo)) - 1.0


def smooth_path_term(degree: int, lo: float, hi: float, signed: bool = False) -> Term:
    """A principal-point path smooth in log focal length, for a lens without a model:
    ``Delta c = sum_{d=1..degree} P_d(u) b_d`` (px per axis; Legendre ``P_d``, ``u`` from
    :func:`log_focal_coordinate` on the table's range ``[lo, hi]`` px; the constant is the
    offset term's). ``signed``: half the difference between moves in and out, ``Delta c =
    s sum_{d=0..degree} P_d(u) b_d`` with ``s`` the direction (+1 in, -1 out), constant
    included."""
    first = 0 if signed else 1
    label = "direction-signed path" if signed else "smooth path"
    names = tuple(f"{'half_' if signed else ''}path_{axis}_p{d}_px"
                  for d in range(first, degree + 1) for axis in "xy")

    def columns(ctx: Context) -> np.ndarray:
        u = log_focal_coordinate(ctx.table.fx, lo, hi)
        vander = np.polynomial.legendre.legvander(u, degree)[:, first:]  # shape (N, D)
        if signed:
            vander = vander * ctx.table.direction[:, None]
        cols = np.einsum("nd,ak->nadk", vander, np.eye(2))
        return cols.reshape(len(u), 2, 2 * vander.shape[1])

    return Term(f"{label} in log f, degree {degree}", names, columns)


def setting_term(labels: np.ndarray, signed: bool = False) -> Term:
    """A free principal point for every distinct zoom setting (``labels``, (N,) int): any
    function of the zoom at all, for testing what a model leaves at the settings. ``signed``:
    multiplied by the direction of the last move (any difference between in and out)."""
    n_settings = int(labels.max()) + 1
    names = tuple(f"{'half_' if signed else ''}setting{k}_{axis}_px"
                  for k in range(n_settings) for axis in "xy")

    def columns(ctx: Context) -> np.ndarray:
        onehot = np.eye(n_settings)[labels]  # shape (N, S)
        if signed:
            onehot = onehot * ctx.table.direction[:, None]
        return np.einsum("ns,ak->nask", onehot, np.eye(2)).reshape(len(labels), 2,
                                                                   2 * n_settings)

    return Term(f"{'direction-signed ' if signed else ''}free principal point per zoom "
                f"setting", names, columns)


def design_matrix(terms: tuple[Term, ...], ctx: Context) -> np.ndarray:
    """(2N, K) columns of ``terms`` with rows ordered (cx_0, cy_0, cx_1, ...)."""
    blocks = [t.columns(ctx) for t in terms]  # each shape (N, 2, k)
    full = np.concatenate(blocks, axis=2)
    return full.reshape(-1, full.shape[2])
