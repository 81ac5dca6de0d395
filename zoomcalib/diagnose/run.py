"""The ``diagnose`` job: a per-zoom table (or a folder of zoom-step images) in, a diagnosis out.

Layout written to OUT::

    OUT/diagnosis.json      cause, baseline, extended, gain, candidates (docs/conventions.md)
    OUT/report.md           the same for people
    OUT/path.png            measured principal points against the simulated path
    OUT/residuals.png       residuals against focal length, before and after the extension
    OUT/calibration/        when INPUT is an image folder: the calibrate job's output
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calibrate.io import read_principal_point_correlation, read_zoom_table
from ..optics.mechanics import Tolerances
from ..optics.prescription import Prescription
from .discrepancy import Diagnosis, baseline_terms, cause_variants, diagnose_table
from .model import DEFAULT_PITCH_MM, LensResponse, moving_groups
from .report import write_diagnosis
from .response import RowCalibration
from .table import ZoomTable
from .tangential import resolve_with_distortion

__all__ = ["DiagnoseRun", "diagnose_input", "load_zoom_table", "largest_model",
           "check_table_size", "MIN_SETTINGS", "ONE_STATE_SPREAD"]

MIN_SETTINGS = 3
"""Fewest distinct zoom settings: with one held out, the others must still span the range."""

ONE_STATE_SPREAD = 1e-3
"""Rows whose focal lengths all lie within this fraction of their median are one lens state."""


@dataclass
class DiagnoseRun:
    """What a diagnose run produced; ``failures`` lists the calibration's skipped steps."""

    diagnosis: Diagnosis
    table_path: Path
    files: list[Path] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


def largest_model(groups: tuple[str, ...] | None, locked_tilt: bool = False) -> int:
    """Parameters of the largest model every cause needs in its simplest form: the baseline
    plus, over the causes, the largest of their smallest variants, as if the table had every
    optional column (``groups`` None: no lens model, the smallest smooth path). Richer variants
    (a drift curve, a signed path) and several causes at once are fitted only where the rows
    allow."""
    two = np.arange(2.0)
    probe = ZoomTable(zoom=two, fx=two + 1, fy=two + 1, cx=two, cy=two, sd_cx=two, sd_cy=two,
                      direction=np.array([1.0, -1.0]), sequence=two, focus=two,
                      temperature=two)
    variants, _ = cause_variants(probe, groups)

    def size(terms) -> int:
        return sum(len(t.params) for t in terms)

    extra = max((min(size(v) for v in options) for options in variants.values()), default=0)
    if groups is None:
        return 4 + extra  # offset and a path linear in log f
    return size(baseline_terms(groups, locked_tilt)) + extra


def check_table_size(zoom: np.ndarray, fx: np.ndarray | None, source: str,
                     groups: tuple[str, ...] | None) -> None:
    """Refuse, before any fit, a table too small for the diagnosis or of one lens state.

    Every model is fitted with the rows of each zoom setting held out in turn, so the rows
    outside any one setting must give as many equations (2 per row) as the largest model
    (:func:`largest_model`) has parameters, and there must be ``MIN_SETTINGS`` settings.

    Parameters
    ----------
    zoom : (N,) ndarray
        The zoom setting of each row (any unit).
    fx : (N,) ndarray or None
        Measured focal lengths, px (None before calibration).

    Raises
    ------
    ValueError
        One line naming ``source``, what it has and the true minimum.
    """
    k = largest_model(groups)
    need = -(-k // 2)  # rows outside any one setting
    _, counts = np.unique(np.round(np.asarray(zoom, dtype=float), 9), return_counts=True)
    n = int(counts.sum())
    if len(counts) < MIN_SETTINGS or n - counts.max() < need:
        raise ValueError(
            f"{source}: {n} rows at {len(counts)} zoom settings are too few; the diagnosis "
            f"needs {MIN_SETTINGS} or more settings and {need} rows outside any one setting "
            f"(so {need + 1} rows with one per setting): its largest model has {k} parameters, "
            f"2 per row, fitted with each setting held out in turn")
    if fx is not None:
        fx = np.asarray(fx, dtype=float)
        mid = float(np.median(fx))
        if np.ptp(fx) <= ONE_STATE_SPREAD * mid:
            raise ValueError(
                f"{source}: all {n} rows are one lens state (fx {mid:.1f} px, within "
                f"{ONE_STATE_SPREAD:.1%}); the diagnosis needs rows across the zoom range")


def usable_rows(path: str | Path) -> tuple[list[dict], list[str]]:
    """The rows of a ``zoom_calibration.csv`` whose ``status`` is not ``unusable`` (a step the
    calibration could not determine is no measurement of the lens), and the steps left out."""
    rows = read_zoom_table(Path(path))
    kept = [r for r in rows if str(r.get("status") or "").strip() != "unusable"]
    return kept, [str(r.get("step")) for r in rows if str(r.get("status") or "").strip()
                  == "unusable"]


def load_zoom_table(path: str | Path) -> ZoomTable:
    """Read and check a ``zoom_calibration.csv`` (its usable rows, :func:`usable_rows`);
    errors name the file and row. A correlation of its rows' principal points beside it
    (``<table name>_correlation.json``, as ``calibrate`` writes for the zoom-wide
    adjustment's solve without the prior: :data:`~zoomcalib.calibrate.io.PP_CORRELATION_FILE`)
    is read into ``pp_correlation``."""
    path = Path(path)
    table = ZoomTable.from_rows(usable_rows(path)[0], str(path))
    beside = path.with_name(f"{path.stem}_correlation.json")
    if beside.exists():
        table.pp_correlation = read_principal_point_correlation(beside, table.step)
    return table


def _row_calibrations(table: ZoomTable, cal) -> list[RowCalibration] | None:
    """Each row's per-step OpenCV calibration from the calibrate run, None unless every row
    has one (the group terms then keep the paraxial shift)."""
    rows = []
    for step in table.step:
        result = cal.results.get(step, {}).get("opencv")
        if result is None or step not in cal.observations:
            return None
        rows.append(RowCalibration(result, cal.observations[step]))
    return rows


def _calibrations_beside(table: ZoomTable, table_path: Path
                         ) -> tuple[list[RowCalibration] | None, str]:
    """Each row's per-step OpenCV calibration from the calibrate output folder that holds the
    table (its ``calibration.json`` and ``detections/``), or None and the reason why not."""
    from ..calibrate.io import read_calibration
    from ..calibrate.opencv_backend import observations_from_detections
    from ..detect.opencv import read_detections

    folder = table_path.parent
    if not (folder / "calibration.json").exists() or not (folder / "detections").is_dir():
        return None, f"no calibration.json and detections/ beside {table_path.name}"
    try:
        results, _ = read_calibration(folder / "calibration.json")
        rows = []
        for step in table.step:
            result = results.get(step, {}).get("opencv")
            if result is None:
                return None, f"step {step} has no per-step OpenCV calibration"
            spec, dets = read_detections(folder / "detections" / f"{step}.json")
            good = [d for d in dets if d.error is None]
            obs = observations_from_detections(good, spec, good[0].image_size if good else None)
            index = {name: i for i, name in enumerate(obs.names)}
            used = list(result.info.get("views", []))
            if not used or any(name not in index for name in used):
                return None, f"step {step}: the calibration's views are not all in its detections"
            keep = [index[name] for name in used]
            obs = obs.subset(keep)
            rows.append(RowCalibration(result, obs))
    except (OSError, ValueError) as exc:
        return None, str(exc)
    return rows, ""


#: Beside a zoom-wide ``zoom_calibration.csv``: its solve without the smoothness prior
#: (``zoomcalib.calibrate.outputs.UNSMOOTHED_TABLE``).
UNSMOOTHED_TABLE = "zoom_calibration_unsmoothed.csv"


def _independent_rows(table_path: Path, log: Callable[[str], None]) -> Path:
    """The table to diagnose for ``table_path``: itself, or for the rows of a zoom-wide
    adjustment (tied by its smoothness prior) the rows of its solve without the prior
    written beside it (:data:`UNSMOOTHED_TABLE`), which the prior does not tie; without that
    file the zoom-wide table itself, which :meth:`ZoomTable.from_rows` refuses."""
    try:
        rows = read_zoom_table(table_path)
    except (OSError, ValueError):
        return table_path  # load_zoom_table says what is wrong with it
    if not any(str(r.get("mode") or "").strip() == "zoom-wide" for r in rows):
        return table_path
    beside = table_path.with_name(UNSMOOTHED_TABLE)
    if beside.exists():
        correlated = beside.with_name(f"{beside.stem}_correlation.json").exists()
        log(f"{table_path}: rows of the zoom-wide adjustment, tied by its smoothness prior; "
            f"diagnosing those of its solve without the prior ({beside.name})"
            + (", weighed with their principal points' correlation" if correlated else ""))
        return beside
    return table_path


def diagnose_input(source: str | Path, out: str | Path, lens: Prescription | None,
                   pixel_pitch: float | str = 0.00645, tolerances: Tolerances | None = None,
                   pattern: str | None = None, backends: tuple[str, ...] = ("opencv",),
                   workers: int = 1, progress: Callable[[int], None] | None = None,
                   log: Callable[[str], None] = print, report: bool = True) -> DiagnoseRun:
    """Diagnose a ``zoom_calibration.csv`` or a folder of zoom-step images.

    Parameters
    ----------
    source : path
        A per-zoom table, or a folder of step subfolders (calibrated first into
        ``OUT/calibration``; needs ``pattern``). The group terms use each row's calibration
        response (:mod:`~zoomcalib.diagnose.response`) when the calibrations are at hand: from
        the folder's calibration, or for a table in a ``calibrate`` output folder from its
        ``calibration.json`` and ``detections/``; else the paraxial image shift, and ``log``
        says why.
    out : path
    lens : Prescription or None
        The lens model whose EFL curve places each row and whose sensitivities make the
        baseline; None for a lens without a model (a smooth path in log f is the baseline).
    pixel_pitch : float or 'auto'
        mm; ``'auto'`` fits it.
    tolerances : Tolerances, optional
        For the random-play scatter (default: built-in).
    pattern, backends, workers, progress, log, report
        Passed to :func:`zoomcalib.calibrate.run.calibrate_folder` for an image folder
        (``report``: write the calibration's ``report.html``).
    """
    source, out = Path(source), Path(out)
    groups = moving_groups(lens) if lens is not None else None
    failures: list[str] = []
    if source.is_dir():
        if not pattern:
            raise ValueError(f"{source}: an image folder needs --pattern to be calibrated first")
        from ..calibrate.run import calibrate_folder
        from ..calibrate.stepfolders import zoom_steps

        steps = zoom_steps(source)
        # one row per step; an unknown zoom counts as a setting of its own until refused below
        zooms = np.array([-1.0 - i if zoom is None else zoom
                          for i, (_, _, zoom, _) in enumerate(steps)])
        check_table_size(zooms, None, str(source), groups)
        unknown = [step for step, _, zoom, _ in steps if zoom is None]
        if unknown:
            raise ValueError(f"{source}: the zoom of step {unknown[0]} is unknown (no steps.csv "
                             f"row, no number in the folder name, no EXIF focal length)")
        # per-step calibrations: the diagnosis treats the rows as independent measurements,
        # which the zoom-wide adjustment's rows (tied by its smoothness prior) are not
        cal = calibrate_folder(source, pattern, out / "calibration", backends,
                               workers=workers, progress=progress, log=log, zoom_wide=False,
                               report=report)
        failures = list(cal.failures)
        table_path = out / "calibration" / "zoom_calibration.csv"
        if not table_path.exists():
            raise ValueError(f"{source}: no zoom table could be made "
                             f"({'; '.join(cal.failures) or 'not a folder of zoom steps'})")
    elif source.exists():
        table_path = _independent_rows(source, log)
    else:
        raise FileNotFoundError(f"{source}: no such file or folder")
    table = load_zoom_table(table_path)
    left_out = usable_rows(table_path)[1]
    if left_out:
        log(f"{table_path}: left out the unusable step{'s' if len(left_out) > 1 else ''} "
            f"{', '.join(left_out)} (status column)")
    check_table_size(table.zoom, table.fx, table.source, groups)
    fit_pitch = isinstance(pixel_pitch, str)
    if fit_pitch and pixel_pitch != "auto":
        raise ValueError(f"pixel pitch must be a number (mm) or 'auto', got {pixel_pitch!r}")
    if lens is None:
        response, fit_pitch = None, False
    else:
        pitch = DEFAULT_PITCH_MM if fit_pitch else float(pixel_pitch)
        # a lens that cannot be this camera's is said first, from the lens's two ends, before
        # its dense EFL curve is traced or any calibration loaded
        ends = LensResponse.of(lens, pitch, n_grid=2)
        if fit_pitch:
            ends.pitch_range(table.fx, table.source)
        else:
            ends.state_of_focal(table.fx, table.source)
        response = LensResponse.of(lens, pitch)
    if source.is_dir():
        table.calibrations = _row_calibrations(table, cal)
    elif lens is not None:
        table.calibrations, why = _calibrations_beside(table, table_path)
        if table.calibrations is None:
            log(f"{table_path}: the group terms use the paraxial image shift ({why})")
    diag = diagnose_table(table, response, tolerances, fit_pitch=fit_pitch)
    if response is not None:
        diag = resolve_with_distortion(
            diag, usable_rows(table_path)[0],
            lambda **changes: diagnose_table(table, response, tolerances, fit_pitch=fit_pitch,
                                             **changes))
    files = write_diagnosis(diag, out)
    return DiagnoseRun(diag, table_path, files, failures)
