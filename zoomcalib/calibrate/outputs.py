"""What a calibrate run writes: the zoom table and its rows, ``calibration.json``'s ``meta``,
the zoom model, the figures and the run's manifest (:func:`zoomcalib.calibrate.run.
calibrate_folder` calls them once the steps are calibrated and judged).

- :func:`table_row` / :func:`table_rows`: one ``zoom_calibration.csv`` row per step, from its
  table backend's result, with its flags, status and capture session;
- :func:`unsmoothed_rows`: the zoom-wide rows of the adjustment's solve without the smoothness
  prior (:data:`UNSMOOTHED_TABLE`), for the diagnosis;
- :func:`fit_zoom_model`: ``zoom_model.json`` (the adjustment's posterior carried between the
  steps, or curves fitted to the table);
- :func:`write_results`, :func:`run_meta`, :func:`write_figures`, :func:`write_run_manifest`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..pool import map_in_processes
from .guards import write_manifest
from .io import (
    KEYSTONE_COLUMNS,
    PP_CORRELATION_FILE,
    write_calibration,
    write_principal_point_correlation,
    write_zoom_table,
)
from .result import DIST_NAMES, CalibrationResult, residual_vectors

if TYPE_CHECKING:
    from .run import CalibrateRun


#: Beside ``zoom_calibration.csv`` of a zoom-wide run: the rows of its solve without the
#: smoothness prior (:func:`unsmoothed_rows`), which ``diagnose`` takes for that table.
UNSMOOTHED_TABLE = "zoom_calibration_unsmoothed.csv"


def unsmoothed_rows(run: CalibrateRun, rows: list[dict]) -> list[dict]:
    """The zoom-wide rows of ``rows`` with fx, fy, cx, cy and their sigmas from the
    adjustment's solve without the smoothness prior
    (:attr:`~zoomcalib.calibrate.zoomwide.ZoomWideResult.unsmoothed`; mode ``zoom-wide, no
    prior``): rows the prior does not tie together, for the diagnosis. The other columns
    (distortion, status, flags) are the adjustment's. Empty without a zoom-wide adjustment
    or when its solve without the prior had no covariance."""
    free = getattr(run.zoom_wide, "unsmoothed", None) or {}
    out = []
    for row in rows:
        own = free.get(row["step"])
        if own is None or row.get("mode") != "zoom-wide":
            continue
        out.append(row | {k: own[k] for k in ("fx", "fy", "cx", "cy", "sd_fx", "sd_fy",
                                              "sd_cx", "sd_cy")}
                   | {"mode": "zoom-wide, no prior"})
    return out


def table_row(step: str, zoom: float | None, extras: dict, res: CalibrationResult) -> dict:
    """The ``zoom_calibration.csv`` row of one step: every distortion term the model has
    (k1..k3 always, k4..k6 for the rational model) with its 1-sigma, and the backend."""
    row = {"step": step, "zoom": np.nan if zoom is None else zoom, "fx": res.fx, "fy": res.fy,
           "cx": res.cx, "cy": res.cy, "backend": res.backend,
           "mode": res.info.get("mode", "per-step"),
           "converged": res.converged}
    for k in ("fx", "fy", "cx", "cy"):
        row[f"sd_{k}"] = res.sd.get(k, np.nan)
    n_terms = max(5, len(res.dist))
    for i, name in enumerate(DIST_NAMES[:n_terms]):
        row[name] = float(res.dist[i]) if i < len(res.dist) else 0.0
        row[f"sd_{name}"] = res.sd.get(name, np.nan)
    row["rms_px"] = res.rms_px
    row["n_views"] = len(res.per_view_rms_px)
    keystone = res.info.get("keystone_response")
    if keystone:
        values = np.vstack([keystone["absorption"], keystone["tangential"]]).ravel()
        row.update(zip(KEYSTONE_COLUMNS, values.tolist(), strict=True))
    for k in ("direction", "sequence", "focus", "temperature"):
        if extras.get(k) not in (None, ""):
            row[k] = extras[k]
    return row


def write_results(run: CalibrateRun, out: Path, meta: dict, rows: list[dict],
                  log: Callable[[str], None]) -> None:
    """``calibration.json`` and ``.yml``, and for a zoom set (``rows``: the zoom table's, else
    empty) ``zoom_calibration.csv``, its unsmoothed twin with the correlation of that twin's
    principal points, and the zoom model."""
    if run.results:
        run.files += list(write_calibration(out, run.results, meta))
    if rows:
        run.files.append(write_zoom_table(out / "zoom_calibration.csv", rows))
        unsmoothed = unsmoothed_rows(run, rows)
        if unsmoothed:
            run.files.append(write_zoom_table(out / UNSMOOTHED_TABLE, unsmoothed))
            correlation = getattr(run.zoom_wide, "unsmoothed_pp_correlation", None)
            if correlation is not None:
                run.files.append(write_principal_point_correlation(
                    out / PP_CORRELATION_FILE, list(run.zoom_wide.unsmoothed), correlation))
        fit_zoom_model(run, [r for r in rows if r["status"] != "unusable"], out, log)


def run_meta(run: CalibrateRun, settings: dict, provenance: dict[str, dict]) -> dict:
    """``calibration.json``'s ``meta``: the run's ``settings``, its failures, table backends,
    flags, detections, cross-validation and zoom-wide adjustment."""
    meta = settings | {
        "failures": run.failures, "partial": run.partial_message(),
        "detections": {s: {k: v for k, v in p.items() if k != "images"}
                       for s, p in provenance.items()},
        "left_out": run.left_out, "copies": run.copies, "ignored_images": run.ignored,
        "table_backend": run.table_backend, "flags": run.flags,
        "flag_records": {s: [f.to_dict() for f in fl] for s, fl in run.flag_records.items()},
        "status": {s: st.to_dict() for s, st in run.status.items()}}
    if run.cross_validation is not None:
        meta["cross_validation"] = run.cross_validation.to_dict()
    if run.budget:
        meta["residual_budget"] = {"steps": {s: b.to_dict() for s, b in run.budget.items()},
                                   "sessions": run.budget_sessions}
    if run.zoom_wide is not None:
        zw = run.zoom_wide
        meta["zoom_wide"] = {"converged": zw.converged, "stop_reason": zw.stop_reason,
                             "aspect": zw.aspect, "aspect_sd": zw.aspect_sd,
                             "iterations": zw.iterations, "tau": zw.tau,
                             "tau_source": zw.tau_source, "zoom_model": zw.zoom_models,
                             "unsmoothed": zw.unsmoothed,
                             "board_modes_mm": zw.board_modes.tolist(),
                             "board_sessions": zw.board_sessions,
                             "board_modes_sd_mm": zw.board_modes_sd.tolist(),
                             "board_point_heights_mm": (None if zw.board_heights is None
                                                        else zw.board_heights.tolist()),
                             "print_modes_mm": (None if zw.print_modes is None
                                                else zw.print_modes.tolist()),
                             "print_modes_sd_mm": (None if zw.print_modes_sd is None
                                                   else zw.print_modes_sd.tolist()),
                             "print_test": (None if zw.print_test is None
                                            else zw.print_test.to_dict()),
                             "distortion_terms": {k: list(v) for k, v in zw.terms.items()},
                             "skipped": zw.skipped,
                             "distortion_choice": {k: v.to_dict()
                                                   for k, v in zw.held_out.items()}}
    return meta


def fit_zoom_model(run: CalibrateRun, rows: list[dict], out: Path,
                   log: Callable[[str], None]) -> None:
    """``zoom_model.json`` from the table rows of known zoom (4 or more), its held-out error in
    ``run.holdout``; a fit that fails is logged and recorded."""
    known = [zoom_model_row(r) for r in rows if np.isfinite(r["zoom"])]
    if len(known) < 4:
        return
    from ..zoom import ZoomModel
    from .zoompath import PosteriorZoomModel

    try:
        if posterior_zoom_model(run, known):
            run.zoom_model = PosteriorZoomModel.from_zoom_wide(
                run.zoom_wide, {r["step"]: r["zoom"] for r in known})
            for note in run.zoom_model.notes:
                log(f"zoom model: {note}")
        else:
            run.zoom_model = ZoomModel.from_table(known)
        if "k1" not in run.zoom_model.names and any(r.get("k4") is not None for r in known):
            log("zoom model: fx, fy, cx, cy only; steps "
                + ", ".join(r["step"] for r in known if r.get("k4") is not None)
                + " hold the rational model, the others five terms")
        run.holdout = run.zoom_model.holdout_error()
        doc = {"model": run.zoom_model.to_dict(),
               "holdout_rms": {k: float(v) for k, v in run.holdout.items()},
               "flags": run.zoom_model.flags()}
        path = out / "zoom_model.json"
        path.write_text(json.dumps(doc, indent=1))
        run.files.append(path)
    except (ValueError, np.linalg.LinAlgError) as exc:
        run.failures.append(f"zoom model: {exc}")
        log(run.failures[-1])


def posterior_zoom_model(run: CalibrateRun, rows: list[dict]) -> bool:
    """Whether the zoom model comes from the zoom-wide adjustment's posterior
    (:mod:`zoomcalib.calibrate.zoompath`): its rows make the table and it has one chain (the
    steps reached zooming in and out are two paths; their table rows are fitted instead)."""
    return (run.zoom_wide is not None and bool(getattr(run.zoom_wide, "u", None))
            and all(run.table_backend.get(r["step"]) == "zoom-wide" for r in rows)
            and len({r.get("direction") or "" for r in rows}) == 1)


def zoom_model_row(row: dict) -> dict:
    """A table row as the zoom model is fitted from: without the distortion terms' 1-sigma
    columns, so the distortion curves are fitted with equal weights as before those columns
    were written (fx, fy, cx, cy stay weighted by theirs)."""
    return {k: v for k, v in row.items() if not k.startswith(("sd_k", "sd_p"))}


def write_run_manifest(out: Path, run: CalibrateRun, folder, steps, provenance: dict,
                       call: dict) -> Path:
    caches = [out / p["file"] for p in provenance.values() if (out / p["file"]).is_file()]
    inputs = {"folder": str(folder), "ignored_images": run.ignored,
              "steps": {step: {"folder": str(step_dir), "zoom": zoom,
                               "images": provenance.get(step, {}).get("images", [])}
                        for step, step_dir, zoom, _ in steps}}
    return write_manifest(out, [*run.files, *caches], inputs, call)


def table_rows(run: CalibrateRun, extras_of: dict[str, dict],
               sessions: dict[str, str]) -> list[dict]:
    """The zoom table's rows: each step's table backend's result, its flags and status, and
    its capture session where the steps were captured in more than one."""
    several = len(set(sessions.values())) > 1
    return [table_row(step, run.zoom[step], extras_of[step],
                      run.results[step][run.table_backend[step]]) | {
                           "flags": "; ".join(run.flags.get(step, [])),
                           "status": run.status[step].status,
                           "status_reasons": "; ".join(run.status[step].reasons)}
            | ({"session": sessions.get(step)} if several else {})
            for step in run.results]


def write_figures(run: CalibrateRun, out: Path, zoom_set: bool, workers: int = 1) -> list[Path]:
    """The run's figures; the steps' residual plots in ``workers`` processes (matplotlib's
    drawing of their thousands of arrows is most of the time)."""
    from ..plots import (
        plot_focal_length,
        plot_principal_point_spiral,
        plot_residuals,
    )

    files = []
    steps = list(run.results)
    best = {s: run.results[s][run.table_backend[s]] for s in steps}
    if zoom_set and len(steps) > 1:
        known = all(run.zoom[s] is not None for s in steps)
        zoom = np.array([run.zoom[s] if known else i for i, s in enumerate(steps)], dtype=float)
        label = ("zoom (the table's zoom column)" if known
                 else "step index (zoom unknown: no steps.csv or zoom in the step names)")
        mean = np.array([[best[s].cx, best[s].cy] for s in steps])
        sd = np.array([[best[s].sd.get("cx", 0.0), best[s].sd.get("cy", 0.0)] for s in steps])
        files.append(plot_principal_point_spiral(
            zoom, mean, sd, out / "principal_point_path.png",
            title="Calibrated principal point across zoom (1-sigma ellipses)",
            zoom_label=label, image_size=run.observations[steps[0]].image_size))
        f = np.array([[best[s].fx, best[s].sd.get("fx", 0.0)] for s in steps])
        files.append(plot_focal_length(zoom, f[:, 0], f[:, 1], out / "focal_length.png",
                                       run.zoom_model if known else None, zoom_label=label))
    cv = run.cross_validation
    if cv is not None and cv.z:
        from ..plots import plot_cross_validation
        from .checks import CROSS_VALIDATED

        names = [s for s in steps if s in cv.z]
        z = np.array([[cv.z[s][q] for q in CROSS_VALIDATED] for s in names])
        files.append(plot_cross_validation(names, z, CROSS_VALIDATED,
                                           out / "cross_validation.png",
                                           title=f"Cross-validation ({cv.backend}): even vs "
                                                 "odd images"))
    plots = [([p for _, p in run.observations[s].views],
              residual_vectors(best[s], run.observations[s]), run.observations[s].image_size,
              out / f"residuals_{run.stems[s]}.png",
              f"step {s}: {best[s].backend}, rms {best[s].rms_px:.3f} px") for s in steps]
    return files + map_in_processes(plot_residuals, plots, workers)
