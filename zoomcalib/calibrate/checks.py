"""Honesty checks of a calibration: ill-conditioning flags and the two-halves cross-validation.

*Ill-conditioning.* A step is flagged, with a one-line reason each, when its focal length is
not positive (a mirrored or failed solution), when its principal point
lies outside the central region of the image (more than a quarter of the width or height from
the centre ``((W-1)/2, (H-1)/2)``), when the 1-sigma of ``cx`` or ``cy`` exceeds 1 % of the
image diagonal, when two intrinsics are correlated beyond ``|r| = 0.999`` (where the backend
reports the correlation; fx with fy is not counted, being one focal length), when OpenCV's
own 1-sigma of fx, fy, cx or cy was truncated by its pseudo-inverse or its normal matrix is
singular (``info['sd_check']``, :func:`zoomcalib.calibrate.opencv_backend._checked_camera_sd`;
a truncated distortion term alone is replaced there but not flagged: the radial terms of a
narrow field are nearly collinear, and their sum is what the views determine), when its views
disagree beyond what the corner noise explains so that the sigma of fx, fy, cx or cy was
scaled up (``info['view_scatter']``, :mod:`zoomcalib.calibrate.scatter`: a lens the model does
not fit, a board that moves, correlated errors within a view), when the corners of one board
point disagree across views beyond that noise (``info['view_scatter']['board_point']``: a
misprinted board, a paper shape the model does not follow), when one of fx, fy, cx, cy
rests on fewer than 4 effective views so that its sigma cannot be checked that way (a few
tilted views of many nearly fronto-parallel ones carry fx), when the choice between the
rational model and five distortion terms was uncertain enough that the other model's spread
widened one of those sigmas by more than 25 % (``info['model_choice']``, zoom-wide), or when
its solve did not converge.

Each flag is a :class:`Flag`: a severity (``note``: the sigmas already carry it; ``warning``:
the row may be off by more than its sigmas, or is barely determined; ``error``: not a
calibration), a few words with the number that matters, the full reason and one action
(:data:`ACTIONS`); :func:`step_flags` returns them, :func:`conditioning_flags` their full texts.

*Cross-validation* (the check mrcal calls its most important): each step's views are split into
two halves (even and odd images; views of nearly one pose count as one and stay together), each
half is calibrated on its own as the full set was, and
for ``q`` in ``fx, cx, cy`` the difference is expressed in its combined sigma,

    z_q = (q_a - q_b) / sqrt(sd_a^2 + sd_b^2),

which is ``N(0, 1)`` when the reported sigmas are honest and the halves see the same camera.
``|z| > 3`` flags the step ("halves disagree").

What matters to a user is where the two halves project a ray: every pixel is unprojected with
one half's intrinsics and projected with the other's, and the difference is divided by the
two fits' projection uncertainty there (:func:`~zoomcalib.calibrate.quality.projection_z`, the
map of the report's cross-validation figure in its own sigma). Its root mean square over the
region the step's views covered, ``z_proj``, is about 1 for honest sigmas (its square's mean
is 1 at every pixel); ``z_proj > 3`` (a chi-square of 2 degrees of freedom above 18 even where
the pixels move as one, p = 1.2e-4) flags the step too ("projection").

A half of 5-15 views has too few for its view-scatter test (:mod:`zoomcalib.calibrate.scatter`)
to see a factor below 2, while the errors views share (a lens misfit, a waving board) are the
whole session's, which the full set's test sees with all its views. So with per-step backends
the halves' tests are pooled over both halves of every step (:func:`pooled_halves`), as the full
set's test is made over all its views; left to their own tests, halves would disagree where
the full set's sigmas are honest. A zoom-wide half is one solution whose test already spans its
steps.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from .basins import MIN_GAIN
from .result import CalibrationResult, Observations
from .scatter import MIN_VIEWS, pooled_over_steps, view_groups

__all__ = ["conditioning_flags", "step_flags", "Flag", "by_severity", "SEVERITIES", "ACTIONS",
           "CrossValidation", "cross_validate", "split_halves",
           "random_halves", "pooled_halves",
           "CROSS_VALIDATED", "Z_LIMIT"]

#: A zoom-wide step is flagged when the other lens model's spread widens a sigma of fx, fy, cx
#: or cy by more than this factor (:func:`~zoomcalib.calibrate.zoomwide.calibrate_zoom_wide`).
MODEL_CHOICE_FLAG = 1.25
#: Parameters compared between the halves.
CROSS_VALIDATED = ("fx", "cx", "cy")
#: |z| beyond which the halves disagree.
Z_LIMIT = 3.0
_CORRELATION_LIMIT = 0.999


#: Flag severities, least severe first: ``note`` (the sigmas already carry it), ``warning``
#: (the row may be off by more than its sigmas, or the data barely determine it) and ``error``
#: (the row is not a calibration).
SEVERITIES = ("note", "warning", "error")

#: The one action each kind of flag asks for.
ACTIONS = {
    "mirrored": "check the pattern spec (inner corners) and that every image is of this camera",
    "centre": "add views tilted 30-45 degrees about the horizontal and the vertical axis",
    "sd_pp": "add the views the capture advice names (tilted 30-45 degrees, the board in "
             "every part of the image)",
    "correlated": "add views tilted 30-45 degrees at two or more distances",
    "singular": "add views tilted 30-45 degrees; the ones given do not determine the camera",
    "near_singular": "add views tilted 30-45 degrees about both axes",
    "views": "keep the camera and the board still while each frame is taken (no live-stream "
             "grabs during a move), or use the sigmas as widened",
    "board": "use a rigid flat board (glass or aluminium), or keep the board's shape fitted "
             "(--board-shape print, the default, or points)",
    "model_choice": "add views with the board in the image corners, where the two lens "
                    "models differ",
    "few_views": "add 4 or more views tilted 20-45 degrees, in turn about each axis",
    "not_converged": "rerun; if it stays, drop the step's worst views (per-view RMS in the "
                     "report)",
    "halves": "compare the halves' maps in the report: a board or camera that changed between "
              "frames is the usual cause; recapture the step in one go",
    "halves_failed": "add views: each half needs enough to be calibrated on its own",
    "basin": "add views with the board in the image corners and tilted 20-45 degrees, where "
             "the two basins' decentring differs most",
}


@dataclass(frozen=True)
class Flag:
    """One reason a step's row is not to be trusted as it stands.

    ``kind``: a key of :data:`ACTIONS`; ``severity``: one of :data:`SEVERITIES`; ``text``: a
    few words with the number that matters; ``detail``: the full reason (the string
    :func:`conditioning_flags` returns); ``action``: what to do, from :data:`ACTIONS`.
    """

    kind: str
    severity: str
    text: str
    detail: str

    @property
    def action(self) -> str:
        return ACTIONS[self.kind]

    def to_dict(self) -> dict:
        return {"kind": self.kind, "severity": self.severity, "text": self.text,
                "action": self.action, "detail": self.detail}


def by_severity(flags: list[Flag]) -> list[Flag]:
    """``flags`` the most severe first, then the shortest text first."""
    return sorted(flags, key=lambda f: (-SEVERITIES.index(f.severity), len(f.text)))


def conditioning_flags(res: CalibrationResult, image_size: tuple[int, int]) -> list[str]:
    """One-line reasons why ``res`` is ill-conditioned (empty when none; module docstring):
    the ``detail`` of each of :func:`step_flags`."""
    return [f.detail for f in step_flags(res, image_size)]


def step_flags(res: CalibrationResult, image_size: tuple[int, int]) -> list[Flag]:
    """Why ``res`` is ill-conditioned, as :class:`Flag` records (module docstring), in the
    order of the checks."""
    w, h = image_size
    flags = []
    if not (res.fx > 0 and res.fy > 0):
        flags.append(Flag("mirrored", "error", "focal length not positive",
                          f"focal length ({res.fx:.1f}, {res.fy:.1f}) px not positive: a "
                          "mirrored or failed solution"))
    dx, dy = res.cx - (w - 1) / 2.0, res.cy - (h - 1) / 2.0
    if abs(dx) > w / 4.0 or abs(dy) > h / 4.0:
        flags.append(Flag("centre", "warning",
                          f"principal point ({res.cx:.0f}, {res.cy:.0f}) off-centre",
                          f"principal point ({res.cx:.0f}, {res.cy:.0f}) outside the central "
                          "region"))
    limit = 0.01 * float(np.hypot(w, h))
    for q in ("cx", "cy"):
        sd = res.sd.get(q, np.nan)
        if not np.isfinite(sd) or sd > limit:
            flags.append(Flag("sd_pp", "warning", f"sd {q} {sd:.1f} px",
                              f"sd {q} {sd:.1f} px > 1 % of the image diagonal ({limit:.1f} "
                              "px)"))
    corr, names = res.info.get("correlation"), res.info.get("correlation_names")
    if corr is not None and names:
        c = np.abs(np.asarray(corr, float)) - np.eye(len(names))
        # one focal length in two pixel pitches; the rational model's numerator and denominator
        # terms of one order (to first order k4 = -k1: only their difference is measured)
        for a, b in (("fx", "fy"), ("k1", "k4"), ("k2", "k5"), ("k3", "k6")):
            if a in names and b in names:
                i, j = names.index(a), names.index(b)
                c[i, j] = c[j, i] = 0.0
        i, j = np.unravel_index(np.argmax(c), c.shape)
        if c[i, j] > _CORRELATION_LIMIT:
            flags.append(Flag("correlated", "note", f"{names[i]}, {names[j]} correlated",
                              f"{names[i]} and {names[j]} correlated (|r| = {c[i, j]:.4f})"))
    check = res.info.get("sd_check")
    if check and check["reason"] == "singular":
        flags.append(Flag("singular", "error", "intrinsics not determined",
                          "normal matrix singular at the solution: the data do not determine "
                          "the intrinsics (sd infinite)"))
    elif check and (pinhole := {nm: r for nm, r in check["ratio"].items()
                                if nm in ("fx", "fy", "cx", "cy")}):
        name, ratio = min(pinhole.items(), key=lambda item: item[1] or 0.0)
        said = ("not a number" if ratio is None
                else f"{check['opencv_sd'][name]:.3g}, 1/{1 / ratio:.0f} of")
        flags.append(Flag("near_singular", "warning", f"sd {name} barely determined",
                          f"near-singular normal matrix: OpenCV's sd {name} {said} the full "
                          f"inverse's {check['sd'][name]:.3g} (used)"))
    scatter = res.info.get("view_scatter")
    if scatter and scatter.get("applied", True):
        factors = {nm: scatter["factor"][nm] for nm in scatter["scaled"]} | scatter.get(
            "pooled", {})
        pinhole = {nm: f for nm, f in factors.items() if nm in ("fx", "fy", "cx", "cy")}
        if pinhole:
            name = max(pinhole, key=pinhole.get)
            pooled = (f", tested over {scatter['steps_pooled']} steps"
                      if scatter.get("steps_pooled") else "")
            flags.append(Flag("views", "note", f"views disagree: sd {name} x{pinhole[name]:.1f}",
                              f"views disagree beyond the corner noise{pooled}: sd {name} x"
                              f"{pinhole[name]:.1f} from their scatter (used; lens model misfit "
                              "or a moving board)"))
    board = (scatter or {}).get("board_point", {}) if (scatter or {}).get("applied", True) else {}
    misprint = {nm: board["factor"][nm] for nm in board.get("flagged", [])
                if nm in ("fx", "fy", "cx", "cy")}
    if misprint:
        name = max(misprint, key=misprint.get)
        grown = np.sqrt(1 + board["excess"][name])
        flags.append(Flag("board", "note", f"board not as printed: sd {name} x{grown:.1f}",
                          f"corners of one board point disagree across views beyond the "
                          f"corner noise: sd {name} x{grown:.1f} from them (used; a "
                          "misprinted or bent board)"))
    flags += _model_choice_flags(res.info.get("model_choice"), res.sd)
    flags += _basin_flags(res.info.get("basin") or {})
    few = {nm: d for nm, d in (scatter or {}).get("unchecked", {}).items()
           if nm in ("fx", "fy", "cx", "cy")}
    for name in (nm for nm in ("fx", "fy", "cx", "cy") if nm in few):
        used = scatter.get("pooled", {}).get(name, scatter.get("widened", {}).get(name, 1.0))
        # the views' part of it: what the board points add (board_point.excess) taken out
        views_part = np.sqrt(max(used**2 - board.get("excess", {}).get(name, 0.0), 0.0))
        jackknife = scatter.get("unchecked_factor", {}).get(name, np.nan)
        sized = (f"; x{used:.1f} from leaving views out (used)"
                 if used > 1.0 and np.isclose(views_part, jackknife, rtol=1e-9) else "")
        rests = (f"rests on {few[name]:.1f} effective views (fewer than {MIN_VIEWS:.0f})"
                 if np.isfinite(few[name]) else "has effective views that cannot be counted")
        flags.append(Flag("few_views", "warning",
                          f"{name} rests on {few[name]:.1f} views" if np.isfinite(few[name])
                          else f"{name}'s views not counted",
                          f"{name} {rests}: its sigma cannot be checked against their "
                          "scatter" + sized))
    if not res.converged:
        why = res.info.get("stop_reason", "unknown reason")
        flags.append(Flag("not_converged", "error", "did not converge",
                          f"did not converge ({why})"))
    return flags


def _basin_flags(basin: dict) -> list[Flag]:
    """Warnings about the principal point's basin
    (:func:`~zoomcalib.calibrate.basins.best_basin`): a second basin about as good as the
    chosen one (fewer than ``MIN_GAIN`` noise variances apart), and a move to a basin that the
    views' paired test does not support."""
    flags = []
    if basin.get("views_disagree"):
        flags.append(Flag("basin", "warning", "moved to a basin few views prefer",
                          f"the principal point was moved to the basin of lower total cost, "
                          f"but the views do not agree on it (paired t "
                          f"{basin.get('view_t') or float('nan'):.1f}, "
                          f"{basin.get('view_t_needed') or float('nan'):.1f} for 3 sigma): a "
                          "few views' errors may have chosen it"))
    second = basin.get("second")
    if basin.get("ambiguous") and second:
        gap = {q: v for q, v in (basin.get("half_gap") or {}).items() if q in ("fx", "cx", "cy")}
        flags.append(Flag("basin", "note", "two basins the views do not tell apart",
                          f"a second basin puts the principal point at ({second['cx']:.0f}, "
                          f"{second['cy']:.0f}) px and the views do not agree that the chosen "
                          f"one is lower (paired t {second.get('view_t') or float('nan'):.1f}, "
                          f"{second.get('view_t_needed') or float('nan'):.1f} for 3 sigma): "
                          "the sigmas cover both (half their distance added: "
                          + ", ".join(f"{q} {v:.0f} px" for q, v in gap.items()) + ")"))
    excess = (second or {}).get("excess_noise_variances")
    if excess is not None and excess < MIN_GAIN:
        cost = (f"{excess:.1f} noise variances more cost" if excess >= 0 else
                f"{-excess:.1f} noise variances less cost")
        flags.append(Flag("basin", "warning", "a second basin for the principal point",
                          f"a second basin puts the principal point at ({second['cx']:.0f}, "
                          f"{second['cy']:.0f}) px for {cost} (within {MIN_GAIN:g}): the "
                          "views barely tell the two apart"))
    return flags


def _model_choice_flags(choice: dict | None, sd: Mapping[str, float]) -> list[Flag]:
    """A step whose sigmas the other lens model's spread widened by more than
    :data:`MODEL_CHOICE_FLAG` (``info['model_choice']``, zoom-wide), or whose other model, at
    least as likely as the chosen one, could not be fitted."""
    if not choice:
        return []
    weight, shift = choice["weight"], choice.get("shift")
    if shift is None:
        return ([Flag("model_choice", "warning", "lens model uncertain",
                      f"lens model uncertain ({choice['other']} model's weight {weight:.2f}), "
                      f"and it could not be fitted ({choice.get('why', 'unknown reason')}): "
                      "its uncertainty is not in the sigmas")] if weight >= 0.5 else [])
    grown = {}
    for name in ("fx", "fy", "cx", "cy"):
        added = weight * shift.get(name, 0.0) ** 2
        before = sd.get(name, 0.0) ** 2 - added
        if added > 0 and before > 0:
            grown[name] = float(np.sqrt(sd[name] ** 2 / before))
    name = max(grown, key=grown.get, default=None)
    if name is None or grown[name] <= MODEL_CHOICE_FLAG:
        return []
    return [Flag("model_choice", "note", f"lens model uncertain: sd {name} x{grown[name]:.1f}",
                 f"lens model uncertain ({choice['other']} model's weight {weight:.2f}): sd "
                 f"{name} x{grown[name]:.1f} from what it would change ({shift[name]:+.2f} px, "
                 "used)")]


def split_halves(obs: Observations) -> tuple[Observations, Observations]:
    """The even and the odd views of ``obs`` (in their order, i.e. by image name), counting
    views of nearly one pose as one (:func:`~zoomcalib.calibrate.scatter.view_groups`: frames
    of a video where the board hardly moved go to the same half, or the halves would share
    their errors)."""
    groups = view_groups(obs.views, obs.image_size)
    return _halves(obs, groups % 2 == 0)


def random_halves(obs: Observations, count: int, rng: np.random.Generator
                  ) -> list[tuple[Observations, Observations]]:
    """``count`` splits of ``obs`` into two halves: :func:`split_halves`' even and odd groups of
    views of nearly one pose, then ``count - 1`` splits of the groups drawn at random (half of
    them, rounded down, in the first half)."""
    groups = view_groups(obs.views, obs.image_size)
    n = int(groups.max()) + 1
    masks = [groups % 2 == 0]
    masks += [np.isin(groups, rng.permutation(n)[: n // 2]) for _ in range(count - 1)]
    return [_halves(obs, mask) for mask in masks]


def _halves(obs: Observations, first: np.ndarray) -> tuple[Observations, Observations]:
    """The views of ``obs`` where ``first`` (per view) is True, and the others."""
    return obs.subset(np.flatnonzero(first)), obs.subset(np.flatnonzero(~first))


@dataclass
class CrossValidation:
    """Per step: each half's values and sigmas and the z of their difference.

    ``halves[step]`` is ``(result_even, result_odd)``; ``z[step][q]`` the normalised difference
    for ``q`` in :data:`CROSS_VALIDATED`; ``failures`` steps whose halves could not be
    calibrated, with the reason.
    """

    backend: str
    halves: dict[str, tuple[CalibrationResult, CalibrationResult]] = field(default_factory=dict)
    z: dict[str, dict[str, float]] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    projection: dict[str, dict] = field(default_factory=dict)

    def disagreeing(self) -> dict[str, list[str]]:
        """Steps whose halves differ by more than :data:`Z_LIMIT` combined sigmas, and in what
        (``"projection"``: the projection difference's RMS z over the observed region)."""
        out = {}
        for step, z in self.z.items():
            bad = [q for q, v in z.items() if not abs(v) <= Z_LIMIT]
            if self.projection.get(step, {}).get("z_rms", 0.0) > Z_LIMIT:
                bad.append("projection")
            if bad:
                out[step] = bad
        return out

    def to_dict(self) -> dict:
        out = {"backend": self.backend, "z_limit": Z_LIMIT, "failures": dict(self.failures),
               "steps": {}}
        for s, (a, b) in self.halves.items():
            out["steps"][s] = {
                "z": self.z[s],
                "projection": self.projection.get(s, {}),
                "halves": [{q: getattr(r, q) for q in CROSS_VALIDATED}
                           | {f"sd_{q}": r.sd.get(q, float("nan")) for q in CROSS_VALIDATED}
                           | {"n_views": len(r.per_view_rms_px)} for r in (a, b)]}
        return out


def _z(a: CalibrationResult, b: CalibrationResult) -> dict[str, float]:
    out = {}
    for q in CROSS_VALIDATED:
        sd = float(np.hypot(a.sd.get(q, np.nan), b.sd.get(q, np.nan)))
        out[q] = float((getattr(a, q) - getattr(b, q)) / sd) if sd > 0 else float("nan")
    return out


def pooled_halves(first: Mapping[str, CalibrationResult], second: Mapping[str, CalibrationResult]
                  ) -> tuple[dict[str, CalibrationResult], dict[str, CalibrationResult]]:
    """Per-step fits of two halves ``{step: result}`` with their view-scatter tests pooled over
    both halves and all steps of each backend
    (:func:`~zoomcalib.calibrate.scatter.pooled_over_steps`; module docstring). A sigma is
    never lowered."""
    joined = pooled_over_steps({**{f"a {s}": r for s, r in first.items()},
                                **{f"b {s}": r for s, r in second.items()}})
    return ({s: joined[f"a {s}"] for s in first}, {s: joined[f"b {s}"] for s in second})


def cross_validate(observations: Mapping[str, Observations],
                   calibrate_steps: Callable[[dict[str, Observations]],
                                             dict[str, CalibrationResult]],
                   backend: str, pool: bool = False) -> CrossValidation:
    """Calibrate the even and the odd halves of every step with ``calibrate_steps`` (which
    takes ``{step: Observations}`` and returns ``{step: CalibrationResult}``, raising
    ``ValueError`` or ``RuntimeError`` on failure) and compare them (module docstring).
    ``pool``: per-step fits whose view-scatter tests are pooled over both halves
    (:func:`pooled_halves`)."""
    cv = CrossValidation(backend)
    even, odd = {}, {}
    for step, obs in observations.items():
        even[step], odd[step] = split_halves(obs)
    try:
        res_even, res_odd = calibrate_steps(even), calibrate_steps(odd)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        for step in observations:
            cv.failures[step] = " ".join(str(exc).split())
        return cv
    if pool:
        res_even, res_odd = pooled_halves(res_even, res_odd)
    for step in observations:
        if step in res_even and step in res_odd:
            cv.halves[step] = (res_even[step], res_odd[step])
            cv.z[step] = _z(res_even[step], res_odd[step])
            cv.projection[step] = _projection_check(res_even[step], even[step],
                                                    res_odd[step], odd[step])
        else:
            cv.failures[step] = "a half could not be calibrated"
    return cv


def _projection_check(a: CalibrationResult, obs_a: Observations, b: CalibrationResult,
                      obs_b: Observations) -> dict:
    """``z_rms``, ``z_max`` and ``difference_max_px`` of :func:`projection_z` over the region
    both halves' views covered; ``error`` instead when it cannot be formed."""
    from .quality import observed_region, projection_z

    try:
        xs, ys, z, diff = projection_z(a, obs_a, b, obs_b)
    except (np.linalg.LinAlgError, ValueError, KeyError) as exc:
        return {"error": " ".join(str(exc).split()) or type(exc).__name__}
    points = np.concatenate([p for o in (obs_a, obs_b) for _, p in o.views])
    inside = observed_region(points, xs, ys)[1] & np.isfinite(z)
    if not inside.any():
        return {"error": "no pixel of the grid inside the observed region"}
    return {"z_rms": float(np.sqrt(np.mean(z[inside] ** 2))), "z_max": float(z[inside].max()),
            "difference_max_px": float(diff[inside].max())}
