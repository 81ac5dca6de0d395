r"""Do the views agree as closely as the corner noise says? The view-scatter check of a sigma.

A calibration's 1-sigma assumes independent corner errors of one variance. Real sets break that
inside each view: a lens the model does not fit leaves a smooth residual field, a paper board
waves, a compressed frame blurs a whole region. The errors of one view's corners are then
correlated, and two halves of the same set disagree by many of their sigmas (mrcal's
figueroa observations: 3-6x in fx, cx, cy; ``python benchmarks/bench_real_halves.py``).

The check compares two estimates of the same variance, from the solution's own residuals.
Eliminating the poses, the unknowns ``y`` (camera, free target coordinates) move by
``dy = S^-1 sum_i Jt_i^T e_i`` under corner errors ``e_i``, with ``S`` the Schur complement and
``Jt_i = J_y,i - J_p,i V_v^-1 W_v^T`` corner ``i``'s Jacobian with its view's pose projected
out. For a camera parameter ``q`` let ``a_iq = (S^-1 Jt_i^T r_i)_q`` (``r_i`` the residual, 2
components per corner) and ``b_vq = sum_{i in v} a_iq``. Then

- ``sum_i a_iq^2`` estimates the variance if corners are independent (the sandwich over corners),
- ``sum_v b_vq^2`` estimates it if only views are (clustered by view; Liang & Zeger 1986),

and their ratio ``F_q`` (the design effect) is 1 under the noise model, whatever the noise's
size, and the number of independent corners per view's worth of information when the errors of
a view move together. The two estimates share the residuals, so the fit's leverage shrinks both
alike and largely cancels in the ratio. ``F_q`` is multiplied by ``d / (d - 1)`` for the one
degree of freedom the fit takes (the ``b_vq`` sum to the prior's gradient, zero without one),
with ``d = (sum_v c_vq)^2 / sum_v c_vq^2``, ``c_vq = sum_{i in v} a_iq^2``, the effective number
of views (Satterthwaite: ``d`` views of equal weight, fewer when some dominate).

``F_q`` is significant when it exceeds the 99.9 % point of ``chi^2_d / d``, its spread under the
noise model. Where it is, the sigma the calibration reports is ``sqrt(F_q)`` times the noise
model's; elsewhere it is kept. Below :data:`MIN_VIEWS` effective views the check is not made.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.stats

__all__ = ["ViewScatter", "view_scatter", "MIN_VIEWS", "SIGNIFICANCE"]

#: Fewest effective views (``d``) for which the check is made.
MIN_VIEWS = 4.0
#: One-sided level of the chi-square test of ``F``.
SIGNIFICANCE = 0.001


@dataclass
class ViewScatter:
    """The view-scatter check of one solution's sigmas, per parameter (``names``).

    Attributes
    ----------
    factor : (k,) ndarray
        ``sqrt(F)``: the view-clustered 1-sigma over the corner-wise one; NaN for a fixed
        parameter or below :data:`MIN_VIEWS` effective views.
    views : (k,) ndarray
        Effective number of views ``d``.
    threshold : (k,) ndarray
        The factor above which the scatter is significant, ``sqrt(chi2_{0.999, d} / d)``.
    names : the parameters, k of them.
    """

    factor: np.ndarray
    views: np.ndarray
    threshold: np.ndarray
    names: tuple[str, ...]

    @property
    def significant(self) -> np.ndarray:
        """(k,) bool: the views disagree beyond what the corner noise explains."""
        with np.errstate(invalid="ignore"):
            return np.nan_to_num(self.factor) > self.threshold

    def scaled(self, sd: dict[str, float]) -> dict[str, float]:
        """``sd`` with each significant parameter's sigma multiplied by its factor."""
        out = dict(sd)
        for q, name in enumerate(self.names):
            if name in out and self.significant[q]:
                out[name] = float(out[name] * self.factor[q])
        return out

    def by_group(self, sep: str = ":") -> dict[str, ViewScatter]:
        """The check split by the names' prefix before ``sep`` (``'step:cx'`` -> step ``'step'``,
        parameter ``'cx'``)."""
        groups: dict[str, list[int]] = {}
        for q, name in enumerate(self.names):
            groups.setdefault(name.rsplit(sep, 1)[0], []).append(q)
        return {g: ViewScatter(self.factor[q], self.views[q], self.threshold[q],
                               tuple(self.names[i].rsplit(sep, 1)[1] for i in q))
                for g, q in groups.items()}

    def to_dict(self) -> dict:
        """``info['view_scatter']`` (docs/conventions.md): per checked parameter ``factor``,
        ``views`` and ``threshold``, and the names whose sigma was ``scaled``."""
        checked = [q for q in range(len(self.names)) if np.isfinite(self.factor[q])]
        return {key: {self.names[q]: float(arr[q]) for q in checked}
                for key, arr in (("factor", self.factor), ("views", self.views),
                                 ("threshold", self.threshold))} | {
            "scaled": [self.names[q] for q in checked if self.significant[q]]}


def view_scatter(influence: np.ndarray, view_idx: np.ndarray, n_views: int,
                 names: tuple[str, ...]) -> ViewScatter:
    """The view-scatter check (module docstring) from each corner's influence.

    Parameters
    ----------
    influence : (N, k) ndarray
        ``a_i``: corner ``i``'s share of the solution's move, ``(S^-1 Jt_i^T r_i)``, per
        parameter (``names``; a fixed parameter's column is zero).
        :meth:`zoomcalib.calibrate.bundle._Problem.camera_influence` computes it.
    view_idx : (N,) int ndarray
        The view of each corner, ``0 <= view_idx < n_views``.
    names : the parameters' names, k of them.
    """
    a = np.asarray(influence, dtype=float)
    if a.ndim != 2 or a.shape[1] != len(names) or len(view_idx) != len(a):
        raise ValueError(f"influence of shape {a.shape} for {len(view_idx)} corners and "
                         f"{len(names)} parameters")
    per_view = np.zeros((n_views, a.shape[1]))
    np.add.at(per_view, view_idx, a)
    corner_sq = np.zeros_like(per_view)
    np.add.at(corner_sq, view_idx, a * a)
    by_corner = corner_sq.sum(axis=0)
    used = by_corner > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        views = np.where(used, by_corner**2 / np.sum(corner_sq**2, axis=0), 0.0)
        ratio = np.sum(per_view**2, axis=0) / by_corner * views / (views - 1.0)
    ok = used & (views >= MIN_VIEWS)
    factor = np.where(ok, np.sqrt(np.clip(ratio, 0.0, None)), np.nan)
    dof = np.where(ok, views, 1.0)
    threshold = np.where(ok, np.sqrt(scipy.stats.chi2.ppf(1.0 - SIGNIFICANCE, dof) / dof),
                         np.nan)
    return ViewScatter(factor=factor, views=views, threshold=threshold, names=tuple(names))
