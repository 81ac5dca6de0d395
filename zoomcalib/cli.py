"""Command-line interface: ``zoomcalib COMMAND --help`` explains each command.

The commands only parse options, call the library and print a short summary.
"""

from __future__ import annotations

import sys

import click
import numpy as np

from . import __version__
from .camera import DEFAULT_SENSOR
from .optics.mechanics import ToleranceError, load_tolerances
from .optics.prescription import PrescriptionError, builtin_lenses, load_prescription
from .optics.principal_point import TRACERS


def _load_lens(name: str):
    try:
        return load_prescription(name)
    except PrescriptionError as exc:
        raise click.BadParameter(str(exc), param_hint="--lens") from None


def _load_tolerances(path, lens):
    try:
        return load_tolerances(path, lens)
    except ToleranceError as exc:
        raise click.BadParameter(str(exc), param_hint="--tolerances") from None


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="zoomcalib")
def main() -> None:
    """Calibrate zoom cameras and measure which error source limits the calibration.

    Start with `zoomcalib simulate`: the principal-point drift and scatter that the
    mechanical errors of a zoom lens cause across its zoom range.
    """


LENS_HELP = (f"Lens prescription: a built-in name ({', '.join(builtin_lenses())}) or a JSON "
             "file in the same form.")


@main.command()
@click.option("--lens", default="laikin-10x", show_default=True, help=LENS_HELP)
@click.option("--tolerances", type=click.Path(dir_okay=False),
              help="Mechanical tolerance file (YAML or JSON); default: the built-in tolerances "
                   "(decentre 10-15 um and tilt 1 arcmin locked to the barrel, play 5 um, "
                   "backlash 4 um, on the variator and compensator).")
@click.option("--steps", default=21, show_default=True, type=click.IntRange(min=2),
              help="Number of evenly spaced zoom states from 0 (wide) to 1 (tele).")
@click.option("--samples", default=1000, show_default=True, type=click.IntRange(min=2),
              help="Monte Carlo draws of the mechanical errors per zoom state.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option("--tracer", type=click.Choice(TRACERS), default="exact", show_default=True,
              help="Real-ray tracer, or the (linear, faster) paraxial one.")
@click.option("--direction", type=click.Choice(["random", "in", "out"]), default="random",
              show_default=True, help="Direction of the last zoom move before each capture "
                                      "(sets the side of the backlash).")
@click.option("--out", default="zoomcalib-simulate", show_default=True,
              type=click.Path(file_okay=False), help="Output folder.")
def simulate(lens, tolerances, steps, samples, seed, tracer, direction, out):
    """Principal-point drift and scatter across the zoom range (the paper's Fig. 5).

    Writes OUT/principal_point.csv (zoom, efl_mm, fx_px, cx_mean, cy_mean, cx_std, cy_std, in
    pixels), OUT/sensitivity.csv (image shift per unit decentre and tilt of every group),
    OUT/spiral.png and OUT/simulate.json (inputs and versions).
    """
    from .simulate import simulate as run

    lens_ = _load_lens(lens)
    tol = _load_tolerances(tolerances, lens_)
    with click.progressbar(length=steps, label="zoom steps", file=sys.stderr) as bar:
        res = run(lens_, tol, out, steps=steps, samples=samples, seed=seed, tracer=tracer,
                  direction=direction, progress=bar.update)
    s = res.scatter
    c0 = DEFAULT_SENSOR.centre_px
    click.echo(f"{lens_.name}: {steps} zoom states, {samples} draws each, seed {seed}, "
               f"{tracer} tracer")
    click.echo("  zoom  EFL[mm]   cx-c0[px]  cy-c0[px]  sd_cx[px]  sd_cy[px]")
    every = max(1, steps // 10)
    for i in list(range(0, steps, every)) + ([steps - 1] if (steps - 1) % every else []):
        d = s.mean_px[i] - c0
        click.echo(f"  {s.zoom[i]:4.2f} {s.efl_mm[i]:8.2f} {d[0]:10.3f} {d[1]:10.3f} "
                   f"{s.std_px[i, 0]:10.3f} {s.std_px[i, 1]:10.3f}")
    path_len = np.linalg.norm(np.diff(s.mean_px, axis=0), axis=1).sum()
    click.echo(f"mean-path length {path_len:.2f} px; largest drift from the sensor centre "
               f"{np.linalg.norm(s.mean_px - c0, axis=1).max():.2f} px; scatter (1-sigma) "
               f"{s.std_px.mean(1).min():.2f}-{s.std_px.mean(1).max():.2f} px")
    click.echo(f"wrote {', '.join(str(p) for p in res.files.values())}")


if __name__ == "__main__":
    main()
