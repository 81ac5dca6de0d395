"""Calibration targets: chessboard, symmetric and asymmetric circle grids, ChArUco.

A target is a flat board in its own frame: x along the board's columns, y along its rows, z = 0,
millimetres. Its *object points* are the points a detector reports (inner chessboard corners,
circle centres, ChArUco inner corners), ordered as OpenCV orders them, so ``ids`` index
``object_points``. Its *appearance* is what a renderer paints: dark polygons and dark discs on a
white board.

Pattern specs (command line): ``chessboard:COLSxROWS:SQUARE`` (inner corners, square in mm),
``circles:COLSxROWS:SPACING``, ``acircles:COLSxROWS:SPACING`` (OpenCV's asymmetric count),
``charuco:SQUARESXxSQUARESY:SQUARE:MARKER:DICT``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Target", "parse_pattern", "PatternError", "write_printable"]


class PatternError(ValueError):
    """A pattern spec that cannot be parsed."""


@dataclass
class Target:
    """A planar calibration target.

    Attributes
    ----------
    kind : {'chessboard', 'circles', 'acircles', 'charuco'}
    spec : str
        The pattern spec it was made from.
    object_points : (n, 3) ndarray
        Detectable points in the board frame, mm (z = 0), OpenCV's order.
    pattern_size : (int, int)
        (columns, rows) as OpenCV's detectors take it (inner corners, or circles).
    pitch_mm : float
        Square size or circle spacing, mm.
    polygons : list of (K, 2) ndarray
        Dark convex polygons (board frame, mm, counter-clockwise).
    discs : (M, 3) ndarray
        Dark discs: centre x, y and radius, mm.
    extent_mm : (4,) ndarray
        The white board: xmin, ymin, xmax, ymax, mm.
    dictionary : str or None
        ArUco dictionary name for ChArUco.
    """

    kind: str
    spec: str
    object_points: np.ndarray
    pattern_size: tuple[int, int]
    pitch_mm: float
    polygons: list[np.ndarray] = field(default_factory=list)
    discs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extent_mm: np.ndarray = field(default_factory=lambda: np.zeros(4))
    dictionary: str | None = None
    marker_mm: float | None = None
    squares: tuple[int, int] | None = None

    @property
    def n_points(self) -> int:
        return len(self.object_points)

    @property
    def size_mm(self) -> np.ndarray:
        """(2,) width and height of the board, mm."""
        return self.extent_mm[2:] - self.extent_mm[:2]

    def scaled(self, factor: float) -> Target:
        """The same pattern with every length multiplied by ``factor``."""
        spec_parts = self.spec.split(":")
        for i in range(2, len(spec_parts)):
            try:
                spec_parts[i] = f"{float(spec_parts[i]) * factor:g}"
            except ValueError:
                pass
        return Target(self.kind, ":".join(spec_parts), self.object_points * factor,
                      self.pattern_size, self.pitch_mm * factor,
                      [p * factor for p in self.polygons], self.discs * factor,
                      self.extent_mm * factor, self.dictionary,
                      None if self.marker_mm is None else self.marker_mm * factor, self.squares)


def _square(x0: float, y0: float, s: float) -> np.ndarray:
    return np.array([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]])


def _grid_size(text: str, spec: str) -> tuple[int, int]:
    try:
        c, r = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise PatternError(f"pattern {spec!r}: size must be COLSxROWS, got {text!r}") from None
    if c < 2 or r < 2:
        raise PatternError(f"pattern {spec!r}: need at least 2x2, got {text!r}")
    return c, r


def _length(text: str, spec: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise PatternError(f"pattern {spec!r}: {what} must be a number in mm, got {text!r}") \
            from None
    if not np.isfinite(v) or v <= 0:
        raise PatternError(f"pattern {spec!r}: {what} must be positive, got {text!r}")
    return v


def chessboard(cols: int, rows: int, square: float, spec: str = "") -> Target:
    """Chessboard with ``cols x rows`` inner corners and a one-square border of squares.

    Object point ``i = r * cols + c`` is at ``(c * square, r * square, 0)``. The square whose
    lower-right corner is the first inner corner is dark.
    """
    ii, jj = np.meshgrid(np.arange(cols), np.arange(rows))
    pts = np.stack([ii.ravel() * square, jj.ravel() * square, np.zeros(cols * rows)], -1)
    polys = [_square(i * square, j * square, square)
             for j in range(-1, rows) for i in range(-1, cols) if (i + j) % 2 == 0]
    margin = square  # white quiet zone around the squares
    extent = np.array([-square - margin, -square - margin, cols * square + margin,
                       rows * square + margin])
    return Target("chessboard", spec or f"chessboard:{cols}x{rows}:{square:g}", pts,
                  (cols, rows), square, polys, np.zeros((0, 3)), extent)


def circle_grid(cols: int, rows: int, spacing: float, asymmetric: bool = False,
                spec: str = "", radius: float | None = None) -> Target:
    """Circle grid in OpenCV's layout.

    Symmetric: point ``r * cols + c`` at ``(c, r) * spacing``. Asymmetric (OpenCV's count):
    ``((2 c + r % 2) * spacing, r * spacing)``. Radius defaults to a quarter of the spacing
    (a third of it for the asymmetric grid, whose neighbours are further apart).
    """
    ii, jj = np.meshgrid(np.arange(cols), np.arange(rows))
    x = (2 * ii + jj % 2) * spacing if asymmetric else ii * spacing
    pts = np.stack([x.ravel(), jj.ravel() * spacing, np.zeros(cols * rows)], -1).astype(float)
    if radius is None:
        radius = spacing / 3 if asymmetric else spacing / 4
    discs = np.concatenate([pts[:, :2], np.full((len(pts), 1), radius)], axis=1)
    margin = spacing
    extent = np.array([pts[:, 0].min() - margin, pts[:, 1].min() - margin,
                       pts[:, 0].max() + margin, pts[:, 1].max() + margin])
    kind = "acircles" if asymmetric else "circles"
    return Target(kind, spec or f"{kind}:{cols}x{rows}:{spacing:g}", pts, (cols, rows), spacing,
                  [], discs, extent)


def charuco(squares_x: int, squares_y: int, square: float, marker: float, dictionary: str,
            spec: str = "") -> Target:
    """ChArUco board as OpenCV builds it (``cv2.aruco.CharucoBoard``).

    Object points are OpenCV's ChArUco corners (``getChessboardCorners``), shifted so the board's
    top-left outer corner is at (-square, -square) like the chessboard's frame: corner id ``i``
    of OpenCV is object point ``i``. Polygons are the dark squares and the dark cells of every
    marker (rows of cells merged).
    """
    import cv2

    if not hasattr(cv2.aruco, dictionary):
        raise PatternError(f"pattern {spec!r}: unknown ArUco dictionary {dictionary!r}")
    if marker >= square:
        raise PatternError(f"pattern {spec!r}: marker ({marker}) must be smaller than the "
                           f"square ({square})")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    board = cv2.aruco.CharucoBoard((squares_x, squares_y), square, marker, d)
    offset = np.array([square, square, 0.0])
    pts = np.asarray(board.getChessboardCorners(), dtype=float).reshape(-1, 3) - offset
    polys = []
    # OpenCV's ChArUco: square (0, 0) (top-left) is dark unless legacy pattern; markers sit in
    # the white squares.
    img = board.generateImage((squares_x * 100, squares_y * 100), marginSize=0, borderBits=1)
    del img  # (generated only to make OpenCV validate the board)
    for j in range(squares_y):
        for i in range(squares_x):
            if (i + j) % 2 == 0:
                polys.append(_square(i * square, j * square, square) - offset[:2])
    bits = d.markerSize + 2
    cell = marker / bits
    ids = np.asarray(board.getIds()).ravel()
    for k, corners in zip(ids, board.getObjPoints(), strict=True):
        c = np.asarray(corners, dtype=float).reshape(-1, 3)
        x0, y0 = c[:, 0].min() - offset[0], c[:, 1].min() - offset[1]
        mk = cv2.aruco.generateImageMarker(d, int(k), bits, borderBits=1)  # 0 = black
        for r in range(bits):
            dark = mk[r] == 0
            c0 = 0
            while c0 < bits:
                if dark[c0]:
                    c1 = c0
                    while c1 + 1 < bits and dark[c1 + 1]:
                        c1 += 1
                    polys.append(np.array([[x0 + c0 * cell, y0 + r * cell],
                                           [x0 + (c1 + 1) * cell, y0 + r * cell],
                                           [x0 + (c1 + 1) * cell, y0 + (r + 1) * cell],
                                           [x0 + c0 * cell, y0 + (r + 1) * cell]]))
                    c0 = c1 + 1
                else:
                    c0 += 1
    margin = square
    extent = np.array([-square - margin, -square - margin, (squares_x - 1) * square + margin,
                       (squares_y - 1) * square + margin])
    t = Target("charuco", spec or f"charuco:{squares_x}x{squares_y}:{square:g}:{marker:g}:"
               f"{dictionary}", pts, (squares_x - 1, squares_y - 1), square, polys,
               np.zeros((0, 3)), extent, dictionary, marker, (squares_x, squares_y))
    return t


def parse_pattern(spec: str) -> Target:
    """Build a :class:`Target` from a pattern spec.

    Examples
    --------
    >>> t = parse_pattern("chessboard:9x6:25")
    >>> t.n_points, t.object_points[10].tolist()
    (54, [25.0, 25.0, 0.0])
    >>> parse_pattern("acircles:4x11:20").object_points[4].tolist()
    [20.0, 20.0, 0.0]
    """
    parts = spec.split(":")
    kind = parts[0].lower()
    if kind == "chessboard" and len(parts) == 3:
        c, r = _grid_size(parts[1], spec)
        return chessboard(c, r, _length(parts[2], spec, "square"), spec)
    if kind in ("circles", "acircles") and len(parts) == 3:
        c, r = _grid_size(parts[1], spec)
        return circle_grid(c, r, _length(parts[2], spec, "spacing"), kind == "acircles", spec)
    if kind == "charuco" and len(parts) == 5:
        c, r = _grid_size(parts[1], spec)
        return charuco(c, r, _length(parts[2], spec, "square"),
                       _length(parts[3], spec, "marker"), parts[4], spec)
    raise PatternError(
        f"pattern {spec!r} not understood; use chessboard:COLSxROWS:SQUARE, "
        "circles:COLSxROWS:SPACING, acircles:COLSxROWS:SPACING or "
        "charuco:SQUARESXxSQUARESY:SQUARE:MARKER:DICT")


def write_printable(target: Target, stem: str, dpi: float = 300.0) -> list[str]:
    """Write a printable target: ``STEM.png`` at ``dpi``, ``STEM.svg`` in mm, and ``STEM.json``
    with the geometry (object points in mm, board frame).

    Returns
    -------
    files : list of str
    """
    import json

    import cv2

    ext = target.extent_mm
    px_per_mm = dpi / 25.4
    w, h = (int(np.ceil((ext[2] - ext[0]) * px_per_mm)), int(np.ceil((ext[3] - ext[1])
                                                                      * px_per_mm)))
    img = np.full((h, w), 255, np.uint8)
    shift = 4  # cv2 fixed-point bits for sub-pixel vertices
    scale = px_per_mm * (1 << shift)
    # pixel centres at integers: the board point at pixel centre (i, j) is ext[:2] + (i+0.5)/ppmm
    polys = [np.round((p - ext[:2]) * scale - 0.5 * (1 << shift)).astype(np.int32)
             for p in target.polygons]
    if polys:
        cv2.fillPoly(img, polys, 0, lineType=cv2.LINE_AA, shift=shift)
    for x, y, r in target.discs:
        c = np.round((np.array([x, y]) - ext[:2]) * scale - 0.5 * (1 << shift)).astype(int)
        cv2.circle(img, tuple(int(v) for v in c), int(round(r * scale)), 0, -1, cv2.LINE_AA,
                   shift)
    files = [f"{stem}.png", f"{stem}.svg", f"{stem}.json"]
    cv2.imwrite(files[0], img)
    wmm, hmm = ext[2] - ext[0], ext[3] - ext[1]
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{wmm:g}mm" height="{hmm:g}mm" '
             f'viewBox="{ext[0]:g} {ext[1]:g} {wmm:g} {hmm:g}">',
             f'<rect x="{ext[0]:g}" y="{ext[1]:g}" width="{wmm:g}" height="{hmm:g}" '
             'fill="white"/>']
    for p in target.polygons:
        pts = " ".join(f"{x:g},{y:g}" for x, y in p)
        parts.append(f'<polygon points="{pts}" fill="black"/>')
    for x, y, r in target.discs:
        parts.append(f'<circle cx="{x:g}" cy="{y:g}" r="{r:g}" fill="black"/>')
    parts.append("</svg>")
    with open(files[1], "w") as fh:
        fh.write("\n".join(parts) + "\n")
    with open(files[2], "w") as fh:
        json.dump({"pattern": target.spec, "units": "mm", "frame": "board: x along columns, "
                   "y along rows, z = 0", "extent_mm": target.extent_mm.tolist(),
                   "pattern_size": list(target.pattern_size),
                   "object_points": target.object_points.tolist(), "dpi": dpi}, fh, indent=1)
    return files
