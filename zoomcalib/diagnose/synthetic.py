"""Synthetic per-zoom calibration tables with hidden causes, to test a diagnosis.

The generators are independent of the diagnosis's linear model: principal points come from the
exact ray tracer (:func:`zoomcalib.optics.principal_point.principal_point_image`) through the
perturbed lens, so any error in the paraxial sensitivities or in the sign conventions of
:mod:`zoomcalib.diagnose.model` shows up as a failed recovery.

A table is a zoom schedule of ``passes`` x (a sweep in, then a sweep out) over ``n_zoom`` settings,
the last move's direction and the capture order recorded per row. The truth is

- a sensor offset and, for every moving group, a decentre and tilt locked to the barrel (random
  amplitude up to the tolerance's, random phase), plus random play at every visit (the
  tolerances' ``play_um`` and ``play_tilt_arcmin``);
- measurement noise of the calibration, 1-sigma ``sd_wide_px * (f / f_min) ** sd_growth``;
- hidden causes, each of a random direction and of a magnitude given as the RMS of its effect
  over the rows (less its mean) in units of the RMS noise.

:func:`synthetic_zoom_table` follows the diagnosis's own assumptions: Gaussian play of exactly
the tolerance file's size, the table's sigmas reported correctly, at most one cause.
:func:`independent_zoom_table` breaks them on purpose: zero, one or two causes at once, play of a
size unknown to the diagnosis and of a non-Gaussian distribution, sigmas misreported by a common
factor, and an optional smooth effect that none of the six causes represents.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.polynomial import legendre

from ..camera import Sensor
from ..optics.cam import barrel_angle, solve_gaps
from ..optics.mechanics import ARCMIN, UM, Tolerances, load_tolerances
from ..optics.misalignment import Misalignment
from ..optics.paraxial import effective_focal_length
from ..optics.prescription import Prescription
from ..optics.principal_point import principal_point_image
from .model import (
    Context,
    LensResponse,
    Term,
    axis_tilt_term,
    covariate_term,
    design_matrix,
    direction_offset_term,
    group_term,
    moving_groups,
    offset_term,
    play_sd_px,
)
from .table import ZoomTable

__all__ = ["TableOptions", "IndependentTableOptions", "synthetic_zoom_table",
           "independent_zoom_table", "unlisted_capture", "cause_terms", "HIDDEN_CAUSES",
           "PLAY_DISTRIBUTIONS", "session_correlation"]

HIDDEN_CAUSES = ("axis_tilt", "backlash", "thermal_drift", "cam_harmonic", "static_decenter",
                 "focus_shift")
_MECHANICAL = ("backlash", "cam_harmonic", "static_decenter")


def _rot(angle: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """(N, 2) rotation of the fixed 2-vector ``vec`` by each angle."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * vec[0] - s * vec[1], s * vec[0] + c * vec[1]], axis=-1)


def _visible_rms(effect: np.ndarray) -> float:
    """RMS of an (N, 2) effect without its mean: a constant shift is the sensor offset's."""
    return float(np.sqrt(np.mean((effect - effect.mean(axis=0)) ** 2)))


def _gaussian(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.standard_normal(shape)


def _uniform(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.uniform(-np.sqrt(3.0), np.sqrt(3.0), shape)


def _laplace(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.laplace(0.0, 1.0 / np.sqrt(2.0), shape)


#: unit-variance draws of the random play, by distribution name
PLAY_DISTRIBUTIONS: dict[str, Callable[[np.random.Generator, tuple[int, ...]], np.ndarray]] = {
    "gaussian": _gaussian, "uniform": _uniform, "laplace": _laplace}


@dataclass
class _Bench:
    """The zoom schedule of a table and the lens state of each row.

    ``z`` lens state in [0, 1], ``direction`` +1 after a move in, ``seq`` capture order,
    ``phi`` barrel angle (rad), ``efl`` (mm), ``fx`` (px), ``thickness`` the gaps per row.
    """

    lens: Prescription
    pitch_mm: float
    groups: tuple[str, ...]
    gi: dict[str, int]
    z: np.ndarray
    direction: np.ndarray
    seq: np.ndarray
    phi: np.ndarray
    efl: np.ndarray
    fx: np.ndarray
    thickness: np.ndarray
    sensor: Sensor

    @property
    def n(self) -> int:
        return len(self.z)

    @classmethod
    def of(cls, lens: Prescription, n_zoom: int, passes: int, pitch_mm: float) -> _Bench:
        settings = np.linspace(0.0, 1.0, n_zoom)
        z = np.concatenate([np.concatenate([settings, settings[::-1]]) for _ in range(passes)])
        direction = np.tile(np.repeat([1.0, -1.0], n_zoom), passes)
        thickness = lens.thickness_at(solve_gaps(lens, z))
        efl = effective_focal_length(lens, thickness)
        groups = moving_groups(lens)
        return cls(lens, pitch_mm, groups, {g: lens.group_index(g) for g in groups}, z,
                   direction, np.arange(len(z), dtype=float), barrel_angle(z), efl,
                   efl / pitch_mm, thickness,
                   Sensor(width_px=1280, height_px=960, pixel_pitch_mm=pitch_mm))

    def principal_points(self, decenter: np.ndarray, tilt: np.ndarray,
                         offset: np.ndarray) -> np.ndarray:
        """(N, 2) principal point (px) from the exact tracer; decentres in mm, tilts in rad."""
        image = principal_point_image(self.lens, self.thickness, Misalignment(decenter, tilt))
        return self.sensor.image_plane_to_pixels(image) + (offset - self.sensor.centre_px)


def _mechanical_errors(b: _Bench, tolerances: Tolerances, rng: np.random.Generator,
                       play: Callable[[np.random.Generator, tuple[int, ...]], np.ndarray],
                       play_scale: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Locked decentre (mm) and tilt (rad) of every moving group, and their random play.

    Returns four arrays of shape (N, G, 2): locked decentre, locked tilt, play decentre, play
    tilt. The play's 1-sigma per axis is ``play_scale`` times the tolerance's.
    """
    shape = (b.n, len(b.lens.groups), 2)
    dec, tilt, play_dec, play_tilt = (np.zeros(shape) for _ in range(4))
    for g in b.groups:
        tol = tolerances.for_group(g)
        a_dec = tol.locked_decenter_um * UM * rng.uniform(0.5, 1.0)
        a_tilt = tol.locked_tilt_arcmin * ARCMIN * rng.uniform(0.5, 1.0)
        dec[:, b.gi[g]] = _rot(b.phi + rng.uniform(0, 2 * np.pi), np.array([a_dec, 0.0]))
        tilt[:, b.gi[g]] = _rot(b.phi + rng.uniform(0, 2 * np.pi), np.array([a_tilt, 0.0]))
        play_dec[:, b.gi[g]] = play(rng, (b.n, 2)) * tol.play_um * UM * play_scale
        play_tilt[:, b.gi[g]] = play(rng, (b.n, 2)) * tol.play_tilt_arcmin * ARCMIN * play_scale
    return dec, tilt, play_dec, play_tilt


def _covariates(b: _Bench, rng: np.random.Generator, with_focus: bool,
                with_temperature: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Focus setting per row (arbitrary unit) and temperature (deg C, warming up), or None."""
    focus = rng.choice([0.0, 0.5, 1.0, 2.0], size=b.n) if with_focus else None
    temperature = None
    if with_temperature:
        warm = 8.0 * (1.0 - np.exp(-b.seq / (0.4 * b.n))) + rng.normal(0.0, 0.1, b.n)
        temperature = 20.0 + warm
    return focus, temperature


@dataclass
class _State:
    """The lens as perturbed so far: decentre (mm) and tilt (rad) per row and group, offset (px),
    the principal points (px) they give together with ``linear``, the (N, 2) sum of the causes
    added outside the tracer (axis tilt, drifts; px)."""

    decenter: np.ndarray
    tilt: np.ndarray
    offset: np.ndarray
    pp: np.ndarray
    linear: np.ndarray | float = 0.0


def _add_cause(b: _Bench, state: _State, cause: str, m: float, noise_rms: float,
               rng: np.random.Generator, focus: np.ndarray | None,
               temperature: np.ndarray | None) -> tuple[np.ndarray, dict[str, float], str | None]:
    """Add one hidden cause of magnitude ``m`` (RMS of its visible effect / ``noise_rms``).

    ``state`` is updated in place. Returns the principal points after the cause (px), its
    parameters named as the diagnosis names them, and its group (None when it has none).
    """
    ang = rng.uniform(0, 2 * np.pi)
    unit = np.array([np.cos(ang), np.sin(ang)])
    if cause in _MECHANICAL:
        g = b.groups[rng.integers(len(b.groups))]
        if cause == "backlash":
            # the group sits +-b/2 along a barrel-fixed direction, sign by the last move
            shift = b.direction[:, None] * _rot(b.phi, unit)
        elif cause == "cam_harmonic":
            shift = _rot(2.0 * b.phi, unit)
        else:
            shift = np.broadcast_to(unit, (b.n, 2))

        def with_amplitude(a_um: float) -> tuple[np.ndarray, np.ndarray]:
            dec = state.decenter.copy()
            dec[:, b.gi[g]] += a_um * UM * shift
            return b.principal_points(dec, state.tilt, state.offset) + state.linear, dec

        per_um = with_amplitude(1.0)[0] - state.pp
        a_um = m * noise_rms / _visible_rms(per_um)
        state.pp, state.decenter = with_amplitude(a_um)
        return state.pp, {f"{g}_x_um": a_um * unit[0], f"{g}_y_um": a_um * unit[1]}, g
    if cause == "axis_tilt":
        per_unit = 1e-3 * b.fx[:, None] * unit
        names = ("tilt_x_mrad", "tilt_y_mrad")
    elif cause == "thermal_drift":
        v = temperature if temperature is not None else b.seq
        per_unit = (v - v.mean())[:, None] * unit
        names = (("rate_x_px_per_K", "rate_y_px_per_K") if temperature is not None
                 else ("rate_x_px_per_capture", "rate_y_px_per_capture"))
    else:  # focus_shift
        if focus is None:
            raise ValueError("focus_shift needs the focus column (with_focus=True)")
        per_unit = (focus - focus.mean())[:, None] * unit
        names = ("rate_x_px_per_focus_unit", "rate_y_px_per_focus_unit")
    a = m * noise_rms / _visible_rms(per_unit)
    state.pp = state.pp + a * per_unit
    state.linear = state.linear + a * per_unit
    return state.pp, {names[0]: a * unit[0], names[1]: a * unit[1]}, None


def _rows(b: _Bench, rng: np.random.Generator, pp: np.ndarray, sd_true: np.ndarray,
          sd_reported: np.ndarray, focus: np.ndarray | None, temperature: np.ndarray | None,
          sessions: np.ndarray | None = None, share: float = 0.0
          ) -> tuple[list[dict], np.ndarray]:
    """The ``zoom_calibration.csv`` rows and the (N, 2) measurement noise added to ``pp`` (px).

    With ``sessions`` ((N,) int labels), the share ``share`` of each row's measurement variance
    is common to its session, per axis: ``sd_i (sqrt(1 - share) e_i + sqrt(share) u_k)``, the
    rows' ``session`` column says which."""
    n = b.n
    noise = np.stack([rng.standard_normal(n) * sd_true, rng.standard_normal(n) * sd_true], -1)
    if sessions is not None:
        common = rng.standard_normal((int(sessions.max()) + 1, 2))[sessions]
        noise = np.sqrt(1.0 - share) * noise + np.sqrt(share) * common * sd_true[:, None]
    cx = pp[:, 0] + noise[:, 0]
    cy = pp[:, 1] + noise[:, 1]
    fx_meas = b.fx * (1.0 + rng.normal(0.0, 5e-4, n))
    counts = np.round(9000.0 * b.z ** 0.8)  # a monotone encoder scale
    rows = []
    for i in range(n):
        row = {"step": f"s{i:03d}", "zoom": float(counts[i]), "fx": fx_meas[i],
               "fy": fx_meas[i] * (1.0 + rng.normal(0.0, 2e-4)), "cx": cx[i], "cy": cy[i],
               "sd_fx": 5e-4 * b.fx[i], "sd_fy": 5e-4 * b.fx[i], "sd_cx": sd_reported[i],
               "sd_cy": sd_reported[i], "direction": "in" if b.direction[i] > 0 else "out",
               "sequence": i}
        if focus is not None:
            row["focus"] = float(focus[i])
        if temperature is not None:
            row["temperature"] = float(temperature[i])
        if sessions is not None:
            row["session"] = f"session{sessions[i] + 1}"
        rows.append(row)
    return rows, noise


def session_correlation(sessions: np.ndarray, share: float) -> np.ndarray:
    """(2N, 2N) correlation of the rows' measured principal points, ``(cx_0, cy_0, cx_1,
    ...)``, when the share ``share`` of each row's variance is common to its session
    (``sessions`` (N,) labels), per axis.

    Examples
    --------
    >>> session_correlation(np.array([0, 0, 1]), 0.5)[0]
    array([1. , 0. , 0.5, 0. , 0. , 0. ])
    """
    same = np.asarray(sessions)[:, None] == np.asarray(sessions)[None, :]
    corr = np.kron(share * same, np.eye(2))
    np.fill_diagonal(corr, 1.0)
    return corr


def _draw(value: float | tuple[float, float], rng: np.random.Generator,
          log: bool = False) -> float:
    """``value``, or a uniform draw in the range (log-uniform when ``log``)."""
    if not isinstance(value, tuple):
        return float(value)
    if log:
        return float(np.exp(rng.uniform(np.log(value[0]), np.log(value[1]))))
    return float(rng.uniform(*value))


@dataclass(frozen=True)
class TableOptions:
    """The zoom schedule, lens and measurement of a synthetic table
    (:func:`synthetic_zoom_table`; the base of :class:`IndependentTableOptions`).

    Attributes
    ----------
    n_zoom : int
        Zoom settings per sweep.
    passes : int
        Repetitions of (in sweep, out sweep).
    pitch_mm : float
        Pixel pitch, mm.
    tolerances : Tolerances, optional
        Locked-error amplitudes and play (default: the built-in tolerances).
    sd_wide_px : float
        Measurement 1-sigma of cx and cy at the shortest focal length, px.
    sd_growth : float or (float, float)
        Exponent of its growth with focal length, ``(f / f_min) ** sd_growth``; a range (drawn
        uniformly) for :func:`independent_zoom_table` only.
    with_focus, with_temperature : bool
        Add a ``focus`` / ``temperature`` column (focus forced on for ``focus_shift``).
    """

    n_zoom: int = 9
    passes: int = 2
    pitch_mm: float = 0.00645
    tolerances: Tolerances | None = None
    sd_wide_px: float = 0.05
    sd_growth: float | tuple[float, float] = 1.0
    with_focus: bool = False
    with_temperature: bool = False

    def bench(self, lens: Prescription) -> _Bench:
        """The table's zoom schedule and the lens state of each row."""
        return _Bench.of(lens, self.n_zoom, self.passes, self.pitch_mm)

    def tolerances_or_default(self) -> Tolerances:
        """``tolerances``, or the built-in ones."""
        return self.tolerances if self.tolerances is not None else load_tolerances()


def synthetic_zoom_table(lens: Prescription, cause: str | None, rng: np.random.Generator,
                         options: TableOptions | None = None, *,
                         magnitude: float | tuple[float, float] = (3.0, 8.0),
                         **fields) -> tuple[list[dict], dict]:
    """A measured ``zoom_calibration.csv`` table with one hidden cause.

    Parameters
    ----------
    lens : Prescription
    cause : str or None
        One of :data:`HIDDEN_CAUSES`, or None for the simulation's model alone.
    rng : numpy.random.Generator
    options : TableOptions, optional
        Zoom schedule, tolerances and measurement noise (default: its defaults); ``fields``,
        keywords named as its fields, replace them (``n_zoom=13, with_focus=True``).
    magnitude : float or (float, float)
        RMS over the rows of the hidden effect less its mean (a constant shift cannot be told
        from the sensor offset), in units of the RMS noise; a range draws it uniformly.

    Returns
    -------
    rows : list of dict
        The table (``zoom_calibration.csv`` columns; ``zoom`` is an encoder count).
    truth : dict
        ``cause``, ``group`` (for mechanical causes), ``params`` named as the diagnosis names
        them, ``magnitude`` (noise units), ``z`` (lens state per row) and ``noise_rms_px``.
    """
    opts = replace(options or TableOptions(), **fields)
    if cause is not None and cause not in HIDDEN_CAUSES:
        raise ValueError(f"cause must be one of {HIDDEN_CAUSES} or None, got {cause!r}")
    tolerances = opts.tolerances_or_default()
    with_focus = opts.with_focus or cause == "focus_shift"
    b = opts.bench(lens)
    dec, tilt, play_dec, play_tilt = _mechanical_errors(b, tolerances, rng, _gaussian, 1.0)
    state = _State(dec + play_dec, tilt + play_tilt,
                   b.sensor.centre_px + rng.normal(0.0, 15.0, 2), np.zeros((b.n, 2)))
    state.pp = b.principal_points(state.decenter, state.tilt, state.offset)
    sd_meas = opts.sd_wide_px * (b.efl / b.efl.min()) ** opts.sd_growth
    # the noise the diagnosis is told about: measurement and play scatter (reported in truth)
    play = play_sd_px(lens, b.z, tolerances, opts.pitch_mm)
    noise_rms = float(np.sqrt(np.mean(sd_meas ** 2 + play ** 2)))
    focus, temperature = _covariates(b, rng, with_focus, opts.with_temperature)
    truth: dict = {"cause": cause or "none", "params": {}, "z": b.z, "noise_rms_px": noise_rms}
    if cause is not None:
        m = _draw(magnitude, rng)
        truth["magnitude"] = m
        _, truth["params"], group = _add_cause(b, state, cause, m, noise_rms, rng, focus,
                                               temperature)
        if group is not None:
            truth["group"] = group
    rows, _ = _rows(b, rng, state.pp, sd_meas, sd_meas, focus, temperature)
    return rows, truth


def cause_terms(groups: tuple[str, ...], table: ZoomTable) -> dict[str, list[tuple[Term, ...]]]:
    """Every variant of the six causes' columns (from :mod:`zoomcalib.diagnose.model`) that the
    table's columns allow: one per moving group for the mechanical causes, the direction-signed
    offset for backlash, drift with temperature and with capture order."""
    terms: dict[str, list[tuple[Term, ...]]] = {
        "axis_tilt": [(axis_tilt_term(),)],
        "backlash": [(direction_offset_term(),)] + [
            (group_term(g, "decenter", 1, "backlash", signed_by="direction"),) for g in groups],
        "thermal_drift": [(covariate_term("sequence", "capture", "drift"),)],
        "cam_harmonic": [(group_term(g, "decenter", 2, "cam"),) for g in groups],
        "static_decenter": [(group_term(g, "decenter", 0, "static"),) for g in groups],
    }
    if table.temperature is not None:
        terms["thermal_drift"].append((covariate_term("temperature", "K", "thermal"),))
    if table.focus is not None:
        terms["focus_shift"] = [(covariate_term("focus", "focus_unit", "focus"),)]
    return terms


def _baseline(groups: tuple[str, ...]) -> tuple[Term, ...]:
    """The paper's model: sensor offset and the rotation-locked decentre of each moving group."""
    return (offset_term(),) + tuple(group_term(g, "decenter", 1, "locked") for g in groups)


def _residual(A: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``y`` less its weighted least-squares fit by the columns of ``A`` (weights ``w**2``)."""
    beta = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)[0]
    return y - A @ beta


def unlisted_capture(effect_px: np.ndarray, ctx: Context, sigma_px: np.ndarray
                     ) -> dict[str, float]:
    """Fraction of an effect's chi2 beyond the baseline that each cause's columns capture.

    Parameters
    ----------
    effect_px : (N, 2) ndarray
        The effect on (cx, cy), px.
    ctx : Context
        The rows (lens state, table columns) the columns are evaluated at.
    sigma_px : (N,) ndarray
        1-sigma per axis of each row (the weights of the projection), px.

    Returns
    -------
    dict
        Per testable cause (best of its variants), ``"pair"`` (the best two distinct causes
        together) and ``"all"`` (every variant at once):
        ``1 - chi2(effect less baseline + cause) / chi2(effect less baseline)``, in [0, 1].
    """
    w = np.repeat(1.0 / sigma_px, 2)
    base = design_matrix(_baseline(ctx.response.groups), ctx)
    e = _residual(base, effect_px.reshape(-1), w)
    e2 = float(np.sum((w * e) ** 2))
    if e2 == 0.0:
        raise ValueError("the effect is all baseline: nothing is left to capture")
    def captured(*blocks: np.ndarray) -> float:
        r = _residual(np.hstack((base,) + blocks), e, w)
        return 1.0 - float(np.sum((w * r) ** 2)) / e2

    columns = {cause: [design_matrix(terms, ctx) for terms in variants]
               for cause, variants in cause_terms(ctx.response.groups, ctx.table).items()}
    out = {cause: max(captured(c) for c in cols) for cause, cols in columns.items()}
    out["pair"] = max(captured(c1, c2) for v1, v2 in itertools.combinations(columns.values(), 2)
                      for c1 in v1 for c2 in v2)
    out["all"] = captured(*(c for cols in columns.values() for c in cols))
    return out


def _unlisted_effect(b: _Bench, ctx: Context, sigma_px: np.ndarray, m: float, noise_rms: float,
                     degree: int, max_captured: float, max_captured_pair: float | None,
                     rng: np.random.Generator, attempts: int = 1000) -> dict:
    """A random smooth curve in log focal length, its baseline part removed, that no cause
    captures more than ``max_captured`` of (nor any two causes together more than
    ``max_captured_pair``, when given); scaled to ``m`` times ``noise_rms`` (visible RMS)."""
    log_f = np.log(b.efl)
    u = 2.0 * (log_f - log_f.min()) / np.ptp(log_f) - 1.0  # in [-1, 1]
    base = design_matrix(_baseline(b.groups), ctx)
    w = np.repeat(1.0 / sigma_px, 2)
    for k in range(1, attempts + 1):
        coef = np.zeros((2, degree + 1))
        coef[:, 1:] = rng.standard_normal((2, degree))  # the constant is the sensor offset's
        curve = np.stack([legendre.legval(u, coef[0]), legendre.legval(u, coef[1])], -1)
        effect = _residual(base, curve.reshape(-1), w).reshape(-1, 2)
        effect *= m * noise_rms / _visible_rms(effect)
        captured = unlisted_capture(effect, ctx, sigma_px)
        if (max(v for c, v in captured.items() if c in HIDDEN_CAUSES) <= max_captured
                and (max_captured_pair is None or captured["pair"] <= max_captured_pair)):
            return {"magnitude": m, "effect_px": effect, "coefficients": coef,
                    "captured": captured, "draws": k}
    raise RuntimeError(f"no unlisted curve of degree {degree} in {attempts} draws kept every "
                       f"cause's captured fraction below {max_captured} (and every pair's "
                       f"below {max_captured_pair})")


@dataclass(frozen=True)
class IndependentTableOptions(TableOptions):
    """How the table of :func:`independent_zoom_table` departs from the diagnosis's
    assumptions, beside the fields of :class:`TableOptions` (whose ``sd_growth`` may here be
    a range, drawn uniformly).

    Attributes
    ----------
    causes : sequence of (cause, magnitude)
        Zero, one or more distinct :data:`HIDDEN_CAUSES`, each with its magnitude: the RMS over
        the rows of its effect less its mean, in units of the true RMS noise (measurement and
        play); a range draws it uniformly. Each cause has its own random direction (and group).
    play_scale : float or (float, float)
        True play 1-sigma over the tolerance file's (the diagnosis assumes 1); a range draws it
        log-uniformly.
    play_distribution : str
        ``"gaussian"``, ``"uniform"`` or ``"laplace"`` (:data:`PLAY_DISTRIBUTIONS`), each of the
        same 1-sigma.
    sd_factor : float or (float, float)
        The table's ``sd_cx`` and ``sd_cy`` are the true 1-sigma times this (log-uniform draw).
    unlisted : float or (float, float)
        Magnitude (noise units, as for ``causes``) of a smooth effect none of the causes
        represents; 0 for none. It is a random Legendre curve of ``unlisted_degree`` per axis in
        ``log f``, less its weighted projection on the baseline (so all of it is visible), and is
        redrawn until no cause captures more than ``max_captured`` of its chi2
        (:func:`unlisted_capture`, weights from the true noise) and, when
        ``max_captured_pair`` is given, no two causes together more than that.
    unlisted_degree : int
        Degree of the unlisted curve's Legendre polynomial per axis.
    max_captured : float
        Largest fraction of the unlisted effect's chi2 any one cause may capture.
    max_captured_pair : float, optional
        Largest fraction any two causes together may capture; None: no limit.
    sessions : int
        Capture sessions, contiguous runs of the capture order (the ``session`` column) when
        more than 1.
    session_share : float or (float, float)
        The share of each row's measurement variance common to the rows of its session, per
        axis (a board that one session shares moves its steps' principal points together);
        a range draws it uniformly. ``truth["sd"]["correlation"]`` is the rows' correlation
        (:func:`session_correlation`).
    """

    causes: Sequence[tuple[str, float | tuple[float, float]]] = ()
    play_scale: float | tuple[float, float] = 1.0
    play_distribution: str = "gaussian"
    sd_factor: float | tuple[float, float] = 1.0
    unlisted: float | tuple[float, float] = 0.0
    unlisted_degree: int = 3
    max_captured: float = 0.5
    max_captured_pair: float | None = None
    sessions: int = 1
    session_share: float | tuple[float, float] = 0.0

    def check(self) -> list[str]:
        """The causes' names; ValueError for an unknown or repeated cause or an unknown play
        distribution."""
        names = [c for c, _ in self.causes]
        bad = [c for c in names if c not in HIDDEN_CAUSES]
        if bad or len(set(names)) != len(names):
            raise ValueError(f"causes must be distinct names from {HIDDEN_CAUSES}, got {names}")
        if self.play_distribution not in PLAY_DISTRIBUTIONS:
            raise ValueError(f"play_distribution must be one of {tuple(PLAY_DISTRIBUTIONS)}, "
                             f"got {self.play_distribution!r}")
        shares = np.ravel(self.session_share)
        if self.sessions < 1 or not np.all((shares >= 0) & (shares < 1)):
            raise ValueError(f"sessions must be at least 1 and session_share in [0, 1), got "
                             f"{self.sessions} and {self.session_share}")
        return names


@dataclass(frozen=True)
class _TrueNoise:
    """The noise of an independent table: the play's linearised 1-sigma per axis ``play_px``
    (N,), the measurement's true 1-sigma ``sd_px`` (N,), both together ``sigma_px`` (N,), its
    RMS ``rms_px`` and the RMS the diagnosis assumes from the reported sigmas and the tolerance
    file's play ``assumed_rms_px`` (all px)."""

    play_px: np.ndarray
    sd_px: np.ndarray
    sigma_px: np.ndarray
    rms_px: float
    assumed_rms_px: float

    @classmethod
    def of(cls, b: _Bench, tolerances: Tolerances, play_scale: float, sd_wide_px: float,
           growth: float, factor: float) -> _TrueNoise:
        """The noise of play ``play_scale`` times the tolerance file's and of a measurement
        1-sigma ``sd_wide_px`` growing with exponent ``growth``, reported times ``factor``."""
        moving = Tolerances({g: tolerances.for_group(g) for g in b.groups})  # the play applied
        play_true = play_scale * play_sd_px(b.lens, b.z, moving, b.pitch_mm)
        sd_true = sd_wide_px * (b.efl / b.efl.min()) ** growth
        sigma_true = np.sqrt(sd_true ** 2 + play_true ** 2)
        assumed = np.sqrt((factor * sd_true) ** 2
                          + play_sd_px(b.lens, b.z, tolerances, b.pitch_mm) ** 2)
        return cls(play_true, sd_true, sigma_true, float(np.sqrt(np.mean(sigma_true ** 2))),
                   float(np.sqrt(np.mean(assumed ** 2))))


def _cause_record(b: _Bench, state: _State, cause: str, m: float, noise_rms: float,
                  rng: np.random.Generator, focus: np.ndarray | None,
                  temperature: np.ndarray | None) -> dict:
    """Add one cause to ``state`` (:func:`_add_cause`); its entry in the truth's ``causes``."""
    before = state.pp
    after, params, group = _add_cause(b, state, cause, m, noise_rms, rng, focus, temperature)
    return {"cause": cause, "magnitude": m, "params": params, "group": group,
            "effect_px": after - before}


def _unlisted_context(b: _Bench, pp: np.ndarray, sd_px: np.ndarray, focus: np.ndarray | None,
                      temperature: np.ndarray | None) -> Context:
    """The rows an unlisted effect's capture is measured at: the table of principal points
    ``pp`` (px) with the true sigmas ``sd_px``, and the lens's sensitivities."""
    table = ZoomTable(zoom=b.z, fx=b.fx, fy=b.fx, cx=pp[:, 0], cy=pp[:, 1],
                      sd_cx=sd_px, sd_cy=sd_px, direction=b.direction, sequence=b.seq,
                      focus=focus, temperature=temperature)
    response = LensResponse(b.lens, b.pitch_mm, b.z, b.efl, b.groups)  # sensitivities only
    return Context.build(table, b.z, response)


def independent_zoom_table(lens: Prescription, rng: np.random.Generator,
                           options: IndependentTableOptions | None = None,
                           **fields) -> tuple[list[dict], dict]:
    """A measured table that departs from the diagnosis's assumptions, and its truth.

    Parameters
    ----------
    lens : Prescription
    rng : numpy.random.Generator
    options : IndependentTableOptions, optional
        Causes, play, misreported sigmas and the unlisted effect (default: none of them, the
        defaults of :class:`TableOptions`); ``fields``, keywords named as its fields, replace
        them (``causes=[("backlash", 8.0)], unlisted=3.0``).

    Returns
    -------
    rows : list of dict
        The table, ``zoom_calibration.csv`` columns only.
    truth : dict
        Kept apart from the rows. ``causes`` (list of dicts with ``cause``, ``magnitude``,
        ``params``, ``group`` or None, ``effect_px`` (N, 2)); ``unlisted`` (None, or a dict with
        ``magnitude``, ``effect_px``, ``captured``, ``coefficients``, ``draws``); ``play``
        (``scale``, ``distribution``, ``sd_px`` (N,) its linearised 1-sigma per axis,
        ``effect_px`` (N, 2) from the tracer, ``decenter_mm`` and ``tilt_rad`` (N, G, 2) the
        draws per lens group); ``sd`` (``factor``, ``growth``, ``true_px``,
        ``reported_px``, ``session_share`` and ``correlation``, the rows' correlation or
        None); ``locked_px`` (N, 2) the principal points of the offset and locked
        errors alone; ``measurement_noise_px`` (N, 2); ``noise_rms_px`` (true) and
        ``assumed_noise_rms_px`` (from the reported sigmas and the tolerance file's play);
        ``z``. The table's (cx, cy) are exactly ``locked_px + play.effect_px + sum of the
        causes' effect_px + unlisted.effect_px + measurement_noise_px``; each cause's effect is
        its change of the traced principal points given the causes before it.
    """
    opts = replace(options or IndependentTableOptions(), **fields)
    names = opts.check()
    tolerances = opts.tolerances_or_default()
    with_focus = opts.with_focus or "focus_shift" in names
    b = opts.bench(lens)
    p_scale = _draw(opts.play_scale, rng, log=True)
    factor = _draw(opts.sd_factor, rng, log=True)
    growth = _draw(opts.sd_growth, rng)
    dec, tilt, play_dec, play_tilt = _mechanical_errors(
        b, tolerances, rng, PLAY_DISTRIBUTIONS[opts.play_distribution], p_scale)
    offset = b.sensor.centre_px + rng.normal(0.0, 15.0, 2)
    locked = b.principal_points(dec, tilt, offset)
    state = _State(dec + play_dec, tilt + play_tilt, offset, np.zeros((b.n, 2)))
    state.pp = b.principal_points(state.decenter, state.tilt, offset)
    play_effect = state.pp - locked
    noise = _TrueNoise.of(b, tolerances, p_scale, opts.sd_wide_px, growth, factor)
    focus, temperature = _covariates(b, rng, with_focus, opts.with_temperature)
    truth_causes = [_cause_record(b, state, cause, _draw(magnitude, rng), noise.rms_px, rng,
                                  focus, temperature)
                    for cause, magnitude in opts.causes]
    pp = state.pp
    m_unlisted = _draw(opts.unlisted, rng)
    extra = None
    if m_unlisted > 0:
        ctx = _unlisted_context(b, pp, noise.sd_px, focus, temperature)
        extra = _unlisted_effect(b, ctx, noise.sigma_px, m_unlisted, noise.rms_px,
                                 opts.unlisted_degree, opts.max_captured,
                                 opts.max_captured_pair, rng)
        pp = pp + extra["effect_px"]
    share = _draw(opts.session_share, rng) if opts.sessions > 1 else 0.0
    labels = (np.repeat(np.arange(opts.sessions), [len(c) for c in np.array_split(
        np.arange(b.n), opts.sessions)]) if opts.sessions > 1 else None)
    rows, measurement = _rows(b, rng, pp, noise.sd_px, factor * noise.sd_px, focus, temperature,
                              labels, share)
    truth = {
        "causes": truth_causes, "unlisted": extra,
        "play": {"scale": p_scale, "distribution": opts.play_distribution,
                 "sd_px": noise.play_px, "effect_px": play_effect, "decenter_mm": play_dec,
                 "tilt_rad": play_tilt},
        "sd": {"factor": factor, "growth": growth, "true_px": noise.sd_px,
               "reported_px": factor * noise.sd_px, "session_share": share,
               "correlation": None if labels is None else session_correlation(labels, share)},
        "locked_px": locked, "measurement_noise_px": measurement,
        "noise_rms_px": noise.rms_px, "assumed_noise_rms_px": noise.assumed_rms_px, "z": b.z,
    }
    return rows, truth
