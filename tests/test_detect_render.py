"""The overlap model's renderer on groups larger than OpenCV filters at once, and groups too large to hold."""

import numpy as np

from conecal.detect.overlap import render


def test_a_group_of_forty_spheres_renders_with_its_jacobian():
    # 40 spheres are 160 derivative channels: OpenCV 5 blurs at most 128 at
    # once (a crowded frame's group fit crashed there)
    sph = np.array([[6.0 + 3.1 * k, 15.0 + (k % 3), 2.5, 0.05 + 0.001 * k] for k in range(40)])
    model, J = render((30, 140), sph, 1.0, jacobian=True)
    assert J.shape == (30 * 140, 160)
    alone = sum(render((30, 140), s[None], 1.0) for s in sph)
    assert np.allclose(model, alone, atol=1e-6)
    for k in (0, 39):
        _, Jk = render((30, 140), sph[k][None], 1.0, jacobian=True)
        assert np.allclose(J[:, 4 * k:4 * k + 4], Jk, atol=1e-6)


def test_a_group_too_large_to_hold_is_not_fitted_jointly():
    # speckle read as a hundred touching shadows across a frame: its joint
    # fit would hold a Jacobian of 1e9 entries (it took 20 GB)
    import time

    from conecal.detect.overlap import fit_group

    a = np.zeros((900, 900), np.float32)
    sph = np.array([[20.0 + 8.5 * k, 20.0 + 8.5 * k, 3.0, 0.05] for k in range(100)])
    t = time.perf_counter()
    assert fit_group(a, sph, 1.0, 0.01) is None
    assert time.perf_counter() - t < 1.0
    # a group that fits in memory is fitted
    assert fit_group(a + 0.0, sph[:2], 1.0, 0.01) is not None
