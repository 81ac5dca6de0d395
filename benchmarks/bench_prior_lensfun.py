"""The second-difference prior in log focal length on real zoom lenses: how well it predicts a
zoom step it has no data for, with ``tau`` from REML and marginalised, on the corner's
displacement and on k1.

``python benchmarks/bench_prior_lensfun.py [--data DIR] [--noise 0.001] [--seed 0]``

The lensfun database (``--data``: a folder of its XML files; default the real-data folder
beside this checkout, else the extract in ``tests/data/lensfun``) holds the distortion of real
zoom lenses measured at several focal lengths. For every lens with 5 or more focal lengths
spanning at least 35 % in focal length, the distortion at the frame's corner (a fraction of the
half-diagonal, :meth:`~zoomcalib.study.lensfun.ZoomLensDistortion.measure`) is the path; each
focal length gets Gaussian noise of sd ``--noise``, and one step is hidden (no data: the long
end, where a zoom-wide calibration's views cannot measure distortion and the prior carries it,
or the middle step). The prior of :mod:`zoomcalib.calibrate.zoommodel` predicts the hidden
value: with REML's ``tau`` (:func:`~zoomcalib.calibrate.zoommodel.pooled_prior_strength`) and
with ``tau`` marginalised (:func:`~zoomcalib.calibrate.zoommodel.marginal_tau`), each for the
prior on the corner's displacement (the zoom-wide adjustment's ``corner2``) and on OpenCV's
k1 (the path ``D (f / d)^2``, ``d`` the half-diagonal: the corner's displacement over the
squared normalised radius there), the same noise scaled alike. Printed per hidden step: the
number of lenses, the RMS and median of ``|z| = |error| / sigma`` (0.67 for honest Gaussian
sigmas) and how often it exceeds 2 and 3 (0.046 and 0.0027).

The paths are measured lenses, not draws from the prior: a lens whose distortion turns sharply
at one end of its range is what a single ``tau`` per path does not describe.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmark this checkout

from zoomcalib.calibrate.zoommodel import (  # noqa: E402
    ZoomModel,
    marginal_tau,
    path_posterior,
    pooled_prior_strength,
)
from zoomcalib.study.lensfun import read_lensfun  # noqa: E402

REAL = ROOT.parent / "shared" / "realdata" / "lensfun"
EXTRACT = ROOT / "tests" / "data" / "lensfun"
HALF_DIAGONAL_MM = 0.5 * np.hypot(36.0, 24.0)  # of the 35 mm frame (crop factor 1)


def held_out_z(lens, hide: int, noise: float, rng, form: str) -> tuple[float, float, bool]:
    """``error / sigma`` of the hidden step's prediction with REML's and the marginalised
    ``tau`` of the prior on the path ``form`` ('corner' or 'k1'), and whether REML sat at its
    lower bound."""
    scale = np.ones(lens.n_focal)
    if form == "k1":
        scale = (lens.focal_mm * lens.crop_factor / HALF_DIAGONAL_MM) ** 2
    truth = lens.measure().corner * scale
    u = np.log(lens.focal_mm)
    sd = noise * scale
    sd[hide] = scale[hide]  # the whole half-diagonal: far beyond any distortion, no data
    values = truth + rng.normal(0.0, 1.0, len(u)) * noise * scale
    values[hide] = 0.0
    chain = (values, sd, u)
    tau, at_bound = pooled_prior_strength([chain], 2)
    mean, cov = path_posterior(chain, 2, tau)
    z_reml = (mean[hide] - truth[hide]) / np.sqrt(cov[hide, hide])
    model = ZoomModel("prior2", 2, tau, at_bound)
    extra = marginal_tau(model, [chain])[0]
    mean, cov = path_posterior(chain, 2, model.tau)
    z_marginal = (mean[hide] - truth[hide]) / np.sqrt(cov[hide, hide] + extra[hide, hide])
    return float(z_reml), float(z_marginal), at_bound


def _summary(label: str, z: np.ndarray) -> str:
    a = np.abs(z)
    return (f"  {label:>10s}: RMS {np.sqrt(np.mean(z ** 2)):.2f}, median |z| {np.median(a):.2f}, "
            f"P(|z| > 2) {np.mean(a > 2):.3f}, P(|z| > 3) {np.mean(a > 3):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REAL if REAL.is_dir() else EXTRACT))
    ap.add_argument("--noise", type=float, default=1e-3,
                    help="sd of the noise added to each step, fraction of the half-diagonal")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    lenses = [lens for lens in read_lensfun(args.data, min_focals=5)
              if np.log(lens.focal_mm[-1] / lens.focal_mm[0]) >= 0.3]
    print(f"# {len(lenses)} zoom lenses from {args.data}; noise {args.noise:g} of the "
          f"half-diagonal; seed {args.seed}")
    for form in ("corner", "k1"):
        for where in ("long end", "middle"):
            hide = [lens.n_focal - 1 if where == "long end" else lens.n_focal // 2
                    for lens in lenses]
            z = np.array([held_out_z(lens, h, args.noise, rng, form)
                          for lens, h in zip(lenses, hide, strict=True)])
            print(f"prior on the {form}, hidden step at the {where} ({len(z)} lenses; REML at "
                  f"its lower bound in {int(z[:, 2].sum())}):")
            print(_summary("REML", z[:, 0]))
            print(_summary("marginal", z[:, 1]))


if __name__ == "__main__":
    main()
