r"""Zoom-wide calibration: every zoom step of one camera in one least-squares adjustment.

Why
---
At the long end of a zoom the views of a board are nearly fronto-parallel and the field of view
is narrow: one step's images hardly separate the principal point and the distortion from the
poses, so a per-step calibration trades them freely (principal points far apart between two
halves of one step, each with a sigma of a few px). The steps are not independent, though: they see
the same board, and the principal point and the distortion of a zoom lens move smoothly with
the focal length. This module estimates all steps together.

Model
-----
Step ``s`` has intrinsics ``theta_s = (fx, fy, cx, cy, k1, k2, p1, p2, k3)`` (OpenCV's pinhole
and Brown-Conrady model, pixels in OpenCV's convention), and the rational model's ``k4, k5, k6``
where its held-out views choose them (:func:`~zoomcalib.calibrate.stepfits.select_distortion`);
each view ``v`` its pose ``Rt_cam_board = (rvec_v, tvec_v)``. The board is one surface for every
view of every step:

.. math::

    X_j = X^0_j + e_z \sum_m a_m \phi_m(x_j, y_j),\qquad
    \phi_m = P_k(\tilde x) P_l(\tilde y),\quad 2 \le k + l \le d,

the nominal flat points ``X^0`` plus a smooth height (paper waviness) in Legendre products of
the normalised board coordinates (degree 0 and 1 are left out: a piston and a tilt are a change
of pose). The amplitudes ``a_m`` (mm) carry a weak zero-mean prior of sd ``board_prior_mm``.
Steps captured in different sessions (``sessions``: a paper board taped to a wall is re-taped,
and bends otherwise, each time) each have their session's amplitudes; the steps of one
session share them. On a real PTZ sweep of four capture days, one shape for all moved the
first day's 1x step by 9 of its own sigmas in fx (docs/notes/calibration-zoom-wide.md).

A paper board ripples at a finer scale than any low degree follows (1-2 mm on that sweep,
millimetres apart). With ``board_points`` (the default) each session's board also has a height
``h_j`` for every point, beyond the modes: ``X_j = X^0_j + e_z (sum_m a_m phi_m + h_j)``, with a
zero-mean prior of sd :data:`POINT_HEIGHT_PRIOR_MM` and the part in the span of a plane and the
modes taken out. The heights are fitted point by point between the Levenberg-Marquardt solves
(:func:`_update_heights`), so they stay out of the dense global block; their uncertainty does
not enter the intrinsics' covariance (a point's height is fitted from dozens of views; the
low-degree shape that trades with the focal length and the distortion is in the modes, which
do). On the real sweep they bring the residual from 0.8-1.1 px to 0.27-0.39 px at 2x-8x.

A printed pattern is not exact in its plane either: a printer's feed makes a trapezoid or a
bow of a few tenths of a millimetre across a large sheet. With ``print_shape`` the board's
points also move in its plane by the same modes,

.. math:: (X_j, Y_j) \mathrel{+}= \sum_m (b^x_m, b^y_m)\, \phi_m(x_j, y_j),

with one set of amplitudes ``b`` for every session (the print does not change when it is
re-taped) and the modes' prior. Degree 0 and 1 are left out: a shift and a rotation are a
pose, a scale is the board's size, and a shear or a stretch would trade with the aspect ratio.
The modes' amplitudes are in the global block, so what they trade with the principal point
enters its covariance. That costs the narrow steps' principal point a factor of 2-4 in sigma
where the print is exact, so they are kept only where a solve without the smoothness prior
finds them beyond their noise (:class:`PrintTest`: a Wald test at p = 0.001). Where a print
is not exact, leaving its shape out moves the narrow steps' principal point by many of its
sigmas (``tests/test_zoomwide.py``; on a real PTZ sweep, docs/real-camera.md).

The smoothness prior ties each parameter ``q`` of ``cx, cy, k1, k2, p1, p2, k3`` across zoom:
with ``u_s = log fx_s`` (from the per-step start) and the steps sorted by ``u``, the second
divided differences

.. math::

    (D q)_i = 2\left[\frac{q_{i+2} - q_{i+1}}{u_{i+2} - u_{i+1}}
              - \frac{q_{i+1} - q_i}{u_{i+1} - u_i}\right] / (u_{i+2} - u_i)
    \sim N(0, \tau_q^2)

(a path that is linear in log focal length costs nothing). ``tau_q`` is estimated from the data
by restricted maximum likelihood (:func:`prior_strength`) from per-step estimates ``q_hat_s`` and
their covariance: those of a first zoom-wide solve without the smoothness prior (one board,
per-step intrinsics), which are free of the flat-board bias of per-step OpenCV values (a waving
board moves OpenCV's principal point by many of its sigmas, and a ``tau`` estimated from such
values lets the long end borrow little). When that first solve has no usable covariance, the
per-step OpenCV values and sigmas are used, and ``tau_source`` says so. For cx and cy ``tau`` is
then marginalised (:func:`~zoomcalib.calibrate.zoommodel.marginal_tau`): the adjustment uses
its posterior median (REML likelihood, half-Cauchy prior at the noise's own roughness), and
the covariance of each step's cx, cy gains what the spread of ``tau``'s posterior moves them by.
With 7 steps REML has 4-5 differences to go on and can sit at its lower bound on a path whose
long-end bend the noise hides; the plug-in sigma then misses. ``fx`` is
free per step; ``fy = a fx`` with one aspect ratio ``a`` for every step (``shared_aspect``):
pixels do not change shape with the zoom, and a long-end step's own views, nearly
fronto-parallel, trade ``fy / fx`` against the principal point and the poses (1.17 on a real
PTZ camera's 9x step). OpenCV's pinhole has no skew, so that is shared at zero. Steps
reached from different zoom directions (backlash) form separate chains,
and neighbours closer than 0.1 % in focal length are not differenced: a lens state met twice
is two measurements, not a curvature.

The cost is ``sum_s sum_obs |uv_obs - uv(theta_s, pose_v, X_j)|^2 / sigma_s^2 + |D q / tau|^2 +
|a / board_prior|^2``, ``sigma_s`` each step's image noise per coordinate, re-estimated from
the residuals (observations beyond 5 sigma are rejected and the fit repeated). It is minimised by
Levenberg-Marquardt on the sparse Jacobian. The covariance of every parameter is the posterior
``(J^T J)^{-1}`` of the whole problem (prior rows included), so a long-end step's sigma includes
what it borrows from its neighbours; ``info["prior_share"]`` says how much that is for cx, cy.

The principal point's prior reads its angle (``pp_model="angle2"``, the default): for
``q = cx`` or ``cy`` the differences are those of ``(q - c) / fx``, with ``c`` a free px
offset integrated out under a flat prior (:func:`~zoomcalib.calibrate.zoommodel.prior_operator`),
so ``q = c + fx (a + b u)`` costs nothing and ``tau`` is in radians per ``u^2``. A decentred or
tilted moving group shifts the image by an amount that grows with the focal length: on the
ray-traced ``laikin-10x`` the principal point's second differences in px grow 5-26 times from
the short to the long end, in angle they stay within about 2 times. A prior in px
(``pp_model="prior2"``) learns its ``tau`` from the precise short-end steps and then holds the
long end to a straightness that it does not have.

The distortion terms' prior reads their displacement at the image corner (``corner2``): for
a term ``q`` the differences are those of ``q (d / fx)^p``, ``d`` the image's half-diagonal in
px, ``p`` = 2, 4, 6 for k1, k2, k3 and 1 for p1, p2 (:data:`CORNER_POWER`), so ``tau`` is a
fraction of the half-diagonal per ``u^2``. OpenCV's terms act on the radius normalised by
``fx``: a real lens whose corner distortion stays near 1 % over a 10x zoom has a k1 that grows
100 times, and a prior on k1 itself is roughest at the long end, where it carries the term.
Predicting a hidden long end of real lenses (``benchmarks/bench_prior_lensfun.py``), the prior
on the corner misses by more than 3 sigma far less often than a prior on k1.

With ``pp_model="select"`` the prior of cx and cy is instead chosen by held-out steps from the
first solve's values and joint covariance (:mod:`zoomcalib.calibrate.zoommodel`): the prior
above, a third-difference prior, or a polynomial of degree 1-3 in ``u`` (a difference prior of
the next order with ``tau -> 0``), kept to the second-difference prior unless another candidate
predicts the left-out steps better by 2 standard errors.

Which distortion terms a step supports is chosen by held-out views
(:func:`~zoomcalib.calibrate.stepfits.select_distortion`):
two-fold cross-validation over the step's views with OpenCV, the simplest term set whose held-out
error is within 1 % of the best. The choice is made twice: on the flat board, for the start,
then on the board's shape estimated by the solve without the smoothness prior (OpenCV with
those 3-D points, started from the step's calibration). The flat board's misfit sits in every
set's held-out error and hides a term whose effect is a fraction of it: the choice then changes
with the noise draw, and each draw reports the sigma of its own choice. When the second choice
differs, the solve without the prior is repeated with it. In the adjustment with the prior, a
term that some steps of a chain estimate is free at all its steps: where a step's own views
cannot measure it (the long end's narrow field), its neighbours carry it through the prior, and
its sigma says how well (:func:`_tie_terms`).

The rational model's denominator ``1 + k4 r^2 + k5 r^4 + k6 r^6`` trades with its numerator
along a curved ridge: with ``k1 = k4``, ``k2 = k5`` growing together the distortion hardly
changes, and a step whose views prefer the ridge by a few noise variances has no minimum at a
finite distance (the solve walks up it until its iteration cap, and the covariance at the
point it stops at gives fx a sigma hundreds of times what the views determine). Each of
``k4 r_c^2, k5 r_c^4, k6 r_c^6`` at the image's corner (``r_c`` the half-diagonal over fx)
therefore has a zero-mean prior of sd :data:`RATIONAL_PRIOR_AT_CORNER`: it bounds the ridge
and barely moves a step that determines its terms (``benchmarks/bench_solver_iterations.py``).

References: Zheng, Wang & Huang, ISPRS J. Photogramm. 2015 (zoom/focus models of the intrinsics
in one self-calibrating bundle); Willson, CMU-RI-TR-94-17 (1994); Wiley & Wong (1995)
(systematic, repeatable principal-point motion of up to 90 px).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..pool import one_blas_thread
from .basins import BasinCheck, best_basin
from .geometry import project_jacobian
from .opencv_backend import (
    calibrate_opencv,
    keystone_response,
    not_a_camera,
    pose_sigmas_unused,
)
from .result import CalibrationResult, Observations
from .solver import Solve, levenberg_marquardt
from .stepfits import (
    DISTORTION_SETS,
    RATIONAL_TERMS,
    StepStarts,
    TermChoice,
    _distortion_flags,
    _eight,
    _guess,
    _map_steps,
    _select_on_board,
    _without,
    held_out_errors,
    observations_fingerprint,
    select_distortion,
    step_starts,
    with_decentring,
)
from .zoommodel import (
    PathPrior,
    pooled_prior_strength,
    prior_strength,
    second_difference,
)
from .zoomproblem import (
    CORNER_POWER,
    HEIGHT_TOL_MM,
    PARAMS,
    SELECTED,
    SMOOTHED,
    PrintTest,
    _Form,
    _joint_covariance,
    _posterior_covariance,
    _print_test,
    _Setup,
    _State,
    _Step,
    _step_scale,
    _tied,
    _update_heights,
    _update_noise,
    _ZoomProblem,
    board_height_modes,
)
from .zoomrows import (
    MIN_MODEL_STEPS,
    _chains,
    _held_out_paths,
    _principal_point_correlation,
    _prior_share,
    _tie_terms,
    _unsmoothed_rows,
    _zoom_models,
)

__all__ = ["PARAMS", "SMOOTHED", "ZOOM_MODELS", "DISTORTION_SETS", "ZoomWideResult",
           "StepStarts", "TermChoice", "calibrate_zoom_wide", "zoom_wide_starts",
           "select_distortion", "held_out_errors", "with_decentring",
           "prior_strength", "pooled_prior_strength", "second_difference", "board_height_modes"]

#: ``pp_model`` of :func:`calibrate_zoom_wide`: the second-difference prior of the angular
#: principal point, that prior in px, or the zoom model chosen by held-out steps.
ZOOM_MODELS = ("angle2", "prior2", "select")


# ----------------------------------------------------------------------------------------------
# the joint problem (zoomproblem.py holds it)


def _levenberg_marquardt(prob: _ZoomProblem, state: _State, max_iterations: int = 50,
                         tol: float = 1e-9) -> Solve:
    """The adjustment's solve: :func:`zoomcalib.calibrate.solver.levenberg_marquardt` (its
    stop rule, on the Gauss-Newton step's predicted decrease, and its stop reasons)."""
    return levenberg_marquardt(prob, state, max_iterations, tol)


# ----------------------------------------------------------------------------------------------
# the adjustment


@dataclass
class ZoomWideResult:
    """What :func:`calibrate_zoom_wide` found.

    Attributes
    ----------
    results : dict of str to CalibrationResult
        Per step, ``backend = "zoom-wide"``: intrinsics, ``sd`` (posterior 1-sigma of the joint
        problem), per-view RMS, poses, rejected observations, and the common board's points.
    covariance : (P, P) ndarray
        Posterior covariance of all per-step intrinsics, ``columns`` names them.
    columns : list of (str, str)
        ``(step, parameter)`` of each row of ``covariance``.
    board_modes, board_modes_sd : (M,) ndarray
        Height amplitudes of the board (mm) and their sigmas, session after session
        (``board_sessions``), each session's in the order of :func:`board_height_modes`.
    board_sessions : list of str
        The capture sessions, in the order of their amplitudes (``[""]``: one session).
    board_heights : (sessions, N) ndarray or None
        With ``board_points``: each session's point heights beyond the modes, mm.
    print_modes, print_modes_sd : (2, M) ndarray or None
        Where the print's shape was kept (:class:`PrintTest`): its in-plane amplitudes (x,
        then y, each in the order of :func:`board_height_modes`), mm, and their sigmas.
    print_test : PrintTest or None
        With ``print_shape``: whether the print's modes were kept.
    u : dict of str to float
        Per step, the abscissa of the smoothness prior, ``log fx`` of the step's start.
    tau : dict of str to float
        Estimated prior strength per smoothed parameter (per ``u^2``, in the units that
        ``prior_strength`` of :func:`calibrate_zoom_wide` lists); ``inf`` = none.
    tau_source : str
        Which per-step values ``tau`` was estimated from (module docstring).
    zoom_models : dict of str to dict
        Per smoothed parameter: the zoom model (``model``: ``prior2``, ``prior3``, ``poly1`` ..
        ``poly3``, :mod:`~zoomcalib.calibrate.zoommodel`), its difference ``order``, ``tau``,
        the held-out log predictive density of every candidate tried, its ``form`` (how the
        prior reads the parameter) and ``held_out``: each step predicted from the others
        (:func:`_held_out_paths`).
    terms : dict of str to tuple
        Distortion terms estimated per step: those its own held-out views chose
        (``held_out``) and, through the smoothness prior, those the other steps of its chain
        estimate.
    held_out : dict of str to TermChoice
        Per step: the held-out errors behind its distortion terms
        (:class:`~zoomcalib.calibrate.stepfits.TermChoice`).
    unsmoothed : dict of str to dict
        Per step, the solve without the smoothness prior (:func:`_unsmoothed_rows`): rows
        that are not tied to each other by the prior, for the diagnosis; empty when that
        solve had no covariance.
    unsmoothed_pp_correlation : (2S, 2S) ndarray or None
        The correlation of those rows' principal points across steps (the solve's steps share
        the aspect ratio, each capture session's board and the print), ordered ``(cx, cy)``
        step by step in the order of ``unsmoothed``
        (:func:`_principal_point_correlation`); None without that solve's covariance or with
        the principal point held.
    converged : bool
    stop_reason : str
    iterations : int
    skipped : dict of str to str
        Steps left out (no starting calibration), with the reason.
    aspect, aspect_sd : float
        The sensor's aspect ratio ``fy / fx`` shared by every step, and its posterior 1-sigma
        (NaN when each step has its own ``fy``).
    """

    results: dict[str, CalibrationResult]
    covariance: np.ndarray
    columns: list[tuple[str, str]]
    board_modes: np.ndarray
    board_modes_sd: np.ndarray
    tau: dict[str, float]
    terms: dict[str, tuple[str, ...]]
    held_out: dict[str, TermChoice] = field(default_factory=dict)
    converged: bool = False
    stop_reason: str = ""
    iterations: int = 0
    skipped: dict[str, str] = field(default_factory=dict)
    tau_source: str = ""
    zoom_models: dict[str, dict] = field(default_factory=dict)
    aspect: float = float("nan")
    aspect_sd: float = float("nan")
    board_sessions: list[str] = field(default_factory=lambda: [""])
    board_heights: np.ndarray | None = None
    print_modes: np.ndarray | None = None
    print_modes_sd: np.ndarray | None = None
    print_test: PrintTest | None = None
    u: dict[str, float] = field(default_factory=dict)
    unsmoothed: dict[str, dict] = field(default_factory=dict)
    unsmoothed_pp_correlation: np.ndarray | None = None


#: The intrinsics ``fixed`` of :func:`calibrate_zoom_wide` can hold, as the per-step OpenCV
#: backend's (:data:`~zoomcalib.calibrate.opencv_backend.FIXABLE`), and the distortion terms
#: each holds at zero.
FIXABLE = {"principal-point": (), "aspect": (), "k1": ("k1",), "k2": ("k2",), "k3": ("k3",),
           "tangential": ("p1", "p2")}


def _held_terms(fixed: tuple[str, ...]) -> tuple[str, ...]:
    """The distortion terms ``fixed`` holds at zero; ValueError naming an unknown name."""
    for name in fixed:
        if name not in FIXABLE:
            raise ValueError(f"cannot fix {name!r}; choose from {', '.join(FIXABLE)}")
    return tuple(t for name in fixed for t in FIXABLE[name])


def _free_mask(names: list[str], terms: Mapping[str, tuple[str, ...]]) -> np.ndarray:
    """(S, 12) bool: the intrinsics each step estimates (fx, fy, cx, cy and its chosen terms)."""
    return np.array([[p in ("fx", "fy", "cx", "cy") or p in terms[s] for p in PARAMS]
                     for s in names])


def _start(init: Mapping[str, CalibrationResult], terms) -> tuple[_State, np.ndarray, list]:
    cams = np.array([[r.fx, r.fy, r.cx, r.cy, *_eight(r.dist)] for r in init.values()])
    # PARAMS order is k1, k2, p1, p2, k3, k4, k5, k6: OpenCV's first eight terms
    free = _free_mask(list(init), terms)
    cams[:, 4:][~free[:, 4:]] = 0.0
    rvecs = np.concatenate([r.rvecs for r in init.values()])
    tvecs = np.concatenate([r.tvecs for r in init.values()])
    sds = [[r.sd.get(p, np.nan) for p in PARAMS] for r in init.values()]
    return _State(cams, np.zeros(0), rvecs, tvecs), free, sds


def _with_scatter(result: ZoomWideResult, names: list[str], cams: np.ndarray, noise,
                  free: np.ndarray, gaps: Sequence[Mapping[str, float]] = ()) -> tuple:
    """``(cams, noise, free)`` with the noise scaled per step and parameter by the factor the
    views' scatter put on the adjustment's sigma (the table's sigma without the basin gap over
    ``sd_noise_model``), and each step's basin gap (:func:`_basin_gaps`, px) added in
    quadrature: a held-out step is then judged by the sigmas the table reports."""
    factor = np.ones((len(names), len(PARAMS)))
    gap2 = np.zeros((len(names), len(PARAMS)))
    for s, gap in enumerate(gaps):
        for q, half in gap.items():
            gap2[s, PARAMS.index(q)] = half**2
    for s, n in enumerate(names):
        res = result.results[n]
        base = res.info.get("sd_noise_model", {})
        for j, q in enumerate(PARAMS):
            if base.get(q, 0.0) > 0 and q in res.sd:
                own = np.sqrt(max(res.sd[q] ** 2 - gap2[s, j], 0.0))
                factor[s, j] = max(own / base[q], 1.0)
    if callable(noise):
        def scaled(steps, j, noise=noise):
            at = np.ix_(np.asarray(steps), np.atleast_1d(j))
            f = factor[at].reshape(-1)
            return noise(steps, j) * np.outer(f, f) + np.diag(gap2[at].reshape(-1))
        return cams, scaled, free
    return cams, np.sqrt((np.asarray(noise, float) * factor) ** 2 + gap2), free


@dataclass(frozen=True)
class ZoomWideOptions:
    """The zoom-wide adjustment's choices (:func:`calibrate_zoom_wide`).

    Attributes
    ----------
    select : bool
        Choose each step's distortion terms by held-out views; else all five are free.
    decentring : bool
        Free p1, p2 wherever a radial term is chosen
        (:func:`~zoomcalib.calibrate.stepfits.with_decentring`): the centre of
        distortion is not taken to be the principal point. False holds them at zero unless
        the held-out views chose them, which pins the long end's principal point to the centre
        of distortion: right only for a lens whose distortion is centred on it.
    board_degree : int
        Highest total degree of the board's height modes (< 2: a flat board).
    board_prior_mm : float
        Prior sd of each height amplitude, mm.
    board_points : bool
        Fit, besides the modes, a height for every board point and session (the ripples of a
        paper board that no low-degree surface follows; :func:`_update_heights`).
    print_shape : bool
        Fit the printed pattern's in-plane shape: the modes' low-degree displacement in the
        board's plane, one for every session (a print does not change when re-taped; module
        docstring). False: the pattern is taken to be printed exactly.
    max_rounds : int
        Rounds of noise re-estimation and outlier rejection.
    chains : mapping of step name to str, optional
        Steps with different labels (e.g. the direction of the last zoom move, ``in`` or
        ``out``) are not tied by the smoothness prior: each label's steps form their own chain
        (with one shared ``tau``). Default: one chain.
    pp_model : {'angle2', 'prior2', 'select'}
        How cx and cy follow the zoom: the second-difference prior of the angular principal
        point (module docstring), that prior in px, or the model chosen by held-out steps among
        the difference priors in px of order 2 and 3 and the polynomials of degree 1-3 in
        ``log fx`` (:mod:`~zoomcalib.calibrate.zoommodel`). ``select`` can pick a polynomial
        that the traced lens path does not follow
        (``docs/notes/calibration-zoom-prior.md``).
    prior_strength : mapping of parameter name to float, optional
        A known ``tau`` for some of :data:`SMOOTHED` (e.g. from an earlier calibration of the
        same lens), used as it is instead of being estimated; units of the prior: radians per
        ``u^2`` for cx, cy under ``angle2``, px per ``u^2`` under ``prior2``, a fraction of the
        half-diagonal per ``u^2`` for the distortion terms (module docstring).
    shared_aspect : bool
        One aspect ratio ``fy / fx`` for every step (the sensor's pixels); False gives each
        step its own ``fy``.
    sessions : mapping of step name to str, optional
        The capture session of each step: steps of different sessions see boards of their
        own shape (a paper board re-taped between sessions), steps of one session share
        it. Default: one session.
    fixed : tuple of str
        Intrinsics held at every step (keys of :data:`FIXABLE`, as OpenCV's ``CALIB_FIX_*``
        flags of the per-step fits): the principal point at the image centre ``((w - 1) / 2,
        (h - 1) / 2)``, the aspect ratio at 1, k1, k2, k3 or the tangential terms at 0. A held
        principal point skips the basin check; a held term is never chosen.
    model : {'standard', 'rational'}
        ``standard``: each step's terms chosen as ``select`` says (the rational model only
        where its held-out views choose it); ``rational``: OpenCV's eight terms at every step,
        no choice (``select`` is then ignored): what ``CALIB_RATIONAL_MODEL`` fits per step.
    """

    select: bool = True
    decentring: bool = True
    board_degree: int = 4
    board_prior_mm: float = 1.0
    board_points: bool = True
    print_shape: bool = False
    max_rounds: int = 4
    chains: Mapping[str, str] | None = None
    pp_model: str = "angle2"
    prior_strength: Mapping[str, float] | None = None
    shared_aspect: bool = True
    sessions: Mapping[str, str] | None = None
    fixed: tuple[str, ...] = ()
    model: str = "standard"


@one_blas_thread
def zoom_wide_starts(observations: Mapping[str, Observations],
                     options: ZoomWideOptions | None = None, *, workers: int = 1,
                     **fields) -> StepStarts:
    """Every step's own fits (:func:`~zoomcalib.calibrate.stepfits.step_starts`: the held-out
    choice of its terms and its OpenCV start) as :func:`calibrate_zoom_wide` makes them with
    these options; give them to adjustments of the same observations (``starts=``) that
    differ in the options the fits do not depend on (all but ``select``, ``decentring``,
    ``fixed`` and ``model``) to skip making them again."""
    opts = replace(options or ZoomWideOptions(), **fields)
    return step_starts(observations, opts.select and opts.model == "standard", opts.decentring,
                       workers, _held_terms(tuple(opts.fixed)), opts.model)


@one_blas_thread
def calibrate_zoom_wide(observations: Mapping[str, Observations],
                        options: ZoomWideOptions | None = None, *, workers: int = 1,
                        starts: StepStarts | None = None, **fields) -> ZoomWideResult:
    """Calibrate every zoom step of one camera together (module docstring).

    Parameters
    ----------
    observations : mapping of step name to Observations
        The same board (same ``object_points``, board frame, mm) at every step; at least 3
        views per step (6 for the choice of distortion terms).
    options : ZoomWideOptions, optional
        The adjustment's choices (default: :class:`ZoomWideOptions`' defaults); ``fields``,
        keywords named as its fields, replace them (``print_shape=True``).
    workers : int
        Processes for the steps' own OpenCV fits (the distortion-term choice by held-out views
        and the starts); the results do not depend on it.
    starts : StepStarts, optional
        The steps' own fits, made earlier by :func:`zoom_wide_starts` for these observations
        and options (ValueError otherwise): the result is the same as without them.


    Returns
    -------
    ZoomWideResult

    Raises
    ------
    ValueError
        If the steps see different boards or have different image sizes, fewer than 2
        steps are given, or ``starts`` were made for other observations or options.
    """
    opts = replace(options or ZoomWideOptions(), **fields)
    _check_options(opts.pp_model, opts.prior_strength)
    if opts.model not in ("standard", "rational"):
        raise ValueError(f"model must be 'standard' or 'rational', got {opts.model!r}")
    held_terms = _held_terms(tuple(opts.fixed))
    setup, state, free = _set_up(observations, opts, held_terms, workers, starts)
    print_test, solved, state = _test_the_print(setup, state, free, opts.max_rounds,
                                                held_terms)
    # first without the smoothness prior: per-step values free of the flat-board bias
    free_solve = _solve_unsmoothed(setup, state, free, observations, opts, held_terms,
                                   workers, solved)
    solve, state, free = free_solve.solve, free_solve.start, free_solve.free
    joint_cov, iterations, basins = (free_solve.joint_cov, free_solve.iterations,
                                     free_solve.basins)
    forms = _Form.of(opts.pp_model, np.exp(setup.u),
                     0.5 * np.hypot(*observations[setup.names[0]].image_size))
    if joint_cov is not None:
        state, tau_source = solve.state, "zoom-wide solve without the prior"
        noise, selected = joint_cov, SELECTED if opts.pp_model == "select" else ()
    else:  # per-step OpenCV values are biased by a waving board: no choice of model from them
        tau_source = "per-step OpenCV (the solve without the prior had no covariance)"
        noise, selected = setup.sds, ()
    models, inflation = _zoom_models(state.cams, noise, free, setup.chain_idx, setup.u,
                                     selected, forms, opts.prior_strength or {})
    unsmoothed = (state.cams.copy(), noise, free.copy())
    free = _tie_terms(state, free, setup.chain_idx, setup.u, models)
    terms = {n: tuple(p for p, f in zip(PARAMS[4:], free[s, 4:], strict=True) if f)
             for s, n in enumerate(setup.names)}
    prob = setup.problem(free, {k: m.tau for k, m in models.items()}, models, forms)
    solve, more = _solve_with_noise(prob, state, free, opts.max_rounds)
    result = _finish(prob, solve, solve.state, setup.init, terms, setup.held, models,
                     iterations + more, inflation, basins)
    result.skipped, result.tau_source = setup.skipped, tau_source
    result.board_sessions = setup.session_names
    result.print_test = print_test
    _describe(result, setup, prob, solve, unsmoothed, basins, forms, models, joint_cov,
              tau_source)
    _add_model_choice_spread(result, observations, setup.held, opts.decentring, held_terms)
    _add_keystone_responses(result, observations, "principal-point" in opts.fixed)
    return result


def _add_keystone_responses(result: ZoomWideResult, observations: Mapping[str, Observations],
                            principal_point_held: bool = False) -> None:
    """Each step's ``info["keystone_response"]``: how its calibration answers a keystone of
    the image (:func:`~zoomcalib.calibrate.opencv_backend.keystone_response`), linearised at
    the adjustment's solution on the step's views and its board's estimated points, with the
    step's distortion terms free, its aspect ratio held where every step shares one and its
    principal point where it is held. The shared board and aspect make the adjustment's own
    answer differ a little from this one-step problem's; the diagnosis reads an axis tilt's
    keystone from it (``docs/diagnose.md``). Left out where that problem is singular."""
    shared_aspect = bool(np.isfinite(result.aspect))
    for name, res in result.results.items():
        flags = _distortion_flags(result.terms.get(name, ()))
        if shared_aspect:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
        if principal_point_held:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        obs = observations[name]
        board = np.asarray(res.object_points, float)
        obj = [board[np.asarray(ids)] for ids, _ in obs.views]
        response = keystone_response(obj, res.K, res.dist, res.rvecs, res.tvecs, flags,
                                     len(res.dist))
        if response is not None:
            res.info["keystone_response"] = {k: v.tolist() for k, v in response.items()}


def _set_up(observations: Mapping[str, Observations], opts: ZoomWideOptions,
            held_terms: tuple[str, ...], workers: int, starts: StepStarts | None = None
            ) -> tuple[_Setup, _State, np.ndarray]:
    """The steps' own fits (``starts``, copied, or made) and the adjustment's start
    (:class:`_Setup`, the state, the free mask); ValueError when fewer than 2 steps can be
    started or ``starts`` do not fit."""
    select = opts.select and opts.model == "standard"
    board = _common_board(observations)
    if starts is None:
        starts = step_starts(observations, select, opts.decentring, workers, held_terms,
                             opts.model)
    else:
        _check_starts(starts, observations, (bool(select), bool(opts.decentring),
                                             tuple(held_terms), opts.model))
        starts = copy.deepcopy(starts)  # the adjustment changes terms and choices in place
    terms, held, init, skipped = starts.terms, starts.held, starts.init, starts.skipped
    names = [n for n in observations if n in init]
    if len(names) < 2:
        raise ValueError("a zoom-wide calibration needs 2 or more steps that can be started; "
                         + "; ".join(skipped.values()))
    state, free, sds = _start(init, terms)
    aspect_held = "aspect" in opts.fixed
    shared_aspect = opts.shared_aspect or aspect_held
    if shared_aspect:  # started at the median of the steps' own ratios, or held at 1
        state.aspect = 1.0 if aspect_held else float(np.median(state.cams[:, 1]
                                                                / state.cams[:, 0]))
        state.cams[:, 1] = state.aspect * state.cams[:, 0]
        free[:, 1] = False
    if "principal-point" in opts.fixed:
        w, h = observations[names[0]].image_size
        state.cams[:, 2:4] = (w - 1) / 2.0, (h - 1) / 2.0
        free[:, 2:4] = False
    u = np.log(state.cams[:, 0])
    chain_idx = _chains(u, [str((opts.chains or {}).get(n, "")) for n in names])
    phi = (board_height_modes(board, opts.board_degree) if opts.board_degree >= 2
           else np.zeros((len(board), 0)))
    labels = [str((opts.sessions or {}).get(n, "")) for n in names]
    session_names = list(dict.fromkeys(labels))
    session = np.array([session_names.index(lab) for lab in labels])
    state.modes = np.zeros(phi.shape[1] * (len(session_names) + 2 * opts.print_shape))
    if opts.board_points:
        state.heights = np.zeros((len(session_names), len(board)))
    rational_sd = _rational_sd(state.cams[:, 0], observations[names[0]].image_size)
    steps = [_Step.from_observations(n, observations[n], max(init[n].rms_px, 1e-3) / np.sqrt(2))
             for n in names]
    setup = _Setup(names, steps, board, phi, u, chain_idx, labels, session_names, session, init,
                   terms, held, skipped, sds, shared_aspect, aspect_held,
                   bool(opts.print_shape and phi.shape[1]), opts.board_prior_mm,
                   rational_sd, _off_the_ridge(state, free, rational_sd, names))
    return setup, state, free


def _check_starts(starts: StepStarts, observations: Mapping[str, Observations],
                  choices: tuple) -> None:
    """ValueError naming what differs when ``starts`` were not made for these observations
    and these choices (``select``, ``decentring``, held terms, model)."""
    made = starts.made_for
    if made[:4] != choices:
        names = ("select", "decentring", "held terms", "model")
        diff = [f"{n} {a!r} (starts: {b!r})" for n, a, b in zip(names, choices, made[:4],
                                                                   strict=True) if a != b]
        raise ValueError("starts were made with other options: " + ", ".join(diff))
    if made[4] != observations_fingerprint(observations):
        raise ValueError("starts were made for other observations (their fingerprints differ)")


def _off_the_ridge(state: _State, free: np.ndarray, rational_sd: np.ndarray,
                   names: list[str]) -> tuple[str, ...]:
    """Start every radial term (k1-k6) of a step at zero where its start (OpenCV's rational
    fit) has a term of k4-k6 beyond 3 of its prior sigmas: OpenCV walks up the ridge the
    prior bounds, and from there the adjustment would have to walk back down its curve (module
    docstring). The steps so started, by name."""
    rational = [PARAMS.index(q) for q in RATIONAL_TERMS]
    far = np.any(free[:, rational] & (np.abs(state.cams[:, rational]) > 3 * rational_sd),
                 axis=1)
    radial = [PARAMS.index(q) for q in ("k1", "k2", "k3", *RATIONAL_TERMS)]
    state.cams[np.ix_(far, radial)] = 0.0
    return tuple(n for n, f in zip(names, far, strict=True) if f)


#: Prior sd of what each of the rational model's denominator terms ``k4 r^2, k5 r^4, k6 r^6``
#: adds at the image's corner (``r`` the corner's distance from the principal point over fx).
RATIONAL_PRIOR_AT_CORNER = 10.0


def _rational_sd(fx: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(S, 3) prior sd of k4, k5, k6 at focal lengths ``fx`` (S,) px: the terms' effect at the
    corner, ``k_n r_c^(2n)`` with ``r_c = half-diagonal / fx``, has sd
    :data:`RATIONAL_PRIOR_AT_CORNER` (module docstring)."""
    corner = 0.5 * np.hypot(*image_size) / np.asarray(fx, float)
    powers = np.array([CORNER_POWER[q] for q in RATIONAL_TERMS])
    return RATIONAL_PRIOR_AT_CORNER / corner[:, None] ** powers


def _test_the_print(setup: _Setup, state: _State, free: np.ndarray, max_rounds: int,
                    held_terms: tuple[str, ...] = ()
                    ) -> tuple[PrintTest | None, tuple[Solve, int] | None, _State]:
    """Whether the print's shape pays (:class:`PrintTest`): the test (None when not asked),
    the solve the adjustment goes on from when the print is kept (else None) and the state to
    start from. Where it is not kept, ``setup.keep_print`` is turned off and the print's modes
    dropped from the state.

    The test's solve frees k1, k2, p1, p2 and k3 at every step (but those ``held_terms``
    holds), whatever terms the step's own views chose: a term each step's views leave out as
    too small to pay alone can still be seen by the whole sweep, and the print's modes, the
    only in-plane unknowns all steps share, would take it up (``benchmarks/
    bench_print_test.py``). Where the print is kept, the adjustment's first solve with the
    chosen terms (on copies of the steps) is the one it goes on from."""
    if not setup.keep_print:
        return None, None, state
    every_term = free.copy()
    every_term[:, [PARAMS.index(q) for q in DISTORTION_SETS["k1k2p1p2k3"]
                   if q not in held_terms]] = True
    given_steps = setup.steps
    candidates = [every_term] if np.array_equal(every_term, free) else [every_term, free]
    why_not = None  # why five terms at every step could not judge it
    for terms in candidates:
        setup.steps = copy.deepcopy(given_steps)
        # rounds of noise re-estimation (a first round at the steps' own noise can stop at
        # the iteration cap where the next converges in a few iterations)
        solved = _solve_with_noise(setup.problem(terms), copy.deepcopy(state), terms,
                                   max_rounds)
        print_test = _print_test(setup.problem(terms), solved[0])
        first = solved if np.array_equal(terms, free) else None
        if why_not is not None:
            print_test = replace(print_test, terms="each step's chosen terms (its solve with "
                                 f"five at every step could not: {why_not})")
        if print_test.why is None:
            break
        why_not = print_test.why
    setup.keep_print = print_test.kept
    if not setup.keep_print:
        setup.steps = given_steps
        state.modes = state.modes[:setup.phi.shape[1] * len(setup.session_names)]
        return print_test, None, state
    if first is None:  # the adjustment's first solve, with the chosen terms
        setup.steps = copy.deepcopy(given_steps)
        first = _solve_with_noise(setup.problem(free), copy.deepcopy(state), free, max_rounds)
    if first[0].converged:  # the solve below goes on from this one (its noise and inliers)
        return print_test, first, first[0].state
    setup.steps = given_steps  # from the start
    return print_test, None, state


def _describe(result: ZoomWideResult, setup: _Setup, prob: _ZoomProblem, solve: Solve,
              unsmoothed: tuple, basins: list, forms: dict, models: dict,
              joint_cov: Callable | None, tau_source: str) -> None:
    """Fill ``result``'s board, print, unsmoothed rows, held-out paths and each step's
    ``info`` (session, basin check, where tau came from, zoom models, the prior's share)."""
    names = setup.names
    if prob.n_print:
        result.print_modes = prob.print_modes(result.board_modes)
        result.print_modes_sd = prob.print_modes(result.board_modes_sd)
        result.board_modes = result.board_modes[:-prob.n_print]
        result.board_modes_sd = result.board_modes_sd[:-prob.n_print]
    result.board_heights = None if solve.state.heights is None else solve.state.heights.copy()
    result.u = {n: float(v) for n, v in zip(names, setup.u, strict=True)}
    scaled = _with_scatter(result, names, *unsmoothed, _basin_gaps(prob.cam_col, basins))
    held_paths = _held_out_paths(*scaled, setup.chain_idx, setup.u, forms, models, names)
    if joint_cov is not None:
        result.unsmoothed = _unsmoothed_rows(*scaled, names)
        result.unsmoothed_pp_correlation = _principal_point_correlation(scaled[1], names)
    for name, doc in result.zoom_models.items():
        doc.update(form=forms.get(name, _Form()).to_dict(), held_out=held_paths.get(name))
    for s, r in enumerate(result.results.values()):
        r.info["board_session"] = setup.labels[s]
        r.info["basin"] = basins[s].to_dict()
        r.info["tau_source"] = tau_source
        if names[s] in setup.restarted:
            r.info["rational_start"] = ("radial terms started at zero: OpenCV's rational fit "
                                        "lay far up the ridge of k1-k3 against k4-k6")
        r.info["zoom_model"] = {k: m.name for k, m in models.items()}
        if joint_cov is not None:
            r.info["prior_share"] = _prior_share(r, joint_cov, s)


#: Smallest probability of the model not chosen
#: (:meth:`~zoomcalib.calibrate.stepfits.TermChoice.other_model_weight`) for
#: which what it would change is added to a step's variance.
OTHER_MODEL_MIN_WEIGHT = 0.01


def _add_model_choice_spread(result: ZoomWideResult, observations: Mapping[str, Observations],
                             held: Mapping[str, TermChoice], decentring: bool = True,
                             held_terms: tuple[str, ...] = ()) -> None:
    """Where a step's choice between the rational model and five terms is uncertain, add what
    the other model would change to the variance of the step's fx, fy, cx, cy (in ``sd`` and
    the joint covariance's diagonal), as model averaging does (Buckland, Burnham & Augustin
    1997) about the chosen model's value:

        var(q) += w (q_other - q_chosen)^2,

    ``w`` the other model's probability of being the better one
    (:meth:`~zoomcalib.calibrate.stepfits.TermChoice.other_model_weight`, at least
    :data:`OTHER_MODEL_MIN_WEIGHT`). The
    change is that of per-step OpenCV calibrations of the step's views on the board's estimated
    shape with either model, started from the adjustment's values. Neither sigma covers it:
    both halves of a step can each choose a model firmly, differently, and be a few sigmas
    apart. ``info["model_choice"]`` records ``other``, ``weight`` and ``shift`` (None with the
    reason when the other model could not be fitted)."""
    column = {c: i for i, c in enumerate(result.columns)}
    for name, res in result.results.items():
        choice = held.get(name)
        weight = choice.other_model_weight() if choice is not None else 0.0
        if weight < OTHER_MODEL_MIN_WEIGHT:
            continue
        other = RATIONAL_TERMS if not choice.rational else DISTORTION_SETS[choice.five_terms]
        record: dict = {"other": "rational" if not choice.rational else choice.five_terms,
                        "weight": weight}
        sets = [_without(with_decentring(t, decentring), held_terms)
                for t in (choice.terms, other)]
        if sets[0] == sets[1]:
            continue
        try:
            shift = _model_shift(observations[name], res, sets)
        except RuntimeError as exc:
            res.info["model_choice"] = record | {"shift": None, "why": str(exc)}
            continue
        for q, moved in shift.items():
            res.sd[q] = float(np.sqrt(res.sd[q] ** 2 + weight * moved**2))
            if (name, q) in column:
                result.covariance[column[name, q], column[name, q]] += weight * moved**2
        res.info["model_choice"] = record | {"shift": shift}


def _model_shift(obs: Observations, res: CalibrationResult, term_sets: list[tuple[str, ...]]
                 ) -> dict[str, float]:
    """fx, fy, cx, cy of the second term set's OpenCV calibration minus the first's, both of
    ``obs`` on the board ``res.object_points``, started from ``res``. RuntimeError when one
    fails or gives no camera."""
    on_board = Observations(res.object_points, obs.views, obs.image_size, obs.names)
    fits = []
    for terms in term_sets:
        try:
            with pose_sigmas_unused():  # a pose's sigma is not used here
                fit = calibrate_opencv(on_board, flags=_distortion_flags(terms),
                                       camera_only=True, **_guess(res, terms))
        except (ValueError, cv2.error) as exc:
            raise RuntimeError(f"{'+'.join(terms)}: {' '.join(str(exc).split())}") from exc
        if (why := not_a_camera(fit, obs.image_size)) is not None:
            raise RuntimeError(f"{'+'.join(terms)}: {why}")
        fits.append(fit)
    return {q: float(getattr(fits[1], q) - getattr(fits[0], q)) for q in ("fx", "fy", "cx", "cy")}


def _check_options(pp_model: str, prior_strength: Mapping[str, float] | None) -> None:
    if pp_model not in ZOOM_MODELS:
        raise ValueError(f"pp_model must be one of {ZOOM_MODELS}, got {pp_model!r}")
    for name, tau in (prior_strength or {}).items():
        if name not in SMOOTHED or not tau > 0:
            raise ValueError(f"prior_strength: {name}={tau!r}; give a positive tau for one of "
                             f"{SMOOTHED}")


def _common_board(observations: Mapping[str, Observations]) -> np.ndarray:
    """The board points (N, 3) every step sees; ValueError when the steps see different boards
    or images of different sizes, or fewer than 2 steps are given."""
    names = list(observations)
    if len(names) < 2:
        raise ValueError(f"a zoom-wide calibration needs 2 or more steps, got {len(names)}")
    board = np.asarray(observations[names[0]].object_points, float)
    size = tuple(observations[names[0]].image_size)
    for n in names[1:]:
        if not np.array_equal(observations[n].object_points, board):
            raise ValueError(f"step {n}: another board than step {names[0]}'s")
        if tuple(observations[n].image_size) != size:
            raise ValueError(f"step {n}: image size {observations[n].image_size} differs from "
                             f"step {names[0]}'s {size} (one camera has one sensor)")
    return board


@dataclass
class _Unsmoothed:
    """The solve without the smoothness prior (:func:`_solve_unsmoothed`): the solve, the state
    it started from, the free mask, the joint covariance of its per-step values
    (:func:`_joint_covariance`; None when it did not converge or has none), its iterations and
    the basin checks (one :class:`~zoomcalib.calibrate.basins.BasinCheck` per step)."""

    solve: Solve
    start: _State
    free: np.ndarray
    joint_cov: Callable | None
    iterations: int
    basins: list[BasinCheck]


def _solve_unsmoothed(setup: _Setup, state: _State, free: np.ndarray,
                      observations: Mapping[str, Observations], opts: ZoomWideOptions,
                      held_terms: tuple[str, ...], workers: int,
                      solved: tuple[Solve, int] | None = None) -> _Unsmoothed:
    """The solve without the smoothness prior (``setup.problem(free)`` builds it; ``solved``:
    that solve and its iterations, already made from ``state``, as the print's test makes it).
    Where the terms are chosen (``opts.select``, the standard model) and the board has height
    modes, the distortion terms are then chosen again on the board's estimated shape
    (:func:`~zoomcalib.calibrate.stepfits._select_on_board`; ``setup.terms`` and ``setup.held``
    updated in place), and the
    solve is
    repeated when a step's terms changed, from the first solve's state. Then every step's
    principal point is checked for a basin of lower cost (:func:`_move_to_best_basins`), and
    the solve repeated when one moved."""
    problem, max_rounds, init = setup.problem, opts.max_rounds, setup.init
    reselect = bool(opts.select and opts.model == "standard" and setup.phi.shape[1])
    unsmoothed = problem(free)
    if solved is None:
        solve, iterations = _solve_with_noise(unsmoothed, state, free, max_rounds)
    else:
        solve, iterations = solved
    if reselect and _select_on_board(
            observations, init, [unsmoothed.points(solve.state, s)
                                 for s in range(len(init))], setup.terms, setup.held,
            opts.decentring, workers, held_terms):
        free = _free_mask(list(init), setup.terms)
        free[:, 1:4] = unsmoothed.free[:, 1:4]  # fy, cx, cy as they were (shared or held)
        state = solve.state
        state.cams[:, 4:][~free[:, 4:]] = 0.0
        unsmoothed = problem(free)
        solve, more = _solve_with_noise(unsmoothed, state, free, max_rounds)
        iterations += more
    if unsmoothed.free[:, 2].any():
        basins = _move_to_best_basins(unsmoothed, solve.state, observations, workers)
    else:
        basins = [BasinCheck(None, False, why="the principal point is held")] * len(init)
    if any(b.moved for b in basins):
        state = solve.state
        solve, more = _solve_with_noise(unsmoothed, state, free, max_rounds)
        iterations += more
    joint_cov = _joint_covariance(unsmoothed, solve.state) if solve.converged else None
    return _Unsmoothed(solve, state, free, joint_cov, iterations, basins)


def _move_to_best_basins(prob: _ZoomProblem, state: _State,
                         observations: Mapping[str, Observations], workers: int = 1
                         ) -> list[BasinCheck]:
    """Per step of ``prob``: :func:`~zoomcalib.calibrate.basins.best_basin` of its views on
    its board's estimated points, from its camera in ``state``; where another basin has the
    lower cost, the step's intrinsics and poses in ``state`` are set to that fit's (its
    aspect ratio is the state's), judged with the terms of :func:`_basin_terms`. The fits
    see the corners the adjustment keeps (its
    inliers): a corner it rejected would pull a narrow step's OpenCV fit far from the
    adjustment's own. Steps run in ``workers`` processes."""
    items, judged = [], [_basin_terms(prob, s) for s in range(len(prob.steps))]
    for s, step in enumerate(prob.steps):
        obs = observations[step.name]
        cam = state.cams[s]
        K = np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])
        rational = bool(np.any(cam[9:]))
        items.append((Observations(prob.points(state, s), _inlier_views(step), obs.image_size,
                                   obs.names),
                      K, cam[4:].copy() if rational else cam[4:9].copy(),
                      _distortion_flags(judged[s]), step.sigma))
    checks = _map_steps(best_basin, items, workers)
    for s, check in enumerate(checks):
        check.terms = judged[s]
        if not check.moved:
            continue
        fit, first, last = check.fit, prob.view_start[s], prob.view_start[s + 1]
        state.cams[s, [0, 2, 3]] = fit.fx, fit.cx, fit.cy
        state.cams[s, 1] = fit.fy
        state.cams[s, 4:4 + len(fit.dist)] = np.where(prob.free[s, 4:4 + len(fit.dist)],
                                                      fit.dist, 0.0)
        state.rvecs[first:last], state.tvecs[first:last] = fit.rvecs, fit.tvecs
    return checks


def _basin_terms(prob: _ZoomProblem, s: int) -> tuple[str, ...]:
    """The distortion terms step ``s``'s basin is judged with: its own, and, where it has a
    radial term (and not the rational model's), each of ``k1, k2, p1, p2, k3`` that
    :data:`MIN_MODEL_STEPS` or more steps of its chain estimate. The adjustment with the
    smoothness prior frees those at this step (:func:`_tie_terms`, the zoom models of
    :func:`_series`), so a basin that needs the chain's k2 to fit would otherwise lose to one
    that does not, and then be the start the adjustment cannot leave (the halves of a real
    narrow step's frames chose basins far apart that way, ``docs/notes/real-camera-print.md``,
    "The default since e8d9d7f"). The state keeps the step's own terms: a lent term's value is
    dropped when the step moves."""
    own = tuple(p for p, f in zip(PARAMS[4:], prob.free[s, 4:], strict=True) if f)
    if not {"k1", "k2", "k3"} & set(own) or set(RATIONAL_TERMS) & set(own):
        return own
    chain = next((c for c in prob.chains if s in c), np.array([s]))
    lent = {q for q in ("k1", "k2", "p1", "p2", "k3")
            if _tied(prob.free, PARAMS.index(q))[chain].sum() >= MIN_MODEL_STEPS}
    return tuple(q for q in PARAMS[4:] if q in own or q in lent)


def _inlier_views(step: _Step, fewest: int = 6) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each view's ``(ids, uv)`` of the step's inlier corners, in view order; a view with
    fewer than ``fewest`` inliers keeps all its corners (every view must stay placeable)."""
    views = []
    for v in range(step.n_views):
        mine = step.view == v
        keep = mine & step.inlier if np.sum(mine & step.inlier) >= fewest else mine
        views.append((step.point[keep], step.uv[keep]))
    return views


def _solve_with_noise(prob: _ZoomProblem, state: _State, free: np.ndarray, max_rounds: int
                      ) -> tuple[Solve, int]:
    """Levenberg-Marquardt, then the board's point heights (if any) and each step's noise and
    inliers re-estimated, until they settle (at most ``max_rounds`` rounds, then one last
    solve)."""
    iterations = 0
    for _ in range(max_rounds):
        solve = _levenberg_marquardt(prob, state)
        state, iterations = solve.state, iterations + solve.iterations
        moved = state.heights is not None and _update_heights(prob, state) > HEIGHT_TOL_MM
        if not _update_noise(prob, state, free) and not moved:
            return solve, iterations
    solve = _levenberg_marquardt(prob, state)
    return solve, iterations + solve.iterations


def _finish(prob, solve, state, init, terms, held, models: dict[str, PathPrior], iterations,
            inflation: list[tuple] = (), basins: list[BasinCheck] = ()) -> ZoomWideResult:
    tau = {k: float(m.tau) for k, m in models.items()}
    cov, scatter = _posterior_covariance(prob, state)
    # a step's sigmas are at least its views' scatter (scatter.SCALE_UNTESTED)
    scale = np.ones(len(cov))
    scale[:prob.n_cam] = scatter.applied()
    cov *= np.outer(scale, scale)
    for steps, j, extra in inflation:  # the uncertainty of tau (_zoom_models)
        col = prob.cam_col[steps, j]
        cov[np.ix_(col, col)] += extra
    gaps = _basin_gaps(prob.cam_col, basins)
    for s, gap in enumerate(gaps):  # two basins the views do not tell apart (basins.py)
        for q, half in gap.items():
            col = prob.cam_col[s, PARAMS.index(q)]
            cov[col, col] += half**2
    if np.any(np.diag(cov) <= 0):
        raise RuntimeError("zoom-wide covariance is not positive definite")
    n_cam, n_modes = prob.n_cam, prob.n_modes
    columns = [(prob.steps[s].name, PARAMS[j]) for s, j in zip(*np.nonzero(prob.free),
                                                               strict=True)]
    results = {}
    step_scatter = scatter.by_group()
    for s, step in enumerate(prob.steps):
        results[step.name] = _step_result(prob, s, state, cov, prob.points(state, s),
                                          init[step.name], terms, tau)
        results[step.name].info.update({
            "view_scatter": step_scatter[step.name].to_dict() | {"applied": True},
            "sd_noise_model": {p: float(np.sqrt(max(v * v - gaps[s].get(p, 0.0) ** 2, 0.0))
                                        / f) for (p, v), f in zip(
                results[step.name].sd.items(), _step_scale(prob, s, scale), strict=False)},
            "converged": solve.converged, "stop_reason": solve.stop_reason,
            "distortion_choice": held[step.name].to_dict() if step.name in held else {},
            "tau_at_lower_bound": {k: m.tau_at_bound for k, m in models.items()},
            "covariance_ridge": prob.covariance_ridge,
        })
    modes_sd = np.sqrt(np.diag(cov)[n_cam:n_cam + n_modes])
    aspect_sd = (float(np.sqrt(cov[prob.aspect_col, prob.aspect_col])) if prob.aspect_col >= 0
                 else 0.0 if prob.shared_aspect else float("nan"))
    return ZoomWideResult(results, cov[:n_cam, :n_cam], columns, state.modes.copy(), modes_sd,
                          tau, terms, held, solve.converged, solve.stop_reason, iterations,
                          zoom_models={k: m.to_dict() for k, m in models.items()},
                          aspect=float(state.aspect), aspect_sd=aspect_sd)


def _basin_gaps(cam_col: np.ndarray, basins: Sequence[BasinCheck]) -> list[dict[str, float]]:
    """Per step (``cam_col`` (S, 12) its columns, -1 where held), the half gap between two
    basins its views do not tell apart (:meth:`~zoomcalib.calibrate.basins.BasinCheck.
    half_gap`) of its free parameters, px; empty dicts without basin checks."""
    gaps = [{} for _ in range(len(cam_col))]
    for s, check in enumerate(basins):
        gaps[s] = {q: v for q, v in check.half_gap().items()
                   if q in PARAMS and cam_col[s, PARAMS.index(q)] >= 0}
    return gaps


def _step_result(prob: _ZoomProblem, s: int, state: _State, cov: np.ndarray, X: np.ndarray,
                 init: CalibrationResult, terms, tau) -> CalibrationResult:
    step = prob.steps[s]
    v0, v1 = prob.view_start[s], prob.view_start[s + 1]
    fx, fy, cx, cy, *dist = state.cams[s]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    cols = prob.cam_col[s]
    # OpenCV's five terms, or its eight where the step estimates the rational ones
    reported = PARAMS if np.any(cols[-len(RATIONAL_TERMS):] >= 0) else PARAMS[:9]
    dist = dist[:len(reported) - 4]
    sd = {p: float(np.sqrt(cov[cols[j], cols[j]])) if cols[j] >= 0 else 0.0
          for j, p in enumerate(reported)}
    shared = prob.shared_aspect and cols[0] >= 0
    if shared and prob.aspect_col < 0:  # fy = a fx, a held
        sd["fy"] = float(state.aspect * np.sqrt(cov[cols[0], cols[0]]))
    elif shared:  # fy = a fx: var = a^2 var fx + fx^2 var a + 2 a fx cov(fx, a)
        i, k, a = cols[0], prob.aspect_col, state.aspect
        sd["fy"] = float(np.sqrt(max(a * a * cov[i, i] + fx * fx * cov[k, k]
                                     + 2 * a * fx * cov[i, k], 0.0)))
    cam = state.cams[s]
    uv = project_jacobian(cam, state.rvecs[v0:v1], state.tvecs[v0:v1], X, step.view,
                          step.point, jacobian=False)
    e2 = np.sum((uv - step.uv) ** 2, axis=1)
    per_view = np.array([np.sqrt(e2[(step.view == v) & step.inlier].mean())
                         for v in range(step.n_views)])
    rejected = [(int(v), int(p)) for v, p in zip(step.view[~step.inlier],
                                                  step.point[~step.inlier], strict=True)]
    intr = cols[cols >= 0]
    sub = cov[np.ix_(intr, intr)]
    corr = sub / np.sqrt(np.outer(np.diag(sub), np.diag(sub)))
    info = {"mode": "zoom-wide", "distortion_terms": list(terms[step.name]),
            "fixed": [p for j, p in enumerate(reported) if cols[j] < 0
                      and not (shared and p == "fy")],
            "aspect_shared": bool(shared),
            "noise_sigma_px": step.sigma, "tau": {k: float(v) for k, v in tau.items()},
            "correlation": corr,
            "correlation_names": [PARAMS[j] for j in np.flatnonzero(cols >= 0)],
            "sd_kind": "posterior of the zoom-wide problem",
            "views": list(init.info.get("views", []))}
    return CalibrationResult("zoom-wide", K, np.asarray(dist, float), sd,
                             float(np.sqrt(e2[step.inlier].mean())), per_view,
                             state.rvecs[v0:v1].copy(), state.tvecs[v0:v1].copy(), rejected,
                             X.copy(), None, info)


#: The zoom-wide adjustment's board models, richest first (``board_shape`` of the calibrate
#: job, whose default is ``print``; docs/real-camera.md says why).
BOARD_SHAPES = ("print", "points", "modes")


def board_options(board_shape: str) -> dict[str, bool]:
    """The :func:`calibrate_zoom_wide` options of a board model named in :data:`BOARD_SHAPES`:
    ``print`` the height modes, a height for every point and the print's in-plane modes;
    ``points`` without the print's; ``modes`` the height modes alone."""
    if board_shape not in BOARD_SHAPES:
        raise ValueError(f"board shape {board_shape!r}: expected one of {', '.join(BOARD_SHAPES)}")
    return {"board_points": board_shape != "modes", "print_shape": board_shape == "print"}
