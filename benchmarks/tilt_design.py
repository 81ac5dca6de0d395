"""How well a zoom set design tells a hidden axis tilt from a static decentre.

The diagnosis fits, over its baseline (sensor offset and the rotation-locked decentre of each
moving group), the columns of each cause (``zoomcalib.diagnose.model``): ``fx * theta`` for an
axis tilt, ``-S_g(z) d / pitch`` for a static decentre of group ``g``. Both are weighted by each
row's 1-sigma. For a design (lens states, views per setting, pixel pitch, board) this script
builds those columns and reports, per design:

- ``tilt chi2``: the chi2 the hidden tilt adds over the baseline, ``|P t|^2`` with ``t`` the
  weighted tilt signature at the hidden tilt and ``P`` the projection off the weighted baseline:
  about the tilt's ``-dBIC + 2 ln n``;
- ``absorbed``: the fraction of ``|P t|^2`` that the static decentre of the best group takes
  (its columns, also off the baseline), so a static decentre wins the BIC by
  ``absorbed * |P t|^2`` and loses it by ``gap = (1 - absorbed) |P t|^2``;
- ``gap / sd``: ``gap`` over its sampling sd, ``2 sqrt(gap)`` (the noise's projection on the
  part of the signature static decentre cannot take); ``P(static)``, the normal tail
  ``Phi(-gap / sd)``: how often the static decentre is named instead;
- what the diagnosis discards: ``mimic um``, the static decentre that best imitates the hidden
  tilt, and ``p chi2``, the chi2 of the tangential distortion (OpenCV ``p1``, ``p2``) that this
  decentre puts into every setting's calibration (the exact tracer's fitted camera, decentred
  against nominal), against the reference table's ``sd_p1``, ``sd_p2`` (scaled like the
  principal point's, and by ``pitch / pitch_ref``: the same pixel noise is a smaller angle). The
  rendered axis tilt moves the image only, and leaves ``p1``, ``p2`` as they are.

Row sigmas come from a reference table: a per-step calibrated rendered set (its
``zoom_calibration.csv``, with the ``dataset.json`` of the render two folders up when there,
e.g. the ``--out`` of ``diagnose_rendered.py``). Its ``sqrt((sd_cx^2 + sd_cy^2) / 2)`` is
interpolated in log-log over the EFL and scaled by ``sqrt(views_ref / views)`` and
``sqrt(corners_ref / corners)``; it does not change with the pixel pitch (in pixels the
principal point's sd of a board spanning the same part of the image is about the same at any
resolution, while the signatures grow as ``1 / pitch``). With the dataset, the sigmas are
multiplied by the RMS of (calibrated - true principal point) / sd of the reference, the factor
by which the table's sigmas understate its errors. The play of the tolerance file (1 um per
group) is added in quadrature.

Usage::

    python benchmarks/tilt_design.py --reference OUT/diag/calibration/zoom_calibration.csv
        [--tilt 0.9,-0.4] [--ref-views 10] [--ref-corners 54]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from zoomcalib.calibrate.io import read_zoom_table
from zoomcalib.diagnose.discrepancy import baseline_terms
from zoomcalib.diagnose.model import (
    Context,
    LensResponse,
    axis_tilt_term,
    decentring_distortion,
    design_matrix,
    group_term,
)
from zoomcalib.diagnose.table import ZoomTable
from zoomcalib.io import read_json
from zoomcalib.optics.mechanics import GroupTolerance, Tolerances
from zoomcalib.optics.prescription import load_prescription


@dataclass(frozen=True)
class Design:
    """A zoom set: lens states in [0, 1], views per setting, pixel pitch (mm), board corners."""

    name: str
    states: tuple[float, ...]
    views: int = 10
    pitch_mm: float = 0.0129
    corners: int = 54


@dataclass(frozen=True)
class NoiseReference:
    """Per-axis principal-point sd (px) against EFL (mm) of a reference set, and its design."""

    efl_mm: np.ndarray
    sd_px: np.ndarray
    views: int
    corners: int
    error_factor: float
    sd_p: np.ndarray  # (M, 2) sd of p1, p2 (normalised image units)
    pitch_mm: float
    p_error_factor: float = 1.0

    @classmethod
    def read(cls, table: Path, views: int, corners: int) -> NoiseReference:
        rows = read_zoom_table(table)
        dataset = table.parents[2] / "set" / "dataset.json"
        doc = read_json(dataset) if dataset.is_file() else None
        pitch = doc["sensor"]["pixel_pitch_mm"] if doc else float(input_pitch(table))
        fx = np.array([r["fx"] for r in rows])
        sd = np.sqrt(0.5 * np.array([r["sd_cx"] ** 2 + r["sd_cy"] ** 2 for r in rows]))
        factor = p_factor = 1.0
        if doc:
            truth = {st["step"]: st["camera"] for st in doc["steps"]}
            z = [(r[q] - truth[r["step"]][q]) / r[f"sd_{q}"] for r in rows for q in ("cx", "cy")]
            factor = float(np.sqrt(np.mean(np.square(z))))
            zp = [(r[q] - truth[r["step"]]["dist"][k]) / r[f"sd_{q}"] for r in rows
                  for k, q in ((2, "p1"), (3, "p2"))]
            p_factor = float(np.sqrt(np.mean(np.square(zp))))
        order = np.argsort(fx)
        sd_p = np.array([[r["sd_p1"], r["sd_p2"]] for r in rows]) * p_factor
        return cls(fx[order] * pitch, sd[order], views, corners, factor, sd_p[order], pitch,
                   p_factor)

    def sd(self, efl_mm: np.ndarray, views: int, corners: int) -> np.ndarray:
        """(N,) per-axis sd, px, at ``efl_mm`` for a set of ``views`` views of ``corners``."""
        log_sd = np.interp(np.log(efl_mm), np.log(self.efl_mm), np.log(self.sd_px))
        scale = np.sqrt(self.views / views * self.corners / corners) * self.error_factor
        return np.exp(log_sd) * scale

    def sd_tangential(self, efl_mm: np.ndarray, views: int, corners: int,
                      pitch_mm: float) -> np.ndarray:
        """(N, 2) sd of ``p1``, ``p2`` at ``efl_mm`` (scaled like :meth:`sd`, and by pitch)."""
        scale = np.sqrt(self.views / views * self.corners / corners) * pitch_mm / self.pitch_mm
        return np.stack([np.exp(np.interp(np.log(efl_mm), np.log(self.efl_mm),
                                           np.log(self.sd_p[:, k]))) for k in (0, 1)], -1) * scale


def input_pitch(table: Path) -> float:
    raise SystemExit(f"{table}: no dataset.json two folders up to give the pixel pitch")


def tolerances() -> Tolerances:
    """The benchmark's tolerances (1 um play per moving group)."""
    return Tolerances({"variator": GroupTolerance(play_um=1.0),
                       "compensator": GroupTolerance(play_um=1.0)}, "design")


def separation(design: Design, response: LensResponse, noise: NoiseReference,
               tilt_mrad: np.ndarray) -> dict:
    """Signature sizes and overlap of axis tilt and static decentre for ``design``."""
    r = response.with_pitch(design.pitch_mm)
    z = np.asarray(design.states, dtype=float)
    efl = np.interp(z, r.zoom_grid, r.efl_grid)
    fx = efl / design.pitch_mm
    n = len(z)
    table = ZoomTable(zoom=z, fx=fx, fy=fx, cx=np.zeros(n), cy=np.zeros(n),
                      sd_cx=np.zeros(n), sd_cy=np.zeros(n))
    ctx = Context.build(table, z, r)
    sigma = np.sqrt(noise.sd(efl, design.views, design.corners) ** 2
                    + r.play_sd_px(z, tolerances()) ** 2)
    w = np.repeat(1.0 / sigma, 2)[:, None]

    def off_baseline(a: np.ndarray) -> np.ndarray:
        q, _ = np.linalg.qr(design_matrix(baseline_terms(r.groups), ctx) * w)
        return a - q @ (q.T @ a)

    t = off_baseline(design_matrix((axis_tilt_term(),), ctx) * w) @ tilt_mrad
    tilt_chi2 = float(t @ t)
    absorbed, mimic = {}, {}
    for g in r.groups:
        d = off_baseline(design_matrix((group_term(g, "decenter", 0, "static"),), ctx) * w)
        mimic[g], *_ = np.linalg.lstsq(d, t, rcond=None)
        absorbed[g] = float(np.sum((d @ mimic[g]) ** 2) / tilt_chi2)
    best = max(absorbed, key=absorbed.get)
    gap = (1.0 - absorbed[best]) * tilt_chi2
    sd = 2.0 * np.sqrt(gap)
    dp = decentring_distortion(response.lens, z, best, mimic[best] * 1e-3)
    sd_p = noise.sd_tangential(efl, design.views, design.corners, design.pitch_mm)
    out = {"design": design.name, "rows": n, "views": n * design.views,
           "tilt_chi2": tilt_chi2, "absorbed": absorbed[best], "group": best, "gap": gap,
           "gap_sd": gap / sd, "p_static": float(stats.norm.sf(gap / sd)),
           "mimic_um": mimic[best], "p_chi2": float(np.sum((dp / sd_p) ** 2))}
    return out | joint_separation(ctx, w, 1.0 / sd_p.reshape(-1)[:, None], tilt_mrad)


def distortion_jacobian(lens, z: float, group: str, step_mm: float = 0.1) -> np.ndarray:
    """(2, 2) change of (p1, p2) per mm of ``group``'s decentre (x, y) at lens state ``z``."""
    key = (group, round(float(z), 9))
    if key not in _JACOBIANS:
        _JACOBIANS[key] = np.stack([decentring_distortion(lens, np.array([z]), group,
                                                          step_mm * e)[0] / step_mm
                                    for e in np.eye(2)], -1)
    return _JACOBIANS[key]


_JACOBIANS: dict[tuple[str, float], np.ndarray] = {}


def tangential_columns(ctx: Context, group: str, harmonic: int) -> np.ndarray:
    """(2N, 2) change of (p1, p2) per um of ``group``'s decentre turning at ``harmonic`` times
    the barrel angle (the tangential rows of that group's term)."""
    angle = harmonic * ctx.phi
    rot = np.stack([np.stack([np.cos(angle), -np.sin(angle)], -1),
                    np.stack([np.sin(angle), np.cos(angle)], -1)], 1)  # shape (N, 2, 2)
    jac = np.array([distortion_jacobian(ctx.response.lens, zz, group) for zz in ctx.z])
    return 1e-3 * np.einsum("nij,njk->nik", jac, rot).reshape(-1, 2)


def joint_separation(ctx: Context, w: np.ndarray, w_p: np.ndarray,
                     tilt_mrad: np.ndarray) -> dict:
    """``gap`` and ``absorbed`` again, with every row's tangential distortion (p1, p2) fitted
    beside its principal point: each decentre term adds its distortion rows, the axis tilt and
    the sensor offset none."""
    groups = ctx.response.groups
    zeros = np.zeros((2 * len(ctx.z), 2))
    base = [np.vstack([design_matrix(baseline_terms(()), ctx) * w, zeros])]
    base += [np.vstack([design_matrix((group_term(g, "decenter", 1, "locked"),), ctx) * w,
                        tangential_columns(ctx, g, 1) * w_p]) for g in groups]
    q, _ = np.linalg.qr(np.hstack(base))
    t = np.vstack([design_matrix((axis_tilt_term(),), ctx) * w, zeros]) @ tilt_mrad
    t = t - q @ (q.T @ t)
    absorbed = {}
    for g in groups:
        d = np.vstack([design_matrix((group_term(g, "decenter", 0, "static"),), ctx) * w,
                       tangential_columns(ctx, g, 0) * w_p])
        d = d - q @ (q.T @ d)
        coef, *_ = np.linalg.lstsq(d, t, rcond=None)
        absorbed[g] = float(np.sum((d @ coef) ** 2) / (t @ t))
    best = max(absorbed.values())
    gap = (1.0 - best) * float(t @ t)
    return {"joint_absorbed": best, "joint_gap": gap, "joint_gap_sd": gap / (2 * np.sqrt(gap))}


def local_absorption(response: LensResponse, noise: NoiseReference, pitch_mm: float,
                     tilt_mrad: np.ndarray, n: int = 13) -> list[tuple[float, float, float]]:
    """Where in the range a static decentre departs from an axis tilt: for every lens state
    ``z0``, one row at ``z0`` added to a uniform 8-setting set; its gain in ``gap``."""
    base = tuple(np.linspace(0.0, 1.0, 8))
    ref = separation(Design("uniform 8", base, pitch_mm=pitch_mm), response, noise, tilt_mrad)
    out = []
    for z0 in np.linspace(0.0, 1.0, n):
        s = separation(Design("+1", base + (float(z0),), pitch_mm=pitch_mm), response, noise,
                       tilt_mrad)
        efl = float(np.interp(z0, response.zoom_grid, response.efl_grid))
        out.append((float(z0), efl, s["gap"] - ref["gap"]))
    return out


def affine_departure(response: LensResponse, n: int = 11
                     ) -> list[tuple[float, float, dict[str, float]]]:
    """Per lens state: each moving group's ``S_g`` less its least-squares line in EFL over a
    dense uniform grid of states, over the range of ``S_g`` (an axis tilt is such a line)."""
    z = np.linspace(0.0, 1.0, 201)
    efl = np.interp(z, response.zoom_grid, response.efl_grid)
    line = np.stack([np.ones_like(efl), efl], -1)
    sens = response.sensitivities(z)
    dev = {}
    for g in response.groups:
        s_d = sens[g][0]
        coef, *_ = np.linalg.lstsq(line, s_d, rcond=None)
        dev[g] = (s_d - line @ coef) / np.ptp(s_d)
    pick = np.linspace(0, len(z) - 1, n).astype(int)
    return [(float(z[i]), float(efl[i]), {g: float(dev[g][i]) for g in dev}) for i in pick]


def designs() -> list[Design]:
    """The designs compared: placements, settings, views, sensors, boards."""
    uni8 = tuple(np.linspace(0.0, 1.0, 8))
    out = [Design("uniform 8 (today)", uni8)]
    for k in (12, 16):
        out.append(Design(f"uniform {k}", tuple(np.linspace(0.0, 1.0, k))))
    out.append(Design("8, long-end heavy (sqrt)", tuple(np.sqrt(np.linspace(0.0, 1.0, 8)))))
    out.append(Design("12, long-end heavy (sqrt)", tuple(np.sqrt(np.linspace(0.0, 1.0, 12)))))
    out.append(Design("8, short-end heavy (z^2)", tuple(np.linspace(0.0, 1.0, 8) ** 2)))
    out.append(Design("12, short-end heavy (z^2)", tuple(np.linspace(0.0, 1.0, 12) ** 2)))
    out.append(Design("8, 20 views", uni8, views=20))
    out.append(Design("8, board 13x9 (117 corners)", uni8, corners=117))
    for w, pitch in ((1280, 0.00645), (1920, 0.0043)):
        out.append(Design(f"8 at {w} px wide", uni8, pitch_mm=pitch))
        out.append(Design(f"12 at {w} px wide", tuple(np.linspace(0.0, 1.0, 12)),
                          pitch_mm=pitch))
        out.append(Design(f"12 z^2 at {w} px wide", tuple(np.linspace(0.0, 1.0, 12) ** 2),
                          pitch_mm=pitch))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", required=True, type=Path,
                    help="zoom_calibration.csv of a per-step calibrated rendered set")
    ap.add_argument("--ref-views", type=int, default=10)
    ap.add_argument("--ref-corners", type=int, default=54, help="corners of its board (9x6: 54)")
    ap.add_argument("--tilt", default="0.9,-0.4", help="TX,TY mrad")
    a = ap.parse_args()
    tilt = np.array([float(v) for v in a.tilt.split(",")])
    response = LensResponse.of(load_prescription("laikin-10x"))
    noise = NoiseReference.read(a.reference, a.ref_views, a.ref_corners)
    print(f"# reference {a.reference}: sd {noise.sd_px.min():.2f}-{noise.sd_px.max():.2f} px "
          f"over {noise.efl_mm.min():.0f}-{noise.efl_mm.max():.0f} mm, error factor "
          f"{noise.error_factor:.2f} (of p1, p2: {noise.p_error_factor:.2f}); tilt "
          f"{tilt.tolist()} mrad")
    print("\n# each group's shift per decentre S_g less its best line in EFL (a + b EFL; "
          "uniform in lens state), as a fraction of its range")
    for z0, efl, dev in affine_departure(response):
        print(f"z {z0:.2f}  efl {efl:6.1f} mm  " + "  ".join(f"{g} {v:+.3f}"
                                                          for g, v in dev.items()))
    print()
    print("| design | rows | views | tilt chi2 | absorbed | by | gap | gap/sd | P(static) "
          "| mimic um | p chi2 | with p: absorbed | gap | gap/sd |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for d in designs():
        s = separation(d, response, noise, tilt)
        print(f"| {s['design']} | {s['rows']} | {s['views']} | {s['tilt_chi2']:.1f} | "
              f"{s['absorbed']:.3f} | {s['group']} | {s['gap']:.1f} | {s['gap_sd']:.2f} | "
              f"{s['p_static']:.3f} | ({s['mimic_um'][0]:.0f}, {s['mimic_um'][1]:.0f}) | "
              f"{s['p_chi2']:.0f} | {s['joint_absorbed']:.3f} | {s['joint_gap']:.1f} | "
              f"{s['joint_gap_sd']:.2f} |")
    print("\n# gain in gap from one more setting at lens state z0 (uniform 8, 12.9 um pitch)")
    for z0, efl, gain in local_absorption(response, noise, 0.0129, tilt):
        print(f"z0 {z0:.3f}  efl {efl:6.1f} mm  gap gain {gain:6.2f}")


if __name__ == "__main__":
    main()
