"""Figures. Matplotlib is imported lazily with the non-interactive Agg backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_principal_point_spiral"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_principal_point_spiral(zoom: np.ndarray, mean_px: np.ndarray, std_px: np.ndarray,
                                path: str | Path, title: str = "",
                                centre_px: np.ndarray | None = None) -> Path:
    """The paper's Fig. 5: mean principal point across zoom with its 1-sigma ellipses.

    Parameters
    ----------
    zoom : (Z,) ndarray
    mean_px, std_px : (Z, 2) ndarray
        Mean (cx, cy) and its 1-sigma scatter per zoom state, px (OpenCV convention).
    path : str or Path
        Output PNG.
    centre_px : (2,) ndarray, optional
        Marked as the nominal image centre.
    """
    from matplotlib.patches import Ellipse

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 6.0), dpi=120)
    ax.plot(mean_px[:, 0], mean_px[:, 1], "-", color="0.6", lw=0.8, zorder=1)
    sc = ax.scatter(mean_px[:, 0], mean_px[:, 1], c=zoom, cmap="viridis", s=14, zorder=3)
    for (x, y), (sx, sy), z in zip(mean_px, std_px, zoom, strict=True):
        ax.add_patch(Ellipse((x, y), 2 * sx, 2 * sy, fill=False, lw=0.7,
                             color=plt.cm.viridis(z), zorder=2))
    label_every = max(1, len(zoom) // 10)
    for i in range(0, len(zoom), label_every):
        ax.annotate(f"{100 * zoom[i]:.0f}%", mean_px[i], textcoords="offset points",
                    xytext=(4, 4), fontsize=7)
    if centre_px is not None:
        ax.plot(*centre_px, "k+", ms=10, label="sensor centre")
        ax.legend(loc="upper right", fontsize=8)
    span = np.max(np.abs(mean_px - mean_px.mean(0)) + std_px) * 1.15 + 1e-6
    cx, cy = mean_px.mean(0)
    ax.set_xlim(cx - span, cx + span)
    ax.set_ylim(cy + span, cy - span)  # image convention: y down
    ax.set_aspect("equal")
    ax.set_xlabel("cx [px]")
    ax.set_ylabel("cy [px]")
    ax.set_title(title or "Principal point across zoom (mean, 1-sigma ellipses)", fontsize=9)
    fig.colorbar(sc, ax=ax, label="zoom", shrink=0.8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
