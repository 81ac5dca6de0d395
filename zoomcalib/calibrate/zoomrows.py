"""The zoom steps' rows over zoom, after the zoom-wide adjustment: which steps form a chain, the
zoom model each parameter's rows take, the rows without the smoothness prior and their principal
points' correlation, and the held-out check of each path.

:mod:`zoomcalib.calibrate.zoomwide` calls these on a solved adjustment
(:mod:`zoomcalib.calibrate.zoomproblem`); the zoom models themselves, the prior and its
strength, are :mod:`zoomcalib.calibrate.zoommodel`'s.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .result import CalibrationResult
from .zoommodel import (
    CANDIDATES,
    PathPrior,
    held_out_residuals,
    marginal_tau,
    pooled_prior_strength,
    select_zoom_model,
)
from .zoomproblem import PARAMS, SELECTED, SMOOTHED, _Form, _State, _tied

#: The fewest steps of a chain that estimate a parameter for it to have a zoom model.
MIN_MODEL_STEPS = 3


def _series(cams: np.ndarray, cov, free: np.ndarray, chains: list[np.ndarray], u: np.ndarray,
            j: int, form: _Form) -> list[tuple[list[int], tuple]]:
    """Per chain of :data:`MIN_MODEL_STEPS` or more free steps of parameter ``j``: the steps
    and the chain ``(values, noise, u, offset)`` (:mod:`~zoomcalib.calibrate.zoommodel`);
    ``noise`` from the sigmas ``cov`` (S, 12) or a function ``cov(steps, j)`` giving a
    covariance. With a ``form.weight`` ``w`` the values are ``w q``, their noise scaled alike
    and ``w`` the free offset's direction."""
    series, tied = [], _tied(free, j)
    for chain in chains:
        steps = [s for s in chain if tied[s]]
        if len(steps) < MIN_MODEL_STEPS:
            continue
        values = cams[steps, j]
        noise = cov(steps, j) if callable(cov) else np.asarray(cov, float)[steps, j]
        w = form.at(steps)
        if w is not None:
            values = w * values
            noise = w[:, None] * noise * w[None, :] if np.ndim(noise) == 2 else w * noise
        series.append((steps, (values, noise, u[steps], w if form.offset else None)))
    return series


def _zoom_models(cams: np.ndarray, cov, free: np.ndarray, chains: list[np.ndarray],
                 u: np.ndarray, selected: tuple[str, ...], forms: Mapping[str, _Form],
                 given: Mapping[str, float]) -> tuple[dict[str, PathPrior], list[tuple]]:
    """Per smoothed parameter with 3 or more free steps in a chain: the zoom model chosen by
    held-out steps (:func:`~zoomcalib.calibrate.zoommodel.select_zoom_model`) for the
    ``selected`` ones, else the second-difference prior of its form (``forms``, default
    ``prior2``) with its REML ``tau``, pooled over the chains. Also, for cx and cy under a
    prior with a REML ``tau``, that ``tau`` is marginalised (its posterior median, and
    ``(steps, j, extra)``: the px covariance ``extra`` that its uncertainty adds to those
    steps' values, :func:`~zoomcalib.calibrate.zoommodel.marginal_tau`). A ``given`` tau is
    used as it is."""
    models, inflation = {}, []
    for name in SMOOTHED:
        form = forms.get(name, _Form())
        j = PARAMS.index(name)
        series = _series(cams, cov, free, chains, u, j, form)
        if not series:
            continue
        tuples = [c for _, c in series]
        if name in given:
            models[name] = PathPrior(form.name, 2, float(given[name]), tau_kind="given")
            continue
        if name in selected:
            models[name] = select_zoom_model(tuples)
        else:
            models[name] = PathPrior(form.name, 2, *pooled_prior_strength(tuples, 2))
        model = models[name]
        if name not in SELECTED or not CANDIDATES.get(model.name, (2, True))[1]:
            continue
        extra = marginal_tau(model, tuples)
        for (steps, (*_, w)), e in zip(series, extra, strict=True):
            inflation.append((steps, j, e if w is None else e / np.outer(w, w)))
    return models, inflation


def _unsmoothed_rows(cams: np.ndarray, cov, free: np.ndarray, names: list[str]
                     ) -> dict[str, dict]:
    """Per step, fx, fy, cx, cy of the solve without the smoothness prior and their 1-sigma
    (its joint covariance ``cov``, scaled by the views' scatter as the table's sigmas are:
    :func:`_with_scatter`), and ``step_correlation``: per parameter, the largest correlation
    of the step's value with another step's (the solve's steps share the aspect ratio and,
    per capture session, the board). Rows a diagnosis can take as measurements of each
    step; ``fy`` is ``fx`` times the step's aspect."""
    steps = np.arange(len(names))
    out = {n: {"fx": float(cams[s, 0]), "fy": float(cams[s, 1]), "cx": float(cams[s, 2]),
               "cy": float(cams[s, 3]), "step_correlation": {}} for s, n in enumerate(names)}
    for q in ("fx", "cx", "cy"):
        j = PARAMS.index(q)
        C = np.asarray(cov(steps, j), float)
        sd = np.sqrt(np.maximum(np.diag(C), 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.abs(C / np.outer(sd, sd))
        np.fill_diagonal(corr, 0.0)
        for s, n in enumerate(names):
            out[n][f"sd_{q}"] = float(sd[s])
            out[n]["step_correlation"][q] = float(np.nan_to_num(corr[s]).max(initial=0.0))
        if q == "fx":
            for s, n in enumerate(names):
                out[n]["sd_fy"] = float(sd[s] * cams[s, 1] / cams[s, 0])
    return out


def _principal_point_correlation(cov, names: list[str]) -> np.ndarray | None:
    """(2S, 2S) correlation of every step's ``(cx, cy)`` with every other's, from ``cov``
    (:func:`_joint_covariance`, scaled as the table's sigmas are: :func:`_with_scatter`),
    ordered ``(cx_0, cy_0, cx_1, ...)``; None when a principal point is held (no variance).

    ``corr_ab = C_ab / sqrt(C_aa C_bb)``: with the table's sigmas it rebuilds the covariance
    of the rows, which the diagnosis weighs them with."""
    C = np.asarray(cov(list(range(len(names))), (PARAMS.index("cx"), PARAMS.index("cy"))),
                   float)
    sd = np.sqrt(np.diag(C))
    if not np.all(sd > 0):
        return None
    corr = C / np.outer(sd, sd)
    np.fill_diagonal(corr, 1.0)
    return 0.5 * (corr + corr.T)


def _held_out_paths(cams: np.ndarray, cov, free: np.ndarray, chains: list[np.ndarray],
                    u: np.ndarray, forms: Mapping[str, _Form], models: Mapping[str, PathPrior],
                    names: list[str]) -> dict[str, dict]:
    """Per modelled parameter: each step of its chains predicted from the other steps' values
    (``cams``, sigmas or joint covariance ``cov`` as :func:`_series` reads them) under its zoom
    model (:func:`~zoomcalib.calibrate.zoommodel.held_out_residuals`; a REML ``tau``
    marginalised over its posterior given the other steps; the values' noise scaled by
    :func:`_with_scatter`):
    ``{"steps": [...], "error": [...], "sd": [...]}``, the value minus
    its prediction and the predictive 1-sigma (the step's own noise included), in the
    parameter's units. A chain too short to predict from is left out."""
    out = {}
    for name, model in models.items():
        form, j = forms.get(name, _Form()), PARAMS.index(name)
        reml = CANDIDATES.get(model.name, (2, True))[1] and model.tau_kind != "given"
        record: dict[str, list] = {"steps": [], "error": [], "sd": []}
        for steps, chain in _series(cams, cov, free, chains, u, j, form):
            got = held_out_residuals(chain, model.order, model.tau, reml, marginal=True)
            if got is None:
                continue
            w = form.at(steps)
            w = np.ones(len(steps)) if w is None else np.abs(w)
            record["steps"] += [names[s] for s in steps]
            record["error"] += [float(v) for v in got[0] / w]
            record["sd"] += [float(v) for v in got[1] / w]
        out[name] = record
    return out


def _chains(u: np.ndarray, labels: list[str], min_gap: float = 1e-3) -> list[np.ndarray]:
    """Step indices of each chain of the smoothness prior: the steps of one label (e.g. one
    zoom direction), sorted by ``u``, cut where two neighbours are closer than ``min_gap`` in
    ``u`` (0.1 % in focal length: one lens state met twice is not a second difference)."""
    chains = []
    for label in dict.fromkeys(labels):
        idx = np.array([i for i, lab in enumerate(labels) if lab == label])
        idx = idx[np.argsort(u[idx], kind="stable")]
        cuts = np.flatnonzero(np.diff(u[idx]) < min_gap) + 1
        chains += [c for c in np.split(idx, cuts) if len(c)]
    return chains


def _prior_share(result: CalibrationResult, joint_cov, s: int) -> dict[str, float]:
    """Per cx, cy of step ``s``: the share of its precision that the smoothness prior gives,
    ``1 - var / var_0`` (``var_0`` from the solve without the prior, ``var`` the adjustment's,
    both the noise model's: the view-scatter factor of one is not the other's; 0: the step's
    own views decide it, near 1: its neighbours do)."""
    sd = result.info.get("sd_noise_model", result.sd)
    out = {}
    for q in SELECTED:
        if not sd.get(q):  # held
            continue
        var0 = float(joint_cov([s], PARAMS.index(q))[0, 0])
        out[q] = float(np.clip(1.0 - sd[q] ** 2 / var0, 0.0, 1.0))
    return out


def _tie_terms(state: _State, free: np.ndarray, chains: list[np.ndarray], u: np.ndarray,
               models: Mapping[str, PathPrior]) -> np.ndarray:
    """``free`` (S, 12) with every distortion term that has a zoom model freed at every step of
    each chain where one of its steps estimates it; a newly freed value starts from the
    chain's estimates, interpolated in ``u`` (held at the ends). ``state.cams`` is updated.

    A step whose own views cannot measure a term (the long end's narrow field) then takes it
    from its neighbours through the smoothness prior, with the prior's uncertainty in its
    sigma, instead of holding it at zero: a term near the limit of what the held-out views can
    tell would otherwise be in or out with the noise draw. p1 and p2 go only to steps that
    estimate a radial term of their own: the decentring they carry is first order in the radial
    distortion (:func:`~zoomcalib.calibrate.stepfits.with_decentring`), and where that is too small
    to measure so is it."""
    free = free.copy()
    radial = free[:, [PARAMS.index(k) for k in ("k1", "k2", "k3")]].any(axis=1)
    for name in models:
        j = PARAMS.index(name)
        if j < 4:
            continue
        takes = radial if name in ("p1", "p2") else np.ones(len(free), bool)
        tied = _tied(free, j)
        for chain in chains:
            have = [s for s in chain if tied[s]]
            new = [s for s in chain if not free[s, j] and takes[s]]
            if not have or not new:
                continue
            state.cams[new, j] = np.interp(u[new], u[have], state.cams[have, j])
            free[new, j] = True
    return free
