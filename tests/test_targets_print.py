"""Printable targets print at size: the PNG carries its DPI, the scale bar and the board's squares
measure what they should at that DPI, and a board too large for the paper is reported."""

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from zoomcalib.cli import main
from zoomcalib.targets import legend_text, parse_pattern

MM_PER_INCH = 25.4


def _target(tmp_path, *args):
    res = CliRunner().invoke(main, ["target", *args, "--out", str(tmp_path / "t")])
    assert res.exit_code == 0, res.output
    return res, tmp_path / "t.png"


@pytest.mark.parametrize("dpi", [127.0, 150.0, 300.0])
def test_png_carries_its_dpi(tmp_path, dpi):
    _, png = _target(tmp_path, "circles:4x3:10", "--dpi", f"{dpi:g}")
    got = Image.open(png).info["dpi"]
    # pHYs stores whole pixels per metre: at most 0.5 px/m = 0.0127 dpi off
    assert got == pytest.approx((dpi, dpi), abs=0.013)


def _scale_bar_length_px(png) -> float:
    """Width of the one long thin dark blob of the image, px (50 % threshold)."""
    img = np.asarray(Image.open(png).convert("L"))
    n, _, stats, _ = cv2.connectedComponentsWithStats((img < 128).astype(np.uint8), 8)
    w, h = stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT]
    bars = np.flatnonzero(w > 20 * h)
    assert len(bars) == 1, f"{len(bars)} bar-shaped blobs"
    return float(w[bars[0]])


@pytest.mark.parametrize("dpi, paper", [(127.0, None), (150.0, "A4"), (300.0, None)])
def test_scale_bar_measures_100_mm(tmp_path, dpi, paper):
    args = ["chessboard:5x4:15", "--dpi", f"{dpi:g}"] + (["--paper", paper] if paper else [])
    _, png = _target(tmp_path, *args)
    # the bar's ends fall on pixel edges to within half a pixel each
    assert abs(_scale_bar_length_px(png) - 100.0 / MM_PER_INCH * dpi) <= 1.0


@pytest.mark.parametrize("pattern, square_mm, dpi", [("chessboard:9x6:20", 20.0, 100.0),
                                                     ("chessboard:7x5:12.5", 12.5, 150.0)])
def test_printed_squares_measure_the_square_size(tmp_path, pattern, square_mm, dpi):
    _, png = _target(tmp_path, pattern, "--dpi", f"{dpi:g}", "--paper", "A4")
    img = np.asarray(Image.open(png).convert("L"))
    cols, rows = (int(v) for v in pattern.split(":")[1].split("x"))
    found, corners = cv2.findChessboardCorners(img, (cols, rows))
    assert found
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    grid = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1), crit).reshape(rows, cols, 2)
    # mean spacing along each row and each column, end to end
    along_rows = np.linalg.norm(grid[:, -1] - grid[:, 0], axis=1) / (cols - 1)
    along_cols = np.linalg.norm(grid[-1] - grid[0], axis=1) / (rows - 1)
    expected = square_mm / MM_PER_INCH * dpi
    # single corners refine to about 0.1 px on a clean anti-aliased edge, so over 4-8 squares
    # the mean spacing is good to about 0.03 px; squares drawn at a DPI rounded to whole pixels
    # per mm are off by more than 1 px in both cases
    for spacing in (along_rows, along_cols):
        assert np.abs(spacing - expected).max() < 0.05


def _warned(res) -> bool:
    return "does not fit" in res.output


def test_board_too_large_for_a4_warns(tmp_path):
    res, png = _target(tmp_path, "chessboard:9x6:25", "--dpi", "50", "--paper", "A4")
    assert _warned(res)
    line = next(x for x in res.output.splitlines() if "does not fit" in x)
    assert line.startswith("warning: ") and "t.png" in line and "A4" in line
    assert png.is_file()


def test_board_that_fits_a4_does_not_warn_and_fills_the_page(tmp_path):
    res, png = _target(tmp_path, "acircles:4x11:20", "--dpi", "100", "--paper", "A4")
    assert not _warned(res) and "portrait" in res.output
    # the whole A4 page, 210 x 297 mm, at 100 dpi
    assert Image.open(png).size == (827, 1170)


def test_board_that_fits_only_landscape_is_laid_landscape(tmp_path):
    # 7 x 5 inner corners of 20 mm: a 200 x 160 mm board, wider than A4's printable width
    res, png = _target(tmp_path, "chessboard:7x5:20", "--dpi", "100", "--paper", "a4")
    assert not _warned(res) and "landscape" in res.output
    assert Image.open(png).size == (1170, 827)


def test_legend_states_the_spec():
    text = " ".join(legend_text(parse_pattern("chessboard:9x6:25"), 300.0))
    for part in ("chessboard:9x6:25", "9 x 6 inner corners", "square 25 mm", "300 dpi",
                 "100 mm"):
        assert part in text
