"""Does a step whose frames were taken in two sittings see two boards?

``python benchmarks/bench_real_sittings.py FOLDER [--out DIR] [--pattern chessboard:22x15:25]
[--gap-hours 1]``

``FOLDER`` is a zoom set whose image names carry their capture time
(``..._YYYYMMDDhhmmss.png``), e.g. the real PTZ set's ``calibration_images``
(``bench_real_ptz.py``; nothing of it is kept here); detections are made or reused from
``OUT/detections``. A step's frames, in time order, form a new sitting after a gap of more
than ``--gap-hours``. Every sitting but a step's largest becomes a step of its own (named
``STEP@hhmm``; a sitting of fewer than 6 views stays with its step), outside the smoothness
prior's chain (its own intrinsics, nothing borrowed from the neighbours), and the zoom-wide
adjustment (the default board, ``print``) runs twice:

- **same board**: the later sitting on its step's session board (as ``calibrate`` takes it);
- **own board**: the later sitting on a board of its own (a board re-taped between sittings).

Printed per run: every affected step's and its neighbours' fx, cx, cy with sigmas and RMS.
A later sitting whose RMS falls on its own board saw another board; the adjustment's sessions
are whole steps, so ``calibrate`` cannot give it one.
"""

from __future__ import annotations

import argparse
import re
import sys
from datetime import datetime, timedelta
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.result import Observations  # noqa: E402
from zoomcalib.calibrate.run import calibrate_folder  # noqa: E402
from zoomcalib.calibrate.stepfolders import capture_date  # noqa: E402
from zoomcalib.calibrate.zoomwide import calibrate_zoom_wide  # noqa: E402

STAMP = re.compile(r"(\d{14})")
#: A sitting of fewer views stays with its step (too few to calibrate apart).
MIN_VIEWS = 6


def sittings(names: list[str], gap: timedelta) -> list[list[int]]:
    """The views' indices grouped into sittings: in capture-time order, a new group after a
    gap longer than ``gap``; views without a time stamp join the first group."""
    stamped = sorted((datetime.strptime(m.group(1), "%Y%m%d%H%M%S"), i)
                     for i, n in enumerate(names) if (m := STAMP.search(n)))
    groups: list[list[int]] = []
    last = None
    for t, i in stamped:
        if last is None or t - last > gap:
            groups.append([])
        groups[-1].append(i)
        last = t
    unstamped = [i for i, n in enumerate(names) if not STAMP.search(n)]
    if groups:
        groups[0] = sorted(groups[0] + unstamped)
    return groups


def _subset(obs: Observations, views: list[int]) -> Observations:
    return Observations(obs.object_points, [obs.views[i] for i in views], obs.image_size,
                        [obs.names[i] for i in views])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--out", type=Path, default=Path("bench-real-sittings"))
    ap.add_argument("--pattern", default="chessboard:22x15:25")
    ap.add_argument("--gap-hours", type=float, default=1.0)
    args = ap.parse_args()
    run = calibrate_folder(args.folder, args.pattern, args.out, ("opencv",), workers=2,
                           log=lambda m: None, report=False, zoom_wide=False)
    steps, session, chains, later = {}, {}, {}, {}
    gap = timedelta(hours=args.gap_hours)
    for step, obs in run.observations.items():
        day = capture_date(list(obs.names))[0] or ""
        groups = sittings(list(obs.names), gap)
        main_group = max(groups, key=len)
        apart = [g for g in groups if g is not main_group and len(g) >= MIN_VIEWS]
        kept = sorted(i for g in groups if not any(g is a for a in apart) for i in g)
        steps[step], session[step] = _subset(obs, kept), day
        for group in apart:
            first = min(STAMP.search(obs.names[i]).group(1) for i in group)
            name = f"{step}@{first[8:12]}"
            steps[name], session[name], chains[name] = _subset(obs, group), day, name
            later[name] = step
            print(f"{step}: {len(group)} of {len(obs.names)} views taken after a gap of more "
                  f"than {args.gap_hours:g} h: step {name}")
    if not later:
        print("no step was taken in more than one sitting")
        return
    names = list(steps)
    shown = set()
    for name, step in later.items():
        i = names.index(step)
        shown |= {name, *names[max(i - 1, 0):i + 2]}
    for label, own in (("same board", False), ("own board", True)):
        sessions = {s: (f"{session[s]} {s}" if own and s in later else session[s])
                    for s in steps}
        result = calibrate_zoom_wide(steps, sessions=sessions, chains=chains, workers=2,
                                     print_shape=True)
        print(f"{label}: aspect {result.aspect:.5f}")
        for s in names:
            if s in shown:
                r = result.results[s]
                sd = r.sd
                print(f"  {s:>14}: fx {r.fx:8.1f} ± {sd['fx']:5.1f}, cx {r.cx:6.1f} ± "
                      f"{sd['cx']:5.1f}, cy {r.cy:6.1f} ± {sd['cy']:5.1f}, RMS {r.rms_px:.3f} px")


if __name__ == "__main__":
    main()
