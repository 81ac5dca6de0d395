"""Figures and the Markdown / HTML report of the study. Every number is read from the tables."""

from __future__ import annotations

import html
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["StudyTables", "study_figures", "write_report", "markdown_to_html"]


def _fmt(v, digits: int = 3) -> str:
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return str(v)
    if not np.isfinite(v):
        return "n/a"
    return f"{v:.{digits}g}"


def _table(rows: list[dict], cols: list[str], digits: int = 3) -> str:
    head = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    return head + "".join("| " + " | ".join(_fmt(r.get(c), digits) for c in cols) + " |\n"
                          for r in rows)


DETECTOR_MARKERS = {"classic": "o", "model": "s"}
DETECTOR_COLOURS = {"classic": "C0", "model": "C3"}  # where colour does not encode the zoom
BACKEND_LINES = {"opencv": "-", "bundle": "--"}


def _style_legend(ax, scatter: list[dict], extra: list | None = None,
                  coloured: bool = False) -> None:
    """Legend of the marker (detector, and its colour if ``coloured``) and line style (backend)
    of the runs present."""
    from matplotlib.lines import Line2D

    dets = [d for d in DETECTOR_MARKERS if any(s["detector"] == d for s in scatter)]
    backs = [b for b in BACKEND_LINES if any(s["backend"] == b for s in scatter)]
    handles = [Line2D([], [], color=DETECTOR_COLOURS[d] if coloured else "0.3",
                      marker=DETECTOR_MARKERS[d], ls="none",
                      label=f"{d} detector") for d in dets]
    handles += [Line2D([], [], color="0.3", ls=BACKEND_LINES[b], label=f"{b} backend")
                for b in backs]
    ax.legend(handles=(extra or []) + handles, fontsize=7, loc="best")


def _runs(scatter: list[dict], det: str, backend: str, **match) -> list[dict]:
    return [s for s in scatter if s["detector"] == det and s["backend"] == backend
            and all(abs(s[k] - v) < 1e-9 for k, v in match.items())]


def plot_fig7(scatter: list[dict], zoom: np.ndarray, path: Path) -> Path:
    """Fig. 7: detection-induced principal-point scatter against image noise, one line per zoom
    step (colour, with its bar), detector (marker) and backend (line style). With a single noise
    level, against the zoom step instead (colour: detector)."""
    from matplotlib.colors import Normalize

    from ..plots import LENS_ZOOM_LABEL, _pyplot, save_figure

    plt = _pyplot()
    noises = sorted({s["noise_dn"] for s in scatter})
    fig, ax = plt.subplots(figsize=(6.4, 4.6), dpi=120, layout="constrained")
    if len(noises) > 1:
        norm = Normalize(zoom.min(), max(zoom.max(), zoom.min() + 1e-9))
        for det, marker in DETECTOR_MARKERS.items():
            for backend, ls in BACKEND_LINES.items():
                for z in zoom:
                    pts = sorted((s["noise_dn"], s["s_det_px"])
                                 for s in _runs(scatter, det, backend, zoom=z))
                    if pts:
                        x, y = np.array(pts).T
                        ax.plot(x, y, ls, marker=marker, color=plt.cm.viridis(norm(z)), ms=4)
        bar = plt.cm.ScalarMappable(norm=norm, cmap="viridis")
        fig.colorbar(bar, ax=ax, label=LENS_ZOOM_LABEL, shrink=0.85)
        ax.set_xlabel("image noise [DN of 255]")
        title = "Fig. 7: principal-point scatter from detection noise"
    else:
        for det, marker in DETECTOR_MARKERS.items():
            for backend, ls in BACKEND_LINES.items():
                pts = sorted((s["zoom"], s["s_det_px"]) for s in _runs(scatter, det, backend))
                if pts:
                    x, y = np.array(pts).T
                    ax.plot(x, y, ls, marker=marker, color=DETECTOR_COLOURS[det], ms=5)
        ax.set_xlabel(LENS_ZOOM_LABEL)
        noise = f"{noises[0]:g} DN" if noises else "no runs"
        title = (f"Fig. 7: principal-point scatter from detection noise, one noise level "
                 f"({noise}): against zoom")
    ax.set_ylabel("scatter of calibrated (cx, cy) [px]")
    ax.set_yscale("log")
    ax.set_title(_wrap(title, 6.4), fontsize=9)
    _style_legend(ax, scatter, coloured=len(noises) <= 1)
    ax.grid(alpha=0.3, which="both")
    save_figure(fig, path)
    return path


def _wrap(text: str, width_in: float) -> str:
    from ..plots import wrap_title

    return wrap_title(text, width_in)


def plot_scatter_vs_focal_length(mech: list[dict], scatter: list[dict], path: Path) -> Path:
    """Mechanical scatter and shift against the detection-induced scatter (middle noise level),
    against focal length."""
    from matplotlib.lines import Line2D

    from ..plots import _pyplot, save_figure

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.6), dpi=120, layout="constrained")
    efl = np.array([m["efl_mm"] for m in mech])
    efl_of = {round(m["zoom"], 9): m["efl_mm"] for m in mech}
    ax.plot(efl, [m["s_mech_px"] for m in mech], "k-o")
    ax.plot(efl, [m["shift_px"] for m in mech], "k:^")
    noise_ref = sorted({s["noise_dn"] for s in scatter})
    ref = noise_ref[len(noise_ref) // 2] if noise_ref else None
    for det, marker in DETECTOR_MARKERS.items():
        for backend, ls in BACKEND_LINES.items():
            pts = sorted((efl_of[round(s["zoom"], 9)], s["s_det_px"])
                         for s in _runs(scatter, det, backend) if s["noise_dn"] == ref
                         and round(s["zoom"], 9) in efl_of)
            if pts:
                x, y = np.array(pts).T
                ax.plot(x, y, ls, color=DETECTOR_COLOURS[det], marker=marker, ms=4)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("effective focal length [mm]")
    ax.set_ylabel("principal-point error [px]")
    mech_handles = [Line2D([], [], color="k", marker="o", label="mechanics: scatter"),
                    Line2D([], [], color="k", ls=":", marker="^",
                           label="mechanics: systematic shift")]
    _style_legend(ax, scatter, mech_handles, coloured=True)
    ax.grid(alpha=0.3, which="both")
    noise = f"noise {ref:g} DN" if ref is not None else "no detection runs"
    ax.set_title(_wrap("Mechanical against detection-induced principal-point error (detection "
                       f"at {noise})", 6.4), fontsize=9)
    save_figure(fig, path)
    return path


def plot_fig6(fig6: dict, width_px: int, height_px: int, path: Path) -> Path:
    """Fig. 6: the detection errors of one calibration view, per detector, as arrows."""
    from ..plots import _pyplot, save_figure

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(fig6), figsize=(5.5 * len(fig6), 4.6), dpi=110,
                             layout="constrained")
    for ax, (det, d) in zip(np.atleast_1d(axes), fig6.items(), strict=True):
        p, e = np.array(d["points"]), np.array(d["errors"])
        norm = np.linalg.norm(e, axis=1)
        scale = 40.0 / max(norm.max(), 1e-9)
        ax.quiver(p[:, 0], p[:, 1], e[:, 0] * scale, e[:, 1] * scale, angles="xy",
                  scale_units="xy", scale=1, width=0.003)
        ax.set_xlim(0, width_px)
        ax.set_ylim(height_px, 0)
        ax.set_aspect("equal")
        ax.set_xlabel("x [px]")
        ax.set_ylabel("y [px]")
        ax.set_title(_wrap(f"{det}: RMS {np.sqrt(np.mean(norm**2)):.4f} px (arrows "
                           f"x{scale:.0f})", 5.5), fontsize=9)
    fig.suptitle("Fig. 6: detection errors (detected - true) of one calibration view",
                 fontsize=10)
    save_figure(fig, path)
    return path


def study_figures(out: Path, mech_dense: list[dict], mech: list[dict], scatter: list[dict],
                  fig6: dict | None, dense_zoom: np.ndarray) -> dict[str, Path]:
    """Fig. 5 (spiral, from the dense mechanics table), Fig. 6 (detection errors of one set),
    Fig. 7 (scatter vs noise) and the scatter versus focal length (at the study's steps)."""
    from ..camera import DEFAULT_SENSOR
    from ..plots import plot_principal_point_spiral

    mean = np.array([[m["cx_mean"], m["cy_mean"]] for m in mech_dense])
    std = np.array([[m["cx_std"], m["cy_std"]] for m in mech_dense])
    zoom = np.array([m["zoom"] for m in mech])
    files = {"spiral": plot_principal_point_spiral(
        dense_zoom, mean, std, out / "fig5_spiral.png", centre_px=DEFAULT_SENSOR.centre_px,
        title="Fig. 5: principal point from the mechanics (mean, 1-sigma)"),
        "fig7": plot_fig7(scatter, zoom, out / "fig7_scatter_vs_noise.png"),
        "vs_zoom": plot_scatter_vs_focal_length(mech, scatter,
                                                out / "scatter_vs_focal_length.png")}
    if fig6:
        files["fig6"] = plot_fig6(fig6, DEFAULT_SENSOR.width_px, DEFAULT_SENSOR.height_px,
                                  out / "fig6_detection_errors.png")
    return files


@dataclass(frozen=True)
class StudyTables:
    """The study's results the report reads, rows as in the CSV files written beside it.

    Attributes
    ----------
    mech : list of dict
        The mechanics per zoom step (``mechanics.csv``).
    scatter : list of dict
        The detection-induced scatter (``detection_scatter.csv``).
    comparison : list of dict
        Mechanics against detection per case (``comparison.csv``).
    claims : list of dict
        The paper's side claims (``claims.csv``).
    timing : dict
        Seconds per stage (``timing.csv``).
    lensfun : dict, optional
        Distortion of real zoom lenses (``lensfun.csv``); None or empty: not reported.
    """

    mech: list[dict]
    scatter: list[dict]
    comparison: list[dict]
    claims: list[dict]
    timing: dict
    lensfun: dict | None = None


def _verdict_lines(comparison: list[dict]) -> list[str]:
    """The report's verdict: per detector and backend at the middle noise level, then the
    count of each verdict over all cases."""
    noise_levels = sorted({c["noise_dn"] for c in comparison})
    ref = noise_levels[len(noise_levels) // 2] if noise_levels else None
    lines = ["## Verdict", ""]
    for det in sorted({c["detector"] for c in comparison}):
        for backend in sorted({c["backend"] for c in comparison}):
            sel = [c for c in comparison if c["detector"] == det and c["backend"] == backend
                   and c["noise_dn"] == ref]
            if not sel:
                continue
            parts = [f"zoom {c['zoom']:.2f} (EFL {c['efl_mm']:.0f} mm): {c['verdict']} "
                     f"(ratio {_fmt(c['ratio'])}, 95 % {_fmt(c['ratio_lo'])}-"
                     f"{_fmt(c['ratio_hi'])})" for c in sel]
            lines.append(f"- **{det} detector, {backend} backend, noise {ref:g} DN** — "
                         + "; ".join(parts) + ".")
    n_mech = sum(c["verdict"] == "mechanics dominate" for c in comparison)
    n_det = sum(c["verdict"] == "detection dominates" for c in comparison)
    lines += ["", f"Over all {len(comparison)} cases (steps x noise x detectors x backends): "
              f"mechanics dominate in {n_mech}, detection dominates in {n_det}, comparable in "
              f"{len(comparison) - n_mech - n_det}. The paper's conclusion (detection dominates, "
              "so mechanics can be neglected) holds where the verdict says \"detection "
              "dominates\" and fails where it says \"mechanics dominate\". Source: "
              "`comparison.csv`.", ""]
    return lines


def write_report(out: Path, config: dict, command: str, versions: dict, tables: StudyTables,
                 figures: dict[str, Path]) -> list[Path]:
    """Write ``report.md`` and ``report.html`` in ``out``: the study's ``config``
    (:meth:`~zoomcalib.study.paper.StudyConfig.to_dict`), the ``command`` that ran it, the
    package ``versions``, its ``tables`` and its ``figures`` (:func:`study_figures`)."""
    mech, scatter, comparison = tables.mech, tables.scatter, tables.comparison
    lines = ["# Detection error against mechanical error across the zoom range", ""]
    lines += [f"Command: `{command}`", "",
              f"Seed {config['seed']}; lens {config['lens']}; tolerances "
              f"{config['tolerances'] or 'built-in'} x {config['tolerance_scale']:g}; "
              f"{config['steps']} zoom steps; noise "
              f"{', '.join(f'{n:g}' for n in config['noise_dn'])} DN; {config['seeds']} "
              f"calibration sets of {config['views']} views per step and noise; "
              f"{config['mc_samples']} mechanical draws per step; rendered with a "
              f"{config.get('psf', 'gaussian')} PSF and {config['blur_px']:g} px of blur.", "",
              "Versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()), ""]
    lines += _verdict_lines(comparison)
    lines += ["## Mechanics (Fig. 5)", "", f"![spiral]({figures['spiral'].name})", "",
              "The spiral and the trends are drawn from `mechanics_dense.csv` (41 zoom states); "
              "the table gives the study's zoom steps.", "",
              _table(mech, ["zoom", "efl_mm", "cx_mean", "cy_mean", "cx_std", "cy_std",
                            "s_mech_px", "shift_px"], digits=5), "Source: `mechanics.csv`.", ""]
    lines += ["## Detection-induced scatter (Fig. 7)", "", f"![fig7]({figures['fig7'].name})",
              "", _table(scatter, ["zoom", "noise_dn", "detector", "backend", "n_sets",
                                   "n_failed", "sd_cx", "sd_cy", "s_det_px",
                                   "predicted_sd_px", "detection_rms_px"]),
              "Source: `detection_scatter.csv` (per-set values in `detection_runs.csv`). "
              "`predicted_sd_px` is the backend's own 1-sigma, RMS over the sets.", ""]
    if "fig6" in figures:
        lines += ["## Detection errors of one set (Fig. 6)", "",
                  f"![fig6]({figures['fig6'].name})", ""]
    lines += ["## Comparison", "", f"![vs zoom]({figures['vs_zoom'].name})", "",
              _table(comparison, ["zoom", "efl_mm", "noise_dn", "detector", "backend",
                                  "s_mech_px", "s_det_px", "ratio", "ratio_lo", "ratio_hi",
                                  "verdict", "shift_px", "shift_over_s_det"]),
              "Source: `comparison.csv`. `ratio = s_mech / s_det`, 95 % interval from the F "
              "law of the two variance estimates.", ""]
    lines += ["## The paper's side claims", "",
              _table(tables.claims, ["claim", "measure", "value", "holds"]),
              "Source: `claims.csv`.", ""]
    if tables.lensfun:
        lines += ["Distortion of real zoom lenses (lensfun database): "
                  + ", ".join(f"{k} {_fmt(v)}" for k, v in tables.lensfun.items()
                              if not isinstance(v, list | dict)) + ". Source: `lensfun.csv`.",
                  ""]
    lines += ["## Time", "", ", ".join(f"{k} {v:.1f} s" for k, v in tables.timing.items()), ""]
    md = "\n".join(lines)
    md_path = out / "report.md"
    md_path.write_text(md)
    html_path = out / "report.html"
    html_path.write_text(markdown_to_html(md, "zoomcalib study"))
    return [md_path, html_path]


def markdown_to_html(md: str, title: str) -> str:
    """HTML for the subset of Markdown the report uses (headings, lists, tables, images,
    inline code and bold)."""

    def inline(text: str) -> str:
        t = html.escape(text)
        t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
        t = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)
        return t

    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
           "</title><style>body{font-family:sans-serif;max-width:70em;margin:auto}"
           "table{border-collapse:collapse;font-size:85%}td,th{border:1px solid #bbb;"
           "padding:2px 6px}img{max-width:100%}</style></head><body>"]
    rows: list[list[str]] = []
    in_list = False
    for line in md.splitlines() + [""]:
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if not all(set(c) <= {"-"} for c in cells):
                rows.append(cells)
            continue
        if rows:
            out.append("<table><tr>" + "".join(f"<th>{inline(c)}</th>" for c in rows[0])
                       + "</tr>" + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r)
                                           + "</tr>" for r in rows[1:]) + "</table>")
            rows = []
        if line.startswith("- "):
            if not in_list:
                out.append("<ul>")
                in_list = True
            out.append(f"<li>{inline(line[2:])}</li>")
            continue
        if in_list:
            out.append("</ul>")
            in_list = False
        m = re.match(r"(#+) (.*)", line)
        img = re.match(r"!\[([^]]*)\]\(([^)]+)\)", line)
        if m:
            n = len(m.group(1))
            out.append(f"<h{n}>{inline(m.group(2))}</h{n}>")
        elif img:
            out.append(f"<p><img alt='{html.escape(img.group(1))}' "
                       f"src='{html.escape(img.group(2))}'></p>")
        elif line.strip():
            out.append(f"<p>{inline(line)}</p>")
    out.append("</body></html>")
    return "\n".join(out)
