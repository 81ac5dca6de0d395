"""Detection error against the ground truth of a rendered data set (``dataset.json``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import read_json
from .opencv import Detection

__all__ = ["load_truth", "truth_names", "error_report", "chessboard_crlb", "dataset_crlb"]


def load_truth(folder: str | Path) -> tuple[Path, dict[str, np.ndarray], dict] | None:
    """Find ``dataset.json`` in ``folder`` or its parent.

    Returns
    -------
    (root, truth, dataset) or None
        ``truth`` maps an image path relative to ``root`` to its (n, 2) true points, px;
        ``dataset`` is the parsed ``dataset.json``.

    Raises
    ------
    ValueError
        One line naming ``dataset.json`` when it is not JSON.
    """
    folder = Path(folder).resolve()
    for root in (folder, folder.parent):
        f = root / "dataset.json"
        if f.exists():
            doc = read_json(f)
            truth = {v["file"]: np.asarray(v["points_px"], dtype=float)
                     for st in doc.get("steps", []) for v in st.get("views", [])}
            return root, truth, doc
    return None


def truth_names(files: list[Path], folder: str | Path, root: str | Path) -> list[str]:
    """Names of ``files``, found in ``folder`` or its subfolders, relative to ``root``.

    ``root`` is what :func:`load_truth` found (``folder`` resolved, or its parent), or the
    resolved ``folder`` when there is no truth. Only ``folder`` is resolved, never the files:
    an image that is a symbolic link to elsewhere keeps its place in the folder, so its name
    matches the truth's (``zoom_00/view_00.png``).
    """
    folder = Path(folder)
    prefix = folder.resolve().relative_to(Path(root).resolve())
    return [(prefix / Path(f).relative_to(folder)).as_posix() for f in files]


def error_report(detections: list[Detection], truth: dict[str, np.ndarray]) -> dict:
    """RMS, bias and noise of the detected points against the truth.

    ``bias`` is the mean error vector (px); ``noise`` the radial 1-sigma about it;
    ``rms`` the radial RMS (``rms^2 = |bias|^2 + noise^2``).
    """
    errs = []
    for d in detections:
        if d.error is None and d.file in truth and len(d.ids):
            errs.append(d.points - truth[d.file][d.ids])
    if not errs:
        return {"n_points": 0, "n_images": 0}
    e = np.concatenate(errs)  # shape (K, 2)
    bias = e.mean(axis=0)
    return {"n_images": len(errs), "n_points": len(e),
            "rms_px": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))),
            "bias_px": bias.tolist(),
            "noise_px": float(np.sqrt(np.sum(e.var(axis=0, ddof=1)))) if len(e) > 1 else 0.0,
            "max_px": float(np.max(np.linalg.norm(e, axis=1)))}


def chessboard_crlb(points: np.ndarray, pattern_size: tuple[int, int], sigma_px: float,
                    noise_sd: float, contrast: float, quant_step: float = 0.0,
                    window: int = 5) -> np.ndarray:
    """Cramér-Rao bound of every corner of a chessboard view, from the renderer's image model.

    The two edges through a corner follow the grid lines, whose image directions are taken from
    the neighbouring true corners (central differences inside the grid, one-sided at its border).

    Parameters
    ----------
    points : (rows * cols, 2) ndarray
        True corner positions, px, row-major (OpenCV order).
    pattern_size : (cols, rows)
    sigma_px, noise_sd, contrast, quant_step : float
        Gaussian PSF sd (px); noise sd, intensity step and quantisation step, all on the same
        intensity scale (fractions of full scale).

    Returns
    -------
    radial : (rows * cols,) ndarray
        ``sqrt(trace(cov))`` of the bound, px, with the blur taken as known.
    """
    from .crlb import corner_crlb

    cols, rows = pattern_size
    g = np.asarray(points, dtype=float).reshape(rows, cols, 2)
    along_row = np.gradient(g, axis=1)  # shape (rows, cols, 2)
    along_col = np.gradient(g, axis=0)
    angles = np.stack([np.arctan2(along_row[..., 1], along_row[..., 0]),
                       np.arctan2(along_col[..., 1], along_col[..., 0])], -1).reshape(-1, 2)
    bound = corner_crlb(sigma_px, noise_sd, contrast, angles, window, fit_sigma=False,
                        quant_step=quant_step)
    return np.asarray(bound.radial_rms).reshape(-1)


def dataset_crlb(dataset: dict, files: list[str], window: int = 5) -> float | None:
    """RMS over the given views' corners of the per-corner bound (px), for chessboard data sets
    rendered by zoomcalib (None for other targets)."""
    from ..targets import parse_pattern

    target = parse_pattern(dataset["pattern"])
    if target.kind != "chessboard":
        return None
    rm = dataset["radiometry"]
    contrast = rm["white"] - rm["black"]
    quant = 1.0 / (2 ** rm["bits"] - 1)
    radial = []
    for st in dataset["steps"]:
        for v in st["views"]:
            if v["file"] in files:
                radial.append(chessboard_crlb(np.asarray(v["points_px"]), target.pattern_size,
                                              st["psf_sigma_px"], rm["noise_sd"], contrast,
                                              quant, window))
    if not radial:
        return None
    r = np.concatenate(radial)
    return float(np.sqrt(np.mean(r**2)))
