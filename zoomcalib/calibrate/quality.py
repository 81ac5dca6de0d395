r"""What a calibration's views constrain, and how well it projects: the numbers of the report.

Conventions: pixels in OpenCV's convention (centre of the top-left pixel = (0, 0), x right,
y down); poses ``Rt_cam_board`` in the units of the object points (mm); angles in degrees.

Geometry of the views (:func:`view_geometry`): a view's *tilt* is the angle between the board's
normal and the optical axis (0 = fronto-parallel); its *distance* the range from the camera
centre to the centre of the board's points.

Coverage verdict (:func:`coverage_verdict`), thresholds in the module constants:

* every view tilted less than :data:`MIN_TILT_DEG` (10 deg): near fronto-parallel views leave
  the focal length and the principal point traded against the board's distance and position;
* no detected point beyond :data:`MIN_REACH` (70 %) of the half-diagonal from the image centre:
  the distortion is extrapolated in the outer region;
* fewer than :data:`MIN_CELLS` (60 %) of the :data:`GRID` x :data:`GRID` (5 x 5) cells of the
  image hold a point, or a corner cell of that grid holds none: the distortion and the
  principal point rest on part of the field only;
* the farthest view less than :data:`MIN_DISTANCE_RATIO` (1.1) times the nearest: one distance
  only (said, not a failure: it weakens the separation of focal length and distance).

Projection uncertainty (:func:`projection_uncertainty`, mrcal's headline figure): the pixel
``q`` is unprojected with the fitted intrinsics to the point ``p`` at range ``d`` on its ray;
``p`` is carried into every board's frame with that view's fitted pose. A perturbed solution
(intrinsics ``theta + dtheta``, poses ``pose_i + dpose_i``) brings the points back to the camera
frame with its own poses, averages them and projects the mean with its intrinsics, ``q'``. To
first order

.. math::

    dq = A\,d\theta + \frac{1}{N}\sum_i P\,\frac{\partial(R_i x_i + t_i)}{\partial pose_i}
    \,dpose_i = A\,d\theta + \sum_i M_i\,dpose_i,

``A = dq/dtheta``, ``P = dq/dp``. Of the fit's normal equations (observations weighted equally,
the board held as the result has it) with blocks ``V_i = J_{p,i}^T J_{p,i}``,
``W_i = J_{theta,i}^T J_{p,i}``, the poses follow the intrinsics as ``dpose_i = R_i dtheta +
e_i``, ``R_i = -V_i^{-1} W_i^T``, ``e_i ~ N(0, s^2 V_i^{-1})``, with ``s^2`` the residual
variance per coordinate. Hence

.. math::

    \mathrm{cov}(q) = G\,\Sigma_\theta\,G^T + s^2 \sum_i M_i V_i^{-1} M_i^T,\qquad
    G = A + \sum_i M_i R_i,

with ``Sigma_theta`` the backend's covariance of the free intrinsics: the reported 1-sigmas
(``CalibrationResult.sd``) with the correlations the backend reports
(``info['correlation']``, the zoom-wide adjustment's posterior, which includes what a step
borrows from its neighbours), else the correlations of ``s^2 (J^T J)^{-1}`` with the poses
marginalised. The figure shows the worst direction's 1-sigma, the square root of the larger
eigenvalue of ``cov(q)``, px.

Cross-validation difference (:func:`projection_difference`): each pixel unprojected with one
half's intrinsics and projected with the other's, ``|q_b - q|`` px, no rotation compensated (a
principal-point difference shows as a shift).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .bundleproblem import scaled_inverse
from .result import DIST_NAMES, CalibrationResult, Observations

__all__ = ["ViewGeometry", "view_geometry", "coverage_verdict", "intrinsic_names",
           "residual_pattern", "PATTERN_SHARE", "ELONGATION", "distortion_map", "board_outlines",
           "intrinsics_covariance", "view_information", "projection_uncertainty", "projection_z",
           "projection_difference",
           "pixel_grid", "observed_region", "MIN_TILT_DEG", "MIN_REACH", "MIN_CELLS", "GRID",
           "MIN_DISTANCE_RATIO"]

#: Largest view tilt (deg) below which the views are called fronto-parallel.
MIN_TILT_DEG = 10.0
#: Fraction of the half-diagonal the detected points must reach from the image centre.
MIN_REACH = 0.7
#: Fraction of the GRID x GRID cells that must hold a detected point.
MIN_CELLS = 0.6
#: Cells per side of the coverage grid.
GRID = 5
#: Ratio of the farthest to the nearest view distance below which all views are at one distance.
MIN_DISTANCE_RATIO = 1.1


@dataclass
class ViewGeometry:
    """Per view: ``tilt_deg`` (m,), ``distance`` (m,) in object-point units (mm)."""

    tilt_deg: np.ndarray
    distance: np.ndarray


def view_geometry(result: CalibrationResult, obs: Observations) -> ViewGeometry:
    """Tilt and distance of every view of ``result`` (module docstring)."""
    obj = obs.object_points if result.object_points is None else result.object_points
    centre = np.asarray(obj, float).mean(axis=0)
    rot = np.array([cv2.Rodrigues(np.asarray(r, float).reshape(3, 1))[0] for r in result.rvecs])
    normal_z = np.abs(rot[:, 2, 2])  # z of the board normal in the camera frame
    tilt = np.degrees(np.arccos(np.clip(normal_z, 0.0, 1.0)))
    board_centre = rot @ centre + np.asarray(result.tvecs, float)
    return ViewGeometry(tilt, np.linalg.norm(board_centre, axis=1))


def _coverage_numbers(points: np.ndarray, image_size: tuple[int, int]) -> tuple[float, float,
                                                                                 bool]:
    """Reach (fraction of the half-diagonal), fraction of grid cells hit, all corner cells
    hit, of the detected points ``(n, 2)`` px."""
    w, h = image_size
    half_diagonal = 0.5 * float(np.hypot(w - 1, h - 1))
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    reach = float(np.linalg.norm(points - centre, axis=1).max(initial=0.0)) / half_diagonal
    col = np.clip((points[:, 0] / w * GRID).astype(int), 0, GRID - 1)
    row = np.clip((points[:, 1] / h * GRID).astype(int), 0, GRID - 1)
    hit = np.zeros((GRID, GRID), bool)
    hit[row, col] = True
    corners = hit[0, 0] and hit[0, -1] and hit[-1, 0] and hit[-1, -1]
    return reach, float(hit.mean()), bool(corners)


def coverage_verdict(points: np.ndarray, image_size: tuple[int, int], geometry: ViewGeometry
                     ) -> tuple[list[str], str]:
    """Plain-words verdict on what the views constrain (module docstring, thresholds).

    Parameters
    ----------
    points : (n, 2) ndarray
        Every detected point of the step, px.
    image_size : (int, int)
        (width, height), px.
    geometry : ViewGeometry

    Returns
    -------
    problems : list of str
        One sentence per check that failed (empty: none).
    summary : str
        The measured numbers the checks used.
    """
    reach, cells, corners = _coverage_numbers(np.asarray(points, float).reshape(-1, 2),
                                              image_size)
    tilt_max = float(geometry.tilt_deg.max(initial=0.0))
    ratio = float(geometry.distance.max() / geometry.distance.min()) if len(
        geometry.distance) else 1.0
    problems = []
    if tilt_max < MIN_TILT_DEG:
        problems.append(f"all views within {MIN_TILT_DEG:g} deg of fronto-parallel (largest "
                        f"tilt {tilt_max:.1f} deg): the focal length and the principal point "
                        "are traded against the board's distance and position")
    if reach < MIN_REACH:
        problems.append(f"no point beyond {100 * reach:.0f} % of the half-diagonal from the "
                        f"image centre (needed: {100 * MIN_REACH:.0f} %): the distortion is "
                        "extrapolated in the outer region")
    if cells < MIN_CELLS or not corners:
        where = "" if corners else "; a corner of the image has no point"
        problems.append(f"points in {100 * cells:.0f} % of the {GRID}x{GRID} image cells "
                        f"(needed: {100 * MIN_CELLS:.0f} %){where}: the distortion and the "
                        "principal point rest on part of the field")
    if ratio < MIN_DISTANCE_RATIO:
        problems.append(f"all views at one distance (farthest / nearest = {ratio:.2f} < "
                        f"{MIN_DISTANCE_RATIO:g})")
    summary = (f"largest tilt {tilt_max:.1f} deg, distances {geometry.distance.min():.0f}-"
               f"{geometry.distance.max():.0f} mm, points reach {100 * reach:.0f} % of the "
               f"half-diagonal and fill {100 * cells:.0f} % of the {GRID}x{GRID} cells")
    return problems, summary


def intrinsic_names(result: CalibrationResult) -> list[str]:
    """``fx, fy, cx, cy`` and the distortion terms of ``result``, in OpenCV's order."""
    return ["fx", "fy", "cx", "cy", *DIST_NAMES[:len(result.dist)]]


def _free(result: CalibrationResult) -> np.ndarray:
    """Indices (into :func:`intrinsic_names`) of the intrinsics the fit estimated: those with a
    positive, finite 1-sigma."""
    sd = np.array([result.sd.get(n, np.nan) for n in intrinsic_names(result)], float)
    return np.flatnonzero(np.isfinite(sd) & (sd > 0))


@dataclass
class _FitBlocks:
    """Normal-equation blocks of the fit: ``V`` (N, 6, 6), ``W`` (N, k, 6), ``S`` (k, k)
    (the Schur complement, poses marginalised), ``s2`` residual variance per coordinate."""

    V: np.ndarray
    W: np.ndarray
    S: np.ndarray
    s2: float


def _fit_blocks(result: CalibrationResult, obs: Observations, free: np.ndarray) -> _FitBlocks:
    obj = np.asarray(obs.object_points if result.object_points is None
                     else result.object_points, np.float64)
    rejected = {(int(v), int(p)) for v, p in result.rejected}
    V, W, U = [], [], np.zeros((len(free), len(free)))
    sq, n_obs = 0.0, 0
    for v, ((ids, pts), r, t) in enumerate(zip(obs.views, result.rvecs, result.tvecs,
                                               strict=True)):
        keep = np.array([(v, int(i)) not in rejected for i in ids], bool)
        uv, jac = cv2.projectPoints(obj[ids[keep]], np.asarray(r, float), np.asarray(t, float),
                                    result.K, result.dist)
        jp, jt = jac[:, :6], jac[:, 6:][:, free]
        V.append(jp.T @ jp)
        W.append(jt.T @ jp)
        U += jt.T @ jt
        sq += float(np.sum((uv.reshape(-1, 2) - pts[keep]) ** 2))
        n_obs += 2 * int(keep.sum())
    V, W = np.array(V), np.array(W)
    S = U - np.einsum("vki,vij,vlj->kl", W, np.linalg.inv(V), W)
    dof = max(n_obs - len(free) - 6 * len(V), 1)
    return _FitBlocks(V, W, S, sq / dof)


def view_information(result: CalibrationResult, obs: Observations
                     ) -> tuple[list[str], np.ndarray, np.ndarray, float]:
    """What the step's own views tell about its free intrinsics under the noise model: their
    names, their indices into :func:`intrinsic_names` (the columns of ``cv2.projectPoints``'
    Jacobian after the six pose columns), the Schur complement ``S`` (poses marginalised,
    unit noise) and the residual variance per coordinate ``s2`` (px^2); the noise model's
    covariance is ``s2 S^-1``."""
    free = _free(result)
    blocks = _fit_blocks(result, obs, free)
    return [intrinsic_names(result)[i] for i in free], free, blocks.S, blocks.s2


def intrinsics_covariance(result: CalibrationResult, obs: Observations,
                          blocks: _FitBlocks | None = None) -> tuple[list[str], np.ndarray]:
    """Covariance of the free intrinsics (module docstring: the backend's 1-sigmas with its
    correlations, else the fit's), and their names. Units: px for fx, fy, cx, cy; OpenCV's
    normalised units for the distortion terms."""
    free = _free(result)
    names = [intrinsic_names(result)[i] for i in free]
    sd = np.array([result.sd[n] for n in names])
    corr = _reported_correlation(result, names)
    if corr is None:
        blocks = blocks or _fit_blocks(result, obs, free)
        cov, _ = scaled_inverse(blocks.S)
        d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
        corr = cov / np.outer(d, d)
    return names, corr * np.outer(sd, sd)


def _reported_correlation(result: CalibrationResult, names: list[str]) -> np.ndarray | None:
    corr, reported = result.info.get("correlation"), result.info.get("correlation_names")
    if corr is None or not reported or not set(names) <= set(reported):
        return None
    idx = [list(reported).index(n) for n in names]
    return np.asarray(corr, float)[np.ix_(idx, idx)]


def pixel_grid(image_size: tuple[int, int], columns: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres of a grid over the image: ``xs`` (columns,), ``ys`` (rows,), px, rows
    chosen for square cells."""
    w, h = image_size
    rows = max(2, int(round(columns * h / w)))
    return np.linspace(0.0, w - 1.0, columns), np.linspace(0.0, h - 1.0, rows)


def _rays(K: np.ndarray, dist: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Unit rays (n, 3), camera frame, of the pixels ``q`` (n, 2)."""
    xy = cv2.undistortPoints(q.reshape(-1, 1, 2).astype(np.float64), K, dist).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def projection_uncertainty(result: CalibrationResult, obs: Observations, distance: float,
                           columns: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Worst-direction 1-sigma of the projection of points at range ``distance`` (object-point
    units, mm) over the image (module docstring).

    Returns
    -------
    xs (C,), ys (R,) : ndarray
        Pixel grid, px.
    sigma : (R, C) ndarray
        1-sigma, px.
    """
    xs, ys = pixel_grid(obs.image_size, columns)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    cov_q = _projection_covariance(result, obs, distance, q)
    return xs, ys, _largest_sd(cov_q).reshape(len(ys), len(xs))


def _projection_covariance(result: CalibrationResult, obs: Observations, distance: float,
                           q: np.ndarray) -> np.ndarray:
    """``cov(q)`` (n, 2, 2), px^2, of the projection of the points at range ``distance`` on the
    rays of the pixels ``q`` (n, 2) (module docstring)."""
    free = _free(result)
    blocks = _fit_blocks(result, obs, free)
    _, cov_theta = intrinsics_covariance(result, obs, blocks)
    p_cam = distance * _rays(result.K, result.dist, q)
    _, jac = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), result.K, result.dist)
    jac = jac.reshape(-1, 2, jac.shape[1])
    A, P = jac[:, :, 6:][:, :, free], jac[:, :, 3:6]
    G = A.copy()
    pose_var = np.zeros((len(q), 2, 2))
    n_views = len(blocks.V)
    for i, (r, t) in enumerate(zip(result.rvecs, result.tvecs, strict=True)):
        M = _pose_gradient(P, p_cam, np.asarray(r, float), np.asarray(t, float)) / n_views
        V_inv = np.linalg.inv(blocks.V[i])
        G += M @ (-V_inv @ blocks.W[i].T)
        pose_var += blocks.s2 * M @ V_inv @ np.swapaxes(M, 1, 2)
    return G @ cov_theta @ np.swapaxes(G, 1, 2) + pose_var


def _pose_gradient(P: np.ndarray, p_cam: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
                   ) -> np.ndarray:
    """``P d(R x + t)/d(rvec, tvec)`` (n, 2, 6) at the board-frame points ``x`` of ``p_cam``."""
    R, dR = cv2.Rodrigues(rvec.reshape(3, 1))
    x = (p_cam - tvec) @ R  # R^T (p - t), row-wise
    d_rot = np.einsum("kab,nb->nak", dR.reshape(3, 3, 3), x)  # (n, 3, 3): d(R x)/d rvec_k
    d_pose = np.concatenate([d_rot, np.broadcast_to(np.eye(3), d_rot.shape)], axis=2)
    return P @ d_pose


def _largest_sd(cov: np.ndarray) -> np.ndarray:
    """Square root of the larger eigenvalue of each 2x2 covariance (n, 2, 2)."""
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    half_trace = 0.5 * (a + c)
    return np.sqrt(half_trace + np.sqrt(np.maximum((0.5 * (a - c)) ** 2 + b * b, 0.0)))


def observed_region(points: np.ndarray, xs: np.ndarray, ys: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull ``(k, 2)`` px of the detected ``points`` (n, 2) and which cells of the grid
    ``xs`` x ``ys`` lie inside it, ``(R, C)`` bool: where the calibration saw the target (the
    rest of a map is extrapolated)."""
    hull = cv2.convexHull(np.asarray(points, np.float32).reshape(-1, 1, 2)).reshape(-1, 2)
    hull = hull.astype(np.float64)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    edge = np.roll(hull, -1, axis=0) - hull  # (k, 2)
    rel = q[:, None, :] - hull[None, :, :]  # (n, k, 2)
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    return hull, inside.reshape(len(ys), len(xs))


def projection_z(a: CalibrationResult, obs_a: Observations, b: CalibrationResult,
                 obs_b: Observations, columns: int = 40
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The halves' projection difference in its own uncertainty over the image.

    Each pixel ``q`` is unprojected with ``a``'s intrinsics and that ray projected with
    ``b``'s, ``d = q_b - q`` (:func:`projection_difference`). To first order ``d = A (theta_b -
    theta_a)`` with ``A = dq / dtheta`` on that ray (the ray held in the camera frame, as the
    map holds it: no rotation compensated), so its covariance is ``A (Sigma_a + Sigma_b)
    A^T`` with each half's intrinsics covariance (:func:`intrinsics_covariance`), and
    ``z = sqrt(d^T (A (Sigma_a + Sigma_b) A^T)^-1 d / 2)``: its square has mean 1 at every pixel
    when the halves see one camera and their sigmas are honest (``2 z^2`` is chi-square with 2
    degrees of freedom).

    Returns ``xs`` (C,), ``ys`` (R,), ``z`` (R, C) and the difference ``|d|`` (R, C), px.
    """
    xs, ys = pixel_grid(obs_a.image_size, columns)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    rays = _rays(a.K, a.dist, q)
    qb, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), b.K, b.dist)
    d = qb.reshape(-1, 2) - q
    cov = np.zeros((len(q), 2, 2))
    for r, o in ((a, obs_a), (b, obs_b)):
        free = _free(r)
        _, cov_theta = intrinsics_covariance(r, o)
        _, jac = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), r.K, r.dist)
        A = jac.reshape(len(q), 2, -1)[:, :, 6:][:, :, free]
        cov += A @ cov_theta @ np.swapaxes(A, 1, 2)
    chi2 = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[:, :, None])[:, :, 0])
    shape = (len(ys), len(xs))
    return xs, ys, np.sqrt(np.maximum(chi2, 0.0) / 2.0).reshape(shape), \
        np.linalg.norm(d, axis=1).reshape(shape)


def projection_difference(a: CalibrationResult, b: CalibrationResult,
                          image_size: tuple[int, int], columns: int = 40
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``|q_b - q|`` px over the image: each pixel ``q`` unprojected with ``a``'s intrinsics,
    projected with ``b``'s (module docstring). Returns ``xs``, ``ys`` and the (R, C) map."""
    xs, ys = pixel_grid(image_size, columns)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    qb, _ = cv2.projectPoints(_rays(a.K, a.dist, q), np.zeros(3), np.zeros(3), b.K, b.dist)
    return xs, ys, np.linalg.norm(qb.reshape(-1, 2) - q, axis=1).reshape(len(ys), len(xs))


#: Share of the residuals' mean square a pattern must explain to be named.
PATTERN_SHARE = 0.10
#: Ratio of the residual cloud's largest to smallest sd beyond which it is called elongated.
ELONGATION = 1.5


def residual_pattern(points: np.ndarray, residuals: np.ndarray, centre: np.ndarray,
                     view: np.ndarray | None = None) -> tuple[str, dict[str, float]]:
    """What the residuals of a fit show, in words, and the numbers behind it.

    ``points`` (n, 2) px where the corners were, ``residuals`` (n, 2) px (inliers), ``centre``
    (2,) px the principal point. Three tests, each the share of the residuals' mean square
    ``mean |e|^2`` it explains:

    - ``radial``: the residuals' component along the ray from ``centre``, fitted by
      ``a rho + b rho^2 + c rho^3`` (``rho`` the radius over the largest radius): a distortion
      the lens model misses;
    - ``smooth``: each component fitted by a quadratic in the image coordinates (6 terms): a
      board shape or a lens error smooth over the image; with ``view`` (n,) the view of each
      residual, the quadratic is fitted view by view (views of 12 points or more), so an
      error smooth within each view but different between views (a camera or a board that
      moved, a focal length of the view's own) counts too;
    - ``elongation``: the ratio of the residual cloud's largest to smallest sd (no share).

    The words name the first of radial, smooth and elongated that reaches
    :data:`PATTERN_SHARE` (or :data:`ELONGATION`), else "a round cloud, no pattern". With n
    points and k terms a fit to pure noise explains about ``k / n`` (1 % at 600 points).
    """
    p = np.asarray(points, float).reshape(-1, 2)
    e = np.asarray(residuals, float).reshape(-1, 2)
    ms = float(np.mean(np.sum(e**2, axis=1)))
    numbers = {"radial": 0.0, "smooth": 0.0, "elongation": 1.0, "points": float(len(e))}
    if len(e) < 12 or ms <= 0:
        return "too few residuals to tell a pattern", numbers
    d = p - np.asarray(centre, float)
    radius = np.linalg.norm(d, axis=1)
    rho = radius / max(radius.max(), 1e-12)
    unit = d / np.maximum(radius, 1e-12)[:, None]
    along = np.sum(e * unit, axis=1)
    basis = np.column_stack([rho, rho**2, rho**3])
    fit = basis @ np.linalg.lstsq(basis, along, rcond=None)[0]
    numbers["radial"] = float(np.sum(fit**2) / len(e) / ms)
    groups = np.zeros(len(e), int) if view is None else np.asarray(view)
    explained = 0.0
    for g in np.unique(groups):
        on = groups == g
        if on.sum() < 12:
            continue
        x, y = ((p[on] - p[on].mean(axis=0)) / np.maximum(p[on].std(axis=0), 1e-12)).T
        quad = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
        explained += float(np.sum((quad @ np.linalg.lstsq(quad, e[on], rcond=None)[0]) ** 2))
    numbers["smooth"] = explained / len(e) / ms
    sd = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(e.T)), 1e-300))
    numbers["elongation"] = float(sd[-1] / sd[0])
    shares = f"radial {numbers['radial']:.0%}, smooth {numbers['smooth']:.0%}"
    if numbers["radial"] >= PATTERN_SHARE:
        return (f"a radial pattern: {numbers['radial']:.0%} of the mean square follows the "
                "radius (a distortion the model misses)"), numbers
    if numbers["smooth"] >= PATTERN_SHARE:
        where = "over the image" if view is None else "within each view"
        return (f"a smooth field: {numbers['smooth']:.0%} of the mean square is smooth {where} "
                "(a board, lens or view error the model misses)"), numbers
    if numbers["elongation"] >= ELONGATION:
        return (f"an elongated cloud: sd {numbers['elongation']:.1f}x larger along one "
                f"direction ({shares})"), numbers
    return f"a round cloud, no pattern ({shares} of the mean square)", numbers


def distortion_map(result: CalibrationResult, image_size: tuple[int, int], columns: int = 40
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far the lens's distortion moves each pixel: the pixel grid of :func:`pixel_grid`
    ``xs`` (C,), ``ys`` (R,) and, per grid point, the distance (px) between the pixel and where
    its ray would image without distortion (the same camera matrix), (R, C)."""
    xs, ys = pixel_grid(image_size, columns)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    rays = _rays(result.K, result.dist, q)
    straight = (rays[:, :2] / rays[:, 2:3]) @ result.K[:2, :2].T + result.K[:2, 2]
    return xs, ys, np.linalg.norm(straight - q, axis=1).reshape(len(ys), len(xs))


def board_outlines(result: CalibrationResult, board: np.ndarray) -> np.ndarray:
    """Each view's board outline in the camera frame (views, 5, 3), the units of ``board``
    (n, 3): the corners of the points' bounding rectangle in the board plane, closed, carried
    by the view's pose ``Rt_cam_board``."""
    lo, hi = board[:, :2].min(axis=0), board[:, :2].max(axis=0)
    corners = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0],
                        [lo[0], hi[1], 0], [lo[0], lo[1], 0]], float)
    out = []
    for rvec, tvec in zip(result.rvecs, result.tvecs, strict=True):
        R = cv2.Rodrigues(np.asarray(rvec, float))[0]
        out.append(corners @ R.T + np.asarray(tvec, float))
    return np.array(out).reshape(-1, 5, 3)
