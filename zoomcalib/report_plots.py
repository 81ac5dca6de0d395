"""Figures of the calibration report, each returned as PNG bytes (Agg backend, imported lazily).

Pixels follow OpenCV's convention (centre of the top-left pixel = (0, 0), y down: image axes
are drawn with y increasing downwards). Every axis is labelled with its unit; a colour bar with
its unit accompanies every colour that encodes a value.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence

import numpy as np

__all__ = ["per_view_figure", "residual_figure", "coverage_figure", "uncertainty_figure",
           "short_labels", "lens_and_poses_figure", "corners_figure",
           "zoom_range_figure"]

_DPI = 80
_MARK = "tab:red"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    """The figure as PNG; axes get at most four value ticks each (tick labels are most of
    the drawing time)."""
    from matplotlib.ticker import MaxNLocator

    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if isinstance(axis.get_major_locator(), MaxNLocator):  # the Auto locators
                axis.set_major_locator(MaxNLocator(4))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI, pil_kwargs={"compress_level": 1})
    _pyplot().close(fig)
    return buf.getvalue()


def _image_axes(ax, image_size: tuple[int, int]) -> None:
    w, h = image_size
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")


def per_view_figure(names: Sequence[str], rms_px: np.ndarray, marked: dict[str, str],
                    absent: Sequence[str]) -> bytes:
    """Per-image reprojection RMS (px) as bars; images in ``marked`` (name -> short reason,
    e.g. '3 points rejected') in red with the reason; ``absent`` images (not in the fit) as
    empty labelled slots."""
    plt = _pyplot()
    labels, prefix = short_labels(list(names) + list(absent))
    fig, ax = plt.subplots(figsize=(min(4.0 + 0.28 * len(labels), 14.0), 3.4))
    x = np.arange(len(labels))
    colours = [_MARK if n in marked else "tab:blue" for n in names]
    ax.bar(x[:len(names)], rms_px, color=colours)
    top = float(np.max(rms_px, initial=0.0)) or 1.0
    for i, n in enumerate(names):
        if n in marked:
            ax.annotate(marked[n], (i, rms_px[i]), xytext=(0, 3), textcoords="offset points",
                        rotation=90, fontsize=7, color=_MARK, ha="center", va="bottom")
    for i in range(len(names), len(labels)):
        ax.bar(i, top, color="none", edgecolor="0.5", hatch="//")
        ax.annotate("not in the fit", (i, top / 2), rotation=90, fontsize=7, ha="center",
                    va="center")
    ax.set_ylim(0, (2.6 if marked else 1.3) * top)  # room for the rotated reasons
    ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
    ax.set_xlabel(f"image (names after the common prefix {prefix!r})" if prefix else "image")
    ax.set_ylabel("reprojection RMS [px]")
    ax.set_title("per-image reprojection error (red: rejected points; hatched: not in the fit)",
                 fontsize=9)
    longest = max((len(t) for t in labels), default=1)
    fig.subplots_adjust(bottom=min(0.12 + 0.017 * longest, 0.6), left=0.1, right=0.98, top=0.9)
    return _png(fig)


def short_labels(names: Sequence[str], min_prefix: int = 4) -> tuple[list[str], str]:
    """``names`` without their common prefix (when it is at least ``min_prefix`` characters and
    leaves every name something), and that prefix (empty when kept): a row of frame names
    such as ``live_ch0_20250805092246.png`` differs only in its last characters."""
    names = [str(n) for n in names]
    prefix = os.path.commonprefix(names) if len(names) > 1 else ""
    if len(prefix) < min_prefix or any(len(n) == len(prefix) for n in names):
        return names, ""
    return [n[len(prefix):] for n in names], prefix


def residual_figure(points: np.ndarray, residuals: np.ndarray, rejected: np.ndarray,
                    image_size: tuple[int, int], pattern: str = "") -> tuple[bytes, float]:
    """Residual vectors over the image (arrows scaled, coloured by length) and their directions
    (dx, dy scatter, titled with ``pattern``, what a test found in them:
    :func:`~zoomcalib.calibrate.quality.residual_pattern`); ``rejected`` (n,) bool marks the
    observations the fit rejected.

    Parameters
    ----------
    points, residuals : (n, 2) ndarray
        Observed points and residuals (projected minus observed), px.

    Returns
    -------
    png : bytes
    scale : float
        Arrow length in image px per px of residual (also written on the figure).
    """
    plt = _pyplot()
    norm = np.linalg.norm(residuals, axis=1)
    inl = ~rejected
    p95 = float(np.percentile(norm[inl], 95)) if inl.any() else 1.0
    scale = 0.05 * max(image_size) / max(p95, 1e-9)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11.5, 4.3),
                                   gridspec_kw={"width_ratios": [1.6, 1]})
    q = ax0.quiver(points[inl, 0], points[inl, 1], residuals[inl, 0] * scale,
                   residuals[inl, 1] * scale, norm[inl], angles="xy", scale_units="xy",
                   scale=1, cmap="viridis", width=0.002)
    fig.colorbar(q, ax=ax0, label="residual length [px]", shrink=0.85)
    if rejected.any():
        ax0.scatter(points[rejected, 0], points[rejected, 1], marker="x", color=_MARK, s=30,
                    label=f"rejected ({int(rejected.sum())})")
        ax0.legend(loc="upper right", fontsize=7)
    _image_axes(ax0, image_size)
    ax0.set_title(f"residual vectors, drawn x{scale:.0f} (arrow of {p95:.3g} px = 95th "
                  "percentile)", fontsize=9)
    ax1.scatter(residuals[inl, 0], residuals[inl, 1], s=3, alpha=0.5, color="tab:blue",
                label="inliers")
    if rejected.any():
        ax1.scatter(residuals[rejected, 0], residuals[rejected, 1], marker="x", s=30,
                    color=_MARK, label="rejected")
    lim = 1.2 * float(np.max(np.abs(residuals[inl]), initial=1e-3)) if inl.any() else 1.0
    ax1.set_xlim(-lim, lim)
    ax1.set_ylim(lim, -lim)
    ax1.axhline(0, color="0.6", lw=0.7)
    ax1.axvline(0, color="0.6", lw=0.7)
    ax1.set_aspect("equal")
    ax1.set_xlabel("dx [px]")
    ax1.set_ylabel("dy [px]")
    ax1.set_title(f"residual directions: {pattern}" if pattern else "residual directions",
                  fontsize=9, wrap=True)
    ax1.legend(loc="upper right", fontsize=7)
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.12, top=0.9, wspace=0.25)
    return _png(fig), scale


def coverage_figure(points: Sequence[np.ndarray], image_size: tuple[int, int],
                    tilt_deg: np.ndarray, distance_mm: np.ndarray, grid: int,
                    reach: float) -> bytes:
    """Where the detected points fell (every view overlaid, the coverage grid and the circle
    of ``reach`` x the half-diagonal drawn), and each view's tilt against its distance."""
    from matplotlib.patches import Ellipse

    plt = _pyplot()
    w, h = image_size
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11.5, 4.0),
                                   gridspec_kw={"width_ratios": [1.6, 1]})
    view = np.concatenate([np.full(len(p), i % 20) for i, p in enumerate(points)])
    xy = np.concatenate(points)
    ax0.scatter(xy[:, 0], xy[:, 1], s=2, c=view, cmap="tab20", vmin=0, vmax=19)
    for k in range(1, grid):
        ax0.axvline(k * w / grid, color="0.8", lw=0.6)
        ax0.axhline(k * h / grid, color="0.8", lw=0.6)
    half_diag = 0.5 * np.hypot(w - 1, h - 1)
    ax0.add_patch(Ellipse(((w - 1) / 2, (h - 1) / 2), 2 * reach * half_diag,
                          2 * reach * half_diag, fill=False, ls="--", color="0.3"))
    _image_axes(ax0, image_size)
    ax0.set_title(f"detected points of all views (colour = view); dashed: {100 * reach:.0f} % "
                  "of the half-diagonal", fontsize=9)
    ax1.scatter(distance_mm, tilt_deg, s=18, color="tab:blue")
    ax1.set_xlabel("distance to the board centre [mm]")
    ax1.set_ylabel("tilt from fronto-parallel [deg]")
    ax1.set_ylim(0, max(45.0, float(np.max(tilt_deg, initial=0.0)) * 1.1))
    ax1.set_title("views: tilt and distance", fontsize=9)
    ax1.grid(alpha=0.3)
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.13, top=0.9, wspace=0.25)
    return _png(fig)


def uncertainty_figure(xs: np.ndarray, ys: np.ndarray, sigma: np.ndarray,
                       image_size: tuple[int, int], distance_mm: float, hull: np.ndarray,
                       inside: np.ndarray, diff: np.ndarray | None = None) -> bytes:
    """Projection 1-sigma (px) over the image at ``distance_mm`` as a heat map with contour
    lines at fifths of its colour range and, when given, the cross-validation difference map
    (px) beside it. ``hull`` (k, 2) px outlines where points were detected; ``inside`` (R, C)
    marks the grid cells within it, and the colour saturates at the largest value there (the
    maps grow without bound where the model is extrapolated)."""
    plt = _pyplot()
    panels = [(sigma, f"projection uncertainty at {distance_mm:.0f} mm (worst direction, "
                      "1-sigma)", "1-sigma [px]")]
    if diff is not None:
        panels.append((diff, "cross-validation: even-half vs odd-half projection",
                       "|difference| [px]"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.8 * len(panels), 4.0), squeeze=False)
    outline = np.vstack([hull, hull[:1]])
    for ax, (values, title, unit) in zip(axes[0], panels, strict=True):
        top = float(np.max(values[inside])) if inside.any() else float(np.max(values))
        im = ax.imshow(values, cmap="magma_r", vmin=0.0, vmax=max(top, 1e-9),
                       extent=(xs[0], xs[-1], ys[-1], ys[0]), interpolation="bilinear")
        levels = np.unique(np.round(np.linspace(0.0, top, 6)[1:], 12))
        if len(levels) > 1:
            ax.contour(xs, ys, values, levels=levels, colors="k", linewidths=0.6)
        ax.plot(outline[:, 0], outline[:, 1], "--", color="tab:cyan", lw=1.2)
        fig.colorbar(im, ax=ax, label=unit + ", saturated beyond the detections", shrink=0.85)
        _image_axes(ax, image_size)
        ax.set_title(title, fontsize=9)
    fig.subplots_adjust(left=0.07, right=0.97, bottom=0.13, top=0.9, wspace=0.3)
    return _png(fig)


def zoom_range_figure(zoom: np.ndarray, zoom_label: str, values: dict[str, np.ndarray],
                      sds: dict[str, np.ndarray], flagged: np.ndarray,
                      model: dict[str, tuple[np.ndarray, np.ndarray, float | None]]) -> bytes:
    """fx, cx, cy, k1 against zoom with 1-sigma bands; flagged steps ringed in red; the zoom
    model's curve and its held-out RMS where given.

    Parameters
    ----------
    zoom : (S,) ndarray
        In the user's units (``zoom_label`` names them).
    values, sds : dict of str to (S,) ndarray
        Per parameter (``fx``, ``cx``, ``cy``, ``k1``): value and 1-sigma (px; k1 unitless).
    flagged : (S,) bool ndarray
    model : dict of str to (zoom (k,), value (k,), held-out RMS or None)
    """
    plt = _pyplot()
    units = {"fx": "fx [px]", "cx": "cx [px]", "cy": "cy [px]", "k1": "k1 [1]"}
    fig, axes = plt.subplots(2, 2, figsize=(11.0, 6.6))
    order = np.argsort(zoom, kind="stable")
    for ax, name in zip(axes.ravel(), ("fx", "cx", "cy", "k1"), strict=True):
        v, s = values[name][order], sds[name][order]
        z = zoom[order]
        ax.fill_between(z, v - s, v + s, color="tab:blue", alpha=0.25, label="1-sigma band")
        ax.plot(z, v, "o-", ms=4, color="tab:blue", label="calibrated")
        if flagged.any():
            ax.scatter(zoom[flagged], values[name][flagged], s=90, facecolor="none",
                       edgecolor=_MARK, lw=1.5, label="flagged step", zorder=5)
        if name in model:
            mz, mv, held = model[name]
            label = "zoom model" + ("" if held is None else f" (held-out RMS {held:.3g})")
            ax.plot(mz, mv, "-", color="k", lw=1, label=label)
        ax.set_xlabel(zoom_label)
        ax.set_ylabel(units[name])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.08, top=0.97, hspace=0.3, wspace=0.25)
    return _png(fig)


def budget_figure(steps: Sequence[str], shares: dict[str, np.ndarray], named: np.ndarray,
                  unexplained: np.ndarray, not_smooth: np.ndarray) -> bytes:
    """The residual budget of each step: each cause's share of the held-out mean square alone
    (bars; hatched where it is not kept), what the kept causes leave and the share no error
    smooth over a view explains (lines).

    Parameters
    ----------
    steps : sequence of str
    shares : dict of str to (S,) ndarray
        Per cause, its share alone (NaN: not tried).
    named : (S, C) bool ndarray
        Whether each cause (in the order of ``shares``) is kept at each step.
    unexplained, not_smooth : (S,) ndarray
        Shares of the held-out mean square.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(11.0, 4.2))
    x = np.arange(len(steps))
    width = 0.8 / max(len(shares), 1)
    for c, (name, vals) in enumerate(shares.items()):
        pos = x - 0.4 + (c + 0.5) * width
        v = np.clip(np.nan_to_num(vals), 0.0, None)
        ax.bar(pos[named[:, c]], v[named[:, c]], width, color=f"C{c}", label=f"{name} (kept)")
        ax.bar(pos[~named[:, c]], v[~named[:, c]], width, color="none", edgecolor=f"C{c}",
               hatch="//", label=f"{name} (not kept)")
    ax.plot(x, unexplained, "k_", ms=22, mew=2, label="left by the kept causes")
    ax.plot(x, not_smooth, "x", color=_MARK, label="not smooth over a view")
    ax.set_xticks(x, steps, fontsize=8)
    ax.set_ylabel("share of the held-out mean square")
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.3, top=0.97)
    return _png(fig)


def lens_and_poses_figure(xs: np.ndarray, ys: np.ndarray, shift_px: np.ndarray,
                          image_size: tuple[int, int], outlines: np.ndarray) -> bytes:
    """Left: how far the distortion moves each pixel (px, a heat map with contours over the
    image; :func:`~zoomcalib.calibrate.quality.distortion_map`). Right: every view's board
    outline (views, 5, 3) in the camera frame (mm; the camera at the origin looking along +z),
    seen from above and behind."""
    plt = _pyplot()
    fig = plt.figure(figsize=(11.5, 4.2))
    ax0 = fig.add_subplot(1, 2, 1)
    mesh = ax0.pcolormesh(xs, ys, shift_px, shading="auto", cmap="magma")
    fig.colorbar(mesh, ax=ax0, label="distortion [px]", shrink=0.85)
    if np.ptp(shift_px) > 0:
        lines = ax0.contour(xs, ys, shift_px, levels=5, colors="w", linewidths=0.6)
        ax0.clabel(lines, fontsize=7, fmt="%.3g")
    _image_axes(ax0, image_size)
    ax0.set_title(f"distortion: up to {np.max(shift_px):.3g} px over the image", fontsize=9)
    ax1 = fig.add_subplot(1, 2, 2, projection="3d")
    for k, outline in enumerate(outlines):
        ax1.plot(outline[:, 0], outline[:, 2], -outline[:, 1], color=f"C{k % 10}", lw=0.9)
    ax1.scatter([0], [0], [0], color="k", marker="^", s=30, label="camera")
    ax1.set_xlabel("x [mm]", fontsize=8)
    ax1.set_ylabel("z (depth) [mm]", fontsize=8)
    ax1.set_zlabel("-y [mm]", fontsize=8)
    ax1.tick_params(labelsize=6)
    ax1.view_init(elev=25, azim=-60)
    ax1.set_title(f"board poses of the {len(outlines)} views (camera frame)", fontsize=9)
    ax1.legend(loc="upper left", fontsize=7)
    fig.subplots_adjust(left=0.05, right=0.97, bottom=0.1, top=0.9, wspace=0.15)
    return _png(fig)


def corners_figure(image: np.ndarray, detected: np.ndarray, projected: np.ndarray,
                   name: str, scale: float) -> bytes:
    """One image with its detected corners (green +) and the fit's projections of them (red
    x), each joined by its residual drawn ``scale`` times its length; ``image`` grey or BGR,
    ``detected`` and ``projected`` (n, 2) px."""
    plt = _pyplot()
    h, w = image.shape[:2]
    fig, ax = plt.subplots(figsize=(8.0, 8.0 * h / w + 0.6))
    shown = image if image.ndim == 2 else image[..., ::-1]
    ax.imshow(shown, cmap="gray" if image.ndim == 2 else None, interpolation="nearest")
    tips = detected + scale * (projected - detected)
    ax.plot(np.stack([detected[:, 0], tips[:, 0]]), np.stack([detected[:, 1], tips[:, 1]]),
            color="yellow", lw=0.7)
    ax.plot(detected[:, 0], detected[:, 1], "+", color="lime", ms=4, label="detected")
    ax.plot(tips[:, 0], tips[:, 1], "x", color=_MARK, ms=3,
            label=f"projected (residual drawn x{scale:.0f})")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(f"{name}: detected corners and the fit's projections", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.08, top=0.94)
    return _png(fig)
