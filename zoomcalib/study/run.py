"""The ``study`` job: the paper's comparison end to end, on the task engine.

Writes to ``OUT``: ``mechanics.csv``, ``detection_runs.csv`` (one row per calibration set,
detector and backend), ``detection_scatter.csv``, ``comparison.csv``, ``claims.csv``,
``lensfun.csv``, ``timing.csv``, the figures, ``report.md``, ``report.html`` and ``study.json``
(configuration, command, versions). Finished Monte Carlo tasks are kept in ``OUT/tasks/``, so an
interrupted study resumes from them.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..io import write_csv
from .engine import Task, run_tasks
from .paper import (
    StudyConfig,
    aggregate_detection,
    check_claims,
    compare,
    detection_task,
    mechanics_table,
)
from .report import StudyTables, study_figures, write_report

__all__ = ["run_study", "detection_tasks", "DENSE_STEPS"]

DENSE_STEPS = 41  # zoom states of the mechanics-only tables (fig. 5 and the side claims)


def detection_tasks(config: StudyConfig) -> list[Task]:
    """One task per (zoom step, noise level, calibration set)."""
    tasks = []
    fig6_zoom = config.zoom[len(config.zoom) // 2]
    for z in config.zoom:
        for noise in config.noise_dn:
            for s in range(config.seeds):
                key = f"det/zoom{z:.4f}/noise{noise:g}/set{s:02d}"
                kwargs = {"lens": config.lens, "zoom": float(z), "noise_dn": float(noise),
                          "views": config.views, "pattern": config.pattern,
                          "blur_px": config.blur_px, "detectors": list(config.detectors),
                          "backends": list(config.backends),
                          "keep_errors": bool(s == 0 and z == fig6_zoom
                                              and noise == config.fig6_noise_dn)}
                if config.psf != "gaussian":
                    # In the task's fingerprint, so a cache of another PSF is not reused; left
                    # out for the default Gaussian, whose tasks keep the fingerprints (and the
                    # caches) they had before the option existed. The key, hence the seed,
                    # is the same: PSFs are compared on the same poses and noise draws.
                    kwargs["psf"] = config.psf
                tasks.append(Task(key, detection_task, kwargs))
    return tasks


def _versions() -> dict:
    import cv2
    import scipy

    return {"zoomcalib": __version__, "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "opencv": cv2.__version__}


def run_study(config: StudyConfig, out: str | Path, workers: int | None = None,
              scheduler=None, command: str = "", progress=None) -> dict:
    """Run the study and write its outputs (module docstring).

    Returns
    -------
    dict
        ``mechanics``, ``scatter``, ``comparison``, ``claims`` rows, ``timing`` and ``files``.
    """
    from ..optics.mechanics import Tolerances, load_tolerances
    from ..optics.prescription import load_prescription

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    lens = load_prescription(config.lens)
    tol = (Tolerances.zero() if config.tolerance_scale == 0
           else load_tolerances(config.tolerances, lens).scaled(config.tolerance_scale))
    t0 = time.perf_counter()
    mech = mechanics_table(lens, tol, config.zoom, config.mc_samples, config.seed)
    # The spiral and the trends are read on a dense zoom grid: study steps that are multiples
    # of half a barrel turn apart would alias the spiral.
    dense_zoom = np.linspace(0.0, 1.0, DENSE_STEPS)
    mech_dense = mechanics_table(lens, tol, dense_zoom, max(50, config.mc_samples // 4),
                                 config.seed)
    t_mech = time.perf_counter() - t0

    tasks = detection_tasks(config)
    results = run_tasks(tasks, seed=config.seed, workers=workers, scheduler=scheduler,
                        cache_dir=out / "tasks", progress=progress)
    runs, fig6, failures = [], None, []
    timing = {"mechanics_s": t_mech, "render_s": 0.0, "detect_s": 0.0, "calibrate_s": 0.0}
    for task in tasks:
        res = results[task.key]
        if "error" in res:
            failures.append(f"{task.key}: {res['error']}")
            continue
        for k in ("render_s", "detect_s", "calibrate_s"):
            timing[k] += res[k]
        if "fig6" in res:
            fig6 = res["fig6"]
        for det, per_backend in res["results"].items():
            for backend, r in per_backend.items():
                runs.append({"key": task.key, "zoom": task.kwargs["zoom"],
                             "noise_dn": task.kwargs["noise_dn"], "detector": det,
                             "backend": backend, "cx": r.get("cx", np.nan),
                             "cy": r.get("cy", np.nan), "fx": r.get("fx", np.nan),
                             "sd_cx": r.get("sd_cx", np.nan), "sd_cy": r.get("sd_cy", np.nan),
                             "rms_px": r.get("rms_px", np.nan),
                             "true_cx": res["truth"]["cx"], "true_cy": res["truth"]["cy"],
                             "detection_rms_px": res["detection_rms_px"].get(det) or np.nan,
                             "error": r.get("error", "")})
    scatter = aggregate_detection(runs)
    comparison = compare(mech, scatter)
    lensfun_summary = _lensfun_summary(out, config.lensfun)
    claims = check_claims(mech_dense, scatter, lensfun_summary, mech)
    files = [
        write_csv(out / "mechanics.csv", mech),
        write_csv(out / "mechanics_dense.csv", mech_dense),
        write_csv(out / "detection_runs.csv", runs),
        write_csv(out / "detection_scatter.csv", scatter),
        write_csv(out / "comparison.csv", comparison),
        write_csv(out / "claims.csv", claims),
    ]
    figures = study_figures(out, mech_dense, mech, scatter, fig6, dense_zoom)
    timing["wall_s"] = time.perf_counter() - t_start
    files.append(write_csv(out / "timing.csv", [timing]))
    versions = _versions()
    tables = StudyTables(mech, scatter, comparison, claims, timing, lensfun_summary)
    files += write_report(out, config.to_dict(), command, versions, tables, figures)
    (out / "study.json").write_text(json.dumps(
        {"config": config.to_dict(), "command": command, "versions": versions,
         "failures": failures, "workers": workers, "scheduler": str(scheduler)}, indent=1))
    return {"mechanics": mech, "scatter": scatter, "comparison": comparison, "claims": claims,
            "timing": timing, "failures": failures, "files": files + list(figures.values())}


def _lensfun_summary(out: Path, source: str | None) -> dict:
    """Distortion versus focal length of real zoom lenses (the lensfun extract shipped with the
    package, or the database at ``source``), written to ``lensfun.csv``."""
    from . import lensfun

    return lensfun.study_summary(out / "lensfun.csv", source)
