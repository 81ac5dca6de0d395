"""The package's stages import downwards only: no import circle, no lower stage that imports a
higher one (docs/conventions.md, "Package layout").

Each module's relative imports are read from its source (imports inside functions too) and
mapped to the top-level unit they reach (``zoomcalib/calibrate/run.py`` is in ``calibrate``).
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "zoomcalib"
#: The data flow's stages, lowest first; a unit imports units of lower stages only.
STAGES = [
    {"__init__", "__version__", "camera", "imaging", "io", "targets", "pool", "plots",
     "report_plots"},
    {"optics", "zoom"},
    {"render", "simulate", "detect"},
    {"calibrate"},
    {"diagnose"},
    {"study"},
    {"cli", "__main__"},
]


def _unit(path: Path, root: Path) -> str:
    return path.relative_to(root).parts[0].removesuffix(".py")


def _imports(path: Path, root: Path) -> set[str]:
    """The top-level units of the package at ``root`` that the module at ``path`` imports."""
    package = path.relative_to(root).parts[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = list(package[:len(package) - (node.level - 1)])
            target = base + (node.module.split(".") if node.module else [])
            found |= {target[0]} if target else {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("zoomcalib."):
            found.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names
                      if a.name.startswith("zoomcalib.")}
    return found


def _upward(root: Path) -> list[str]:
    """Every import of a unit of the same or a higher stage, as ``"module imports unit"``."""
    stage = {u: i for i, units in enumerate(STAGES) for u in units}
    found = []
    for path in sorted(root.rglob("*.py")):
        unit = _unit(path, root)
        for target in sorted(_imports(path, root) - {unit}):
            if stage.get(target, len(STAGES)) >= stage.get(unit, -1):
                found.append(f"{path.relative_to(root)} imports {target}")
    return found


def test_every_unit_has_a_stage():
    units = {_unit(p, ROOT) for p in ROOT.rglob("*.py")}
    staged = set().union(*STAGES)
    assert units <= staged, units - staged


def test_stages_import_downwards_only():
    assert _upward(ROOT) == []


def test_an_upward_import_is_found(tmp_path):
    # render/pp_path.py once imported the diagnosis; render and detect share a stage
    (tmp_path / "render").mkdir()
    (tmp_path / "render" / "pp_path.py").write_text(
        "from ..diagnose.model import moving_groups\nfrom ..optics.cam import solve_gaps\n")
    (tmp_path / "detect").mkdir()
    (tmp_path / "detect" / "opencv.py").write_text(
        "def f():\n    from ..render.image import Optics\n")
    assert _upward(tmp_path) == ["detect/opencv.py imports render",
                                 "render/pp_path.py imports diagnose"]
