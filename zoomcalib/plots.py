"""Figures. Matplotlib is imported lazily with the non-interactive Agg backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_principal_point_spiral", "plot_focal_length", "plot_residuals",
           "plot_cross_validation", "wrap_title", "limit_ticks", "save_figure"]


LENS_ZOOM_LABEL = "lens zoom state (0 = shortest focal length, 1 = longest)"
"""Colour-bar / axis label of the simulation's zoom (docs/conventions.md)."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def limit_ticks(fig, n: int = 4) -> None:
    """At most ``n`` value ticks on each axis of ``fig`` that matplotlib places itself (tick
    labels are most of a figure's drawing time); axes with ticks of their own are left."""
    from matplotlib.ticker import MaxNLocator

    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if isinstance(axis.get_major_locator(), MaxNLocator):  # the Auto locators
                axis.set_major_locator(MaxNLocator(n))


def save_figure(fig, path: str | Path) -> Path:
    """Write ``fig`` as PNG to ``path`` and close it, as every figure of the package is:
    :func:`limit_ticks`, and PNG's fastest compression."""
    limit_ticks(fig)
    fig.savefig(path, format="png", pil_kwargs={"compress_level": 1})
    _pyplot().close(fig)
    return Path(path)


def wrap_title(text: str, fig_width_in: float, fontsize: float = 9.0) -> str:
    """``text`` broken into lines that fit 80 % of a figure ``fig_width_in`` inches wide at
    ``fontsize`` points (a character taken as 0.6 em wide)."""
    import textwrap

    chars = max(20, int(0.8 * fig_width_in * 72 / (0.6 * fontsize)))
    return "\n".join(textwrap.wrap(text, chars)) if text else text


def plot_principal_point_spiral(zoom: np.ndarray, mean_px: np.ndarray, std_px: np.ndarray,
                                path: str | Path, title: str = "",
                                centre_px: np.ndarray | None = None,
                                zoom_label: str = LENS_ZOOM_LABEL,
                                image_size: tuple[int, int] | None = None) -> Path:
    """The paper's Fig. 5: mean principal point across zoom with its 1-sigma ellipses.

    The path joins the states in increasing zoom; points, ellipses and the colour bar show the
    zoom in the caller's unit, named by ``zoom_label``.

    Parameters
    ----------
    zoom : (Z,) ndarray
        Zoom of each state, any monotone unit (any order).
    mean_px, std_px : (Z, 2) ndarray
        Mean (cx, cy) and its 1-sigma scatter per zoom state, px (OpenCV convention).
    path : str or Path
        Output PNG.
    centre_px : (2,) ndarray, optional
        Marked as the nominal image centre.
    zoom_label : str
        Colour-bar label: the zoom's name and unit.
    image_size : (int, int), optional
        (width, height) px: an inset shows the path inside the image's outline (pixel edges at
        -0.5 and size - 0.5), so where it lies in the image is seen beside its detail.
    """
    from matplotlib.colors import Normalize
    from matplotlib.patches import Ellipse, Rectangle

    plt = _pyplot()
    order = np.argsort(zoom, kind="stable")
    zoom, mean_px, std_px = (np.asarray(a, dtype=float)[order] for a in (zoom, mean_px, std_px))
    norm = Normalize(zoom.min(), zoom.max() if zoom.max() > zoom.min() else zoom.min() + 1)
    fig, ax = plt.subplots(figsize=(6.4, 6.0), dpi=120, layout="constrained")
    ax.plot(mean_px[:, 0], mean_px[:, 1], "-", color="0.6", lw=0.8, zorder=1,
            label="path in zoom order")
    sc = ax.scatter(mean_px[:, 0], mean_px[:, 1], c=zoom, cmap="viridis", norm=norm, s=14,
                    zorder=3)
    for (x, y), (sx, sy), z in zip(mean_px, std_px, zoom, strict=True):
        ax.add_patch(Ellipse((x, y), 2 * sx, 2 * sy, fill=False, lw=0.7,
                             color=plt.cm.viridis(norm(z)), zorder=2))
    label_every = max(1, len(zoom) // 10)
    for i in range(0, len(zoom), label_every):
        ax.annotate(f"{zoom[i]:.3g}", mean_px[i], textcoords="offset points", xytext=(4, 4),
                    fontsize=7)
    if centre_px is not None:
        ax.plot(*centre_px, "k+", ms=10, label="sensor centre")
    span = np.max(np.abs(mean_px - mean_px.mean(0)) + std_px) * 1.15 + 1e-6
    cx, cy = mean_px.mean(0)
    ax.set_xlim(cx - span, cx + span)
    ax.set_ylim(cy + span, cy - span)  # image convention: y down
    ax.legend(loc="upper right", fontsize=8)
    if image_size is not None:
        w, h = image_size
        inset = ax.inset_axes([0.02, 0.02, 0.3, 0.3 * h / w])
        inset.add_patch(Rectangle((-0.5, -0.5), w, h, fill=False, lw=0.8, color="0.3"))
        inset.plot(mean_px[:, 0], mean_px[:, 1], "-", color="C3", lw=1.2)
        margin = 0.04 * max(w, h)
        inset.set_xlim(-0.5 - margin, w - 0.5 + margin)
        inset.set_ylim(h - 0.5 + margin, -0.5 - margin)
        inset.set_aspect("equal")
        inset.set_xticks([])
        inset.set_yticks([])
        inset.set_title(f"in the image ({w} x {h} px)", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("cx [px]")
    ax.set_ylabel("cy [px]")
    ax.set_title(wrap_title(title or "Principal point across zoom (mean, 1-sigma ellipses)",
                            5.0), fontsize=9)
    fig.colorbar(sc, ax=ax, label=zoom_label, shrink=0.8)
    path = Path(path)
    save_figure(fig, path)
    return path


def plot_focal_length(zoom: np.ndarray, fx: np.ndarray, sd_fx: np.ndarray, path: str | Path,
                      zoom_model=None, zoom_label: str = "zoom") -> Path:
    """Focal length (px) versus zoom (``zoom_label`` names its unit) with 1-sigma error bars
    and, if given, the zoom model."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120, layout="constrained")
    ax.errorbar(zoom, fx, yerr=sd_fx, fmt="o", ms=4, capsize=3, label="calibrated fx")
    if zoom_model is not None:
        z = np.linspace(np.min(zoom), np.max(zoom), 200)
        pred = zoom_model.predict(z)
        ax.plot(z, pred["fx"], "-", lw=1, label="zoom model")
    ax.set_yscale("log")
    ax.set_xlabel(zoom_label)
    ax.set_ylabel("fx [px]")
    ax.set_title("Focal length across zoom (1-sigma error bars)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    path = Path(path)
    save_figure(fig, path)
    return path


def plot_residuals(points: list[np.ndarray], residuals: list[np.ndarray],
                   image_size: tuple[int, int], path: str | Path, title: str = "") -> Path:
    """Coverage of the image by the detected points and their reprojection residuals.

    Parameters
    ----------
    points, residuals : list of (k, 2) ndarray
        Per view: observed points and residuals (projected minus observed), px.
    image_size : (int, int)
        (width, height), px.
    """
    plt = _pyplot()
    w, h = image_size
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.6), dpi=110)
    p = np.concatenate(points)
    r = np.concatenate(residuals)
    view = np.concatenate([np.full(len(q), i + 1) for i, q in enumerate(points)])
    cover = ax0.scatter(p[:, 0], p[:, 1], s=2, c=view, cmap="viridis")
    fig.colorbar(cover, ax=ax0, label="view (1 = first)", shrink=0.8)
    ax0.set_title("coverage: detected points", fontsize=9)
    norm = np.linalg.norm(r, axis=1)
    p95 = np.percentile(norm, 95)
    scale = 0.08 * max(w, h) / max(p95, 1e-9)
    arrows = ax1.quiver(p[:, 0], p[:, 1], r[:, 0] * scale, r[:, 1] * scale, norm, angles="xy",
                        scale_units="xy", scale=1, cmap="viridis", width=0.002)
    fig.colorbar(arrows, ax=ax1, label="residual length [px]", shrink=0.8)
    panel_title = wrap_title(f"residuals (projected - observed), drawn x{scale:.0f}; 95th "
                             f"percentile {p95:.3f} px", 4.5)
    ax1.set_title(panel_title, fontsize=9)
    for ax in (ax0, ax1):
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_xlabel("x [px]")
        ax.set_ylabel("y [px]")
    suptitle = wrap_title(title, 11.0, 10.0)
    fig.suptitle(suptitle, fontsize=10)
    # fixed margins (a layout engine would take as long as the drawing): room above the
    # panels for the title's and the panel title's lines, 0.18 in each
    lines = (suptitle.count("\n") + 1 if suptitle else 0) + panel_title.count("\n") + 1
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.1, wspace=0.25,
                        top=1.0 - (0.2 + 0.18 * lines) / 4.6)
    path = Path(path)
    save_figure(fig, path)
    return path


def plot_cross_validation(steps: list[str], z: np.ndarray, names: tuple[str, ...],
                          path: str | Path, limit: float = 3.0, title: str = "") -> Path:
    """Two-halves check: per step, the difference of each parameter between the even and the
    odd images in combined sigmas, with the +-``limit`` band.

    Parameters
    ----------
    steps : list of str
        Step names, in zoom order.
    z : (S, P) ndarray
        ``(q_even - q_odd) / sqrt(sd_even^2 + sd_odd^2)`` per step and parameter.
    names : tuple of str
        The P parameter names.
    """
    plt = _pyplot()
    width = max(6.4, 0.5 * len(steps) + 2)
    fig, ax = plt.subplots(figsize=(width, 4.0), dpi=120, layout="constrained")
    x = np.arange(len(steps))
    ax.axhspan(-limit, limit, color="0.92", zorder=0, label=f"|z| <= {limit:g}")
    for k, name in enumerate(names):
        ax.plot(x + (k - (len(names) - 1) / 2) * 0.12, z[:, k], "o", label=name)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xticks(x, steps, rotation=45, ha="right")
    ax.set_xlabel("zoom step")
    ax.set_ylabel("difference between halves / combined sigma")
    ax.set_title(wrap_title(title or "Cross-validation: even vs odd images per step", width,
                            10.0), fontsize=10)
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, path)
    return Path(path)
