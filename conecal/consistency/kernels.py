"""Compiled loops of the Radon-derivative tables and their look-up (numba)."""

from __future__ import annotations

import numpy as np
from ..jit import njit, prange


@njit(cache=True)
def cosine_weight(img, pu, pv, c_ref, r_ref, pp_u, pp_v, D):
    """``img * D / sqrt(D^2 + u^2 + v^2)`` with (u, v) in mm from the
    principal point (pp_u, pp_v), itself in mm from pixel (c_ref, r_ref)."""
    rows, cols = img.shape
    out = np.empty((rows, cols), np.float32)
    for r in range(rows):
        v = (r - r_ref) * pv - pp_v
        for c in range(cols):
            u = (c - c_ref) * pu - pp_u
            out[r, c] = img[r, c] * D / np.sqrt(D * D + u * u + v * v)
    return out


@njit(cache=True, parallel=True)
def radon_joseph(img, pu, pv, c_ref, r_ref, cos_a, sin_a, s0, ds, n_s):
    """2D Radon transform by Joseph's method.

    The line ``u cos(a) + v sin(a) = s`` (u, v in mm from pixel (c_ref,
    r_ref)) is stepped one pixel at a time along its major direction and the
    image interpolated linearly across it, so every line sees a smooth
    sampling of the image (pixel-driven splatting aliases at rational
    slopes). Returns (n_a, n_s) in image units * mm. Their noise:
    :func:`radon_joseph_variance`.
    """
    n_a = cos_a.shape[0]
    out = np.zeros((n_a, n_s), np.float32)
    # flat lines walk columns: a contiguous transposed copy keeps them row walks
    img_t = np.ascontiguousarray(img.T)
    for a in prange(n_a):
        ca = cos_a[a]
        sa = sin_a[a]
        acc = np.zeros(n_s)
        if abs(ca) >= abs(sa):     # steep line: one sample per row
            _angle_sums(img, s0, ds, sa, ca, pv, pu, r_ref, c_ref, acc)
            step = pv / abs(ca)
        else:                      # flat line: one sample per column
            _angle_sums(img_t, s0, ds, ca, sa, pu, pv, c_ref, r_ref, acc)
            step = pu / abs(sa)
        for k in range(n_s):
            out[a, k] = acc[k] * step
    return out


@njit(cache=True, inline="always")
def _row_span(base, step, top, n_s):
    """First and last offset index whose line meets one image row within
    [0, top] (``base``: the row coordinate of offset 0's line, ``step``:
    the distance between successive offsets' lines along the row)."""
    if step > 0:
        klo = int(np.ceil((0.0 - base) / step))
        khi = int(np.floor((top - base) / step))
    else:
        klo = int(np.ceil((top - base) / step))
        khi = int(np.floor((0.0 - base) / step))
    return max(klo, 0), min(khi, n_s - 1)


@njit(cache=True)
def _angle_sums(img, s0, ds, a_major, a_minor, p_major, p_minor, ref_major, ref_minor, acc):
    """Adds to ``acc[k]`` the samples of ``img[major, minor]`` on the lines
    ``a_minor * x_minor + a_major * x_major = s0 + k ds`` (mm from
    (ref_major, ref_minor), pitches p_*), one per major index, linear across
    the minor one; |a_minor| >= |a_major|.

    Row by row rather than line by line: along one image row the lines of
    successive k fall a fixed step apart, so the row is read in order
    (1.26 times faster than walking each line across the rows, same sums:
    benchmarks/bench_radon.py).
    """
    n_major, n_minor = img.shape
    n_s = acc.shape[0]
    first = (s0 + ref_major * p_major * a_major) / (a_minor * p_minor) + ref_minor
    step = ds / (a_minor * p_minor)
    dm = -p_major * a_major / (a_minor * p_minor)
    top = n_minor - 1.0
    for j in range(n_major):
        base = first + dm * j
        klo, khi = _row_span(base, step, top, n_s)
        row = img[j]
        for k in range(klo, khi + 1):
            m = base + step * k
            i = min(max(int(m), 0), n_minor - 2)
            acc[k] += row[i] + (row[i + 1] - row[i]) * (m - i)


@njit(cache=True, parallel=True)
def radon_joseph_variance(var, pu, pv, c_ref, r_ref, cos_a, sin_a, s0, ds, n_s):
    """Noise variance of :func:`radon_joseph`'s sums and covariance of each
    sum with the next offset's, for an image of independent pixel variances
    ``var``. Returns (V, C), each (n_a, n_s) in image units * mm^2:
    ``V[a, k] = Var(R[a, k])``, ``C[a, k] = Cov(R[a, k], R[a, k + 1])``.

    Neighbouring offsets (1 to 1.41 px apart along a row) share a pixel
    whenever both interpolate it: at 0 and 90 deg, where every row's phase
    is the same, the covariance is half the variance. A derivative taken
    across offsets needs it, or its variance is wrong by an angle-dependent
    factor. Offsets two apart never share a pixel.
    """
    n_a = cos_a.shape[0]
    V = np.zeros((n_a, n_s), np.float32)
    C = np.zeros((n_a, n_s), np.float32)
    var_t = np.ascontiguousarray(var.T)
    for a in prange(n_a):
        ca = cos_a[a]
        sa = sin_a[a]
        acc_v = np.zeros(n_s)
        acc_c = np.zeros(n_s)
        if abs(ca) >= abs(sa):
            _angle_variance(var, s0, ds, sa, ca, pv, pu, r_ref, c_ref, acc_v, acc_c)
            step = pv / abs(ca)
        else:
            _angle_variance(var_t, s0, ds, ca, sa, pu, pv, c_ref, r_ref, acc_v, acc_c)
            step = pu / abs(sa)
        for k in range(n_s):
            V[a, k] = acc_v[k] * step * step
            C[a, k] = acc_c[k] * step * step
    return V, C


@njit(cache=True)
def _angle_variance(img, s0, ds, a_major, a_minor, p_major, p_minor, ref_major, ref_minor, acc_v, acc_c):
    """As :func:`_angle_sums` with squared weights into ``acc_v`` and the
    products of the weights of offsets k and k + 1 on shared pixels into ``acc_c``."""
    n_major, n_minor = img.shape
    n_s = acc_v.shape[0]
    first = (s0 + ref_major * p_major * a_major) / (a_minor * p_minor) + ref_minor
    step = ds / (a_minor * p_minor)
    dm = -p_major * a_major / (a_minor * p_minor)
    top = n_minor - 1.0
    for j in range(n_major):
        base = first + dm * j
        klo, khi = _row_span(base, step, top, n_s)
        row = img[j]
        for k in range(klo, khi + 1):
            m = base + step * k
            i = min(max(int(m), 0), n_minor - 2)
            f = m - i
            acc_v[k] += row[i] * (1.0 - f) * (1.0 - f) + row[i + 1] * f * f
            if k < khi:
                m2 = m + step
                i2 = min(max(int(m2), 0), n_minor - 2)
                f2 = m2 - i2
                # weights of line k: (1-f) at i, f at i+1; of line k+1: (1-f2) at i2, f2 at i2+1
                if i2 == i:
                    acc_c[k] += row[i] * (1.0 - f) * (1.0 - f2) + row[i + 1] * f * f2
                elif i2 == i + 1:
                    acc_c[k] += row[i + 1] * f * (1.0 - f2)
                elif i2 == i - 1:
                    acc_c[k] += row[i] * (1.0 - f) * f2


@njit(cache=True, inline="always")
def _half_turn(alpha, s, da):
    """Table row (index, fraction) of a line at ``alpha`` and its ``s`` and
    sign: alpha in [pi, 2 pi) is the line (alpha - pi, -s) with the sign flipped."""
    a = alpha % (2 * np.pi)
    sign = 1.0
    if a >= np.pi:
        a -= np.pi
        s = -s
        sign = -1.0
    xa = a / da
    ia = int(np.floor(xa))
    return ia, xa - ia, s, sign


@njit(cache=True, parallel=True)
def lookup(tables, view, alpha, s, s0, ds):
    """Bilinear look-up of ``tables[view](alpha, s)`` with its derivatives.

    ``tables`` is (n_views, n_a, n_s) over alpha in [0, pi) and
    s = s0 + k*ds. Angles outside [0, pi) use T(alpha + pi, s) = -T(alpha, -s)
    (the derivative of the Radon transform is odd under that flip). Values
    outside the table are zero. Returns value, d/dalpha, d/ds.
    """
    n = view.shape[0]
    _, n_a, n_s = tables.shape
    da = np.pi / n_a
    val = np.zeros(n)
    d_alpha = np.zeros(n)
    d_s = np.zeros(n)
    for k in prange(n):
        ia, fa, sk, sign = _half_turn(alpha[k], s[k], da)
        if ia >= n_a:
            ia = n_a - 1
            fa = 1.0
        t0v = 0.0
        t1v = 0.0
        d0 = 0.0
        d1 = 0.0
        for j in range(2):
            row_i = ia + j
            sj = sk
            sg = sign
            if row_i == n_a:                 # alpha = pi wraps to 0 with s -> -s
                row_i = 0
                sj = -sk
                sg = -sign
            xs = (sj - s0) / ds
            i = int(np.floor(xs))
            f = xs - i
            if i < 0 or i + 1 >= n_s:
                continue
            a0 = tables[view[k], row_i, i]
            a1 = tables[view[k], row_i, i + 1]
            # d/ds in the caller's s: every flip of s comes with a flip of
            # sign, so the two cancel
            if j == 0:
                t0v = sg * (a0 + f * (a1 - a0))
                d0 = (a1 - a0) / ds
            else:
                t1v = sg * (a0 + f * (a1 - a0))
                d1 = (a1 - a0) / ds
        val[k] = t0v + fa * (t1v - t0v)
        d_alpha[k] = (t1v - t0v) / da
        d_s[k] = d0 + fa * (d1 - d0)
    return val, d_alpha, d_s


@njit(cache=True, inline="always")
def _keys(f):
    """Catmull-Rom (Keys, a = -1/2) weights of the taps at -1, 0, 1, 2 and their d/df."""
    f2 = f * f
    f3 = f2 * f
    w0 = -0.5 * f3 + f2 - 0.5 * f
    w1 = 1.5 * f3 - 2.5 * f2 + 1.0
    w2 = -1.5 * f3 + 2.0 * f2 + 0.5 * f
    w3 = 0.5 * f3 - 0.5 * f2
    d0 = -1.5 * f2 + 2.0 * f - 0.5
    d1 = 4.5 * f2 - 5.0 * f
    d2 = -4.5 * f2 + 4.0 * f + 0.5
    d3 = 1.5 * f2 - f
    return w0, w1, w2, w3, d0, d1, d2, d3


@njit(cache=True, inline="always")
def _bspline(f):
    """Cubic B-spline weights of the taps at -1, 0, 1, 2 and their d/df (on
    prefiltered coefficients they interpolate; see :func:`spline_coefficients`)."""
    g = 1.0 - f
    f2 = f * f
    w0 = g * g * g / 6.0
    w1 = (3.0 * f2 * f - 6.0 * f2 + 4.0) / 6.0
    w2 = (-3.0 * f2 * f + 3.0 * f2 + 3.0 * f + 1.0) / 6.0
    w3 = f2 * f / 6.0
    d0 = -0.5 * g * g
    d1 = 1.5 * f2 - 2.0 * f
    d2 = -1.5 * f2 + f + 0.5
    d3 = 0.5 * f2
    return w0, w1, w2, w3, d0, d1, d2, d3


@njit(cache=True)
def _row_cubic(tables, view, row, sk, s0, ds, n_a, n_s, flip, spline=False):
    """Value and d/d(sk) of one table row at ``sk`` (Catmull-Rom along s);
    rows outside [0, n_a) wrap with T(alpha + pi, s) = flip * T(alpha, -s)."""
    wrapped = row < 0 or row >= n_a
    if row < 0:
        row += n_a
    elif row >= n_a:
        row -= n_a
    x = -sk if wrapped else sk
    xs = (x - s0) / ds
    i = int(np.floor(xs))
    f = xs - i
    if spline:
        w0, w1, w2, w3, d0, d1, d2, d3 = _bspline(f)
    else:
        w0, w1, w2, w3, d0, d1, d2, d3 = _keys(f)
    val = 0.0
    der = 0.0
    for t, (w, d) in enumerate(((w0, d0), (w1, d1), (w2, d2), (w3, d3))):
        k = i - 1 + t
        if 0 <= k < n_s:
            y = tables[view, row, k]
            val += w * y
            der += d * y
    if wrapped:
        return flip * val, -flip * der / ds
    return val, der / ds


@njit(cache=True, parallel=True)
def lookup_cubic(tables, view, alpha, s, s0, ds, flip=-1.0, spline=False):
    """As :func:`lookup`, with Catmull-Rom interpolation along both alpha and s.

    Bilinear look-ups make the cost piecewise quadratic: each plane's
    interpolation error swings with its line's position within a cell, and
    summed over many planes these swings ripple the cost by more than the
    slope of its shallow directions (v against the tilt about u), so that a
    Gauss-Newton refinement stops on a ripple. Cubic look-ups are C1 and
    their error is an order of magnitude smaller.

    ``flip``: T(alpha + pi, s) = flip * T(alpha, -s); -1 for the odd
    derivative tables, +1 for even ones (the noise variance tables).
    """
    n = view.shape[0]
    _, n_a, n_s = tables.shape
    da = np.pi / n_a
    val = np.zeros(n)
    d_alpha = np.zeros(n)
    d_s = np.zeros(n)
    for k in prange(n):
        ia, fa, sk, half = _half_turn(alpha[k], s[k], da)
        sign = flip if half < 0 else 1.0
        # d/ds in the caller's s: the half turn flips s
        ds_sign = -sign if half < 0 else 1.0
        w0, w1, w2, w3, e0, e1, e2, e3 = _keys(fa)
        v0, s0d = _row_cubic(tables, view[k], ia - 1, sk, s0, ds, n_a, n_s, flip, spline)
        v1, s1d = _row_cubic(tables, view[k], ia, sk, s0, ds, n_a, n_s, flip, spline)
        v2, s2d = _row_cubic(tables, view[k], ia + 1, sk, s0, ds, n_a, n_s, flip, spline)
        v3, s3d = _row_cubic(tables, view[k], ia + 2, sk, s0, ds, n_a, n_s, flip, spline)
        val[k] = sign * (w0 * v0 + w1 * v1 + w2 * v2 + w3 * v3)
        d_alpha[k] = sign * (e0 * v0 + e1 * v1 + e2 * v2 + e3 * v3) / da
        d_s[k] = ds_sign * (w0 * s0d + w1 * s1d + w2 * s2d + w3 * s3d)
    return val, d_alpha, d_s


@njit(cache=True)
def lookup_spline(tables, view, alpha, s, s0, ds):
    """As :func:`lookup_cubic` for tables of cubic B-spline coefficients along
    s (Catmull-Rom along alpha)."""
    return lookup_cubic(tables, view, alpha, s, s0, ds, -1.0, True)
