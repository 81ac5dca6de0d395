"""Docstrings state formulas, units, conventions and defaults; measured results (timings,
errors against a reference, speed ratios) go stale, so they live in the benchmarks' outputs and
in ``docs/``, and a docstring names the command instead.

The patterns below are phrasings of measured results; each is checked here on a sentence it must
flag and on formulas and defaults it must leave alone, then every module, class and function
docstring of the package is scanned.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import zoomcalib

PACKAGE = Path(zoomcalib.__file__).resolve().parent

NUMBER = r"\d+(?:\.\d+)?(?:e-?\d+)?"
MEASURED_RESULT = re.compile("|".join([
    rf"{NUMBER}\s*(?:ms|s) (?:per|a) (?:image|frame|corner|view|call|state)\b",  # timings
    rf"{NUMBER}\s*s (?:wall|CPU)\b",
    rf"{NUMBER}\s*px RMS\b",                                                   # error levels
    rf"{NUMBER}\s*x (?:faster|slower|worse|better|with(?:out)? (?:it|the))\b",  # ratios
    rf"\bmeasured[:,]?\s+(?:max(?:imum)?\s+)?(?:errors?\s+)?{NUMBER}",         # quoted results
    r"\bmeasured max(?:imum)? errors?\b",
    r"% of the time\b",
    r"\bon (?:the|a) (?:busy )?\d-core machine\b",
    rf"\bthis gives {NUMBER}\s*px\b",
]), re.IGNORECASE)

FLAGGED = [
    "the refiner takes 42 ms per image of 80 corners",
    "the intensity error is 1.1e-3 max (2.5e-4 px RMS) at sigma = 0.7 px",
    "on figueroa, 4.7 x with the prior and 20 x without it",
    "boards it makes the corners 4x worse",
    "that suggests: measured max 1.6e-4 px at sigma = 0.7",
    "Measured maximum errors of the X-junction over a window",
    "a multi-threaded BLAS on a busy 2-core machine spends most of its time",
    "At the reference setting this gives 0.0060 px radial for a square-on corner",
    "Measured: 2074.02, 2077.34",
]
LEFT_ALONE = [
    "Half-size of the window, px (5 -> 11 x 11 pixels).",
    "shrunk to 0.45 x the corner spacing",
    "the residual RMS per corner, intensity units of the input image",
    "``3.7e-6`` for the default 5, so clean data lose nothing",
    "1.4826 x median absolute residual component: sigma of Gaussian residuals",
    "The measured numbers the checks used.",
    "measured by ``python benchmarks/bench_refine.py --model-accuracy``",
    "Axial position of each group's tilt pivot, mm, measured from its first vertex.",
    "the 1-sigma of ``cx`` or ``cy`` exceeds 1 % of the image diagonal",
]


@pytest.mark.parametrize("text", FLAGGED)
def test_pattern_flags_a_measured_result(text):
    assert MEASURED_RESULT.search(text), text


@pytest.mark.parametrize("text", LEFT_ALONE)
def test_pattern_leaves_formulas_and_defaults_alone(text):
    assert not MEASURED_RESULT.search(text), MEASURED_RESULT.search(text)


def measured_results_in_docstrings(package: Path) -> list[str]:
    """``path:line: text`` of every docstring line under ``package`` that quotes a measured
    result. A sentence broken over two lines is matched with its two lines joined."""
    found = []
    for path in sorted(package.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                     ast.AsyncFunctionDef)):
                continue
            doc = ast.get_docstring(node, clean=False)
            if not doc:
                continue
            lines = [line.strip() for line in doc.splitlines()]
            for i in range(len(lines)):
                pair = " ".join(lines[i:i + 2])
                if MEASURED_RESULT.search(pair) and not (
                        i > 0 and MEASURED_RESULT.search(" ".join(lines[i - 1:i + 1]))):
                    found.append(f"{path.relative_to(package.parent)}:"
                                 f"{node.body[0].lineno + i}: {pair}")
    return found


def test_docstrings_carry_no_measured_results():
    found = measured_results_in_docstrings(PACKAGE)
    assert not found, ("measured results belong in a benchmark's output and docs/, with the "
                       "command named in the docstring:\n" + "\n".join(found))
