"""Calibration inputs and results shared by every backend.

Pixels follow OpenCV's convention (centre of the top-left pixel = (0, 0)); distortion coefficients
are in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])``; poses ``rvec, tvec`` map board to camera
coordinates (``Rt_cam_board``), in the units of the object points (mm unless stated).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import cv2
import numpy as np

__all__ = ["Observations", "CalibrationResult", "DIST_NAMES", "one_opencv_thread",
           "residual_vectors"]

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass
class Observations:
    """Detected target points of one calibration set.

    Attributes
    ----------
    object_points : (n, 3) ndarray
        The target's points in its own frame (z = 0 for a flat board).
    views : list of (ids (k,) int ndarray, points (k, 2) ndarray)
        Per view: which object points were seen and where, px.
    image_size : (int, int)
        (width, height), px.
    names : list of str
        One name per view (image file).
    n_fallback : int
        Detected points left out because their refinement fell back to the initial detector.
    """

    object_points: np.ndarray
    views: list[tuple[np.ndarray, np.ndarray]]
    image_size: tuple[int, int]
    names: list[str] = field(default_factory=list)
    n_fallback: int = 0

    @property
    def n_views(self) -> int:
        return len(self.views)

    @property
    def n_observations(self) -> int:
        return int(sum(len(ids) for ids, _ in self.views))

    def subset(self, views) -> Observations:
        """The views of index ``views`` (in that order), with their names, on the same board
        and image size (``n_fallback`` 0: the count is the whole set's, not per view)."""
        views = [int(v) for v in views]
        return Observations(self.object_points, [self.views[v] for v in views], self.image_size,
                            [self.names[v] for v in views] if self.names else [])


@dataclass
class CalibrationResult:
    """One backend's calibration of one image set.

    Attributes
    ----------
    backend : str
        ``'opencv'``, ``'opencv-ro'`` or ``'bundle'``.
    K : (3, 3) ndarray
    dist : (5,) or (8,) ndarray
        OpenCV order.
    sd : dict of str to float
        1-sigma of ``fx, fy, cx, cy`` and of each distortion term (by name, ``DIST_NAMES``).
    rms_px : float
        Root-mean-square reprojection error over the inlier observations.
    per_view_rms_px : (m,) ndarray
    rvecs, tvecs : (m, 3) ndarray
        ``Rt_cam_board`` per view.
    rejected : list of (int, int)
        (view index, object point id) of observations rejected as outliers.
    object_points : (n, 3) ndarray or None
        Refined target points (target-releasing backends), else None.
    object_points_sd : (n, 3) ndarray or None
        Their 1-sigma.
    info : dict
        Backend-specific extras (iterations, flatness, gauge, ...). Every backend sets
        ``converged`` (bool), ``stop_reason`` (str: ``'tolerance'`` when converged, else e.g.
        ``'iteration cap'``, ``'damping limit'``) and ``sd_kind`` (``'repeatability'``: the
        spread of the estimate over noise draws, which ``sd`` and the backend's other
        1-sigmas are).
    """

    backend: str
    K: np.ndarray
    dist: np.ndarray
    sd: dict[str, float]
    rms_px: float
    per_view_rms_px: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    rejected: list[tuple[int, int]] = field(default_factory=list)
    object_points: np.ndarray | None = None
    object_points_sd: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def converged(self) -> bool:
        """True when the backend's solver reported convergence (``info['converged']``); False
        when it stopped short (``info['stop_reason']`` says why) or did not report."""
        return bool(self.info.get("converged", False))

    def to_dict(self) -> dict:
        """The ``calibration.json`` entry of this backend (docs/conventions.md)."""
        d = {"K": self.K.tolist(), "dist": [float(v) for v in self.dist],
             "sd": {k: float(v) for k, v in self.sd.items()}, "rms_px": float(self.rms_px),
             "per_view_rms_px": [float(v) for v in self.per_view_rms_px],
             "rejected": [[int(a), int(b)] for a, b in self.rejected],
             "n_views": int(len(self.per_view_rms_px)), "converged": self.converged}
        if self.object_points is not None:
            d["object_points"] = self.object_points.tolist()
        if self.object_points_sd is not None:
            d["object_points_sd"] = self.object_points_sd.tolist()
        d["info"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                     for k, v in self.info.items()}
        return d


@contextlib.contextmanager
def one_opencv_thread():
    """Run OpenCV on one thread inside the block: its parallel sums make calibrateCamera's
    result differ in the last digits from run to run, and a rerun must give the
    same files."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def residual_vectors(result: CalibrationResult, obs: Observations) -> list[np.ndarray]:
    """Per view, ``(k, 2)`` reprojection residuals (projected minus observed), px."""
    obj = obs.object_points if result.object_points is None else result.object_points
    out = []
    for (ids, pts), r, t in zip(obs.views, result.rvecs, result.tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj[ids].astype(np.float64), np.asarray(r, float),
                                    np.asarray(t, float), result.K, result.dist)
        out.append(proj.reshape(-1, 2) - pts)
    return out
