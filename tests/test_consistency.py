"""Radon-derivative tables against the analytic transform of a Gaussian."""

import numpy as np

from conecal.consistency import cosine_weighted, radon_derivative_table


def test_radon_and_derivative_of_a_gaussian():
    rows, cols, pitch = 160, 200, 0.5
    pp = (99.5, 79.5)
    u0, v0, sig, amp = 6.0, -4.0, 5.0, 2.0                    # mm
    u = (np.arange(cols) - pp[0]) * pitch
    v = (np.arange(rows) - pp[1]) * pitch
    img = amp * np.exp(-((u[None, :] - u0) ** 2 + (v[:, None] - v0) ** 2) / (2 * sig**2))
    a, s, R, dR = radon_derivative_table(img, pitch, pp, n_angles=36)
    for k in range(0, 36, 5):
        c = u0 * np.cos(a[k]) + v0 * np.sin(a[k])
        ref = amp * np.sqrt(2 * np.pi) * sig * np.exp(-((s - c) ** 2) / (2 * sig**2))
        dref = -ref * (s - c) / sig**2
        assert np.abs(R[k] - ref).max() < 0.01 * ref.max(), k
        assert np.abs(dR[k] - dref).max() < 0.02 * np.abs(dref).max(), k


def test_cosine_weight_is_one_on_the_principal_ray():
    img = np.ones((11, 11))
    w = cosine_weighted(img, (0.2, 0.2), (5, 5), 500.0)
    assert w[5, 5] == 1.0 and w[0, 0] < 1.0
    assert np.isclose(w[0, 0], 500 / np.sqrt(500**2 + 2 * 1.0**2))


def _odd_tables(n_views=3, n_a=90, n_s=121, ds=1.0):
    """Tables of a smooth function with the symmetry of Radon derivatives,
    T(alpha + pi, s) = -T(alpha, -s), and the function itself."""
    def g(x):
        return np.exp(-(x / 4) ** 2) * x / 4

    def f(a, s):
        return g(s - 30 * np.cos(a)) - g(s + 30 * np.cos(a)) + 0.3 * np.cos(2 * a) * (g(s - 10) + g(s + 10))

    s0 = -(n_s // 2) * ds
    a = np.arange(n_a) * np.pi / n_a
    s = s0 + np.arange(n_s) * ds
    return np.stack([f(a[:, None], s[None, :])] * n_views).astype(np.float32), s0, ds, f


def test_cubic_lookup_is_accurate_smooth_and_has_consistent_derivatives():
    """Catmull-Rom look-ups: an order of magnitude closer to the function
    than bilinear ones (whose cost ripples stall Gauss-Newton in shallow
    valleys), continuous across cells and across the alpha = pi wrap, and
    their derivatives match finite differences."""
    from conecal.consistency import kernels

    tables, s0, ds, f = _odd_tables()
    rng = np.random.default_rng(1)
    n = 5000
    view = rng.integers(0, 3, n)
    alpha = rng.uniform(-np.pi, 3 * np.pi, n)
    s = rng.uniform(-45, 45, n)
    lin = kernels.lookup(tables, view, alpha, s, s0, ds)[0]
    val, d_a, d_s = kernels.lookup_cubic(tables, view, alpha, s, s0, ds)
    truth = f(alpha, s)
    assert np.sqrt(np.mean((val - truth) ** 2)) < 0.15 * np.sqrt(np.mean((lin - truth) ** 2))
    h = 1e-6
    fd_a = (kernels.lookup_cubic(tables, view, alpha + h, s, s0, ds)[0] - kernels.lookup_cubic(tables, view, alpha - h, s, s0, ds)[0]) / (2 * h)
    fd_s = (kernels.lookup_cubic(tables, view, alpha, s + h, s0, ds)[0] - kernels.lookup_cubic(tables, view, alpha, s - h, s0, ds)[0]) / (2 * h)
    assert np.allclose(d_a, fd_a, atol=1e-5 * np.abs(d_a).max()) and np.allclose(d_s, fd_s, atol=1e-5 * np.abs(d_s).max())
    # continuity: just either side of a cell edge in s, and of the wrap at alpha = pi
    edge = s0 + 50 * ds
    a = np.array([0.3, 0.3])
    v2 = kernels.lookup_cubic(tables, np.zeros(2, np.int64), a, np.array([edge - 1e-9, edge + 1e-9]), s0, ds)[0]
    assert abs(v2[0] - v2[1]) < 1e-6
    w = kernels.lookup_cubic(tables, np.zeros(2, np.int64), np.array([np.pi - 1e-9, np.pi + 1e-9]), np.array([7.3, 7.3]), s0, ds)[0]
    assert abs(w[0] - w[1]) < 1e-6


def test_spline_lookup_along_offsets_is_ten_times_closer_than_catmull_rom():
    """Tables prefiltered into cubic B-spline coefficients along s (rp-grid's
    default): the look-up interpolates the samples and is ten times closer
    to a function smoothed over a few samples than Catmull-Rom, whose error,
    swinging with each line's position within a cell, ripples the cost
    along the v shift (local minima half a pixel apart, RESULTS.md); its
    derivatives match finite differences."""
    from scipy.ndimage import spline_filter1d

    from conecal.consistency import kernels

    tables, s0, ds, f = _odd_tables(n_a=360)         # fine in alpha: the error along s dominates
    coef = spline_filter1d(tables, 3, axis=-1, mode="mirror").astype(np.float32)
    rng = np.random.default_rng(1)
    n = 5000
    view = rng.integers(0, 3, n)
    alpha = rng.uniform(-np.pi, 3 * np.pi, n)
    s = rng.uniform(-45, 45, n)
    truth = f(alpha, s)
    cubic = kernels.lookup_cubic(tables, view, alpha, s, s0, ds)[0]
    val, d_a, d_s = kernels.lookup_spline(coef, view, alpha, s, s0, ds)
    assert np.sqrt(np.mean((val - truth) ** 2)) < 0.15 * np.sqrt(np.mean((cubic - truth) ** 2))
    # at the samples it is the samples
    k = np.arange(40, 80)
    at = kernels.lookup_spline(coef, np.zeros(k.size, np.int64), np.full(k.size, 7 * np.pi / 360), s0 + k * ds, s0, ds)[0]
    assert np.allclose(at, tables[0, 7, k], atol=1e-5)
    h = 1e-6
    fd_a = (kernels.lookup_spline(coef, view, alpha + h, s, s0, ds)[0] - kernels.lookup_spline(coef, view, alpha - h, s, s0, ds)[0]) / (2 * h)
    fd_s = (kernels.lookup_spline(coef, view, alpha, s + h, s0, ds)[0] - kernels.lookup_spline(coef, view, alpha, s - h, s0, ds)[0]) / (2 * h)
    assert np.allclose(d_a, fd_a, atol=1e-5 * np.abs(d_a).max()) and np.allclose(d_s, fd_s, atol=1e-5 * np.abs(d_s).max())


def test_radon_variance_and_neighbour_covariance_match_monte_carlo():
    """The noise model of the tables: variance of each Radon sum and its
    covariance with the next offset's, against 3000 draws of independent
    pixel noise, at 0 and 90 deg (where neighbouring offsets share half their
    pixels' weight) and in between; and the variance of the s-derivative
    they imply. Without the covariance the derivative's variance was off by
    an angle-dependent factor of 0.8 to 1.5 (RESULTS.md)."""
    from conecal.consistency import kernels
    from conecal.consistency.radon import derivative_kernel
    from scipy.ndimage import correlate1d

    rng = np.random.default_rng(3)
    n = 24
    var = rng.uniform(0.5, 2.0, (n, n)).astype(np.float32)
    angles = np.deg2rad([0.0, 17.0, 45.0, 90.0, 123.0])
    ca, sa = np.cos(angles), np.sin(angles)
    s0, ds, n_s = -16.0, 1.0, 33
    c = (n - 1) / 2
    V, C = kernels.radon_joseph_variance(var, 1.0, 1.0, c, c, ca, sa, s0, ds, n_s)
    draws = np.stack([kernels.radon_joseph((rng.normal(size=(n, n)) * np.sqrt(var)).astype(np.float32),
                                           1.0, 1.0, c, c, ca, sa, s0, ds, n_s) for _ in range(3000)])
    emp_v = draws.var(axis=0)
    emp_c = np.mean((draws[:, :, :-1] - draws[:, :, :-1].mean(0)) * (draws[:, :, 1:] - draws[:, :, 1:].mean(0)), axis=0)
    big = V > 0.3 * V.max(axis=1, keepdims=True)
    assert np.allclose(emp_v[big], V[big], rtol=0.12)
    assert np.allclose(emp_c[big[:, :-1]], C[:, :-1][big[:, :-1]], atol=0.12 * V.max())
    assert C[0][big[0]].mean() > 0.3 * V[0][big[0]].mean()       # 0 deg: neighbours share pixels
    taps = derivative_kernel(1.5)
    d = correlate1d(draws, taps, axis=-1, mode="constant")
    model = correlate1d(V, taps**2, axis=-1, mode="constant") + 2 * correlate1d(C, np.append(taps[:-1] * taps[1:], 0.0), axis=-1, mode="constant")
    inside = model > 0.3 * model.max(axis=1, keepdims=True)
    assert np.allclose(d.var(axis=0)[inside], model[inside], rtol=0.12)
