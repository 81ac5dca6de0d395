"""Does lens distortion fall as a zoom lens zooms in? A check against the lensfun database.

Gardel, Lázaro & Lavest (2002), "Influence of mechanical errors in a zoom camera", leave lens
distortion out of their zoom calibration on the grounds that it decreases as the focal length
increases. This module reads the measured distortion of real zoom lenses from the lensfun database
(XML, licence CC-BY-SA 3.0) and tests that claim lens by lens.

Lensfun conventions used here
-----------------------------
Sources: lensfun's ``include/lensfun/lensfun.h.in`` (``enum lfDistortionModel``), its manual
(``docs/manual-main.txt``, elements ``<lens>``, ``<aspect-ratio>``, ``<distortion>``), and the
coordinate-system note in ``libs/lensfun/modifier.cpp`` (0.3.x; kept as
``libs/lensfun/legacy/legacy-modifier.cpp`` in later versions).

* Radii are normalised, centred on the image centre, with ``r = 1`` at the middle of the long edge,
  i.e. half the *shorter* side (the half height, in landscape) of the image the calibration was
  made on. That image has the lens's ``<aspect-ratio>`` (long / short side, default 3:2) and
  ``<cropfactor>``, so its corner (the half-diagonal) is at ``r_c = sqrt(1 + aspect^2)``:
  1.803 for 3:2, 5/3 for 4:3. Lensfun maps other sensors onto this frame by matching diagonals
  (crop factors), so a fraction of the half-diagonal carries over to any sensor.
* The models map the undistorted (ideal, rectilinear) radius ``r_u`` to the distorted (recorded)
  radius ``r_d``:

  - ``ptlens`` (attributes a, b, c): ``r_d = r_u (a r_u^3 + b r_u^2 + c r_u + 1 - a - b - c)``;
  - ``poly3`` (k1): ``r_d = r_u (1 - k1 + k1 r_u^2)``;
  - ``poly5`` (k1, k2): ``r_d = r_u (1 + k1 r_u^2 + k2 r_u^4)``.

  ``ptlens`` and ``poly3`` (Hugin's models) are pinned at ``r_d(1) = 1``: their linear term
  ``1 - a - b - c`` (or ``1 - k1``) is a change of scale (a focal length), not distortion.
* Each ``<distortion>`` entry holds at one nominal focal length ``focal`` (mm); lensfun
  interpolates between them.

Distortion measure
------------------
Every model is written as ``r_d = sum_j p_j r_u^j`` (j = 1..5). The radial displacement that is
*distortion* depends on which linear mapping ``s r_u`` counts as distortion-free
(``reference``):

* ``"paraxial"`` (default): ``s = p_1 = dr_d/dr_u`` at ``r_u = 0``, the optical definition
  (ISO 9039: distortion relative to the paraxial image height) and the one a pinhole + radial
  polynomial calibration (OpenCV) uses, where the focal length absorbs the linear term.
  For ``poly3`` it gives ``D(r) = k1 r^2 / (1 - k1)``.
* ``"best_scale"``: ``s`` the least-squares scale over points spread uniformly over the
  calibration frame: what is left if distortion is *ignored* in calibration and the focal length
  takes up what it can (the paper's situation).
* ``"lensfun"``: ``s = 1``, the raw model (pinned at the half height for ptlens and poly3,
  paraxial for poly5).

The displacement ``delta(r) = r_d(r) - s r`` is expressed as a fraction of the distortion-free
half-diagonal ``s r_c``; over ``r in [0, r_c]`` (every radius present in the frame) the measure
reports the value at the corner, the largest magnitude (``max_abs``) and its signed value
(``peak``: < 0 barrel, > 0 pincushion; the dominant kind of a "moustache" lens). In pixels it is
the fraction times the sensor's half-diagonal: 800 px for the 1280 x 960 default sensor.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO
from xml.etree import ElementTree

import numpy as np
from scipy.stats import spearmanr

__all__ = [
    "DISTORTION_MODELS",
    "REFERENCES",
    "ZoomLensDistortion",
    "DistortionMeasure",
    "LensTrend",
    "TrendSummary",
    "read_lensfun",
    "read_lensfun_xml",
    "lensfun_poly",
    "lensfun_forward",
    "distortion_measure",
    "half_diagonal_px",
    "lens_trend",
    "distortion_trend",
    "trend_table",
]

#: Lensfun distortion models read, with their coefficient names (in ``coeffs`` column order).
DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "ptlens": ("a", "b", "c"),
    "poly3": ("k1",),
    "poly5": ("k1", "k2"),
}
#: Choices of the distortion-free linear mapping (see the module docstring).
REFERENCES: tuple[str, ...] = ("paraxial", "best_scale", "lensfun")

_NUM = r"(\d+(?:\.\d+)?)"
_RANGE_MM = re.compile(_NUM + r"\s*-\s*" + _NUM + r"\s*mm", re.IGNORECASE)
_SINGLE_MM = re.compile(_NUM + r"\s*mm", re.IGNORECASE)
# lensfun's "[aperture]/[focal]" pattern, e.g. "2.8-3.5/25-45" or "4.5/300".
_APERTURE_FOCAL = re.compile(r"\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?/" + _NUM + r"(?:-" + _NUM + r")?")
_N_RADII = 401
_GRID = 64


@dataclass(frozen=True, eq=False)
class ZoomLensDistortion:
    """The distortion calibration of one zoom lens from the lensfun database.

    Attributes
    ----------
    maker, model : str
        The lens's identifying ``<maker>`` and ``<model>`` (the entries without ``lang``).
    mounts : tuple of str
    crop_factor : float
        Crop factor of the camera the calibration was made on (36 x 24 mm diagonal / sensor
        diagonal).
    aspect_ratio : float
        Long / short side of the calibration images (lensfun's default 1.5).
    focal_mm : (k,) ndarray
        Nominal focal lengths of the calibration entries, mm, ascending, distinct.
    dist_models : tuple of str
        (k,) lensfun model of each entry: ``"ptlens"``, ``"poly3"`` or ``"poly5"``.
    coeffs : (k, 3) ndarray
        Coefficients per entry, columns in :data:`DISTORTION_MODELS` order (``a, b, c``;
        ``k1, 0, 0``; ``k1, k2, 0``), dimensionless (normalised radius).
    focal_range_mm : tuple of float
        Nominal (min, max) focal length from the model name, ``<focal>`` or the calibration.
    source : str
        File name the entry was read from.
    """

    maker: str
    model: str
    mounts: tuple[str, ...]
    crop_factor: float
    aspect_ratio: float
    focal_mm: np.ndarray
    dist_models: tuple[str, ...]
    coeffs: np.ndarray
    focal_range_mm: tuple[float, float]
    source: str

    @property
    def n_focal(self) -> int:
        """Number of calibrated focal lengths ``k``."""
        return int(self.focal_mm.size)

    @property
    def r_corner(self) -> float:
        """Normalised radius of the calibration frame's corner, ``sqrt(1 + aspect^2)``."""
        return math.hypot(1.0, self.aspect_ratio)

    def measure(self, reference: str = "paraxial") -> DistortionMeasure:
        """The distortion measure at every calibrated focal length (:func:`distortion_measure`)."""
        return distortion_measure(self.dist_models, self.coeffs, self.aspect_ratio, reference)

    def opencv_distortion(self, fx: np.ndarray, image_size: tuple[int, int]
                          ) -> tuple[np.ndarray, float]:
        """OpenCV terms ``(k1, k2, 0, 0, k3)`` (n, 5) that render this lens's distortion at the
        steps ``fx`` (n,) px of a zoom sweep on an image of ``image_size`` (width, height) px.

        * Zoom: the sweep's position ``log(fx / fx_0) / log(fx_-1 / fx_0)`` is the lens's
          ``log(f / f_0) / log(f_-1 / f_0)`` over its calibrated focal lengths; the polynomial
          ``r_d = sum_j p_j r_u^j`` (:func:`lensfun_poly`) is interpolated linearly in
          ``log f`` between its entries and scaled to ``p_1 = 1`` (the paraxial scale is the
          focal length).
        * Field: the image's corner is the calibration frame's corner (lensfun's own rule for
          other sensors): ``r_u = r_c rho / d``, ``rho`` the radius in px, ``d`` the image's
          half-diagonal in px.
        * ``r_d / r_u = 1 + k1 x^2 + k2 x^4 + k3 x^6`` with ``x = rho / fx``, fitted by least
          squares on the displacement in px over ``rho in [0, d]`` (exact for ``poly3`` and
          ``poly5``; ``ptlens``'s odd powers are approximated).

        Returns the terms and the largest fit residual over the frame, px.
        """
        fx = np.asarray(fx, float)
        zoom = np.log(fx / fx[0]) / np.log(fx[-1] / fx[0]) if fx[-1] != fx[0] else 0 * fx
        log_f = np.log(self.focal_mm)
        at = log_f[0] + zoom * (log_f[-1] - log_f[0])
        poly = lensfun_poly(self.dist_models, self.coeffs)
        poly = poly / poly[:, :1]
        poly = np.column_stack([np.interp(at, log_f, poly[:, j]) for j in range(5)])
        d = 0.5 * math.hypot(*image_size)
        rho = np.linspace(0.0, d, 200)
        ratio = (poly[:, 1:] @ (self.r_corner * rho / d)[None, :] ** np.arange(1, 5)[:, None])
        terms, worst = np.zeros((len(fx), 5)), 0.0
        for i, f in enumerate(fx):
            x = rho / f
            basis = rho[:, None] * x[:, None] ** np.array([2, 4, 6])[None, :]  # px per term
            k, *_ = np.linalg.lstsq(basis, rho * ratio[i], rcond=None)
            terms[i, [0, 1, 4]] = k
            worst = max(worst, float(np.abs(basis @ k - rho * ratio[i]).max()))
        return terms, worst


@dataclass(frozen=True, eq=False)
class DistortionMeasure:
    """Model-independent distortion at ``k`` calibration entries.

    All values are fractions of the distortion-free half-diagonal ``s r_c`` (multiply by 100 for
    per cent, by the sensor's half-diagonal in px for pixels); negative = barrel, positive =
    pincushion.

    Attributes
    ----------
    corner : (k,) ndarray
        ``delta(r_c) / (s r_c)``: the displacement at the frame's corner.
    peak : (k,) ndarray
        The signed displacement of largest magnitude over ``r in [0, r_c]``.
    max_abs : (k,) ndarray
        ``|peak|``.
    r_peak : (k,) ndarray
        Where the peak is, as a fraction of ``r_c`` (1 = corner).
    scale : (k,) ndarray
        The distortion-free scale ``s`` of the reference (dimensionless).
    reference : str
    """

    corner: np.ndarray
    peak: np.ndarray
    max_abs: np.ndarray
    r_peak: np.ndarray
    scale: np.ndarray
    reference: str


def _parse_aspect(text: str | None) -> float:
    """Lensfun ``<aspect-ratio>``: a number or ``"W:H"``; default 1.5. Returns long / short."""
    if text is None or not text.strip():
        return 1.5
    text = text.strip()
    if ":" in text:
        w, h = (float(v) for v in text.split(":", 1))
        value = w / h
    else:
        value = float(text)
    return max(value, 1.0 / value)


def _name_focal_range(model: str) -> tuple[float, float] | None:
    """Focal range named in a lens model string (lensfun's patterns), or None."""
    m = _RANGE_MM.search(model)
    if m:
        return float(m.group(1)), float(m.group(2))
    m = _APERTURE_FOCAL.search(model)
    if m:
        lo = float(m.group(1))
        return lo, float(m.group(2)) if m.group(2) else lo
    m = _SINGLE_MM.search(model)
    if m:
        f = float(m.group(1))
        return f, f
    return None


def _plain_text(elem: ElementTree.Element, tag: str) -> str | None:
    """Text of the first child ``tag`` without a ``lang`` attribute (lensfun's identifier)."""
    for child in elem.findall(tag):
        if "lang" not in child.attrib:
            return (child.text or "").strip()
    return None


def _expand_paths(paths: str | Path | Iterable[str | Path]) -> list[Path]:
    if isinstance(paths, (str, Path)):
        paths = [paths]
    files: list[Path] = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.xml")) if p.is_dir() else [p])
    return files


def _parse_lens(
    elem: ElementTree.Element, source: str, min_focals: int, rectilinear_only: bool
) -> ZoomLensDistortion | None:
    maker = _plain_text(elem, "maker")
    model = _plain_text(elem, "model")
    crop = elem.findtext("cropfactor")
    if not maker or not model or crop is None:
        return None
    lens_type = (elem.findtext("type") or "rectilinear").strip()
    if rectilinear_only and lens_type != "rectilinear":
        return None
    entries: dict[float, tuple[str, list[float]]] = {}
    for dist in elem.iterfind("calibration/distortion"):
        name = dist.get("model", "")
        if name not in DISTORTION_MODELS or dist.get("focal") is None:
            continue
        focal = round(float(dist.get("focal")), 6)
        if focal in entries:  # a repeated focal length: keep the first entry
            continue
        values = [float(dist.get(c, "0")) for c in DISTORTION_MODELS[name]]
        entries[focal] = (name, values + [0.0] * (3 - len(values)))
    if len(entries) < min_focals:
        return None
    focals = sorted(entries)
    # The nominal focal range: model name first, then <focal>, then the calibration itself.
    rng = _name_focal_range(model)
    fel = elem.find("focal")
    if rng is None and fel is not None:
        if fel.get("min") is not None and fel.get("max") is not None:
            rng = (float(fel.get("min")), float(fel.get("max")))
        elif fel.get("value") is not None:
            rng = (float(fel.get("value")),) * 2
    if rng is None:
        rng = (focals[0], focals[-1])
    if not rng[0] < rng[1]:
        return None  # a prime
    return ZoomLensDistortion(
        maker=maker,
        model=model,
        mounts=tuple((m.text or "").strip() for m in elem.findall("mount")),
        crop_factor=float(crop),
        aspect_ratio=_parse_aspect(elem.findtext("aspect-ratio")),
        focal_mm=np.array(focals, dtype=float),
        dist_models=tuple(entries[f][0] for f in focals),
        coeffs=np.array([entries[f][1] for f in focals], dtype=float),
        focal_range_mm=(float(rng[0]), float(rng[1])),
        source=source,
    )


def read_lensfun(
    paths: str | Path | Iterable[str | Path],
    min_focals: int = 4,
    rectilinear_only: bool = True,
) -> list[ZoomLensDistortion]:
    """Read the zoom lenses with distortion calibrated at several focal lengths.

    Parameters
    ----------
    paths : path or iterable of paths
        Lensfun XML files, or directories (all their ``*.xml``, sorted by name).
    min_focals : int
        Keep lenses with ``ptlens``/``poly3``/``poly5`` entries at this many distinct focal
        lengths or more (a repeated focal length keeps its first entry).
    rectilinear_only : bool
        Skip lenses whose ``<type>`` is not rectilinear (fisheyes: their models are relative to
        another projection).

    Returns
    -------
    list of ZoomLensDistortion
        In file order, then document order. A lens is a zoom if the focal range in its model
        name (``"18-55mm"``, ``"2.8-3.5/25-45"``), or else its ``<focal min max>``, or else its
        calibration, has min < max; a named prime is skipped whatever its calibration says.
        Entries without a ``<cropfactor>`` are skipped (lensfun requires one).

    Examples
    --------
    >>> import io
    >>> xml = ('<lensdatabase><lens><maker>X</maker><model>X 10-30mm</model>'
    ...        '<cropfactor>2</cropfactor><calibration>'
    ...        + ''.join(f'<distortion model="poly3" focal="{f}" k1="-0.01"/>'
    ...                  for f in (10, 15, 20, 30))
    ...        + '</calibration></lens></lensdatabase>')
    >>> lens, = read_lensfun_xml(io.StringIO(xml))
    >>> lens.focal_mm.tolist(), lens.dist_models[0], lens.aspect_ratio
    ([10.0, 15.0, 20.0, 30.0], 'poly3', 1.5)
    """
    lenses: list[ZoomLensDistortion] = []
    for path in _expand_paths(paths):
        lenses.extend(read_lensfun_xml(path, min_focals, rectilinear_only, path.name))
    return lenses


def read_lensfun_xml(
    source: str | Path | IO,
    min_focals: int = 4,
    rectilinear_only: bool = True,
    source_name: str | None = None,
) -> list[ZoomLensDistortion]:
    """Read one lensfun XML file (path or file object); see :func:`read_lensfun`.

    ``source_name`` is recorded as each lens's ``source`` (default: the file name).
    """
    name = source_name
    if name is None:
        name = Path(source).name if isinstance(source, (str, Path)) else "<stream>"
    root = ElementTree.parse(source).getroot()
    out = []
    for elem in root.iter("lens"):
        lens = _parse_lens(elem, name, min_focals, rectilinear_only)
        if lens is not None:
            out.append(lens)
    return out


def lensfun_poly(dist_models: str | Sequence[str], coeffs: np.ndarray) -> np.ndarray:
    """Lensfun models as polynomials ``r_d = sum_j p_j r_u^j``, j = 1..5.

    Parameters
    ----------
    dist_models : str or sequence of str
        One model name, or (k,) names.
    coeffs : (3,) or (k, 3) ndarray
        Coefficients in :data:`DISTORTION_MODELS` column order.

    Returns
    -------
    p : (k, 5) ndarray
        ``p[:, j-1]`` multiplies ``r_u^j``; ``p[:, 0]`` is the paraxial scale ``dr_d/dr_u(0)``.

    Examples
    --------
    >>> lensfun_poly("ptlens", np.array([0.01, -0.03, 0.0])).round(3).tolist()
    [[1.02, 0.0, -0.03, 0.01, 0.0]]
    >>> lensfun_poly("poly3", np.array([-0.02, 0.0, 0.0])).round(3).tolist()
    [[1.02, 0.0, -0.02, 0.0, 0.0]]
    """
    c = np.atleast_2d(np.asarray(coeffs, dtype=float))
    names = [dist_models] * c.shape[0] if isinstance(dist_models, str) else list(dist_models)
    if len(names) != c.shape[0]:
        raise ValueError(f"{len(names)} model names for {c.shape[0]} coefficient rows")
    p = np.zeros((c.shape[0], 5))
    for i, (name, (c0, c1, c2)) in enumerate(zip(names, c, strict=True)):
        if name == "ptlens":
            p[i] = (1.0 - c0 - c1 - c2, c2, c1, c0, 0.0)
        elif name == "poly3":
            p[i] = (1.0 - c0, 0.0, c0, 0.0, 0.0)
        elif name == "poly5":
            p[i] = (1.0, 0.0, c0, 0.0, c1)
        else:
            raise ValueError(f"unknown lensfun distortion model {name!r}")
    return p


def lensfun_forward(r_u: np.ndarray, dist_models: str | Sequence[str], coeffs) -> np.ndarray:
    """Distorted radius ``r_d`` of undistorted radii ``r_u`` (lensfun normalised units).

    Parameters
    ----------
    r_u : (n,) ndarray
        Undistorted radii, normalised (1 = half the short side of the calibration frame).
    dist_models, coeffs
        As in :func:`lensfun_poly`: k entries.

    Returns
    -------
    r_d : (k, n) ndarray

    Examples
    --------
    >>> lensfun_forward(np.array([0.0, 1.0, 2.0]), "poly3", [-0.02, 0, 0]).round(4).tolist()
    [[0.0, 1.0, 1.88]]
    """
    p = lensfun_poly(dist_models, coeffs)
    r = np.asarray(r_u, dtype=float)
    powers = r[None, :] ** np.arange(1, 6)[:, None]  # (5, n)
    return p @ powers


_RECT_SAMPLES: dict[float, np.ndarray] = {}


def _frame_radii(aspect_ratio: float) -> np.ndarray:
    """(_GRID^2,) radii of cell centres of a uniform grid over a quadrant of the frame."""
    key = round(float(aspect_ratio), 9)
    if key not in _RECT_SAMPLES:
        t = (np.arange(_GRID) + 0.5) / _GRID
        x, y = np.meshgrid(t * aspect_ratio, t)
        _RECT_SAMPLES[key] = np.hypot(x, y).ravel()
    return _RECT_SAMPLES[key]


def distortion_measure(
    dist_models: str | Sequence[str],
    coeffs,
    aspect_ratio: float = 1.5,
    reference: str = "paraxial",
) -> DistortionMeasure:
    """Distortion of lensfun entries as displacement over the frame (see the module docstring).

    Parameters
    ----------
    dist_models : str or sequence of str
        Model name(s), k entries.
    coeffs : (3,) or (k, 3) array_like
        Coefficients in :data:`DISTORTION_MODELS` column order.
    aspect_ratio : float
        Long / short side of the calibration frame; the corner is at ``r_c = sqrt(1 + aspect^2)``.
    reference : {'paraxial', 'best_scale', 'lensfun'}
        Which linear mapping ``s r_u`` is distortion-free.

    Returns
    -------
    DistortionMeasure
        Arrays of shape (k,), fractions of the half-diagonal ``s r_c``.

    Examples
    --------
    Paraxial distortion of ``poly3`` is ``k1 r^2 / (1 - k1)``; at the 3:2 corner ``r^2 = 3.25``:

    >>> m = distortion_measure("poly3", [-0.02, 0, 0])
    >>> float(m.corner[0].round(6)), float(m.peak[0].round(6)), float(-3.25 * 0.02 / 1.02)
    (-0.063725, -0.063725, -0.06372549019607843)
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {REFERENCES}, not {reference!r}")
    p = lensfun_poly(dist_models, coeffs)
    r_c = math.hypot(1.0, aspect_ratio)
    r = np.linspace(0.0, r_c, _N_RADII)
    r_d = p @ (r[None, :] ** np.arange(1, 6)[:, None])  # (k, n)
    if reference == "paraxial":
        s = p[:, 0].copy()
    elif reference == "lensfun":
        s = np.ones(p.shape[0])
    else:
        rs = _frame_radii(aspect_ratio)
        rd_s = p @ (rs[None, :] ** np.arange(1, 6)[:, None])
        s = rd_s @ rs / (rs @ rs)
    delta = (r_d - s[:, None] * r[None, :]) / (s[:, None] * r_c)
    i_peak = np.argmax(np.abs(delta), axis=1)
    rows = np.arange(delta.shape[0])
    peak = delta[rows, i_peak]
    return DistortionMeasure(
        corner=delta[:, -1].copy(),
        peak=peak,
        max_abs=np.abs(peak),
        r_peak=r[i_peak] / r_c,
        scale=s,
        reference=reference,
    )


def half_diagonal_px(width_px: int = 1280, height_px: int = 960) -> float:
    """Half the diagonal of a ``width_px x height_px`` sensor, px (800 for 1280 x 960).

    >>> half_diagonal_px()
    800.0
    """
    return 0.5 * math.hypot(width_px, height_px)


@dataclass(frozen=True)
class LensTrend:
    """How the distortion of one zoom lens varies with focal length.

    Magnitudes are ``max_abs`` of :class:`DistortionMeasure` (fraction of the half-diagonal);
    ``*_px`` are the same in pixels on the summary's sensor. Signs: -1 barrel, +1 pincushion,
    0 below the sign tolerance.

    Attributes
    ----------
    maker, model, source : str
    crop_factor : float
    n_focal : int
    focal_min_mm, focal_max_mm : float
        The calibrated focal range, mm.
    abs_wide, abs_tele : float
        ``max_abs`` at the shortest and longest calibrated focal length.
    abs_min : float
        The smallest ``max_abs`` over the calibrated focal lengths.
    focal_at_min_mm : float
        Where it is (first occurrence), mm.
    min_location : {'wide', 'interior', 'tele'}
    spearman : float
        Spearman rank correlation of focal length and ``max_abs`` (nan if ``max_abs`` is
        constant); -1 = strictly decreasing.
    monotone_decreasing : bool
        ``max_abs`` never rises by more than the tolerance from one focal length to the next, and
        ends lower than it starts: the paper's assumption.
    tele_below_wide : bool
        ``abs_tele < abs_wide`` (the weak form).
    sign_wide, sign_tele : int
        Sign of ``peak`` at the two ends.
    sign_change : bool
        Both barrel and pincushion occur across the zoom.
    barrel_to_pincushion : bool
        Barrel at the wide end, pincushion at the tele end.
    abs_wide_px, abs_tele_px : float
    tele_rise_px : float
        ``abs_tele - abs_min`` in pixels: how far |distortion| climbs back from its minimum by the
        tele end (0 when the minimum is at the tele end).
    """

    maker: str
    model: str
    source: str
    crop_factor: float
    n_focal: int
    focal_min_mm: float
    focal_max_mm: float
    abs_wide: float
    abs_tele: float
    abs_min: float
    focal_at_min_mm: float
    min_location: str
    spearman: float
    monotone_decreasing: bool
    tele_below_wide: bool
    sign_wide: int
    sign_tele: int
    sign_change: bool
    barrel_to_pincushion: bool
    abs_wide_px: float
    abs_tele_px: float
    tele_rise_px: float


def lens_trend(
    lens: ZoomLensDistortion,
    reference: str = "paraxial",
    tol: float = 0.0,
    sign_tol: float = 1e-4,
    width_px: int = 1280,
    height_px: int = 960,
) -> LensTrend:
    """The trend of one lens's distortion with focal length (see :class:`LensTrend`).

    Parameters
    ----------
    lens : ZoomLensDistortion
    reference : {'paraxial', 'best_scale', 'lensfun'}
    tol : float
        Rise of ``max_abs`` between neighbouring focal lengths still counted as "not increasing",
        fraction of the half-diagonal (0: strict).
    sign_tol : float
        ``|peak|`` below this has no sign (fraction of the half-diagonal; 1e-4 is 0.08 px on a
        1280 x 960 sensor).
    width_px, height_px : int
        Sensor for the pixel values.
    """
    m = lens.measure(reference)
    mag, f = m.max_abs, lens.focal_mm
    sign = np.where(mag < sign_tol, 0, np.sign(m.peak)).astype(int)
    i_min = int(np.argmin(mag))
    location = "wide" if i_min == 0 else "tele" if i_min == mag.size - 1 else "interior"
    rho = float(spearmanr(f, mag).statistic) if np.ptp(mag) > 0 else float("nan")
    hd = half_diagonal_px(width_px, height_px)
    return LensTrend(
        maker=lens.maker,
        model=lens.model,
        source=lens.source,
        crop_factor=lens.crop_factor,
        n_focal=lens.n_focal,
        focal_min_mm=float(f[0]),
        focal_max_mm=float(f[-1]),
        abs_wide=float(mag[0]),
        abs_tele=float(mag[-1]),
        abs_min=float(mag[i_min]),
        focal_at_min_mm=float(f[i_min]),
        min_location=location,
        spearman=rho,
        monotone_decreasing=bool(np.all(np.diff(mag) <= tol) and mag[-1] < mag[0]),
        tele_below_wide=bool(mag[-1] < mag[0]),
        sign_wide=int(sign[0]),
        sign_tele=int(sign[-1]),
        sign_change=bool(np.any(sign < 0) and np.any(sign > 0)),
        barrel_to_pincushion=bool(sign[0] < 0 and sign[-1] > 0),
        abs_wide_px=float(mag[0] * hd),
        abs_tele_px=float(mag[-1] * hd),
        tele_rise_px=float((mag[-1] - mag[i_min]) * hd),
    )


@dataclass(frozen=True)
class TrendSummary:
    """The trend of distortion with focal length across zoom lenses.

    Fractions are of ``n_lenses``; magnitudes are ``max_abs`` (fraction of the half-diagonal)
    and pixels on a ``width_px x height_px`` sensor; quartiles are (25, 50, 75) percentiles.

    Attributes
    ----------
    n_lenses : int
    reference : str
    tol, sign_tol : float
    width_px, height_px : int
    half_diagonal_px : float
    frac_monotone_decreasing : float
        Fraction of lenses whose |distortion| falls monotonically with focal length.
    frac_assumption_holds : float
        The paper's assumption ("distortion decreases as focal length increases"), read as
        monotone decrease: equal to ``frac_monotone_decreasing``.
    frac_tele_below_wide : float
        Weak form: less distortion at the tele end than at the wide end.
    frac_spearman_negative : float
        Rank correlation of focal length and |distortion| below zero.
    spearman_quartiles : tuple of float
        Over lenses with a defined correlation.
    min_location_frac : dict
        Fraction of lenses with the minimum |distortion| at the 'wide' end, 'interior', 'tele' end.
    frac_sign_change : float
        Both barrel and pincushion occur across the zoom.
    frac_barrel_to_pincushion : float
        Barrel at the wide end and pincushion at the tele end.
    frac_barrel_wide, frac_pincushion_tele : float
    abs_wide_quartiles, abs_tele_quartiles : tuple of float
        |distortion| at the ends, fraction of the half-diagonal.
    abs_wide_px_quartiles, abs_tele_px_quartiles : tuple of float
        The same in pixels.
    frac_tele_above_1px : float
        Lenses with more than 1 px of distortion at the tele end.
    frac_tele_rise_above_1px : float
        Lenses whose |distortion| climbs back by more than 1 px from its minimum to the tele end.
    lenses : tuple of LensTrend
    """

    n_lenses: int
    reference: str
    tol: float
    sign_tol: float
    width_px: int
    height_px: int
    half_diagonal_px: float
    frac_monotone_decreasing: float
    frac_assumption_holds: float
    frac_tele_below_wide: float
    frac_spearman_negative: float
    spearman_quartiles: tuple[float, float, float]
    min_location_frac: dict[str, float]
    frac_sign_change: float
    frac_barrel_to_pincushion: float
    frac_barrel_wide: float
    frac_pincushion_tele: float
    abs_wide_quartiles: tuple[float, float, float]
    abs_tele_quartiles: tuple[float, float, float]
    abs_wide_px_quartiles: tuple[float, float, float]
    abs_tele_px_quartiles: tuple[float, float, float]
    frac_tele_above_1px: float
    frac_tele_rise_above_1px: float
    lenses: tuple[LensTrend, ...]

    def as_dict(self) -> dict:
        """The aggregate numbers (without the per-lens list), JSON-friendly."""
        d = asdict(self)
        d.pop("lenses")
        return d


def _quartiles(x: np.ndarray) -> tuple[float, float, float]:
    if x.size == 0:
        return (float("nan"),) * 3
    q = np.percentile(x, [25.0, 50.0, 75.0])
    return float(q[0]), float(q[1]), float(q[2])


def distortion_trend(
    lenses: Sequence[ZoomLensDistortion],
    reference: str = "paraxial",
    tol: float = 0.0,
    sign_tol: float = 1e-4,
    width_px: int = 1280,
    height_px: int = 960,
) -> TrendSummary:
    """Test "distortion decreases as focal length increases" across zoom lenses.

    Parameters
    ----------
    lenses : sequence of ZoomLensDistortion
        At least one lens.
    reference, tol, sign_tol, width_px, height_px
        As in :func:`lens_trend`.

    Returns
    -------
    TrendSummary
    """
    if not lenses:
        raise ValueError("no lenses")
    trends = tuple(
        lens_trend(lens, reference, tol, sign_tol, width_px, height_px) for lens in lenses
    )
    n = len(trends)

    def frac(flags: Iterable[bool]) -> float:
        return float(sum(bool(v) for v in flags)) / n

    rho = np.array([t.spearman for t in trends])
    wide = np.array([t.abs_wide for t in trends])
    tele = np.array([t.abs_tele for t in trends])
    hd = half_diagonal_px(width_px, height_px)
    mono = frac(t.monotone_decreasing for t in trends)
    return TrendSummary(
        n_lenses=n,
        reference=reference,
        tol=tol,
        sign_tol=sign_tol,
        width_px=width_px,
        height_px=height_px,
        half_diagonal_px=hd,
        frac_monotone_decreasing=mono,
        frac_assumption_holds=mono,
        frac_tele_below_wide=frac(t.tele_below_wide for t in trends),
        frac_spearman_negative=frac(r < 0 for r in rho),
        spearman_quartiles=_quartiles(rho[np.isfinite(rho)]),
        min_location_frac={
            loc: frac(t.min_location == loc for t in trends) for loc in ("wide", "interior", "tele")
        },
        frac_sign_change=frac(t.sign_change for t in trends),
        frac_barrel_to_pincushion=frac(t.barrel_to_pincushion for t in trends),
        frac_barrel_wide=frac(t.sign_wide < 0 for t in trends),
        frac_pincushion_tele=frac(t.sign_tele > 0 for t in trends),
        abs_wide_quartiles=_quartiles(wide),
        abs_tele_quartiles=_quartiles(tele),
        abs_wide_px_quartiles=_quartiles(wide * hd),
        abs_tele_px_quartiles=_quartiles(tele * hd),
        frac_tele_above_1px=frac(tele * hd > 1.0),
        frac_tele_rise_above_1px=frac(t.tele_rise_px > 1.0 for t in trends),
        lenses=trends,
    )


def trend_table(summary: TrendSummary, digits: int = 6) -> list[dict]:
    """One row per lens, for CSV output (``csv.DictWriter(f, rows[0].keys())``).

    Parameters
    ----------
    summary : TrendSummary
    digits : int
        Floats are rounded to this many decimals.

    Returns
    -------
    list of dict
        Keys: the fields of :class:`LensTrend` plus ``reference``; magnitudes ``abs_*`` are
        fractions of the half-diagonal, ``abs_*_px`` pixels on the summary's sensor.
    """
    rows = []
    for t in summary.lenses:
        row: dict = {}
        for key, value in asdict(t).items():
            row[key] = round(value, digits) if isinstance(value, float) else value
        row["reference"] = summary.reference
        rows.append(row)
    return rows


def packaged_extract() -> Path:
    """The lensfun extract shipped with the package (56 entries, CC-BY-SA 3.0)."""
    from importlib import resources

    return Path(str(resources.files("zoomcalib.study") / "data" / "lensfun-zoom-extract.xml"))


def find_lens(name: str, source: str | Path | None = None) -> ZoomLensDistortion:
    """The one zoom lens of a lensfun database (``source``, default :func:`packaged_extract`)
    whose ``"maker model"`` equals ``name`` or, failing that, contains it (case-insensitive).
    ValueError naming the candidates when none or several match."""
    source = source or packaged_extract()
    lenses = read_lensfun(source, min_focals=2)
    key = name.lower()
    hits = [x for x in lenses if key in f"{x.maker} {x.model}".lower()]
    exact = [x for x in hits if key == f"{x.maker} {x.model}".lower()]
    hits = exact if len(exact) == 1 else hits
    if len(hits) != 1:
        found = "; ".join(f"{x.maker} {x.model}" for x in hits[:5]) or "none"
        raise ValueError(f"{len(hits)} zoom lenses in {source} match {name!r} ({found}); "
                         "name one lens")
    return hits[0]


def sweep_distortion(name: str, fx: np.ndarray, image_size: tuple[int, int],
                     source: str | Path | None = None) -> dict:
    """Options ``dist`` and ``distortion_source`` of
    :func:`zoomcalib.render.sweep.render_zoom_sweep` that render a sweep (steps ``fx`` px)
    through the distortion of the lens :func:`find_lens` finds
    (:meth:`ZoomLensDistortion.opencv_distortion`)."""
    lens = find_lens(name, source)
    dist, residual = lens.opencv_distortion(fx, image_size)
    return {"dist": dist, "distortion_source": {
        "kind": "lensfun", "lens": f"{lens.maker} {lens.model}", "source": lens.source,
        "focal_mm": lens.focal_mm.tolist(), "fit_residual_px": residual}}


def study_summary(csv_path: str | Path, source: str | Path | None = None) -> dict:
    """Summary numbers of the distortion trend for the study report, with the per-lens table
    written to ``csv_path``.

    Parameters
    ----------
    source : path, optional
        A lensfun database (folder or XML files); default :func:`packaged_extract`.
    """
    from ..io import write_csv

    src = packaged_extract() if source is None else Path(source)
    lenses = read_lensfun(src)
    summary = distortion_trend(lenses)
    write_csv(csv_path, trend_table(summary))
    d = summary.as_dict()
    return {"source": str(src), "n_lenses": d["n_lenses"],
            "fraction_monotone_decreasing": d["frac_monotone_decreasing"],
            "fraction_tele_below_wide": d["frac_tele_below_wide"],
            "fraction_sign_change": d["frac_sign_change"],
            "median_abs_wide_px": d["abs_wide_px_quartiles"][1],
            "median_abs_tele_px": d["abs_tele_px_quartiles"][1],
            "fraction_tele_above_1px": d["frac_tele_above_1px"]}
