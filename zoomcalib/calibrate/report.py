"""The calibration report ``OUT/report.html``: one self-contained page per calibrate run.

The figures are PNG images embedded in the page as ``data:`` URIs, so the file opens in any
browser without a server and can be moved or mailed alone. For every step (with the zoom
table's backend, :attr:`CalibrateRun.table_backend`): per-image reprojection error with the
images the fit rejected points of or left out named; residual vectors and directions; coverage
of the image and the views' tilt and distance, with a verdict
(:func:`zoomcalib.calibrate.quality.coverage_verdict`); the projection uncertainty over the
image at one distance and, after ``--cross-validate``, the halves' projection difference
(:mod:`zoomcalib.calibrate.quality`). Then, for a zoom set, fx, cx, cy and k1 against zoom with
their 1-sigma bands, the zoom model with its held-out error, and the flagged steps. The page's
script sets ``data-images-loaded`` on ``<body>`` to ``"all"`` once every image has decoded
(``"missing"`` otherwise), which the tests read. docs/report.md describes each figure.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .. import report_plots as figs
from .checks import Z_LIMIT
from .quality import (
    GRID,
    MIN_REACH,
    ViewGeometry,
    board_outlines,
    coverage_verdict,
    distortion_map,
    observed_region,
    projection_difference,
    projection_uncertainty,
    residual_pattern,
    view_geometry,
)
from .result import CalibrationResult, Observations, residual_vectors

if TYPE_CHECKING:
    from .run import CalibrateRun

__all__ = ["write_report", "report_html", "ZOOM_LABELS"]

#: Axis label of the zoom, by where the zoom values came from (``zoom_steps``' zoom_source).
ZOOM_LABELS = {"steps.csv": "zoom [steps.csv units]", "name": "zoom [number in the folder name]",
               "exif": "focal length from EXIF [mm]"}

_STYLE = """
body { font-family: sans-serif; max-width: 1200px; margin: 1em auto; color: #222; }
h1 { font-size: 1.5em; } h2 { border-top: 2px solid #888; padding-top: .4em; }
h3 { font-size: 1.05em; margin-bottom: .2em; }
table { border-collapse: collapse; font-size: .85em; }
td, th { border: 1px solid #bbb; padding: 2px 6px; text-align: right; }
th { background: #eee; } td.text { text-align: left; }
.bad { color: #b00; } .ok { color: #070; } img { max-width: 100%; }
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.every(function (im) { return im.complete && im.naturalWidth > 0; });
  document.body.setAttribute('data-images-loaded', ok ? 'all' : 'missing');
  document.body.setAttribute('data-image-count', String(imgs.length));
});
"""


def write_report(run: CalibrateRun, out: str | Path, distance_mm: float | None = None,
                 images: tuple[str, ...] = ()) -> Path:
    """Write ``out/report.html`` for a :class:`zoomcalib.calibrate.run.CalibrateRun`.

    Parameters
    ----------
    run : CalibrateRun
    out : path
        The run's output folder.
    distance_mm : float, optional
        Range (object-point units, mm) of the points whose projection uncertainty is mapped;
        default: each step's median distance to the board centre.
    images : tuple of str
        Images whose detected corners and the fit's projections are drawn, beside each step's
        image of the largest error: a file name (``view_03.png``, every step that has it) or
        ``STEP/NAME``. A name no step has is listed among the run's problems.

    Returns
    -------
    Path
        The report.
    """
    path = Path(out) / "report.html"
    path.write_text(report_html(run, distance_mm, images), encoding="utf-8")
    return path


def chosen_views(run: CalibrateRun, images: tuple[str, ...]
                 ) -> tuple[dict[str, list[int]], list[str]]:
    """Per step, the indices of its views that ``images`` names (``NAME`` or ``STEP/NAME``;
    see :func:`write_report`), and the names no step has."""
    chosen: dict[str, list[int]] = {}
    unknown = []
    for image in images:
        step_name, _, name = image.rpartition("/")
        found = False
        for step in run.results:
            if step_name and step_name != step:
                continue
            names = _view_names(run.observations[step])
            if name in names:
                chosen.setdefault(step, []).append(names.index(name))
                found = True
        if not found:
            unknown.append(image)
    return chosen, unknown


def report_html(run: CalibrateRun, distance_mm: float | None = None,
                images: tuple[str, ...] = ()) -> str:
    """The report's HTML text (see :func:`write_report`)."""
    steps = list(run.results)
    chosen, unknown = chosen_views(run, images)
    problems = run.failures + [f"report image {name}: no calibrated step has a view of that "
                               "name" for name in unknown]
    body = [f"<h1>Calibration report</h1>{_summary(run, steps)}"]
    if problems:
        body.append("<h3>Problems of this run</h3><ul>" + "".join(
            f"<li class='bad'>{_e(f)}</li>" for f in problems) + "</ul>")
    for step in steps:
        body.append(_step_section(run, step, distance_mm, chosen.get(step, [])))
    if len(steps) >= 2:
        body.append(_zoom_section(run, steps))
    if run.budget:
        body.append(_budget_section(run))
    return ("<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<title>Calibration report</title><style>{_STYLE}</style>"
            f"<script>{_SCRIPT}</script></head><body>\n" + "\n".join(body)
            + "\n</body></html>\n")


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def _img(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f"<p><img alt='{_e(alt)}' src='data:image/png;base64,{data}'></p>"


def _summary(run: CalibrateRun, steps: list[str]) -> str:
    rows = []
    for s in steps:
        r = run.results[s][run.table_backend[s]]
        flags = run.flags.get(s, [])
        zoom = run.zoom.get(s)
        st = run.status.get(s)
        status = "" if st is None else (
            f"<td class='text {'ok' if st.status == 'ok' else 'bad'}'><b>{_e(st.status)}</b>"
            + (f"<details><summary>why, what to do</summary>{_e('; '.join(st.reasons))}. "
               f"<i>To do:</i> {_e('; '.join(st.remedies))}."
               + (f" <i>Capture advice:</i> {_e(st.advice['text'])}." if st.advice else "")
               + "</details>" if st.reasons else "")
            + "</td>")
        rows.append(
            f"<tr><td class='text'><a href='#step-{_e(run.stems[s])}'>{_e(s)}</a></td>"
            f"<td>{'' if zoom is None else f'{zoom:g}'}</td><td class='text'>{_e(r.backend)}</td>"
            + status +
            f"<td>{r.fx:.2f} &plusmn; {r.sd.get('fx', np.nan):.2f}</td>"
            f"<td>{r.fy:.2f} &plusmn; {r.sd.get('fy', np.nan):.2f}</td>"
            f"<td>{r.cx:.2f} &plusmn; {r.sd.get('cx', np.nan):.2f}</td>"
            f"<td>{r.cy:.2f} &plusmn; {r.sd.get('cy', np.nan):.2f}</td><td>{r.rms_px:.3f}</td>"
            f"<td>{len(r.per_view_rms_px)}</td>"
            + _flags_cell(run.flag_records.get(s), flags) + "</tr>")
    head = "<th>status</th>" if run.status else ""
    return ("<table><tr><th>step</th><th>zoom</th><th>backend</th>" + head +
            "<th>fx [px]</th><th>fy [px]</th>"
            "<th>cx [px]</th><th>cy [px]</th><th>RMS [px]</th><th>views</th><th>flags</th></tr>"
            + "".join(rows) + "</table>")


def _flags_cell(records: list | None, details: list[str]) -> str:
    """The summary table's flags: each flag's severity and few words, the most severe first,
    and behind a link its full text and what to do (the texts alone where no records are)."""
    if not records:
        text = _e("; ".join(details) or "none")
        return f"<td class='text {'bad' if details else 'ok'}'>{text}</td>"
    short = "<br>".join(f"<b>{_e(f.severity)}</b> {_e(f.text)}" for f in records)
    long = "".join(f"<li>{_e(f.detail)}. <i>To do:</i> {_e(f.action)}.</li>" for f in records)
    worst = records[0].severity
    return (f"<td class='text {'ok' if worst == 'note' else 'bad'}'>{short}"
            f"<details><summary>details, what to do</summary><ul>{long}</ul></details></td>")


def _rejected_mask(result: CalibrationResult, obs: Observations) -> list[np.ndarray]:
    """Per view, which observations the fit rejected (bool (k,))."""
    rejected = {(int(v), int(p)) for v, p in result.rejected}
    return [np.array([(v, int(i)) in rejected for i in ids], bool)
            for v, (ids, _) in enumerate(obs.views)]


def _view_names(obs: Observations) -> list[str]:
    return list(obs.names) if len(obs.names) == obs.n_views else [
        f"view {i}" for i in range(obs.n_views)]


def _absent_images(run: CalibrateRun, step: str) -> list[tuple[str, str]]:
    """(image, why) of the step's images that are not in the fit."""
    out = [(name, "not the step's image size") for name in run.left_out.get(step, [])]
    for error in run.skipped_images.get(step, []):
        name, _, why = error.partition(": ")
        out.append((name, why or error))
    return out


def _step_section(run: CalibrateRun, step: str, distance_mm: float | None,
                  chosen: list[int]) -> str:

    res = run.results[step][run.table_backend[step]]
    obs = run.observations[step]
    names = _view_names(obs)
    masks = _rejected_mask(res, obs)
    counts = {n: int(m.sum()) for n, m in zip(names, masks, strict=True) if m.any()}
    marked = {n: f"{c} point{'s' if c > 1 else ''} rejected" for n, c in counts.items()}
    absent = _absent_images(run, step)
    parts = [f"<section class='step' id='step-{_e(run.stems[step])}'>"
             f"<h2>Step {_e(step)}</h2><p>backend {_e(res.backend)}, {obs.n_views} images, "
             f"{obs.n_observations} points, RMS {res.rms_px:.3f} px.</p>"]
    parts.append("<h3>Reprojection error per image</h3>" + _img(figs.per_view_figure(
        names, np.asarray(res.per_view_rms_px, float), marked, [a for a, _ in absent]),
        f"per-image reprojection error of step {step}"))
    parts.append(_marked_list(marked, absent))
    points = np.concatenate([p for _, p in obs.views])
    resid = np.concatenate(residual_vectors(res, obs))
    rejected = np.concatenate(masks)
    view = np.concatenate([np.full(len(p), i) for i, (_, p) in enumerate(obs.views)])
    pattern, _ = residual_pattern(points[~rejected], resid[~rejected],
                                  np.array([res.cx, res.cy]), view[~rejected])
    png, scale = figs.residual_figure(points, resid, rejected, obs.image_size, pattern)
    parts.append(f"<h3>Residuals</h3>{_img(png, f'residuals of step {step}')}"
                 f"<p>Arrows drawn {scale:.0f} times their length; residual = projected minus "
                 f"observed. The residuals show {_e(pattern)}.</p>")
    rms = [np.sqrt(np.mean(np.sum(r**2, axis=1))) for r in np.split(
        resid, np.cumsum([len(p) for _, p in obs.views])[:-1])]
    worst = int(np.argmax(rms))
    parts.append(_view_corners(run, step, obs, resid, scale, worst,
                               "The image of the largest error"))
    parts += [_view_corners(run, step, obs, resid, scale, i, "A chosen image")
              for i in dict.fromkeys(chosen) if i != worst]
    geometry = view_geometry(res, obs)
    problems, summary = coverage_verdict(points, obs.image_size, geometry)
    parts.append("<h3>Coverage</h3>" + _img(figs.coverage_figure(
        [p for _, p in obs.views], obs.image_size, geometry.tilt_deg, geometry.distance, GRID,
        MIN_REACH), f"coverage of step {step}") + _verdict(problems, summary))
    parts.append(_uncertainty(run, step, res, obs, geometry, distance_mm, points))
    xs, ys, shift = distortion_map(res, obs.image_size)
    board = res.object_points if res.object_points is not None else obs.object_points
    parts.append("<h3>Lens distortion and board poses</h3>" + _img(figs.lens_and_poses_figure(
        xs, ys, shift, obs.image_size, board_outlines(res, np.asarray(board, float))),
        f"distortion and board poses of step {step}")
        + f"<p>The distortion moves a pixel by up to {np.max(shift):.3g} px (at the image "
          f"centre {shift[len(ys) // 2, len(xs) // 2]:.3g} px); the boards as the fit placed "
          "them.</p>")
    parts.append("</section>")
    return "\n".join(parts)


def _marked_list(marked: dict[str, str], absent: list[tuple[str, str]]) -> str:
    items = [f"<li>{_e(n)}: {_e(why)}</li>" for n, why in marked.items()]
    items += [f"<li>{_e(n)}: not in the fit ({_e(why)})</li>" for n, why in absent]
    if not items:
        return "<p class='ok'>No image rejected or left out; no point rejected.</p>"
    return "<p>Images the fit rejected points of, or left out:</p><ul class='bad'>" + "".join(
        items) + "</ul>"


def _verdict(problems: list[str], summary: str) -> str:
    if not problems:
        return (f"<p class='ok'>Verdict: the views constrain the principal point and the "
                f"distortion by these checks ({_e(summary)}).</p>")
    return (f"<p class='bad'>Verdict: the views may not constrain the principal point or the "
            f"distortion ({_e(summary)}):</p><ul class='bad'>"
            + "".join(f"<li>{_e(p)}</li>" for p in problems) + "</ul>")


def _uncertainty(run: CalibrateRun, step: str, res: CalibrationResult, obs: Observations,
                 geometry: ViewGeometry, distance_mm: float | None, points: np.ndarray) -> str:
    d = float(np.median(geometry.distance)) if distance_mm is None else float(distance_mm)
    xs, ys, sigma = projection_uncertainty(res, obs, d)
    hull, inside = observed_region(points, xs, ys)
    diff, note = None, ""
    cv = run.cross_validation
    if cv is not None and step in cv.halves:
        diff = projection_difference(*cv.halves[step], obs.image_size)[2]
        proj = cv.projection.get(step, {})
        note = (" Right: each pixel unprojected with the even half's intrinsics and projected "
                f"with the odd half's: up to {_largest(diff, inside)} px where points were "
                "detected"
                + (f"; in the halves' own sigma, RMS z {proj['z_rms']:.2f} over the observed "
                   f"region (flagged above {Z_LIMIT:g})." if "z_rms" in proj else ".")
                + halves_verdict(proj.get("z_rms"), _largest(diff, inside)))
    elif cv is not None and step in cv.failures:
        note = f" Cross-validation: halves not calibrated ({_e(cv.failures[step])})."
    centre = sigma[len(ys) // 2, len(xs) // 2]
    return ("<h3>Projection uncertainty</h3>"
            + _img(figs.uncertainty_figure(xs, ys, sigma, obs.image_size, d, hull, inside,
                                           diff), f"projection uncertainty of step {step}")
            + f"<p>1-sigma of the projection of points {d:.0f} mm away "
              f"({'the median board distance' if distance_mm is None else 'chosen'}), from "
              f"the intrinsics' covariance and the poses: {centre:.3g} px at the image centre, "
              f"up to {_largest(sigma, inside)} px where points were detected (inside the "
              f"dashed outline), {np.max(sigma):.3g} px at most over the image.{note}</p>"
            + _reading(res, sigma, inside, diff))


def _view_corners(run: CalibrateRun, step: str, obs: Observations, resid: np.ndarray,
                  scale: float, index: int, title: str) -> str:
    """View ``index``'s image with its detected corners and the fit's projections drawn over
    it, under ``title``; a note when the image cannot be read (a report written from results
    alone, or a file moved since)."""
    points = obs.views[index][1]
    start = int(np.sum([len(p) for _, p in obs.views[:index]]))
    error = resid[start:start + len(points)]
    rms = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
    name = _view_names(obs)[index]
    folder = run.step_dirs.get(step)
    image = None if folder is None else cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
    if image is None:
        return (f"<p>{_e(title)}, {_e(name)} ({rms:.3g} px RMS), could not be read to draw "
                "its corners.</p>")
    return (f"<h3>{_e(title)}</h3>"
            + _img(figs.corners_figure(image, points, points + error, name, scale),
                   f"corners of {name}")
            + f"<p>{_e(name)}: {rms:.3g} px RMS; residuals drawn {scale:.0f} times "
              "their length, as above.</p>")


def halves_verdict(z_rms: float | None, apart: str) -> str:
    """One sentence on the even/odd map: whether the halves' projections are as far apart as
    their own sigmas allow (RMS z over the observed region at most :data:`Z_LIMIT`), and what
    that means for the step's sigmas; empty without a z.

    Examples
    --------
    >>> halves_verdict(0.8, "12.4")[:46]
    ' Verdict: the halves agree. Their projections,'
    """
    if z_rms is None or not np.isfinite(z_rms):
        return ""
    if z_rms <= Z_LIMIT:
        return (" Verdict: the halves agree. Their projections, up to " + apart + " px apart, "
                f"are within what their own sigmas allow (RMS z {z_rms:.2f}), so the step's "
                "sigmas cover what its frames do.")
    return (" Verdict: the halves disagree. Their projections, up to " + apart + " px apart, "
            f"are {z_rms:.2f} of their sigmas apart (RMS z, more than {Z_LIMIT:g}): the step's "
            "sigmas are too small for what its frames do (a board or a camera that changed "
            "between the frames, or a model that misses); compare the halves' rows.")


def _reading(res: CalibrationResult, sigma: np.ndarray, inside: np.ndarray,
             diff: np.ndarray | None) -> str:
    """How the table's sigmas, the uncertainty map and the even/odd map fit together."""
    pp = max(res.sd.get("cx", np.nan), res.sd.get("cy", np.nan))
    text = (f"<p><i>Reading the signals together.</i> The table's 1-sigma of the principal "
            f"point ({pp:.3g} px here) is the principal point's own. The map above is where a "
            "point at that distance projects: the views' poses take up what a small turn of "
            "the camera would absorb, so at a narrow field a principal point known to tens "
            f"of px can still project known to {_largest(sigma, inside)} px.")
    if diff is not None:
        text += (" The even/odd map allows no such turn and shows the halves' principal points "
                 "apart whole; its z, in the halves' own sigmas, says whether that is "
                 "expected.")
    return text + "</p>"


def _largest(values: np.ndarray, inside: np.ndarray) -> str:
    return f"{np.max(values[inside]):.3g}" if inside.any() else "(no grid cell)"


def _zoom_section(run: CalibrateRun, steps: list[str]) -> str:
    best = [run.results[s][run.table_backend[s]] for s in steps]
    zooms = [run.zoom.get(s) for s in steps]
    sources = {run.zoom_source.get(s) for s in steps}
    if any(z is None for z in zooms):
        zoom, label = np.arange(len(steps), dtype=float), "step index (zoom unknown)"
    else:
        zoom = np.array(zooms, float)
        label = ZOOM_LABELS.get(sources.pop(), "zoom") if len(sources) == 1 else "zoom"
    values = {"fx": [r.fx for r in best], "cx": [r.cx for r in best],
              "cy": [r.cy for r in best], "k1": [float(r.dist[0]) for r in best]}
    values = {k: np.array(v) for k, v in values.items()}
    sds = {k: np.array([r.sd.get(k, np.nan) for r in best], float) for k in values}
    flagged = np.array([s in run.flags for s in steps])
    png = figs.zoom_range_figure(zoom, label, values, sds, flagged, _model_curves(run, zoom))
    flags = "".join(f"<li>{_e(s)}: {_e('; '.join(run.flags[s]))}</li>" for s in steps
                    if s in run.flags)
    text = ("<p class='ok'>No step flagged.</p>" if not flags else
            f"<p>Flagged steps (ringed in red):</p><ul class='bad'>{flags}</ul>")
    return ("<section id='zoom-range'><h2>The zoom range</h2>"
            + _img(png, "intrinsics against zoom") + text + _holdout_text(run) + "</section>")


def _model_curves(run: CalibrateRun, zoom: np.ndarray) -> dict:
    model = run.zoom_model
    if model is None:
        return {}
    grid = np.linspace(float(np.min(zoom)), float(np.max(zoom)), 200)
    pred = model.predict(grid)
    held = run.holdout or {}
    return {k: (grid, np.asarray(pred[k]), held.get(k)) for k in ("fx", "cx", "cy", "k1")
            if k in pred}


def _holdout_text(run: CalibrateRun) -> str:
    if not run.holdout:
        return ("<p>No zoom model (it needs four or more steps of known zoom).</p>"
                if run.zoom_model is None else "")
    flags = run.zoom_model.flags() if run.zoom_model is not None else []
    return ("<p>Zoom model, held-out interpolation error (RMS, leave one step out): "
            + ", ".join(f"{_e(k)} {v:.3g}{' px' if k in ('fx', 'fy', 'cx', 'cy') else ''}"
                        for k, v in run.holdout.items()) + ".</p>"
            + ("<ul class='bad'>" + "".join(f"<li>{_e(f)}</li>" for f in flags) + "</ul>"
               if flags else ""))


def _budget_section(run: CalibrateRun) -> str:
    """The residual budget: one figure of every step, one line per step and session."""
    from .budget import CAUSES

    steps = list(run.budget)
    budgets = [run.budget[s] for s in steps]
    shares = {c: np.array([next(k.share for k in b.causes if k.name == c) for b in budgets])
              for c in CAUSES}
    named = np.array([[c in b.named for c in CAUSES] for b in budgets])
    png = figs.budget_figure(steps, shares, named, np.array([b.unexplained for b in budgets]),
                             np.array([b.corner_level for b in budgets]))
    lines = "".join(f"<li>{_e(b.summary())}</li>" for b in budgets)
    sessions = "".join(
        f"<li>session {_e(label or '(one)')} ({_e(', '.join(d['steps']))}): "
        + _e(", ".join(f"{k} {100 * v:.0f} %" for k, v in d["share"].items() if v is not None))
        + f"; unexplained {100 * d['unexplained']:.0f} %</li>"
        for label, d in run.budget_sessions.items())
    return ("<section id='residual-budget'><h2>What the residual is made of</h2>"
            "<p>Each cause's share of the held-out mean square on the flat nominal board, "
            "alone; the causes kept by forward selection (each pays beside those kept "
            "before it); what they leave; and the share no error smooth over a view "
            "explains (docs/calibration.md, 'Residual budget').</p>"
            + _img(png, "residual budget per step") + f"<ul>{lines}</ul>"
            + f"<h3>Per capture session</h3><ul>{sessions}</ul></section>")
