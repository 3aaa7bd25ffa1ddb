"""Tests of residual structure against everything the recording has.

Each test regresses the whitened residuals (dx/sigma, dy/sigma) on a small
basis of one recorded variable and asks how much chi^2 the basis explains
beyond a constant: under pure noise the drop is chi^2-distributed with
2 * (basis size) degrees of freedom. p-values are adjusted for the number
of tests by Holm's method, so trying many variables does not manufacture
a finding.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from ..stats import holm


def _drop(z, basis):
    """chi^2 explained by ``basis`` (m, k) beyond a constant, summed over the components of ``z`` (m, c)."""
    A = np.column_stack([np.ones(len(z)), basis])
    total = 0.0
    for c in range(z.shape[1]):
        y = z[:, c]
        y0 = y - y.mean()
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        r = y - A @ coef
        total += float(y0 @ y0 - r @ r)
    return total


def _standardise(x):
    x = np.asarray(x, float)
    s = x.std()
    return (x - x.mean()) / s if s > 0 else None


def variables(model) -> dict:
    """Bases (m, k) of every variable the recording offers, per observation."""
    o = model.obs
    rows = o.row
    t = model.times[rows]
    out = {"time": _standardise(t), "frame order": _standardise(rows)}
    for k, name in enumerate(model.axis_names):
        q = model.readings[:, k]
        if np.ptp(q) <= 0:
            continue
        v = np.gradient(q, model.times) if len(q) > 1 else np.zeros_like(q)
        out[f"reading {name}"] = _standardise(q[rows])
        if np.ptp(v) > 1e-9 * max(1.0, np.abs(v).max()):
            out[f"velocity {name}"] = _standardise(v[rows])
        if (np.sign(v) > 0).any() and (np.sign(v) < 0).any():
            out[f"direction of {name}"] = _standardise(np.sign(v[rows]))
        if model.rotary[k]:
            a = np.deg2rad(q[rows])
            out[f"{name} harmonics 1-2"] = np.column_stack([np.cos(a), np.sin(a), np.cos(2 * a), np.sin(2 * a)])
    if hasattr(o, "xy"):
        rows_, cols_ = model.geometry.shape
        xy = o.xy - np.array([(cols_ - 1) / 2, (rows_ - 1) / 2])
        out["detector position"] = np.column_stack([xy, xy[:, 0] * np.hypot(*xy.T), xy[:, 1] * np.hypot(*xy.T)])
    ids = np.unique(o.ids)
    if len(ids) > 1:
        out["marker id"] = np.column_stack([(o.ids == i).astype(float) for i in ids[1:]])
    return {k: (v if v is None or v.ndim == 2 else v[:, None]) for k, v in out.items() if v is not None}


def structure_tests(model, residual_whitened: np.ndarray, alpha: float = 0.01) -> list[dict]:
    """One record per variable: chi^2 drop, dof, p, Holm-adjusted p, significant."""
    z = residual_whitened.reshape(-1, model.n_comp)
    tests = []
    for name, basis in variables(model).items():
        d = _drop(z, basis)
        dof = z.shape[1] * basis.shape[1]
        tests.append({"variable": name, "chi2_explained": d, "dof": dof, "p": float(chi2.sf(d, dof))})
    for t, adj in zip(tests, holm([t["p"] for t in tests])):
        t["p_adjusted"] = float(adj)
        t["significant"] = bool(adj < alpha)
    return sorted(tests, key=lambda t: t["p"])
