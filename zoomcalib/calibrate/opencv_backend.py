"""Calibration with OpenCV: ``cv2.calibrateCameraExtended`` and the object-releasing
``cv2.calibrateCameraROExtended``.

Conventions: pixels in OpenCV's convention (centre of the top-left pixel = (0, 0), x right,
y down); distortion in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``; poses ``rvec, tvec``
are ``Rt_cam_board`` (board to camera), in the units of the target's object points (mm for
targets from :func:`zoomcalib.targets.parse_pattern`). Uncertainties are 1-sigma, as OpenCV
reports them (from the Gauss-Newton normal matrix, scaled by the residual variance).

Reprojection errors: ``rms_px`` is ``sqrt(sum |e_i|^2 / N)`` over the N observed points, with
``|e_i|`` the Euclidean (2-D) reprojection error of one point, px. This is the number OpenCV's
calibration functions return; it is recomputed here from the result (``cv2.projectPoints``) and
OpenCV's own value is kept in ``info["opencv_rms_px"]``. ``per_view_rms_px`` is the same
quantity per view.

Convergence and uncertainties: OpenCV reports neither its iteration count nor why it stopped, so
the Gauss-Newton step is re-evaluated at its solution (:func:`_stationarity`): ``info`` gets
``converged`` (the step is at most :data:`STATIONARY_SIGMA` sigma long), ``stop_reason``
(``'tolerance'`` or ``'not stationary'``) and ``convergence_check`` (the step, the criteria).
OpenCV's 1-sigmas come from ``s^2 (J^T J)^-1`` with no prior, which is both the posterior and the
repeatability (``info['sd_kind'] = 'repeatability'``, as the bundle's). OpenCV inverts ``J^T J``
with an unscaled SVD pseudo-inverse, which drops the weak directions of a near-singular matrix
and reports them with a variance of zero (or a negative one): at the long end of a zoom, fx
sigmas 1000x too small. The camera's 1-sigmas of :func:`calibrate_opencv` are therefore checked
against the full inverse of the same matrix, scaled to unit diagonal
(:func:`_checked_camera_sd`); where OpenCV's is below half of it or not a number, the full
inverse's is reported and ``info['sd_check']`` records both (a conditioning flag,
:mod:`zoomcalib.calibrate.checks`); the poses' 1-sigmas are then the full inverse's too. A
1-sigma that is not a number stops the object-releasing calibration for a camera parameter
and is listed in
``info['sd_invalid']``, with a ``RuntimeWarning``, for a pose or target coordinate.

Flag quirks of OpenCV 5.0 handled here
--------------------------------------
* ``CALIB_DISABLE_SCHUR_COMPLEMENT`` has the same value as ``CALIB_TILTED_MODEL`` (``1 << 18``),
  so asking for the Bouguet engine also frees the two tilted-sensor terms (tau_x, tau_y), which
  trade against the principal point (``tests/test_calibrate_opencv.py`` shows how far cx moves).
  Whenever that bit is set, ``CALIB_FIX_TAUX_TAUY`` is added with zero tilt, which gives
  the same result as the default (Schur) engine.
* ``calibrateCameraRO`` with ``CALIB_USE_INTRINSIC_GUESS`` fails an assertion in the Schur
  engine (``nparams == NINTRINSIC + nimages * 6``); :func:`calibrate_opencv_ro` then switches to
  the Bouguet engine (``CALIB_DISABLE_SCHUR_COMPLEMENT | CALIB_FIX_TAUX_TAUY``) and says so in
  ``info["engine"]``.
* OpenCV only takes ``float32`` points; they are converted here (``float32`` keeps about 1e-4 px
  at 10^3 px, far below detection noise).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from zoomcalib.calibrate.bundleproblem import (
    CAMERA_NAMES,
    _Data,
    _Problem,
    _State,
    as_blocks,
    scaled_inverse,
)
from zoomcalib.calibrate.result import (
    DIST_NAMES,
    CalibrationResult,
    Observations,
    one_opencv_thread,
)
from zoomcalib.calibrate.scatter import ViewScatter, view_groups, view_scatter
from zoomcalib.calibrate.solver import predicted_decrease, schur_step
from zoomcalib.detect.opencv import Detection
from zoomcalib.targets import Target, parse_pattern

__all__ = [
    "MODELS",
    "calibrate_opencv",
    "calibrate_opencv_multistart",
    "calibrate_opencv_robust",
    "not_a_camera",
    "pose_sigmas_unused",
    "calibrate_opencv_ro",
    "default_fixed_point",
    "flag_names",
    "observations_from_detections",
]

#: Distortion model name -> number of coefficients (OpenCV order).
MODELS: dict[str, int] = {"standard": 5, "rational": 8}

_BIT18 = 1 << 18  # CALIB_DISABLE_SCHUR_COMPLEMENT == CALIB_TILTED_MODEL in OpenCV 5.0
_DISABLE_SCHUR = int(getattr(cv2, "CALIB_DISABLE_SCHUR_COMPLEMENT", 0))
_FIX_TAU = int(getattr(cv2, "CALIB_FIX_TAUX_TAUY", 0))
_N_OPENCV_DIST = 14  # k1..k6, p1, p2, s1..s4, tau_x, tau_y: the longest vector OpenCV returns

# Flag names in order of preference: where two names share a value, the first is reported.
_FLAG_ORDER = (
    "CALIB_USE_INTRINSIC_GUESS", "CALIB_FIX_ASPECT_RATIO", "CALIB_FIX_PRINCIPAL_POINT",
    "CALIB_ZERO_TANGENT_DIST", "CALIB_FIX_FOCAL_LENGTH", "CALIB_FIX_K1", "CALIB_FIX_K2",
    "CALIB_FIX_K3", "CALIB_FIX_K4", "CALIB_FIX_K5", "CALIB_FIX_K6", "CALIB_RATIONAL_MODEL",
    "CALIB_THIN_PRISM_MODEL", "CALIB_FIX_S1_S2_S3_S4", "CALIB_USE_LU",
    "CALIB_DISABLE_SCHUR_COMPLEMENT", "CALIB_TILTED_MODEL", "CALIB_FIX_TAUX_TAUY",
    "CALIB_USE_QR", "CALIB_FIX_TANGENT_DIST", "CALIB_USE_EXTRINSIC_GUESS",
    "CALIB_RECOMPUTE_EXTRINSIC", "CALIB_CHECK_COND", "CALIB_FIX_SKEW",
)


def flag_names(flags: int) -> list[str]:
    """The ``cv2.CALIB_*`` names whose bits are set in ``flags``.

    Bits that two names share in OpenCV 5.0 (``1 << 18``: ``CALIB_DISABLE_SCHUR_COMPLEMENT``
    and ``CALIB_TILTED_MODEL``) are reported under the first name of the module's list.

    Examples
    --------
    >>> flag_names(cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_RATIONAL_MODEL)
    ['CALIB_FIX_ASPECT_RATIO', 'CALIB_RATIONAL_MODEL']
    """
    out, seen = [], 0
    for name in _FLAG_ORDER:
        v = int(getattr(cv2, name, 0))
        if v and flags & v == v and not seen & v:
            out.append(name)
            seen |= v
    rest = int(flags) & ~seen
    if rest:
        out.append(f"0x{rest:x}")
    return out


# ----------------------------------------------------------------------------------------------
# observations


def observations_from_detections(detections: Iterable[Detection], target: Target | str,
                                 image_size: tuple[int, int] | None = None,
                                 min_points: int = 4) -> Observations:
    """Collect the usable detections of one image set into :class:`Observations`.

    Parameters
    ----------
    detections : iterable of Detection
        As returned by :func:`zoomcalib.detect.opencv.detect_folder`; points in px, OpenCV
        convention, ``ids`` indexing ``target.object_points``.
    target : Target or str
        The target (or its pattern spec); its object points (board frame, mm, z = 0) become
        ``Observations.object_points``.
    image_size : (int, int), optional
        (width, height), px. Default: the detections' own ``image_size``, which must then agree.
    min_points : int
        Views with fewer points are left out (a planar pose needs 4).

    Returns
    -------
    Observations
        One view per image that was detected with at least ``min_points`` points, in input
        order, ``names`` the images' file names. Failed images are skipped, and so are points
        whose refinement fell back to the initial detector (``Detection.fallback``); their
        number is ``Observations.n_fallback``.

    Raises
    ------
    ValueError
        If an image's size differs from the others (or from ``image_size``), if ids fall
        outside the target or repeat, or if no size can be found; the message names the file.
    """
    target = parse_pattern(target) if isinstance(target, str) else target
    n = target.n_points
    views, names, n_fallback = [], [], 0
    size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
    for d in detections:
        keep = ~d.fallback if d.ok else np.zeros(0, bool)
        if not d.ok or np.count_nonzero(keep) < min_points:
            continue
        if d.image_size != (0, 0):
            if size is None:
                size = d.image_size
            elif d.image_size != size:
                raise ValueError(f"{d.file}: image size {d.image_size[0]}x{d.image_size[1]} "
                                 f"differs from the set's {size[0]}x{size[1]}")
        ids = np.asarray(d.ids, np.int64)
        outside = ids[(ids < 0) | (ids >= n)]
        if outside.size:
            raise ValueError(f"{d.file}: point id {int(outside[0])} outside the target's {n} "
                             f"points ({target.spec})")
        if len(np.unique(ids)) != len(ids):
            raise ValueError(f"{d.file}: repeated point ids")
        points = np.asarray(d.points, np.float64).reshape(-1, 2)
        views.append((ids[keep].copy(), points[keep].copy()))
        names.append(d.file)
        n_fallback += int(np.count_nonzero(~keep))
    if size is None:
        if not views:
            size = (0, 0)
        else:
            raise ValueError("image size unknown: pass image_size (the detections carry none)")
    return Observations(np.asarray(target.object_points, np.float64).copy(), views, size, names,
                        n_fallback)


# ----------------------------------------------------------------------------------------------
# shared helpers


def _check_model(model: str, flags: int) -> tuple[str, int, int]:
    if model not in MODELS:
        raise ValueError(f"unknown distortion model {model!r}; choose "
                         + " or ".join(repr(m) for m in MODELS))
    flags = int(flags)
    if flags & cv2.CALIB_RATIONAL_MODEL:
        model = "rational"
    if model == "rational":
        flags |= cv2.CALIB_RATIONAL_MODEL
    if flags & cv2.CALIB_THIN_PRISM_MODEL:
        raise ValueError("CALIB_THIN_PRISM_MODEL is not supported: results hold 5 (standard) or "
                         "8 (rational) distortion coefficients")
    if flags & _BIT18:
        # In OpenCV 5.0 this bit is both DISABLE_SCHUR_COMPLEMENT and TILTED_MODEL: keep the
        # Bouguet engine, keep the sensor untilted.
        flags |= _FIX_TAU
    return model, flags, MODELS[model]


def _names(obs: Observations) -> list[str]:
    return list(obs.names) if len(obs.names) == obs.n_views else \
        [f"view {i}" for i in range(obs.n_views)]


def _check_views(obs: Observations, names: Sequence[str], n_dist: int, min_views: int,
                 extra_unknowns: int, what: str) -> None:
    if obs.n_views < min_views:
        raise ValueError(f"{what}: {obs.n_views} usable view{'s' if obs.n_views != 1 else ''}; "
                         f"need at least {min_views}")
    w, h = obs.image_size
    if w <= 0 or h <= 0:
        raise ValueError(f"{what}: image size {w}x{h} is not valid")
    for name, (ids, pts) in zip(names, obs.views, strict=True):
        if len(ids) < 4:
            raise ValueError(f"{what}: view {name} has {len(ids)} points; a pose needs at least 4")
        if len(pts) != len(ids):
            raise ValueError(f"{what}: view {name} has {len(pts)} points but {len(ids)} ids")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"{what}: view {name} has non-finite image points")
    n_unknowns = 4 + n_dist + 6 * obs.n_views + extra_unknowns
    n_equations = 2 * obs.n_observations
    if n_equations <= n_unknowns:
        raise ValueError(f"{what}: {obs.n_observations} points give {n_equations} equations for "
                         f"{n_unknowns} unknowns; add views or points")


def _initial(obs: Observations, flags: int, fix_aspect: bool, K_guess, dist_guess,
             n_dist: int) -> tuple[np.ndarray, np.ndarray, int]:
    if fix_aspect:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    K = np.eye(3)
    if K_guess is not None:
        K = np.array(K_guess, np.float64).reshape(3, 3)
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    elif flags & cv2.CALIB_USE_INTRINSIC_GUESS:
        raise ValueError("CALIB_USE_INTRINSIC_GUESS needs K_guess")
    elif flags & cv2.CALIB_FIX_ASPECT_RATIO:
        K[0, 0] = K[1, 1] = 1.0  # only the ratio fx / fy = 1 is used
    dist = np.zeros(_N_OPENCV_DIST)
    if dist_guess is not None:
        g = np.asarray(dist_guess, np.float64).ravel()
        if len(g) > n_dist:
            raise ValueError(f"dist_guess has {len(g)} terms; the model has {n_dist}")
        dist[:len(g)] = g
    return K, dist, flags


def _sd_by_name(sdi: np.ndarray, K: np.ndarray, flags: int, n_dist: int) -> tuple[dict, list]:
    sdi = np.asarray(sdi, np.float64).ravel()
    sd = {"fx": sdi[0], "fy": sdi[1], "cx": sdi[2], "cy": sdi[3]}
    for i, name in enumerate(DIST_NAMES[:n_dist]):
        # OpenCV's order: k1, k2, p1, p2, k3, k4, k5, k6 (= DIST_NAMES)
        sd[name] = sdi[4 + i]
    notes = []
    if flags & cv2.CALIB_FIX_ASPECT_RATIO and sd["fx"] == 0.0:
        # fx = (fx/fy) * fy is tied to fy: its 1-sigma follows.
        sd["fx"] = sd["fy"] * K[0, 0] / K[1, 1]
        notes.append("fx tied to fy (CALIB_FIX_ASPECT_RATIO): sd fx = sd fy * fx / fy")
    return {k: float(v) for k, v in sd.items()}, notes


def _fixed_names(flags: int, n_dist: int) -> list[str]:
    fixed = []
    if flags & cv2.CALIB_FIX_FOCAL_LENGTH and flags & cv2.CALIB_USE_INTRINSIC_GUESS:
        fixed += ["fx", "fy"]
    if flags & cv2.CALIB_FIX_PRINCIPAL_POINT:
        fixed += ["cx", "cy"]
    if flags & (cv2.CALIB_ZERO_TANGENT_DIST | int(getattr(cv2, "CALIB_FIX_TANGENT_DIST", 0))):
        fixed += ["p1", "p2"]
    for k in range(1, 7):
        if f"k{k}" in DIST_NAMES[:n_dist] and flags & getattr(cv2, f"CALIB_FIX_K{k}"):
            fixed.append(f"k{k}")
    return fixed


def _residuals(obj: list[np.ndarray], img: list[np.ndarray], rvecs, tvecs, K, dist
               ) -> tuple[float, np.ndarray]:
    sq, per_view, n = 0.0, [], 0
    for o, p, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(np.asarray(o, np.float64), np.asarray(r, np.float64),
                                    np.asarray(t, np.float64), K, dist)
        e2 = np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2, axis=1)
        per_view.append(np.sqrt(e2.mean()))
        sq += e2.sum()
        n += len(e2)
    return float(np.sqrt(sq / n)), np.asarray(per_view)


#: OpenCV's solution counts as converged when the Gauss-Newton step left at it is at most this
#: long in the metric of its own covariance, sigma (see :func:`_stationarity`).
STATIONARY_SIGMA = 0.05


def _free_camera_columns(flags: int, n_dist: int, K: np.ndarray) -> np.ndarray:
    """(12, nc) map from the camera parameters OpenCV adjusted under ``flags`` to the bundle's
    ``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6``."""
    fixed = set(_fixed_names(flags, n_dist))
    eye = np.eye(12)
    cols = []
    if "fx" not in fixed:
        if flags & cv2.CALIB_FIX_ASPECT_RATIO:
            cols.append(eye[0] * (K[0, 0] / K[1, 1]) + eye[1])   # f with fx / fy held
        else:
            cols += [eye[0], eye[1]]
    names = ("cx", "cy") + DIST_NAMES[:n_dist]
    bundle_index = {"cx": 2, "cy": 3, "k1": 4, "k2": 5, "p1": 6, "p2": 7, "k3": 8, "k4": 9,
                    "k5": 10, "k6": 11}
    cols += [eye[bundle_index[nm]] for nm in names if nm not in fixed]
    return np.array(cols).T


def _problem_at_solution(obj: list[np.ndarray], img: list[np.ndarray], K: np.ndarray,
                         dist: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray, flags: int,
                         n_dist: int) -> tuple[_Problem, _State]:
    """The bundle's least-squares problem over the parameters OpenCV adjusted under ``flags``
    (camera, every pose; a released target held at its refined points), observing ``img``,
    and OpenCV's solution as its state."""
    ids = [np.arange(len(o)) for o in obj]
    offsets = np.cumsum([0] + [len(o) for o in obj])
    points = np.concatenate([np.asarray(o, np.float64).reshape(-1, 3) for o in obj])
    vi = np.concatenate([np.full(len(i), v) for v, i in enumerate(ids)])
    pi = np.concatenate([i + offsets[v] for v, i in enumerate(ids)])
    uv = np.concatenate([np.asarray(p, np.float64).reshape(-1, 2) for p in img])
    cam = np.zeros(12)
    cam[:4] = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cam[4:4 + n_dist] = dist[:n_dist]
    cam_map = _free_camera_columns(flags, n_dist, K)
    prob = _Problem(_Data(vi, pi, uv, np.ones(len(vi)), len(obj), len(points), points), cam_map,
                    np.zeros((len(points), 3), bool), None, 0.0)
    state = _State(cam, np.asarray(rvecs, np.float64), np.asarray(tvecs, np.float64), points)
    return prob, state


class _AtSolution(NamedTuple):
    """The undamped normal equations at OpenCV's solution and what they came from."""

    blocks: tuple            # U, W, V, g, g_p, r (Problem.normal_equations)
    s2: float                # residual variance
    cam_map: np.ndarray      # (12, nc) camera columns
    prob: _Problem
    state: _State


def _normal_matrix_at_solution(obj: list[np.ndarray], img: list[np.ndarray], K: np.ndarray,
                               dist: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray,
                               flags: int, n_dist: int):
    """The undamped normal equations of :func:`_problem_at_solution` (``U, W, V, g, g_p, r``),
    its residual variance ``s^2``, the map of its camera columns (12, nc), the problem and its
    state."""
    prob, state = _problem_at_solution(obj, img, K, dist, rvecs, tvecs, flags, n_dist)
    blocks = prob.normal_equations(state)
    r = blocks[-1]
    dof = 2 * prob.N - prob.n_unknowns
    s2 = float(np.einsum("ij,ij->", r, r)) / dof if dof > 0 else float("nan")
    return _AtSolution(blocks, s2, prob.cam_map, prob, state)


def _stationarity(obj: list[np.ndarray], img: list[np.ndarray], K: np.ndarray,
                  dist: np.ndarray, rvecs: np.ndarray, tvecs: np.ndarray, flags: int,
                  n_dist: int) -> float:
    r"""Length of the Gauss-Newton step left at OpenCV's solution, in sigma.

    ``cv2.calibrateCamera*`` does not say how many iterations it used nor why it stopped, so
    the solution is checked instead: with the Jacobian ``J`` of the reprojection errors ``r``
    over the parameters OpenCV adjusted (camera under ``flags``, every pose; a released target
    is held at its refined points), the step ``d = -N^-1 J^T r`` (``N = J^T J``) has length
    ``sqrt(d^T N d / s^2)`` in the metric of the covariance ``s^2 N^-1``
    (``s^2 = |r|^2 / (2 N_obs - n_unknowns)``): the largest distance, in 1-sigma, of any
    parameter or combination of them from the stationary point. ``inf`` if ``N`` is singular.
    """
    return _step_sigma(_normal_matrix_at_solution(obj, img, K, dist, rvecs, tvecs, flags, n_dist))


def _step_sigma(at_solution) -> float:
    """:func:`_stationarity` from the normal equations at the solution."""
    (U, W, V, g, gp, _), s2 = at_solution.blocks, at_solution.s2
    sol = _gauss_newton_step(U, W, V, g, gp)
    if sol is None or not s2 > 0:
        return float("inf")
    return float(np.sqrt(max(sol[1], 0.0) / s2))


def _gauss_newton_step(U, W, V, g, gp) -> tuple[np.ndarray, float] | None:
    """The undamped step of the bundle's normal equations (:meth:`_Problem.normal_equations`'
    blocks) over its camera and target unknowns, and the cost decrease it predicts
    (:mod:`zoomcalib.calibrate.solver`); None when the system is singular."""
    blocks = as_blocks(U, W, V, g, gp)
    delta = schur_step(blocks, 0.0)
    return None if delta is None else (delta[:len(U)], predicted_decrease(blocks, delta))


def _camera_covariance(at_solution: _AtSolution
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    r"""Covariance ``s^2 N^-1`` of the camera parameters, (12, 12) over the bundle's ``fx, fy,
    cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`` (zero rows for fixed ones), the poses' 1-sigmas
    (m, 6) ``rvec, tvec`` and ``S^-1`` (nc, nc), from the normal equations at OpenCV's solution;
    None when ``N`` is singular.

    The poses are eliminated (``S = U - W^T V^-1 W``, per view) and ``S`` is inverted scaled to
    unit diagonal (:func:`~zoomcalib.calibrate.bundleproblem.scaled_inverse`): the columns of fx
    (px) and of a k3 seen through a 2-degree field differ by 10^10, which the scaling removes and a
    pseudo-inverse of the unscaled matrix does not survive. A pose's covariance is
    ``s^2 (V^-1 + H S^-1 H^T)`` with ``H = V^-1 W^T``.
    """
    (U, W, V, *_), s2, cam_map = at_solution.blocks, at_solution.s2, at_solution.cam_map
    try:
        pose_chol_inv = np.linalg.inv(np.linalg.cholesky(V))
    except np.linalg.LinAlgError:
        return None
    G = pose_chol_inv @ W.transpose(0, 2, 1)                           # (m, 6, nc) = L^-1 W^T
    nc = cam_map.shape[1]
    pose_coupling = G.reshape(-1, U.shape[0])
    S_inv, full_rank = scaled_inverse((U - pose_coupling.T @ pose_coupling)[:nc, :nc])
    if not (full_rank and np.isfinite(s2)):
        return None
    H = pose_chol_inv.transpose(0, 2, 1) @ G                           # (m, 6, nc) = V^-1 W^T
    # diag(V^-1): the column norms of L^-1
    pose_var = (np.einsum("vij,vij->vj", pose_chol_inv, pose_chol_inv)
                + np.einsum("vik,kl,vil->vi", H, S_inv, H))
    return s2 * cam_map @ S_inv @ cam_map.T, np.sqrt(s2 * pose_var), S_inv


def _view_scatter(at_solution: _AtSolution, covariance, groups: np.ndarray | None,
                  point_ids: np.ndarray | None = None) -> ViewScatter:
    """The view-scatter check (:mod:`zoomcalib.calibrate.scatter`) at OpenCV's solution, from
    its :func:`_camera_covariance`; ``groups`` (m,) joins views of nearly one pose
    (:func:`~zoomcalib.calibrate.scatter.view_groups`; None: none); ``point_ids`` the board
    point of each observation, views in order (None: the board points are not checked)."""
    prob, state, (U, W, V, *_) = at_solution.prob, at_solution.state, at_solution.blocks
    cov, _, S_inv = covariance
    groups = np.arange(prob.m) if groups is None else groups
    return view_scatter(prob.camera_influence(state, W, V, S_inv), groups[prob.vi],
                        int(groups.max()) + 1, CAMERA_NAMES, np.sqrt(np.diag(cov)),
                        lambda: prob.camera_deletions(state, U, W, V, groups),
                        prob.camera_noise_share(state, W, V, S_inv, groups),
                        None if point_ids is None else point_ids[prob.order])


#: OpenCV's 1-sigma of a camera parameter below this fraction of the full inverse's is taken
#: as truncated (see :func:`_checked_camera_sd`); where the normal matrix is well conditioned
#: the two agree to a fraction of a percent.
SD_TRUNCATED_BELOW = 0.5


def _checked_camera_sd(sd: dict, cov: np.ndarray | None, free: Sequence[str]) -> dict | None:
    r"""Check OpenCV's camera 1-sigmas against the full inverse ``cov``
    (:func:`_camera_covariance`); returns None when they agree, else what to record.

    OpenCV inverts its normal matrix with an SVD pseudo-inverse, unscaled: directions whose
    singular value falls below the machine precision times the largest are dropped, and their
    variance is reported as zero. At the long end of a zoom (views within a few degrees of
    fronto-parallel) that is the focal length's: fx sigmas of 0.05 px where the full inverse,
    and the scatter over repeated noise draws, give 80 px. A parameter whose OpenCV sigma is
    below :data:`SD_TRUNCATED_BELOW` of the full inverse's takes the full one; with ``cov``
    None (a singular normal matrix) every free camera parameter's sigma is infinite.
    """
    index = {nm: i for i, nm in enumerate(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2",
                                           "k3", "k4", "k5", "k6"))}
    if cov is None:
        return {"reason": "singular", "opencv_sd": dict(sd),
                "sd": {nm: float("inf") for nm in free}}
    full = {nm: float(np.sqrt(max(cov[index[nm], index[nm]], 0.0))) for nm in free}
    truncated = [nm for nm in free if not sd[nm] >= SD_TRUNCATED_BELOW * full[nm]]
    if not truncated:
        return None
    return {"reason": "truncated", "opencv_sd": dict(sd), "sd": full,
            "ratio": {nm: (float(sd[nm] / full[nm]) if np.isfinite(sd[nm]) and full[nm] > 0
                           else None) for nm in truncated}}


def solution_points(obj: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                    rvecs: np.ndarray, tvecs: np.ndarray
                    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view, a calibration's projections of its target points ``(k, 2)`` px and their
    normalised camera coordinates ``(X/Z, Y/Z)`` ``(k, 2)`` (the scene directions)."""
    uv, xn = [], []
    for o, r, t in zip(obj, rvecs, tvecs, strict=True):
        o, r, t = (np.asarray(a, np.float64) for a in (o, r, t))
        uv.append(cv2.projectPoints(o, r, t, K, dist)[0].reshape(-1, 2))
        cam = o.reshape(-1, 3) @ cv2.Rodrigues(r.reshape(3, 1))[0].T + t.reshape(3)
        xn.append(cam[:, :2] / cam[:, 2:3])
    return uv, xn


def displacement_response(obj: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                          rvecs: np.ndarray, tvecs: np.ndarray, flags: int, n_dist: int,
                          fields: list[list[np.ndarray]]) -> np.ndarray | None:
    r"""How a calibration answers small displacements of its image points.

    Each field moves every observed point by a displacement ``delta`` (per view ``(k, 2)``,
    px). Linearised at the solution, the parameters move by the Gauss-Newton step
    ``N^-1 J^T delta`` of the problem over the parameters OpenCV adjusted (``flags``; the
    poses with them), evaluated at the solution's own projections: what the calibration would
    report had the images been displaced so, to first order.

    Returns
    -------
    (F, 12) ndarray or None
        Per field, the change of ``fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`` (0 for the
        terms not adjusted); None when ``N`` is singular.
    """
    proj, _ = solution_points(obj, K, dist, rvecs, tvecs)
    out = np.zeros((len(fields), 12))
    for i, field in enumerate(fields):
        moved = [p + np.asarray(d, np.float64).reshape(-1, 2) for p, d in zip(proj, field,
                                                                               strict=True)]
        prob, state = _problem_at_solution(obj, moved, K, dist, rvecs, tvecs, flags, n_dist)
        sol = _gauss_newton_step(*prob.normal_equations(state)[:5])
        if sol is None:
            return None
        out[i] = prob.cam_map @ sol[0][:prob.nc]
    return out


def keystone_response(obj: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                      rvecs: np.ndarray, tvecs: np.ndarray, flags: int = 0,
                      n_dist: int = 5) -> dict[str, np.ndarray] | None:
    r"""How a calibration answers a keystone of the image (a sensor tilted against the lens).

    A keystone moves every image point ``uv`` to ``uv + p (p . kappa)``, ``p = uv - c`` (px
    from the principal point), ``kappa`` (2,) in 1/px (``kappa = pitch theta / L`` for a
    sensor tilted by ``theta`` rad with the exit pupil ``L`` mm in front of it). To first order
    it is the image of a camera turned by ``eps = f kappa`` (rad, ``f = (fx, fy)``) whose
    principal point moved by ``-f eps``, so a calibration can take it into the poses; how much
    it takes depends on the views and on the terms fitted (the distortion trades with it at a
    long focal length), not only on the lens. Linearised at the solution, per ``eps``
    (:func:`displacement_response` of the keystone of a unit ``eps_x``, then ``eps_y``, scaled
    down to stay linear):

        dc = -diag(f) A eps        (px; A = I: the keystone went into the poses and c,
                                    A = 0: it stayed in the residuals)
        d(p1, p2) = B eps          (OpenCV's tangential terms)

    Returns
    -------
    dict or None
        ``absorption`` A (2, 2) and ``tangential`` B (2, 2), dimensionless, rows (x, y) resp.
        (p1, p2), columns (eps_x, eps_y); None when ``N`` is singular.
    """
    proj, _ = solution_points(obj, K, dist, rvecs, tvecs)
    centre, f = K[[0, 1], [2, 2]], K[[0, 1], [0, 1]]
    eps = 1e-6
    fields = [[(p - centre) * ((p - centre) @ (np.eye(2)[j] * eps / f[j]))[:, None]
               for p in proj] for j in range(2)]
    response = displacement_response(obj, K, dist, rvecs, tvecs, flags, n_dist, fields)
    if response is None:
        return None
    response = response.T / eps  # shape (12, 2)
    return {"absorption": -response[2:4] / f[:, None], "tangential": response[6:8]}


def _convergence(at_solution, criteria) -> dict:
    """``converged``, ``stop_reason`` and how they were found (``convergence_check``), from the
    normal equations at OpenCV's solution (:func:`_normal_matrix_at_solution`)."""
    step = _step_sigma(at_solution)
    ok = step <= STATIONARY_SIGMA
    kind, count, eps = criteria
    return {"converged": bool(ok),
            "stop_reason": "tolerance" if ok else "not stationary",
            "convergence_check": {
                "method": "Gauss-Newton step re-evaluated at OpenCV's solution (OpenCV does "
                          "not report its iterations); converged when at most "
                          f"{STATIONARY_SIGMA} sigma long",
                "step_sigma": step, "threshold_sigma": STATIONARY_SIGMA,
                "criteria": {"type": int(kind), "max_count": int(count), "epsilon": float(eps)},
                "note": ("" if ok else "OpenCV stopped short of the minimum: its iteration cap "
                         f"({int(count)}) or its step tolerance ({float(eps):g}) ended it")}}


#: OpenCV's stop rule for a calibration that is reported: at most 100 iterations, or a relative
#: step below 1e-12.
CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
#: OpenCV's stop rule for a fit that only starts another solve or scores a term set on held-out
#: views (the zoom-wide adjustment's starts, its basins' fits and its held-out folds), as for
#: the basins' grid (``basins.GRID_CRITERIA``): such a fit needs its basin, not its last digits.
#: The solve it starts ends at its own criteria; a held-out error moves far below its standard
#: error (``docs/performance.md``, "Starts at a looser stop").
START_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-6)


def _criteria(criteria):
    return CRITERIA if criteria is None else tuple(criteria)


def _run(fn, what: str, *args, **kwargs):
    try:
        with one_opencv_thread():
            return fn(*args, **kwargs)
    except cv2.error as exc:
        msg = " ".join(str(exc).split())
        raise RuntimeError(f"{what}: OpenCV failed: {msg}") from None


def _invalid_sd(sd: np.ndarray, names: list[str]) -> list[str]:
    """Names of the 1-sigmas that are not non-negative numbers (OpenCV takes the square root of
    its covariance's diagonal: NaN means a negative variance there; ``inf`` is a parameter the
    data do not determine, see :func:`_checked_camera_sd`)."""
    sd = np.asarray(sd, np.float64).ravel()
    return [names[i] for i in np.flatnonzero(~(sd >= 0))]


#: The start of the warning :func:`_check_sd` gives for pose or target sigmas OpenCV could not
#: compute (:func:`pose_sigmas_unused` silences it alone).
_NO_POSE_SIGMA = "OpenCV gives no valid 1-sigma"


@contextlib.contextmanager
def pose_sigmas_unused():
    """Silence, inside the block, only the warning that some pose or target 1-sigmas are not
    numbers (the intrinsics' are checked regardless): for callers that use the camera alone,
    such as held-out fits and profiles."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=f".*{_NO_POSE_SIGMA}", category=RuntimeWarning)
        yield


def _check_sd(res: CalibrationResult, invalid: list[str], n_camera: int) -> None:
    """Refuse a result whose camera 1-sigmas are invalid; flag invalid pose or target ones in
    ``info['sd_invalid']`` with a ``RuntimeWarning``."""
    if not invalid:
        return
    if any(nm in invalid for nm in ("fx", "fy", "cx", "cy", *DIST_NAMES)[:n_camera]):
        raise RuntimeError(f"{res.backend}: the 1-sigma of {invalid[0]} is not a number "
                           f"({len(invalid)} parameters affected): OpenCV's covariance is not "
                           "positive semi-definite at its solution")
    res.info["sd_invalid"] = invalid
    warnings.warn(f"{res.backend}: {_NO_POSE_SIGMA} (negative variance) for "
                  f"{len(invalid)} parameters: {', '.join(invalid[:6])}"
                  f"{' ...' if len(invalid) > 6 else ''} (listed in info['sd_invalid'])",
                  RuntimeWarning, stacklevel=3)


@dataclass(frozen=True)
class _Fit:
    """One OpenCV calibration call: the backend's name, its inputs (``obj``, ``img`` per view,
    OpenCV's arrays), flags, the number of distortion terms, the lens model, the views'
    names and the termination criteria."""

    backend: str
    obj: list
    img: list
    flags: int
    n_dist: int
    model: str
    names: list[str]
    criteria: tuple


@dataclass(frozen=True)
class _Output:
    """What OpenCV returned: its RMS, camera matrix, distortion, poses, the intrinsics' and
    poses' 1-sigmas (``sdi``, ``sde``) and its per-view RMS."""

    rms: float
    K: np.ndarray
    dist: np.ndarray
    rvecs: object
    tvecs: object
    sdi: np.ndarray
    sde: np.ndarray
    per_view: np.ndarray


def _finish(fit: _Fit, out: _Output, groups: np.ndarray | None = None,
            point_ids: np.ndarray | None = None, camera_only: bool = False,
            keystone: bool = True) -> tuple[CalibrationResult, list[str]]:
    """The result of one OpenCV calibration, and the names of its invalid 1-sigmas;
    ``groups`` and ``point_ids`` as in :func:`_view_scatter`; ``camera_only`` and
    ``keystone`` as in :func:`calibrate_opencv`."""
    backend, obj, img, flags, n_dist = fit.backend, fit.obj, fit.img, fit.flags, fit.n_dist
    model, names, criteria = fit.model, fit.names, fit.criteria
    out_K, out_dist, rvecs, tvecs, sdi, sde = (out.K, out.dist, out.rvecs, out.tvecs,
                                                out.sdi, out.sde)
    opencv_rms, opencv_per_view = out.rms, out.per_view
    K = np.asarray(out_K, np.float64).reshape(3, 3)
    dist_all = np.asarray(out_dist, np.float64).ravel()
    dist = dist_all[:n_dist].copy()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise RuntimeError(f"{backend}: calibration diverged (non-finite intrinsics)")
    rv = np.asarray(rvecs, np.float64).reshape(-1, 3)
    tv = np.asarray(tvecs, np.float64).reshape(-1, 3)
    rms, per_view = _residuals(obj, img, rv, tv, K, dist)
    sd, notes = _sd_by_name(sdi, K, flags, n_dist)
    at_solution = _normal_matrix_at_solution(obj, img, K, dist, rv, tv, flags, n_dist)
    sd_check = scatter = None
    if backend == "opencv":  # the object-releasing fit's covariance includes its target's
        fixed = _fixed_names(flags, n_dist)
        free = [nm for nm in ("fx", "fy", "cx", "cy", *DIST_NAMES[:n_dist]) if nm not in fixed]
        covariance = _camera_covariance(at_solution)
        sd_check = _checked_camera_sd(sd, None if covariance is None else covariance[0], free)
        if sd_check is not None:
            sd.update(sd_check["sd"])
            # the poses' sigmas come from the same truncated inverse: the full one's replace them
            sde = np.full((len(obj), 6), np.inf) if covariance is None else covariance[1]
        if covariance is not None and not camera_only:
            sd_noise_model = dict(sd)
            scatter = _view_scatter(at_solution, covariance, groups, point_ids)
            sd = scatter.scaled(sd)
    sde = np.asarray(sde, np.float64).reshape(-1, 6)
    invalid = (_invalid_sd(list(sd.values()), list(sd))
               + _invalid_sd(sde, [f"{nm}.{p}" for nm in names
                                   for p in ("rx", "ry", "rz", "tx", "ty", "tz")]))
    info = {
        "model": model, "flags": int(flags), "flag_names": flag_names(flags),
        "views": list(names), "n_points": int(sum(len(o) for o in obj)),
        "opencv_rms_px": float(opencv_rms),
        "opencv_per_view_rms_px": np.asarray(opencv_per_view, np.float64).ravel(),
        "sd_rvecs": sde[:, :3], "sd_tvecs": sde[:, 3:],
        "fixed": _fixed_names(flags, n_dist),
        "engine": "bouguet" if flags & _DISABLE_SCHUR else "schur",
        # no prior: OpenCV's s^2 (J^T J)^-1 is both the posterior and the repeatability
        "sd_kind": "repeatability",
        **_convergence(at_solution, criteria),
    }
    if sd_check is not None:
        info["sd_check"] = sd_check
    if scatter is not None:
        info["view_scatter"] = scatter.to_dict() | {"applied": True}
        info["sd_noise_model"] = sd_noise_model
    if notes:
        info["notes"] = notes
    if camera_only:
        info["camera_only"] = True
    elif backend == "opencv" and keystone:  # the object-releasing fit moves the target too
        response = keystone_response(obj, K, dist, rv, tv, flags, n_dist)
        if response is not None:
            info["keystone_response"] = {k: v.tolist() for k, v in response.items()}
    return CalibrationResult(backend, K, dist, sd, rms, per_view, rv, tv, info=info), invalid


# ----------------------------------------------------------------------------------------------
# calibration


def calibrate_opencv(obs: Observations, model: str = "standard", flags: int = 0,
                     fix_aspect: bool = False, *, K_guess: np.ndarray | None = None,
                     dist_guess: Sequence[float] | None = None, criteria=None,
                     min_views: int = 3, camera_only: bool = False,
                     keystone: bool = True) -> CalibrationResult:
    """Calibrate with ``cv2.calibrateCameraExtended`` (target points taken as exact).

    Parameters
    ----------
    obs : Observations
        Object points (board frame, any length unit; mm for parsed targets) and per-view
        detections (px, OpenCV convention).
    model : {'standard', 'rational'}
        5 coefficients ``(k1, k2, p1, p2, k3)`` or 8 (``CALIB_RATIONAL_MODEL``, adds k4..k6).
    flags : int
        Further ``cv2.CALIB_*`` flags (``CALIB_FIX_K3``, ``CALIB_ZERO_TANGENT_DIST``, ...).
        ``CALIB_THIN_PRISM_MODEL`` is refused; bit ``1 << 18`` is taken as
        ``CALIB_DISABLE_SCHUR_COMPLEMENT`` and the sensor tilt is then fixed at zero (see the
        module notes).
    fix_aspect : bool
        Add ``CALIB_FIX_ASPECT_RATIO``: fx / fy stays at 1 (or at ``K_guess``'s ratio).
    K_guess : (3, 3) ndarray, optional
        Initial camera matrix, px; sets ``CALIB_USE_INTRINSIC_GUESS``.
    dist_guess : sequence of float, optional
        Initial distortion, OpenCV order (used with ``K_guess`` or ``CALIB_FIX_K*``).
    criteria : tuple, optional
        OpenCV termination criteria; default :data:`CRITERIA` (``COUNT + EPS, 100, 1e-12``);
        :data:`START_CRITERIA` for a fit that only starts another solve.
    min_views : int
        Fewest views accepted. Two views of a plane give exactly the four constraints that the
        four intrinsics of a zero-skew camera need, leaving nothing to check them by; 3 is the
        default.
    camera_only : bool
        For a caller that uses the camera and the poses alone (a held-out fold, a start): the
        view-scatter check and the keystone response are not computed, so the 1-sigmas are
        the noise model's (still checked), and ``info["camera_only"]`` is True.
    keystone : bool
        False: ``info["keystone_response"]`` is not computed, for a caller that reads the
        camera, its 1-sigmas and the poses alone (a start, a basin's fit).

    Returns
    -------
    CalibrationResult
        ``backend = "opencv"``; ``K`` (3, 3) px; ``dist`` (5,) or (8,); ``sd`` 1-sigma of fx, fy,
        cx, cy and each distortion term by name (0 for a fixed term; with a fixed aspect ratio
        ``sd["fx"] = sd["fy"] * fx / fy``); ``rms_px`` and ``per_view_rms_px`` (m,) as in the
        module notes; ``rvecs, tvecs`` (m, 3) ``Rt_cam_board``. ``info``: ``model``,
        ``flags``/``flag_names`` (as run), ``views`` (names), ``n_points``, ``opencv_rms_px``,
        ``opencv_per_view_rms_px``, ``sd_rvecs``/``sd_tvecs`` (m, 3), ``fixed`` (names of
        parameters held fixed), ``engine``, ``converged``, ``stop_reason``,
        ``convergence_check``, ``sd_kind``, ``sd_invalid`` (module notes).

    Raises
    ------
    ValueError
        Too few views (``min_views``), a view with fewer than 4 points, fewer equations than
        unknowns, or inconsistent options.
    RuntimeError
        If OpenCV fails or diverges, or a camera parameter's 1-sigma is not a number.
    """
    model, flags, n_dist = _check_model(model, flags)
    names = _names(obs)
    _check_views(obs, names, n_dist, min_views, 0, "calibrate_opencv")
    K0, d0, flags = _initial(obs, flags, fix_aspect, K_guess, dist_guess, n_dist)
    obj = [np.asarray(obs.object_points[ids], np.float32) for ids, _ in obs.views]
    img = [np.asarray(pts, np.float32).reshape(-1, 1, 2) for _, pts in obs.views]
    out = _run(cv2.calibrateCameraExtended, "calibrate_opencv", obj, img,
               tuple(int(v) for v in obs.image_size), K0, d0, flags=flags,
               criteria=_criteria(criteria))
    res, invalid = _finish(_Fit("opencv", obj, img, flags, n_dist, model, names,
                                _criteria(criteria)), _Output(*out),
                           None if camera_only else view_groups(obs.views, obs.image_size),
                           np.concatenate([np.asarray(ids) for ids, _ in obs.views]),
                           camera_only, keystone)
    _check_sd(res, invalid, 4 + n_dist)
    return res


def calibrate_opencv_camera(obs: Observations, flags: int = 0, *,
                            K_guess: np.ndarray | None = None,
                            dist_guess: Sequence[float] | None = None, criteria=None
                            ) -> tuple[np.ndarray, np.ndarray]:
    """The camera matrix (3, 3) px and distortion (5,) or (8,) of :func:`calibrate_opencv`'s
    solve (``cv2.calibrateCamera``, the same inputs, criteria and result to the last bit) and
    nothing else: no sigmas, poses nor check that OpenCV reached its minimum. For fits whose
    camera alone is used and judged by its effect elsewhere (the held-out folds of the term
    choice: a fold that stopped short only raises that set's held-out error). ``criteria``
    as in :func:`calibrate_opencv`. Raises as :func:`calibrate_opencv` does, and RuntimeError
    for non-finite intrinsics."""
    _, flags, n_dist = _check_model("standard", flags)
    _check_views(obs, _names(obs), n_dist, 3, 0, "calibrate_opencv_camera")
    K0, d0, flags = _initial(obs, flags, False, K_guess, dist_guess, n_dist)
    obj = [np.asarray(obs.object_points[ids], np.float32) for ids, _ in obs.views]
    img = [np.asarray(pts, np.float32).reshape(-1, 1, 2) for _, pts in obs.views]
    _, K, dist, _, _ = _run(cv2.calibrateCamera, "calibrate_opencv_camera", obj, img,
                            tuple(int(v) for v in obs.image_size), K0, d0, flags=flags,
                            criteria=_criteria(criteria))
    K, dist = np.asarray(K, np.float64).reshape(3, 3), np.asarray(dist, np.float64).ravel()
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise RuntimeError("calibrate_opencv_camera: calibration diverged (non-finite "
                           "intrinsics)")
    return K, dist[:n_dist].copy()


def default_fixed_point(object_points: np.ndarray) -> int:
    """The target point :func:`calibrate_opencv_ro` holds fixed by default.

    OpenCV fixes three things to set the gauge of the released target: point 0 (all three
    coordinates), the chosen point (all three) and the z of the last point. The chosen point is
    the one farthest from the line through the first and last points, so that the three span the
    largest triangle: for a chessboard, the top-right corner OpenCV recommends (ties go to the
    lower index).

    Parameters
    ----------
    object_points : (n, 3) ndarray

    Returns
    -------
    int
        In ``[1, n - 2]``.

    Examples
    --------
    >>> default_fixed_point(parse_pattern("chessboard:9x6:25").object_points)
    8
    """
    p = np.asarray(object_points, np.float64)
    a, b = p[0], p[-1]
    u = (b - a) / max(np.linalg.norm(b - a), 1e-300)
    rel = p[1:-1] - a
    dist = np.linalg.norm(rel - np.outer(rel @ u, u), axis=1)
    best = np.flatnonzero(dist >= dist.max() * (1 - 1e-9))[0]
    return int(best + 1)


def not_a_camera(result: CalibrationResult | np.ndarray, image_size: tuple[int, int]
                 ) -> str | None:
    """Why a calibration (or its camera matrix (3, 3), px) is no camera (None when it is one):
    intrinsics that are not finite, a focal length below a tenth of the image's larger side (a
    field of view over 157 degrees, or a mirrored solution), pixels more than 2:1 from square,
    or a principal point outside the image."""
    K = np.asarray(result.K if isinstance(result, CalibrationResult) else result, float)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w, h = image_size
    if not np.all(np.isfinite([fx, fy, cx, cy])):
        return "intrinsics not finite"
    if min(fx, fy) < 0.1 * max(w, h):
        return f"fx, fy ({fx:.1f}, {fy:.1f}) px below a tenth of the image"
    if not 0.5 < fx / fy < 2.0:
        return f"fx / fy = {fx / fy:.2f}"
    if not (0 <= cx <= w - 1 and 0 <= cy <= h - 1):
        return f"principal point ({cx:.0f}, {cy:.0f}) outside the image"
    return None


def calibrate_opencv_multistart(obs: Observations, model: str = "standard", flags: int = 0,
                                focal_range: tuple[float, float] = (0.5, 32.0), starts: int = 4,
                                camera_only: bool = False, criteria=None
                                ) -> CalibrationResult | None:
    """:func:`calibrate_opencv` from ``starts`` focal lengths log-spaced over ``focal_range``
    times the image's larger side (principal point at the centre and square pixels held for a
    first solve, then freed); the result with the smallest RMS that is a camera
    (:func:`not_a_camera`), or None; ``camera_only`` and ``criteria`` as in
    :func:`calibrate_opencv` (the first solves, with the principal point held, are always
    camera only).

    OpenCV's own start comes from the views' homographies (Zhang's closed form), which is
    ill-posed when the views are nearly fronto-parallel, as at the long end of a zoom: through
    a long-end pincushion of 1.5 % its solve ends at 2-4 times the focal length (k1 taking the
    difference), without distortion at no camera at all (``tests/test_zoomwide.py``).
    """
    w, h = obs.image_size
    best = None
    for focal in max(w, h) * np.geomspace(*focal_range, starts):
        K = np.array([[focal, 0.0, (w - 1) / 2.0], [0.0, focal, (h - 1) / 2.0], [0, 0, 1]])
        try:
            held = calibrate_opencv(obs, model, flags | cv2.CALIB_FIX_PRINCIPAL_POINT,
                                    fix_aspect=True, K_guess=K, camera_only=True,
                                    criteria=criteria)
            result = calibrate_opencv(obs, model, flags, K_guess=held.K, dist_guess=held.dist,
                                      camera_only=camera_only, criteria=criteria)
        except (ValueError, RuntimeError):
            continue
        if not_a_camera(result, obs.image_size) is None and (
                best is None or result.rms_px < best.rms_px):
            best = result
    if best is not None:
        best.info["start"] = "multi-start"
    return best


#: What a per-step OpenCV calibration can hold fixed (``calibrate --fix``), and OpenCV's flag
#: for each: the principal point at the image centre, ``fy / fx`` at 1, a radial term at 0, the
#: tangential terms p1, p2 at 0.
FIXABLE = {"principal-point": cv2.CALIB_FIX_PRINCIPAL_POINT,
           "aspect": cv2.CALIB_FIX_ASPECT_RATIO, "k1": cv2.CALIB_FIX_K1,
           "k2": cv2.CALIB_FIX_K2, "k3": cv2.CALIB_FIX_K3,
           "tangential": cv2.CALIB_ZERO_TANGENT_DIST}


def fix_flags(names) -> int:
    """OpenCV's flags holding ``names`` (keys of :data:`FIXABLE`) fixed; ValueError naming an
    unknown one and the known ones."""
    flags = 0
    for name in names:
        if name not in FIXABLE:
            raise ValueError(f"cannot fix {name!r}; choose from {', '.join(FIXABLE)}")
        flags |= FIXABLE[name]
    return flags


#: Views all tilted less than this from fronto-parallel (degrees) leave OpenCV's own start
#: ill-posed: :func:`calibrate_opencv_robust` then also tries a range of focal lengths (per-step
#: OpenCV, and each step's start in the zoom-wide adjustment).
FRONTO_PARALLEL_DEG = 15.0


def calibrate_opencv_robust(obs: Observations, model: str = "standard", flags: int = 0,
                            fronto_parallel_deg: float | None = None, camera_only: bool = False,
                            criteria=None) -> CalibrationResult:
    """:func:`calibrate_opencv` from OpenCV's own start and also from
    :func:`calibrate_opencv_multistart`: always, or with ``fronto_parallel_deg`` only when the
    first is no camera (:func:`not_a_camera`) or all its views are tilted less than that
    (degrees) from fronto-parallel, where OpenCV's own start is ill-posed. Returns the camera
    with the smallest RMS (``info["start"]``: ``"opencv"`` or ``"multi-start"``); raises what
    OpenCV raised, or ValueError naming why its result is no camera, when no start gives one;
    ``camera_only`` and ``criteria`` as in :func:`calibrate_opencv`.
    """
    from .quality import view_geometry

    try:
        own = calibrate_opencv(obs, model, flags, camera_only=camera_only, criteria=criteria)
        failure = not_a_camera(own, obs.image_size)
    except (ValueError, RuntimeError) as exc:
        own, failure, error = None, str(exc), exc
    candidates = [] if failure else [own]
    if (fronto_parallel_deg is None or failure
            or view_geometry(own, obs).tilt_deg.max() < fronto_parallel_deg):
        candidates += [r for r in [calibrate_opencv_multistart(
            obs, model, flags, camera_only=camera_only, criteria=criteria)] if r]
    if not candidates:
        if own is None:
            raise error
        raise ValueError(f"opencv: no camera from any start ({failure})")
    best = min(candidates, key=lambda r: r.rms_px)
    best.info.setdefault("start", "opencv")
    return best


def calibrate_opencv_ro(obs: Observations, model: str = "standard", flags: int = 0,
                        fix_aspect: bool = False, *, i_fixed_point: int | None = None,
                        K_guess: np.ndarray | None = None,
                        dist_guess: Sequence[float] | None = None, criteria=None,
                        min_views: int = 3) -> CalibrationResult:
    """Calibrate with OpenCV's object-releasing method (``cv2.calibrateCameraROExtended``,
    Strobl & Hirzinger 2011): the target points are refined together with the camera.

    OpenCV needs the same points, in the same order, in every view, so only the views that
    see every target point are used (sorted by id); the others are left out and listed in
    ``info["dropped_views"]``.

    Parameters
    ----------
    obs, model, flags, fix_aspect, K_guess, dist_guess, criteria, min_views
        As in :func:`calibrate_opencv`. With ``CALIB_USE_INTRINSIC_GUESS`` (or ``K_guess``)
        the Bouguet engine is used (``CALIB_DISABLE_SCHUR_COMPLEMENT | CALIB_FIX_TAUX_TAUY``):
        OpenCV 5.0's Schur engine asserts on that combination.
    i_fixed_point : int, optional
        Index of the target point held fixed together with point 0 and the z of the last point
        (OpenCV's gauge), in ``[1, n - 2]``. Default :func:`default_fixed_point`.

    Returns
    -------
    CalibrationResult
        ``backend = "opencv-ro"``; as :func:`calibrate_opencv` for the used views, plus
        ``object_points`` (n, 3), the refined target points in the board frame (the distance
        between point 0 and the fixed point keeps its nominal value, which sets the scale),
        and ``object_points_sd`` (n, 3), their 1-sigma (0 for the fixed coordinates).
        ``info`` adds ``i_fixed_point``, ``dropped_views`` (names), ``full_views_only``
        (an explanation) and ``max_point_shift`` (largest move of a target point from its
        nominal position, same units as the object points).

    Raises
    ------
    ValueError
        Fewer than ``min_views`` full views, too few points, or a bad ``i_fixed_point``.
    RuntimeError
        If OpenCV fails or diverges.
    """
    model, flags, n_dist = _check_model(model, flags)
    names_all = _names(obs)
    n = len(obs.object_points)
    keep, dropped = [], []
    for name, (ids, pts) in zip(names_all, obs.views, strict=True):
        if len(ids) == n and np.array_equal(np.sort(ids), np.arange(n)):
            order = np.argsort(ids)
            keep.append((name, ids[order], pts[order]))
        else:
            dropped.append(name)
    full = Observations(obs.object_points, [(i, p) for _, i, p in keep], obs.image_size,
                        [nm for nm, _, _ in keep])
    if full.n_views < min_views:
        raise ValueError(f"calibrate_opencv_ro: {full.n_views} of {obs.n_views} views see all "
                         f"{n} target points; object releasing needs at least {min_views} "
                         "such views")
    if n < 4:
        raise ValueError(f"calibrate_opencv_ro: the target has {n} points; need at least 4")
    # Released points: 3 n unknowns less the 7 fixed by the gauge.
    _check_views(full, full.names, n_dist, min_views, 3 * n - 7, "calibrate_opencv_ro")
    if i_fixed_point is None:
        i_fixed_point = default_fixed_point(obs.object_points)
    i_fixed_point = int(i_fixed_point)
    if not 1 <= i_fixed_point <= n - 2:
        raise ValueError(f"calibrate_opencv_ro: i_fixed_point {i_fixed_point} outside "
                         f"[1, {n - 2}]")
    K0, d0, flags = _initial(full, flags, fix_aspect, K_guess, dist_guess, n_dist)
    engine_note = None
    if flags & cv2.CALIB_USE_INTRINSIC_GUESS and not flags & _DISABLE_SCHUR:
        flags |= _DISABLE_SCHUR | _FIX_TAU
        engine_note = ("CALIB_USE_INTRINSIC_GUESS: Bouguet engine (CALIB_DISABLE_SCHUR_COMPLEMENT"
                       " | CALIB_FIX_TAUX_TAUY); OpenCV 5.0's Schur engine asserts with RO")
    obj_nominal = np.asarray(obs.object_points, np.float32)
    obj = [obj_nominal] * full.n_views
    img = [np.asarray(pts, np.float32).reshape(-1, 1, 2) for _, pts in full.views]
    out = _run(cv2.calibrateCameraROExtended, "calibrate_opencv_ro", obj, img,
               tuple(int(v) for v in obs.image_size), i_fixed_point, K0, d0, flags=flags,
               criteria=_criteria(criteria))
    rms, K, dist, rvecs, tvecs, new_obj, sdi, sde, sdo, per_view = out
    refined = np.asarray(new_obj, np.float64).reshape(n, 3)
    if not np.all(np.isfinite(refined)):
        raise RuntimeError("calibrate_opencv_ro: refined target points are not finite")
    res, invalid = _finish(_Fit("opencv-ro", [refined] * full.n_views, img, flags, n_dist,
                                model, full.names, _criteria(criteria)),
                           _Output(rms, K, dist, rvecs, tvecs, sdi, sde, per_view))
    res.object_points = refined
    res.object_points_sd = np.asarray(sdo, np.float64).reshape(n, 3)
    invalid += _invalid_sd(res.object_points_sd, [f"point{j}.{a}" for j in range(n)
                                                  for a in "xyz"])
    _check_sd(res, invalid, 4 + n_dist)
    res.info.update({
        "i_fixed_point": i_fixed_point,
        "dropped_views": dropped,
        "full_views_only": (f"object releasing needs every point in every view: used "
                            f"{full.n_views} of {obs.n_views} views"),
        "max_point_shift": float(np.max(np.linalg.norm(refined - obs.object_points, axis=1))),
    })
    if engine_note:
        res.info["engine_note"] = engine_note
    return res
