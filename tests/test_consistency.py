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
