"""Tangential distortion as further evidence between causes the principal points cannot part.

On ``laikin-10x`` a static decentre of a group moves the principal point almost exactly as an
axis tilt does (its shift per decentre is nearly a straight line in focal length). But a
decentred group also bends the image: the calibration's tangential distortion ``p1``, ``p2``
(OpenCV) changes with it (:func:`zoomcalib.diagnose.model.decentring_distortion`), while an
axis tilt moves the image and, through the tilted sensor's keystone, changes ``p1``, ``p2``
only as far as the calibration took the keystone into them (the table's keystone response,
:func:`zoomcalib.diagnose.model.axis_tilt_term`; nothing without it). Every row of a
calibration table holds ``p1``, ``p2`` and their sigmas beside ``cx``, ``cy``.

:func:`distortion_evidence` fits each candidate cause again with every row's ``p1``, ``p2``
stacked under its principal point. Each decentre or tilt of a group adds its distortion rows
(``J_g(z) R(m phi) a``, ``J_g`` the change of (p1, p2) per decentre, or per tilt, at the row's
lens state, from the exact tracer's camera fits); the axis tilt adds its keystone's, the
sensor offset none.
The baseline is the diagnosis's with the locked tilt of each moving group (a locked tilt and
a locked decentre move the principal point alike but bend the image differently) and the
other causes the diagnosis selected (a backlash of a group bends the image too). Weights: the
principal points keep the variances of the diagnosis's selected model; the distortion rows
have ``(k sd_p)^2`` with one scale ``k`` estimated from the largest model's distortion
residuals (chi2 per degree of freedom, since calibration sigmas are often off by a common
factor). Each cause is scored by ``delta_bic`` against this baseline, as in the diagnosis.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..optics.lens_camera import lens_camera
from ..optics.mechanics import ARCMIN, UM
from .discrepancy import BIC_MARGIN, Diagnosis, baseline_terms, cause_variants
from .model import Context, Term, design_matrix
from .noise import RowWeights
from .response import opposite_errors

__all__ = ["distortion_jacobian", "distortion_evidence", "resolve_with_distortion",
           "table_distortion", "EVIDENCE_CAUSES"]

#: the causes compared (those whose columns the principal points cannot tell apart)
EVIDENCE_CAUSES = ("axis_tilt", "static_decenter")
#: finite-difference steps: decentre (mm) and tilt (rad)
_STEP = {"decenter": 0.05, "tilt": 1e-3}


def distortion_jacobian(lens, z: float, group: str, kind: str) -> np.ndarray:
    """(2, 2) change of (p1, p2) per mm of decentre (``kind='decenter'``) or per rad of tilt
    (``'tilt'``) of ``group`` along x and y (columns), at lens state ``z``; central
    differences of the exact tracer's camera fits."""
    step = _STEP[kind]
    cols = []
    for axis in np.eye(2):
        plus, minus = opposite_errors(lens, group, kind, step * axis)
        cols.append((lens_camera(lens, z, plus).camera.dist[2:4]
                     - lens_camera(lens, z, minus).camera.dist[2:4]) / (2 * step))
    return np.stack(cols, -1)


class _Tangential:
    """Distortion rows of the terms, with the Jacobians of each (group, kind, state) cached."""

    def __init__(self, ctx: Context):
        self.ctx = ctx
        self._jac: dict[tuple[str, str, float], np.ndarray] = {}

    def _jacobians(self, group: str, kind: str) -> np.ndarray:
        measured = self.ctx.group_response(group, kind)
        if measured is not None:  # as each row's calibration takes it
            return measured[:, 2:]
        out = []
        for z in self.ctx.z:
            key = (group, kind, round(float(z), 9))
            if key not in self._jac:
                self._jac[key] = distortion_jacobian(self.ctx.response.lens, float(z), group,
                                                     kind)
            out.append(self._jac[key])
        return np.array(out)  # shape (N, 2, 2)

    def rows(self, term: Term) -> np.ndarray:
        """(2N, k) change of (p1, p2) per unit of each parameter of ``term``."""
        n, k = len(self.ctx.z), len(term.params)
        if term.tangential is not None:
            return term.tangential(self.ctx).reshape(2 * n, k)
        group, kind, harmonic = _group_term_parts(term, self.ctx.response.groups)
        if group is None:
            return np.zeros((2 * n, k))
        angle = harmonic * self.ctx.phi
        c, s = np.cos(angle), np.sin(angle)
        rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], 1)  # shape (N, 2, 2)
        unit = UM if kind == "decenter" else ARCMIN
        if term.name.startswith("backlash"):  # the side follows the last zoom move
            rot = rot * self.ctx.table.direction[:, None, None]
        return unit * np.einsum("nij,njk->nik", self._jacobians(group, kind),
                                rot).reshape(2 * n, 2)


def _group_term_parts(term: Term, groups: tuple[str, ...]) -> tuple[str | None, str, int]:
    """(group, kind, harmonic) of a group term by its name, (None, '', 0) for any other."""
    harmonics = {"locked decentre": ("decenter", 1), "locked tilt": ("tilt", 1),
                 "static decentre": ("decenter", 0), "cam harmonic": ("decenter", 2),
                 "backlash": ("decenter", 1)}
    label, _, group = term.name.rpartition(", ")
    if group in groups and label in harmonics:
        return (group, *harmonics[label])
    return None, "", 0


def _fit(cols: np.ndarray, y: np.ndarray, weights: RowWeights
         ) -> tuple[float, np.ndarray, np.ndarray]:
    """chi2, parameters and their covariance of the weighted linear fit."""
    beta, *_ = np.linalg.lstsq(weights.whiten(cols), weights.whiten(y), rcond=None)
    cov = np.linalg.pinv(weights.normal(cols))
    return weights.chi2(y - cols @ beta), beta, cov


def distortion_evidence(diag: Diagnosis, p: np.ndarray, sd_p: np.ndarray,
                        causes: tuple[str, ...] = EVIDENCE_CAUSES) -> dict:
    """Score ``causes`` on the principal points and the tangential distortion together.

    Parameters
    ----------
    diag : Diagnosis
        A diagnosis with a lens model (its rows' lens states and selected model's noise).
    p, sd_p : (N, 2) ndarray
        Every row's calibrated (p1, p2) and their 1-sigma (dimensionless), in the table's order.
    causes : tuple of str
        The causes to score (each by its variant of lowest BIC).

    Returns
    -------
    dict with ``p_scale`` (the estimated ``k``), ``baseline_chi2`` (the baseline with the
    diagnosis's other selected causes, ``base_causes``), and per cause in
    ``causes``: ``variant``, ``delta_bic`` (against the baseline with distortion rows),
    ``params`` and ``params_sd`` of its best variant, and ``variants`` (each variant's
    ``delta_bic``); ``best``, the cause of lowest ``delta_bic``.

    Raises
    ------
    ValueError
        Without a lens model, or with distortion sigmas that are not all positive.
    """
    if diag.response is None:
        raise ValueError(f"{diag.table.source}: distortion evidence needs a lens model")
    p, sd_p = np.asarray(p, dtype=float), np.asarray(sd_p, dtype=float)
    if p.shape != (diag.table.n, 2) or sd_p.shape != p.shape or not np.all(sd_p > 0):
        raise ValueError(f"{diag.table.source}: p1, p2 and positive sd_p1, sd_p2 are needed "
                         f"for every row")
    ctx = Context.build(diag.table, diag.z, diag.response)
    tangential = _Tangential(ctx)

    def columns(terms: tuple[Term, ...]) -> np.ndarray:
        return np.vstack([design_matrix(terms, ctx),
                          np.hstack([tangential.rows(t) for t in terms])])

    variants, _ = cause_variants(diag.table, diag.response.groups)
    others = tuple(t for s in diag.causes if s.cause not in causes for t in s.terms)
    base = baseline_terms(diag.response.groups, locked_tilt=True) + others
    y = np.concatenate([diag.table.principal_point.reshape(-1), p.reshape(-1)])
    w_c = diag.final.weights or RowWeights(np.repeat(1.0 / diag.final.variance, 2))
    largest = base + tuple(t for c in causes for v in variants[c] for t in v)
    scale = 1.0
    for _ in range(20):  # fixed point of the distortion rows' chi2 per degree of freedom
        w = w_c.stacked(1.0 / (scale * sd_p.reshape(-1)) ** 2)
        _, beta, _ = _fit(columns(largest), y, w)
        r = (y - columns(largest) @ beta)[2 * diag.table.n:] / sd_p.reshape(-1)
        new = float(np.sqrt(np.sum(r ** 2) / max(r.size - len(beta) / 2, 1.0)))
        if abs(new - scale) < 1e-4 * scale:
            break
        scale = new
    w = w_c.stacked(1.0 / (scale * sd_p.reshape(-1)) ** 2)
    base_chi2, _, _ = _fit(columns(base), y, w)
    out: dict = {"p_scale": scale, "baseline_chi2": base_chi2, "causes": {},
                 "base_causes": [s.cause for s in diag.causes if s.cause not in causes]}
    for cause in causes:
        scored = []
        for extra in variants[cause]:
            chi2, beta, cov = _fit(columns(base + extra), y, w)
            k = sum(len(t.params) for t in extra)
            names = [q for t in extra for q in t.params]
            scored.append({"variant": " + ".join(t.name for t in extra),
                           "delta_bic": chi2 - base_chi2 + k * np.log(y.size),
                           "params": dict(zip(names, beta[-k:].tolist(), strict=True)),
                           "params_sd": dict(zip(names, np.sqrt(np.diag(cov))[-k:].tolist(),
                                                 strict=True))})
        out["causes"][cause] = min(scored, key=lambda s: s["delta_bic"])
        out["causes"][cause]["variants"] = {s["variant"]: s["delta_bic"] for s in scored}
    out["best"] = min(out["causes"], key=lambda c: out["causes"][c]["delta_bic"])
    pairs = [base + a + b for a in variants[causes[0]] for b in variants[causes[1]]]
    k_pair = [sum(len(t.params) for t in terms) - sum(len(t.params) for t in base)
              for terms in pairs]
    out["pair_delta_bic"] = min(_fit(columns(terms), y, w)[0] - base_chi2 + k * np.log(y.size)
                                for terms, k in zip(pairs, k_pair, strict=True))
    return out


def table_distortion(rows: list[dict]) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 2) p1, p2 and (N, 2) their sigmas from a table's rows, None unless every row has
    them finite and the sigmas positive."""
    try:
        p = np.array([[float(r["p1"]), float(r["p2"])] for r in rows])
        sd = np.array([[float(r["sd_p1"]), float(r["sd_p2"])] for r in rows])
    except (KeyError, TypeError, ValueError):
        return None
    ok = np.all(np.isfinite(p)) and np.all(np.isfinite(sd)) and np.all(sd > 0)
    return (p, sd) if ok else None


def resolve_with_distortion(diag: Diagnosis, rows: list[dict],
                            refit: Callable[..., Diagnosis]) -> Diagnosis:
    """Weigh an axis tilt against a static decentre with the tangential distortion too.

    Needs a lens model and every row's ``p1``, ``p2`` with sigmas. The causes are scored by
    :func:`distortion_evidence` when

    - both are among the selected causes or ``ambiguous_with`` (the principal points cannot
      part them): when one's ``delta_bic`` is lower by more than
      :data:`~zoomcalib.diagnose.discrepancy.BIC_MARGIN` and the other was selected, the
      diagnosis is made again without the other (``exclude``, its reason under ``skipped``);
    - or the axis tilt was not selected but the table holds the calibration's keystone
      response (:attr:`ZoomTable.keystone`): a calibration takes most of a tilted sensor's
      keystone into its poses, which leaves the tilt a faint trace in the principal points
      and a clear one in ``p1``, ``p2``. When the tilt lowers the BIC of the principal points
      and ``p1``, ``p2`` together by more than ``BIC_MARGIN`` and fits them better than the
      static decentre, the diagnosis is made again with it required (``require``); a static
      decentre that lowers that BIC by more than ``BIC_MARGIN`` too, and trails the tilt by
      less than it, is not told apart (``ambiguous``, listed in ``ambiguous_with``).

    Either way, a selected one of the two that does not lower the BIC of the two together by
    more than ``BIC_MARGIN`` is left out (``exclude``): its trace in the principal points is
    not matched in ``p1``, ``p2``. And a selected cause whose variant (e.g. which group is
    decentred) the two together put behind another of its variants by more than
    ``BIC_MARGIN`` is made again with that variant (``restrict``): groups whose
    principal-point signatures are nearly one bend the image differently.
    ``refit(exclude=..., require=..., restrict=...)`` makes the diagnosis again. The scores
    are attached as ``distortion`` either way, with ``margin``, ``excluded`` (the contradicted
    cause, None when the margin is not passed), which ``ambiguous_with`` then leaves out,
    ``required`` (the cause the scores put in, or None), ``ambiguous`` (the other of the two
    when the required tilt leads it by at most ``BIC_MARGIN``), ``unsupported`` (the causes left out
    for want of support) and ``restricted`` (cause: variant).
    """
    named = {s.cause for s in diag.causes} | set(diag.ambiguous_with)
    selected = {s.cause: s.variant for s in diag.causes}
    data = table_distortion(rows)
    settle = set(EVIDENCE_CAUSES) <= named
    keystone = diag.table.keystone is not None and "axis_tilt" not in selected
    if diag.response is None or data is None or not (settle or keystone):
        return diag
    ev = distortion_evidence(diag, *data)
    winner = ev["best"]
    loser = next(c for c in EVIDENCE_CAUSES if c != winner)
    margin = ev["causes"][loser]["delta_bic"] - ev["causes"][winner]["delta_bic"]
    ev |= {"margin": margin, "excluded": None, "required": None, "ambiguous": None,
           "restricted": {}}
    changes: dict[str, dict[str, str]] = {"exclude": {}, "require": {}, "restrict": {}}
    if settle:
        ev["excluded"] = loser if margin > BIC_MARGIN else None
        if margin > BIC_MARGIN and loser in selected:
            changes["exclude"][loser] = (
                f"contradicted by the tangential distortion p1, p2: {winner} fits them and the "
                f"principal points better by {margin:.1f} in BIC (distortion_evidence)")
    elif winner == "axis_tilt" and ev["causes"][winner]["delta_bic"] < -BIC_MARGIN:
        ev["required"] = winner
        changes["require"][winner] = _tilt_evidence(ev, margin, loser)
        if margin <= BIC_MARGIN and ev["causes"][loser]["delta_bic"] < -BIC_MARGIN:
            ev["ambiguous"] = loser  # supported too, and not contradicted: not told apart
    ev["unsupported"] = [c for c in EVIDENCE_CAUSES if c in selected
                         and c not in changes["exclude"]
                         and ev["causes"][c]["delta_bic"] > -BIC_MARGIN]
    for cause in ev["unsupported"]:
        changes["exclude"][cause] = (
            f"not supported by the principal points and p1, p2 together: delta_bic "
            f"{ev['causes'][cause]['delta_bic']:.1f} (distortion_evidence); its trace in the "
            f"principal points is not matched in p1, p2")
    for cause, variant in selected.items():
        scores = ev["causes"].get(cause, {}).get("variants", {})
        best = min(scores, key=scores.get, default=variant)
        if cause not in changes["exclude"] and scores.get(variant, 0.0) - scores.get(
                best, 0.0) > BIC_MARGIN:
            ev["restricted"][cause] = changes["restrict"][cause] = best
    if any(changes.values()):
        diag = refit(**{k: v for k, v in changes.items() if v})
        if set(EVIDENCE_CAUSES) <= {s.cause for s in diag.causes} and (
                ev["pair_delta_bic"] > ev["causes"][winner]["delta_bic"] - BIC_MARGIN):
            # the refit selected the other one beside the winner on the principal points
            ev["unsupported"].append(loser)
            changes["exclude"][loser] = (
                f"adds less than {BIC_MARGIN:g} in BIC to {winner} on the principal points "
                f"and p1, p2 together (distortion_evidence)")
            diag = refit(**{k: v for k, v in changes.items() if v})
    diag.distortion = ev
    return diag


def _tilt_evidence(ev: dict, margin: float, loser: str) -> str:
    tilt = ev["causes"]["axis_tilt"]
    return (f"the tangential distortion p1, p2 with the calibrations' keystone response: "
            f"delta_bic {tilt['delta_bic']:.1f} on the principal points and p1, p2 together, "
            f"{margin:.1f} ahead of {loser}; tilt " + ", ".join(
                f"{k} {v:.2f} +- {tilt['params_sd'][k]:.2f}" for k, v in tilt["params"].items())
            + " (distortion_evidence)")
