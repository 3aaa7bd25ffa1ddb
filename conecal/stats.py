"""Robust statistics shared by the stages (one home for each formula)."""

from __future__ import annotations

import numpy as np

# sigma of a normal distribution per median absolute deviation: 1 / Phi^-1(3/4)
MAD_TO_SIGMA = 1.4826


def mad_sigma(x, axis=None, centre: bool = True):
    """Normal sigma of ``x`` from its median absolute deviation, about the
    median (``centre``) or about zero (values known to scatter about 0)."""
    x = np.asarray(x, dtype=float)
    c = np.median(x, axis=axis, keepdims=True) if centre else 0.0
    return MAD_TO_SIGMA * np.median(np.abs(x - c), axis=axis)


def difference_sigma(d, axis=None, centre: bool = True):
    """Sigma of one value from differences ``d = a - b`` of two equally noisy
    values (neighbouring pixels, consecutive frames): the differences scatter
    sqrt(2) times as much as each value."""
    return mad_sigma(d, axis=axis, centre=centre) / np.sqrt(2.0)


def paired_behind(r2_a: np.ndarray, r2_b: np.ndarray) -> tuple[float, float]:
    """Paired held-out chi^2 by which ``a`` trails ``b`` (per-observation held-out
    squared residuals of each) and its standard error."""
    d = np.asarray(r2_a) - np.asarray(r2_b)
    return float(d.sum()), (float(np.sqrt(len(d) * d.var())) if len(d) > 1 else 0.0)


def not_worse(behind: float, se: float) -> bool:
    """Held-out data cannot tell it is worse: within two standard errors, and 3."""
    return behind < max(3.0, 2 * se)


def holm(p) -> np.ndarray:
    """Holm's step-down adjustment of p-values (family-wise error over all of them)."""
    p = np.asarray(p, float)
    adj = np.empty(len(p))
    running = 0.0
    for rank, i in enumerate(np.argsort(p)):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        adj[i] = running
    return adj
