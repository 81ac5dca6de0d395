"""Render what a camera records when it looks at a calibration target through a lens.

For every pixel the renderer finds where its sub-samples land on the board (back through the
lens mapping and the pose), paints the target there with exact coverage of straight edges,
blurs with the PSF *before* integrating over the pixel (as in a camera), then applies vignetting,
gain, shot and read noise, gamma and quantisation.

Geometry
--------
Pixel sub-sample ``(u, v)`` (OpenCV convention, pixel centres at integers; sub-sample ``k`` of
``S`` at ``i + (k + 0.5) / S - 0.5``) has normalised coordinates ``xy = mapping.unproject(u, v)``;
its ray ``s (x, y, 1)`` meets the board plane of pose ``Rt_cam_board = (R, t)`` (board -> camera,
``P = R b + t``) at ``s = (n . t) / (n . (x, y, 1))``, ``n = R e_z``, i.e. at board point
``b = R^T (s (x, y, 1) - t)``. A non-flat board (:class:`BoardSurface`, height ``z = w(x, y)``
in board mm; the point printed at ``(x, y)`` sits at ``(x, y, w(x, y))``) is met where
``b_z = w(b_x, b_y)``, i.e. ``s = (n . t + w(b_x(s), b_y(s))) / (n . (x, y, 1))``, solved by
fixed-point iteration from the plane's ``s`` (see :func:`_intersect_surface`). This
board-coordinate field is computed on a coarse pixel lattice and interpolated by bicubic splines
(it is smooth: perspective, lens distortion and the board's waves), which also give its
derivatives ``d b / d (u, v)``.

Coverage
--------
Targets are painted as a rectilinear grid of constant cells (every edge of chessboard squares and
ChArUco marker cells is a grid line in the board frame) plus dark discs. A straight edge at signed
distance ``d`` (px, along its image normal: ``d_board / |grad_uv b|``) from a sub-sample centre
covers an exactly computed fraction of that square sub-sample (see :func:`_coverage_beyond`);
crossings of two edges use the tensor product. The PSF is a
Gaussian of standard deviation ``sigma`` (see :func:`psf_sigma_px`), applied to the sub-sampled
coverage before the ``S x S`` box integration.

PSF
---
``Optics.psf`` selects the PSF. ``'gaussian'`` (default) and ``'elliptical'`` (an anisotropic
Gaussian) are rendered in closed form when they can be (see :func:`_render_analytic`; for
'elliptical' not on targets with dots). The others exist only as a kernel sampled on the
``S x S`` fine grid (:func:`psf_kernel`), convolved with the sub-sampled coverage before the box
integration, so they always take the supersampled path (as 'elliptical' does when the closed
form does not apply): ``'airy'`` (diffraction pattern with its first dark
ring at ``Optics.airy_radius_px``, convolved with the Gaussian of blur and defocus), ``'halo'``
(the Gaussian core plus a fraction ``halo_fraction`` of the energy in a wide Gaussian of sigma
``halo_sigma_px``, as veiling glare) and ``'elliptical'`` (a Gaussian of sigma ``psf_sigma_px``
along the axis at ``ellipse_angle_deg`` from the image u axis towards +v, and
``ellipse_ratio`` times that across it, as astigmatism or motion).
"""

from __future__ import annotations

import weakref
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import scipy.sparse
from scipy.interpolate import BSpline, RectBivariateSpline
from scipy.spatial import cKDTree
from scipy.special import ndtr

from ..camera import Sensor
from ..imaging import auto_n_sub, bivariate_normal_cdf, pixel_nodes
from ..targets import Target

__all__ = ["Radiometry", "Optics", "PSF_KINDS", "psf_sigma_px", "psf_kernel",
           "elliptical_psf_covariance", "BoardSurface",
           "board_coordinates", "render_coverage", "render_image", "apply_radiometry",
           "project_points", "RenderedView", "camera_mapping", "RollingShutterMapping"]

BACKGROUND = 0.5  # relative reflectance of what lies beyond the board

PSF_KINDS = ("gaussian", "airy", "halo", "elliptical")


@dataclass(frozen=True)
class Optics:
    """What sets the blur.

    Attributes
    ----------
    blur_px : float
        Extra Gaussian blur (aberrations, sensor MTF), 1-sigma in px.
    f_number : float
        For the diffraction term.
    defocus_mm : float
        Image-side defocus; the blur circle of diameter ``defocus / N`` enters as a Gaussian of
        sigma = diameter / 4.
    wavelength_um : float
    psf : {'gaussian', 'airy', 'halo', 'elliptical'}
        PSF shape (module docstring, section PSF). 'gaussian' and 'elliptical' are rendered
        analytically when they can be, the others always supersampled.
    airy_radius_px : float
        'airy': radius of the first dark ring, px; 0 takes the diffraction limit
        ``1.22 lambda N`` of ``wavelength_um`` and ``f_number``.
    halo_fraction, halo_sigma_px : float
        'halo': fraction of the energy in the wide Gaussian, and its sigma (px).
    ellipse_ratio, ellipse_angle_deg : float
        'elliptical': sigma across the major axis over sigma along it, and the angle of the
        major axis from the image u axis towards +v, degrees.
    """

    blur_px: float = 0.7
    f_number: float = 2.4
    defocus_mm: float = 0.0
    wavelength_um: float = 0.55
    psf: str = "gaussian"
    airy_radius_px: float = 0.0
    halo_fraction: float = 0.05
    halo_sigma_px: float = 6.0
    ellipse_ratio: float = 0.5
    ellipse_angle_deg: float = 30.0

    def __post_init__(self):
        if self.psf not in PSF_KINDS:
            raise ValueError(f"psf must be one of {', '.join(PSF_KINDS)}, got {self.psf!r}")
        if not 0.0 <= self.halo_fraction < 1.0 or self.halo_sigma_px <= 0:
            raise ValueError("halo_fraction must lie in [0, 1) and halo_sigma_px be positive")
        if not 0.0 < self.ellipse_ratio <= 1.0 or self.airy_radius_px < 0:
            raise ValueError("ellipse_ratio must lie in (0, 1] and airy_radius_px be >= 0")


def psf_sigma_px(optics: Optics, pixel_pitch_mm: float) -> float:
    """Gaussian PSF sigma (px): ``sqrt(blur^2 + s_diff^2 + s_defocus^2)``.

    ``s_diff = 0.42 lambda N`` (the Gaussian that best matches the Airy core) and
    ``s_defocus = |defocus| / (4 N)``, both converted from mm to px. For ``psf='airy'``,
    ``s_diff`` is ``0.42 / 1.22`` of :func:`airy_radius_px` (the Gaussian matching the core of
    the rendered Airy pattern). For 'halo' this is the core's sigma, for 'elliptical' the sigma
    along the major axis.
    """
    s_def = abs(optics.defocus_mm) / (4 * optics.f_number) / pixel_pitch_mm
    if optics.psf == "airy":
        s_diff = 0.42 / 1.22 * airy_radius_px(optics, pixel_pitch_mm)
    else:
        s_diff = 0.42 * optics.wavelength_um * 1e-3 * optics.f_number / pixel_pitch_mm
    return float(np.sqrt(optics.blur_px**2 + s_diff**2 + s_def**2))


def airy_radius_px(optics: Optics, pixel_pitch_mm: float) -> float:
    """Radius of the Airy pattern's first dark ring, px: ``optics.airy_radius_px`` when set,
    else ``1.22 lambda N``."""
    if optics.airy_radius_px > 0:
        return float(optics.airy_radius_px)
    return 1.22 * optics.wavelength_um * 1e-3 * optics.f_number / pixel_pitch_mm


def elliptical_psf_covariance(optics: Optics, pixel_pitch_mm: float) -> np.ndarray:
    """Covariance of the 'elliptical' PSF, px^2, rows and columns in (u, v) order.

    Sd :func:`psf_sigma_px` along the major axis (at ``ellipse_angle_deg`` from the u axis
    towards +v) and ``ellipse_ratio`` times that across it: the second moments of
    :func:`psf_kernel`'s elliptical kernel.
    """
    sigma = psf_sigma_px(optics, pixel_pitch_mm)
    a = np.deg2rad(optics.ellipse_angle_deg)
    major = np.array([np.cos(a), np.sin(a)])
    minor = np.array([-np.sin(a), np.cos(a)])
    return sigma**2 * (np.outer(major, major)
                       + optics.ellipse_ratio**2 * np.outer(minor, minor))


AIRY_REACH = 6.0  # Airy kernels are cut at this many first-ring radii (2.8 % of the energy beyond)
J1_FIRST_ZERO = 3.8317059702075125


def psf_kernel(optics: Optics, pixel_pitch_mm: float, supersample: int) -> np.ndarray:
    """The PSF of ``optics`` point-sampled on the fine grid (spacing ``1 / supersample`` px).

    'airy' is the Airy pattern (cut at ``AIRY_REACH`` first-ring radii) convolved with the
    Gaussian of blur and defocus; the others are as in the module docstring. Point sampling
    resolves the core when the PSF spans a few fine samples: an Airy radius or sigma of at
    least ``2 / supersample`` px.

    Returns
    -------
    kernel : (k, k) float64 ndarray
        Odd side, centred, summing to 1; rows along v, columns along u.
    """
    from scipy.special import j1

    S = int(supersample)
    sigma = psf_sigma_px(optics, pixel_pitch_mm)
    if optics.psf == "airy":
        radius = airy_radius_px(optics, pixel_pitch_mm)
        s_gauss = np.sqrt(max(sigma**2 - (0.42 / 1.22 * radius) ** 2, 0.0))
        reach = AIRY_REACH * radius + 4 * s_gauss
    elif optics.psf == "halo":
        reach = 4 * max(sigma, optics.halo_sigma_px)
    else:
        reach = 4 * sigma
    half = int(np.ceil(reach * S)) + 1
    y, x = np.mgrid[-half:half + 1, -half:half + 1] / S  # px; x along u, y along v
    if optics.psf == "airy":
        r = np.hypot(x, y)
        arg = np.maximum(J1_FIRST_ZERO * r / radius, 1e-12)
        k = np.where(r <= AIRY_REACH * radius, (2 * j1(arg) / arg) ** 2, 0.0)
        if s_gauss > 0:
            k = cv2.GaussianBlur(k, (0, 0), s_gauss * S, borderType=cv2.BORDER_CONSTANT)
    elif optics.psf == "halo":
        r2 = x * x + y * y
        h = optics.halo_sigma_px
        k = ((1 - optics.halo_fraction) * np.exp(-0.5 * r2 / sigma**2) / sigma**2
             + optics.halo_fraction * np.exp(-0.5 * r2 / h**2) / h**2)
    else:
        a = np.deg2rad(optics.ellipse_angle_deg)
        s_minor = sigma * (optics.ellipse_ratio if optics.psf == "elliptical" else 1.0)
        along = x * np.cos(a) + y * np.sin(a)
        across = -x * np.sin(a) + y * np.cos(a)
        k = np.exp(-0.5 * (along**2 / sigma**2 + across**2 / s_minor**2))
    return k / k.sum()


@dataclass(frozen=True)
class Radiometry:
    """From relative reflectance (0 dark print .. 1 white paper) to digital numbers.

    Attributes
    ----------
    white, black : float
        Signal of white paper and of the dark print, as a fraction of full scale.
    noise_sd : float
        Additive Gaussian read noise, fraction of full scale (2/255 = 2 DN at 8 bits).
    full_well_e : float or None
        Electrons at full scale; gives Poisson shot noise. None: no shot noise.
    gain : float
        Multiplies the signal before clipping (exposure).
    gamma : float
        Output = signal ** (1 / gamma).
    bits : {8, 12, 16}
    vignetting : float
        Fractional fall-off at the image corner: ``1 - vignetting * (r / r_corner)^2``.
    """

    white: float = 0.85
    black: float = 0.08
    noise_sd: float = 2.0 / 255.0
    full_well_e: float | None = None
    gain: float = 1.0
    gamma: float = 1.0
    bits: int = 8
    vignetting: float = 0.0


def _cell_grid(target: Target) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rectilinear grid of the target's axis-aligned dark rectangles.

    Returns
    -------
    xs, ys : (Nx,), (Ny,) ndarray
        Sorted grid lines, board mm (the board's outer edge included).
    value : (Nx + 1, Ny + 1) ndarray
        Reflectance of each cell (cell ``i`` lies between ``xs[i-1]`` and ``xs[i]``).
    """
    ext = target.extent_mm
    xs = {ext[0], ext[2]}
    ys = {ext[1], ext[3]}
    for p in target.polygons:
        if not (np.allclose(p[0, 1], p[1, 1]) and np.allclose(p[1, 0], p[2, 0])):
            raise ValueError("renderer paints axis-aligned rectangles and discs only")
        xs.update(np.round(p[:, 0], 9))
        ys.update(np.round(p[:, 1], 9))
    xs, ys = np.array(sorted(xs)), np.array(sorted(ys))
    xc = np.concatenate([[xs[0] - 1], 0.5 * (xs[:-1] + xs[1:]), [xs[-1] + 1]])
    yc = np.concatenate([[ys[0] - 1], 0.5 * (ys[:-1] + ys[1:]), [ys[-1] + 1]])
    value = np.ones((len(xc), len(yc)))
    inside = ((xc[:, None] > ext[0]) & (xc[:, None] < ext[2])
              & (yc[None, :] > ext[1]) & (yc[None, :] < ext[3]))
    value[~inside] = BACKGROUND
    for p in target.polygons:
        mx = (xc > p[:, 0].min()) & (xc < p[:, 0].max())
        my = (yc > p[:, 1].min()) & (yc < p[:, 1].max())
        value[np.ix_(mx, my)] = 0.0
    return xs, ys, value


@dataclass(frozen=True)
class BoardSurface:
    """A smoothly waving board: height ``z = w(x, y)`` above its plane, board frame, mm.

    ``w(x, y) = sum_k a_k sin(2 pi (kx_k x + ky_k y) + phase_k)``. The point printed at board
    ``(x, y)`` sits at ``(x, y, w(x, y))`` (the paper's stretch, of order ``(a k)^2``, is
    neglected: 1e-5 for tenths of a mm over tens of cm). Board +z points away from the side the
    pattern is seen from in the usual poses (along the camera's +z at zero rotation).

    Attributes
    ----------
    modes : tuple of (amplitude_mm, kx_per_mm, ky_per_mm, phase_rad)
        No modes: the flat board.
    """

    modes: tuple[tuple[float, float, float, float], ...] = ()

    @property
    def is_flat(self) -> bool:
        return all(m[0] == 0 for m in self.modes)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``w(x, y)``, mm, for board coordinates in mm (any matching shapes)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        w = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in self.modes:
            w += a * np.sin(2 * np.pi * (kx * x + ky * y) + ph)
        return w

    def lift(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) board points (z = 0 on the print) -> on the surface, ``z + w(x, y)``."""
        p = np.array(points, dtype=float)
        p[:, 2] += self.height(p[:, 0], p[:, 1])
        return p

    def to_dict(self) -> dict:
        return {"model": "sum of a sin(2 pi (kx x + ky y) + phase), board mm",
                "modes": [{"amplitude_mm": a, "kx_per_mm": kx, "ky_per_mm": ky, "phase_rad": ph}
                          for a, kx, ky, ph in self.modes]}

    @classmethod
    def from_dict(cls, doc: dict) -> BoardSurface:
        return cls(tuple((float(m["amplitude_mm"]), float(m["kx_per_mm"]), float(m["ky_per_mm"]),
                          float(m["phase_rad"])) for m in doc["modes"]))

    @classmethod
    def random(cls, extent_mm: np.ndarray, amplitude_mm: float,
               rng: np.random.Generator | int = 0, n_modes: int = 3,
               cycles: tuple[float, float] = (0.3, 1.5)) -> BoardSurface:
        """Low-order waves over a board: ``n_modes`` sinusoids of random direction and phase,
        each with ``cycles`` (uniform range) periods across the board's diagonal, scaled so the
        largest ``|w|`` over ``extent_mm = (xmin, ymin, xmax, ymax)`` is ``amplitude_mm``."""
        rng = np.random.default_rng(rng)
        ext = np.asarray(extent_mm, float)
        diag = float(np.hypot(*(ext[2:] - ext[:2])))
        freq = rng.uniform(*cycles, n_modes) / diag  # cycles per mm
        angle = rng.uniform(0, 2 * np.pi, n_modes)
        amp = rng.uniform(0.5, 1.0, n_modes)
        phase = rng.uniform(0, 2 * np.pi, n_modes)
        modes = tuple((float(a), float(f * np.cos(t)), float(f * np.sin(t)), float(p))
                      for a, f, t, p in zip(amp, freq, angle, phase, strict=True))
        gy, gx = np.mgrid[ext[1]:ext[3]:65j, ext[0]:ext[2]:65j]
        peak = np.max(np.abs(cls(modes).height(gx, gy)))
        scale = amplitude_mm / peak
        return cls(tuple((a * scale, kx, ky, p) for a, kx, ky, p in modes))


SURFACE_MAX_ITER = 30
SURFACE_TOL_MM = 1e-9  # fixed-point step along the ray at which the intersection has converged


def _intersect_surface(ray: np.ndarray, R: np.ndarray, t: np.ndarray,
                       surface: BoardSurface) -> np.ndarray:
    """Ray parameter ``s`` where ``s ray`` (camera frame) meets the board surface.

    Fixed-point iteration ``s <- (n . t + w(b_xy(s))) / (n . ray)`` from the plane's solution;
    it contracts by ``|grad w| tan(incidence)`` per step (about 0.02 for 0.3 mm waves of 10 cm
    at 40 degrees), so a few steps reach ``SURFACE_TOL_MM``.

    Raises
    ------
    ValueError
        When it does not converge in ``SURFACE_MAX_ITER`` steps (a surface too steep for the
        view).
    """
    n = R[:, 2]
    nr = ray @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / nr
        ray_len = np.linalg.norm(ray, axis=1)
        for _ in range(SURFACE_MAX_ITER):
            b = (s[:, None] * ray - t) @ R
            s_new = (n @ t + surface.height(b[:, 0], b[:, 1])) / nr
            step = np.nanmax(np.abs(s_new - s) * ray_len, initial=0.0)
            s = s_new
            if step < SURFACE_TOL_MM:
                return s
    raise ValueError(f"the ray intersection with the board surface did not converge (last step "
                     f"{step:.2g} mm): the surface is too steep for this view")


#: Each mapping's unprojected lattices (by the mapping's id), dropped when the mapping is: the
#: rays through the lattice do not depend on the pose, and unprojecting through a traced lens's
#: splines is most of a view's board coordinates.
_LATTICES: dict[int, dict] = {}


def _unprojected_lattice(mapping, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """``mapping.unproject`` of the lattice ``us x vs`` (row-major in ``(v, u)``), (M, 2),
    computed once per mapping and lattice while the mapping lives and still unprojects three of
    its points to the same rays (a mapping that cannot be weakly referenced is unprojected every
    time)."""
    owner = id(mapping)
    if owner not in _LATTICES:
        try:
            weakref.finalize(mapping, _LATTICES.pop, owner, None)
            _LATTICES[owner] = {}
        except TypeError:
            pass
    cached = _LATTICES.get(owner, {})
    key = (us[0], us[-1], len(us), vs[0], vs[-1], len(vs))
    gv, gu = np.meshgrid(vs, us, indexing="ij")
    grid = np.stack([gu.ravel(), gv.ravel()], -1)
    if key in cached:  # a mapping changed in place since is unprojected again
        probe = np.array([0, len(grid) // 2, len(grid) - 1])
        if np.array_equal(mapping.unproject(grid[probe]), cached[key][probe]):
            return cached[key]
    cached[key] = mapping.unproject(grid)
    cached[key].setflags(write=False)
    return cached[key]


class LatticeSpline(RectBivariateSpline):
    """A :class:`scipy.interpolate.RectBivariateSpline` whose evaluation on a grid goes through
    the B-spline basis: ``s^(a,b)(x_i, y_j) = sum_pq B^(a)_p(x_i) c_pq B^(b)_q(y_j)``, i.e.
    ``Bx^(a) C By^(b)^T`` with the basis matrices sparse (``k + 1`` non-zeros a row). The
    product ``C By^(b)^T`` is kept for each column set and derivative order, so the bands of
    one image, which share their columns, each cost a sparse product of their rows alone.
    Values equal FITPACK's to rounding; scattered points (``grid=False``, :meth:`ev`) are
    FITPACK's own."""

    def __call__(self, x, y, dx: int = 0, dy: int = 0, grid: bool = True):
        if not grid:
            return super().__call__(x, y, dx=dx, dy=dy, grid=False)
        x, y = np.asarray(x, float), np.asarray(y, float)
        return _basis(self, 0, x, dx) @ self._times_columns(y, dy)

    def _times_columns(self, y: np.ndarray, dy: int) -> np.ndarray:
        """``C By^(dy)^T`` (nx, len(y)), kept for the last column sets."""
        cache = self.__dict__.setdefault("_columns", {})
        key = (dy, y.shape, y.tobytes())
        if key not in cache:
            if len(cache) > 8:
                cache.clear()
            tx, ty = self.tck[:2]
            coeffs = self.tck[2].reshape(len(tx) - self.degrees[0] - 1, -1)
            cache[key] = (_basis(self, 1, y, dy) @ coeffs.T).T
        return cache[key]


#: Basis matrices of :func:`_basis`, by knots, degree, order and points: the lattices of one
#: sensor share their knots, and its images their bands' rows and columns.
_BASES: dict[tuple, scipy.sparse.csr_matrix] = {}


def _basis(spline: RectBivariateSpline, axis: int, at: np.ndarray, order: int):
    """(len(at), n) sparse matrix of the ``order``-th derivative of each B-spline of the
    spline's knots along ``axis`` (0: x, 1: y) at the points ``at``."""
    knots, degree = spline.tck[axis], spline.degrees[axis]
    key = (knots.tobytes(), degree, order, at.tobytes())
    if key not in _BASES:
        if len(_BASES) >= 256:
            _BASES.clear()
        _BASES[key] = _basis_matrix(knots, degree, at, order)
    return _BASES[key]


def _basis_matrix(knots: np.ndarray, degree: int, at: np.ndarray, order: int):
    n = len(knots) - degree - 1
    at = np.clip(at, knots[degree], knots[n])  # outside its knots FITPACK takes the nearest end
    dense = BSpline(knots, np.eye(n), degree, extrapolate=True)(at, nu=order)
    # the k + 1 splines that do not vanish at each point: those of its knot span
    first = np.clip(np.searchsorted(knots, at, side="right") - 1, degree, n - 1) - degree
    cols = first[:, None] + np.arange(degree + 1)
    data = np.take_along_axis(dense, cols, axis=1)
    return scipy.sparse.csr_matrix((data.ravel(), cols.ravel(),
                                    np.arange(0, data.size + 1, degree + 1)),
                                   shape=(len(at), n))


def board_coordinates(mapping, R: np.ndarray, t: np.ndarray, sensor: Sensor,
                      step_px: int = 4, surface: BoardSurface | None = None
                      ) -> tuple[LatticeSpline, LatticeSpline]:
    """Splines of the board point seen by each pixel position.

    Parameters
    ----------
    mapping : object with ``unproject((M, 2) pixels) -> (M, 2) normalised``
    R, t : (3, 3), (3,) ndarray
        ``Rt_cam_board``: board -> camera, mm.
    step_px : int
        Lattice spacing of the exactly computed nodes.
    surface : BoardSurface, optional
        Non-flat board; None (or no modes) is the plane.

    Returns
    -------
    bx, by : LatticeSpline
        Board x and y (mm) as functions of ``(v, u)`` (row, column order).
    """
    us = np.arange(-2 * step_px, sensor.width_px + 2 * step_px, step_px, dtype=float)
    vs = np.arange(-2 * step_px, sensor.height_px + 2 * step_px, step_px, dtype=float)
    gv, gu = np.meshgrid(vs, us, indexing="ij")
    xy = _unprojected_lattice(mapping, us, vs)
    ray = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)  # shape (M, 3)
    if surface is None or surface.is_flat:
        n = R[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (n @ t) / (ray @ n)
    else:
        s = _intersect_surface(ray, R, t, surface)
    s = np.where(s > 0, s, np.nan)
    b = (s[:, None] * ray - t) @ R  # R^T (P - t), shape (M, 3)
    if np.any(~np.isfinite(b)):
        raise ValueError("the board plane does not cover the whole field of view "
                         "(a pose looks past the board's horizon)")
    bx = LatticeSpline(vs, us, b[:, 0].reshape(gv.shape), kx=3, ky=3)
    by = LatticeSpline(vs, us, b[:, 1].reshape(gv.shape), kx=3, ky=3)
    return bx, by


def _coverage_beyond(d: np.ndarray, nu: np.ndarray, nv: np.ndarray, S: int) -> np.ndarray:
    """Fraction of a square sub-sample (side 1/S px) beyond a straight edge at distance ``d`` px.

    The sub-sample projected on the edge normal ``(nu, nv)`` is the sum of two uniform variables of
    widths ``a = |nu| / S`` and ``b = |nv| / S`` (a >= b); the covered fraction is its tail:
    ``1/2 - d / a`` for ``d <= (a - b) / 2``, ``((a + b) / 2 - d)^2 / (2 a b)`` up to
    ``(a + b) / 2``, and 0 beyond. Exact for any edge direction.
    """
    a = np.maximum(np.abs(nu), np.abs(nv)) / S
    b = np.minimum(np.abs(nu), np.abs(nv)) / S
    d = np.abs(d)
    lin = 0.5 - d / a
    with np.errstate(divide="ignore", invalid="ignore"):
        quad = np.where(b > 1e-12, ((a + b) / 2 - d) ** 2 / (2 * a * b), 0.0)
    out = np.where(d <= (a - b) / 2, lin, quad)
    return np.where(d >= (a + b) / 2, 0.0, out)


def _edge_weight(coord, grad_u, grad_v, lines, S):
    """Index of the cell, step towards the nearest line, and the coverage across it."""
    i = np.searchsorted(lines, coord)  # cell index, shape like coord
    left = lines[np.clip(i - 1, 0, len(lines) - 1)]
    right = lines[np.clip(i, 0, len(lines) - 1)]
    d_left = np.where(i > 0, coord - left, np.inf)
    d_right = np.where(i < len(lines), right - coord, np.inf)
    nearer_right = d_right < d_left
    g = np.maximum(np.hypot(grad_u, grad_v), 1e-300)  # board mm per px across the line
    d = np.minimum(d_left, d_right) / g  # px
    w = _coverage_near(d, grad_u / g, grad_v / g, S)
    step = np.where(nearer_right, 1, -1)
    return i, step, w


def _coverage_near(d: np.ndarray, nu: np.ndarray, nv: np.ndarray, S: int) -> np.ndarray:
    """:func:`_coverage_beyond`, evaluated only where it is not 0 (the sub-samples an edge
    crosses, a few % of them); the same numbers, computed faster."""
    near = np.abs(d) < (np.abs(nu) + np.abs(nv)) / (2 * S) * (1 + 1e-9)
    w = np.zeros(np.shape(d))
    w[near] = _coverage_beyond(d[near], nu[near], nv[near], S)
    return w


SUPERSAMPLED_BAND_ROWS = 96  # image rows the supersampled renderer paints at once (memory)
ANALYTIC_BAND_ROWS = 160  # image rows the analytic renderer paints at once (memory)


def render_coverage(target: Target, mapping, R: np.ndarray, t: np.ndarray, sensor: Sensor,
                    sigma_px: float, supersample: int = 4, method: str = "auto",
                    surface: BoardSurface | None = None,
                    optics: Optics | None = None) -> np.ndarray:
    """Relative reflectance seen by each pixel: painted, blurred, then pixel-integrated.

    Parameters
    ----------
    sigma_px : float
        Sigma of the Gaussian PSF, px (unused when ``optics`` has a non-Gaussian PSF).
    method : {'auto', 'analytic', 'supersample'}
        'analytic' (:func:`_render_analytic`) needs a Gaussian PSF of at least 0.3 px and grid
        lines further apart than the blur's reach; 'auto' takes it when it applies, else
        'supersample' (sub-sampled coverage, blurred, then box-integrated).
    surface : BoardSurface, optional
        Non-flat board (None: the plane).
    optics : Optics, optional
        When its ``psf`` is not 'gaussian', it replaces the Gaussian of ``sigma_px``: an
        'elliptical' PSF is rendered in closed form when it can be, like the Gaussian (its
        covariance, :func:`elliptical_psf_covariance`), else supersampled with its
        :func:`psf_kernel`; 'airy' and 'halo' always take the supersampled path ('analytic'
        raises ``ValueError``).

    Returns
    -------
    image : (H, W) float64 ndarray
        0 = dark print, 1 = white paper, ``BACKGROUND`` beyond the board.
    """
    if method not in ("auto", "analytic", "supersample"):
        raise ValueError(f"method must be 'auto', 'analytic' or 'supersample', got {method!r}")
    kernel = psf_cov = None
    if optics is not None and optics.psf == "elliptical":
        psf_cov = elliptical_psf_covariance(optics, sensor.pixel_pitch_mm)
        if method != "analytic":
            kernel = psf_kernel(optics, sensor.pixel_pitch_mm, supersample)
    elif optics is not None and optics.psf != "gaussian":
        if method == "analytic":
            raise ValueError(f"the analytic renderer paints a Gaussian PSF only; psf "
                             f"{optics.psf!r} needs method='supersample' (or 'auto')")
        kernel = psf_kernel(optics, sensor.pixel_pitch_mm, supersample)
        method = "supersample"
    bxs, bys = board_coordinates(mapping, R, t, sensor, surface=surface)
    if method in ("auto", "analytic"):
        out = _render_analytic(target, bxs, bys, sensor, sigma_px, psf_cov=psf_cov)
        if out is not None:
            return out
        if method == "analytic":
            raise ValueError("the analytic renderer needs a blur >= 0.3 px (along every axis), "
                             "grid lines more than the blur's reach apart and, for an "
                             "elliptical PSF, no dots; use method='supersample'")
    return _render_supersampled(target, bxs, bys, sensor, sigma_px, supersample,
                                SUPERSAMPLED_BAND_ROWS, kernel)


ANALYTIC_MIN_SIGMA = 0.3  # px; below this the 6-node pixel rule is not accurate enough


def _render_analytic(target: Target, bxs, bys, sensor: Sensor, sigma: float,
                     band_rows: int = ANALYTIC_BAND_ROWS, psf_cov: np.ndarray | None = None
                     ) -> np.ndarray | None:
    """Closed-form blur of locally straight edges, integrated over each pixel by quadrature.

    Around each pixel the nearest vertical and horizontal board lines are straight in the image
    (first-order expansion of the board-coordinate field, with the distance from the pixel
    centre to second order along the normal). With ``t_1, t_2`` the signed distances (px) into
    the neighbouring cells across them, ``m_1, m_2`` their image normals and ``V_ab`` the four
    cell values, the blurred pattern is exactly

        P = V_00 + (V_10 - V_00) Phi(t_1/s) + (V_01 - V_00) Phi(t_2/s)
            + (V_11 - V_10 - V_01 + V_00) Phi_2(t_1/s, t_2/s; m_1 . m_2),

    averaged over the pixel with the Gauss-Legendre rule of :func:`zoomcalib.imaging.pixel_nodes`.
    A dot (dark disc) multiplies by ``1 - Phi(d/s - s kappa/2)``, ``d`` the distance inside its
    imaged rim and ``kappa`` the rim's curvature (px^-1). Returns None when it does not apply
    (blur below ``ANALYTIC_MIN_SIGMA``, or a second line of a family within ``4 sigma + 0.75``
    px of a pixel centre).

    With ``psf_cov`` (the (2, 2) covariance of an anisotropic Gaussian PSF, px^2, (u, v)
    order, from :func:`elliptical_psf_covariance`; ``sigma`` is then unused) the same is exact
    with each line's own sd ``s_i = sqrt(m_i^T C m_i)`` and the correlation
    ``m_1^T C m_2 / (s_1 s_2)``; reaches and the pixel rule follow the major and minor sd.
    Targets with dots then return None (their rims are written for an isotropic PSF).
    """
    s_major = s_minor = sigma
    if psf_cov is not None:
        s_minor, s_major = np.sqrt(np.linalg.eigvalsh(psf_cov))
        if len(target.discs):
            return None
    if s_minor < ANALYTIC_MIN_SIGMA:
        return None
    xs, ys, value = _cell_grid(target)
    nodes, weights = pixel_nodes(auto_n_sub(s_minor))
    # Beyond ``reach`` an edge changes a pixel by < 1e-9. A second line of the same family is
    # ignored; beyond 4 sigma it would change a pixel by < 3e-5 of the contrast.
    psf = _AnalyticPsf(sigma, psf_cov, reach=6.0 * s_major + 0.75,
                       second_reach=4.0 * s_major + 0.75, nodes=nodes, weights=weights)
    W, H = sensor.width_px, sensor.height_px
    u = np.arange(W, dtype=float)
    out = np.empty((H, W))
    discs = target.discs
    tree = cKDTree(discs[:, :2]) if len(discs) else None
    for r0 in range(0, H, band_rows):
        band = _Band.of(bxs, bys, np.arange(r0, min(H, r0 + band_rows), dtype=float), u)
        line_x, line_y = (_nearest_line(band, axis, lines, psf)
                          for axis, lines in ((0, xs), (1, ys)))
        if line_x is None or line_y is None:
            return None  # two lines of one family within reach: not locally one edge
        pix = _blend_cells(value, line_x, line_y, psf)
        if tree is not None:
            _dot_rims(pix, discs, tree, band, psf)
        out[r0:r0 + len(band.v)] = pix
    return out


@dataclass(frozen=True)
class _AnalyticPsf:
    """The PSF and pixel rule of :func:`_render_analytic`: the isotropic sd ``sigma`` (px) or
    the covariance ``cov`` ((2, 2), px^2, (u, v) order) of an anisotropic Gaussian, the
    ``reach`` (px) beyond which an edge leaves a pixel unchanged, the ``second_reach`` (px)
    within which a second line of one family is not locally one edge, and the pixel's
    quadrature ``nodes`` (px) and ``weights``."""

    sigma: float
    cov: np.ndarray | None
    reach: float
    second_reach: float
    nodes: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True)
class _Band:
    """A band of pixels: rows ``v`` and columns ``u`` (px), the board-coordinate splines
    ``bxs``, ``bys`` and, at each pixel (V, W), the board coordinates ``bx``, ``by`` (board
    units) and their derivatives by u and by v (board units per px)."""

    v: np.ndarray
    u: np.ndarray
    bxs: object
    bys: object
    bx: np.ndarray
    by: np.ndarray
    bx_u: np.ndarray
    bx_v: np.ndarray
    by_u: np.ndarray
    by_v: np.ndarray

    @classmethod
    def of(cls, bxs, bys, v: np.ndarray, u: np.ndarray) -> _Band:
        """The splines evaluated on the grid of rows ``v`` and columns ``u``."""
        bx, by = bxs(v, u), bys(v, u)  # shape (V, W)
        bx_v, bx_u = bxs(v, u, dx=1), bxs(v, u, dy=1)
        by_v, by_u = bys(v, u, dx=1), bys(v, u, dy=1)
        return cls(v, u, bxs, bys, bx, by, bx_u, bx_v, by_u, by_v)

    def family(self, axis: int) -> tuple:
        """Spline, coordinate and its derivatives by u and v of the board's x (``axis`` 0)
        or y (1)."""
        if axis == 0:
            return self.bxs, self.bx, self.bx_u, self.bx_v
        return self.bys, self.by, self.by_u, self.by_v

    def normal_curvature(self, spl, nu: np.ndarray, nv: np.ndarray) -> np.ndarray:
        """``n^T (d^2 b / d uv^2) n`` of the board coordinate of spline ``spl`` along the unit
        image direction ``n = (nu, nv)`` (board units per px^2)."""
        v, u = self.v, self.u
        return (spl(v, u, dy=2) * nu * nu + 2 * spl(v, u, dx=1, dy=1) * nu * nv
                + spl(v, u, dx=2) * nv * nv)


@dataclass(frozen=True)
class _NearestLine:
    """The nearest board line of one family at each pixel of a band (V, W): the index of the
    cell boundary ``index``, the side of the neighbouring cell ``step`` (+-1), the signed
    distance ``t_c`` (px) from the pixel centre into it (second order along the normal), the
    unit ``normal`` (V, W, 2) into it and the PSF's sd across the line ``sd`` (px; a scalar
    for an isotropic PSF)."""

    index: np.ndarray
    step: np.ndarray
    t_c: np.ndarray
    normal: np.ndarray
    sd: float | np.ndarray


def _nearest_line(band: _Band, axis: int, lines: np.ndarray,
                  psf: _AnalyticPsf) -> _NearestLine | None:
    """The nearest line of the board's x (``axis`` 0) or y (1) family (board coordinates
    ``lines``) at each pixel of ``band``; None when a second line of the family lies within
    ``psf.second_reach``: not locally one edge."""
    spl, coord, gu, gv = band.family(axis)
    psf_cov = psf.cov
    i = np.searchsorted(lines, coord)
    left = lines[np.clip(i - 1, 0, len(lines) - 1)]
    right = lines[np.clip(i, 0, len(lines) - 1)]
    d_left = np.where(i > 0, coord - left, np.inf)
    d_right = np.where(i < len(lines), right - coord, np.inf)
    g = np.maximum(np.hypot(gu, gv), 1e-300)  # board units per px across the line
    if np.any(np.maximum(d_left, d_right) / g < psf.second_reach):
        return None
    step = np.where(d_right < d_left, 1, -1)
    t_c = -np.minimum(d_left, d_right) / g  # px, < 0: the centre is in its own cell
    # Second order along the normal: perspective (and distortion) make |grad b| vary across
    # the line, so (board distance) / |grad b| at the centre is t - step (h/2) t^2 for an image
    # distance t, h = n^T (d^2 b / d uv^2) n / |grad b| (px^-1, n = grad b / |grad b|). The
    # error has one sign on both sides of the line: it moved every edge by
    # (h / 2) (sigma^2 + 1/12) px along n (1/12 from the pixel box);
    # benchmarks/render_accuracy.py measures what is left.
    nu, nv = gu / g, gv / g
    h = band.normal_curvature(spl, nu, nv) / g
    t_c += np.where(t_c > -psf.reach, 0.5 * step * h * t_c**2, 0.0)
    m = np.stack([step * gu / g, step * gv / g], -1)  # unit normal into the neighbour
    s_n = (psf.sigma if psf_cov is None else np.sqrt(
        psf_cov[0, 0] * m[..., 0] ** 2 + 2 * psf_cov[0, 1] * m[..., 0] * m[..., 1]
        + psf_cov[1, 1] * m[..., 1] ** 2))
    return _NearestLine(i, step, t_c, m, s_n)


def _blend_cells(value: np.ndarray, line_x: _NearestLine, line_y: _NearestLine,
                 psf: _AnalyticPsf) -> np.ndarray:
    """Each pixel of a band from the four cells around its nearest lines of the two families
    (:func:`_nearest_line`), by the closed form of :func:`_render_analytic`, averaged over the
    pixel with the PSF's nodes and weights."""
    ix, sx, t1c, m1, s1 = line_x.index, line_x.step, line_x.t_c, line_x.normal, line_x.sd
    iy, sy, t2c, m2, s2 = line_y.index, line_y.step, line_y.t_c, line_y.normal, line_y.sd
    nodes, weights, reach, psf_cov = psf.nodes, psf.weights, psf.reach, psf.cov
    nx, ny = value.shape
    ix2, iy2 = np.clip(ix + sx, 0, nx - 1), np.clip(iy + sy, 0, ny - 1)
    v00, v10 = value[ix, iy], value[ix2, iy]
    v01, v11 = value[ix, iy2], value[ix2, iy2]
    pix = v00.copy()
    # Only pixels within the blur's reach of a line differ from their cell's value.
    for t_c, m, s_n, dv in ((t1c, m1, s1, v10 - v00), (t2c, m2, s2, v01 - v00)):
        sel = (t_c > -reach) & (dv != 0)
        tn = (t_c[sel][:, None] + m[sel][:, 0:1] * nodes[:, 0]
              + m[sel][:, 1:2] * nodes[:, 1]) / _pick(s_n, sel)
        pix[sel] += dv[sel] * (ndtr(tn) @ weights)
    cross = v11 - v10 - v01 + v00
    near = (cross != 0) & (t1c > -reach) & (t2c > -reach)
    if np.any(near):
        if psf_cov is None:
            rho = np.sum(m1[near] * m2[near], -1)
        else:
            rho = np.sum((m1[near] @ psf_cov) * m2[near], -1) / (s1[near] * s2[near])
        rho = np.clip(rho, -0.98, 0.98)
        h = (t1c[near][:, None] + m1[near][:, 0:1] * nodes[:, 0]
             + m1[near][:, 1:2] * nodes[:, 1]) / _pick(s1, near)
        k = (t2c[near][:, None] + m2[near][:, 0:1] * nodes[:, 0]
             + m2[near][:, 1:2] * nodes[:, 1]) / _pick(s2, near)
        pix[near] += cross[near] * (bivariate_normal_cdf(h, k, rho[:, None]) @ weights)
    return pix


def _dot_rims(pix: np.ndarray, discs: np.ndarray, tree: cKDTree, band: _Band,
              psf: _AnalyticPsf) -> None:
    """Multiply each pixel of ``band`` (``pix``, in place) by the blurred inside of the nearest
    dark disc (``discs`` (n, 3): centre and radius on the board; ``tree`` of their centres),
    ``1 - Phi(d/s - s kappa/2)`` (:func:`_render_analytic`; an isotropic PSF)."""
    bx, by, bx_u, bx_v, by_u, by_v = band.bx, band.by, band.bx_u, band.bx_v, band.by_u, band.by_v
    reach, sigma, nodes, weights = psf.reach, psf.sigma, psf.nodes, psf.weights
    dist, kk = tree.query(np.stack([bx.ravel(), by.ravel()], -1))
    dist, kk = dist.reshape(bx.shape), kk.reshape(bx.shape)
    ex = (bx - discs[kk, 0]) / np.maximum(dist, 1e-12)
    ey = (by - discs[kk, 1]) / np.maximum(dist, 1e-12)
    gu, gv = bx_u * ex + by_u * ey, bx_v * ex + by_v * ey  # grad of |b - c| in px
    g = np.maximum(np.hypot(gu, gv), 1e-300)
    d_in = (discs[kk, 2] - dist) / g  # px inside the rim
    # Second order along the normal, as for the lines. With e = (ex, ey), J = d b / d uv and
    # n = J^T e / g, |b - c| has n^T H n = sum_k e_k n^T (d^2 b_k / d uv^2) n
    # + (|J n|^2 - g^2) / |b - c| (px^-2 times mm), and the distance inside the rim is
    # d_in - (h / 2) d_in^2 with h = n^T H n / g (px^-1).
    nu, nv = gu / g, gv / g
    h = sum(e_k * band.normal_curvature(spl, nu, nv) for e_k, spl in ((ex, band.bxs),
                                                                       (ey, band.bys)))
    jn_sq = (bx_u * nu + bx_v * nv) ** 2 + (by_u * nu + by_v * nv) ** 2
    h = (h + (jn_sq - g * g) / np.maximum(dist, 1e-12)) / g
    d_in -= np.where(np.abs(d_in) < reach, 0.5 * h * d_in**2, 0.0)
    pix[d_in >= reach] = 0.0  # deep inside a dot
    sel = np.abs(d_in) < reach
    # rim curvature in the image: |det A| / (r |A e'|^3), A = (d b / d uv)^-1
    det_j = (bx_u * by_v - bx_v * by_u)[sel]
    exs, eys = ex[sel], ey[sel]
    a_u = (by_v[sel] * -eys - bx_v[sel] * exs) / det_j  # A @ e', e' = (-ey, ex)
    a_v = (-by_u[sel] * -eys + bx_u[sel] * exs) / det_j
    kappa = 1.0 / (np.abs(det_j) * discs[kk[sel], 2] * np.hypot(a_u, a_v) ** 3)
    nu, nv = (gu / g)[sel], (gv / g)[sel]
    dn = (d_in[sel][:, None] - nu[:, None] * nodes[:, 0]
          - nv[:, None] * nodes[:, 1]) / sigma
    pix[sel] *= 1.0 - ndtr(dn - 0.5 * sigma * kappa[:, None]) @ weights


def _pick(s_n: float | np.ndarray, sel: np.ndarray) -> float | np.ndarray:
    """The sd (px) of the selected pixels as a column, or the scalar of an isotropic PSF."""
    return s_n if np.isscalar(s_n) else s_n[sel][:, None]


def _render_supersampled(target: Target, bxs, bys, sensor: Sensor, sigma_px: float,
                         supersample: int, band_rows: int,
                         kernel: np.ndarray | None = None) -> np.ndarray:
    """Sub-sampled coverage (exact per straight edge), blur on the fine grid (the Gaussian of
    ``sigma_px``, or ``kernel`` sampled on the fine grid when given), then ``S x S`` box
    integration (see the module docstring)."""
    S = int(supersample)
    xs, ys, value = _cell_grid(target)
    discs = target.discs
    tree = cKDTree(discs[:, :2]) if len(discs) else None
    W, H = sensor.width_px, sensor.height_px
    if kernel is None:
        halo = int(np.ceil(4 * sigma_px)) + 1
    else:
        halo = int(np.ceil((kernel.shape[0] // 2) / S)) + 1
    out = np.empty((H, W))
    sub = (np.arange(S) + 0.5) / S - 0.5
    u = (np.arange(W)[:, None] + sub).ravel()  # shape (W S,)
    for r0 in range(0, H, band_rows):
        r1 = min(H, r0 + band_rows)
        a0, a1 = r0 - halo, r1 + halo
        v = (np.arange(a0, a1)[:, None] + sub).ravel()  # shape ((a1 - a0) S,)
        band = _Band.of(bxs, bys, v, u)  # shape (V, U)
        bx, by, bx_u, bx_v, by_u, by_v = (band.bx, band.by, band.bx_u, band.bx_v, band.by_u,
                                          band.by_v)
        ix, sx, wx = _edge_weight(bx, bx_u, bx_v, xs, S)
        iy, sy, wy = _edge_weight(by, by_u, by_v, ys, S)
        nx, ny = value.shape
        cov = value[ix, iy]  # away from every edge; blend the neighbours across edges:
        e = (wx > 0) | (wy > 0)
        ix, iy, wx, wy, ix2, iy2 = (ix[e], iy[e], wx[e], wy[e], np.clip(ix[e] + sx[e], 0, nx - 1),
                                    np.clip(iy[e] + sy[e], 0, ny - 1))
        cov[e] = ((1 - wx) * (1 - wy) * value[ix, iy] + wx * (1 - wy) * value[ix2, iy]
                  + (1 - wx) * wy * value[ix, iy2] + wx * wy * value[ix2, iy2])
        if tree is not None:
            dist, k = tree.query(np.stack([bx.ravel(), by.ravel()], -1))
            dist, k = dist.reshape(bx.shape), k.reshape(bx.shape)
            ex = (bx - discs[k, 0]) / np.maximum(dist, 1e-12)
            ey = (by - discs[k, 1]) / np.maximum(dist, 1e-12)
            # gradient of |b - c| in px: J^T e with J = d b / d (u, v)
            gu, gv = bx_u * ex + by_u * ey, bx_v * ex + by_v * ey
            g = np.maximum(np.hypot(gu, gv), 1e-300)
            d_px = (discs[k, 2] - dist) / g  # > 0 inside the disc
            beyond = _coverage_near(d_px, gu / g, gv / g, S)
            cov = cov * np.where(d_px > 0, beyond, 1.0 - beyond)
        if kernel is not None:
            cov = cv2.filter2D(cov, -1, kernel, borderType=cv2.BORDER_REPLICATE)
        elif sigma_px > 0:
            cov = cv2.GaussianBlur(cov, (0, 0), sigmaX=sigma_px * S, sigmaY=sigma_px * S,
                                   borderType=cv2.BORDER_REPLICATE)
        cov = cov.reshape(a1 - a0, S, W, S).mean(axis=(1, 3))
        out[r0:r1] = cov[halo: halo + (r1 - r0)]
    return out


def apply_radiometry(reflectance: np.ndarray, radiometry: Radiometry, rng: np.random.Generator
                     ) -> np.ndarray:
    """Signal, vignetting, noise, gamma and quantisation.

    Returns
    -------
    image : (H, W) uint8 or uint16 ndarray
    """
    rm = radiometry
    H, W = reflectance.shape
    signal = rm.black + (rm.white - rm.black) * (reflectance - 0.0)
    if rm.vignetting:
        v, u = np.mgrid[0:H, 0:W]
        r2 = ((u - (W - 1) / 2) ** 2 + (v - (H - 1) / 2) ** 2) / (((W - 1) / 2) ** 2
                                                                 + ((H - 1) / 2) ** 2)
        signal = signal * (1 - rm.vignetting * r2)
    signal = signal * rm.gain
    if rm.full_well_e:
        signal = rng.poisson(np.clip(signal, 0, None) * rm.full_well_e) / rm.full_well_e
    if rm.noise_sd:
        signal = signal + rng.normal(0.0, rm.noise_sd, signal.shape)
    signal = np.clip(signal, 0.0, 1.0)
    if rm.gamma != 1.0:
        signal = signal ** (1.0 / rm.gamma)
    full = 2**rm.bits - 1
    dtype = np.uint8 if rm.bits <= 8 else np.uint16
    return np.round(signal * full).astype(dtype)


def sharpen_image(image: np.ndarray, amount: float, sigma_px: float) -> np.ndarray:
    """A camera's in-built sharpening, an unsharp mask on the quantised frame:
    ``I' = (1 + amount) I - amount (G_sigma * I)``, ``G_sigma`` a Gaussian of ``sigma_px`` px,
    clipped and rounded to the input's integer type. Edges overshoot on both sides, which no
    Gaussian blur with pixel integration makes (the real PTZ set's frames do: a profile that
    overshoots 208 and settles at 195 DN within 1.5 px)."""
    if amount < 0 or sigma_px <= 0:
        raise ValueError(f"sharpening: amount {amount} must be >= 0 and sigma {sigma_px} px > 0")
    x = image.astype(float)
    wide = cv2.GaussianBlur(x, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    full = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    out = np.clip((1.0 + amount) * x - amount * wide, 0, full)
    return np.round(out).astype(image.dtype) if full != 1.0 else out


def project_points(points_board: np.ndarray, mapping, R: np.ndarray, t: np.ndarray
                   ) -> np.ndarray:
    """True image positions of board points, px (OpenCV convention).

    Parameters
    ----------
    points_board : (n, 3) ndarray
        Board frame, mm.

    Returns
    -------
    uv : (n, 2) ndarray
    """
    P = points_board @ R.T + t
    return mapping.project(P[:, :2] / P[:, 2:3])


@dataclass
class RenderedView:
    """One rendered image and its truth."""

    image: np.ndarray
    points_px: np.ndarray
    visible: np.ndarray
    R: np.ndarray
    t: np.ndarray
    sigma_px: float

    def truth_dict(self) -> dict:
        return {"rvec": cv2.Rodrigues(self.R)[0].ravel().tolist(), "tvec": self.t.tolist(),
                "points_px": self.points_px.tolist(), "visible": self.visible.tolist()}


def render_image(target: Target, mapping, R: np.ndarray, t: np.ndarray, sensor: Sensor,
                 optics: Optics | None = None, radiometry: Radiometry | None = None,
                 rng: np.random.Generator | int = 0, supersample: int = 4,
                 surface: BoardSurface | None = None) -> RenderedView:
    """Render one view of ``target`` at pose ``Rt_cam_board = (R, t)`` through ``mapping``.

    ``mapping`` is an :class:`~zoomcalib.optics.lens_camera.ExactMapping` (render through the
    exact ray-traced lens) or a :class:`~zoomcalib.camera.CameraModel` wrapped by
    :func:`camera_mapping`. A Gaussian PSF takes the analytic path when it applies, any other
    ``optics.psf`` the supersampled one (``supersample`` sub-samples per pixel side). With a
    non-flat ``surface`` the truth is the projection of the object points lifted onto it.

    Returns
    -------
    RenderedView
        The image, the true pixel position of every object point, and which of them fall
        inside the image (with a 1-px margin).
    """
    rng = np.random.default_rng(rng)
    optics = optics or Optics()
    radiometry = radiometry or Radiometry()
    sigma = psf_sigma_px(optics, sensor.pixel_pitch_mm)
    cov = render_coverage(target, mapping, R, t, sensor, sigma, supersample, surface=surface,
                          optics=optics)
    image = apply_radiometry(cov, radiometry, rng)
    points = target.object_points if surface is None else surface.lift(target.object_points)
    pts = project_points(points, mapping, R, t)
    visible = ((pts[:, 0] > 0) & (pts[:, 0] < sensor.width_px - 1)
               & (pts[:, 1] > 0) & (pts[:, 1] < sensor.height_px - 1))
    return RenderedView(image, pts, visible, R, t, sigma)


class camera_mapping:  # noqa: N801 (used like a function)
    """Adapter: a :class:`~zoomcalib.camera.CameraModel` as a renderer mapping."""

    def __init__(self, camera):
        self.camera = camera

    def project(self, xy: np.ndarray) -> np.ndarray:
        return self.camera.project_normalized(np.asarray(xy, float).reshape(-1, 2))

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        return self.camera.unproject_normalized(uv)


def _turn(vectors: np.ndarray, rotvecs: np.ndarray) -> np.ndarray:
    """Rotate each of ``vectors`` (n, 3) by its rotation vector ``rotvecs`` (n, 3), rad
    (Rodrigues: ``v cos a + (k x v) sin a + k (k . v)(1 - cos a)``, ``a = |w|, k = w / a``)."""
    angle = np.linalg.norm(rotvecs, axis=1, keepdims=True)
    k = np.divide(rotvecs, angle, out=np.zeros_like(rotvecs), where=angle > 0)
    return (vectors * np.cos(angle) + np.cross(k, vectors) * np.sin(angle)
            + k * np.sum(k * vectors, axis=1, keepdims=True) * (1.0 - np.cos(angle)))


class RollingShutterMapping:
    """A mapping whose rows are read out while the camera turns (a rolling shutter).

    Row ``v`` of an image ``height`` px high is read at ``f = v / height - 1/2`` of the readout
    from its middle, when the camera has turned by the rotation vector ``f w`` (``w``, rad, the
    turn over the whole readout): a point ``P`` of the camera frame at mid-readout is at
    ``R(f w) P`` then. ``project`` finds the row at which a point is seen (a fixed point: the
    row moves by about ``fx |w| / height`` px per px, a small fraction); ``unproject``
    turns a pixel's ray back to the mid-readout frame. Poses and truth refer to mid-readout.
    """

    def __init__(self, mapping, turn: np.ndarray, height: int):
        self.mapping, self.height = mapping, int(height)
        self.turn = np.asarray(turn, dtype=float).reshape(3)

    def _rotvecs(self, uv: np.ndarray) -> np.ndarray:
        return (uv[:, 1:2] / self.height - 0.5) * self.turn

    def project(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, 2)
        ray = np.column_stack([xy, np.ones(len(xy))])
        uv = self.mapping.project(xy)
        for _ in range(50):
            seen = _turn(ray, self._rotvecs(uv))
            moved, uv = uv, self.mapping.project(seen[:, :2] / seen[:, 2:3])
            if np.all(np.abs(uv - moved) < 1e-9):
                return uv
        raise RuntimeError(f"rolling shutter: the turn {self.turn.tolist()} rad moves a point's "
                           "row by more than a row per row: no frame is read out so")

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, float).reshape(-1, 2)
        xy = self.mapping.unproject(uv)
        ray = _turn(np.column_stack([xy, np.ones(len(xy))]), -self._rotvecs(uv))
        return ray[:, :2] / ray[:, 2:3]


def optics_dict(optics: Optics) -> dict:
    return asdict(optics)
