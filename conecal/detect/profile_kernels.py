"""Compiled loops of the edge profile's fit (``background.fit_profile``, numba).

One pass over a patch's pixels builds the normal equations of a
piecewise-linear profile across an edge plus a few columns; a banded
Cholesky and a small Schur complement solve them. Coordinates: pixel
offsets from the patch's centre (px); values: attenuation.
"""

from __future__ import annotations

import numpy as np
from ..jit import njit


@njit(cache=True)
def profile_sums(dx, dy, phi, kappa, s_lo, knot, k, w2, extra, target):
    """Normal equations of an edge profile (``background.fit_profile``): the
    piecewise-linear profile on ``k`` knots ``knot`` px apart from ``s_lo`` of
    s = u + kappa v^2 (u across the direction ``phi``, v along it; ``dx``,
    ``dy`` pixel offsets, px), plus the columns v and ``extra`` (n, m - 1),
    weights ``w2``, data ``target``, all per pixel. Returns the knots'
    diagonal and first off-diagonal (k, k - 1), knots x columns (k, m),
    columns x columns (m, m), right-hand sides of knots (k) and columns
    (m), and per pixel its left knot, the right knot's weight and its
    columns (n, m). Sums run in pixel order, as ``np.bincount``'s do."""
    n = dx.shape[0]
    m = 1 + extra.shape[1]
    c, s = np.cos(phi), np.sin(phi)
    d = np.zeros(k)
    off = np.zeros(k - 1)
    BX = np.zeros((k, m))
    C = np.zeros((m, m))
    rB = np.zeros(k)
    rX = np.zeros(m)
    idx = np.empty(n, np.int64)
    tt = np.empty(n)
    X = np.empty((n, m))
    top = k - 1 - 1e-9
    for p in range(n):
        u = dx[p] * c + dy[p] * s
        v = -dx[p] * s + dy[p] * c
        q = min(max((u + kappa * v * v - s_lo) / knot, 0.0), top)
        i = int(np.floor(q))
        t = q - i
        idx[p] = i
        tt[p] = t
        X[p, 0] = v
        for j in range(1, m):
            X[p, j] = extra[p, j - 1]
        wp = w2[p]
        a0 = wp * (1 - t)
        a1 = wp * t
        y = target[p]
        d[i] += a0 * (1 - t)
        d[i + 1] += a1 * t
        off[i] += a0 * t
        rB[i] += a0 * y
        rB[i + 1] += a1 * y
        for j in range(m):
            xj = X[p, j]
            BX[i, j] += a0 * xj
            BX[i + 1, j] += a1 * xj
            rX[j] += wp * xj * y
            for l in range(m):
                C[j, l] += wp * xj * X[p, l]
    return d, off, BX, C, rB, rX, idx, tt, X


@njit(cache=True)
def profile_fit(dx, dy, phi, kappa, s_lo, knot, k, w2, extra, target, reg2):
    """The edge profile's least-squares fit (:func:`profile_sums`' normal
    equations and the smoothness prior ``reg2`` |second differences of the
    knots|^2, k >= 4): the knots' block (five bands) by a banded Cholesky, the few columns by
    their Schur complement. Returns (coefficients (k knots, then v's and the
    ``extra`` columns'), chi-square with the prior's term, model per pixel),
    or chi-square inf when a block is not positive definite."""
    d, off, BX, C, rB, rX, idx, tt, X = profile_sums(dx, dy, phi, kappa, s_lo, knot, k, w2, extra, target)
    m = X.shape[1]
    n = dx.shape[0]
    tr = 0.0
    for j in range(m):
        tr += C[j, j]
    # the prior's bands: reg2 times D2^T D2's diagonal (1 5 6 .. 6 5 1), first (-2 -4 .. -4 -2) and second (1 ..) off-diagonals
    b0 = np.full(k, 6.0 * reg2)
    b0[0] = b0[k - 1] = reg2
    b0[1] = b0[k - 2] = 5.0 * reg2
    b1 = np.full(k - 1, -4.0 * reg2)
    b1[0] = b1[k - 2] = -2.0 * reg2
    eps = 1e-9 * (d.sum() + b0.sum() + tr) / (k + m)
    # banded Cholesky A = L L^T, L's diagonal and two sub-diagonals
    L0 = np.empty(k)
    L1 = np.zeros(k)
    L2 = np.zeros(k)
    for i in range(k):
        if i >= 2:
            L2[i] = reg2 / L0[i - 2]
        if i >= 1:
            a1 = b1[i - 1] + off[i - 1]
            L1[i] = (a1 - (L2[i] * L1[i - 1] if i >= 2 else 0.0)) / L0[i - 1]
        q = b0[i] + d[i] + eps - L1[i] * L1[i] - L2[i] * L2[i]
        if not q > 0.0:
            return np.zeros(k + m), np.inf, np.zeros(n)
        L0[i] = np.sqrt(q)
    Z = np.empty((k, m + 1))
    for j in range(m + 1):
        for i in range(k):
            v = BX[i, j] if j < m else rB[i]
            if i >= 1:
                v -= L1[i] * Z[i - 1, j]
            if i >= 2:
                v -= L2[i] * Z[i - 2, j]
            Z[i, j] = v / L0[i]
        for i in range(k - 1, -1, -1):
            v = Z[i, j]
            if i + 1 < k:
                v -= L1[i + 1] * Z[i + 1, j]
            if i + 2 < k:
                v -= L2[i + 2] * Z[i + 2, j]
            Z[i, j] = v / L0[i]
    # the columns' Schur complement, by Gaussian elimination with pivoting
    S = C + eps * np.eye(m)
    b = rX.copy()
    for j in range(m):
        for i in range(k):
            b[j] -= BX[i, j] * Z[i, m]
            for l in range(m):
                S[j, l] -= BX[i, j] * Z[i, l]
    for c in range(m):
        piv = c + np.argmax(np.abs(S[c:, c]))
        if not abs(S[piv, c]) > 0.0:
            return np.zeros(k + m), np.inf, np.zeros(n)
        if piv != c:
            for l in range(m):
                S[c, l], S[piv, l] = S[piv, l], S[c, l]
            b[c], b[piv] = b[piv], b[c]
        for r in range(c + 1, m):
            f = S[r, c] / S[c, c]
            for l in range(c, m):
                S[r, l] -= f * S[c, l]
            b[r] -= f * b[c]
    cx = np.empty(m)
    for c in range(m - 1, -1, -1):
        v = b[c]
        for l in range(c + 1, m):
            v -= S[c, l] * cx[l]
        cx[c] = v / S[c, c]
    coef = np.empty(k + m)
    for i in range(k):
        v = Z[i, m]
        for j in range(m):
            v -= Z[i, j] * cx[j]
        coef[i] = v
    coef[k:] = cx
    model = np.empty(n)
    chi2 = 0.0
    for p in range(n):
        i = idx[p]
        t = tt[p]
        v = coef[i] * (1 - t) + coef[i + 1] * t
        for j in range(m):
            v += X[p, j] * cx[j]
        model[p] = v
        e = v - target[p]
        chi2 += w2[p] * e * e
    for i in range(k - 2):
        e = coef[i] - 2 * coef[i + 1] + coef[i + 2]
        chi2 += reg2 * e * e
    return coef, chi2, model
