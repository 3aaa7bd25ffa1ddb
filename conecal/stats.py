"""Robust statistics shared by the stages (one home for each formula)."""

from __future__ import annotations

import numpy as np
from scipy.special import bdtrc, ndtri

# sigma of a normal distribution per median absolute deviation: 1 / Phi^-1(3/4)
MAD_TO_SIGMA = 1.4826


def mad_sigma(x, axis=None, centre: bool = True):
    """Normal sigma of ``x`` from its median absolute deviation, about the
    median (``centre``) or about zero (values known to scatter about 0)."""
    x = np.asarray(x, dtype=float)
    c = np.median(x, axis=axis, keepdims=True) if centre else 0.0
    return MAD_TO_SIGMA * np.median(np.abs(x - c), axis=axis)


def spread_sigma(x, centre: bool = True) -> float:
    """Normal sigma of ``x`` by :func:`mad_sigma`, unless half of ``x`` or
    more sits on its median (within 1e-6 of the largest deviation): an 8-bit
    or JPEG image's flat blocks, whose neighbour differences are 0 where the
    noise was quantised away, so that the MAD is 0 while steps of a grey
    level or two are what a faint "shadow" is made of. Then the RMS of the
    share p of ``|x - median|`` nearest the median (p = 0.9, or half the way
    from the tied share to 1), scaled to sigma (exact for a normal
    distribution). A noiseless image's structure counts when it covers
    more than half of what is not tied."""
    x = np.asarray(x, dtype=float).ravel()
    if x.size == 0:
        return 0.0
    r = np.sort(np.abs(x - np.median(x)) if centre else np.abs(x))
    s = MAD_TO_SIGMA * float(np.median(r))
    tied = np.searchsorted(r, 1e-6 * float(r[-1]), side="right") / r.size
    if tied < 0.5:
        return s
    p = min(max(0.9, tied + (1.0 - tied) / 2), 0.999)
    keep = r[:max(int(np.ceil(p * r.size)), 1)]
    z = float(ndtri((1 + p) / 2))
    return max(s, float(np.sqrt(np.mean(keep * keep) / (1 - 2 * z * np.exp(-z * z / 2) / np.sqrt(2 * np.pi) / p))))


def difference_sigma(d, axis=None, centre: bool = True):
    """Sigma of one value from differences ``d = a - b`` of two equally noisy
    values (neighbouring pixels, consecutive frames): the differences scatter
    sqrt(2) times as much as each value."""
    return mad_sigma(d, axis=axis, centre=centre) / np.sqrt(2.0)


def _cluster_sums(d: np.ndarray, clusters) -> np.ndarray:
    """``d`` summed per cluster label (one label per value)."""
    return np.bincount(np.unique(clusters, return_inverse=True)[1], weights=d)


def paired_behind(r2_a: np.ndarray, r2_b: np.ndarray, clusters=None) -> tuple[float, float]:
    """Paired held-out chi^2 by which ``a`` trails ``b`` (per-observation held-out
    squared residuals of each) and its standard error. ``clusters`` (one label
    per observation, e.g. its frame): the error from the clusters' sums, for
    observations that share a cause within a cluster (a frame's own term)."""
    d = np.asarray(r2_a) - np.asarray(r2_b)
    if clusters is not None:
        d = _cluster_sums(d, clusters)
    return float(d.sum()), (float(np.sqrt(len(d) * d.var())) if len(d) > 1 else 0.0)


def mostly_behind(r2_a: np.ndarray, r2_b: np.ndarray, clusters, p: float = 1e-3, tie: float = 1.0) -> bool:
    """Whether ``a`` trails ``b`` in more clusters than chance allows: a
    one-sided sign test over the clusters' summed differences of held-out
    squared residuals (those within ``tie`` of 0 left out) at level ``p``.
    A gain that nearly every frame shares but a few hold most of is
    significant here while the clusters' standard error (``paired_behind``),
    dominated by those few, is not."""
    d = _cluster_sums(np.asarray(r2_a) - np.asarray(r2_b), clusters)
    d = d[np.abs(d) > tie]
    return len(d) > 0 and float(bdtrc(int(np.sum(d > 0)) - 1, len(d), 0.5)) < p


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
