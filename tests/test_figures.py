"""Every figure says what it shows: x and y labels on every axes, a colour bar for every
colour-coded artist, titles and labels inside the figure; and the specific fixes: the path in
zoom order and the user's zoom unit, fig7's legend and axis, the residual panels' colouring."""

from dataclasses import replace

import matplotlib
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import Collection
from matplotlib.figure import Figure

from zoomcalib import plots
from zoomcalib.diagnose import report as diag_report
from zoomcalib.diagnose.discrepancy import diagnose_table
from zoomcalib.diagnose.model import LensResponse
from zoomcalib.diagnose.synthetic import synthetic_zoom_table
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.optics.prescription import load_prescription
from zoomcalib.study import report as study_report

matplotlib.use("Agg")


@pytest.fixture
def saved(monkeypatch):
    """The figures the code under test saves, kept for inspection."""
    figures = []
    original = Figure.savefig

    def keep(fig, *args, **kwargs):
        figures.append(fig)
        return original(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def _colorbar_axes(fig):
    return [ax for ax in fig.axes if hasattr(ax, "_colorbar")]


def _check_readable(fig):
    """Labels on every data axes, a colour bar for every colour-coded collection, every title
    and label inside the figure once drawn."""
    canvas = FigureCanvasAgg(fig)  # the figure was closed after saving
    canvas.draw()
    renderer = canvas.get_renderer()
    box = fig.bbox
    bars = _colorbar_axes(fig)
    texts = [t for t in (fig._suptitle,) if t is not None and t.get_text()]
    for ax in fig.axes:
        texts += [t for t in (ax.title, ax.xaxis.label, ax.yaxis.label) if t.get_text()]
        if ax in bars:
            continue
        assert ax.get_xlabel().strip() and ax.get_ylabel().strip(), ax.get_title()
        coded = [c for c in ax.collections
                 if isinstance(c, Collection) and c.get_array() is not None]
        with_bar = [c for c in coded if c.colorbar is not None]
        for coll in coded:  # its own colour bar, or one of the same colour mapping's
            assert any(c.norm is coll.norm and c.cmap is coll.cmap for c in with_bar), \
                f"{type(coll).__name__} in {ax.get_title()!r} has no colour bar"
        for coll in with_bar:
            assert coll.colorbar.ax.get_ylabel().strip() or coll.colorbar.ax.get_xlabel()
    for t in texts:
        ext = t.get_window_extent(renderer)
        inside = (ext.x0 >= box.x0 - 1 and ext.x1 <= box.x1 + 1 and ext.y0 >= box.y0 - 1
                  and ext.y1 <= box.y1 + 1)
        assert inside, f"{t.get_text()!r} reaches out of the figure"


def _colorbar_labels(fig):
    return [ax.get_ylabel() for ax in _colorbar_axes(fig)]


def test_principal_point_path_in_zoom_order_and_user_units(tmp_path, saved):
    rng = np.random.default_rng(1)
    zoom = np.array([35.0, 12.0, 70.0, 24.0, 50.0])  # mm on the barrel, not in order
    mean = 640 + rng.normal(0, 3, (5, 2))
    sd = rng.uniform(0.2, 0.5, (5, 2))
    plots.plot_principal_point_spiral(zoom, mean, sd, tmp_path / "p.png",
                                      zoom_label="zoom ring [mm]",
                                      title="a long title " * 12)
    (fig,) = saved
    _check_readable(fig)
    ax = fig.axes[0]
    path = next(line for line in ax.lines if line.get_label() == "path in zoom order")
    order = np.argsort(zoom)
    np.testing.assert_array_equal(path.get_xydata(), mean[order])
    assert _colorbar_labels(fig) == ["zoom ring [mm]"]
    vmin, vmax = ax.collections[0].get_clim()
    assert (vmin, vmax) == (12.0, 70.0)
    assert {t.get_text() for t in ax.texts} >= {"12", "70"}


def test_principal_point_path_is_drawn_in_the_image(tmp_path, saved):
    # a calibrated path spans tens of px: an inset with the image's outline shows where it
    # lies (a principal point near the image's edge is a finding) beside its detail
    from matplotlib.patches import Rectangle

    rng = np.random.default_rng(2)
    mean = np.array([300.0, 500.0]) + rng.normal(0, 20, (6, 2))
    sd = rng.uniform(1, 4, (6, 2))
    plots.plot_principal_point_spiral(np.arange(6.0), mean, sd, tmp_path / "p.png",
                                      image_size=(1280, 720))
    (fig,) = saved
    ax = fig.axes[0]
    (inset,) = ax.child_axes
    (outline,) = [p for p in inset.patches if isinstance(p, Rectangle)]
    assert outline.get_xy() == (-0.5, -0.5)
    assert (outline.get_width(), outline.get_height()) == (1280, 720)
    x0, x1 = inset.get_xlim()
    y1, y0 = inset.get_ylim()                   # y down
    assert x0 < -0.5 and x1 > 1279.5 and y0 < -0.5 and y1 > 719.5
    assert inset.get_title() == "in the image (1280 x 720 px)"
    # the main axes keep the path's detail: it fills them, not the image
    assert np.ptp(ax.get_xlim()) < 0.2 * 1280


def test_calibration_figures_are_readable(tmp_path, saved):
    rng = np.random.default_rng(2)
    plots.plot_focal_length(np.array([1.0, 2, 3]), np.array([800.0, 1600, 2400]),
                            np.array([2.0, 3, 4]), tmp_path / "f.png", zoom_label="zoom [x]")
    points = [rng.uniform(0, [640, 480], (30, 2)) for _ in range(4)]
    residuals = [rng.normal(0, 0.2, (30, 2)) for _ in range(4)]
    plots.plot_residuals(points, residuals, (640, 480), tmp_path / "r.png",
                         title="step zoom_3: zoom-wide, rms 0.201 px")
    plots.plot_cross_validation(["a", "b", "c"], rng.normal(0, 1, (3, 2)), ("cx", "cy"),
                                tmp_path / "c.png")
    assert len(saved) == 3
    for fig in saved:
        _check_readable(fig)
    assert saved[0].axes[0].get_xlabel() == "zoom [x]"
    labels = _colorbar_labels(saved[1])
    assert any("[px]" in label for label in labels) and any("view" in label for label in labels)


def _scatter_rows(noises, rng):
    return [{"zoom": z, "noise_dn": n, "detector": d, "backend": b,
             "s_det_px": float(rng.uniform(0.01, 0.1))}
            for z in (0.0, 0.5, 1.0) for n in noises for d in ("classic", "model")
            for b in ("opencv", "bundle")]


MECH = [{"zoom": z, "efl_mm": 10 + 90 * z, "s_mech_px": 1 + z, "shift_px": 2 + z}
        for z in (0.0, 0.5, 1.0)]


def _legend_texts(ax):
    return {t.get_text() for t in ax.get_legend().get_texts()}


def test_fig7_legend_names_both_backends_and_colour_bar_for_zoom(tmp_path, saved):
    scatter = _scatter_rows([2.0, 4.0, 8.0], np.random.default_rng(3))
    study_report.plot_fig7(scatter, np.array([0.0, 0.5, 1.0]), tmp_path / "f7.png")
    (fig,) = saved
    _check_readable(fig)
    ax = fig.axes[0]
    assert {"opencv backend", "bundle backend", "classic detector",
            "model detector"} <= _legend_texts(ax)
    assert any("zoom" in label for label in _colorbar_labels(fig))  # colour = zoom step
    assert {line.get_linestyle() for line in ax.lines} == {"-", "--"}


def test_fig7_with_one_noise_level_is_drawn_against_zoom(tmp_path, saved):
    scatter = _scatter_rows([4.0], np.random.default_rng(4))
    study_report.plot_fig7(scatter, np.array([0.0, 0.5, 1.0]), tmp_path / "f7.png")
    (fig,) = saved
    _check_readable(fig)
    ax = fig.axes[0]
    assert "zoom" in ax.get_xlabel()
    assert ax.lines and all(len(np.unique(line.get_xdata())) == 3 for line in ax.lines)
    assert {"opencv backend", "bundle backend"} <= _legend_texts(ax)


def test_study_comparison_and_fig6_are_readable(tmp_path, saved):
    rng = np.random.default_rng(5)
    study_report.plot_scatter_vs_focal_length(MECH, _scatter_rows([2.0, 4.0], rng),
                                              tmp_path / "vs.png")
    fig6 = {d: {"points": rng.uniform(0, 100, (12, 2)).tolist(),
                "errors": rng.normal(0, 0.05, (12, 2)).tolist()} for d in ("classic", "model")}
    study_report.plot_fig6(fig6, 100, 80, tmp_path / "f6.png")
    assert len(saved) == 2
    for fig in saved:
        _check_readable(fig)
    assert {"mechanics: scatter", "opencv backend", "bundle backend"} <= _legend_texts(
        saved[0].axes[0])


@pytest.fixture(scope="module")
def diagnoses():
    """One seeded synthetic table's diagnosis, and the same with the capture order left out of
    its table (the figures read the table; the fit is the same)."""
    lens = load_prescription("laikin-10x")
    rows, _ = synthetic_zoom_table(lens, "backlash", np.random.default_rng(6), n_zoom=5,
                                   passes=1)
    diag = diagnose_table(ZoomTable.from_rows(rows, "with.csv"), LensResponse.of(lens, n_grid=101))
    long_name = "a/long/folder/name/of/a/real/calibration/session/zoom_calibration.csv"
    no_order = replace(diag, table=replace(diag.table, sequence=None, source=long_name))
    return {"rows": rows, "diag": diag}, {"rows": rows, "diag": no_order}


@pytest.mark.parametrize("which", [0, 1], ids=["capture-order", "no-capture-order"])
def test_diagnose_figures(tmp_path, saved, diagnoses, which):
    case = diagnoses[which]
    diag_report.plot_path(case["diag"], tmp_path / "path.png")
    diag_report.plot_residuals(case["diag"], tmp_path / "res.png")
    for fig in saved:
        _check_readable(fig)
    zoom = np.array([float(r["zoom"]) for r in case["rows"]])
    path_fig, res_fig = saved
    measured = next(c for c in path_fig.axes[0].collections if c.get_label() == "measured")
    np.testing.assert_array_equal(measured.get_array(), zoom)
    right = res_fig.axes[1]  # top-right residual panel
    colours = np.asarray(right.collections[0].get_array())
    labels = " ".join(_colorbar_labels(res_fig))
    if which == 0:
        sequence = np.array([float(r["sequence"]) for r in case["rows"]])
        np.testing.assert_array_equal(colours, sequence)
        assert "capture order" in labels
    else:
        np.testing.assert_array_equal(colours, zoom)
        assert "no capture order" in labels and "zoom" in labels
