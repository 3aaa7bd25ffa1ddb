"""The robust sigma and the sigma from differences of two noisy values."""

import numpy as np

from conecal.stats import difference_sigma, mad_sigma


def test_mad_sigma_and_difference_sigma_recover_a_normal_sigma():
    rng = np.random.default_rng(5)
    a, b = rng.normal(3.0, 2.0, 200_000), rng.normal(-1.0, 2.0, 200_000)
    assert abs(mad_sigma(a) - 2.0) < 0.02
    # the difference of two values with sigma 2 scatters by 2*sqrt(2); its sigma per value is 2
    assert abs(mad_sigma(a - b) - 2.0 * np.sqrt(2)) < 0.03
    assert abs(difference_sigma(a - b) - 2.0) < 0.02
    # outliers do not move it
    a[:5000] = 1e6
    assert abs(mad_sigma(a) - 2.0) < 0.1
    # about zero for values known to scatter about 0, per column along an axis
    z = rng.normal(0.0, [1.0, 3.0], (100_000, 2))
    assert np.allclose(mad_sigma(z, axis=0, centre=False), [1.0, 3.0], rtol=0.02)
