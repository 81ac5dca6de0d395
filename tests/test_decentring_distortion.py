"""The tangential distortion a decentred group adds (``decentring_distortion``), against the
image field of the exact ray tracer.

Truth: the exact tracer's image of a grid of field directions, with the group decentred and
centred. Their difference is fitted here, by its own least squares, with the first-order change
of the OpenCV model (principal point, focal length, k1-k3, p1, p2); its p1, p2 must match what
``decentring_distortion`` reports from the camera fits it compares.
"""

import numpy as np
import pytest

from zoomcalib.camera import Sensor
from zoomcalib.diagnose.model import decentring_distortion
from zoomcalib.optics.cam import solve_gaps
from zoomcalib.optics.lens_camera import exact_projection
from zoomcalib.optics.misalignment import Misalignment
from zoomcalib.optics.prescription import load_prescription

LENS = load_prescription("laikin-10x")
SENSOR = Sensor(640, 480, 0.0129)


def _tangential_from_field(z: float, group: str, decenter_mm: np.ndarray) -> np.ndarray:
    """(2,) change of (p1, p2): the exact image field's change fitted by the model's terms."""
    thickness = LENS.thickness_at(solve_gaps(LENS, [z]))[0]
    names = list(LENS.group_names)
    moved = np.zeros((len(names), 2))
    moved[names.index(group)] = decenter_mm
    still = np.zeros_like(moved)
    f_px = float(np.ptp(exact_projection(LENS, thickness, np.array([[-1e-3, 0.0], [1e-3, 0.0]]),
                                         Misalignment(still, still), SENSOR)[:, 0]) / 2e-3)
    half = np.array([SENSOR.width_px, SENSOR.height_px]) / 2 / f_px
    gx, gy = np.meshgrid(np.linspace(-half[0], half[0], 21), np.linspace(-half[1], half[1], 16))
    x, y = gx.ravel(), gy.ravel()
    xy = np.stack([x, y], -1)
    du = (exact_projection(LENS, thickness, xy, Misalignment(moved, still), SENSOR)
          - exact_projection(LENS, thickness, xy, Misalignment(still, still), SENSOR)) / f_px
    r2 = x ** 2 + y ** 2
    one, nil = np.ones_like(x), np.zeros_like(x)
    # columns: cx, cy, focal scale, k1, k2, k3, p1, p2 (first-order changes, normalised units)
    cols_u = [one, nil, x, x * r2, x * r2 ** 2, x * r2 ** 3, 2 * x * y, r2 + 2 * x ** 2]
    cols_v = [nil, one, y, y * r2, y * r2 ** 2, y * r2 ** 3, r2 + 2 * y ** 2, 2 * x * y]
    a = np.vstack([np.stack(cols_u, -1), np.stack(cols_v, -1)])
    coef, *_ = np.linalg.lstsq(a, np.concatenate([du[:, 0], du[:, 1]]), rcond=None)
    return coef[6:8]


@pytest.mark.parametrize("z, group", [(0.6, "variator"), (1.0, "variator"),
                                      (0.3, "compensator")])
def test_decentring_distortion_matches_the_exact_field(z, group):
    d = np.array([0.08, -0.05])  # mm, about what imitates a 1 mrad axis tilt on this lens
    got = decentring_distortion(LENS, np.array([z]), group, d)[0]
    want = _tangential_from_field(z, group, d)
    # two fits of one field by the same first-order terms, on different grids: they agree to
    # 1e-4 of the change here; 1 % leaves room for the grids, not for a swapped or lost term
    assert np.linalg.norm(got - want) < 0.01 * np.linalg.norm(want), (got, want)
    assert np.linalg.norm(want) > 1e-5  # a change far above the table's sd_p at short focal


def test_no_decentre_no_change_and_unknown_group_refused():
    assert np.allclose(decentring_distortion(LENS, np.array([0.5]), "variator",
                                             np.zeros(2)), 0.0, atol=1e-9)
    with pytest.raises(ValueError, match="no group 'zoom'"):
        decentring_distortion(LENS, np.array([0.5]), "zoom", np.zeros(2))
