import numpy as np
import pytest

from zoomcalib.optics.cam import solve_gaps
from zoomcalib.optics.misalignment import Misalignment, vertex_z
from zoomcalib.optics.paraxial import (
    chief_ray_image,
    image_shift_sensitivity,
    surface_matrices,
    trace_paraxial,
)
from zoomcalib.optics.prescription import _parse
from zoomcalib.optics.principal_point import neutral_pivot_offset
from zoomcalib.optics.raytrace import chief_ray_image_real, trace_real


def _random_misalignment(rng, shape, n_groups, decenter_mm, tilt_rad):
    return Misalignment(rng.normal(0, decenter_mm, shape + (n_groups, 2)),
                        rng.normal(0, tilt_rad, shape + (n_groups, 2)))


def test_paraxial_and_exact_agree_for_small_errors(laikin, rng):
    zoom = rng.uniform(0, 1, 6)
    thickness = laikin.thickness_at(solve_gaps(laikin, zoom))[:, None, :]  # shape (6, 1, N)
    mis = _random_misalignment(rng, (6, 50), 4, 0.005, 1e-4)  # 5 um, 0.1 mrad
    par = chief_ray_image(laikin, thickness, mis)
    real = chief_ray_image_real(laikin, thickness, mis)
    shift = np.linalg.norm(par, axis=-1)
    assert np.median(shift) > 1e-4  # the errors do move the image (um level)
    # second-order terms: (0.1 mrad)^2-level relative differences
    assert np.all(np.linalg.norm(real - par, axis=-1) < 1e-3 * shift + 1e-9)


def test_paraxial_matrices_match_ray_trace(laikin, rng):
    thickness = laikin.thickness_at(solve_gaps(laikin, [rng.uniform()]))[0]
    mis = _random_misalignment(rng, (), 4, 0.02, 3e-4)
    z = vertex_z(thickness)
    group_of = laikin.surface_group_index()
    delta = np.array([mis.surface(laikin, z, k, group_of)[0] for k in range(24)])  # (N, 2)
    tilt = np.array([mis.surface(laikin, z, k, group_of)[1] for k in range(24)])
    y0, u0 = rng.normal(size=2), rng.normal(scale=0.05, size=2)
    rays = trace_paraxial(laikin, thickness, y0, u0, mis)
    for axis in range(2):
        m = np.eye(3)
        for mk in surface_matrices(laikin, thickness, delta[:, axis], tilt[:, axis]):
            m = mk @ m
        y, nu, _ = m @ np.array([y0[axis], u0[axis], 1.0])
        assert y == pytest.approx(rays.y_image[axis], abs=1e-12)
        assert nu == pytest.approx(rays.u_image[axis], abs=1e-12)


def _plate_lens(thickness_mm, index):
    surf = [
        {"radius_mm": None, "thickness_mm": 5.0, "nd": 1.0, "group": "A"},
        {"radius_mm": None, "thickness_mm": thickness_mm, "nd": index, "group": "P"},
        {"radius_mm": None, "thickness_mm": 5.0, "nd": 1.0, "group": "P"},
        {"radius_mm": None, "thickness_mm": 5.0, "nd": 1.0, "group": "C"},
        {"radius_mm": None, "thickness_mm": 10.0, "nd": 1.0, "group": "S", "stop": True},
    ]
    doc = {"surfaces": surf, "groups": {"A": {"surfaces": [1, 1]}, "P": {"surfaces": [2, 3]},
                                        "C": {"surfaces": [4, 4]}, "S": {"surfaces": [5, 5]}},
           "variable_gaps_mm": {"after_surface": [1, 3, 4],
                                "design_positions": [[5, 5, 5], [6, 4, 5]]}}
    return _parse(doc, "plate")


def test_exact_tracer_tilted_plate_against_snell(rng):
    # A plate of thickness T and index n tilted by t displaces an axial ray by
    # T sin(t - t') / cos t' with sin t = n sin t' (independent closed form).
    T, n = rng.uniform(2, 10), rng.uniform(1.45, 1.9)
    t = rng.uniform(0.05, 0.4)
    lens = _plate_lens(T, n)
    tilt = np.zeros((4, 2))
    tilt[1] = [t, 0.0]
    mis = Misalignment(np.zeros((4, 2)), tilt)
    rays = trace_real(lens, lens.thickness, np.array([0.0, 0.0, -3.0]),
                      np.array([0.0, 0.0, 1.0]), mis)
    tp = np.arcsin(np.sin(t) / n)
    assert rays.position[0] == pytest.approx(T * np.sin(t - tp) / np.cos(tp), rel=1e-12)
    np.testing.assert_allclose(rays.direction, [0, 0, 1], atol=1e-14)
    # A decentred plate changes nothing.
    dec = np.zeros((4, 2))
    dec[1] = rng.normal(size=2)
    rays = trace_real(lens, lens.thickness, np.array([0.3, -0.2, -3.0]),
                      np.array([0.0, 0.0, 1.0]), Misalignment(dec, np.zeros((4, 2))))
    np.testing.assert_allclose(rays.position[:2], [0.3, -0.2], atol=1e-14)


@pytest.mark.parametrize("group", ["variator", "compensator"])
def test_tilt_about_neutral_pivot_leaves_image_in_place(laikin, rng, group):
    zoom = rng.uniform(0, 1)
    thickness = laikin.thickness_at(solve_gaps(laikin, [zoom]))[0]
    g = laikin.group_index(group)
    tilt = np.zeros((4, 2))
    tilt[g] = [1e-3, 0]
    zero = np.zeros((4, 2))
    about_vertex = chief_ray_image_real(laikin, thickness, Misalignment(zero, tilt))
    pivot = np.zeros(4)
    pivot[g] = neutral_pivot_offset(laikin, zoom, group)
    about_neutral = chief_ray_image_real(laikin, thickness, Misalignment(zero, tilt, pivot))
    assert abs(about_vertex[0]) > 1e-3  # the vertex pivot does move the image (um level)
    assert np.linalg.norm(about_neutral) < 2e-3 * np.linalg.norm(about_vertex)


def test_paraxial_shift_is_linear_in_decentre(laikin):
    thickness = laikin.thickness_at(solve_gaps(laikin, [0.3]))[0]
    s_d, s_t = image_shift_sensitivity(laikin, thickness, "variator")
    for scale in (0.5, 2.0):
        dec = np.zeros((4, 2))
        dec[1] = [scale * 1e-3, -scale * 1e-3]
        img = chief_ray_image(laikin, thickness, Misalignment(dec, np.zeros((4, 2))))
        np.testing.assert_allclose(img, [s_d * scale * 1e-3, -s_d * scale * 1e-3], rtol=1e-12)
