"""The ``diagnose`` job: a per-zoom table (or a folder of zoom-step images) in, a diagnosis out.

Layout written to OUT::

    OUT/diagnosis.json      cause, baseline, extended, gain, candidates (contract in DESIGN.md)
    OUT/report.md           the same for people
    OUT/path.png            measured principal points against the simulated path
    OUT/residuals.png       residuals against focal length, before and after the extension
    OUT/calibration/        when INPUT is an image folder: the calibrate job's output
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..calibrate.io import read_zoom_table
from ..optics.mechanics import Tolerances
from ..optics.prescription import Prescription
from .discrepancy import Diagnosis, diagnose_table
from .model import LensResponse
from .report import write_diagnosis
from .table import ZoomTable

__all__ = ["DiagnoseRun", "diagnose_input", "load_zoom_table"]


@dataclass
class DiagnoseRun:
    diagnosis: Diagnosis
    table_path: Path
    files: list[Path] = field(default_factory=list)


def load_zoom_table(path: str | Path) -> ZoomTable:
    """Read and check a ``zoom_calibration.csv``; errors name the file and row."""
    path = Path(path)
    return ZoomTable.from_rows(read_zoom_table(path), str(path))


def diagnose_input(source: str | Path, out: str | Path, lens: Prescription,
                   pixel_pitch: float | str = 0.00645, tolerances: Tolerances | None = None,
                   pattern: str | None = None, backends: tuple[str, ...] = ("opencv",),
                   workers: int = 1, progress: Callable[[int], None] | None = None,
                   log: Callable[[str], None] = print) -> DiagnoseRun:
    """Diagnose a ``zoom_calibration.csv`` or a folder of zoom-step images.

    Parameters
    ----------
    source : path
        A per-zoom table, or a folder of step subfolders (calibrated first into
        ``OUT/calibration``; needs ``pattern``).
    out : path
    lens : Prescription
        The lens model whose EFL curve places each row and whose sensitivities make the
        baseline.
    pixel_pitch : float or 'auto'
        mm; ``'auto'`` fits it.
    tolerances : Tolerances, optional
        For the random-play scatter (default: built-in).
    pattern, backends, workers, progress, log
        Passed to :func:`zoomcalib.calibrate.run.calibrate_folder` for an image folder.
    """
    source, out = Path(source), Path(out)
    if source.is_dir():
        if not pattern:
            raise ValueError(f"{source}: an image folder needs --pattern to be calibrated first")
        from ..calibrate.run import calibrate_folder

        cal = calibrate_folder(source, pattern, out / "calibration", backends,
                               workers=workers, progress=progress, log=log)
        table_path = out / "calibration" / "zoom_calibration.csv"
        if not table_path.exists():
            raise ValueError(f"{source}: no zoom table could be made "
                             f"({'; '.join(cal.failures) or 'not a folder of zoom steps'})")
    elif source.exists():
        table_path = source
    else:
        raise FileNotFoundError(f"{source}: no such file or folder")
    table = load_zoom_table(table_path)
    fit_pitch = isinstance(pixel_pitch, str)
    if fit_pitch and pixel_pitch != "auto":
        raise ValueError(f"pixel pitch must be a number (mm) or 'auto', got {pixel_pitch!r}")
    response = LensResponse.of(lens, 0.00645 if fit_pitch else float(pixel_pitch))
    diag = diagnose_table(table, response, tolerances, fit_pitch=fit_pitch)
    files = write_diagnosis(diag, out)
    return DiagnoseRun(diag, table_path, files)
