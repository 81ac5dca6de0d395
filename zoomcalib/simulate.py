"""The ``simulate`` job: principal-point drift and scatter across the zoom range.

Writes, in the output folder:

- ``principal_point.csv``: ``zoom, efl_mm, fx_px, cx_mean, cy_mean, cx_std, cy_std`` (px);
- ``sensitivity.csv``: ``zoom, efl_mm, group, shift_per_decenter`` (um/um),
  ``shift_per_tilt_um_per_mrad`` (pivot at the group's first vertex), from the paraxial tracer;
- ``spiral.png``: the paper's Fig. 5;
- ``simulate.json``: the inputs (lens, tolerances, seed, tracer, sensor) and versions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .camera import DEFAULT_SENSOR, Sensor
from .io import write_csv, write_json
from .optics.mechanics import Tolerances
from .optics.prescription import Prescription
from .optics.principal_point import (
    PrincipalPointScatter,
    principal_point_scatter,
    sensitivity_rows,
)
from .plots import plot_principal_point_spiral

__all__ = ["SimulationResult", "simulate"]

PRINCIPAL_POINT_COLUMNS = ["zoom", "efl_mm", "fx_px", "cx_mean", "cy_mean", "cx_std", "cy_std"]
SENSITIVITY_COLUMNS = ["zoom", "efl_mm", "group", "shift_per_decenter",
                       "shift_per_tilt_um_per_mrad"]


@dataclass
class SimulationResult:
    scatter: PrincipalPointScatter
    sensitivity: list[dict]
    files: dict[str, Path]


def simulate(lens: Prescription, tolerances: Tolerances, out: str | Path, steps: int = 21,
             samples: int = 1000, seed: int = 0, tracer: str = "exact",
             sensor: Sensor = DEFAULT_SENSOR, direction: str = "random",
             progress: Callable[[int], None] | None = None) -> SimulationResult:
    """Run the principal-point Monte Carlo over ``steps`` evenly spaced zoom states and write
    the outputs listed in the module docstring into ``out``."""
    if steps < 2:
        raise ValueError("steps must be at least 2")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    zoom = np.linspace(0.0, 1.0, steps)
    scatter = principal_point_scatter(lens, tolerances, zoom, samples, seed, tracer, sensor,
                                      direction, progress)
    sens = sensitivity_rows(lens, zoom)
    files = {
        "principal_point": write_csv(out / "principal_point.csv", scatter.rows(),
                                     PRINCIPAL_POINT_COLUMNS),
        "sensitivity": write_csv(out / "sensitivity.csv", sens, SENSITIVITY_COLUMNS),
        "spiral": plot_principal_point_spiral(
            zoom, scatter.mean_px, scatter.std_px, out / "spiral.png",
            title=f"{lens.name}: principal point across zoom, {samples} draws/step, "
                  f"seed {seed} ({tracer} tracer)",
            centre_px=sensor.centre_px),
    }
    files["metadata"] = write_json(out / "simulate.json", {
        "zoomcalib_version": __version__, "lens": lens.name, "lens_file": lens.path,
        "tolerances": tolerances.to_dict(), "tolerance_file": tolerances.source,
        "steps": steps, "samples": samples, "seed": seed, "tracer": tracer,
        "direction": direction,
        "sensor": {"width_px": sensor.width_px, "height_px": sensor.height_px,
                   "pixel_pitch_mm": sensor.pixel_pitch_mm},
    })
    return SimulationResult(scatter, sens, files)
