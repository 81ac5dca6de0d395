"""The zoom model of a calibrate output folder: its held-out check, and how far its camera at
each step's zoom lies from the step's own table row, beside curves refitted to the table.

    python benchmarks/bench_zoom_path.py OUT
    python benchmarks/bench_zoom_path.py --wiener 8

``OUT`` is a ``zoomcalib calibrate`` output folder of a zoom set (``zoom_model.json`` and
``zoom_calibration.csv``). Prints, per parameter of the zoom model, its held-out steps (each
predicted from the others; interior steps only): RMS error, RMS z and the largest |z|. Then,
per step, the largest displacement over a 9x5 grid of image points between the step's row and
the model's camera at the step's zoom (a pixel of the row's camera, undistorted to its ray,
projected by the model's), for the model written to ``zoom_model.json`` and for curves refitted
to the table's rows (:meth:`zoomcalib.zoom.ZoomModel.from_table`, the model of a per-step
table). Last, the model's 1-sigma of cx and cy halfway between neighbouring steps.

``--wiener SEEDS``: how honest the path between the steps is, on paths the model does not
share. Per seed, 150 integrated Wiener processes (on a fine grid) seen at 10 irregular steps
with noise 1e-3, ``tau`` by REML from those; each predicted at a random point between two
steps by :func:`zoomcalib.calibrate.zoommodel.path_between` (the prior read as the continuous
process it discretises) and, as the peer, by the difference prior itself with the new point put
among the steps (its conditional given all the steps). Prints the RMS z, a median-based scale
(``median |z| / 0.6745``) and the fraction beyond 3, 1 when honest.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import cv2
import numpy as np

from zoomcalib.calibrate.io import read_zoom_table
from zoomcalib.calibrate.zoommodel import divided_difference, path_between, prior_strength
from zoomcalib.calibrate.zoompath import PosteriorZoomModel
from zoomcalib.render.pp_path import wiener_draw
from zoomcalib.zoom import ZoomModel

_DIST = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def _camera(values: dict) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[values["fx"], 0, values["cx"]], [0, values["fy"], values["cy"]], [0, 0, 1]])
    n = 8 if any(values.get(k) not in (None, 0.0) for k in _DIST[5:]) else 5
    return K, np.array([float(values.get(k) or 0.0) for k in _DIST[:n]])


def displacement(row: dict, lens, size: tuple[int, int]) -> float:
    """Largest displacement (px) over a 9x5 grid of image points from the row's camera to
    ``lens`` (a ZoomIntrinsics)."""
    w, h = size
    grid = np.stack(np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 5)), -1)
    pix = grid.reshape(-1, 1, 2).astype(float)
    K, d = _camera(row)
    rays = cv2.undistortPoints(pix, K, d).reshape(-1, 2)
    Km, dm = _camera(lens.values | {"fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy})
    obj = np.column_stack([rays, np.ones(len(rays))])
    out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), Km, dm)
    return float(np.max(np.linalg.norm(out.reshape(-1, 2) - pix.reshape(-1, 2), axis=1)))


def grid_conditional(u: np.ndarray, u_new: float, tau: float) -> tuple[np.ndarray, float]:
    """The peer: the second-difference prior with ``u_new`` put among the steps, its
    conditional given the steps' values (weights, variance)."""
    grid = np.append(u, u_new)
    rank = np.argsort(grid)
    D = np.zeros((len(grid) - 2, len(grid)))
    D[:, rank] = divided_difference(grid[rank], 2)
    col = D[:, -1]
    return -(col @ D[:, :-1]) / (col @ col), tau**2 / float(col @ col)


def wiener(seeds: int, reps: int = 150) -> None:
    sd = 1e-3
    print(f"{'seed':>4} | {'path_between: rms z':>20} {'scale':>6} {'>3':>6} | "
          f"{'grid prior: rms z':>18} {'scale':>6} {'>3':>6}")
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        z = np.empty((reps, 2))
        for r in range(reps):
            u, v, u_new, truth = wiener_draw(rng, noise=sd)
            tau, _ = prior_strength(v, np.full(len(u), sd), u)
            for k, (lam, var) in enumerate((path_between(u, u_new, 2, tau),
                                            grid_conditional(u, u_new, tau))):
                z[r, k] = (lam @ v - truth) / np.sqrt(var + lam @ lam * sd**2)
        cells = [f"{np.sqrt(np.mean(c**2)):20.2f} {np.median(np.abs(c)) / 0.6745:6.2f} "
                 f"{np.mean(np.abs(c) > 3):6.3f}" for c in z.T]
        print(f"{seed:4d} | {cells[0]} | {cells[1][2:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--wiener", type=int, default=0, metavar="SEEDS")
    ap.add_argument("--size", type=int, nargs=2, default=None,
                    help="image width and height, px (default: from OUT/ros)")
    args = ap.parse_args()
    if args.wiener:
        wiener(args.wiener)
    if args.out is None:
        return
    doc = json.loads((args.out / "zoom_model.json").read_text())
    rows = [r for r in read_zoom_table(args.out / "zoom_calibration.csv")
            if r.get("status") != "unusable"]
    size = tuple(args.size) if args.size else _image_size(args.out)
    if doc["model"].get("kind") != "posterior":
        raise SystemExit(f"{args.out}/zoom_model.json is not a posterior zoom model "
                         f"(kind {doc['model'].get('kind')!r})")
    model = PosteriorZoomModel.from_dict(doc["model"])
    print(f"zoom model of {args.out}: {len(model.steps)} steps, kind {model.kind}")
    print(f"{'param':>6} {'n':>3} {'rms error':>11} {'rms z':>6} {'max |z|':>8}  at")
    for name, d in model.holdout_error(details=True).items():
        z = d["z"][np.isfinite(d["z"])]
        if not len(z):
            continue
        worst = int(np.nanargmax(np.abs(d["z"])))
        print(f"{name:>6} {len(z):3d} {d['rms']:11.4g} {np.sqrt(np.mean(z**2)):6.2f} "
              f"{abs(d['z'][worst]):8.2f}  {d['steps'][worst]}")
    for flag in model.flags():
        print(f"  flag: {flag}")
    table = ZoomModel.from_table([{k: v for k, v in r.items() if not k.startswith(("sd_k",
                                                                                  "sd_p"))}
                                  for r in rows])
    print("\nlargest image displacement at each step's zoom, px (row -> model)")
    print(f"{'step':>10} {'zoom':>6} {'posterior':>10} {'table fit':>10}")
    for r in rows:
        print(f"{r['step']:>10} {r['zoom']:6g} "
              f"{displacement(r, model.at(r['zoom']), size):10.3g} "
              f"{displacement(r, table.at(r['zoom']), size):10.3g}")
    mid = 0.5 * (model.zoom[1:] + model.zoom[:-1])
    pred = model.predict(mid)
    print("\n1-sigma halfway between the steps (posterior model), px")
    print("  zoom " + " ".join(f"{z:7g}" for z in mid))
    for q in ("cx", "cy"):
        if q in pred:
            print(f"  {q:>4} " + " ".join(f"{v:7.3g}" for v in pred[f"sd_{q}"]))


def _image_size(out: Path) -> tuple[int, int]:
    """(width, height) from the first ROS file of ``out/ros``."""
    for path in sorted((out / "ros").glob("*.yaml")):
        text = path.read_text()
        got = {k: int(v) for k, v in re.findall(r"^(image_width|image_height): (\d+)$", text,
                                                  re.MULTILINE)}
        if len(got) == 2:
            return got["image_width"], got["image_height"]
    raise SystemExit(f"{out}/ros holds no camera file with the image size: pass --size W H")


if __name__ == "__main__":
    main()
