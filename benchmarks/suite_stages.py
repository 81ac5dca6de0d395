"""Where the test suite's time goes by stage, timed without a profiler: the README's test command
with each stage of :data:`STAGES` wrapped in a clock, summed over the pytest-xdist workers.

``python benchmarks/suite_stages.py [--out DIR] [--top 4] [-- PYTEST ARGUMENTS]``

Runs ``python -m pytest -q`` (arguments after ``--`` are passed on, e.g. one test file) with this
file loaded as a pytest plugin (``-p suite_stages``). In each worker the plugin replaces every
stage's function, in its module and wherever a module of the package imported it by name, with
one that adds its wall time (``time.perf_counter``; a call inside a call of the same stage is
counted once) to the test file running it; at the worker's exit it writes the sums to ``DIR``.
Then it prints, per stage, the seconds, the calls and the test files that spend most in it.

Unlike ``benchmarks/profile_suite.py`` (cProfile, which slows Python code and not OpenCV's) the
seconds are those of a normal run. Stages nest (a basin check's OpenCV fits are OpenCV's too), so
the rows do not add up. The time of processes the tests start themselves (the command line's
subprocesses, the pools' and Dask's workers) is not seen.
"""

from __future__ import annotations

import argparse
import atexit
import collections
import functools
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: Environment variable through which the plugin learns where to write its sums.
STAGE_DIR = "ZOOMCALIB_STAGE_DIR"
#: The stages timed: (module, attribute; ``Class.method`` for a method).
STAGES = (
    ("cv2", "calibrateCamera"),
    ("cv2", "calibrateCameraExtended"),
    ("zoomcalib.calibrate.zoomwide", "calibrate_zoom_wide"),
    ("zoomcalib.calibrate.stepfits", "select_distortion"),
    ("zoomcalib.calibrate.stepfits", "_robust_start"),
    ("zoomcalib.calibrate.stepfits", "_opencv_start"),
    ("zoomcalib.calibrate.basins", "best_basin"),
    ("zoomcalib.calibrate.solver", "levenberg_marquardt"),
    ("zoomcalib.calibrate.opencv_backend", "calibrate_opencv"),
    ("zoomcalib.calibrate.bundle", "calibrate_bundle"),
    ("zoomcalib.render.image", "render_image"),
    ("zoomcalib.detect.opencv", "detect_image"),
    ("zoomcalib.diagnose.discrepancy", "diagnose_table"),
    ("zoomcalib.calibrate.report", "write_report"),
    ("zoomcalib.plots", "plot_residuals"),
    ("matplotlib.figure", "Figure.savefig"),
)

_spent: dict[tuple[str, str], float] = collections.defaultdict(float)
_calls: collections.Counter = collections.Counter()
_depth: collections.Counter = collections.Counter()


def _timed(label: str, function):
    @functools.wraps(function)
    def timed(*args, **kwargs):
        _depth[label] += 1
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            _depth[label] -= 1
            if not _depth[label]:
                test_file = os.environ.get("PYTEST_CURRENT_TEST", "?").split("::")[0]
                _spent[label, test_file] += time.perf_counter() - start
                _calls[label, test_file] += 1

    return timed


def _install() -> None:
    """Wrap every stage where it is defined and wherever the package imported it by name."""
    import pkgutil

    import zoomcalib

    for info in pkgutil.walk_packages(zoomcalib.__path__, "zoomcalib."):
        importlib.import_module(info.name)
    for module_name, attribute in STAGES:
        module = importlib.import_module(module_name)
        if "." in attribute:                       # a method: wrapped on its class
            owner_name, name = attribute.split(".")
            owner = getattr(module, owner_name)
            setattr(owner, name, _timed(attribute, getattr(owner, name)))
            continue
        original = getattr(module, attribute)
        wrapped = _timed(attribute, original)
        for name, other in list(sys.modules.items()):
            if other is not None and (name == module_name or name.startswith("zoomcalib")) \
                    and getattr(other, attribute, None) is original:
                setattr(other, attribute, wrapped)


def pytest_configure(config) -> None:  # noqa: ARG001 (pytest's hook signature)
    if os.environ.get(STAGE_DIR):
        _install()


@atexit.register
def _write() -> None:
    if os.environ.get(STAGE_DIR) and _calls:
        path = Path(os.environ[STAGE_DIR]) / f"worker_{os.getpid()}.json"
        path.write_text(json.dumps([[label, test_file, seconds, _calls[label, test_file]]
                                    for (label, test_file), seconds in _spent.items()]))


def summarise(rows: list[list], top: int) -> list[str]:
    """The report's lines from the workers' ``[stage, test file, seconds, calls]`` rows."""
    seconds, calls = collections.defaultdict(float), collections.Counter()
    by_file: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for label, test_file, spent, n in rows:
        seconds[label] += spent
        calls[label] += n
        by_file[label][test_file] += spent
    lines = [f"{'stage':28s} {'seconds':>8s} {'calls':>7s}  most in"]
    for label in sorted(seconds, key=seconds.get, reverse=True):
        most = ", ".join(f"{Path(f).name} {s:.0f}" for f, s in by_file[label].most_common(top))
        lines.append(f"{label:28s} {seconds[label]:8.1f} {calls[label]:7d}  {most}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="folder for the workers' sums (default: a "
                        "temporary one)")
    parser.add_argument("--top", type=int, default=4, help="test files named per stage")
    parser.add_argument("pytest_args", nargs="*", help="after --: passed on to pytest")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="suite_stages_"))
    out.mkdir(parents=True, exist_ok=True)
    here = Path(__file__).resolve().parent
    env = dict(os.environ, **{STAGE_DIR: str(out)},
               PYTHONPATH=os.pathsep.join(filter(None, [str(here),
                                                        os.environ.get("PYTHONPATH")])))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "suite_stages",
                           *args.pytest_args], cwd=here.parent, env=env)
    print(f"pytest exit code {done.returncode}, {time.perf_counter() - start:.0f} s wall")
    rows = [row for f in sorted(out.glob("worker_*.json")) for row in json.loads(f.read_text())]
    print("\n".join(summarise(rows, args.top)))


if __name__ == "__main__" and not os.environ.get(STAGE_DIR):
    main()
