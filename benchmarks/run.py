"""Run every benchmark and print one table: ``python benchmarks/run.py [--quick]``.

Each row times our code and, where there is one, a peer in the same run (machines here are shared
and noisy, so the ratio is the number to read). Rows whose peer is not installed say so.

- paraxial principal point: lens states per second (zoom states x error draws), peer: the exact
  tracer on the same states;
- exact tracer: ray-surface intersections per second through laikin-10x with every group
  misaligned, peer: optiland (``pip install optiland``) tracing the same rays;
- optiland lens states: building and tracing the chief ray of misaligned lens states in optiland,
  against our exact tracer on the same states.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "fixtures"))

from zoomcalib.optics.cam import solve_gaps  # noqa: E402
from zoomcalib.optics.misalignment import Misalignment  # noqa: E402
from zoomcalib.optics.paraxial import chief_ray_image  # noqa: E402
from zoomcalib.optics.prescription import load_prescription  # noqa: E402
from zoomcalib.optics.raytrace import DEFAULT_Z_START, chief_ray_image_real, trace_real  # noqa: E402


def best_of(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _draws(rng, shape, n_groups):
    return Misalignment(rng.normal(0, 0.01, shape + (n_groups, 2)),
                        rng.normal(0, 3e-4, shape + (n_groups, 2)))


def bench_paraxial(lens, quick):
    n_zoom, n_draw = 10, (10_000 if quick else 100_000)
    th = lens.thickness_at(solve_gaps(lens, np.linspace(0, 1, n_zoom)))[:, None, :]
    mis = _draws(np.random.default_rng(0), (n_zoom, n_draw), len(lens.groups))
    t = best_of(lambda: chief_ray_image(lens, th, mis))
    ours = n_zoom * n_draw / t
    sub = Misalignment(mis.decenter[:, :2000], mis.tilt[:, :2000])
    t_ex = best_of(lambda: chief_ray_image_real(lens, th, sub), repeat=1)
    peer = n_zoom * 2000 / t_ex
    return ("paraxial principal point", "lens states/s", ours, "exact tracer (same states)",
            peer, ">= 1e6/s")


def _rays(rng, n):
    p = np.zeros((n, 3))
    p[:, :2] = rng.uniform(-3, 3, (n, 2))
    p[:, 2] = DEFAULT_Z_START
    d = np.concatenate([rng.normal(0, 0.02, (n, 2)), np.ones((n, 1))], axis=1)
    return p, d / np.linalg.norm(d, axis=1, keepdims=True)


def bench_exact(lens, quick):
    n = 50_000 if quick else 400_000
    rng = np.random.default_rng(1)
    th = lens.thickness_at(solve_gaps(lens, [0.4]))[0]
    mis = _draws(rng, (), len(lens.groups))
    p, d = _rays(rng, n)
    t = best_of(lambda: trace_real(lens, th, p, d, mis))
    ours = n * lens.n_surfaces / t
    peer = None
    try:
        import make_optiland_fixture as ol

        gaps = list(solve_gaps(lens, [0.4])[0])
        doc = _lens_doc(lens)
        pert = {g: {"decenter_mm": list(mis.decenter[i]), "tilt_rad": list(mis.tilt[i])}
                for i, g in enumerate(lens.group_names)}
        _, z_img = ol.nominal_layout(doc, gaps)
        optic = ol.build_optic(ol.surface_poses(doc, gaps, pert), z_img)
        rays = [(tuple(pi - [0, 0, DEFAULT_Z_START - ol.Z_START]), tuple(di))
                for pi, di in zip(p[:20000], d[:20000], strict=True)]
        # optiland starts rays on its dummy plane; move ours there along z (same rays)
        t_ol = best_of(lambda: ol.trace_rays(optic, rays), repeat=2)
        peer = 20000 * lens.n_surfaces / t_ol
    except ImportError:
        pass
    return ("exact tracer", "ray-surface intersections/s", ours, "optiland", peer, ">= 2e6/s")


def _lens_doc(lens):
    import json
    from importlib import resources

    return json.loads((resources.files("zoomcalib.optics") / "lenses" /
                       f"{lens.name}.json").read_text())


def bench_optiland_states(lens, quick):
    try:
        import make_optiland_fixture as ol
    except ImportError:
        return ("lens states vs optiland", "lens states/s", None, "optiland (not installed)",
                None, "")
    n = 10 if quick else 40
    rng = np.random.default_rng(2)
    gaps = list(solve_gaps(lens, [0.4])[0])
    th = lens.thickness_at(np.array(gaps))
    mis = _draws(rng, (n,), len(lens.groups))
    doc = _lens_doc(lens)

    def run_optiland():
        for i in range(n):
            pert = {g: {"decenter_mm": list(mis.decenter[i, j]), "tilt_rad": list(mis.tilt[i, j])}
                    for j, g in enumerate(lens.group_names)}
            _, z_img = ol.nominal_layout(doc, gaps)
            optic = ol.build_optic(ol.surface_poses(doc, gaps, pert), z_img)
            ol.trace_rays(optic, [((0.0, 0.0, ol.Z_START), (0.0, 0.0, 1.0))])

    t_ol = best_of(run_optiland, repeat=1)
    t = best_of(lambda: chief_ray_image_real(lens, th, mis))
    return ("exact principal point per state", "lens states/s", n / t,
            "optiland build+trace per state", n / t_ol, "")


def _bench_scene(lens):
    import cv2

    from zoomcalib.optics.lens_camera import exact_mapping
    from zoomcalib.targets import parse_pattern

    mapping = exact_mapping(lens, 0.3)
    target = parse_pattern("chessboard:17x12:10")  # squares of about 60 px at 500 mm
    R = cv2.Rodrigues(np.array([0.25, -0.2, 0.03]))[0]
    t = np.array([-80.0, -55.0, 500.0])
    return mapping, target, R, t


def bench_render(lens, quick):
    from zoomcalib.camera import DEFAULT_SENSOR
    from zoomcalib.render.image import Optics, psf_sigma_px, render_coverage

    mapping, target, R, t = _bench_scene(lens)
    sigma = psf_sigma_px(Optics(), DEFAULT_SENSOR.pixel_pitch_mm)
    t_an = best_of(lambda: render_coverage(target, mapping, R, t, DEFAULT_SENSOR, sigma,
                                           method="analytic"), repeat=1 if quick else 3)
    t_ss = best_of(lambda: render_coverage(target, mapping, R, t, DEFAULT_SENSOR, sigma,
                                           method="supersample"), repeat=1)
    return ("render 1280x960 chessboard, analytic", "images/s", 1 / t_an,
            "4x4 supersampled renderer", 1 / t_ss, "<= 0.5 s/image")


def bench_detect(lens, quick):
    import cv2

    from zoomcalib.camera import DEFAULT_SENSOR
    from zoomcalib.detect import detect_image
    from zoomcalib.render.image import render_image

    mapping, target, R, t = _bench_scene(lens)
    img = render_image(target, mapping, R, t, DEFAULT_SENSOR, rng=0).image
    t_model = best_of(lambda: detect_image(img, target, "model"))
    t_sb = best_of(lambda: cv2.findChessboardCornersSB(img, (17, 12),
                                                       flags=cv2.CALIB_CB_ACCURACY))
    t_cl = best_of(lambda: detect_image(img, target, "classic"))
    return [("detect + model refinement (187 pts)", "images/s", 1 / t_model,
             "cv2.findChessboardCornersSB", 1 / t_sb, "<= 0.3 s/image"),
            ("detect + model refinement (187 pts)", "images/s", 1 / t_model,
             "findChessboardCorners+cornerSubPix", 1 / t_cl, "")]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller batches")
    args = ap.parse_args()
    lens = load_prescription("laikin-10x")
    print(f"machine: {platform.machine()}, {platform.processor() or 'cpu'}, "
          f"python {platform.python_version()}, numpy {np.__version__}")
    rows = [bench_paraxial(lens, args.quick), bench_exact(lens, args.quick),
            bench_optiland_states(lens, args.quick), bench_render(lens, args.quick),
            *bench_detect(lens, args.quick)]
    print(f"{'benchmark':34s} {'unit':28s} {'ours':>10s}  {'peer':34s} {'peer rate':>10s} "
          f"{'ratio':>8s}  goal")
    for name, unit, ours, peer_name, peer, goal in rows:
        o = f"{ours:10.3g}" if ours else f"{'-':>10s}"
        pr = f"{peer:10.3g}" if peer else f"{'n/a':>10s}"
        ratio = f"{ours / peer:8.3g}" if ours and peer else f"{'-':>8s}"
        print(f"{name:34s} {unit:28s} {o}  {peer_name:34s} {pr} {ratio}  {goal}")


if __name__ == "__main__":
    main()
