"""The paper's study: does detection error or mechanical error limit the principal point?

Gardel, Lázaro & Lavest (2002) concluded that the mechanical errors of a zoom lens can be
neglected in calibration because detection errors move the principal point more. This module
answers the question on rendered images:

1. *Mechanics* — Monte Carlo of the principal point over the mechanical error draws (exact
   tracer) at each zoom step: its mean path (the spiral), its scatter ``s_mech`` (1-sigma per
   axis, RMS over x and y) and the systematic shift of the mean from the aligned lens.
2. *Detection* — at each zoom step and noise level, calibration sets rendered through the
   *aligned* lens (target scaled to the focal length), detected by each detector and calibrated
   by each backend, repeated over seeds: the scatter ``s_det`` of the calibrated (cx, cy) over
   the seeds (1-sigma per axis, RMS over x and y).
3. *Comparison* — per step, detector and backend: ``ratio = s_mech / s_det`` with a 95 %
   interval from the sampling distribution of ``s_det`` (``(n-1) s^2 / sigma^2 ~ chi^2_{n-1}``)
   and of ``s_mech``; the verdict is "mechanics dominate" when the whole interval lies above 1,
   "detection dominates" when it lies below 1, else "comparable". The systematic shift is set
   against ``s_det`` the same way.
4. *Side claims* of the paper, checked on the computed numbers (see :func:`check_claims`).

Every number in the report is read from the CSV tables written beside it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy import stats

from ..camera import DEFAULT_SENSOR, Sensor

__all__ = ["StudyConfig", "DetectionSetting", "detection_task", "mechanics_table",
           "aggregate_detection", "compare", "check_claims"]


@dataclass
class StudyConfig:
    """What the study computes (defaults: the full study; :meth:`quick` for CI)."""

    lens: str = "laikin-10x"
    tolerances: str | None = None
    tolerance_scale: float = 1.0
    steps: int = 5
    noise_dn: tuple[float, ...] = (1.0, 2.0, 4.0)
    seeds: int = 8
    views: int = 8
    pattern: str = "chessboard:9x6:25"
    detectors: tuple[str, ...] = ("classic", "model")
    backends: tuple[str, ...] = ("opencv", "bundle")
    mc_samples: int = 2000
    blur_px: float = 0.7
    psf: str = "gaussian"  # the renderer's PSF shape (zoomcalib.render.image.PSF_KINDS)
    seed: int = 0
    fig6_noise_dn: float = 2.0
    lensfun: str | None = None
    zooms: tuple[float, ...] | None = None  # explicit zoom states instead of ``steps``
    notes: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        from ..render.image import PSF_KINDS

        if self.psf not in PSF_KINDS:
            raise ValueError(f"psf must be one of {', '.join(PSF_KINDS)}, got {self.psf!r}")

    @classmethod
    def quick(cls, **overrides) -> StudyConfig:
        """A reduced but complete study: 3 steps, one noise level, 4 seeds of 6 views."""
        base = {"steps": 3, "noise_dn": (2.0,), "seeds": 4, "views": 6, "mc_samples": 400}
        base.update(overrides)
        return cls(**base)

    @property
    def zoom(self) -> np.ndarray:
        if self.zooms is not None:
            return np.asarray(self.zooms, dtype=float)
        return np.linspace(0.0, 1.0, self.steps) if self.steps > 1 else np.zeros(1)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["noise_dn"] = list(self.noise_dn)
        d["detectors"] = list(self.detectors)
        d["backends"] = list(self.backends)
        d["zooms"] = [float(z) for z in self.zoom]
        d["steps"] = len(self.zoom)
        return d


@dataclass(frozen=True)
class DetectionSetting:
    """One calibration set of the study's detection part (:func:`detection_task`).

    Attributes
    ----------
    lens : str
        Name of the lens prescription, rendered aligned.
    zoom : float
        Lens state in [0, 1].
    noise_dn : float
        Read noise, 1-sigma in 8-bit digital numbers (of 255).
    views : int
        Views of the set.
    pattern : str
        Target spec (scaled to the focal length).
    blur_px : float
        The renderer's extra Gaussian blur, px (1-sigma).
    detectors : list of str
        Detection methods, each run on every view.
    backends : list of str
        ``'opencv'`` or ``'bundle'``: each calibrates every detector's points.
    keep_errors : bool
        Keep the detection errors of the first view (for the paper's Fig. 6).
    psf : str
        The renderer's PSF shape (:class:`~zoomcalib.render.image.Optics`; shape parameters at
        their defaults): the ``model`` detector assumes a Gaussian, so any other shape is a PSF
        it does not model.
    binning : int
        The default sensor's pixels taken ``binning`` x ``binning`` at a time: the same field
        of view on an image ``binning`` times smaller each way, pitch ``binning`` times larger
        (``blur_px`` and the noise are per binned pixel).
    """

    lens: str
    zoom: float
    noise_dn: float
    views: int
    pattern: str
    blur_px: float
    detectors: list[str]
    backends: list[str]
    keep_errors: bool = False
    psf: str = "gaussian"
    binning: int = 1

    def sensor(self) -> Sensor:
        """The sensor the set is rendered on (:attr:`binning` of the default one); ValueError
        for a binning that is not a whole divisor of its width and height."""
        b, full = self.binning, DEFAULT_SENSOR
        if not isinstance(b, int) or b < 1 or full.width_px % b or full.height_px % b:
            raise ValueError(f"binning must be a whole divisor of the default sensor's "
                             f"{full.width_px} x {full.height_px} px, got {b!r}")
        return Sensor(full.width_px // b, full.height_px // b, full.pixel_pitch_mm * b)


def detection_task(seed: int, setting: DetectionSetting | None = None, **fields) -> dict:
    """Render one calibration set through the aligned lens, detect, calibrate.

    A task of :mod:`zoomcalib.study.engine`: ``seed`` seeds the poses and the noise; the set is
    ``setting`` with ``fields`` (keywords named as its fields) replacing its own, or made of
    ``fields`` alone.

    Returns
    -------
    dict
        ``truth`` (cx, cy, fx of the lens state's fitted model), ``results``
        ``{detector: {backend: {fx, fy, cx, cy, sd_cx, sd_cy, rms_px} or {error}}}``,
        ``detection_rms_px`` per detector (against the rendered truth), timings ``render_s``,
        ``detect_s``, ``calibrate_s``, and with ``keep_errors`` the detection errors of the first
        view (for the paper's Fig. 6).
    """
    from ..calibrate.result import Observations
    from ..detect import detect_image

    spec = DetectionSetting(**fields) if setting is None else replace(setting, **fields)
    rng = np.random.default_rng(seed)
    sensor = spec.sensor()
    t0 = time.perf_counter()
    mapping, target, rendered = _render_set(spec, sensor, rng)
    t1 = time.perf_counter()
    out = {"truth": {"cx": mapping.camera.cx, "cy": mapping.camera.cy, "fx": mapping.camera.fx},
           "results": {}, "detection_rms_px": {}, "render_s": t1 - t0, "detect_s": 0.0,
           "calibrate_s": 0.0}
    for det_name in spec.detectors:
        t2 = time.perf_counter()
        dets = [detect_image(v.image, target, det_name, name=f"view_{i:02d}")
                for i, v in enumerate(rendered)]
        t3 = time.perf_counter()
        out["detect_s"] += t3 - t2
        ok = [(d, v) for d, v in zip(dets, rendered, strict=True) if d.error is None]
        errs = [d.points - v.points_px[d.ids] for d, v in ok]
        out["detection_rms_px"][det_name] = (float(np.sqrt(np.mean(np.sum(
            np.concatenate(errs) ** 2, axis=1)))) if errs else None)
        if spec.keep_errors and ok:
            out.setdefault("fig6", {})[det_name] = {
                "points": ok[0][1].points_px[ok[0][0].ids].tolist(),
                "errors": errs[0].tolist()}
        obs = Observations(target.object_points, [(d.ids, d.points) for d, _ in ok],
                           (sensor.width_px, sensor.height_px), [d.file for d, _ in ok])
        out["results"][det_name] = {backend: _calibrate_set(obs, backend)
                                    for backend in spec.backends}
        out["calibrate_s"] += time.perf_counter() - t3
    return out


def _render_set(task: DetectionSetting, sensor, rng: np.random.Generator
                ) -> tuple[object, object, list]:
    """The set's exact mapping of the aligned lens, its target scaled to the focal length and
    its rendered views (:class:`~zoomcalib.render.image.RenderedView`), at 2 m."""
    from ..optics.lens_camera import exact_mapping
    from ..optics.prescription import load_prescription
    from ..render.dataset import generate_poses, scaled_target_for_view
    from ..render.image import Optics, Radiometry, render_image
    from ..targets import parse_pattern

    lens_ = load_prescription(task.lens)
    mapping = exact_mapping(lens_, float(task.zoom), None, sensor)
    distance = 2000.0
    target = scaled_target_for_view(parse_pattern(task.pattern), mapping.camera.fy, sensor,
                                    distance)
    poses = generate_poses(target, mapping, sensor, task.views, distance, rng)
    optics = Optics(blur_px=task.blur_px, f_number=lens_.f_number, psf=task.psf)
    radiometry = Radiometry(noise_sd=task.noise_dn / 255.0)
    rendered = [render_image(target, mapping, R, t, sensor, optics, radiometry, rng)
                for R, t in poses]
    return mapping, target, rendered


def _calibrate_set(obs, backend: str) -> dict:
    """One backend's calibration of a set's detections: its fx, fy, cx, cy, their sds and
    the residual RMS (px), or the one-line error that stopped it."""
    try:
        if backend == "opencv":
            from ..calibrate.opencv_backend import calibrate_opencv

            r = calibrate_opencv(obs)
        else:
            from ..calibrate.bundle import calibrate_bundle

            r = calibrate_bundle(obs)
        return {"fx": r.fx, "fy": r.fy, "cx": r.cx, "cy": r.cy, "sd_fx": r.sd.get("fx"),
                "sd_cx": r.sd.get("cx"), "sd_cy": r.sd.get("cy"), "rms_px": r.rms_px}
    except Exception as exc:  # noqa: BLE001 (one failed fit must not lose the others)
        return {"error": " ".join(str(exc).split())[:300]}


def mechanics_table(lens, tolerances, zoom: np.ndarray, samples: int, seed: int) -> list[dict]:
    """Principal-point mean, scatter and systematic shift from the mechanics per zoom step."""
    from ..optics.principal_point import principal_point_scatter

    res = principal_point_scatter(lens, tolerances, zoom, samples, seed, "exact")
    rows = []
    for i, z in enumerate(zoom):
        shift = res.mean_px[i] - DEFAULT_SENSOR.centre_px  # the aligned lens images at centre
        rows.append({"zoom": float(z), "efl_mm": float(res.efl_mm[i]),
                     "cx_mean": float(res.mean_px[i, 0]), "cy_mean": float(res.mean_px[i, 1]),
                     "cx_std": float(res.std_px[i, 0]), "cy_std": float(res.std_px[i, 1]),
                     "s_mech_px": float(np.sqrt(np.mean(res.std_px[i] ** 2))),
                     "shift_px": float(np.linalg.norm(shift)), "n_samples": samples})
    return rows


def aggregate_detection(runs: list[dict]) -> list[dict]:
    """Scatter of the calibrated principal point over seeds, per (zoom, noise, detector,
    backend).

    Parameters
    ----------
    runs : list of dict
        One row per (task, detector, backend): ``zoom, noise_dn, detector, backend, cx, cy,
        sd_cx, sd_cy`` (failed fits have NaN).
    """
    groups: dict[tuple, list[dict]] = {}
    for r in runs:
        groups.setdefault((r["zoom"], r["noise_dn"], r["detector"], r["backend"]), []).append(r)
    out = []
    for (z, noise, det, backend), rows in sorted(groups.items()):
        cx = np.array([r["cx"] for r in rows], float)
        cy = np.array([r["cy"] for r in rows], float)
        good = np.isfinite(cx) & np.isfinite(cy)
        n = int(good.sum())
        sx = float(np.std(cx[good], ddof=1)) if n > 1 else np.nan
        sy = float(np.std(cy[good], ddof=1)) if n > 1 else np.nan
        pred = np.array([[r["sd_cx"], r["sd_cy"]] for r in rows], float)[good]
        out.append({"zoom": z, "noise_dn": noise, "detector": det, "backend": backend,
                    "n_sets": n, "n_failed": len(rows) - n, "sd_cx": sx, "sd_cy": sy,
                    "s_det_px": float(np.sqrt(0.5 * (sx**2 + sy**2))) if n > 1 else np.nan,
                    "predicted_sd_px": (float(np.sqrt(np.mean(pred**2))) if len(pred)
                                        else np.nan),
                    "mean_cx": float(np.mean(cx[good])) if n else np.nan,
                    "mean_cy": float(np.mean(cy[good])) if n else np.nan,
                    "detection_rms_px": float(np.nanmean([r.get("detection_rms_px", np.nan)
                                                          for r in rows]))})
    return out


def _ratio_interval(s_mech: float, n_mech: int, s_det: float, n_det: int,
                    level: float = 0.95) -> tuple[float, float]:
    """Interval for ``s_mech / s_det`` from the chi-square laws of both sample sds (2 axes
    each, pooled: 2 (n - 1) degrees of freedom)."""
    if not (np.isfinite(s_det) and s_det > 0):
        return (np.nan, np.nan)
    dof_d, dof_m = 2 * (n_det - 1), 2 * (n_mech - 1)
    # the ratio of variances is F-distributed
    lo_f, hi_f = stats.f.ppf([(1 - level) / 2, (1 + level) / 2], dof_m, dof_d)
    r = s_mech / s_det
    return (float(r / np.sqrt(hi_f)), float(r / np.sqrt(lo_f)))


def _verdict(lo: float, hi: float) -> str:
    if not np.isfinite(lo):
        return "undetermined"
    if lo > 1.0:
        return "mechanics dominate"
    if hi < 1.0:
        return "detection dominates"
    return "comparable"


def compare(mech: list[dict], scatter: list[dict]) -> list[dict]:
    """Per zoom step, noise, detector and backend: mechanics against detection."""
    by_zoom = {round(m["zoom"], 9): m for m in mech}
    rows = []
    for s in scatter:
        m = by_zoom[round(s["zoom"], 9)]
        s_m, s_d = m["s_mech_px"], s["s_det_px"]
        if s_m == 0.0:
            lo = hi = 0.0
        else:
            lo, hi = _ratio_interval(s_m, m["n_samples"], s_d, s["n_sets"])
        ratio = s_m / s_d if (np.isfinite(s_d) and s_d > 0) else np.nan
        shift_ratio = m["shift_px"] / s_d if (np.isfinite(s_d) and s_d > 0) else np.nan
        rows.append({"zoom": s["zoom"], "efl_mm": m["efl_mm"], "noise_dn": s["noise_dn"],
                     "detector": s["detector"], "backend": s["backend"],
                     "s_mech_px": s_m, "s_det_px": s_d, "ratio": ratio, "ratio_lo": lo,
                     "ratio_hi": hi, "verdict": _verdict(lo, hi), "shift_px": m["shift_px"],
                     "shift_over_s_det": shift_ratio,
                     "shift_verdict": ("mechanical shift exceeds detection scatter"
                                       if shift_ratio > 1 else
                                       "mechanical shift within detection scatter")
                     if np.isfinite(shift_ratio) else "undetermined"})
    return rows


def _spearman(x, y) -> float:
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(stats.spearmanr(x, y)[0])


def check_claims(mech: list[dict], scatter: list[dict], lensfun_summary: dict | None,
                 mech_steps: list[dict] | None = None) -> list[dict]:
    """The paper's side claims, each with the numbers that decide it.

    - the spiral: the mean principal point turns about the centre (total turning angle of the
      mean path, in turns);
    - larger displacement at short focal length: Spearman correlation of the systematic shift
      with the focal length (the claim predicts < 0);
    - scatter growing with focal length: Spearman correlation of ``s_mech`` with focal length;
    - the pinhole model less well defined at long focal length: correlation of the calibrated
      principal point's detection scatter with focal length;
    - distortion decreasing as focal length increases: from the lensfun database.

    ``mech`` is the dense mechanics table; ``mech_steps`` (default ``mech``) the one at the
    study's zoom steps, which the detection scatter is matched to.
    """
    mech_steps = mech if mech_steps is None else mech_steps
    claims = []
    efl = np.array([m["efl_mm"] for m in mech])
    d = np.array([[m["cx_mean"], m["cy_mean"]] for m in mech])
    centred = d - d.mean(axis=0) if len(d) > 1 else d
    ang = np.unwrap(np.arctan2(centred[:, 1], centred[:, 0])) if len(d) > 1 else np.zeros(1)
    turns = float(abs(ang[-1] - ang[0]) / (2 * np.pi)) if len(d) > 1 else 0.0
    claims.append({"claim": "the principal point follows a spiral across the zoom range",
                   "measure": "turns of the mean path about its centroid", "value": turns,
                   "holds": bool(turns >= 0.75) if len(d) > 3 else "too few steps"})
    shift = [m["shift_px"] for m in mech]
    rho = _spearman(efl, shift)
    claims.append({"claim": "larger displacement at short focal length",
                   "measure": "Spearman(EFL, |systematic shift|)", "value": rho,
                   "holds": bool(rho < 0) if np.isfinite(rho) else "undetermined"})
    rho = _spearman(efl, [m["s_mech_px"] for m in mech])
    claims.append({"claim": "mechanical scatter grows with focal length",
                   "measure": "Spearman(EFL, s_mech)", "value": rho,
                   "holds": bool(rho > 0) if np.isfinite(rho) else "undetermined"})
    by_zoom: dict[float, list[float]] = {}
    for s in scatter:
        if np.isfinite(s["s_det_px"]):
            by_zoom.setdefault(s["zoom"], []).append(s["s_det_px"])
    zs = sorted(by_zoom)
    efl_of = {round(m["zoom"], 9): m["efl_mm"] for m in mech_steps}
    rho = _spearman([efl_of[round(z, 9)] for z in zs], [np.median(by_zoom[z]) for z in zs])
    claims.append({"claim": "the pinhole model is less well defined at long focal length",
                   "measure": "Spearman(EFL, detection-induced scatter of the principal point)",
                   "value": rho, "holds": bool(rho > 0) if np.isfinite(rho) else "undetermined"})
    if lensfun_summary:
        frac = lensfun_summary.get("fraction_monotone_decreasing")
        claims.append({"claim": "distortion decreases as focal length increases (so it can be "
                                "ignored)",
                       "measure": "fraction of lensfun zoom lenses whose |distortion| falls "
                                  "monotonically with focal length",
                       "value": frac,
                       "holds": bool(frac is not None and frac > 0.5)})
    return claims
