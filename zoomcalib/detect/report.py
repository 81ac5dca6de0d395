"""Detection error against the ground truth of a rendered data set (``dataset.json``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .opencv import Detection

__all__ = ["load_truth", "error_report"]


def load_truth(folder: str | Path) -> tuple[Path, dict[str, np.ndarray]] | None:
    """Find ``dataset.json`` in ``folder`` or its parent.

    Returns
    -------
    (root, truth) or None
        ``truth`` maps an image path relative to ``root`` to its (n, 2) true points, px.
    """
    folder = Path(folder).resolve()
    for root in (folder, folder.parent):
        f = root / "dataset.json"
        if f.exists():
            doc = json.loads(f.read_text())
            truth = {v["file"]: np.asarray(v["points_px"], dtype=float)
                     for st in doc.get("steps", []) for v in st.get("views", [])}
            return root, truth
    return None


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
