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

__all__ = ["Target", "parse_pattern", "PatternError", "write_printable", "plan_print",
           "PrintLayout", "PAPER_MM"]


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


# --- printable targets -------------------------------------------------------------------------

PAPER_MM: dict[str, tuple[float, float]] = {"A4": (210.0, 297.0), "A3": (297.0, 420.0),
                                            "letter": (215.9, 279.4)}
"""Paper sizes, portrait (width, height), mm."""
PRINTER_MARGIN_MM = 6.35
"""Edge of the paper most printers cannot print on, each side, mm (a quarter inch)."""
SCALE_BAR_MM = 100.0
MM_PER_INCH = 25.4
"""Length of the scale bar printed under the board, mm."""
_TEXT_MM = 3.0  # height of the legend's capital letters, mm
_LINE_MM = 5.5  # legend line spacing, mm
_BAR_MM = 2.0  # thickness of the scale bar, mm
_PAD_MM = 4.0  # white space around the legend, mm
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX


@dataclass
class PrintLayout:
    """Where the board, the legend and the scale bar go on the printed image.

    Sheet frame: millimetres from the top-left corner of the image, x right, y down.

    Attributes
    ----------
    sheet_mm : (2,) ndarray
        Width and height of the image, mm (the whole page when ``orientation`` is set).
    board_mm : (2,) ndarray
        Top-left corner of the board's white extent on the sheet, mm.
    bar_mm : (4,) ndarray
        The scale bar: x0, y0, x1, y1, mm (``x1 - x0`` is :data:`SCALE_BAR_MM`).
    lines : list of (float, float, str)
        Legend text: left end and baseline of each line, mm, and the text.
    paper : str or None
        Requested paper (a key of :data:`PAPER_MM`).
    orientation : {'portrait', 'landscape'} or None
        Orientation the board fits the paper in; None without paper or when it does not fit.
    problem : str or None
        Why the board does not fit the paper (None when it fits or no paper was asked for).
    """

    sheet_mm: np.ndarray
    board_mm: np.ndarray
    bar_mm: np.ndarray
    lines: list[tuple[float, float, str]]
    paper: str | None = None
    orientation: str | None = None
    problem: str | None = None


def legend_text(target: Target, dpi: float) -> list[str]:
    """The two lines printed under the board: its spec, and how to check the print."""
    w, h = target.size_mm
    if target.kind == "chessboard":
        what = (f"{target.pattern_size[0]} x {target.pattern_size[1]} inner corners, "
                f"square {target.pitch_mm:g} mm")
    elif target.kind == "charuco":
        what = (f"{target.squares[0]} x {target.squares[1]} squares of {target.pitch_mm:g} mm, "
                f"marker {target.marker_mm:g} mm, {target.dictionary}")
    else:
        what = (f"{target.pattern_size[0]} x {target.pattern_size[1]} circles, "
                f"spacing {target.pitch_mm:g} mm")
    return [f"{target.spec}: {what}; board {w:g} x {h:g} mm; {dpi:g} dpi",
            f"Print at 100 % (no fit to page). The bar below must measure {SCALE_BAR_MM:g} mm."]


def _text_size_mm(text: str) -> tuple[float, float]:
    """Width and cap height of ``text`` in the legend's font, mm."""
    import cv2

    (w, h), _ = cv2.getTextSize(text, _FONT, 1.0, 2)
    return w * _TEXT_MM / h, _TEXT_MM


def _fit_paper(content_mm: np.ndarray, paper: str) -> tuple[str | None, np.ndarray]:
    """The orientation (portrait first) in which ``content_mm`` fits the printable area of
    ``paper``, or None; and that area (portrait), mm."""
    area = np.array(PAPER_MM[paper]) - 2 * PRINTER_MARGIN_MM
    for name, a in (("portrait", area), ("landscape", area[::-1])):
        if np.all(content_mm <= a + 1e-9):
            return name, area
    return None, area


def _largest_pitch(target: Target, strip_mm: float, area_mm: np.ndarray) -> str:
    """``'; a square of at most P mm fits'`` (spacing for circle grids): the pitch, rounded
    down to 0.5 mm, at which the board and the strip fit ``area_mm`` in either orientation."""
    board = target.size_mm
    factor = max(min(a[0] / board[0], (a[1] - strip_mm) / board[1])
                 for a in (area_mm, area_mm[::-1]))
    pitch = np.floor(2 * target.pitch_mm * factor) / 2
    what = "spacing" if target.kind in ("circles", "acircles") else "square"
    return f"; a {what} of at most {pitch:g} mm fits" if pitch > 0 else ""


def plan_print(target: Target, dpi: float, paper: str | None = None) -> PrintLayout:
    """Lay out the board with its legend and scale bar underneath, on ``paper`` if given.

    The content is the board's white extent with a strip below it (two lines of text and the
    :data:`SCALE_BAR_MM` bar), at least as wide as the text. With a paper whose printable area
    (:data:`PRINTER_MARGIN_MM` in from each edge) holds the content, portrait or else landscape,
    the sheet is the whole page and the content is centred on it; otherwise the sheet is the
    content and ``problem`` says why it does not fit.
    """
    lines = legend_text(target, dpi)
    text_w = max(_text_size_mm(t)[0] for t in lines)
    board = target.size_mm
    strip = _PAD_MM + 2 * _LINE_MM + _BAR_MM + _PAD_MM
    content = np.array([max(board[0], text_w + 2 * _PAD_MM, SCALE_BAR_MM + 2 * _PAD_MM),
                        board[1] + strip])
    sheet, origin, orientation, problem = content, np.zeros(2), None, None
    if paper is not None:
        orientation, area = _fit_paper(content, paper)
        if orientation is None:
            problem = (f"the board with its legend ({content[0]:.0f} x {content[1]:.0f} mm) "
                       f"does not fit the printable area of {paper} ({area[0]:.0f} x "
                       f"{area[1]:.0f} mm, {PRINTER_MARGIN_MM:g} mm margins) either way round"
                       + _largest_pitch(target, strip, area))
        else:
            page = np.array(PAPER_MM[paper])
            sheet = page if orientation == "portrait" else page[::-1]
            origin = (sheet - content) / 2
    board_at = origin + np.array([(content[0] - board[0]) / 2, 0.0])
    x_text = origin[0] + _PAD_MM
    y0 = origin[1] + board[1] + _PAD_MM
    text = [(x_text, y0 + _TEXT_MM + i * _LINE_MM, t) for i, t in enumerate(lines)]
    y_bar = y0 + 2 * _LINE_MM
    bar = np.array([x_text, y_bar, x_text + SCALE_BAR_MM, y_bar + _BAR_MM])
    return PrintLayout(sheet, board_at, bar, text, paper, orientation, problem)


def _coverage_1d(lo: float, hi: float, n: int) -> tuple[int, np.ndarray]:
    """First pixel and the covered fraction of pixels ``[first, first + len)`` by the interval
    ``[lo, hi]`` in pixel-edge units (pixel ``i`` spans ``[i, i + 1)``), clipped to ``n``."""
    first, last = max(int(np.floor(lo)), 0), min(int(np.ceil(hi)), n)
    edges = np.arange(first, last + 1, dtype=float)
    return first, np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, 1.0)


def _is_box(p: np.ndarray) -> bool:
    """True if polygon ``p`` is an axis-aligned rectangle."""
    xs, ys = np.unique(np.round(p[:, 0], 9)), np.unique(np.round(p[:, 1], 9))
    return len(p) == 4 and len(xs) == 2 and len(ys) == 2


def _darkness(target: Target, layout: PrintLayout, px_per_mm: float,
              shape: tuple[int, int]) -> np.ndarray:
    """Fraction of each pixel covered by the board's dark shapes and the scale bar: exact for
    axis-aligned rectangles, to first order in pixel size over the curvature for discs."""
    import cv2

    h, w = shape
    dark = np.zeros(shape)
    to_sheet = layout.board_mm - target.extent_mm[:2]
    x0, y0, x1, y1 = layout.bar_mm
    bar = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    others = []
    for p in [q + to_sheet for q in target.polygons] + [bar]:
        if not _is_box(p):
            others.append(np.round((p * px_per_mm - 0.5) * 16).astype(np.int32))
            continue
        (lx, ly), (hx, hy) = p.min(0) * px_per_mm, p.max(0) * px_per_mm
        cx, fx = _coverage_1d(lx, hx, w)
        cy, fy = _coverage_1d(ly, hy, h)
        dark[cy:cy + len(fy), cx:cx + len(fx)] += np.outer(fy, fx)
    for x, y, r in target.discs:
        cx, cy, rp = (x + to_sheet[0]) * px_per_mm, (y + to_sheet[1]) * px_per_mm, r * px_per_mm
        i0, i1 = max(int(cy - rp) - 1, 0), min(int(cy + rp) + 2, h)
        j0, j1 = max(int(cx - rp) - 1, 0), min(int(cx + rp) + 2, w)
        d = np.hypot(np.arange(j0, j1) + 0.5 - cx, np.arange(i0, i1)[:, None] + 0.5 - cy)
        dark[i0:i1, j0:j1] += np.clip(rp - d + 0.5, 0.0, 1.0)
    if others:  # general polygons: OpenCV's anti-aliased fill
        mask = np.zeros(shape, np.uint8)
        cv2.fillPoly(mask, others, 255, lineType=cv2.LINE_AA, shift=4)
        dark += mask / 255.0
    return np.minimum(dark, 1.0)


def _raster(target: Target, layout: PrintLayout, dpi: float) -> np.ndarray:
    """The layout as an 8-bit grey image at ``dpi`` (0 black, 255 white). Sheet point ``s``
    (mm) is at pixel ``s * dpi / 25.4 - 0.5`` (pixel centres at integers)."""
    import cv2

    px_per_mm = dpi / MM_PER_INCH
    w, h = np.ceil(layout.sheet_mm * px_per_mm - 1e-6).astype(int)
    dark = _darkness(target, layout, px_per_mm, (h, w))
    img = np.round(255.0 * (1.0 - dark)).astype(np.uint8)
    (_, cap), _ = cv2.getTextSize("H", _FONT, 1.0, 1)
    scale = _TEXT_MM * px_per_mm / cap
    thick = max(1, int(round(0.1 * _TEXT_MM * px_per_mm)))  # stroke a tenth of the height
    for x, y, text in layout.lines:
        cv2.putText(img, text, (int(round(x * px_per_mm)), int(round(y * px_per_mm))), _FONT,
                    scale, 0, thick, cv2.LINE_AA)
    return img


def _svg(target: Target, layout: PrintLayout) -> str:
    """The layout as SVG in mm (board, legend and scale bar)."""
    from xml.sax.saxutils import escape

    w, h = layout.sheet_mm
    dx, dy = layout.board_mm - target.extent_mm[:2]
    ext = target.extent_mm
    bw, bh = target.size_mm
    x0, y0, x1, y1 = layout.bar_mm
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w:g}mm" height="{h:g}mm" '
             f'viewBox="0 0 {w:g} {h:g}">',
             f'<rect x="0" y="0" width="{w:g}" height="{h:g}" fill="white"/>',
             f'<g transform="translate({dx:g} {dy:g})">',
             f'<rect x="{ext[0]:g}" y="{ext[1]:g}" width="{bw:g}" height="{bh:g}" '
             'fill="white"/>']
    parts += [f'<polygon points="{" ".join(f"{x:g},{y:g}" for x, y in p)}" fill="black"/>'
              for p in target.polygons]
    parts += [f'<circle cx="{x:g}" cy="{y:g}" r="{r:g}" fill="black"/>'
              for x, y, r in target.discs]
    parts.append("</g>")
    parts.append(f'<rect x="{x0:g}" y="{y0:g}" width="{x1 - x0:g}" height="{y1 - y0:g}" '
                 'fill="black"/>')
    parts += [f'<text x="{x:g}" y="{y:g}" font-family="sans-serif" '
              f'font-size="{_TEXT_MM * 1.4:g}">{escape(t)}</text>' for x, y, t in layout.lines]
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _write_png(path: str, img: np.ndarray, dpi: float) -> None:
    """Write ``img`` as PNG with its resolution in the pHYs chunk, so it prints at size."""
    from PIL import Image

    Image.fromarray(img).save(path, format="PNG", dpi=(dpi, dpi))


def write_printable(target: Target, stem: str, dpi: float = 300.0,
                    paper: str | None = None) -> tuple[list[str], PrintLayout]:
    """Write a printable target: ``STEM.png`` at ``dpi`` (stored in the file, so it prints at
    size), ``STEM.svg`` in mm, and ``STEM.json`` with the geometry (object points in mm, board
    frame) and the layout. Under the board: its spec and a :data:`SCALE_BAR_MM` bar to check
    the print with a ruler. See :func:`plan_print` for ``paper``.

    Returns
    -------
    files : list of str
    layout : PrintLayout
        Its ``problem`` says when the board does not fit the paper (the files are written all
        the same, at the content's size).
    """
    import json

    layout = plan_print(target, dpi, paper)
    files = [f"{stem}.png", f"{stem}.svg", f"{stem}.json"]
    _write_png(files[0], _raster(target, layout, dpi), dpi)
    with open(files[1], "w") as fh:
        fh.write(_svg(target, layout))
    origin_px = (layout.board_mm - target.extent_mm[:2]) * dpi / MM_PER_INCH - 0.5
    with open(files[2], "w") as fh:
        json.dump({"pattern": target.spec, "units": "mm", "frame": "board: x along columns, "
                   "y along rows, z = 0", "extent_mm": target.extent_mm.tolist(),
                   "pattern_size": list(target.pattern_size),
                   "object_points": target.object_points.tolist(), "dpi": dpi,
                   "sheet_mm": layout.sheet_mm.tolist(), "paper": layout.paper,
                   "orientation": layout.orientation,
                   "board_origin_px": origin_px.tolist(),
                   "scale_bar_mm": layout.bar_mm.tolist()}, fh, indent=1)
    return files, layout
