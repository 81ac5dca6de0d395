"""Where the test suite's CPU time goes: the README's test command with every pytest-xdist worker
under cProfile, the workers' statistics summed.

``python benchmarks/profile_suite.py [--out DIR] [--top 25] [-- PYTEST ARGUMENTS]``

Runs ``python -m pytest -q`` (the README's test command; arguments after ``--`` are passed on,
e.g. one test file) with this file loaded as a pytest plugin (``-p profile_suite``), which
profiles each worker process from its start and writes its statistics to ``DIR`` at its exit.
Then it prints:

- the functions with the most time of their own (s, summed over the workers);
- the share of each stage of :data:`STAGES` in the profiled time: its cumulative time (a
  stage called inside another counts in both), over the workers' time less their waiting.

Processes that the tests start themselves (the command line's subprocesses, the pools'
workers) are not profiled: their time is the parent's waiting, left out of the total.
cProfile slows Python code, not OpenCV's, so read the shares, not the seconds.
"""

from __future__ import annotations

import atexit
import cProfile
import os
import sys

#: Environment variable through which the plugin learns where to write its statistics.
PROFILE_DIR = "ZOOMCALIB_PROFILE_DIR"
#: A worker's time in these is waiting for another process (or for time), not CPU.
WAITING = ("<method 'acquire' of '_thread.lock' objects>",
           "<method 'poll' of 'select.poll' objects>", "<built-in method time.sleep>")
#: The stages reported: a label, the end of the function's file name ('~' for a builtin) and
#: its name.
STAGES = (
    ("OpenCV calibrateCameraExtended", "~", "<calibrateCameraExtended>"),
    ("OpenCV calibrateCamera", "~", "<calibrateCamera>"),
    ("zoom-wide adjustment, in all", "calibrate/zoomwide.py", "calibrate_zoom_wide"),
    ("  steps' term choice (held-out folds)", "calibrate/stepfits.py", "select_distortion"),
    ("  steps' robust starts", "calibrate/stepfits.py", "_robust_start"),
    ("  steps' OpenCV starts", "calibrate/stepfits.py", "_opencv_start"),
    ("  basin checks", "calibrate/basins.py", "best_basin"),
    ("  Levenberg-Marquardt engine", "calibrate/solver.py", "levenberg_marquardt"),
    ("per-step OpenCV fits (all callers)", "calibrate/opencv_backend.py", "calibrate_opencv"),
    ("  their checks after OpenCV", "calibrate/opencv_backend.py", "_finish"),
    ("bundle adjustment", "calibrate/bundle.py", "calibrate_bundle"),
    ("projection with Jacobians", "calibrate/geometry.py", "project_jacobian"),
    ("rendering a sweep", "render/sweep.py", "render_zoom_sweep"),
    ("rendering an image (all callers)", "render/image.py", "render_image"),
    ("figures (matplotlib's savefig)", "matplotlib/figure.py", "savefig"),
    ("corner detection", "detect/opencv.py", "detect_image"),
    ("diagnosis", "diagnose/discrepancy.py", "diagnose_table"),
)

if os.environ.get(PROFILE_DIR) and __name__ != "__main__":      # loaded as the plugin
    _profile = cProfile.Profile()
    _profile.enable()

    @atexit.register
    def _write() -> None:
        _profile.disable()
        _profile.dump_stats(os.path.join(os.environ[PROFILE_DIR], f"worker_{os.getpid()}.prof"))


def summarise(stats, top: int) -> list[str]:
    """The report's lines from summed :class:`pstats.Stats` (module docstring)."""
    raw = stats.stats
    total = sum(v[2] for v in raw.values())
    waiting = sum(v[2] for k, v in raw.items() if k[2] in WAITING)
    cpu = total - waiting
    lines = [f"profiled time {total:.1f} s, of which waiting for other processes "
             f"{waiting:.1f} s: {cpu:.1f} s of CPU", "", "most time of their own:"]
    own = sorted(((v[2], v[0], k) for k, v in raw.items() if k[2] not in WAITING), reverse=True)
    for seconds, calls, (path, line, name) in own[:top]:
        where = name if path == "~" else f"{os.path.relpath(path)}:{line}({name})"
        lines.append(f"  {seconds:8.1f} s {100 * seconds / cpu:5.1f} %  {calls:9d} calls  {where}")
    lines += ["", "stages (cumulative time, share of the CPU time):"]
    for label, file_end, name in STAGES:
        seconds = sum(v[3] for (path, _, fn), v in raw.items()
                      if fn == name and (path == "~" if file_end == "~"
                                         else path.endswith(file_end)))
        lines.append(f"  {label:40s} {seconds:8.1f} s {100 * seconds / cpu:5.1f} %")
    return lines


def main() -> None:
    import argparse
    import glob
    import pstats
    import subprocess
    import tempfile
    from pathlib import Path

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None,
                    help="folder for the workers' statistics (default: a temporary one)")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("pytest_args", nargs="*")
    args = ap.parse_args()
    root = Path(__file__).resolve().parents[1]
    out = args.out or Path(tempfile.mkdtemp(prefix="profile-suite-"))
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("worker_*.prof"):
        old.unlink()
    env = dict(os.environ, **{PROFILE_DIR: str(out)})
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(root / "benchmarks"),
                                                      env.get("PYTHONPATH")]))
    command = [sys.executable, "-m", "pytest", "-q", "-p", "profile_suite",
               *args.pytest_args]
    print("running:", " ".join(command[1:]), flush=True)
    done = subprocess.run(command, cwd=root, env=env)
    files = sorted(glob.glob(str(out / "worker_*.prof")))
    if not files:
        sys.exit(f"profile_suite: no statistics were written to {out} (pytest exit "
                 f"{done.returncode})")
    print(f"\n{len(files)} processes profiled (pytest exit {done.returncode}); statistics in "
          f"{out}\n")
    print("\n".join(summarise(pstats.Stats(*files), args.top)))


if __name__ == "__main__":
    main()
