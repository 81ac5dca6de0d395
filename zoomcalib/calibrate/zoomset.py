"""The capture sessions of a zoom set and what is said of them in a calibrate run: the steps
taken in several sittings, each step's capture session (the board's shape is one per session
in the zoom-wide adjustment), the notes of the adjustment's steps, and the residual budget per
step and session (:func:`zoomcalib.calibrate.run.calibrate_folder` calls them).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from .stepfolders import capture_date, capture_sittings

if TYPE_CHECKING:
    from .run import CalibrateRun


def residual_budgets(run: CalibrateRun, sessions: dict[str, str], workers: int,
                     log: Callable[[str], None]) -> None:
    """The residual budget of every usable step's table result and of each capture session
    (:mod:`zoomcalib.calibrate.budget`); a step whose budget fails is logged, the others kept."""
    from .budget import session_budgets, step_budgets

    usable = {s: run.results[s][run.table_backend[s]] for s in run.results
              if s in run.observations and (s not in run.status or run.status[s].usable)}
    log(f"residual budget of {len(usable)} steps (each cause judged on held-out corners)")
    run.budget, failed = step_budgets({s: run.observations[s] for s in usable}, usable,
                                      workers)
    for step, why in failed.items():
        run.failures.append(f"step {step}: residual budget failed: {why}")
        log(run.failures[-1])
    run.budget_sessions = session_budgets(run.budget, sessions)
    for budget in run.budget.values():
        log(f"budget {budget.summary()}")
    for label, d in run.budget_sessions.items():
        shares = ", ".join(f"{k} {100 * v:.0f} %" for k, v in d["share"].items()
                           if v is not None)
        log(f"budget of session {label or '(one)'} ({', '.join(d['steps'])}): {shares}; "
            f"unexplained {100 * d['unexplained']:.0f} %")


#: Frames of one step more than this apart (hours) are taken as two sittings (logged).
SITTING_GAP_H = 1.0


def log_sittings(run: CalibrateRun, log: Callable[[str], None]) -> None:
    """Name the steps whose frames were taken in several sittings (capture times in the
    image names more than :data:`SITTING_GAP_H` apart, :func:`capture_sittings`): a board
    re-taped or moved between them is not one shape, and the board model's sessions are whole
    steps (on the real PTZ set one step's two sittings saw two board shapes:
    ``docs/notes/real-camera-table.md``)."""
    for step, obs in run.observations.items():
        sittings = capture_sittings(list(obs.names), SITTING_GAP_H)
        if len(sittings) < 2:
            continue
        spans = "; ".join(f"{a:%Y-%m-%d %H:%M}-{b:%H:%M}, {n} frame{'s' if n > 1 else ''}"
                          for a, b, n in sittings)
        log(f"step {step}: its frames were taken in {len(sittings)} sittings more than "
            f"{SITTING_GAP_H:g} h apart ({spans}); the board model gives them one shape: if "
            "the board was re-taped or moved between them, recapture the step in one sitting")


def capture_sessions(run: CalibrateRun, extras_of: dict[str, dict],
                     log: Callable[[str], None]) -> dict[str, str]:
    """Each step's capture session for the zoom-wide board shape: the ``session`` column of
    steps.csv where given, else the capture date most of the step's image names carry
    (:func:`~zoomcalib.calibrate.stepfolders.capture_date`); one session when neither tells. Logged
    when there is more than one."""
    given = {s: str(e["session"]) for s, e in extras_of.items() if e.get("session")}
    if given:
        if len(given) < len(extras_of):
            log("steps.csv gives a session to some steps only: one board shape for all")
            return {}
        source = "steps.csv"
        sessions = given
    else:
        source = "the capture dates in the image names"
        sessions, odd = {}, {}
        for step in extras_of:
            date, others = capture_date(list(run.observations[step].names))
            if date is None:
                return {}
            sessions[step] = date
            if others:
                odd[step] = others
        if odd:
            log("images of another capture date than most of their step's (modelled with "
                "their step's board shape): " + ", ".join(f"{s} {n}" for s, n in odd.items()))
    if len(set(sessions.values())) > 1:
        log(f"zoom-wide: one board shape per capture session, from {source}: "
            + "; ".join(f"{lab} ({', '.join(s for s in sessions if sessions[s] == lab)})"
                        for lab in dict.fromkeys(sessions.values())))
    return sessions


def zoom_wide_step_notes(info: dict) -> list[str]:
    """What the log says of one step of the zoom-wide adjustment, from its result's ``info``:
    a basin it moved to, why its distortion terms were not chosen, the term sets that could
    not be fitted on held-out views, and the held-out views a term set could not place."""
    notes = []
    if info.get("basin", {}).get("moved"):
        notes.append(info["basin"]["summary"])
    choice = info.get("distortion_choice") or {}
    if choice.get("why"):
        notes.append(f"distortion terms not chosen ({choice['why']})")
    elif choice.get("failed"):
        notes.append("term sets not fitted on held-out views, so not candidates: "
                     + ", ".join(choice["failed"]))
    if choice.get("unplaced"):
        notes.append("held-out views a term set could not place, left out of every set's "
                     "comparison: " + ", ".join(f"{k} {n}" for k, n in choice["unplaced"].items()))
    return notes
