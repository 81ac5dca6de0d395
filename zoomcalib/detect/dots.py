"""The bias of dot centres: the centre of an imaged circle is not the image of its centre.

Under perspective a circle images as an ellipse whose centre is displaced from the projection of
the circle's centre towards the vanishing line; lens distortion bends the ellipse and moves its
centre again. Given the camera mapping and the board pose, both effects are computed together by
imaging the circle's rim (a dense polygon), taking the centre of the imaged shape as a fit of a
blurred disc would see it (the area centroid), and subtracting the mapped circle centre:

    bias = centroid(map(R c_rim + t)) - map(R c + t)

The detector's dot centre minus this bias estimates the image of the circle's centre. The camera
and pose come from a first calibration; the correction is then iterated with the calibration.

References
----------
J. Heikkilä, "Geometric camera calibration using circular control points", IEEE TPAMI 22(10),
2000 (the perspective bias of circle centres and its correction).
"""

from __future__ import annotations

import numpy as np

__all__ = ["dot_centre_bias", "polygon_centroid"]


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid of closed polygons.

    Parameters
    ----------
    poly : (..., N, 2) ndarray
        Vertices in order (the last joins the first).

    Returns
    -------
    centroid : (..., 2) ndarray

    Examples
    --------
    >>> polygon_centroid(np.array([[0, 0], [2, 0], [2, 2], [0, 2.0]]))
    array([1., 1.])
    """
    x, y = poly[..., 0], poly[..., 1]
    xn, yn = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum(-1)
    cx = ((x + xn) * cross).sum(-1) / (6 * area)
    cy = ((y + yn) * cross).sum(-1) / (6 * area)
    return np.stack([cx, cy], -1)


def dot_centre_bias(project, R: np.ndarray, t: np.ndarray, centres: np.ndarray, radius: float,
                    n_rim: int = 256) -> np.ndarray:
    """Offset of each imaged dot's centre from the image of the dot's centre, px.

    Parameters
    ----------
    project : callable
        (M, 2) normalised camera coordinates -> (M, 2) pixels (a camera model or the exact lens).
    R, t : (3, 3), (3,) ndarray
        ``Rt_cam_board``.
    centres : (n, 2) or (n, 3) ndarray
        Dot centres on the board, board frame (z = 0 if only x, y are given).
    radius : float
        Dot radius, board units.
    n_rim : int
        Rim vertices per dot.

    Returns
    -------
    bias : (n, 2) ndarray
        ``centroid of the imaged dot - image of its centre``, px.
    """
    c = np.asarray(centres, dtype=float)
    if c.shape[-1] == 2:
        c = np.concatenate([c, np.zeros((len(c), 1))], axis=1)
    phi = np.linspace(0, 2 * np.pi, n_rim, endpoint=False)
    rim = c[:, None, :] + radius * np.stack([np.cos(phi), np.sin(phi), 0 * phi], -1)
    pts = np.concatenate([rim, c[:, None, :]], axis=1) @ R.T + t  # shape (n, n_rim + 1, 3)
    uv = project((pts[..., :2] / pts[..., 2:3]).reshape(-1, 2)).reshape(len(c), n_rim + 1, 2)
    # The polygon under-estimates the curved rim by O(1/n_rim^2) symmetrically; its centroid
    # converges fast.
    return polygon_centroid(uv[:, :n_rim]) - uv[:, n_rim]
