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


def test_spread_sigma_is_the_mad_unless_ties_hold_the_median():
    from conecal.stats import spread_sigma

    rng = np.random.default_rng(2)
    a = rng.normal(0.0, 2.0, 100_001)
    assert spread_sigma(a) == mad_sigma(a)
    a[:3000] = 1e6                       # outliers do not move it
    assert spread_sigma(a) == mad_sigma(a)
    # noise quantised away to mostly 0 (an 8-bit JPEG's flat blocks): the MAD
    # says 0, the steps that are left say about the sigma they were cut from
    for sd in (0.3, 0.5):
        q = np.round(rng.normal(0.0, sd, 100_000))
        assert mad_sigma(q) == 0.0 and 0.7 * sd < spread_sigma(q) < 1.3 * sd
    assert spread_sigma(np.zeros(50)) == 0.0
