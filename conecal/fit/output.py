"""The ``conecal-geometry/1`` document that every fit writes."""

from __future__ import annotations

import numpy as np

from .. import __version__
from ..geometry import ConeGeometry
from ..jsonio import rounded
from .core import FitResult

GEOMETRY_FORMAT = "conecal-geometry/1"


def fit_summary(res: FitResult, residual_px: np.ndarray, *, start: str, loss: str, centre_model: str = "centroid") -> dict:
    free = [n for n, f in zip(res.names, res.free) if f]
    return {
        "parameters": res.parameters_dict(),
        "correlation": {"names": free, "matrix": np.where(np.isfinite(res.correlation), res.correlation, 0.0)},
        "rms_px": float(np.sqrt(np.mean(residual_px ** 2))) if residual_px.size else None,
        "chi2_reduced": res.reduced_chi2,
        "n_observations": int(residual_px.shape[0]),
        "dof": res.dof,
        "function_evaluations": res.nfev,
        "start": start,
        "loss": loss,
        # what each measured marker centre was predicted as (see --centre-model)
        "centre_model": centre_model,
        "outliers": int(res.outliers.reshape(-1, 2).any(axis=1).sum()) if res.outliers.size else 0,
        "undetermined": res.undetermined,
        "null_combinations": res.null_combinations,
        "converged": res.success,
        "chi2_history": list(res.history),
    }


def geometry_document(stage: str, geometry: ConeGeometry, axes: list[dict], summary: dict,
                      residuals: list[dict], scan: str, extra: dict | None = None) -> dict:
    doc = {"format": GEOMETRY_FORMAT, "software": f"conecal {__version__}", "stage": stage, "scan": scan,
           **geometry.to_dict(), "axes": axes, "fit": summary, "residuals": residuals,
           "units": {"length": "mm", "angle": "deg", "residual": "px (measured - predicted)"}}
    if extra:
        doc.update(extra)
    return rounded(doc)
