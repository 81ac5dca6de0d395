"""Command-line interface: ``zoomcalib COMMAND --help`` explains each command.

The commands only parse options, call the library and print a short summary.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

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


EXIT_PARTIAL = 3
EXIT_NOTHING = 4
EXIT_CODES = ("Exit codes: 0 all done; 1 the input could not be used, or a file could not be "
              "written (one line says which); 2 bad option or argument, or an output path that "
              "cannot be written (before any work); 3 partial: some images or steps failed, "
              "the results of the rest are written; 4 nothing usable.")


class _Group(click.Group):
    """The command group; an operating-system error that no check foresaw (a disk full, a
    file removed while in use) ends with one line naming the file, never a traceback, and
    Ctrl-C in any command with one line and exit code 130 (the shell's for SIGINT), where
    click would say "Aborted!" with 1."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second press cannot cut the exit
            click.echo("\ninterrupted (exit code 130)", err=True)
            sys.exit(130)
        except BrokenPipeError:
            raise
        except OSError as exc:
            text = exc.strerror or str(exc) or type(exc).__name__
            raise click.ClickException(f"{exc.filename}: {text}" if exc.filename else text) \
                from None


class _Finite(click.ParamType):
    """A finite float in ``[lo, hi]`` (click's FloatRange lets 'nan' through)."""

    name = "float"

    def __init__(self, lo: float = -math.inf, hi: float = math.inf) -> None:
        self.lo, self.hi = lo, hi

    def convert(self, value, param, ctx) -> float:
        try:
            v = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(v):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        if not self.lo <= v <= self.hi:
            bounds = (f">= {self.lo:g}" if math.isinf(self.hi) else
                      f"<= {self.hi:g}" if math.isinf(self.lo) else
                      f"in [{self.lo:g}, {self.hi:g}]")
            self.fail(f"{v:g} is not {bounds}", param, ctx)
        return v


def _nearest_existing(path: Path) -> Path:
    return next(p for p in (path, *path.parents) if p.exists() or p.is_symlink())


def _folder_problem(folder: Path) -> str | None:
    """Why files cannot be created in ``folder`` (created when missing), or None."""
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        kind = "a broken link" if not existing.exists() else "a file"
        return f"{existing} is {kind}, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"no permission to write in {existing}"
    return None


@contextlib.contextmanager
def _image_progress(length: int, label: str) -> Iterator[Callable[[int], None]]:
    """A progress bar over ``length`` images on stderr, with the count, the rate and the time
    left; yields the callable that advances it by a number of images done."""
    start, done = time.monotonic(), 0
    with click.progressbar(length=length, label=label, file=sys.stderr, show_pos=True,
                           item_show_func=lambda rate: rate) as bar:
        def advance(n: int = 1) -> None:
            nonlocal done
            done += n
            bar.update(n, f"{done / max(time.monotonic() - start, 1e-9):.1f} images/s")
        yield advance


def _check_out_folder(path: str, hint: str = "--out") -> None:
    """Refuse, before any work, an output folder that cannot be created or written."""
    problem = _folder_problem(Path(os.path.abspath(path)))
    if problem:
        raise click.BadParameter(f"{path}: {problem}", param_hint=hint)


def _check_out_file(path: str, hint: str = "--out", suffixes: tuple[str, ...] = ("",)) -> None:
    """Refuse, before any work, output files ``path + suffix`` that cannot be written; create
    their folder."""
    full = Path(os.path.abspath(path))
    problem = _folder_problem(full.parent)
    for f in (Path(str(full) + x) for x in suffixes):
        if problem is None and f.is_dir():
            problem = f"{f} is a folder, not a file"
        elif problem is None and f.exists() and not os.access(f, os.W_OK):
            problem = f"{f} is not writable"
    if problem:
        raise click.BadParameter(f"{path}: {problem}", param_hint=hint)
    full.parent.mkdir(parents=True, exist_ok=True)


def _calibration_problems(failures: list[str], messages: list[str]) -> list[str]:
    """Short names of what a calibrate run could not do: its failures (``step S: why``,
    ``step S: backend B failed: why``, ``zoom model: why``) and the images it skipped (logged
    as ``step S: skipped FILE: why``)."""
    out = []
    for f in failures:
        head, _, rest = f.partition(": ")
        out.append(f"{head} {rest.split(' failed')[0]}" if rest.startswith("backend ") else head)
    for m in messages:
        if m.startswith("step ") and ": skipped " in m:
            step, _, rest = m[len("step "):].partition(": skipped ")
            name = rest.split(":", 1)[0]
            out.append(f"image {name}" if step == "." else f"image {step}/{name}")
    return out


def _exit_nothing(what: str) -> None:
    click.echo(f"nothing usable: {what} (exit code {EXIT_NOTHING})", err=True)
    sys.exit(EXIT_NOTHING)


def _exit_if_partial(problems: list[str], summary: str) -> None:
    """When there are ``problems``, print ``summary`` and their names and exit EXIT_PARTIAL."""
    if problems:
        click.echo(f"partial result: {summary}: {', '.join(problems)} "
                   f"(exit code {EXIT_PARTIAL})", err=True)
        sys.exit(EXIT_PARTIAL)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]},
             epilog=EXIT_CODES)
@click.version_option(__version__, prog_name="zoomcalib")
def main() -> None:
    """Calibrate zoom cameras and measure which error source limits the calibration.

    Start with `zoomcalib simulate`: the principal-point drift and scatter that the
    mechanical errors of a zoom lens cause across its zoom range.
    """


LENS_HELP = (f"Lens prescription: a built-in name ({', '.join(builtin_lenses())}) or a JSON "
             "file in the same form.")


@main.command(epilog=EXIT_CODES)
@click.option("--lens", default="laikin-10x", show_default=True, help=LENS_HELP)
@click.option("--tolerances", type=click.Path(dir_okay=False),
              help="Mechanical tolerance file (YAML or JSON); default: the built-in tolerances "
                   "(decentre 10-15 um and tilt 1 arcmin locked to the barrel, play 5 um, "
                   "backlash 4 um, on the variator and compensator).")
@click.option("--steps", default=21, show_default=True, type=click.IntRange(min=2),
              help="Number of evenly spaced zoom states from 0 (wide) to 1 (tele).")
@click.option("--samples", default=1000, show_default=True, type=click.IntRange(min=2),
              help="Monte Carlo draws of the mechanical errors per zoom state.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="Random seed.")
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
    _check_out_folder(out)
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


MAX_SIDE_PX = 16384  # render --size: a larger image would not fit the renderer's buffers


def _parse_target(spec):
    from .targets import PatternError, parse_pattern

    try:
        return parse_pattern(spec)
    except PatternError as exc:
        raise click.BadParameter(str(exc), param_hint="PATTERN") from None


@main.command(epilog=EXIT_CODES)
@click.argument("pattern")
@click.option("--dpi", default=300.0, show_default=True, type=_Finite(10, 2400),
              help="Resolution of the PNG.")
@click.option("--out", default="target", show_default=True,
              help="Output stem: writes STEM.png, STEM.svg (mm) and STEM.json (geometry).")
@click.option("--paper", type=click.Choice(["A4", "A3", "letter"], case_sensitive=False),
              default=None,
              help="Lay the board out on this paper (portrait, or landscape if it fits only "
                   "that way); warns when it does not fit the printable area.")
def target(pattern, dpi, out, paper):
    """Write a printable target for PATTERN.

    PATTERN is chessboard:COLSxROWS:SQUARE (inner corners, mm), circles:COLSxROWS:SPACING,
    acircles:COLSxROWS:SPACING or charuco:SQUARESXxSQUARESY:SQUARE:MARKER:DICT. The PNG carries
    its DPI; under the board are its spec and a 100 mm bar to check the print with a ruler.
    """
    from .targets import PAPER_MM, write_printable

    t = _parse_target(pattern)
    _check_out_file(out, suffixes=(".png", ".svg", ".json"))
    if paper is not None:
        paper = next(p for p in PAPER_MM if p.lower() == paper.lower())
    files, layout = write_printable(t, out, dpi, paper)
    w, h = t.size_mm
    click.echo(f"{t.spec}: {t.n_points} points, board {w:g} x {h:g} mm; wrote {', '.join(files)}")
    if layout.orientation is not None:
        click.echo(f"laid out on {paper} {layout.orientation}; print at 100 % (no fit to page)")
    if layout.problem is not None:
        click.echo(f"warning: {files[0]}: {layout.problem}", err=True)


def _testbed_options(func):
    """Options of the non-flat board, the PSF shape and JPEG output (render, render-sweep)."""
    options = [
        click.option("--wave", default=0.0, show_default=True, type=click.FloatRange(min=0),
                     help="Peak height of the board's waves, mm (a few low-order sine modes "
                          "drawn from --seed); 0: a flat board."),
        click.option("--psf", default="gaussian", show_default=True,
                     type=click.Choice(["gaussian", "airy", "halo", "elliptical"]),
                     help="PSF shape; airy and halo are rendered supersampled."),
        click.option("--airy-radius", default=0.0, show_default=True,
                     type=click.FloatRange(min=0),
                     help="airy: radius of the first dark ring, px (0: 1.22 lambda N)."),
        click.option("--halo", default="0.05,6", show_default=True,
                     help="halo: FRACTION,SIGMA_PX of the energy in a wide Gaussian."),
        click.option("--ellipse", default="0.5,30", show_default=True,
                     help="elliptical: RATIO,ANGLE_DEG (minor over major sigma, major axis from "
                          "the u axis towards +v)."),
        click.option("--jpeg-quality", type=click.IntRange(1, 100),
                     help="Write JPEG files of this quality (1-100) instead of PNG; the truth "
                          "is unchanged."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _two_numbers(text: str, hint: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise click.BadParameter(f"must be two numbers separated by a comma, got {text!r}",
                                 param_hint=hint) from None
    return a, b


def _make_optics(blur, f_number, defocus, psf, airy_radius, halo, ellipse):
    from .render.image import Optics

    fraction, sigma = _two_numbers(halo, "--halo")
    ratio, angle = _two_numbers(ellipse, "--ellipse")
    try:
        return Optics(blur_px=blur, f_number=f_number, defocus_mm=defocus, psf=psf,
                      airy_radius_px=airy_radius, halo_fraction=fraction, halo_sigma_px=sigma,
                      ellipse_ratio=ratio, ellipse_angle_deg=angle)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--halo/--ellipse") from None


@main.command(epilog=EXIT_CODES)
@click.option("--lens", default="laikin-10x", show_default=True, help=LENS_HELP)
@click.option("--tolerances", type=click.Path(dir_okay=False),
              help="Mechanical tolerance file; default: the built-in tolerances. Each zoom step "
                   "gets one draw of the errors.")
@click.option("--nominal", is_flag=True, help="Render through the aligned lens (no errors).")
@click.option("--zoom", "zoom_list", help="Comma-separated zoom values in [0, 1].")
@click.option("--steps", default=3, show_default=True, type=click.IntRange(min=1),
              help="Evenly spaced zoom steps (when --zoom is not given).")
@click.option("--views", default=6, show_default=True, type=click.IntRange(min=1),
              help="Views per zoom step.")
@click.option("--pattern", default="chessboard:9x6:25", show_default=True,
              help="Target (scaled per zoom step to fill the view).")
@click.option("--noise", default=2.0, show_default=True, type=_Finite(0, 255),
              help="Read noise, 1-sigma in 8-bit digital numbers (of 255).")
@click.option("--blur", default=0.7, show_default=True, type=_Finite(0),
              help="Gaussian blur sigma, px (added to diffraction and defocus).")
@click.option("--defocus", default=0.0, show_default=True, type=_Finite(),
              help="Image-side defocus, mm. The PSF sigma of blur, diffraction and defocus "
                   "together must stay within 1 % of the image's shorter side (at least 3 px).")
@click.option("--bits", default=8, show_default=True, type=click.Choice(["8", "12", "16"]))
@click.option("--through", default="exact", show_default=True,
              type=click.Choice(["exact", "model"]),
              help="Render through the exact ray-traced lens, or its fitted OpenCV model.")
@click.option("--size", default="1280x960", show_default=True,
              help=f"Sensor size WIDTHxHEIGHT in pixels (6.45 um pixels), each side at most "
                   f"{MAX_SIDE_PX}.")
@click.option("--direction", default="random", show_default=True,
              help="Direction of the last zoom move before each step (sets the backlash side): "
                   "random, in, out, or one of in/out per step, comma-separated.")
@_testbed_options
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
def render(lens, tolerances, nominal, zoom_list, steps, views, pattern, noise, blur, defocus,
           bits, through, size, direction, wave, psf, airy_radius, halo, ellipse, jpeg_quality,
           seed, out):
    """Render calibration images through the (perturbed) zoom lens.

    Writes one subfolder per zoom step (OUT/zoom_XX/view_YY.png), OUT/steps.csv and
    OUT/dataset.json with every truth: camera per step, lens errors, poses and the true
    pixel position of every target point (OpenCV convention). With --wave each step's board
    waves (its surface is in dataset.json and the truth lies on it).
    """
    from .render.dataset import RenderOptions, check_render_inputs, render_dataset
    from .render.image import Radiometry

    lens_ = _load_lens(lens)
    _parse_target(pattern)
    if nominal and tolerances:
        raise click.UsageError("give --tolerances or --nominal, not both")
    tol = None if nominal else _load_tolerances(tolerances, lens_)
    if zoom_list:
        try:
            zoom = [float(z) for z in zoom_list.split(",")]
        except ValueError:
            raise click.BadParameter("must be numbers separated by commas",
                                     param_hint="--zoom") from None
        if any(not 0 <= z <= 1 for z in zoom):
            raise click.BadParameter("zoom values must lie in [0, 1]", param_hint="--zoom")
    else:
        zoom = list(np.linspace(0, 1, steps)) if steps > 1 else [0.0]
    from .camera import Sensor

    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{size!r} is not WIDTHxHEIGHT, e.g. 1280x960",
                                 param_hint="--size") from None
    if not (1 <= width <= MAX_SIDE_PX and 1 <= height <= MAX_SIDE_PX):
        raise click.BadParameter(f"{size}: each side must be 1 to {MAX_SIDE_PX} px",
                                 param_hint="--size")
    sensor = Sensor(width, height)
    if "," in direction:
        direction = [d.strip() for d in direction.split(",")]
        if len(direction) != len(zoom) or not set(direction) <= {"in", "out"}:
            raise click.BadParameter(f"give 'in' or 'out' for each of the {len(zoom)} steps",
                                     param_hint="--direction")
    elif direction not in ("random", "in", "out"):
        raise click.BadParameter("must be random, in, out or a comma-separated list",
                                 param_hint="--direction")
    optics = _make_optics(blur, lens_.f_number, defocus, psf, airy_radius, halo, ellipse)
    try:
        check_render_inputs(optics, sensor, views)
    except ValueError as exc:
        raise click.BadParameter(f"{exc}; reduce --blur or --defocus, or use a larger --size",
                                 param_hint="--blur / --defocus") from None
    radiometry = Radiometry(noise_sd=noise / 255.0, bits=int(bits))
    if jpeg_quality is not None and radiometry.bits != 8:
        raise click.BadParameter("JPEG holds 8-bit images only; use --bits 8",
                                 param_hint="--jpeg-quality")
    options = RenderOptions(optics=optics, radiometry=radiometry, seed=seed, sensor=sensor,
                            through=through, direction=direction, board_surface=wave or None,
                            jpeg_quality=jpeg_quality)
    _check_out_folder(out)
    try:
        with click.progressbar(length=len(zoom) * views, label="rendering",
                               file=sys.stderr) as bar:
            doc = render_dataset(lens_, tol, out, zoom, views, pattern, options,
                                 progress=bar.update)
    except ValueError as exc:  # found before any file is written
        raise click.BadParameter(f"{exc}; use a larger --size or fewer --views",
                                 param_hint="--size / --views") from None
    for st in doc["steps"]:
        cam = st["camera"]
        click.echo(f"  {st['step']}: zoom {st['zoom']:.3f}, EFL {st['efl_mm']:.2f} mm, "
                   f"fx {cam['fx']:.1f}, c ({cam['cx']:.2f}, {cam['cy']:.2f}) px, "
                   f"target {st['target']}, {len(st['views'])} views")
    click.echo(f"wrote {out}/steps.csv, {out}/dataset.json and {len(zoom) * views} images")


@main.command("render-sweep", epilog=EXIT_CODES)
@click.option("--fx", "fx_range", default="2300,23000", show_default=True,
              help="Focal length at the short and long end, MIN,MAX px (log-spaced steps).")
@click.option("--steps", default=7, show_default=True, type=click.IntRange(min=1))
@click.option("--views", default=10, show_default=True, type=click.IntRange(min=1),
              help="Views per zoom step.")
@click.option("--size", default="1280x720", show_default=True, help="Image WIDTHxHEIGHT, px.")
@click.option("--pattern", default="chessboard:22x15:20", show_default=True,
              help="The board (one physical size for every step).")
@click.option("--noise", default=2.0, show_default=True, type=click.FloatRange(min=0),
              help="Read noise, 1-sigma in 8-bit digital numbers (of 255).")
@click.option("--blur", default=0.8, show_default=True, type=click.FloatRange(min=0),
              help="Gaussian blur sigma, px (added to diffraction at f/2.8, 3 um pixels).")
@click.option("--supersample", default=3, show_default=True, type=click.IntRange(1, 8),
              help="Sub-samples per pixel side for non-Gaussian PSFs.")
@click.option("--pp-path", default="bow", show_default=True,
              type=click.Choice(["bow", "traced"]),
              help="Principal-point path: bow (30, -18 px, quadratic in log fx) or traced (the "
                   "ray-traced zoom lens laikin-10x with mechanical errors drawn from --seed).")
@click.option("--pp-span", default=40.0, show_default=True, type=click.FloatRange(min=0),
              help="traced: largest distance of the path from its short-end point, px.")
@click.option("--pp-runout", default=1.0, show_default=True, type=click.FloatRange(min=0),
              help="traced: cam-track run-out, times the default tolerance file's (0: none).")
@click.option("--lens", default=None,
              help="Distortion of a real zoom lens from lensfun (part of its maker and model, "
                   "e.g. 'Nikkor 80-400'), its focal range stretched over --fx; default: a "
                   "barrel fading towards the long end.")
@click.option("--lensfun", type=click.Path(exists=True),
              help="lensfun database (folder or XML) for --lens; default: the packaged extract.")
@click.option("--dist-centre", default="0,0", show_default=True,
              help="Centre of the distortion relative to the principal point, DX,DY px (OpenCV's "
                   "model, which calibration fits: 0,0).")
@_testbed_options
@click.option("--sharpen", help="The camera's sharpening, AMOUNT,SIGMA_PX: an unsharp mask "
                                "(1 + AMOUNT) I - AMOUNT G_SIGMA * I on each frame, e.g. 0.8,1.2.")
@click.option("--zoom-jitter", default=0.0, show_default=True, type=click.FloatRange(min=0),
              help="A zoom that does not return: each view's focal length scaled by e^s, s of "
                   "this sd (0.01: 1 %).")
@click.option("--retape-at", type=click.IntRange(min=1),
              help="Steps from this index (0-based) see the board re-taped: another waving "
                   "surface, a session column in steps.csv.")
@click.option("--rolling-shutter", default=0.0, show_default=True, type=click.FloatRange(min=0),
              help="A rolling shutter read out while the camera turns: each view's turn over "
                   "the readout, about the x and y axes, of this sd in rad (3e-4: 0.2 px at "
                   "fx 1500).")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--out", required=True, type=click.Path(file_okay=False), help="Output folder.")
def render_sweep(fx_range, steps, views, size, pattern, noise, blur, supersample, pp_path,
                 pp_span, pp_runout, lens, lensfun, dist_centre, wave, psf, airy_radius, halo,
                 ellipse, jpeg_quality, sharpen, zoom_jitter, retape_at, rolling_shutter, seed,
                 out):
    """Render a zoom sweep like a real session through pinhole + distortion cameras.

    fx log-spaced over --fx, a principal point drifting by tens of px (--pp-path), barrel
    distortion fading towards the long end (or a real lens's: --lens), tilts up to 40 degrees
    at the short end and
    near-fronto-parallel views at the long end. Writes OUT/fx_NNNNN/view_YY.png (or .jpg),
    OUT/steps.csv (zoom = fx) and OUT/truth.json (K, dist, board surface, principal-point
    path, poses and true points per step).
    """
    from .render.image import Radiometry
    from .render.sweep import CaptureEffects, SweepOptions, render_zoom_sweep

    _parse_target(pattern)
    fx = _two_numbers(fx_range, "--fx")
    if not 0 < fx[0] <= fx[1]:
        raise click.BadParameter("need 0 < MIN <= MAX", param_hint="--fx")
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise click.BadParameter("must be WIDTHxHEIGHT, e.g. 1280x720", param_hint="--size") \
            from None
    optics = _make_optics(blur, 2.8, 0.0, psf, airy_radius, halo, ellipse)
    lens_options = {}
    if lens is not None:
        lens_options = _lens_distortion(lens, lensfun, np.geomspace(fx[0], fx[1], steps),
                                        (width, height))
    elif lensfun is not None:
        raise click.BadParameter("only with --lens", param_hint="--lensfun")
    lens_options["dist_centre_px"] = _two_numbers(dist_centre, "--dist-centre")
    if retape_at is not None and retape_at >= steps:
        raise click.BadParameter(f"{retape_at}: the sweep's steps are 0-{steps - 1}",
                                 param_hint="--retape-at")
    try:
        effects = CaptureEffects(None if sharpen is None else _two_numbers(sharpen, "--sharpen"),
                                 zoom_jitter, retape_at, rolling_shutter)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--sharpen") from None
    options = SweepOptions(fx_range=fx, steps=steps, views=views, size=(width, height),
                           pattern=pattern, board_surface=wave or None,
                           jpeg_quality=jpeg_quality, seed=seed, optics=optics,
                           radiometry=Radiometry(noise_sd=noise / 255.0),
                           supersample=supersample, effects=effects)
    _check_out_folder(out)
    with click.progressbar(length=steps * views, label="rendering", file=sys.stderr) as bar:
        try:
            doc = render_zoom_sweep(out, options, progress=bar.update, pp_path=pp_path,
                                    pp_span_px=pp_span, pp_runout=pp_runout, **lens_options)
        except RuntimeError as exc:
            raise click.ClickException(str(exc)) from None
    for st in doc["steps"]:
        cam = st["camera"]
        click.echo(f"  {st['step']}: fx {cam['fx']:.1f}, c ({cam['cx']:.2f}, {cam['cy']:.2f}) px, "
                   f"k1 {cam['dist'][0]:.4f}, tilts up to {st['max_tilt_deg']:.1f} deg, "
                   f"{len(st['views'])} views")
    click.echo(f"wrote {out}/steps.csv, {out}/truth.json and {steps * views} images in "
               f"{doc['render_s']:.1f} s")


def _lens_distortion(name: str, database: str | None, fx: np.ndarray,
                     size: tuple[int, int]) -> dict:
    """:func:`~zoomcalib.study.lensfun.sweep_distortion` with its errors as BadParameter."""
    from .study.lensfun import sweep_distortion

    try:
        return sweep_distortion(name, fx, size, database)
    except (ValueError, OSError) as exc:
        raise click.BadParameter(str(exc), param_hint="--lens") from None


@main.command(epilog=EXIT_CODES)
@click.argument("folder", type=click.Path(exists=True, file_okay=False))
@click.option("--pattern", required=True, help="Target spec, e.g. chessboard:9x6:25.")
@click.option("--method", "methods", multiple=True,
              type=click.Choice(["sb", "classic", "circles", "charuco", "model"]),
              help="Detector (repeat to compare several); default: the target's usual one. "
                   "'model' refines OpenCV's points with our blurred-target model fit.")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(min=1),
              help="Parallel processes.")
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="Detections JSON (with several methods: one file per method, METHOD in "
                   "the name).")
def detect(folder, pattern, methods, workers, out):
    """Detect target points in the images of FOLDER (and its step subfolders).

    Writes {"pattern", "images": [{"file", "points", "ids", "error"}]}. When FOLDER (or its
    parent) holds a rendered dataset.json, prints each method's error against the truth:
    RMS, bias and noise, next to the Cramér-Rao bound of the renderer's image model.
    """
    from .detect import default_method, detect_folder, image_files, write_detections
    from .detect.report import dataset_crlb, error_report, load_truth, truth_names

    target = _parse_target(pattern)
    root = Path(folder)
    files = image_files(root) or sorted(p for sub in sorted(root.iterdir()) if sub.is_dir()
                                        for p in image_files(sub))
    if not files:
        raise click.BadParameter(f"{folder}: no images found", param_hint="FOLDER")
    methods = methods or (default_method(target),)
    if len(methods) == 1:
        _check_out_file(out)
    else:
        _check_out_file(str(Path(out).with_suffix("")),
                        suffixes=tuple(f"_{m}.json" for m in methods))
    try:
        found = load_truth(root)
    except ValueError as exc:  # a dataset.json that is not JSON
        raise click.BadParameter(str(exc), param_hint="FOLDER") from None
    names = truth_names(files, root, found[0] if found else root)
    failed_images = set()
    for method in methods:
        try:
            with _image_progress(len(files), method) as advance:
                dets = detect_folder(files, target, method, workers=workers, progress=advance)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--method") from None
        for d, name in zip(dets, names, strict=True):
            d.file = name
        path = out if len(methods) == 1 else str(Path(out).with_suffix("")) + f"_{method}.json"
        write_detections(path, dets, pattern)
        failed = [d for d in dets if d.error]
        click.echo(f"{method}: {len(dets) - len(failed)}/{len(dets)} images detected; "
                   f"wrote {path}")
        for d in failed:
            click.echo(f"  skipped {d.error}")
        failed_images |= {f"{d.file} ({method})" if len(methods) > 1 else d.file for d in failed}
        if found:
            rep = error_report(dets, found[1])
            if rep["n_points"]:
                bound = dataset_crlb(found[2], [d.file for d in dets if d.error is None])
                extra = f", bound {bound:.4f} px" if bound else ""
                click.echo(f"  vs truth ({rep['n_points']} points): RMS {rep['rms_px']:.4f} px, "
                           f"bias ({rep['bias_px'][0]:+.4f}, {rep['bias_px'][1]:+.4f}) px, "
                           f"noise {rep['noise_px']:.4f} px, max {rep['max_px']:.4f} px{extra}")
    what = "images" if len(methods) == 1 else "(image, method) pairs"
    if len(failed_images) == len(files) * len(methods):
        _exit_nothing(f"no target detected in any of the {len(files)} images")
    _exit_if_partial(sorted(failed_images),
                     f"{len(failed_images)} of {len(files) * len(methods)} {what} failed")


@main.command(epilog=EXIT_CODES)
@click.argument("folder", type=click.Path(exists=True, file_okay=False))
@click.option("--pattern", required=True, help="Target spec, e.g. chessboard:9x6:25.")
@click.option("--backend", type=click.Choice(["opencv", "bundle", "both"]),
              help="Per-step calibration: cv2.calibrateCameraExtended, our photogrammetric "
                   "bundle (refines the target points), or both on the same detections. "
                   "Default: opencv beside the zoom-wide adjustment; both with --per-step or "
                   "for a single image set.")
@click.option("--per-step", is_flag=True,
              help="Calibrate each zoom step on its own only (no zoom-wide adjustment); the "
                   "zoom table then comes from the per-step backends.")
@click.option("--pp-model", default="angle2", show_default=True,
              type=click.Choice(["angle2", "prior2", "select"]),
              help="Zoom-wide: how cx, cy follow the zoom. angle2: a second-difference prior "
                   "in log fx of REML strength on the angle (c - c0) / fx, c0 free; prior2: "
                   "that prior in px; select: the px prior, a third-difference prior or a "
                   "polynomial of degree 1-3 in log fx, chosen by held-out steps.")
@click.option("--cross-validate", is_flag=True,
              help="Also calibrate the even and the odd images of every step apart and report "
                   "their differences in combined sigmas (flags |z| > 3).")
@click.option("--residual-budget", is_flag=True,
              help="Also say per step and per capture session what the residual is made of: "
                   "lens terms, board shape, a focal length per view and a readout shift, "
                   "each judged on held-out corners (calibration.md, 'Residual budget').")
@click.option("--board-shape", default="print", show_default=True,
              type=click.Choice(["print", "points", "modes"]),
              help="Zoom-wide: the board of each capture session, a smooth surface of degree 4 "
                   "plus a height for every point (the ripples of a paper board), and the "
                   "print's in-plane shape, shared by the sessions, where a test says it pays "
                   "(print); without the print's shape (points); or the smooth surface alone "
                   "(modes).")
@click.option("--model", default="standard", show_default=True,
              type=click.Choice(["standard", "rational"]),
              help="Distortion model: k1, k2, p1, p2, k3, or OpenCV's rational k1..k6, p1, p2.")
@click.option("--fix", "fixed", multiple=True,
              type=click.Choice(["principal-point", "aspect", "k1", "k2", "k3", "tangential"]),
              help="Hold an intrinsic fixed (repeat for more): the principal point at the "
                   "image centre, fy/fx at 1, k1, k2, k3 or p1, p2 at 0. In the zoom-wide "
                   "adjustment and the OpenCV fits; not with the bundle backend.")
@click.option("--method", type=click.Choice(["sb", "classic", "circles", "charuco", "model"]),
              help="Detector; default: the target's usual one.")
@click.option("--workers", default=0, show_default=True, type=click.IntRange(min=0),
              help="Processes for detection, the zoom-wide per-step fits and the residual "
                   "budget (0: all cores).")
@click.option("--out", default="zoomcalib-calibration", show_default=True,
              type=click.Path(file_okay=False), help="Output folder.")
@click.option("--grid-points", default=50, show_default=True, type=click.IntRange(min=2),
              help="Zoom values of OUT/zoom_model_grid.csv, spread over the calibrated range.")
@click.option("--camera-name", help="camera_name of the ROS files in OUT/ros (default: "
                                    "FOLDER's name).")
@click.option("--no-report", is_flag=True, help="Do not write OUT/report.html.")
@click.option("--report-distance", type=click.FloatRange(min=0, min_open=True),
              help="Distance (mm) of the report's projection-uncertainty maps; default: each "
                   "step's median board distance.")
@click.option("--report-image", "report_images", multiple=True, metavar="[STEP/]NAME",
              help="Also draw this image's detected corners and the fit's projections in the "
                   "report (each step's image of the largest error is always drawn); "
                   "repeatable.")
def calibrate(folder, pattern, backend, per_step, pp_model, cross_validate, residual_budget,
              board_shape, model, fixed, method, workers, out, grid_points, camera_name,
              no_report, report_distance, report_images):
    """Calibrate FOLDER: one calibration, or one per zoom-step subfolder.

    The zoom of each step comes from FOLDER/steps.csv, else the number in the folder name,
    else the images' EXIF focal length. A zoom set is calibrated by one zoom-wide adjustment
    (every step together: one board, a smoothness prior across zoom; --per-step turns it off)
    beside per-step OpenCV. Writes OUT/calibration.json and .yml, per step OpenCV, ROS and
    mrcal files (OUT/opencv, OUT/ros, OUT/mrcal), and for zoom sets OUT/zoom_calibration.csv,
    OUT/zoom_model.json, OUT/zoom_model_grid.csv and figures, and OUT/report.html (every
    figure in one page; --no-report skips it). Detections are cached in
    OUT/detections/, so a rerun (or an interrupted run) does not detect unchanged images
    again. Exit code 3: a partial result (a step dropped, a backend the zoom table needs failed
    on a step, or an image that could not be read or searched; a frame without the whole
    target in view is left aside with a note).
    """
    import os

    from .calibrate.run import CalibrateOptions, calibrate_folder
    from .detect import image_files

    _parse_target(pattern)
    from .calibrate.stepfolders import zoom_steps

    try:
        steps = zoom_steps(folder)
    except (ValueError, FileNotFoundError) as exc:
        raise click.BadParameter(str(exc), param_hint="FOLDER") from None
    per_step = per_step or len(steps) < 2  # one set of images: nothing to adjust zoom-wide
    backend = backend or ("both" if per_step and not fixed else "opencv")
    backends = ("opencv", "bundle") if backend == "both" else (backend,)
    if fixed and backend != "opencv":
        raise click.BadParameter(f"the {backend} backend estimates every intrinsic; use "
                                 "--backend opencv with --fix", param_hint="--fix")
    if camera_name is not None and not re.fullmatch(r"[A-Za-z0-9_]+", camera_name):
        raise click.BadParameter(f"{camera_name!r}: ROS camera names are letters, digits and _",
                                 param_hint="--camera-name")
    for image in report_images:
        step_name, _, name = image.rpartition("/")
        if not any((d / name).is_file() for s, d, _, _ in steps if step_name in ("", s)):
            raise click.BadParameter(
                f"{image}: no such image in {'step ' + step_name if step_name else 'any step'}"
                f" of {folder}", param_hint="--report-image")
    _check_out_folder(out)
    n_images = sum(len(image_files(d)) for _, d, _, _ in steps)
    messages = []
    try:
        with _image_progress(n_images, "detecting") as advance:
            options = CalibrateOptions(
                model=model, method=method, zoom_wide=not per_step,
                cross_validate=cross_validate, pp_model=pp_model, grid_points=grid_points,
                camera_name=camera_name, report=not no_report, report_distance=report_distance,
                report_images=tuple(report_images), residual_budget=residual_budget,
                board_shape=board_shape, fixed=tuple(fixed))
            run = calibrate_folder(folder, pattern, out, backends, options,
                                   workers=workers or os.cpu_count() or 1, progress=advance,
                                   log=messages.append)
    except KeyboardInterrupt:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second press cannot cut the exit
        for m in messages:
            click.echo(m)
        click.echo(f"\ninterrupted: the detections finished so far are kept in {out}/detections;"
                   " the same command resumes from them", err=True)
        sys.exit(130)
    for m in messages:
        click.echo(m)
    _print_calibration(run)
    if run.holdout:
        click.echo("zoom model, held-out interpolation error (RMS): " + ", ".join(
            f"{k} {v:.3g}" for k, v in run.holdout.items() if k in ("fx", "fy", "cx", "cy")))
        for flag in run.zoom_model.flags():
            click.echo(f"  flagged: {flag}")
    if not run.results:
        _exit_nothing("no step could be calibrated")
    click.echo(f"wrote {len(run.files)} files to {out}")
    # partial (exit 3): a step dropped, a backend the table needs failed, an image skipped or
    # left out for its size; a per-step backend failing on a step the zoom-wide adjustment
    # calibrated is only reported
    problems = ([f"step {s}" for s in run.dropped]
                + [f"step {s} {', '.join(b)}" for s, b in run.backend_failures.items()]
                + _calibration_problems([], messages)
                + [f"image {name}" if s == "." else f"image {s}/{name}"
                   for s, names in run.left_out.items() for name in names]
                + [f"{what} not written" for what in run.not_written])
    _exit_if_partial(problems, "not calibrated, skipped or not written" if run.not_written
                     else "not calibrated or skipped")


def _print_calibration(run) -> None:
    """The per-step table (table backend marked *), cross-validation and flags."""
    nan = float("nan")
    click.echo(f"{'step':>12s} {'zoom':>7s} {'backend':>10s} {'fx':>10s} {'fy':>10s} "
               f"{'cx':>9s} {'cy':>9s} {'sd_cx':>7s} {'sd_cy':>7s} {'rms':>7s} views")
    for step, res in run.results.items():
        z = run.zoom.get(step)
        for name, r in res.items():
            mark = "*" if run.table_backend.get(step) == name else " "
            click.echo(f"{step:>12s} {'' if z is None else f'{z:7.3f}':>7s} {name:>9s}{mark} "
                       f"{r.fx:10.2f} {r.fy:10.2f} {r.cx:9.2f} {r.cy:9.2f} "
                       f"{r.sd.get('cx', nan):7.3f} {r.sd.get('cy', nan):7.3f} "
                       f"{r.rms_px:7.3f} {len(r.per_view_rms_px)}")
    click.echo("* = the zoom table's row")
    cv = run.cross_validation
    if cv is not None:
        click.echo(f"cross-validation ({cv.backend}; even vs odd images, difference / combined "
                   "sigma):")
        for step, z in cv.z.items():
            proj = cv.projection.get(step, {})
            click.echo(f"{step:>12s} " + " ".join(f"z_{q} {v:+6.2f}" for q, v in z.items())
                       + (f"  projection z {proj['z_rms']:.2f} (up to "
                          f"{proj['difference_max_px']:.2f} px apart)" if "z_rms" in proj
                          else f"  projection: {proj.get('error', 'not compared')}"))
        for step, why in cv.failures.items():
            click.echo(f"{step:>12s} halves not calibrated: {why}")
    for step, res in run.results.items():
        for name, r in res.items():
            if not r.converged and run.table_backend.get(step) != name:  # the table's: flagged
                click.echo(f"warning: step {step} ({name}) did not converge "
                           f"({r.info.get('stop_reason', 'no reason reported')})")
    actions: dict[str, list[str]] = {}  # each action once, with the steps that need it
    for step, records in run.flag_records.items():
        click.echo(f"FLAGGED step {step} ({records[0].severity}): "
                   + "; ".join(f"{f.text} [{f.severity}]" for f in records))
        for f in records:
            if step not in actions.setdefault(f.action, []):
                actions[f.action].append(step)
    for action, steps in actions.items():
        click.echo(f"  to do ({', '.join(steps)}): {action}")
    _print_status(run)


def _print_status(run) -> None:
    """Each step's status, and for the others than ``ok`` the reasons and what to do."""
    if not run.status:
        return
    click.echo("status: " + ", ".join(f"{s} {st.status}" for s, st in run.status.items()))
    for step, st in run.status.items():
        if st.status != "ok":
            click.echo(f"{st.status.upper()} step {step}: " + "; ".join(st.reasons))
            click.echo("  to do: " + "; ".join(st.remedies))
            if st.advice:
                click.echo("  capture advice: " + st.advice["text"])


@main.command(epilog=EXIT_CODES)
@click.option("--lens", default="laikin-10x", show_default=True, help=LENS_HELP)
@click.option("--tolerances", type=click.Path(dir_okay=False),
              help="Mechanical tolerance file; default: the built-in tolerances.")
@click.option("--tolerance-scale", default=1.0, show_default=True,
              type=click.FloatRange(min=0), help="Multiply every mechanical error (0: none).")
@click.option("--steps", type=click.IntRange(min=1), help="Zoom steps (default 5; quick 3).")
@click.option("--quick", is_flag=True,
              help="Reduced study (3 steps, one noise level, 4 sets of 6 views): every stage "
                   "on real rendered images, in a few minutes.")
@click.option("--seeds", type=click.IntRange(min=2), help="Calibration sets per step and noise.")
@click.option("--views", type=click.IntRange(min=3), help="Views per calibration set.")
@click.option("--noise", help="Comma-separated noise levels in DN (of 255), e.g. 1,2,4.")
@click.option("--backend", default="both", show_default=True,
              type=click.Choice(["opencv", "bundle", "both"]))
@click.option("--workers", default=0, show_default=True, type=click.IntRange(min=0),
              help="Local worker processes (0: all cores).")
@click.option("--scheduler", help="Dask scheduler address (tcp://HOST:PORT): run the Monte Carlo "
                                  "on that cluster (needs zoomcalib[distributed]).")
@click.option("--lensfun", type=click.Path(exists=True),
              help="A lensfun database (folder or XML) for the distortion claim; default: the "
                   "extract shipped with zoomcalib.")
@click.option("--psf", default="gaussian", show_default=True,
              type=click.Choice(["gaussian", "airy", "halo", "elliptical"]),
              help="PSF shape of the rendered images (the renderer's default shape "
                   "parameters); the model detector assumes a Gaussian. airy and halo are "
                   "rendered supersampled, several times slower.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0))
@click.option("--out", default="zoomcalib-study", show_default=True,
              type=click.Path(file_okay=False), help="Output folder.")
def study(lens, tolerances, tolerance_scale, steps, quick, seeds, views, noise, backend,
          workers, scheduler, lensfun, psf, seed, out):
    """The paper's study: detection error against mechanical error across the zoom range.

    Renders calibration sets through the aligned lens at each zoom step, detects them with
    OpenCV's cornerSubPix and with our model fit (at the Cramér-Rao bound), calibrates with
    both backends, repeats over seeds and noise levels, and compares the scatter of the
    principal point with the scatter the mechanical errors cause. Writes OUT/report.md and
    OUT/report.html with figures, the CSV tables behind every number, and the verdict per
    zoom step. Finished tasks are kept in OUT/tasks/: an interrupted study resumes.
    """
    import os
    import shlex

    from .study.paper import StudyConfig
    from .study.run import detection_tasks, run_study

    lens_ = _load_lens(lens)
    _load_tolerances(tolerances, lens_)
    _check_out_folder(out)
    overrides = {"lens": lens, "tolerances": tolerances, "tolerance_scale": tolerance_scale,
                 "seed": seed, "lensfun": lensfun, "psf": psf,
                 "backends": ("opencv", "bundle") if backend == "both" else (backend,)}
    for name, value in (("steps", steps), ("seeds", seeds), ("views", views)):
        if value is not None:
            overrides[name] = value
    if noise:
        try:
            overrides["noise_dn"] = tuple(float(v) for v in noise.split(","))
        except ValueError:
            raise click.BadParameter("must be numbers separated by commas",
                                     param_hint="--noise") from None
        if not all(0 <= v <= 255 for v in overrides["noise_dn"]):
            raise click.BadParameter(f"{noise}: each level must be a number in [0, 255] DN",
                                     param_hint="--noise")
    config = StudyConfig.quick(**overrides) if quick else StudyConfig(**overrides)
    n_tasks = len(detection_tasks(config))
    command = "zoomcalib " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    with click.progressbar(length=n_tasks, label="calibration sets", file=sys.stderr) as bar:
        res = run_study(config, out, workers=workers or os.cpu_count() or 1,
                        scheduler=scheduler, command=command, progress=bar)
    for f in res["failures"]:
        click.echo(f"failed: {f}")
    click.echo(f"{'zoom':>5s} {'EFL':>6s} {'detector':>8s} {'backend':>7s} {'s_mech':>7s} "
               f"{'s_det':>7s} {'ratio':>6s}  verdict")
    ref = sorted(config.noise_dn)[len(config.noise_dn) // 2]
    for c in res["comparison"]:
        if c["noise_dn"] == ref:
            click.echo(f"{c['zoom']:5.2f} {c['efl_mm']:6.1f} {c['detector']:>8s} "
                       f"{c['backend']:>7s} {c['s_mech_px']:7.3f} {c['s_det_px']:7.3f} "
                       f"{c['ratio']:6.2f}  {c['verdict']}")
    t = res["timing"]
    click.echo(f"time: render {t['render_s']:.0f} s, detection {t['detect_s']:.0f} s, "
               f"calibration {t['calibrate_s']:.0f} s (summed over workers), mechanics "
               f"{t['mechanics_s']:.1f} s, wall {t['wall_s']:.0f} s")
    click.echo(f"wrote {out}/report.md, {out}/report.html and the CSV tables")
    if len(res["failures"]) == n_tasks:
        _exit_nothing(f"all {n_tasks} calibration sets failed")
    _exit_if_partial([f.split(":", 1)[0] for f in res["failures"]],
                     f"{len(res['failures'])} of {n_tasks} calibration sets failed")


@main.command(epilog=EXIT_CODES)
@click.argument("input_path", metavar="INPUT", type=click.Path(exists=True))
@click.option("--lens", default="laikin-10x", show_default=True,
              help=LENS_HELP + " 'none': no lens model; the baseline is a principal-point path "
                   "smooth in log focal length and only the causes that need no optics are "
                   "tested.")
@click.option("--pixel-pitch", default="0.00645", show_default=True,
              help="Sensor pixel pitch in mm, or 'auto' to fit it (a scale between the "
                   "measured px and the lens's mm).")
@click.option("--tolerances", type=click.Path(dir_okay=False),
              help="Tolerance file (YAML/JSON) for the random-play scatter; default: built-in.")
@click.option("--pattern", help="Target spec, needed when INPUT is a folder of zoom-step images.")
@click.option("--backend", default="opencv", show_default=True,
              type=click.Choice(["opencv", "bundle", "both"]),
              help="Calibration backend for an image folder (the bundle's values are used when "
                   "it ran).")
@click.option("--workers", default=0, type=click.IntRange(min=0),
              help="Detection processes for an image folder (0: all cores).")
@click.option("--out", default="zoomcalib-diagnose", show_default=True,
              type=click.Path(file_okay=False), help="Output folder.")
@click.option("--no-report", is_flag=True,
              help="For an image folder: do not write OUT/calibration/report.html.")
def diagnose(input_path, lens, pixel_pitch, tolerances, pattern, backend, workers, out,
             no_report):
    """Show what the simulation gets wrong on measured per-zoom data, and name the cause.

    INPUT is a zoom_calibration.csv (needs zoom, fx, fy, cx, cy; uses sd_cx, sd_cy, direction,
    sequence, focus, temperature when present) or a folder of zoom-step images, calibrated
    first. Each row's lens state comes from its measured fx through the lens's EFL curve, so
    the zoom column may be in any unit.

    The paper's model (sensor offset, barrel-locked decentre and tilt of each moving group) is
    fitted with the noise scales estimated from the table, then causes (axis_tilt, backlash,
    thermal_drift, cam_harmonic, static_decenter, focus_shift) are selected together: a cause
    enters when it beats the model by BIC and predicts held-out zoom steps better. The
    selected model is then checked: when it leaves structure over zoom, direction or capture
    order, the answer is 'unexplained' with what remains; with no cause, 'none'. Writes
    OUT/diagnosis.json, OUT/report.md, OUT/path.png and OUT/residuals.png.
    """
    import os

    from .diagnose.model import FocalRangeError
    from .diagnose.run import diagnose_input

    lens_rx = None if lens.strip().lower() == "none" else _load_lens(lens)
    if lens_rx is None and tolerances:
        raise click.BadParameter("a tolerance file needs a lens model (not --lens none)",
                                 param_hint="--tolerances")
    tol = _load_tolerances(tolerances, lens_rx) if tolerances else None
    if pixel_pitch != "auto":
        try:
            pixel_pitch = float(pixel_pitch)
        except ValueError:
            raise click.BadParameter(f"{pixel_pitch!r} is neither a number (mm) nor 'auto'",
                                     param_hint="--pixel-pitch") from None
        if not pixel_pitch > 0:
            raise click.BadParameter("must be positive", param_hint="--pixel-pitch")
    if os.path.isdir(input_path) and pattern:
        _parse_target(pattern)
    _check_out_folder(out)
    backends = ("opencv", "bundle") if backend == "both" else (backend,)
    n_images = 0
    if os.path.isdir(input_path):
        from .calibrate.stepfolders import zoom_steps
        from .detect import image_files

        try:
            n_images = sum(len(image_files(d)) for _, d, _, _ in zoom_steps(input_path))
        except (ValueError, FileNotFoundError) as exc:
            raise click.BadParameter(str(exc), param_hint="INPUT") from None
    messages = []
    try:
        with click.progressbar(length=n_images, label="detecting", file=sys.stderr,
                               hidden=n_images == 0) as bar:
            run = diagnose_input(input_path, out, lens_rx, pixel_pitch, tol, pattern, backends,
                                 workers or os.cpu_count() or 1, bar.update, messages.append,
                                 report=not no_report)
    except (FocalRangeError, ValueError, FileNotFoundError) as exc:
        raise click.ClickException(str(exc)) from None
    for m in messages:
        click.echo(m)
    d = run.diagnosis
    doc = d.to_dict()
    if d.pitch_fit:
        click.echo(f"pixel pitch fitted: {d.pitch_mm:.5g} +- {d.pitch_fit['sd_mm']:.2g} mm"
                   + (" (at an end of the admissible range: not determined by the data; "
                      f"the lens {d.response.lens.name!r} may not be this camera's, and the "
                      "diagnosis below assumes it is)"
                      if d.pitch_fit["at_range_end"] else ""))
    _print_diagnosis(d, doc)
    click.echo(f"wrote {out}/diagnosis.json, report.md, path.png, residuals.png")
    _exit_if_partial(_calibration_problems(run.failures, messages), "not calibrated or skipped")


def _print_diagnosis(d, doc: dict) -> None:
    """The models' table, the selected causes, the fit check and the noise, in a few lines."""
    b = doc["baseline"]
    click.echo(f"{'model':<28s} {'rms px':>8s} {'cv_rms px':>10s} {'cv_norm':>8s}")
    click.echo(f"{'baseline':<28s} {b['rms_px']:8.3f} {b['cv_rms_px']:10.3f} "
               f"{b['cv_norm_rms']:8.2f}")
    for c in doc["candidates"]:
        click.echo(f"{'+ ' + c['cause']:<28s} {c['rms_px']:8.3f} {c['cv_rms_px']:10.3f} "
                   f"{c['cv_norm_rms']:8.2f}  dBIC {c['delta_bic']:7.1f}")
    for s in doc["skipped"]:
        click.echo(f"not tested: {s['cause']} ({s['reason']})")
    noise = doc["noise"]
    if "sigma_scale" in noise:
        click.echo(f"noise: table sigmas x{noise['sigma_scale']:.2f}, play "
                   f"x{noise['play_scale']:.2f} ({noise['play_shape']})")
    names = ", ".join(f"{c['cause']} ({c['variant']})" for c in doc["causes"])
    gain = (f"; held-out gain {doc['gain']['cv_norm_ratio']:.2f}x (sigma-normalised), "
            f"{doc['gain']['cv_rms_ratio']:.2f}x (px)" if doc["causes"] else "")
    check = doc["explained"]
    if d.cause == "unexplained":
        click.echo(f"cause: unexplained: {check['remaining']}"
                   + (f"; improving but not explaining: {names}" if names else ""))
    else:
        click.echo(f"cause: {d.cause}" + (f"; selected: {names}" if names else "") + gain)
        if check["explained"] is None:
            click.echo("the fit could not be checked (no repeated settings, sigmas or lens "
                       "model)")
    if doc["ambiguous_with"]:
        click.echo(f"not told apart from: {', '.join(doc['ambiguous_with'])}")
    for c in doc["causes"]:
        if c.get("evidence"):
            click.echo(f"{c['cause']} named by {c['evidence']}")
    click.echo(f"group terms: {doc['group_columns']}")


if __name__ == "__main__":
    main()
