r"""Do the views agree as closely as the corner noise says? The view-scatter check of a sigma.

A calibration's 1-sigma assumes independent corner errors of one variance. Real sets break that
inside each view: a lens the model does not fit leaves a smooth residual field, a paper board
waves, a compressed frame blurs a whole region. The errors of one view's corners are then
correlated, and two halves of the same set disagree by many of their sigmas
(``python benchmarks/bench_real_halves.py`` on real sets).

The check compares the noise model's variance with one that assumes only that views are
independent. Eliminating the poses, the unknowns ``y`` (camera, free target coordinates) move by
``dy = S^-1 sum_i Jt_i^T e_i`` under corner errors ``e_i``, with ``S`` the Schur complement and
``Jt_i = J_y,i - J_p,i V_v^-1 W_v^T`` corner ``i``'s Jacobian with its view's pose projected
out. For a camera parameter ``q`` let ``a_iq = (S^-1 Jt_i^T r_i)_q`` (``r_i`` the residual, 2
components per corner) and ``b_vq = sum_{i in v} a_iq``. Then

    var_views(q) = sum_v b_vq^2 / s_q

is the variance clustered by view (Liang & Zeger 1986): it holds whatever the errors inside a
view do, as long as views are independent. ``s_q`` restores what the fit takes: each view's
residuals are pulled towards the solution it helped make, so under the noise model
``E[sum_v b_vq^2] = s_q var_model(q)`` with ``s_q = 1 - sum_v [B_v^T S^-1 B_v]_qq / M_q``,
``B_v = A_v S^-1 e_q``, ``A_v = sum_{i in v} Jt_i^T Jt_i`` and ``M_q = sum_v [S^-1 e_q]^T B_v``
(:func:`noise_share`, which also counts a prior): the views' leverage on ``q``. A parameter
that two views of eight carry keeps a quarter of its variance in the clustered sum, one that
all carry alike ``(d - 1) / d`` of it (the approximation used when the leverage is not
given), with ``d = (sum_v c_vq)^2 / sum_v c_vq^2``, ``c_vq = sum_{i in v} a_iq^2``, the
effective number of views (Satterthwaite: ``d`` views of equal weight, fewer when some
dominate). The factor is ``sqrt(var_views / var_model)``; under the noise model it is spread
about 1 like ``chi^2_d / d``.

The leverage's correction holds on average; the size of a scaled sigma needs more. Where the
global unknowns are few enough to solve once per view (at most ``DELETION_MAX_UNKNOWNS``
camera and free target unknowns in the bundle, which OpenCV's fits and a 10 x 10 board are;
the zoom-wide adjustment's intrinsics and board modes), the size of a scaled sigma comes from
the delete-one-view jackknife in one Gauss-Newton step (CR3 of Bell & McCaffrey 2002):
``delta_v = (S - A_v)^-1 g_v`` with ``g_v = sum_{i in v} Jt_i^T r_i``, and
``var_views = (m - 1) / m sum_v (delta_v - mean delta)^2``. The test stays on the clustered
sum: the jackknife's spread under the noise model has heavier tails than ``chi^2_d / d`` where
the fit is not linear in one view (on rendered sweeps it flagged a long-end fx whose
noise-model sigma was honest).

The clustered sum's factor is significant when its square exceeds the 99.9 % point of
``chi^2_d / d``: the views disagree, and the parameter is flagged (``scaled``). The sigma
the calibration reports is the factor (the jackknife's where computed, at least 1) times the
noise model's. A factor below the threshold is scaled by too (listed as ``widened``, not
flagged): a misfit too small for 20 views to show at that level still leaves the noise model's
sigma too small, so each checked sigma is the larger of the model's and the view-clustered one
(the rule Angrist & Pischke 2009, section 8.1, give for robust standard errors;
:data:`SCALE_UNTESTED`). Below :data:`MIN_VIEWS` effective views (a focal length that two tilted
views of ten carry) a parameter cannot be checked; when another parameter of the same fit is
takes the median factor ``F_g`` of the fit's checked parameters, since the errors the views
share act on all of them, or its own jackknife factor where that is larger and was computed:
a parameter that few views carry moves most when one of them is left out, which the fit's
median does not see.

A factor from ``d`` = 5-10 effective views is itself uncertain (its square spreads like
``chi^2_d / d``, a relative sd of 45-63 %), and a sigma scaled by it gives z with the heavy
tails of Student's t with ``d`` degrees of freedom (3 % beyond 3 at ``d = 5``, against 0.27 %).
So a factor is moderated towards the fit's, as variances are in the moderated t-statistic
(Smyth 2004): ``F^2 <- (d F^2 + d_g F_g^2) / (d + d_g)``, ``d_g`` the fit's median effective
views. A parameter significant on its own keeps at least its own factor.

The fit's median ``F_g`` is uncertain in the same way, and the errors that views share (a
lens misfit, a waving board) act on every fit of a solution (a zoom-wide adjustment's steps, or
the steps of a per-step backend pooled by :func:`pooled_over_steps`). So ``F_g`` is first
moderated towards the factor the fits share, ``F_g^2 <- (d_g F_g^2 + d_0 F_0^2) / (d_g + d_0)``,
with ``F_0`` and the prior's degrees of freedom ``d_0`` estimated from the fits' ``F_g`` as
Smyth estimates a prior for sample variances (:func:`shared_factor`): ``d_0`` is large where the
``F_g`` spread no more than ``chi^2_{d_g} / d_g`` does, small where the fits truly differ.
Borrowing never lowers a fit's factor: with a handful of fits ``d_0`` is itself uncertain, and
a fit whose views disagree more than the others' must keep its own.

One parameter's test has little power with few views (``d = 6`` needs a factor of 1.9). The
solution as a whole is also tested (:meth:`ViewScatter.fit_test`): for each fit ``g`` (a
zoom-wide step, or the one fit) the squared factors are averaged over its checked parameters
and counted as one draw of ``chi^2_{d_g} / d_g``, ``d_g`` the median of their effective views
(they share the views, so not as independent ones); fits are independent, so
``sum_g d_g mean_g(F^2) ~ chi^2_D``, ``D = sum_g d_g``. Where that is significant, every checked
parameter is flagged (``scaled``), significant alone or not. With :data:`SCALE_UNTESTED` off, only
a flagged parameter takes its factor (moderated as above, at least 1) and the rest keep the
noise model's sigma.

*Errors a board point carries.* A board printed with its corners a few hundredths of a
millimetre off, or a paper sheet whose shape the model does not follow, displaces a corner the
same way in every view that sees it. Such errors are correlated across views, not within one:
a view's share of the move is then much the same in every view, the views agree, and the
clustered sum by view does not see them. Clustered by board point instead, ``V_point = sum_p
b_pq^2`` with ``b_pq = sum_{i in p} a_iq`` does; the variance clustered both ways (Cameron,
Gelbach & Miller 2011) is ``V_view + V_point - V_corner``, ``V_corner = sum_i a_iq^2`` being
the part the two share (one corner is one view's and one point's). So each sigma takes the
excess ``E = max(V_point - V_corner, 0) / var_model`` on top of its view factor:
``sqrt(F^2 + E)`` (:func:`board_point_scatter`). The points are tested like the views:
``V_point / V_corner`` against the 99.9 % point of ``chi^2_d / d``, ``d`` the effective
number of points. A board whose points the fit estimates (the bundle, the zoom-wide
adjustment's board modes) keeps only what its model of the board does not follow. Where each
point has coordinates of its own under a prior (the bundle), its corners' residuals keep the
part of its error the point did not absorb, and the points are checked with each corner's
influence with its own point's coordinates held (``point_influence``): the full influence
would take that part through the point once more and count about half of what the prior
leaves in the camera.

"Views" are independent draws only if they are different views. Frames of a video where the
board hardly moved see it through the same part of the lens and share their systematic errors;
:func:`view_groups` joins them, and the check clusters (and deletes) by group.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse
import scipy.sparse.csgraph
import scipy.special
import scipy.stats

from .result import CalibrationResult

__all__ = ["ViewScatter", "view_scatter", "board_point_scatter", "noise_share", "view_groups",
           "pooled_over_fits", "pooled_over_steps", "MIN_VIEWS", "SIGNIFICANCE",
           "SAME_VIEW_FRACTION", "deletion_steps", "DELETION_MIN_PIVOT"]

#: Fewest effective views (``d``) for which the check is made.
MIN_VIEWS = 4.0
#: One-sided level of the chi-square test of ``F``.
SIGNIFICANCE = 0.001
#: Every checked sigma takes its moderated factor (at least 1) whether or not a test found the
#: views disagreeing: the rule of taking the larger of the model's and the clustered sigma
#: (Angrist & Pischke 2009, section 8.1). The default: a misfit too small for the test leaves
#: the noise model's sigmas too small (``benchmarks/bench_scatter_power.py --tested-only``);
#: the price is a few percent of conservatism where the noise model holds (docs,
#: calibration.md, "What the check cannot see"). False: only where a test fired.
SCALE_UNTESTED = True
#: Check the errors a board point carries across views where the backend gives the corners'
#: board points (module docstring, "Errors a board point carries"); False: the views only.
CHECK_BOARD_POINTS = True
#: The :class:`ViewScatter` fields of the board-point check.
POINT_FIELDS = ("point_factor", "point_count", "point_excess")
#: Two views whose common corners lie closer than this fraction of the image diagonal (RMS) are
#: one view for the check (:func:`view_groups`).
SAME_VIEW_FRACTION = 0.01


def view_groups(views: list[tuple[np.ndarray, np.ndarray]], image_size: tuple[int, int],
                fraction: float = SAME_VIEW_FRACTION) -> np.ndarray:
    """(m,) int: a group per view, views of nearly one pose sharing one (labels ``0..G-1`` in
    order of their first view).

    Two views are linked when at least 4 corners are common to both and those lie within
    ``fraction`` of the image diagonal of each other (RMS, px); groups are the linked views'
    connected sets. Frames taken from a video where the board hardly moved see the same board
    through the same part of the lens: their systematic errors are one draw, not several, and
    the check (and the two halves of ``--cross-validate``) must count them once.

    ``views``: ``(ids (k,), points (k, 2))`` per view, px; ``image_size`` ``(width, height)``.
    """
    m = len(views)
    n = 1 + max((int(ids.max()) for ids, _ in views if len(ids)), default=-1)
    grid = np.full((m, max(n, 1), 2), np.nan)
    for v, (ids, pts) in enumerate(views):
        grid[v, ids] = pts
    limit2 = (fraction * float(np.hypot(*image_size))) ** 2
    linked = np.zeros((m, m), bool)
    for v in range(m):
        d2 = np.sum((grid - grid[v]) ** 2, axis=2)                      # (m, n), NaN unseen
        common = np.sum(np.isfinite(d2), axis=1)
        with np.errstate(invalid="ignore"):
            linked[v] = (common >= 4) & (np.nanmean(np.where(common[:, None] > 0, d2, 0.0),
                                                    axis=1) < limit2)
    _, labels = scipy.sparse.csgraph.connected_components(scipy.sparse.csr_matrix(linked),
                                                          directed=False)
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(np.argsort(first))          # renumber groups by their first view
    return order[labels]


@dataclass
class ViewScatter:
    """The view-scatter check of one solution's sigmas, per parameter (``names``).

    Attributes
    ----------
    factor : (k,) ndarray
        The view-clustered 1-sigma over the noise model's (the jackknife's where it was
        computed); NaN for a fixed parameter or below :data:`MIN_VIEWS` effective views.
    test_factor : (k,) ndarray
        The same from the clustered sum, which the significance test reads.
    views : (k,) ndarray
        Effective number of views ``d``.
    threshold : (k,) ndarray
        The factor above which the scatter is significant, ``sqrt(chi2_{0.999, d} / d)``.
    names : the parameters, k of them; ``'group:name'`` for several fits in one (a zoom-wide
        adjustment's steps).
    free : (k,) bool ndarray
        Estimated (not fixed); a free parameter with a NaN factor had too few effective views.
    whole : (factor, d, threshold), optional
        The :meth:`fit_test` of the solution this check is a part of (:meth:`by_group`).
    unchecked_factor : (k,) ndarray, optional
        The jackknife's factor of a free parameter below :data:`MIN_VIEWS` effective views
        (NaN where not computed or checked): the least factor it takes when scaled.
    shared : (factor, d0), optional
        The :meth:`shared_factor` of the solution this check is a part of (:meth:`by_group`).
    null_share : (k,) ndarray, optional
        The clustered sum's expectation under the noise model over the model variance
        (:func:`noise_share`, or ``(d - 1) / d``; NaN where not checked): ``test_factor^2`` is
        the clustered sum over this times the model variance.
    point_factor : (k,) ndarray, optional
        The sum clustered by board point over the one by corner, ``sqrt(V_point / V_corner)``
        (module docstring, "Errors a board point carries"); NaN where not checked.
    point_count : (k,) ndarray, optional
        Effective number of board points behind it.
    point_excess : (k,) ndarray, optional
        ``max(V_point - V_corner, 0)`` over the model variance: the variance that errors shared
        by a board point across views add (0 where not checked).
    """

    factor: np.ndarray
    test_factor: np.ndarray
    views: np.ndarray
    threshold: np.ndarray
    names: tuple[str, ...]
    free: np.ndarray
    whole: tuple[float, float, float] | None = None
    unchecked_factor: np.ndarray | None = None
    shared: tuple[float, float] | None = None
    null_share: np.ndarray | None = None
    point_factor: np.ndarray | None = None
    point_count: np.ndarray | None = None
    point_excess: np.ndarray | None = None

    @property
    def significant(self) -> np.ndarray:
        """(k,) bool: the views disagree beyond what the corner noise explains."""
        with np.errstate(invalid="ignore"):
            return np.nan_to_num(self.test_factor) > self.threshold

    def fit_test(self) -> tuple[float, float, float]:
        """``(factor, d, threshold)`` of the whole solution (module docstring): the factor
        pooled over every checked parameter, ``sqrt(sum_g d_g mean_g(F^2) / sum_g d_g)`` with
        ``d_g`` the median effective views of fit ``g``, and the factor above which it is
        significant, ``sqrt(chi2_{0.999, D} / D)``, ``D = sum_g d_g``. NaN when nothing was
        checked. A part of a solution (:meth:`by_group`) answers for the whole."""
        if self.whole is not None:
            return self.whole
        weighted, dof = 0.0, 0.0
        for members in self._groups().values():
            q = np.array(members)
            q = q[np.isfinite(self.test_factor[q])]
            if len(q):
                d = float(np.median(self.views[q]))
                weighted += d * float(np.mean(self.test_factor[q] ** 2))
                dof += d
        if dof == 0.0:
            return float("nan"), 0.0, float("nan")
        return (float(np.sqrt(weighted / dof)), dof,
                float(np.sqrt(scipy.stats.chi2.ppf(1.0 - SIGNIFICANCE, dof) / dof)))

    @property
    def fit_significant(self) -> bool:
        """The views disagree over the solution as a whole (:meth:`fit_test`)."""
        factor, _, threshold = self.fit_test()
        return bool(factor > threshold)

    def shared_factor(self) -> tuple[float, float]:
        """``(F_0, d_0)``: the factor the fits of the solution share and the degrees of
        freedom of that prior, estimated from the fits' median factors (module docstring;
        :func:`shared_factor`). ``d_0 = 0`` with fewer than two fits checked, ``inf`` when
        the fits' factors differ no more than their noise. A part of a solution
        (:meth:`by_group`) answers for the whole."""
        if self.shared is not None:
            return self.shared
        typical = []
        for members in self._groups().values():
            q = np.array(members)
            q = q[np.isfinite(self.factor[q])]
            if len(q):
                typical.append((np.median(self.factor[q]), np.median(self.views[q])))
        if len(typical) < 2:
            return float("nan"), 0.0
        return shared_factor(*np.array(typical).T)

    def _tested(self) -> np.ndarray:
        """(k,) bool: the parameters whose sigma takes their own factor because a test found
        the views disagreeing."""
        return self.significant | (self.fit_significant & np.isfinite(self.factor))

    def _own(self) -> np.ndarray:
        """(k,) bool: the parameters whose sigma takes their own factor (every checked one
        under :data:`SCALE_UNTESTED`)."""
        return self._tested() | (SCALE_UNTESTED & np.isfinite(self.factor))

    @property
    def point_significant(self) -> np.ndarray:
        """(k,) bool: corners of one board point disagree across views beyond the corner
        noise (:attr:`point_factor` above ``sqrt(chi2_{0.999, d} / d)``, ``d`` the effective
        number of points)."""
        factor, count = self._point("point_factor"), self._point("point_count")
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(factor) & (count >= MIN_VIEWS)
            dof = np.where(ok, count, 1.0)
            return ok & (factor > np.sqrt(scipy.stats.chi2.ppf(1.0 - SIGNIFICANCE, dof) / dof))

    def _point(self, key: str) -> np.ndarray:
        value = getattr(self, key)
        return np.full(len(self.names), np.nan) if value is None else value

    def _unchecked(self) -> np.ndarray:
        if self.unchecked_factor is None:
            return np.full(len(self.names), np.nan)
        return self.unchecked_factor

    def _null_share(self) -> np.ndarray:
        if self.null_share is None:
            return np.full(len(self.names), np.nan)
        return self.null_share

    def _groups(self) -> dict[str, list[int]]:
        groups: dict[str, list[int]] = {}
        for q, name in enumerate(self.names):
            groups.setdefault(name.rsplit(":", 1)[0] if ":" in name else "", []).append(q)
        return groups

    def applied(self) -> np.ndarray:
        """(k,) the factor each sigma is multiplied by (at least 1).

        Where a parameter is significant on its own, or the solution as a whole is
        (:meth:`fit_significant`), each checked parameter of the fit takes its factor
        moderated towards the fit's (module docstring): the fit's median factor, first
        moderated towards the one the fits share (:meth:`shared_factor`),
        ``F_g^2 <- (d_g F_g^2 + d_0 F_0^2) / (d_g + d_0)``, ``d_g`` the fit's median effective
        views; then ``sqrt((d F^2 + d_g F_g^2) / (d + d_g))``. One significant on its own
        keeps at least its own ``F``. A free parameter with too few effective views to be
        checked takes ``F_g``, or its :attr:`unchecked_factor` where larger. Else 1.

        Errors a board point carries across views add their variance (module docstring):
        the factor becomes ``sqrt(F^2 + E)``, ``E`` the :attr:`point_excess` (under
        :data:`SCALE_UNTESTED`, or where :attr:`point_significant`)."""
        out = self._view_applied()
        excess = np.nan_to_num(self._point("point_excess"))
        use = (self.free & SCALE_UNTESTED) | self.point_significant
        return np.where(use, np.sqrt(out**2 + excess), out)

    def _view_applied(self) -> np.ndarray:
        """(k,) the view part of :meth:`applied`."""
        own = self._own()
        out = np.ones(len(self.names))
        shared, shared_views = self.shared_factor()
        for members in self._groups().values():
            q = np.array(members)
            if not own[q].any():
                continue
            checked = q[np.isfinite(self.factor[q])]
            factor, views = self.factor[checked], self.views[checked]
            typical, typical_views = (float(np.median(a)) for a in (factor, views))
            typical = max(typical, _moderated(typical, typical_views, shared, shared_views))
            moderated = _moderated(factor, views, typical, typical_views)
            chosen = np.where(self.significant[checked], np.maximum(factor, moderated),
                              moderated)
            out[checked] = np.where(own[checked], np.maximum(chosen, 1.0), 1.0)
            unchecked = q[self.free[q] & ~np.isfinite(self.factor[q])]
            out[unchecked] = np.fmax(max(typical, 1.0), self._unchecked()[unchecked])
        return out

    def scaled(self, sd: dict[str, float]) -> dict[str, float]:
        """``sd`` with each sigma multiplied by its :meth:`applied` factor."""
        out = dict(sd)
        for name, f in zip(self.names, self.applied(), strict=True):
            if name in out:
                out[name] = float(out[name] * f)
        return out

    def by_group(self) -> dict[str, ViewScatter]:
        """The check split by fit (``'step:cx'`` -> fit ``'step'``, parameter ``'cx'``)."""
        whole, shared = self.fit_test(), self.shared_factor()
        points = {f: getattr(self, f) for f in POINT_FIELDS if getattr(self, f) is not None}
        return {g: ViewScatter(self.factor[q], self.test_factor[q], self.views[q],
                               self.threshold[q],
                               tuple(self.names[i].rsplit(":", 1)[-1] for i in q), self.free[q],
                               whole, self._unchecked()[q], shared, self._null_share()[q],
                               **{f: a[q] for f, a in points.items()})
                for g, q in ((g, np.array(q)) for g, q in self._groups().items())}

    @classmethod
    def from_dict(cls, saved: dict) -> ViewScatter:
        """The check back from :meth:`to_dict` (its free parameters; ``whole`` and ``shared``
        not kept)."""
        names = tuple(saved["free"])
        arrays = {key: np.array([saved[key].get(nm, np.nan) for nm in names], dtype=float)
                  for key in ("factor", "test_factor", "views", "threshold")}
        unchecked, null_share = (np.array([saved.get(key, {}).get(nm, np.nan) for nm in names],
                                          dtype=float)
                                 for key in ("unchecked_factor", "null_share"))
        board = saved.get("board_point")
        points = {} if board is None else {
            field: np.array([board[key].get(nm, np.nan) for nm in names], dtype=float)
            for field, key in zip(POINT_FIELDS, ("factor", "points", "excess"), strict=True)}
        return cls(names=names, free=np.ones(len(names), bool), unchecked_factor=unchecked,
                   null_share=null_share, **arrays, **points)

    def to_dict(self, applied: np.ndarray | None = None) -> dict:
        """``info['view_scatter']`` (docs/conventions.md): per checked parameter ``factor``,
        ``test_factor``, ``views``, ``threshold`` and ``null_share``; the names whose sigma was
        ``scaled`` by its own factor, and those scaled by the fit's median factor (``pooled``,
        too few views to check); the
        ``free`` parameters, and the effective views of those not checked (``unchecked``).
        ``applied``: the factors used, if not :meth:`applied`'s."""
        checked = [q for q in range(len(self.names)) if np.isfinite(self.factor[q])]
        applied = self.applied() if applied is None else applied
        # what a test found (under SCALE_UNTESTED the rest is only widened, not flagged)
        tested = self._tested() if SCALE_UNTESTED else np.ones(len(self.names), bool)
        fit_factor, fit_views, fit_threshold = self.fit_test()
        shared, shared_views = self.shared_factor()
        free = [self.names[q] for q in range(len(self.names)) if self.free[q]]
        return {key: {self.names[q]: float(arr[q]) for q in checked}
                for key, arr in (("factor", self.factor), ("test_factor", self.test_factor),
                                 ("views", self.views), ("threshold", self.threshold),
                                 ("null_share", self._null_share()))} | {
            "fit": {"factor": fit_factor, "views": fit_views, "threshold": fit_threshold,
                    "shared_factor": shared if np.isfinite(shared) else None,
                    "shared_views": shared_views if np.isfinite(shared_views) else None},
            "free": free,
            "unchecked": {self.names[q]: float(self.views[q]) for q in range(len(self.names))
                          if self.free[q] and q not in checked},
            "unchecked_factor": {self.names[q]: float(self._unchecked()[q])
                                 for q in range(len(self.names))
                                 if np.isfinite(self._unchecked()[q])},
            "scaled": [self.names[q] for q in checked if applied[q] > 1.0 and tested[q]],
            "pooled": {self.names[q]: float(applied[q]) for q in range(len(self.names))
                       if q not in checked and applied[q] != 1.0 and tested.any()}} | ({
            "widened": {self.names[q]: float(applied[q]) for q in range(len(self.names))
                        if applied[q] > 1.0 and not (tested[q] if q in checked
                                                     else tested.any())}}
            if SCALE_UNTESTED else {}) | self._board_point_dict()

    def _board_point_dict(self) -> dict:
        """``{'board_point': {factor, points, excess, flagged}}`` where the points were
        checked (module docstring, "Errors a board point carries"), else empty."""
        if self.point_factor is None:
            return {}
        rows = [q for q in range(len(self.names)) if np.isfinite(self.point_factor[q])]
        keys = (("factor", self.point_factor), ("points", self._point("point_count")),
                ("excess", np.nan_to_num(self._point("point_excess"))))
        flagged = self.point_significant
        return {"board_point": {key: {self.names[q]: float(arr[q]) for q in rows}
                                for key, arr in keys}
                | {"flagged": [self.names[q] for q in rows if flagged[q]]}}


def view_scatter(influence: np.ndarray, view_idx: np.ndarray, n_views: int,
                 names: tuple[str, ...], model_sd: np.ndarray,
                 deletions: Callable[[], np.ndarray | None] | None = None,
                 null_share: np.ndarray | None = None,
                 point_idx: np.ndarray | None = None,
                 point_influence: np.ndarray | None = None) -> ViewScatter:
    """The view-scatter check (module docstring) from each corner's influence.

    Parameters
    ----------
    influence : (N, k) ndarray
        ``a_i``: corner ``i``'s share of the solution's move, ``(S^-1 Jt_i^T r_i)``, per
        parameter (``names``; a fixed parameter's column is zero), in the parameters' units.
        :meth:`zoomcalib.calibrate.bundleproblem._Problem.camera_influence` computes it.
    view_idx : (N,) int ndarray
        The view of each corner, ``0 <= view_idx < n_views``.
    names : the parameters' names, k of them.
    model_sd : (k,) ndarray
        The noise model's 1-sigma of each parameter (0 or NaN: not checked).
    deletions : callable, optional
        Returns each view's deletion step ``(S - A_v)^-1 g_v`` (n_views, k), or None: the
        variance is then the jackknife's (module docstring) for the size of a scaled sigma;
        where a view carries a parameter alone (a NaN move) the clustered sum's is used. Called
        only when a parameter is found disagreeing (it costs a solve per view).
    null_share : (k,) ndarray, optional
        The clustered sum's expectation under the noise model over the model variance
        (:func:`noise_share`), at most 1; ``(d - 1) / d`` (``d`` the effective views) where
        not given, not finite or not positive (the record's ``null_share`` says which).
    point_idx : (N,) int ndarray, optional
        The board point of each corner (one index per physical point, shared by every view
        and step that sees it): errors a point carries across views are then checked too
        (module docstring, "Errors a board point carries"; :func:`board_point_scatter`).
    point_influence : (N, k) ndarray, optional
        The influences the board points are checked with, where they differ from
        ``influence``: a fit that refines the board points under a shape prior passes each
        corner's share with its own point's coordinates held (``a_i`` less
        ``S^-1[q, x_p] J_x,i^T r_i``). Its residuals keep only the part of a point's error the
        point did not absorb, and this is the camera's response to that part; with the point's
        term in, the point would be counted as absorbing it twice.
    """
    a = np.asarray(influence, dtype=float)
    model_sd = np.asarray(model_sd, dtype=float)
    if (a.ndim != 2 or a.shape[1] != len(names) or len(view_idx) != len(a)
            or model_sd.shape != (len(names),)):
        raise ValueError(f"influence of shape {a.shape} for {len(view_idx)} corners, "
                         f"{len(names)} parameters and {model_sd.shape} sigmas")
    corner_sq = np.zeros((n_views, a.shape[1]))
    np.add.at(corner_sq, view_idx, a * a)
    total = corner_sq.sum(axis=0)
    used = (total > 0) & (model_sd > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        views = np.where(used, total**2 / np.sum(corner_sq**2, axis=0), 0.0)
        per_view = np.zeros((n_views, a.shape[1]))
        np.add.at(per_view, view_idx, a)
        share = (views - 1.0) / views
        if null_share is not None:   # an expectation of squares over the variance: in (0, 1]
            given = np.asarray(null_share, dtype=float)
            share = np.where(np.isfinite(given) & (given > 0), np.minimum(given, 1.0), share)
        clustered = np.sum(per_view**2, axis=0) / share
        test_factor = np.sqrt(np.clip(clustered, 0.0, None)) / model_sd
    ok = used & (views >= MIN_VIEWS) & np.isfinite(test_factor)
    dof = np.where(ok, views, 1.0)
    threshold = np.where(ok, np.sqrt(scipy.stats.chi2.ppf(1.0 - SIGNIFICANCE, dof) / dof),
                         np.nan)
    check = ViewScatter(factor=np.where(ok, test_factor, np.nan),
                        test_factor=np.where(ok, test_factor, np.nan), views=views,
                        threshold=threshold, names=tuple(names), free=used)
    moves = (deletions() if deletions is not None
             and (check.significant.any() or check.fit_significant) else None)
    jackknife = _jackknife_factor(moves, view_idx, n_views, model_sd)
    points = ({} if point_idx is None or not CHECK_BOARD_POINTS else
              dict(zip(POINT_FIELDS, board_point_scatter(
                  a if point_influence is None else np.asarray(point_influence, dtype=float),
                  point_idx, model_sd), strict=True)))
    return ViewScatter(factor=np.where(ok, np.where(np.isfinite(jackknife), jackknife,
                                                    test_factor), np.nan),
                       test_factor=np.where(ok, test_factor, np.nan), views=views,
                       threshold=threshold, names=tuple(names), free=used,
                       unchecked_factor=np.where(used & ~ok, jackknife, np.nan),
                       null_share=np.where(ok, share, np.nan), **points)


def board_point_scatter(influence: np.ndarray, point_idx: np.ndarray, model_sd: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The check of errors a board point carries across views (module docstring).

    With ``a_i`` the corners' influences (N, k) and ``b_pq = sum_{i in p} a_iq`` their sums
    by board point: ``V_point = sum_p b_pq^2``, ``V_corner = sum_i a_iq^2``.

    Returns
    -------
    factor : (k,) ndarray
        ``sqrt(V_point / V_corner)``; under independent corner errors spread about 1 like
        ``chi^2_d / d`` (NaN where ``d`` < :data:`MIN_VIEWS` or nothing moves the parameter).
    count : (k,) ndarray
        ``d``, the effective number of points: ``(sum_p c_pq)^2 / sum_p c_pq^2``,
        ``c_pq = sum_{i in p} a_iq^2``.
    excess : (k,) ndarray
        ``max(V_point - V_corner, 0) / model_sd^2``: the cross-view covariance of a point's
        errors in the parameter, over the model variance (0 where not checked).
    """
    a = np.asarray(influence, dtype=float)
    point_idx = np.asarray(point_idx)
    if point_idx.shape != (len(a),):
        raise ValueError(f"point_idx of shape {point_idx.shape} for {len(a)} corners")
    n_points = int(point_idx.max()) + 1 if len(point_idx) else 0
    per_point, corner_sq = np.zeros((n_points, a.shape[1])), np.zeros((n_points, a.shape[1]))
    np.add.at(per_point, point_idx, a)
    np.add.at(corner_sq, point_idx, a * a)
    v_point, v_corner = np.sum(per_point**2, axis=0), np.sum(corner_sq, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        count = np.where(v_corner > 0, v_corner**2 / np.sum(corner_sq**2, axis=0), 0.0)
        ok = (count >= MIN_VIEWS) & (model_sd > 0)
        factor = np.where(ok, np.sqrt(v_point / v_corner), np.nan)
        excess = np.where(ok, np.clip(v_point - v_corner, 0.0, None) / model_sd**2, 0.0)
    return factor, count, excess


def noise_share(columns: np.ndarray, blocks: np.ndarray, inverse: np.ndarray,
                model_variance: np.ndarray | None = None,
                prior: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(p,) the clustered sum's expectation under the noise model over the model variance,
    ``E[sum_g b_g b_g^T]_qq / var_model(q)`` (module docstring), from the Schur complement's
    inverse ``inverse`` ``S^-1`` (k, k), its ``columns`` ``C = S^-1 E`` (k, p) of the checked
    parameters ``E``, and each group's ``blocks`` ``B_g = A_g C`` (G, k, p).

    The residuals are the errors with the fit's pull removed: a group's gradient is
    ``g_g = z_g - A_g dy`` with ``z_g = sum Jt_i^T e_i`` (covariance ``A_g``, unit noise) and
    ``dy = S^-1 (sum_h z_h + z_prior)``. So ``E[g_g g_g^T] = A_g - 2 A_g S^-1 A_g +
    A_g S^-1 Z S^-1 A_g``, ``Z`` the covariance of the total gradient, and with
    ``M = sum_g diag(C^T B_g)`` and ``L = sum_g diag(B_g^T S^-1 B_g)``:

    - a prior that is part of the noise model (``Z = S``; zoom-wide's smoothness prior, whose
      sigma is the posterior ``diag(E^T S^-1 E)``, passed as ``model_variance``):
      ``(M - L) / model_variance``;
    - a prior held fixed (``Z = S - P``; the bundle's shape prior, whose sigma is the
      repeatability ``M``; ``prior(X)`` gives ``diag(X^T P X)`` for ``X`` (k, p)):
      ``(M - L - sum_g prior(S^-1 B_g)) / M``; without a prior the same with ``P = 0``.

    ``L / M`` is the groups' leverage on the parameter, which ``(d - 1) / d`` approximates as
    if every group pulled alike; NaN where ``M`` is 0 (a fixed parameter).
    """
    blocks = np.asarray(blocks, dtype=float)
    data = np.einsum("kp,gkp->p", columns, blocks)
    pulled = inverse @ blocks                                            # (G, k, p)
    leverage = np.einsum("gkp,gkp->p", blocks, pulled)
    with np.errstate(invalid="ignore", divide="ignore"):
        if model_variance is not None:
            return (data - leverage) / np.asarray(model_variance, dtype=float)
        if prior is not None:
            leverage = leverage + sum(prior(x) for x in pulled)
        return np.where(data > 0, (data - leverage) / np.where(data > 0, data, 1.0), np.nan)


def shared_factor(factor: np.ndarray, views: np.ndarray) -> tuple[float, float]:
    """``(F_0, d_0)`` from fits' factors ``factor`` (G,) on ``views`` (G,) effective views,
    as Smyth (2004, section 6.2) estimates a prior for sample variances: with
    ``e_g = log F_g^2 - digamma(d_g / 2) + log(d_g / 2)``, the variance of ``e`` beyond what
    each ``chi^2_{d_g} / d_g`` gives, ``trigamma(d_0 / 2) = G / (G - 1) mean (e - mean e)^2 -
    mean trigamma(d_g / 2)``, and ``log F_0^2 = mean e + digamma(d_0 / 2) - log(d_0 / 2)``.
    Where the factors spread no more than their noise, ``d_0 = inf`` and ``F_0^2 =
    exp(mean e)``."""
    half = np.asarray(views, dtype=float) / 2.0
    e = (np.log(np.maximum(np.asarray(factor, dtype=float), 1e-12) ** 2)
         - scipy.special.digamma(half) + np.log(half))
    extra = (len(e) / (len(e) - 1) * float(np.mean((e - e.mean()) ** 2))
             - float(np.mean(scipy.special.polygamma(1, half))))
    if extra <= 0.0:
        return float(np.sqrt(np.exp(e.mean()))), float("inf")
    half0 = scipy.optimize.brentq(lambda x: scipy.special.polygamma(1, np.exp(x)) - extra,
                                  -30.0, 30.0)
    d0 = 2.0 * float(np.exp(half0))
    return (float(np.sqrt(np.exp(e.mean() + scipy.special.digamma(d0 / 2) - np.log(d0 / 2)))),
            d0)


def _moderated(factor, views, prior: float, prior_views: float):
    """``sqrt((d F^2 + d_0 F_0^2) / (d + d_0))``: ``prior`` where ``prior_views`` is
    infinite, ``factor`` where it is 0."""
    if prior_views == 0.0:
        return factor
    if np.isinf(prior_views):
        return np.full_like(np.asarray(factor, dtype=float), prior)[()]
    return np.sqrt((views * np.square(factor) + prior_views * prior**2)
                   / (views + prior_views))


def _jackknife_factor(moves: np.ndarray | None, view_idx: np.ndarray, n_views: int,
                      model_sd: np.ndarray) -> np.ndarray:
    """(k,) the delete-one-view jackknife's 1-sigma over the noise model's, from each view's
    deletion step ``moves`` (n_views, k); NaN where a move is NaN or none was computed."""
    if moves is None:
        return np.full(len(model_sd), np.nan)
    if np.shape(moves) != (n_views, len(model_sd)):
        raise ValueError(f"deletions of shape {np.shape(moves)} for {n_views} views and "
                         f"{len(model_sd)} parameters")
    moves = np.asarray(moves, dtype=float)[np.bincount(view_idx, minlength=n_views) > 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        variance = ((len(moves) - 1) / len(moves)
                    * np.sum((moves - moves.mean(axis=0))**2, axis=0))
        return np.sqrt(variance) / model_sd


def pooled_over_fits(checks: Mapping[str, ViewScatter]) -> dict[str, ViewScatter]:
    """Separate fits' checks (one per key) as the parts of one solution: each part answers for
    the test of them all (:meth:`ViewScatter.fit_test`, ``whole``), as a zoom-wide
    adjustment's steps do."""
    parts = list(checks.values())
    joined = ViewScatter(
        *(np.concatenate([getattr(c, f) for c in parts])
          for f in ("factor", "test_factor", "views", "threshold")),
        names=tuple(f"{key}:{name}" for key, c in checks.items() for name in c.names),
        free=np.concatenate([c.free for c in parts]),
        unchecked_factor=np.concatenate([c._unchecked() for c in parts]),
        null_share=np.concatenate([c._null_share() for c in parts]),
        **{f: np.concatenate([c._point(f) for c in parts]) for f in POINT_FIELDS
           if any(getattr(c, f) is not None for c in parts)})
    return joined.by_group()


def pooled_over_steps(results: Mapping[str, CalibrationResult]) -> dict[str, CalibrationResult]:
    """Separate calibrations of a sweep's steps, with the whole-solution test of their
    view-scatter checks pooled over the steps of each backend.

    One step of 10-30 views has too few for its test to see a factor of 1.5; the errors views
    share (a lens misfit, a waving board) are the same kind at every step, and the pooled test
    (module docstring) sees them. Where it is significant, every checked parameter of every
    pooled step takes its own factor (moderated, at least 1), as a zoom-wide adjustment's do.
    A sigma is never lowered: what a step's own check applied stays. Results whose check was
    not applied (the bundle's ``scatter_check=False``) or that have none are returned
    unchanged, as are all when fewer than two steps can be pooled.
    ``info['view_scatter']['fit']`` is then the pooled test and ``['steps_pooled']`` the number
    of steps in it; ``sd`` and ``info['sd_posterior']`` are scaled.
    """
    out = dict(results)
    by_backend: dict[str, dict[str, ViewScatter]] = {}
    for step, res in results.items():
        saved = res.info.get("view_scatter")
        if saved and saved.get("applied") and "free" in saved:
            by_backend.setdefault(res.backend, {})[step] = ViewScatter.from_dict(saved)
    for checks in by_backend.values():
        if len(checks) < 2:
            continue
        for step, part in pooled_over_fits(checks).items():
            res, own = results[step], checks[step]
            applied = np.maximum(part.applied(), own.applied())
            factor = dict(zip(own.names, applied / own.applied(), strict=True))
            info = res.info | {"view_scatter": part.to_dict(applied) | {
                "applied": True, "steps_pooled": len(checks)}}
            if "sd_posterior" in info:
                info["sd_posterior"] = _times(info["sd_posterior"], factor)
            out[step] = dataclasses.replace(res, sd=_times(res.sd, factor), info=info)
    return out


def _times(sd: dict[str, float], factor: dict[str, float]) -> dict[str, float]:
    return {name: float(value * factor.get(name, 1.0)) for name, value in sd.items()}


#: Smallest eigenvalue of ``S - A_v`` (scaled to ``S``'s unit diagonal) in a direction that a
#: view's deletion leaves determined. Leaving out a view that alone carries a direction (the
#: rational model's numerator-denominator ridge at a step of few views) leaves eigenvalues at
#: the rounding level: on the real zoom sweep's halves the squared pivots lie below 1e-6, none
#: between 1e-6 and 1e-3. Solved as they are, such deletions made a step's factors jump from
#: 1.1-2.0 to 5.6-37 when one corner of another step was dropped.
DELETION_MIN_PIVOT = 1e-6
#: A parameter whose share (scaled) in such a direction exceeds this has no deletion move.
DELETION_NULL_SHARE = 0.01


def deletion_steps(S: np.ndarray, A: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``(S - A_v)^-1 g_v`` for each ``v`` (``S`` (k, k), ``A`` (m, k, k), ``g`` (m, k)), solved
    by Cholesky scaled to ``S``'s unit diagonal.

    Where ``S - A_v`` is singular up to rounding (not positive definite, or a squared pivot
    below :data:`DELETION_MIN_PIVOT`) the view carries some direction alone: the move is solved
    in the directions the other views determine (eigenvalues above the limit), and is NaN for
    the parameters with more than :data:`DELETION_NULL_SHARE` of an undetermined direction."""
    d = np.sqrt(np.clip(np.diag(S), 0.0, None))
    scale = np.divide(1.0, d, out=np.zeros_like(d), where=d > 0)
    M = (S - A) * np.outer(scale, scale)
    M[:, d == 0, d == 0] = 1.0
    out = np.full(g.shape, np.nan)
    for v in range(len(M)):
        try:
            factor = scipy.linalg.cho_factor(M[v], check_finite=False)
            if np.min(np.diag(factor[0])) ** 2 > DELETION_MIN_PIVOT:
                out[v] = scipy.linalg.cho_solve(factor, g[v] * scale, check_finite=False) * scale
                continue
        except np.linalg.LinAlgError:
            pass
        out[v] = _determined_move(M[v], g[v] * scale) * scale
    return out


def _determined_move(M: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``M^+ g`` over the eigen-directions of ``M`` (k, k) above :data:`DELETION_MIN_PIVOT`;
    NaN for the parameters that share in the others (:func:`deletion_steps`)."""
    w, U = np.linalg.eigh(M)
    kept = w > DELETION_MIN_PIVOT
    move = U[:, kept] @ ((U[:, kept].T @ g) / w[kept])
    undetermined = np.any(np.abs(U[:, ~kept]) > DELETION_NULL_SHARE, axis=1)
    return np.where(undetermined, np.nan, move)
