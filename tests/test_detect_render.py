"""The overlap model's renderer on groups larger than OpenCV filters at once."""

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
