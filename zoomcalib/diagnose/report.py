"""``diagnosis.json``, ``report.md`` and the figures of a diagnosis."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import write_json
from ..plots import _pyplot, save_figure, wrap_title
from .discrepancy import Diagnosis, LinearFit
from .model import Context, design_matrix
from .table import ZoomTable

__all__ = ["write_diagnosis", "plot_path", "plot_residuals"]


def _dense_context(diag: Diagnosis, n: int = 400) -> Context:
    """Lens states spanning the measured focal range, for drawing the simulated path."""
    z = np.linspace(diag.z.min(), diag.z.max(), n)
    if diag.response is None:  # z is the log focal length on [0, 1]
        fx = np.exp(np.log(diag.table.fx.min()) + z * np.log(diag.table.fx.max()
                                                              / diag.table.fx.min()))
    else:
        fx = np.interp(z, diag.response.zoom_grid, diag.response.efl_grid) / diag.pitch_mm
    zeros = np.zeros(n)
    table = ZoomTable(zoom=z, fx=fx, fy=fx, cx=zeros, cy=zeros, sd_cx=zeros, sd_cy=zeros,
                      source="dense")
    return Context.build(table, z, diag.response)


def _fitted(fit: LinearFit, ctx: Context) -> np.ndarray:
    """(N, 2) principal points of a fit at the rows of ``ctx``."""
    return (design_matrix(fit.terms, ctx) @ fit.params).reshape(-1, 2)


def _focal(diag: Diagnosis) -> tuple[np.ndarray, str]:
    """(N,) focal length of the rows and its axis label: mm with a lens model, else px."""
    if diag.pitch_mm is None:
        return diag.table.fx, "focal length fx [px]"
    return diag.table.fx * diag.pitch_mm, "focal length [mm] (from measured fx)"


ZOOM_LABEL = "zoom (the table's zoom column)"


def plot_path(diag: Diagnosis, path: str | Path) -> Path:
    """Measured principal points against the simulation's path (baseline fit) and the extension.

    The measured points are coloured by the table's zoom (the user's unit), their mean per zoom
    setting joined in zoom order. The baseline is drawn along the whole measured focal range
    (its terms depend on the lens state only); the extended model at the measured rows, because
    its extra terms may depend on the direction, capture order or focus of each row.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 6.0), dpi=120, layout="constrained")
    dense = _dense_context(diag)
    curve = _fitted(diag.baseline, dense)
    ax.plot(curve[:, 0], curve[:, 1], "-", color="0.45", lw=1.0,
            label="simulated path (baseline fit)" if diag.response is not None
            else "smooth path in log f (baseline fit)")
    meas = diag.table.principal_point
    groups = diag.table.zoom_groups()  # labels in increasing zoom
    per_zoom = np.array([meas[groups == g].mean(0) for g in np.unique(groups)])
    ax.plot(per_zoom[:, 0], per_zoom[:, 1], ":", color="0.55", lw=0.9, zorder=1,
            label="measured, mean per zoom, in zoom order")
    sd = np.maximum(diag.sigma_px, 1e-9)
    sc = ax.scatter(meas[:, 0], meas[:, 1], c=diag.table.zoom, cmap="viridis", s=16, zorder=3,
                    label="measured")
    ax.errorbar(meas[:, 0], meas[:, 1], xerr=sd, yerr=sd, fmt="none", ecolor="0.7", lw=0.6,
                zorder=2)
    if diag.extended is not None:
        ctx = Context.build(diag.table, diag.z, diag.response)
        ext = _fitted(diag.extended.fit, ctx)
        ax.plot(ext[:, 0], ext[:, 1], "x", color="C3", ms=5,
                label=f"extended ({diag.cause}) at the rows")
    ax.invert_yaxis()  # image convention: y down
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("cx [px]")
    ax.set_ylabel("cy [px]")
    ax.legend(fontsize=7, loc="best")
    fig.colorbar(sc, ax=ax, label=ZOOM_LABEL, shrink=0.8)
    against = ("simulated through the lens model" if diag.response is not None
               else "a smooth path in log f (no lens model: nothing simulated)")
    ax.set_title(wrap_title(f"Principal point: measured vs {against} ({diag.table.source})",
                            5.0), fontsize=9)
    save_figure(fig, path)
    return Path(path)


def _order_colour(table: ZoomTable) -> tuple[np.ndarray, str, str]:
    """Values that colour the right-hand residual panels, the colour bar's label and the
    panel's title: capture order if the table has it, else the zoom."""
    if table.sequence is not None:
        return table.sequence, "capture order (the table's sequence column)", "capture order"
    return table.zoom, f"{ZOOM_LABEL}; no capture order in the table", "zoom"


def plot_residuals(diag: Diagnosis, path: str | Path) -> Path:
    """Residuals against focal length, before (baseline) and after the extension, coloured by
    the direction of the last zoom move (left) and by capture order, or by the zoom when the
    table has no capture order (right)."""
    plt = _pyplot()
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    fig, axes = plt.subplots(2, 2, figsize=(10, 6.8), dpi=110, sharex=True, sharey="row",
                             layout="constrained")
    efl, focal_label = _focal(diag)
    after = diag.extended.fit if diag.extended is not None else diag.baseline
    colour, colour_label, colour_name = _order_colour(diag.table)
    direction = (diag.table.direction if diag.table.direction is not None
                 else np.zeros(diag.table.n))
    for row, (fit, name) in enumerate([(diag.baseline, "baseline"),
                                       (after, f"extended: {diag.cause}")]):
        r = fit.residual_px
        ax = axes[row, 0]
        for sign, tint, label in [(1.0, "C0", "in"), (-1.0, "C1", "out"),
                                  (0.0, "0.5", "unknown")]:
            m = direction == sign
            if m.any():
                ax.plot(efl[m], r[m, 0], "o", color=tint, ms=4, label=f"cx, {label}")
                ax.plot(efl[m], r[m, 1], "s", color=tint, ms=4, mfc="none",
                        label=f"cy, {label}")
        ax.legend(fontsize=6, ncol=2)
        ax = axes[row, 1]
        sc = ax.scatter(efl, r[:, 0], c=colour, cmap="plasma", s=14, marker="o")
        ax.scatter(efl, r[:, 1], c=colour, cmap=sc.cmap, norm=sc.norm, s=18, marker="x")
        fig.colorbar(sc, ax=ax, label=wrap_title(colour_label, 2.2, 8.0))
        for a in axes[row]:
            a.set_ylabel(f"{name}\nresidual [px]")
            a.set_xlabel(focal_label)
            a.axhline(0.0, color="0.6", lw=0.6)
            a.set_xscale("log")
            a.xaxis.set_major_formatter(ScalarFormatter())
            a.xaxis.set_minor_formatter(NullFormatter())
    axes[0, 0].set_title("by direction of the last zoom move (o cx, square cy)", fontsize=8)
    axes[0, 1].set_title(f"by {colour_name} (o cx, x cy)", fontsize=8)
    save_figure(fig, path)
    return Path(path)


def _fmt_params(params: dict, sds: dict) -> str:
    return ", ".join(f"{k} = {v:.4g} ± {sds[k]:.2g}" for k, v in params.items()) or "-"


def _polar(params: dict) -> str:
    """Magnitude and direction of (x, y) parameter pairs, e.g. ``compensator: 50.2 um at
    211 deg`` (direction measured from +x towards +y, image convention)."""
    out = []
    for kx, vx in params.items():
        if "_x_" not in kx:
            continue
        ky = kx.replace("_x_", "_y_", 1)
        if ky in params:
            name, unit = kx.split("_x_", 1)
            ang = np.degrees(np.arctan2(params[ky], vx)) % 360.0
            out.append(f"{name}: {np.hypot(vx, params[ky]):.4g} {unit} at {ang:.0f} deg")
    return "; ".join(out)


def report_markdown(diag: Diagnosis, doc: dict) -> str:
    """A short human report of the diagnosis."""
    t = diag.table
    lines = [f"# Diagnosis of {t.source}", ""]
    lines += [_verdict(diag, doc), ""]
    ev = doc["distortion_evidence"]
    if doc["ambiguous_with"]:
        by_p = (ev or {}).get("ambiguous")
        close = [c for c in doc["ambiguous_with"] if c != by_p]
        why = ([f"{', '.join(close)}: BIC within {doc['selection']['ambiguity_bic']:g}"]
               if close else [])
        if by_p in doc["ambiguous_with"]:
            why.append(f"{by_p}: within {doc['selection']['bic_margin']:g} of the tilt on the "
                       "principal points and p1, p2")
        lines += [f"Not told apart from: {', '.join(doc['ambiguous_with'])} ({'; '.join(why)});"
                  " their signatures are nearly the same on this lens at this noise.", ""]
    if ev:
        lines += ["With the tangential distortion p1, p2 fitted beside the principal points: "
                  + ", ".join(f"{c} delta BIC {v['delta_bic']:.1f}"
                              for c, v in ev["causes"].items())
                  + f" (margin {ev['margin']:.1f}; "
                  + (f"{ev['excluded']} contradicted)." if ev["excluded"]
                     else f"{ev['required']} named by it)." if ev.get("required")
                     else "not decisive).")
                  + "".join(f" It chose the variant of {c}: {v}."
                            for c, v in (ev.get("restricted") or {}).items()), ""]
    lines += _setting_lines(diag, doc) + [""]
    b, e = doc["baseline"], doc["extended"]
    base_name = "paper's model" if diag.response is not None else "smooth path in log f"
    lines += ["| model | rms [px] | chi2/dof | held-out cv_rms [px] | held-out normalised "
              "| parameters |", "|---|---|---|---|---|---|",
              f"| baseline ({base_name}) | {b['rms_px']:.3g} | {b['chi2_dof']:.3g} | "
              f"{b['cv_rms_px']:.3g} | {b['cv_norm_rms']:.3g} | {b['n_params']} |",
              f"| extended ({e['cause']}) | {e['rms_px']:.3g} | {e['chi2_dof']:.3g} | "
              f"{e['cv_rms_px']:.3g} | {e['cv_norm_rms']:.3g} | {e['n_params']} |", "",
              f"Gain, held-out RMS of sigma-normalised residuals (baseline / extended, at the "
              f"extended model's noise): {doc['gain']['cv_norm_ratio']:.3g}; in px: "
              f"{doc['gain']['cv_rms_ratio']:.3g}", ""]
    for c in doc["causes"]:
        lines += [f"`{c['cause']}` ({c['variant']}; BIC rises by {c['drop_bic']:.1f} without it): "
                  + _fmt_params(c["params"], c["params_sd"])
                  + (f". As magnitude and direction: {_polar(c['params'])}"
                     if _polar(c["params"]) else "")
                  + (f". In the model by other evidence: {c['evidence']}"
                     if c.get("evidence") else ""), ""]
    lines += _check_lines(doc["explained"])
    lines += ["## Each cause alone", "",
              "| cause | variant | delta BIC | cv_rms [px] | parameters |",
              "|---|---|---|---|---|"]
    for c in doc["candidates"]:
        lines.append(f"| {c['cause']} | {c['variant']} | {c['delta_bic']:.1f} | "
                     f"{c['cv_rms_px']:.3g} | {_fmt_params(c['params'], c['params_sd'])} |")
    if doc["skipped"]:
        lines += ["", "Not testable with this table: " + "; ".join(
            f"{s['cause']} ({s['reason']})" for s in doc["skipped"])]
    if doc.get("data_advice"):
        lines += ["", "## What more data would tell", ""] + [f"- {a}" for a in doc["data_advice"]]
    lines += ["", f"Rule: {doc['selection']['rule']} (bic_margin "
              f"{doc['selection']['bic_margin']:g}).", "",
              "Figures: `path.png` (the measured principal point against "
              + ("the path simulated through the lens model" if diag.response is not None
                 else "a smooth path in log f: no lens model, nothing simulated")
              + "), `residuals.png` (residuals before and after the extension).", ""]
    return "\n".join(lines)


def _verdict(diag: Diagnosis, doc: dict) -> str:
    """The one-line answer."""
    causes = ", ".join(f"`{c['cause']}`" for c in doc["causes"])
    if diag.cause == "unexplained":
        what = doc["explained"]["remaining"]
        return (f"**Not explained.** {causes} improve{'s' if len(doc['causes']) == 1 else ''} "
                f"the fit but do not explain the table: {what}." if causes else
                f"**Not explained.** No listed cause improves the fit, and the model leaves "
                f"{what}.")
    if diag.cause == "none":
        return "**Cause: `none`**: no extension beats the baseline significantly."
    more = f" (with {', '.join(c['cause'] for c in doc['causes'][1:])})" if len(
        doc["causes"]) > 1 else ""
    checked = ("" if doc["explained"]["explained"] else
               " The fit could not be checked (no repeated settings, sigmas or lens model).")
    return f"**Cause: `{diag.cause}`**{more}: the selected model explains the table.{checked}"


def _setting_lines(diag: Diagnosis, doc: dict) -> list[str]:
    """The table, lens, pitch and noise in a few bullets."""
    t = diag.table
    noise = doc["noise"]
    fitted = (f"; estimated scales: table sigmas x{noise['sigma_scale']:.3g}, play "
              f"x{noise['play_scale']:.3g} ({noise['play_shape']})" if "sigma_scale" in noise
              else "")
    lines = [f"- {t.n} rows, {len(np.unique(t.zoom_groups()))} zoom settings; "
             + (f"lens `{diag.response.lens.name}`, moving groups "
                f"{', '.join(diag.response.groups)}" if diag.response is not None else
                "no lens model (`--lens none`)")]
    if diag.response is not None:
        pitch = f"{diag.pitch_mm:.6g} mm"
        if diag.pitch_fit:
            pitch += (f" (fitted: ± {diag.pitch_fit['sd_mm']:.2g} mm, admissible "
                      f"{diag.pitch_fit['range_mm'][0]:.5g}-{diag.pitch_fit['range_mm'][1]:.5g}"
                      " mm)")
            if diag.pitch_fit["at_range_end"]:
                pitch += (" **at an end of the admissible range: the data do not determine the "
                          f"pitch; give it with --pixel-pitch. The lens {diag.response.lens.name}"
                          " may not be this camera's, and what follows assumes it is**")
        efl = t.fx * diag.pitch_mm
        lines.append(f"- pixel pitch {pitch}; measured focal lengths {efl.min():.2f}-"
                     f"{efl.max():.2f} mm (lens states {diag.z.min():.3f}-{diag.z.max():.3f})")
    measured = "sigmas from the table" if t.has_sd else "unknown"
    lines.append(f"- noise per row: measurement {measured} and play, RMS "
                 f"{noise['rms_sigma_px']:.3g} px (play alone {noise['rms_play_px']:.3g} px)"
                 f"{fitted}")
    return lines


def _check_lines(check: dict) -> list[str]:
    """The absolute fit check as a short table."""
    lines = ["## Does the selected model explain the table?", "",
             f"explained: **{check['explained']}**"
             + (f" ({check['remaining']})" if check["remaining"] else ""), ""]
    if check.get("noise_scale") is not None:
        lines += [f"Scatter {check['noise_scale']:.3g}x what the table's sigmas and the "
                  f"tolerance file claim (the table's sigmas alone without a lens model; limit "
                  f"{check['noise_scale_max']:g}); chi2/dof at that noise "
                  f"{check['chi2_dof_assumed']:.3g}.", ""]
    lines += ["| structure left over | F | dof | p | significant |", "|---|---|---|---|---|"]
    for name, t in check["tests"].items():
        lines.append(f"| {name} | {t['F']:.3g} | {t['q']}, {t['dof']} | {t['p_value']:.2g} | "
                     f"{t['significant']} |" if t["tested"] else
                     f"| {name} | - | - | - | not testable |")
    return lines + ["", f"(F-tests at family-wise alpha {check['alpha']:g}.)", ""]


def write_diagnosis(diag: Diagnosis, out: str | Path) -> list[Path]:
    """Write ``diagnosis.json``, ``report.md``, ``path.png`` and ``residuals.png`` to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    doc = diag.to_dict()
    files = [write_json(out / "diagnosis.json", doc)]
    md = out / "report.md"
    md.write_text(report_markdown(diag, doc))
    files += [md, plot_path(diag, out / "path.png"), plot_residuals(diag, out / "residuals.png")]
    return files
