"""Compiled inner loops of the sub-pixel refinement (numba).

Pixel loops over one marker's region of interest: the robust background
fitted on an annulus, and the moments of the background-corrected
attenuation in the centroid window. Coordinates are ROI pixel indices;
the background polynomial is in offsets from the centre it was fitted at.
"""

from __future__ import annotations

import numpy as np
from ..jit import njit
from ..stats import MAD_TO_SIGMA
from .profile_kernels import profile_fit


@njit(cache=True)
def _design(dx, dy, quad, out):
    out[0] = 1.0
    out[1] = dx
    out[2] = dy
    if quad:
        out[3] = dx * dx
        out[4] = dx * dy
        out[5] = dy * dy


@njit(cache=True)
def _outside_all(i, j, ox, oy, orad):
    for k in range(ox.shape[0]):
        ex = j - ox[k]
        ey = i - oy[k]
        if ex * ex + ey * ey <= orad[k] * orad[k]:
            return False
    return True


@njit(cache=True)
def _kept_fit(X, Y, Z, keep, quad):
    """Least-squares coefficients (3 or 6, ``_design``'s order) of the points
    ``keep`` marks, and how many they are (the solve is skipped below 6)."""
    p = 6 if quad else 3
    row = np.zeros(6)
    AtA = np.zeros((p, p))
    Atz = np.zeros(p)
    cnt = 0
    for t in range(X.shape[0]):
        if not keep[t]:
            continue
        cnt += 1
        _design(X[t], Y[t], quad, row)
        for a in range(p):
            Atz[a] += row[a] * Z[t]
            for b in range(p):
                AtA[a, b] += row[a] * row[b]
    if cnt < 2 * p:
        return np.zeros(p), cnt
    return np.linalg.solve(AtA, Atz), cnt


@njit(cache=True)
def fit_background(roi, inv, cx, cy, r_in, r_out, rw, ox, oy, orad, quad_min, f_quad=0.0):
    """Robust polynomial background from the annulus ``r_in..r_out`` about (cx, cy).

    Neighbour discs (ox, oy, orad) are left out unless that leaves < 30 % of
    the ring; pixels flagged in ``inv`` never count. The fit is quadratic
    when the ring is nearly whole and has more than ``quad_min`` pixels,
    planar otherwise; 3 rounds of rejection at 3.5 sigma. With ``f_quad`` >
    0 the quadratic terms are kept only when they explain the ring's inliers
    better than a plane by that F ratio: on an annulus the curvature
    x^2 + y^2 is nearly constant, so a curvature the ring does not show
    moves the value extrapolated to the centre by several times the ring's
    noise over its pixels (and a shadow's second moment, which weighs the
    window's rim by rho^2, by more than a small sphere's whole size).

    Returns (coef[6], quad, sigma, n_inliers, rms dx of inliers, hidden
    fraction of the window); n_inliers = 0 on failure.
    """
    h, w = roi.shape
    n_full = 0
    n_masked = 0
    n_win = 0
    n_hidden = 0
    has_inv = inv.shape[0] == h
    for i in range(h):
        for j in range(w):
            dx = j - cx
            dy = i - cy
            r2 = dx * dx + dy * dy
            bad = has_inv and inv[i, j]
            if r2 <= rw * rw:
                n_win += 1
                if bad:
                    n_hidden += 1
            if r2 < r_in * r_in or r2 > r_out * r_out or bad:
                continue
            n_full += 1
            if _outside_all(i, j, ox, oy, orad):
                n_masked += 1
    hidden = n_hidden / max(n_win, 1)
    use_mask = n_masked >= 0.3 * n_full
    n = n_masked if use_mask else n_full
    coef = np.zeros(6)
    if n < 12:
        return coef, False, 0.0, 0, 0.0, hidden
    X = np.empty(n)
    Y = np.empty(n)
    Z = np.empty(n)
    m = 0
    for i in range(h):
        for j in range(w):
            dx = j - cx
            dy = i - cy
            r2 = dx * dx + dy * dy
            if r2 < r_in * r_in or r2 > r_out * r_out or (has_inv and inv[i, j]):
                continue
            if use_mask and not _outside_all(i, j, ox, oy, orad):
                continue
            X[m] = dx
            Y[m] = dy
            Z[m] = roi[i, j]
            m += 1
    quad = n > quad_min and n >= 0.85 * n_full
    p = 6 if quad else 3
    keep = np.ones(n, np.bool_)
    row = np.zeros(6)
    sig = 0.0
    res = np.empty(n)
    for _ in range(3):
        sol, cnt = _kept_fit(X, Y, Z, keep, quad)
        if cnt < 2 * p:
            break
        for a in range(p):
            coef[a] = sol[a]
        for a in range(p, 6):
            coef[a] = 0.0
        nk = 0
        absr = np.empty(cnt)
        for t in range(n):
            _design(X[t], Y[t], quad, row)
            v = Z[t]
            for a in range(p):
                v -= coef[a] * row[a]
            res[t] = v
            if keep[t]:
                absr[nk] = abs(v)
                nk += 1
        sig = MAD_TO_SIGMA * np.median(absr) + 1e-7  # floor: noiseless (simulated) data
        changed = False
        for t in range(n):
            k = abs(res[t]) < 3.5 * sig
            if k != keep[t]:
                changed = True
            keep[t] = k
        if not changed:
            break
    if quad and f_quad > 0:
        # the plane on the same inliers, and the F ratio of the three curvature terms
        rss_q = 0.0
        for t in range(n):
            if keep[t]:
                rss_q += res[t] * res[t]
        sol, cnt = _kept_fit(X, Y, Z, keep, False)
        if cnt > 12:
            rss_p = 0.0
            for t in range(n):
                if keep[t]:
                    v = Z[t] - sol[0] - sol[1] * X[t] - sol[2] * Y[t]
                    rss_p += v * v
            if (rss_p - rss_q) / 3.0 < f_quad * rss_q / (cnt - 6):
                quad = False
                for a in range(3):
                    coef[a] = sol[a]
                for a in range(3, 6):
                    coef[a] = 0.0
    n_in = 0
    sdx = 0.0
    for t in range(n):
        if keep[t]:
            n_in += 1
            sdx += X[t] * X[t]
    return coef, quad, sig, n_in, np.sqrt(sdx / max(n_in, 1) + 1e-9), hidden


@njit(cache=True)
def subtract_background(roi, coef, fx, fy):
    """``roi - background`` as float64; background centred at (fx, fy)."""
    h, w = roi.shape
    out = np.empty((h, w))
    row = np.zeros(6)
    for i in range(h):
        for j in range(w):
            _design(j - fx, i - fy, True, row)
            v = roi[i, j]
            for a in range(6):
                v -= coef[a] * row[a]
            out[i, j] = v
    return out


@njit(cache=True)
def window_moments(roi, coef, fx, fy, cx, cy, rw):
    """Moments of the background-corrected attenuation b in the disc of
    radius ``rw`` about (cx, cy).

    Returns (V, mx, my, Mxx, Myy, Mxy, Sxx_e, Syy_e, Sxx, sum|ex|, n) where
    (mx, my) is the centroid offset from (cx, cy), M.. the central second
    moments, S.._e = sum exp(clip(b, 0, 8)) * e^2 (for the noise that grows
    with attenuation), Sxx = sum ex^2, about the new centroid.
    """
    h, w = roi.shape
    row = np.zeros(6)
    V = 0.0
    Sx = 0.0
    Sy = 0.0
    Sxx = 0.0
    Syy = 0.0
    Sxy = 0.0
    E = 0.0
    Ex = 0.0
    Ey = 0.0
    Exx = 0.0
    Eyy = 0.0
    n = 0
    D = 0.0
    Dx = 0.0
    Dxx = 0.0
    i0 = max(int(np.floor(cy - rw - 1)), 0)
    i1 = min(int(np.ceil(cy + rw + 1)) + 1, h)
    j0 = max(int(np.floor(cx - rw - 1)), 0)
    j1 = min(int(np.ceil(cx + rw + 1)) + 1, w)
    lim = (rw + 0.5) * (rw + 0.5)
    for i in range(i0, i1):
        for j in range(j0, j1):
            dx = j - cx
            dy = i - cy
            r2 = dx * dx + dy * dy
            if r2 >= lim:
                continue
            # anti-aliased edge: a pixel counts by how much of it the disc covers,
            # so a window cut through a bright region stays symmetric
            wgt = min(rw + 0.5 - np.sqrt(r2), 1.0)
            _design(j - fx, i - fy, True, row)
            b = roi[i, j]
            for a in range(6):
                b -= coef[a] * row[a]
            b *= wgt
            n += 1
            V += b
            Sx += b * dx
            Sy += b * dy
            Sxx += b * dx * dx
            Syy += b * dy * dy
            Sxy += b * dx * dy
            e = np.exp(min(max(b, 0.0), 8.0)) * wgt * wgt
            E += e
            Ex += e * dx
            Ey += e * dy
            Exx += e * dx * dx
            Eyy += e * dy * dy
            D += wgt
            Dx += wgt * dx
            Dxx += wgt * (dx * dx + dy * dy)
    if V <= 0:
        return V, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, n
    mx = Sx / V
    my = Sy / V
    Mxx = Sxx / V - mx * mx
    Myy = Syy / V - my * my
    Mxy = Sxy / V - mx * my
    Sxx_e = Exx - 2 * mx * Ex + mx * mx * E
    Syy_e = Eyy - 2 * my * Ey + my * my * E
    sum_e2 = Dxx - 2 * (mx * Dx) + (mx * mx + my * my) * D  # approx: sum over window of |e|^2
    abs_ex = 0.0
    for i in range(i0, i1):
        for j in range(j0, j1):
            dx = j - cx
            dy = i - cy
            r2 = dx * dx + dy * dy
            if r2 >= lim:
                continue
            abs_ex += min(rw + 0.5 - np.sqrt(r2), 1.0) * abs(dx - mx)
    return V, mx, my, Mxx, Myy, Mxy, Sxx_e, Syy_e, sum_e2 / 2.0, abs_ex, n


@njit(cache=True)
def chord_patch(spheres, h, w, ss, jacobian):
    """Sphere shadows' chord profiles 2 mu sqrt(R^2 - rho^2) on an h x w px
    patch, each averaged over ss x ss samples per pixel (only the pixels its
    disc reaches are sampled). ``spheres``: (k, 4) x, y (px, patch
    pixel indices), R (px), mu (per px of chord). Returns (h, w, 1) float32:
    the sum over spheres; with ``jacobian`` (h, w, 4k): per sphere d/dx,
    d/dy, d/dR and d/dmu (the last times mu is its profile). The rim's
    1/sqrt(R^2 - rho^2), integrable over a pixel but not by samples, is
    kept finite at a fraction of a pixel inside the rim."""
    k = spheres.shape[0]
    out = np.zeros((h, w, 4 * k if jacobian else 1), np.float32)
    wt = 2.0 / (ss * ss)
    for n in range(k):
        x, y, R, mu = spheres[n, 0], spheres[n, 1], spheres[n, 2], spheres[n, 3]
        r = abs(R)
        c0 = min(max(int(np.floor(x - r - 1.0)), 0), w)
        c1 = min(max(int(np.ceil(x + r + 1.0)) + 1, 0), w)
        q0 = min(max(int(np.floor(y - r - 1.0)), 0), h)
        q1 = min(max(int(np.ceil(y + r + 1.0)) + 1, 0), h)
        r2 = R * R
        floor = 0.5 * r + 1e-6
        for i in range(q0, q1):
            for si in range(ss):
                dy = i + (si + 0.5) / ss - 0.5 - y
                for j in range(c0, c1):
                    a0 = 0.0
                    a1 = 0.0
                    a2 = 0.0
                    a3 = 0.0
                    for sj in range(ss):
                        dx = j + (sj + 0.5) / ss - 0.5 - x
                        q = r2 - dx * dx - dy * dy
                        if q <= 0.0:
                            continue
                        sq = np.sqrt(q)
                        a0 += sq
                        if jacobian:
                            inv = 1.0 / (sq if q > floor else np.sqrt(floor))
                            a1 += dx * inv
                            a2 += dy * inv
                            a3 += inv
                    if jacobian:
                        out[i, j, 4 * n] += wt * mu * a1
                        out[i, j, 4 * n + 1] += wt * mu * a2
                        out[i, j, 4 * n + 2] += wt * mu * R * a3
                        out[i, j, 4 * n + 3] += wt * a0
                    else:
                        out[i, j, 0] += wt * mu * a0
    return out


def warm_up() -> None:
    """Compile (or load from the cache) every kernel in this process, so that
    forked workers inherit them instead of each loading them again."""
    roi = np.zeros((16, 16), np.float32)
    e = np.zeros(0)
    coef = fit_background(roi, np.zeros((0, 0), np.bool_), 8.0, 8.0, 4.0, 7.0, 3.0, e, e, e, 150, 4.0)[0]
    subtract_background(roi, coef, 8.0, 8.0)
    window_moments(roi, coef, 8.0, 8.0, 8.0, 8.0, 3.0)
    for jacobian in (False, True):
        chord_patch(np.array([[4.0, 4.0, 2.0, 0.1]]), 8, 8, 3, jacobian)
    z = np.zeros(4)
    for extra in (np.zeros((4, 0)), np.zeros((4, 1)), np.zeros((4, 1), np.float32)):
        profile_fit(z, z, 0.0, 0.0, -2.0, 1.0, 6, z, extra, z, 1.0)
