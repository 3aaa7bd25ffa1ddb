"""The edge profile's compiled least squares against the same problem solved densely."""

import numpy as np
import pytest

from conecal.detect.profile_kernels import profile_fit


@pytest.mark.parametrize("n_extra", [0, 1, 2])
def test_the_banded_profile_fit_is_the_dense_least_squares_solution(n_extra):
    rng = np.random.default_rng(3 + n_extra)
    h, w = 19, 23
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    dx, dy = (xx - 11.3).ravel(), (yy - 8.7).ravel()
    phi, kappa, reg2 = 0.37, 1 / 100, 0.4
    span = np.hypot(dx, dy).max()
    s_lo = -span - 0.02 * span**2 - 2
    k = int(np.ceil(2 * span + 0.04 * span**2 + 4)) + 1
    w2 = rng.uniform(0.0, 2.0, dx.size) * (rng.uniform(size=dx.size) > 0.1)
    extra = rng.normal(size=(dx.size, n_extra))
    target = np.tanh((dx * np.cos(phi) + dy * np.sin(phi)) / 3) + rng.normal(0, 0.1, dx.size)

    coef, chi2, model = profile_fit(dx, dy, phi, kappa, s_lo, 1.0, k, w2, extra, target, reg2)

    # the same problem, dense: hat functions of s = u + kappa v^2 on 1 px knots, then v and the extras
    u = dx * np.cos(phi) + dy * np.sin(phi)
    v = -dx * np.sin(phi) + dy * np.cos(phi)
    t = np.clip(u + kappa * v * v - s_lo, 0, k - 1 - 1e-9)
    i = np.floor(t).astype(int)
    B = np.zeros((dx.size, k))
    B[np.arange(dx.size), i] = 1 - (t - i)
    B[np.arange(dx.size), i + 1] = t - i
    A = np.column_stack([B, v, extra])
    D2 = (np.eye(k, k=-1) - 2 * np.eye(k) + np.eye(k, k=1))[1:-1]
    P = np.zeros((A.shape[1], A.shape[1]))
    P[:k, :k] = reg2 * D2.T @ D2
    N = A.T @ (A * w2[:, None]) + P
    # (the fit's ridge: 1e-9 of the mean diagonal, for knots no pixel and only the prior pins)
    N += 1e-9 * np.trace(N) / N.shape[0] * np.eye(N.shape[0])
    ref = np.linalg.solve(N, A.T @ (w2 * target))
    ref_model = A @ ref
    ref_chi2 = float(np.sum(w2 * (ref_model - target) ** 2) + ref @ P @ ref)

    assert np.allclose(coef, ref, rtol=1e-6, atol=1e-6)
    assert np.allclose(model, ref_model, atol=1e-8)
    assert chi2 == pytest.approx(ref_chi2, rel=1e-9)
