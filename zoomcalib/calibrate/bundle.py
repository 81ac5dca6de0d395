r"""Photogrammetric bundle adjustment that also refines the 3D target points.

In the manner of Lavest, Viala & Dhome (ECCV 1998): the calibration target is not trusted to be
the nominal flat board; every target point's 3D position is an unknown beside the intrinsics,
the distortion and the poses, so a board that is bowed, or printed slightly off scale along one
axis, does not bias the camera.

Model
-----
OpenCV's pinhole + distortion model (``zoomcalib.camera``), OpenCV pixel convention (centre of
the top-left pixel = (0, 0)). For view ``v`` with pose ``Rt_cam_board`` (``R_v = Rod(r_v)``,
``t_v``), target point ``X_j`` (target frame, the units of ``Observations.object_points``, mm by
the package's convention) is seen at

.. math::

    (X, Y, Z)^T = R_v X_j + t_v,\quad x = X/Z,\ y = Y/Z,\quad r^2 = x^2 + y^2,

    x_d = x\,\frac{1 + k_1 r^2 + k_2 r^4 + k_3 r^6}{1 + k_4 r^2 + k_5 r^4 + k_6 r^6}
          + 2 p_1 x y + p_2 (r^2 + 2 x^2),\quad (y_d \text{ likewise}),

    u = f_x x_d + c_x,\quad v = f_y y_d + c_y .

Unknowns: ``fx, fy, cx, cy``, ``k1, k2, p1, p2, k3`` (``model='standard'``; ``'rational'`` adds
``k4, k5, k6``), 6 per view (Rodrigues ``rvec``, ``tvec``) and ``3 n`` target coordinates, less
the 7 gauge constraints below: ``9 + 6 m + 3 n - 7`` for the standard model.

Gauge
-----
Pixel observations are unchanged if the target frame is moved by a similarity (rotation,
translation, scale) and the poses compensate, so 7 constraints are needed. By default
(``gauge_points=None``) three points of the nominal target seen in at least 2 views are chosen:
``i0`` = the first (point 0 of a fully seen grid), ``ia`` = the one farthest from it (the
opposite corner), ``ib`` = the one farthest from the line ``i0``–``ia``. Fixed at their nominal
values are: all three coordinates of ``i0`` (translation), all three of ``ia`` (two rotations,
and the scale: the distance ``|X_ia - X_i0|`` stays at its nominal value, the known size of the
target) and the coordinate of ``ib`` along the normal of the plane through the three points
(``z`` for a flat ``z = 0`` board: the rotation about the line ``i0``–``ia``). The choice is
described in ``info['gauge']``. Another choice of gauge points gives the same camera and the
same target up to a similarity (tested: to the LM tolerance), since both the reprojection error
and the shape prior below are invariant to a similarity.

Shape prior (the guard)
-----------------------
Free target points can soak up lens-model misfit: on mrcal's figueroa set (186 views of a
0.77 m board through a wide lens that OpenCV's 8-term model does not fit exactly), this
bundle with every coordinate free moves the camera away from mrcal's warped-board solution by
far more than its 1-sigma. Real boards bow and twist by millimetres, but their points are
placed far more accurately than that; so the adjustment minimises

.. math::

    F = \sum_i \| w_i (\hat u_i - u_i) \|^2 + \sigma_{px}^2\, d^T \Lambda\, d,
    \qquad d = \mathrm{vec}\big(R^T (X - s R X_0 - t) / s\big),

    \Lambda = \frac{I - Q Q^T - B B^T}{\sigma_t^2} + \frac{B (T T^T)^{-1} B^T}{\sigma_w^2},

where ``d`` is the deviation of the target points ``X`` from the nominal board ``X_0`` aligned
on them by the least-squares similarity ``(s, R, t)`` (Umeyama), expressed in the nominal frame;
``Q`` spans the 7 infinitesimal similarity motions of ``X_0`` and ``B = B_0 T^{-1}`` the 3
smooth warp modes ``B_0`` (displacement along the board normal by ``u^2``, ``u v``, ``v^2``,
``(u, v)`` in-plane coordinates scaled to 1 at the farthest point: bow, cylinders, twist; see
:func:`warp_basis`). ``sigma_w = warp_sigma_mm`` (default 2) is the prior 1-sigma of each warp
amplitude, ``sigma_t = target_sigma_mm`` (default 0.01) that of every other deformation of each
coordinate (printing, drilling, placement), and ``sigma_px`` the pixel noise (MAD estimate from
the residuals, updated after the target is released). The prior is exactly invariant to a
similarity of ``X``, so it does not depend on the gauge; ``Lambda`` is rotated with ``R`` in the
normal equations. ``target_sigma_mm=None`` removes it (the plain Lavest bundle).

On figueroa (all 186 views, mrcal's weights, no rejection) the guard brings the camera back
to mrcal's warped-board solution (checked in ``tests/test_bundle.py``). The fits with and
without it are printed by ``python benchmarks/bench_bundle.py --accuracy``; results in
``docs/calibration.md`` ("mrcal's figueroa observations").

A diagnostic guard: ``info['guard']`` splits the refined target's deviation into warp
amplitudes and an irregular rest, and holds the flat-target fit for comparison; a
``RuntimeWarning`` is raised when the irregular rest is more than ``guard_warn_ratio`` times what
the noise explains (the free points are then fitting something systematic). The ratio on
figueroa with and without the prior and on synthetic boards with a smooth bow is printed by the
same benchmark.

Solver
------
Levenberg–Marquardt (the engine of :mod:`zoomcalib.calibrate.solver`, shared with the zoom-wide
adjustment: Marquardt's scaling, the stop rule on the Gauss-Newton step's predicted decrease
[4]) on the normal equations with an analytic
Jacobian (:func:`project_jacobian`; checked against finite differences in the tests). The 6 pose
unknowns of each view are eliminated by the Schur complement, so each iteration factors a dense
system of ``n_cam + 3 n - 7`` unknowns only:

.. math::

    \begin{pmatrix} U & W \\ W^T & V \end{pmatrix}
    \begin{pmatrix} \delta_y \\ \delta_p \end{pmatrix} = -\begin{pmatrix} g_y \\ g_p \end{pmatrix},
    \quad (U - W V^{-1} W^T)\,\delta_y = -g_y + W V^{-1} g_p,
    \quad \delta_p = -V^{-1}(g_p + W^T \delta_y),

``V`` being block diagonal (6 x 6 per view). The per-view and per-point sums of Jacobian
products are batched matrix products on the (view, point) grid when at least a third of it is
observed (else per-observation products summed by view and by point). Rotation columns are
taken with respect to a small rotation of the camera frame, ``-B [R X_j]_x``, and mapped to the
Rodrigues vector by the view's left Jacobian of SO(3) (:func:`left_jacobian`), which equals
Gallego & Yezzi's derivative [3] (:func:`rodrigues`).

Stages: (1) initial camera and poses from ``cv2.calibrateCamera`` (standard model: the
rational model started from scratch falls into poor local minima on wide lenses, as on mrcal's
figueroa set, ``python benchmarks/bench_bundle.py --accuracy``); (2) LM with
the target held at its nominal shape (for ``'rational'``: up to 10 iterations of the 5-term model
first, then all 8 terms); (3) LM with the target released; (4) if ``robust``, observations whose
residual norm exceeds ``reject_sigma`` robust sigmas are rejected and (3) is re-solved, while the
set changes (at most 3 rounds: with lens-model misfit the tails keep growing as they are
cut, and rejection would otherwise eat the field edges); (5) covariance.

Covariance
----------
Two kinds are computed, from ``N = J^T J + \sigma_p^2 \Lambda_R`` at the solution (free
parameters only; ``Lambda_R`` the rotated prior precision, ``sigma_p`` the pixel sigma that
weighted the prior in the final solve, ``info['prior_sigma_px']``, so that ``N`` is the normal
matrix of the cost actually minimised) and ``s^2 = \sum_i \|w_i r_i\|^2 / (2 N_{obs} -
n_{unknowns} + tr((N^{-1} P)^2))`` (``info['sigma_px']`` is ``s``). The residuals are
``r = (I - H) e`` with the hat matrix ``H = J N^{-1} J^T``, so ``E|r|^2 = sigma^2 (2 N_{obs} -
2 tr H + tr H^2)``, and ``N^{-1} J^T J = I - N^{-1} P`` makes that the denominator: a prior
that holds the points gives back the degrees of freedom their coordinates would take (with
10 views of 88 points at 0.2 px and the default prior, ``2 N_{obs} - n_{unknowns}``
overestimated ``s^2`` by 16 %; ``benchmarks/bench_scatter_null.py``):

- the **repeatability** ``s^2 N^{-1} J^T J N^{-1}`` (sandwich; its marginal over camera and
  points ``s^2 S^{-1} (S - P) S^{-1}`` with ``S`` the Schur complement over the poses and
  ``P`` the prior's block): the spread of the estimates over noise draws for this board;
- the **posterior** ``s^2 N^{-1}``, which also counts the prior's allowance for an irregular
  board, and is larger.

Without the prior the two are equal. Every 1-sigma the result reports by default is the
repeatability (``info['sd_kind'] = 'repeatability'``): ``sd`` (intrinsics and distortion),
``object_points_sd`` (0 for the gauge-fixed coordinates), ``info['rvecs_sd']``,
``info['tvecs_sd']``, ``flatness_sd_mm`` and the guard's noise level. The posterior's are in
``info['sd_posterior']``, ``info['rvecs_sd_posterior']``, ``info['tvecs_sd_posterior']``; the
whole matrices on request (``return_covariance=True``) as ``info['covariance_repeatability']``
and ``info['covariance_posterior']``. A variance that comes out negative (beyond rounding:
:data:`VARIANCE_ROUNDING` of the posterior variance) raises a ``ValueError`` naming the
parameter; none is clipped.

Convergence
-----------
Each LM stage records how it stopped in ``info['stages']`` (``iterations``, ``converged``,
``stop_reason``: ``'tolerance'``, ``'iteration cap'`` or ``'damping limit'``, ``role``,
``cost_px2``). ``info['converged']`` (and ``CalibrationResult.converged``) is True only when
every stage but the two capped by design (``role='start'``: the initial ``cv2.calibrateCamera``
and the rational model's 5-term warm start) converged; ``info['stop_reason']`` is the first
failing stage's reason, else ``'tolerance'``. A result that did not converge also raises a
``RuntimeWarning`` naming the stages.

With ``threadpoolctl`` installed the BLAS runs single-threaded inside :func:`calibrate_bundle`
(``_single_threaded_blas``): the result does not depend on it, the wall time does.

Result
------
``CalibrationResult.info`` of :func:`calibrate_bundle`:

- ``converged`` (bool; also ``CalibrationResult.converged``), ``stop_reason``,
  ``stages`` (per LM stage: ``iterations``, ``converged``, ``stop_reason``, ``role``,
  ``cost_px2``), ``iterations`` (LM iterations per stage);
- ``gauge`` (text), ``gauge_points``, ``n_unknowns`` (free parameters after the
  gauge), ``n_observations`` (inliers), ``residual_dof`` (the denominator of ``s^2``,
  module docstring), ``sigma_px`` (``s``, weighted px),
  ``prior_sigma_px`` (the prior's pixel sigma in the final solve; None without a
  prior), ``model``, ``max_tilt_deg``;
- ``sd_kind`` (``'repeatability'``), ``sd_posterior`` (by name),
  ``rvecs_sd_posterior``, ``tvecs_sd_posterior`` (m, 3);
- ``flatness_mm``, ``flatness_sd_mm``: RMS distance of the refined points from their
  best-fit plane, and its linearised 1-sigma;
- ``guard``: the flat-target fit (``flat_fx`` ...), the shifts from it
  (``shift_fx_px``, ``shift_fx_sigma`` ...), ``warp_amplitude_mm`` (the 3 warp
  modes' amplitudes), ``irregular_rms_mm`` and ``irregular_noise_rms_mm``;
- ``rvecs_sd``, ``tvecs_sd`` (m, 3); ``points_held`` (points seen in fewer than 2
  views, kept at their nominal position); ``target_sigma_mm``, ``warp_sigma_mm``.

References
----------
.. [1] J.-M. Lavest, M. Viala, M. Dhome, "Do we really need an accurate calibration pattern to
   achieve a reliable camera calibration?", ECCV 1998, LNCS 1406, pp. 158-174.
.. [2] B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment — a modern
   synthesis", Vision Algorithms: Theory and Practice, LNCS 1883, 2000 (Schur complement, gauge).
.. [3] G. Gallego, A. Yezzi, "A compact formula for the derivative of a 3-D rotation in
   exponential coordinates", J. Math. Imaging Vis. 51, 2015.
.. [4] K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares problems",
   IMM, DTU, 2004 (Levenberg–Marquardt damping).
.. [5] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import contextlib
import functools
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import cv2
import numpy as np
import scipy.linalg
import scipy.sparse

from zoomcalib.calibrate.bundleproblem import (
    CAMERA_NAMES,
    _Data,
    _inverse_from_cholesky,
    _PointCovariance,
    _Problem,
    _shape_modes,
    _ShapePrior,
    _State,
    shape_precision,
)
from zoomcalib.calibrate.geometry import (
    fit_similarity,
    project_jacobian,
    rodrigues,
)
from zoomcalib.calibrate.result import (
    CalibrationResult,
    Observations,
    one_opencv_thread,
)
from zoomcalib.calibrate.scatter import (
    ViewScatter,
    view_groups,
    view_scatter,
)
from zoomcalib.calibrate.solver import (
    STOP_ITERATION_CAP,
    Solve,
    levenberg_marquardt,
)

__all__ = ["BundleOptions", "calibrate_bundle", "shape_precision", "CAMERA_NAMES"]


_BLAS = []   # a threadpoolctl controller, made on first use if threadpoolctl is installed


def _single_threaded_blas(fn):
    """Run ``fn`` with a single-threaded BLAS when threadpoolctl is installed.

    The dense systems here have a few hundred unknowns, too small for a multi-threaded BLAS
    to gain more than it spends synchronising threads on a busy machine (compare
    ``python benchmarks/bench_bundle.py --blas-threads 0`` with the default of one thread).
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if not _BLAS:
            try:
                from threadpoolctl import ThreadpoolController
                _BLAS.append(ThreadpoolController())
            except ImportError:
                _BLAS.append(None)
        ctx = (contextlib.nullcontext() if _BLAS[0] is None
               else _BLAS[0].limit(limits=1, user_api="blas"))
        with ctx:
            return fn(*args, **kwargs)
    return wrapper














# --------------------------------------------------------------------------------------------
# The problem: indices, residuals, normal equations, LM
# --------------------------------------------------------------------------------------------













def _solve(prob: _Problem, s: _State, max_iterations: int, tol: float, lam: float = 1e-10
           ) -> tuple[_State, Solve, tuple | None]:
    """:func:`~zoomcalib.calibrate.solver.levenberg_marquardt` on ``prob`` from ``s``: the
    state, the :class:`~zoomcalib.calibrate.solver.Solve` and, when converged, the normal
    equations at the state (:meth:`_Problem.normal_equations`' tuple), else None."""
    solve = levenberg_marquardt(prob, s, max_iterations, tol, lam)
    return solve.state, solve, (prob.last_normal if solve.converged else None)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------

def _gauge(X0: np.ndarray, gauge_points, seen: np.ndarray
           ) -> tuple[np.ndarray, str, tuple[int, int, int]]:
    """Fixed-coordinate mask (n, 3) and its description; automatic gauge points are chosen
    among the points ``seen`` (in at least 2 views)."""
    n = len(X0)
    if gauge_points is None:
        for cand in (np.flatnonzero(seen), np.arange(n)):   # all points if the seen are too few
            if len(cand) < 3:
                continue
            i0 = int(cand[0])
            ia = int(cand[np.argmax(np.linalg.norm(X0[cand] - X0[i0], axis=1))])
            e = (X0[ia] - X0[i0]) / max(np.linalg.norm(X0[ia] - X0[i0]), 1e-300)
            d = X0[cand] - X0[i0]
            off = np.linalg.norm(d - np.outer(d @ e, e), axis=1)
            ib = int(cand[np.argmax(off)])
            if off.max() > 1e-6 * np.linalg.norm(X0[ia] - X0[i0]):
                break
    else:
        i0, ia, ib = (int(i) for i in gauge_points)
    if len({i0, ia, ib}) < 3 or min(i0, ia, ib) < 0 or max(i0, ia, ib) >= n:
        raise ValueError(f"gauge_points {gauge_points!r}: need three distinct point ids < {n}")
    normal = np.cross(X0[ia] - X0[i0], X0[ib] - X0[i0])
    if np.linalg.norm(normal) < 1e-9 * np.linalg.norm(X0[ia] - X0[i0]) ** 2:
        raise ValueError(f"gauge points {i0}, {ia}, {ib} are collinear")
    kb = int(np.argmax(np.abs(normal)))
    fixed = np.zeros((n, 3), bool)
    fixed[i0] = True
    fixed[ia] = True
    fixed[ib, kb] = True
    length = float(np.linalg.norm(X0[ia] - X0[i0]))
    text = (f"point {i0} fixed (x, y, z); point {ia} fixed (x, y, z), so the scale is the nominal "
            f"distance |X{ia} - X{i0}| = {length:.6g}; point {ib} {'xyz'[kb]} fixed; all at "
            f"their nominal values")
    return fixed, text, (i0, ia, ib)


def _cam_map(model: str, fix_aspect: bool, aspect: float) -> tuple[np.ndarray, list[str]]:
    """(12, nc) linear map from the free camera parameters to ``CAMERA_NAMES`` and their names."""
    nd = 5 if model == "standard" else 8
    cols, names = [], []
    if fix_aspect:
        c = np.zeros(12)
        c[0], c[1] = aspect, 1.0
        cols.append(c)
        names.append("f")
    else:
        cols += [np.eye(12)[0], np.eye(12)[1]]
        names += ["fx", "fy"]
    for k in range(2, 4 + nd):
        cols.append(np.eye(12)[k])
        names.append(CAMERA_NAMES[k])
    return np.array(cols).T, names


#: iterations of the initial cv2.calibrateCamera; our flat-target LM finishes the job
INIT_ITERATIONS = 6
#: iterations of the 5-term model before the rational model's k4..k6 are freed
WARM_START_ITERATIONS = 10
#: starting damping of the flat-target LM after that start
FLAT_LAMBDA = 1e-3


def _initial_camera(image_size, X0: np.ndarray, ids_list, pts_list, fix_aspect: bool):
    """Camera (12,) and poses from ``cv2.calibrateCamera``, standard model, nominal target."""
    objp = [X0[i].astype(np.float32) for i in ids_list]
    imgp = [p.astype(np.float32).reshape(-1, 1, 2) for p in pts_list]
    if np.any(np.abs(X0[:, 2]) > 0):
        raise ValueError("automatic initialisation needs a flat nominal target (z = 0): pass K0, "
                         "dist0 (and optionally rvecs0, tvecs0)")
    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0
    K = None
    if fix_aspect:
        w, h = image_size
        K = np.array([[max(w, h), 0, (w - 1) / 2], [0, max(w, h), (h - 1) / 2], [0, 0, 1.0]])
    try:
        with one_opencv_thread():
            _, K, d, rv, tv = cv2.calibrateCamera(
                objp, imgp, tuple(int(v) for v in image_size), K, None, flags=flags,
                criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, INIT_ITERATIONS,
                          2.2e-16))
    except cv2.error as exc:
        raise ValueError(f"the initial cv2.calibrateCamera failed ({exc.err}); the views may be "
                         "degenerate (e.g. all fronto-parallel)") from exc
    cam = np.zeros(12)
    cam[:4] = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cam[4:9] = np.ravel(d)[:5]
    return cam, np.array(rv).reshape(-1, 3), np.array(tv).reshape(-1, 3)


def _outliers(z: np.ndarray, inlier: np.ndarray, pi: np.ndarray, n: int, k: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Observations to reject and to re-admit, from normalised residual norms ``z``.

    A free target point pulled by a gross outlier drags its other observations too, so per
    round and per point only the observations above ``max(k, z_max / 2)`` are rejected
    (``z_max`` the point's largest inlier ``z``); rejected observations whose ``z`` fell below
    ``k`` after the re-solve are re-admitted.
    """
    cand = inlier & (z > k)
    zmax = np.zeros(n)
    np.maximum.at(zmax, pi[cand], z[cand])
    new_out = cand & (z >= 0.5 * zmax[pi])
    return new_out, ~inlier & (z <= k)


def _robust_sigma(r: np.ndarray) -> float:
    """1.4826 x median absolute residual component: sigma of Gaussian residuals.

    The median is of ``|r|`` about zero, the fit's own centre, not about the residuals' median
    (``scipy.stats.median_abs_deviation``): an outlier-heavy side must not move the centre."""
    return float(1.4826 * np.median(np.abs(r)))


#: A repeatability variance is a posterior variance less a positive semi-definite term, so it
#: can fall below zero by rounding only: by at most this fraction of that posterior variance.
VARIANCE_ROUNDING = 1e-9


def _checked_variances(var: np.ndarray, ref: np.ndarray, names, what: str) -> np.ndarray:
    """``var`` with its rounding-level negatives set to 0; raises on a real negative variance.

    ``ref`` is the (non-negative) variance ``var`` was computed from (the posterior one for a
    repeatability variance, ``var`` itself for a posterior one); ``names[i]`` names entry ``i``.

    Raises
    ------
    ValueError
        Naming the first parameter whose variance is not finite or below
        ``-VARIANCE_ROUNDING * |ref|``: the covariance is not positive semi-definite.
    """
    var = np.asarray(var, dtype=float)
    bad = ~np.isfinite(var) | (var < -VARIANCE_ROUNDING * np.abs(ref))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"the {what} variance of {names[i]} is {var[i]:.3g} "
                         f"({int(bad.sum())} of {len(var)} parameters affected): the covariance "
                         "is not positive semi-definite, the normal equations are too badly "
                         "conditioned at the solution to give uncertainties")
    return np.where(var < 0.0, 0.0, var)


def _parameter_names(cam_names, free_idx: np.ndarray, m: int) -> list[str]:
    """Names of the unknowns in the order of the covariance: camera, free target coordinates,
    poses (``cam.fx``, ``X12.z``, ``view3.rx`` ...)."""
    fj, fk = np.divmod(free_idx, 3)
    return ([f"cam.{c}" for c in cam_names]
            + [f"X{j}.{'xyz'[k]}" for j, k in zip(fj, fk, strict=True)]
            + [f"view{v}.{p}" for v in range(m) for p in ("rx", "ry", "rz", "tx", "ty", "tz")])


@dataclass
class _Covariances:
    r"""Both kinds of covariance of the final solve's unknowns (module docstring).

    With ``N = J^T J + P`` the normal matrix of the cost the final solve minimised (``P`` the
    shape prior's block, at the prior weight that solve used) and ``s2`` the residual variance:
    ``'posterior'`` is ``s2 N^-1`` and ``'repeatability'`` the sandwich
    ``s2 N^-1 J^T J N^-1 = s2 (N^-1 - N^-1 P N^-1)``; without a prior they are equal. ``N^-1``
    is held through the Schur complement over the poses: ``Sinv = S^-1`` (camera and points),
    ``pose_response = V^-1 W^T`` (6m, ny), ``Vinv`` (m, 6, 6) and
    ``whitened_pose_response = R^-T pose_response^T`` (``S = R^T R``). The prior on the free
    points is ``ca I + prior_modes cD prior_modes^T`` (``ca = 0``, ``prior_modes = None``: none);
    ``dof`` the denominator of ``s2`` (module docstring).
    """

    s2: float
    nc: int
    Sinv: np.ndarray
    pose_response: np.ndarray
    Vinv: np.ndarray
    whitened_pose_response: np.ndarray
    names: list[str]
    ca: float = 0.0
    prior_modes: np.ndarray | None = None
    cD: np.ndarray | None = None
    dof: float = float("nan")

    @property
    def points(self) -> _PointCovariance:
        """Repeatability covariance of the free target coordinates, as an operator."""
        Sxx = self.Sinv[self.nc:, self.nc:]
        if self.prior_modes is None:
            return _PointCovariance(Sxx, self.s2)
        return _PointCovariance(Sxx, self.s2, self.ca, Sxx @ self.prior_modes, self.cD)

    def prior_dof(self) -> float:
        """``tr((N^-1 P)^2)``, the degrees of freedom the prior gives back to the residuals
        (module docstring): with ``Y`` the points' block of ``S^-1`` and ``P = ca I + U cD
        U^T``, ``ca^2 |Y|_F^2 + 2 ca tr(cD (Y U)^T (Y U)) + tr((cD U^T Y U)^2)``."""
        Y = self.Sinv[self.nc:, self.nc:]
        YU = Y @ self.prior_modes
        modes = self.cD @ (self.prior_modes.T @ YU)
        return float(self.ca**2 * np.sum(Y * Y) + 2.0 * self.ca * np.sum((YU @ self.cD) * YU)
                     + np.sum(modes * modes.T))

    def _prior_term(self, A: np.ndarray, B: np.ndarray | None = None) -> np.ndarray:
        """``A P B^T`` / s2 for rows ``A``, ``B`` of ``N^-1[:, x]`` (x: the free points)."""
        B = A if B is None else B
        AU, BU = A @ self.prior_modes, B @ self.prior_modes
        return self.ca * (A @ B.T) + AU @ self.cD @ BU.T

    def _prior_diag(self, A: np.ndarray) -> np.ndarray:
        """``diag(A P A^T)`` / s2."""
        AU = A @ self.prior_modes
        return self.ca * np.einsum("ij,ij->i", A, A) + np.einsum("ij,ij->i", AU @ self.cD, AU)

    def camera_sd(self, cam_map: np.ndarray, kind: str) -> np.ndarray:
        """(12,) 1-sigma of ``CAMERA_NAMES`` through ``cam_map`` (12, nc); ``kind``
        ``'repeatability'`` or ``'posterior'``."""
        nc = self.nc
        post = self.s2 * self.Sinv[:nc, :nc]
        post_var = np.einsum("ij,jk,ik->i", cam_map, post, cam_map)
        var = _checked_variances(post_var, post_var, CAMERA_NAMES, "posterior")
        if kind == "repeatability" and self.prior_modes is not None:
            rep = post - self.s2 * self._prior_term(self.Sinv[:nc, nc:])
            var = _checked_variances(np.einsum("ij,jk,ik->i", cam_map, rep, cam_map),
                                     post_var, CAMERA_NAMES, "repeatability")
        return np.sqrt(var)

    def pose_sd(self, kind: str) -> np.ndarray:
        """(m, 6) 1-sigma of ``rvec, tvec`` per view: ``Cov(p) / s2 = V^-1 + H S^-1 H^T``."""
        names = self.names[len(self.Sinv):]
        whitened = self.whitened_pose_response
        post = self.s2 * (np.einsum("vii->vi", self.Vinv).ravel()
                          + np.einsum("ij,ij->j", whitened, whitened))
        var = _checked_variances(post, post, names, "posterior")
        if kind == "repeatability" and self.prior_modes is not None:
            rep = post - self.s2 * self._prior_diag(self.pose_response @ self.Sinv[:, self.nc:])
            var = _checked_variances(rep, post, names, "repeatability")
        return np.sqrt(var).reshape(-1, 6)

    def point_variances(self) -> np.ndarray:
        """Repeatability variances of the free target coordinates."""
        nc = self.nc
        post = self.s2 * np.einsum("ii->i", self.Sinv[nc:, nc:])
        names = self.names[nc:len(self.Sinv)]
        _checked_variances(post, post, names, "posterior")
        return _checked_variances(self.points.diag(), post, names, "repeatability")

    def full(self, kind: str) -> np.ndarray:
        """The whole matrix over ``names`` (camera, free points, poses)."""
        HS = self.pose_response @ self.Sinv
        cov_pp = self.pose_response @ HS.T
        for v in range(len(self.Vinv)):
            cov_pp[6 * v:6 * v + 6, 6 * v:6 * v + 6] += self.Vinv[v]
        out = self.s2 * np.block([[self.Sinv, -HS.T], [-HS, cov_pp]])
        if kind == "repeatability" and self.prior_modes is not None:
            Nx = np.vstack([self.Sinv[:, self.nc:], -HS[:, self.nc:]])   # N^-1[:, x]
            out -= self.s2 * self._prior_term(Nx)
        return out


def _covariances(prob: _Problem, state: _State, normal_eqs, cam_names, m: int) -> _Covariances:
    """Covariances at the solution ``state`` of ``prob``, from the normal equations
    ``normal_eqs`` of its last linearisation (None: linearised afresh). The prior's weight is
    the problem's own (``prob.sig2``), so ``N`` is the normal matrix of the cost that was
    minimised."""
    U, W, V = (normal_eqs if normal_eqs is not None else prob.normal_equations(state))[:3]
    r = prob.residuals(state)
    dof = 2 * prob.N - prob.n_unknowns
    try:
        pose_chol_inv = np.linalg.inv(np.linalg.cholesky(V))      # V = L L^T, per view
        G = pose_chol_inv @ W.transpose(0, 2, 1)                  # (m, 6, ny) = L^-1 W^T
        pose_coupling = G.reshape(6 * m, -1)
        schur_chol = scipy.linalg.cho_factor(U - pose_coupling.T @ pose_coupling,
                                             check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise ValueError("the normal equations are singular at the solution (rms "
                         f"{np.sqrt(np.mean(r**2) * 2):.3g} px): the data do not determine "
                         "the unknowns, or the adjustment diverged from a poor start (pass "
                         "K0/dist0)") from exc
    pose_response = (pose_chol_inv.transpose(0, 2, 1) @ G).reshape(6 * m, -1)
    cov = _Covariances(
        s2=np.nan, nc=prob.nc, Sinv=_inverse_from_cholesky(schur_chol[0]),
        pose_response=pose_response, Vinv=pose_chol_inv.transpose(0, 2, 1) @ pose_chol_inv,
        whitened_pose_response=scipy.linalg.solve_triangular(
            schur_chol[0], pose_response.T, trans="T", check_finite=False),
        names=_parameter_names(cam_names, prob.free_idx, m))
    if prob.Lam is not None:
        # the prior block of N is c (a I + prior_modes D prior_modes^T), c = sig2 / sc^2
        # (normal_equations)
        _, sc, Rs = prob.shape_deviation(state.X)
        c = prob.sig2 / sc**2
        cov.ca, cov.prior_modes = c * prob.Lam.a, prob.Lam.rotated_columns(Rs, prob.free_idx)
        cov.cD = c * prob.Lam.D
        dof += cov.prior_dof()
    cov.dof = float(dof)
    cov.s2 = float(np.einsum("ij,ij->", r, r)) / dof if dof > 0 else np.nan
    return cov


def _convergence_summary(stages: dict[str, Solve], initialised: bool
                         ) -> tuple[dict, bool, str]:
    """Per-stage ``iterations``, ``converged``, ``stop_reason``, ``role``, ``cost_px2``; whether
    the result converged and why its solve stopped.

    Roles: ``'start'`` (starting values only, capped by design: the initial
    ``cv2.calibrateCamera`` and the rational model's 5-term warm start), ``'result'`` (the
    solves the camera comes from) and ``'guard'`` (the flat-target fit the guard compares
    with). The result converged when every stage but the ``'start'`` ones did; the reason given
    is that of the first stage that did not, else of the last stage.
    """
    out: dict = {}
    if initialised:
        out["initial"] = {"iterations": None, "converged": False, "role": "start",
                          "stop_reason": f"{STOP_ITERATION_CAP} (by design: cv2.calibrateCamera "
                                         f"capped at {INIT_ITERATIONS} iterations gives starting "
                                         "values only)", "cost_px2": None}
    for name, o in stages.items():
        role = {"flat_standard": "start", "flat_inliers": "guard"}.get(name, "result")
        out[name] = {"iterations": o.iterations, "converged": o.converged, "role": role,
                     "stop_reason": o.stop_reason, "cost_px2": o.cost}
    checked = [v for v in out.values() if v["role"] != "start"]
    failed = [v for v in checked if not v["converged"]]
    return out, not failed, (failed[0] if failed else checked[-1])["stop_reason"]


def _initial_values(image_size, X0: np.ndarray, ids_list, pts_list, model: str, K0, dist0,
                    rvecs0, tvecs0, fix_aspect: bool):
    """Starting camera (12,) and poses (m, 3), (m, 3): from ``cv2.calibrateCamera`` when ``K0``
    is None, else from ``K0``, ``dist0`` and the given poses (``cv2.solvePnP`` without them)."""
    m = len(ids_list)
    if K0 is None:
        cam, rv0, tv0 = _initial_camera(image_size, X0, ids_list, pts_list, fix_aspect)
    else:
        cam = np.zeros(12)
        K0 = np.asarray(K0, float)
        cam[:4] = K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]
        if dist0 is not None:
            d0 = np.ravel(dist0)
            cam[4:4 + len(d0)] = d0
        rv0 = tv0 = None
    if model == "standard":
        cam[9:] = 0.0
    if rvecs0 is not None and tvecs0 is not None:
        rv0 = np.asarray(rvecs0, float).reshape(m, 3).copy()
        tv0 = np.asarray(tvecs0, float).reshape(m, 3).copy()
    elif rv0 is None:
        rv0, tv0 = _initial_poses(cam, X0, ids_list, pts_list)
    return cam, rv0, tv0


def _board_tilts_deg(rvecs: np.ndarray, min_tilt_deg: float) -> np.ndarray:
    """(m,) angle between each board normal and the optical axis, deg; refuses the data when
    every view is within ``min_tilt_deg`` of fronto-parallel."""
    R0, _ = rodrigues(rvecs, False)
    tilts = np.degrees(np.arccos(np.clip(np.abs(R0[:, 2, 2]), 0.0, 1.0)))
    if tilts.max() < min_tilt_deg:
        raise ValueError(f"all {len(tilts)} views are within {min_tilt_deg:g} deg of "
                         f"fronto-parallel (largest board tilt {tilts.max():.2f} deg): the focal "
                         "length and the target distance are not separable; add views with the "
                         "board tilted by 15-45 deg")
    return tilts


def _warn_not_converged(stage_info: dict) -> None:
    """``RuntimeWarning`` naming the stages (other than the capped starts) that stopped short."""
    bad = [k for k, v in stage_info.items() if v["role"] != "start" and not v["converged"]]
    warnings.warn(f"the bundle adjustment did not converge: stage{'s' * (len(bad) > 1)} "
                  + ", ".join(f"{k} ({stage_info[k]['stop_reason']} after "
                              f"{stage_info[k]['iterations']} iterations)" for k in bad)
                  + "; the camera and its sd are not a minimum of the cost (raise "
                  "max_iterations, or pass a better K0/dist0)", RuntimeWarning, stacklevel=4)


def _warn_guard(g: dict, guard_warn_ratio: float, target_sigma_mm: float | None) -> None:
    """``RuntimeWarning`` when the refined target's irregular deformation exceeds
    ``guard_warn_ratio`` times what the noise explains."""
    if g["irregular_rms_mm"] > guard_warn_ratio * g["irregular_noise_rms_mm"]:
        prior = ("every target coordinate is free" if target_sigma_mm is None
                 else f"or the target departs from its nominal shape by more than "
                      f"target_sigma_mm, {target_sigma_mm:g} mm")
        warnings.warn(f"the refined target departs from a smoothly warped board by "
                      f"{g['irregular_rms_mm']:.3g} mm RMS, "
                      f"{g['irregular_rms_mm'] / g['irregular_noise_rms_mm']:.1f} x what "
                      "the noise explains: the free target points are likely absorbing "
                      f"lens-model misfit ({prior}); "
                      "try the rational model (calibrate --per-step --model rational), or "
                      "the OpenCV backend, which keeps the target fixed",
                      RuntimeWarning, stacklevel=4)


@dataclass
class _Stages:
    """What stages 2-4 give (:func:`_solve_stages`): the flat-target fit (on the final
    inliers), the solution, the final problem, the inlier mask (N,), the per-stage
    :class:`~zoomcalib.calibrate.solver.Solve` and the normal equations at the final solve's
    end when it converged (else None)."""

    flat_state: _State
    state: _State
    problem: _Problem
    inlier: np.ndarray
    stages: dict
    normal_eqs: tuple | None


def _solve_stages(data: _Data, state: _State, cam_map: np.ndarray, free_pts: np.ndarray,
                  Lam: _ShapePrior | None, opts: BundleOptions) -> _Stages:
    """Stages 2-4 of the module docstring from the starting ``state``."""
    model, fix_aspect, refine_target = opts.model, opts.fix_aspect, opts.refine_target
    robust, reject_sigma = opts.robust, opts.reject_sigma
    max_iterations, tol = opts.max_iterations, opts.tol
    vi, pi, uv, w, m, n, X0 = (data.vi, data.pi, data.uv, data.w, data.m, data.n, data.X0)
    no_pts = np.zeros((n, 3), bool)

    def problem(sig: float, free: np.ndarray, sel: np.ndarray | None = None) -> _Problem:
        s = slice(None) if sel is None else sel
        return _Problem(_Data(vi[s], pi[s], uv[s], w[s], m, n, X0), cam_map, free, Lam, sig**2)

    last: dict = {}
    stages: dict[str, Solve] = {}

    def lm(name: str, prob: _Problem, st: _State, lam: float = 1e-10) -> _State:
        st, stages[name], normal_eqs = _solve(prob, st, max_iterations, tol, lam)
        last["prob"], last["normal_eqs"] = prob, normal_eqs
        return st

    # ---- stage 2: target held at its nominal shape --------------------------------------
    if model == "rational" and not np.any(state.cam[9:]):
        # free k4..k6 only after some iterations of the 5-term model: from a poor start the
        # rational model has bad local minima (figueroa: benchmarks/bench_bundle.py --accuracy)
        std_map, _ = _cam_map("standard", fix_aspect, state.cam[0] / state.cam[1])
        std_prob = _Problem(data, std_map, no_pts, None, 0.0)
        state, stages["flat_standard"], _ = _solve(
            std_prob, state, min(max_iterations, WARM_START_ITERATIONS), tol, 1e-3)
    flat_prob = problem(0.0, no_pts)
    state = lm("flat", flat_prob, state, lam=FLAT_LAMBDA)
    flat_state = state.copy()
    sigma_px = _robust_sigma(flat_prob.residuals(state))
    # ---- stage 3: target released -------------------------------------------------------
    prob = flat_prob
    if refine_target:
        prob = problem(sigma_px, free_pts)
        state = lm("target", prob, state)
    # ---- stage 4: outliers; the prior's pixel sigma from the refined residuals ----------
    N = len(vi)
    inlier = np.ones(N, bool)
    for rounds in range(1, 4):
        r = (project_jacobian(state.cam, state.rvecs, state.tvecs, state.X, vi, pi,
                              jacobian=False) - uv) * w[:, None]
        sig = _robust_sigma(r)
        new_out = readmit = np.zeros(N, bool)
        if robust:
            new_out, readmit = _outliers(np.hypot(r[:, 0], r[:, 1]) / sig, inlier, pi, n,
                                         reject_sigma)
        reweight = Lam is not None and abs(sig / sigma_px - 1.0) > 0.2
        if not new_out.any() and not readmit.any() and not reweight:
            break
        inlier = (inlier & ~new_out) | readmit
        sigma_px = sig
        prob = problem(sigma_px, free_pts, np.flatnonzero(inlier))
        state = lm(f"reject{rounds}", prob, state)
    if refine_target and not inlier.all():
        # the flat-target fit (for the guard's comparison) on the same inliers
        flat_state, stages["flat_inliers"], _ = _solve(
            problem(0.0, no_pts, np.flatnonzero(inlier)), flat_state, max_iterations, tol)

    # a converged solve's last linearisation is at its solution
    normal_eqs = last.get("normal_eqs") if last.get("prob") is prob else None
    return _Stages(flat_state, state, prob, inlier, stages, normal_eqs)


@dataclass(frozen=True)
class BundleOptions:
    """The bundle adjustment's choices (:func:`calibrate_bundle`).

    Attributes
    ----------
    model : {'standard', 'rational'}
        OpenCV's 5-term (``k1, k2, p1, p2, k3``) or 8-term rational model (adds ``k4..k6``).
    refine_target : bool
        Release the target points (else only the camera and poses are adjusted).
    robust : bool
        After convergence, reject observations with ``|w_i r_i| > reject_sigma * sigma_rob``,
        ``sigma_rob = 1.4826 median |w r|`` over all residual components (the MAD estimate of
        the noise, insensitive to the outliers themselves), and re-solve; repeated (at most 3
        rounds) while the set changes. Per round and target point only the observations above
        half the point's largest normalised residual go (a gross outlier drags its free point
        and so its other observations); rejected ones back below the threshold return.
    fix_aspect : bool
        Keep ``fx / fy`` at its initial value (1 if initialised here).
    target_sigma_mm : float or None
        Tolerance of the target's irregular deformation: prior 1-sigma of each coordinate of
        each point about the nominal board once a similarity and the smooth warp are removed
        (module docstring), in the units of ``obs.object_points``. None: no prior at all
        (every target coordinate free but for the gauge, the plain Lavest bundle).
    warp_sigma_mm : float or None
        Prior 1-sigma of the amplitude of each smooth warp mode (bow, cylinder, twist). None:
        the warp modes get ``target_sigma_mm`` like every other deformation.
    gauge_points : (int, int, int), optional
        ``(i0, ia, ib)`` for the gauge (module docstring); chosen automatically if None.
    reject_sigma : float
        Outlier threshold in robust sigmas. A 2D Gaussian residual exceeds ``k`` sigma with
        probability ``exp(-k^2/2)``: ``3.7e-6`` for the default 5, so clean data lose nothing.
    min_tilt_deg : float
        Refuse the data when every view's board normal is within this angle of the optical axis.
    guard_warn_ratio : float
        Warn (``RuntimeWarning``) when the irregular part of the refined target's deformation
        has an RMS above this many times the RMS the noise alone gives (from the covariance).
    max_iterations : int
        Per LM stage. A stage that reaches it stops with ``stop_reason='iteration cap'`` and the
        result is marked as not converged (module docstring, Convergence).
    tol : float
        Stop when the Gauss-Newton step from the current state is predicted to lower the cost
        by less than ``tol`` times the cost (that step is not taken: the cost is within about
        that much of its minimum; :mod:`zoomcalib.calibrate.solver`); the change from
        1e-7 to 1e-8 on the benchmark sets is printed by ``python benchmarks/bench_bundle.py
        --accuracy`` (results in ``docs/notes/calibration-checks.md``).
    return_covariance : bool
        Also put the full covariances of all free parameters, both kinds, in
        ``info['covariance_repeatability']`` and ``info['covariance_posterior']`` (module
        docstring, Covariance), with their names in ``info['parameter_names']``. Covariances
        use the normal equations at the solution (the solver's last linearisation).
    scatter_check : bool
        Check the camera's sigmas against the scatter between views
        (:mod:`zoomcalib.calibrate.scatter`) and report the larger of the noise model's and
        the view-clustered sigma (``sd`` and ``info['sd_posterior']``; the noise model's in
        ``info['sd_noise_model']``, the check in ``info['view_scatter']``, which flags views
        that disagree beyond what the corner noise explains). False reports the noise model's
        sigmas, still checked.

    """

    model: str = "standard"
    refine_target: bool = True
    robust: bool = True
    fix_aspect: bool = False
    target_sigma_mm: float | None = 0.01
    warp_sigma_mm: float | None = 2.0
    gauge_points: tuple[int, int, int] | None = None
    reject_sigma: float = 5.0
    min_tilt_deg: float = 3.0
    guard_warn_ratio: float = 3.0
    max_iterations: int = 100
    tol: float = 1e-7
    return_covariance: bool = False
    scatter_check: bool = True


@_single_threaded_blas
def calibrate_bundle(obs: Observations, options: BundleOptions | None = None, *,
                     K0: np.ndarray | None = None, dist0: np.ndarray | None = None,
                     rvecs0: np.ndarray | None = None, tvecs0: np.ndarray | None = None,
                     weights: list[np.ndarray] | None = None, **fields) -> CalibrationResult:
    r"""Calibrate a camera by bundle adjustment, refining the 3D target points too.

    See the module docstring for the model, the gauge, the shape prior and the solver.

    Parameters
    ----------
    obs : Observations
        Nominal target (``object_points`` (n, 3), mm unless stated) and per-view ``(ids (k,),
        points (k, 2))`` detections, px, OpenCV convention. Each view needs at least 4 points
        and no point twice.
    options : BundleOptions, optional
        The adjustment's choices (default: :class:`BundleOptions`' defaults); ``fields``,
        keywords named as its fields, replace them (``model="rational", robust=False``).
    K0 : (3, 3) ndarray, optional
        Initial camera matrix. If None, the initial camera and poses come from
        ``cv2.calibrateCamera`` (:data:`INIT_ITERATIONS` iterations, standard model, the
        nominal flat target; module docstring, Stages).
    dist0 : (5,) or (8,) ndarray, optional
        Initial distortion (zeros if None and ``K0`` is given).
    rvecs0, tvecs0 : (m, 3) ndarray, optional
        Initial ``Rt_cam_board`` poses; from ``cv2.solvePnP`` if None and ``K0`` is given.
    weights : list of (k,) ndarray, optional
        Per-observation weights (noise ``sigma / w``, mrcal's convention); weights <= 0 are
        dropped as outliers.

    Returns
    -------
    CalibrationResult
        ``backend='bundle'``; ``K``, ``dist`` ((5,) or (8,)), ``sd`` (``fx, fy, cx, cy`` and the
        distortion terms; repeatability 1-sigma, as every sd here), ``rms_px`` and
        ``per_view_rms_px`` over inliers (unweighted px), ``rvecs``, ``tvecs``
        (``Rt_cam_board``, target in the gauge frame), ``rejected`` (view, id),
        ``object_points`` (refined, gauge frame; None if ``refine_target`` is False) and
        ``object_points_sd`` (0 for gauge-fixed coordinates). ``info``: module docstring,
        Result.

    Raises
    ------
    ValueError
        Fewer than 3 views; a view with fewer than 4 points, a repeated or out-of-range id;
        every view fronto-parallel; fewer equations (2 per observation) than unknowns; an
        unknown model; normal equations singular at the solution; a negative variance
        (naming the parameter).

    Examples
    --------
    >>> from zoomcalib.calibrate.bundle import calibrate_bundle  # doctest: +SKIP
    >>> res = calibrate_bundle(obs, model="rational")             # doctest: +SKIP
    >>> res.fx, res.sd["fx"], res.info["flatness_mm"], res.rejected   # doctest: +SKIP
    """
    opts = replace(options or BundleOptions(), **fields)
    if opts.model not in ("standard", "rational"):
        raise ValueError(f"model must be 'standard' or 'rational', not {opts.model!r}")
    X0 = np.asarray(obs.object_points, dtype=float).reshape(-1, 3)
    n, m = len(X0), obs.n_views
    if m < 3:
        raise ValueError(f"bundle adjustment needs at least 3 views, got {m}: with fewer the "
                         "intrinsics, poses and target points are not determined")
    vi, pi, uv, w, ids_list, pts_list = _flatten(obs, weights)
    unknowns = _unknowns(X0, pi, opts, 1.0 if K0 is None else float(K0[0][0] / K0[1][1]))
    _refuse_underdetermined(len(vi), unknowns.cam_map.shape[1], m,
                            int(unknowns.free_pts.sum()))
    # stage 1: initial values and the fronto-parallel refusal
    cam, rv0, tv0 = _initial_values(obs.image_size, X0, ids_list, pts_list, opts.model, K0,
                                    dist0, rvecs0, tvecs0, opts.fix_aspect)
    if K0 is None and opts.fix_aspect:
        unknowns.cam_map, unknowns.cam_names = _cam_map(opts.model, opts.fix_aspect,
                                                        cam[0] / cam[1])
    tilts = _board_tilts_deg(rv0, opts.min_tilt_deg)
    # stages 2-4: the flat fit, the free target, outlier rounds
    modes = _shape_modes(X0) if opts.refine_target else None
    shape_prior = (_ShapePrior.from_modes(modes, opts.target_sigma_mm, opts.warp_sigma_mm)
                   if opts.refine_target and opts.target_sigma_mm is not None else None)
    solved = _solve_stages(
        _Data(vi, pi, uv, w, m, n, X0), _State(cam, rv0, tv0, X0.copy()), unknowns.cam_map,
        unknowns.free_pts, shape_prior, opts)
    flat_state, state, prob = solved.flat_state, solved.state, solved.problem
    inlier, stages, normal = solved.inlier, solved.stages, solved.normal_eqs
    # stage 5: covariance, the view-scatter check and the result
    normal = prob.normal_equations(state) if normal is None else normal
    cov = _covariances(prob, state, normal, unknowns.cam_names, m)
    sigmas = _camera_sigmas(prob, state, normal, cov, unknowns.cam_map, opts.model, obs,
                            opts.scatter_check)
    stage_info, converged, stop_reason = _convergence_summary(stages, K0 is None)
    if not converged:
        _warn_not_converged(stage_info)
    info: dict = {"gauge": unknowns.gauge_text, "gauge_points": list(unknowns.gauge_pts),
                  "converged": converged, "stop_reason": stop_reason, "stages": stage_info,
                  "iterations": {k: v.iterations for k, v in stages.items()},
                  "max_tilt_deg": float(tilts.max()),
                  "points_held": [int(i) for i in unknowns.held]}
    obj = None
    if opts.refine_target:
        obj = _refined_target(prob, state, cov, modes, X0, flat_state.cam,
                              sigmas.noise_model, opts.guard_warn_ratio, info)
    return _bundle_result(prob, state, cov, sigmas, inlier, (vi, pi, uv), opts, info, obj)


@dataclass
class _Unknowns:
    """The bundle's unknowns: which target coordinates are free (``free_pts`` (n, 3)), the
    points held for being seen in fewer than 2 views, the gauge and its points, the camera
    parameters' map and names (:func:`_cam_map`)."""

    free_pts: np.ndarray
    held: np.ndarray
    gauge_text: str
    gauge_pts: tuple[int, int, int]
    cam_map: np.ndarray
    cam_names: list[str]


def _unknowns(X0: np.ndarray, pi: np.ndarray, opts: BundleOptions, aspect: float
              ) -> _Unknowns:
    """The target coordinates left free by the gauge and by the points seen in fewer than
    2 views, and the camera parameters of ``opts.model``."""
    n = len(X0)
    seen = np.bincount(pi, minlength=n) >= 2
    held = np.flatnonzero(~seen) if opts.refine_target else np.zeros(0, int)
    fixed, gauge_text, gauge_pts = _gauge(X0, opts.gauge_points, seen)
    fixed[held] = True
    free_pts = ~fixed if opts.refine_target else np.zeros((n, 3), bool)
    cam_map, cam_names = _cam_map(opts.model, opts.fix_aspect, aspect)
    return _Unknowns(free_pts, held, gauge_text, gauge_pts, cam_map, cam_names)


def _bundle_result(prob: _Problem, state: _State, cov: _Covariances, sigmas: _CameraSigmas,
                   inlier: np.ndarray, data: tuple, opts: BundleOptions, info: dict,
                   obj: tuple | None) -> CalibrationResult:
    """The :class:`CalibrationResult` of a finished adjustment: ``info`` completed with the
    counts, the noise, the sigmas of both kinds and the poses'; ``obj`` the refined target
    and its sigmas (None when the target was held)."""
    vi, pi, uv = data
    m = len(state.rvecs)
    pose_sd, pose_sd_post = cov.pose_sd("repeatability"), cov.pose_sd("posterior")
    cam = state.cam
    residual_sq = np.sum((project_jacobian(cam, state.rvecs, state.tvecs, state.X, vi, pi,
                                           jacobian=False) - uv) ** 2, axis=1)  # unweighted
    per_view = np.sqrt(np.bincount(vi[inlier], residual_sq[inlier], m)
                       / np.maximum(np.bincount(vi[inlier], minlength=m), 1))
    info.update({"n_unknowns": int(prob.n_unknowns), "n_observations": int(prob.N),
                 "residual_dof": cov.dof, "sigma_px": float(np.sqrt(cov.s2)),
                 "model": opts.model,
                 "prior_sigma_px": (float(np.sqrt(prob.sig2)) if prob.Lam is not None
                                    else None),
                 "sd_kind": "repeatability",
                 "rvecs_sd": pose_sd[:, :3], "tvecs_sd": pose_sd[:, 3:],
                 "target_sigma_mm": opts.target_sigma_mm, "warp_sigma_mm": opts.warp_sigma_mm,
                 "sd_posterior": sigmas.posterior, "rvecs_sd_posterior": pose_sd_post[:, :3],
                 "tvecs_sd_posterior": pose_sd_post[:, 3:],
                 "view_scatter": sigmas.scatter.to_dict() | {"applied": opts.scatter_check},
                 "sd_noise_model": sigmas.noise_model})
    if opts.return_covariance:
        info["parameter_names"] = cov.names
        info["covariance_repeatability"] = cov.full("repeatability")
        info["covariance_posterior"] = cov.full("posterior")
    obj_pts, obj_sd = obj if obj is not None else (None, None)
    n_dist = 5 if opts.model == "standard" else 8
    return CalibrationResult(backend="bundle", K=_camera_matrix(cam),
                             dist=cam[4:4 + n_dist].copy(), sd=sigmas.reported,
                             rms_px=float(np.sqrt(residual_sq[inlier].mean())),
                             per_view_rms_px=per_view, rvecs=state.rvecs.copy(),
                             tvecs=state.tvecs.copy(),
                             rejected=[(int(vi[i]), int(pi[i])) for i in np.flatnonzero(~inlier)],
                             object_points=obj_pts, object_points_sd=obj_sd, info=info)


def _refuse_underdetermined(n_obs: int, n_camera: int, n_views: int, n_target: int) -> None:
    """Raise when the observations give fewer equations (2 each) than there are unknowns."""
    n_unknowns = n_camera + 6 * n_views + n_target
    if 2 * n_obs < n_unknowns:
        raise ValueError(f"{n_obs} observations give {2 * n_obs} equations for {n_unknowns} "
                         f"unknowns ({n_camera} camera + 6 x {n_views} pose + {n_target} "
                         "target coordinates): add views, or set refine_target=False")


def _camera_matrix(cam: np.ndarray) -> np.ndarray:
    """(3, 3) ``K`` from the camera vector ``(fx, fy, cx, cy, ...)``."""
    return np.array([[cam[0], 0.0, cam[2]], [0.0, cam[1], cam[3]], [0.0, 0.0, 1.0]])


class _CameraSigmas(NamedTuple):
    """The camera's 1-sigmas by name: ``reported`` (repeatability, scaled where the views
    disagree and the check is applied), ``posterior`` (likewise), ``noise_model`` (unscaled),
    and the view-scatter ``scatter`` check behind the scaling."""

    reported: dict[str, float]
    posterior: dict[str, float]
    noise_model: dict[str, float]
    scatter: ViewScatter


def _camera_sigmas(prob: _Problem, state: _State, normal, cov: _Covariances,
                   cam_map: np.ndarray, model: str, obs: Observations,
                   scatter_check: bool) -> _CameraSigmas:
    """The camera's sigmas from the covariance, checked against the scatter between views
    (groups of nearly one pose counted once, :mod:`zoomcalib.calibrate.scatter`)."""
    names = CAMERA_NAMES[:4 + (5 if model == "standard" else 8)]
    camera_sd = cov.camera_sd(cam_map, "repeatability")
    groups = view_groups(obs.views, obs.image_size)
    prior = None if cov.prior_modes is None else (lambda x: cov._prior_diag(x[prob.nc:].T))
    scatter = view_scatter(prob.camera_influence(state, normal[1], normal[2],
                                                 cov.Sinv[:prob.nc]),
                           groups[prob.vi], int(groups.max()) + 1, CAMERA_NAMES, camera_sd,
                           lambda: prob.camera_deletions(state, *normal[:3], groups),
                           prob.camera_noise_share(state, normal[1], normal[2], cov.Sinv,
                                                   groups, prior), prob.pi,
                           None if cov.prior_modes is None else prob.camera_influence(
                               state, normal[1], normal[2], cov.Sinv[:prob.nc],
                               hold_points=True))
    noise_model = dict(zip(names, camera_sd[:len(names)].tolist(), strict=True))
    posterior = dict(zip(names, cov.camera_sd(cam_map, "posterior")[:len(names)].tolist(),
                         strict=True))
    if not scatter_check:
        return _CameraSigmas(noise_model, posterior, noise_model, scatter)
    return _CameraSigmas(scatter.scaled(noise_model), scatter.scaled(posterior), noise_model,
                         scatter)


def _refined_target(prob: _Problem, state: _State, cov: _Covariances, modes, X0: np.ndarray,
                    flat_cam: np.ndarray, sd_noise_model: dict[str, float],
                    guard_warn_ratio: float, info: dict) -> tuple[np.ndarray, np.ndarray]:
    """The refined points (n, 3) and their sigmas (0 where gauge-fixed); adds ``flatness_mm``,
    ``flatness_sd_mm`` and the ``guard`` to ``info`` and warns when the guard trips."""
    n = len(X0)
    var = np.zeros(3 * n)
    var[prob.free_idx] = cov.point_variances()
    points = state.X.copy()
    info["flatness_mm"], info["flatness_sd_mm"] = _flatness(points, cov.points, prob.free_idx)
    info["guard"] = _guard(modes, X0, points, cov.points, prob.free_idx, flat_cam, state.cam,
                           sd_noise_model)
    _warn_guard(info["guard"], guard_warn_ratio, info.get("target_sigma_mm"))
    return points, np.sqrt(var).reshape(n, 3)


def _flatten(obs: Observations, weights):
    """Validate and concatenate the views: view and point index, uv, weight per observation."""
    n = len(obs.object_points)
    ids_list, pts_list, w_list = [], [], []
    for v, (ids, pts) in enumerate(obs.views):
        ids = np.asarray(ids, dtype=int).ravel()
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        wv = np.ones(len(ids)) if weights is None else np.asarray(weights[v], float).ravel()
        name = f" ({obs.names[v]!r})" if v < len(obs.names) else ""
        if not (len(ids) == len(pts) == len(wv)):
            raise ValueError(f"view {v}{name}: {len(ids)} ids, {len(pts)} points, {len(wv)} "
                             "weights")
        keep = (wv > 0) & np.all(np.isfinite(pts), axis=1)
        ids, pts, wv = ids[keep], pts[keep], wv[keep]
        if len(ids) < 4:
            raise ValueError(f"view {v}{name} has {len(ids)} usable points; at least 4 are "
                             "needed to determine its pose")
        if ids.min() < 0 or ids.max() >= n:
            raise ValueError(f"view {v}{name}: point ids must lie in [0, {n})")
        if len(np.unique(ids)) != len(ids):
            raise ValueError(f"view {v}{name}: a point id appears twice")
        ids_list.append(ids)
        pts_list.append(pts)
        w_list.append(wv)
    vi = np.concatenate([np.full(len(i), v) for v, i in enumerate(ids_list)])
    return (vi, np.concatenate(ids_list), np.concatenate(pts_list), np.concatenate(w_list),
            ids_list, pts_list)


def _initial_poses(cam: np.ndarray, X0: np.ndarray, ids_list, pts_list):
    """``Rt_cam_board`` of every view from ``cv2.solvePnP`` with the camera ``cam``."""
    Kc = np.array([[cam[0], 0, cam[2]], [0, cam[1], cam[3]], [0, 0, 1.0]])
    m = len(ids_list)
    rv, tv = np.zeros((m, 3)), np.zeros((m, 3))
    for v in range(m):
        ok, r_, t_ = cv2.solvePnP(X0[ids_list[v]], pts_list[v], Kc, cam[4:])
        if not ok:
            raise ValueError(f"view {v}: cv2.solvePnP found no initial pose")
        rv[v], tv[v] = r_.ravel(), t_.ravel()
    return rv, tv


def _guard(modes, X0: np.ndarray, X: np.ndarray, cov_x: _PointCovariance, free: np.ndarray,
           cam_flat: np.ndarray, cam: np.ndarray, sd: dict) -> dict:
    """Deformation of the refined target split into similarity, smooth warp and the irregular
    rest, and the camera's shift from the flat-target fit.

    ``irregular_noise_rms_mm`` is ``sqrt(trace(P C P) / 3n)``: the RMS the irregular part
    would have from the noise alone (``C`` the covariance of the points, ``P`` the projector on
    the irregular deformations, in the nominal frame; ``C`` is given for the ``free``
    coordinates of the point-major (3n,) vector, the others are held)."""
    n = len(X0)
    Q, B, Ti = modes
    # deviation from the nominal board aligned on X, in the nominal frame (gauge-independent)
    sc, Rs, t = fit_similarity(X0, X)
    d = ((((X - t) @ Rs) / sc) - X0).ravel()
    d = d - Q @ (Q.T @ d)
    irr = d - B @ (B.T @ d)
    # tr(P C_nom) with C_nom = (I (x) Rs^T) C (I (x) Rs) / sc^2 and P = I - Q Q^T - B B^T:
    # tr(C) - tr(M^T C M) with M = (I (x) Rs) [Q B], rotated once instead of C
    M = (Rs @ np.hstack([Q, B]).reshape(n, 3, -1)).reshape(3 * n, -1)[free]
    diag = cov_x.diag()
    trace = float(np.sum(diag) - np.einsum("ij,ij->", M, cov_x @ M)) / sc**2
    # tr(P C P) = tr(P C) >= 0 for a positive semi-definite C
    noise2 = _checked_variances(np.array([trace]), np.array([np.sum(diag) / sc**2]),
                                ["the irregular target deformation"], "noise")[0] / (3 * n)
    g = {"flat_fx": float(cam_flat[0]), "flat_fy": float(cam_flat[1]),
         "flat_cx": float(cam_flat[2]), "flat_cy": float(cam_flat[3]),
         "warp_amplitude_mm": [float(a) for a in Ti @ (B.T @ d)],
         "irregular_rms_mm": float(np.sqrt(np.mean(irr**2))),
         "irregular_noise_rms_mm": float(np.sqrt(noise2))}
    for k, name in enumerate(("fx", "fy", "cx", "cy")):
        g[f"shift_{name}_px"] = float(cam[k] - cam_flat[k])
        g[f"shift_{name}_sigma"] = float((cam[k] - cam_flat[k]) / sd[name])
    return g


def _flatness(X: np.ndarray, cov_x: _PointCovariance, free: np.ndarray
              ) -> tuple[float, float]:
    r"""RMS distance of points from their best-fit plane, and its linearised 1-sigma.

    With plane normal ``n`` (smallest singular vector of the centred points) and signed
    distances ``d_j``, ``phi = sqrt(mean d_j^2)``; since the plane minimises ``sum d_j^2``,
    ``d phi / d X_j = d_j n / (n_pts phi)`` and ``sd(phi)^2 = g^T C g`` (``C`` over the
    ``free`` coordinates; the others are held).
    """
    c = X - X.mean(0)
    _, _, Vt = np.linalg.svd(c, full_matrices=False)
    nrm = Vt[2]
    d = c @ nrm
    phi = float(np.sqrt(np.mean(d * d)))
    if phi == 0:
        return 0.0, 0.0
    gvec = (d[:, None] * nrm[None, :] / (len(X) * phi)).ravel()
    gf = gvec[free]
    var = _checked_variances(np.array([gf @ (cov_x @ gf)]), np.array([gf**2 @ cov_x.diag()]),
                             ["the flatness"], "repeatability")
    return phi, float(np.sqrt(var[0]))

