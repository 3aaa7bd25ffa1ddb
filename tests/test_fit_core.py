"""The least-squares core: its Newton mode on a numerical Hessian."""

import numpy as np
import pytest

from conecal.fit.core import Parameter, _trust_step, robust_loss, solve


def _decay(rng, n=200, sigma=0.01):
    t = np.linspace(0, 3, n)
    y = 2.0 * np.exp(-1.3 * t) + rng.normal(0, sigma, n)

    def r(p):
        return (p[0] * np.exp(-p[1] * t) - y) / sigma

    def j(p):
        e = np.exp(-p[1] * t)
        return np.column_stack([e, -p[0] * t * e]) / sigma

    return r, j


def test_numerical_hessian_agrees_with_gauss_newton_on_small_residuals(rng):
    r, j = _decay(rng)
    params = [Parameter("amplitude", 1.0, scale=0.1), Parameter("rate", 1.0, scale=0.1)]
    gn = solve(params, r, j, tol=1e-12)
    nt = solve(params, r, j, tol=1e-12, hessian="numerical")
    assert nt.success and nt.x == pytest.approx(gn.x, abs=1e-7)
    # the sandwich H^-1 (sum g g^T) H^-1 is the Gauss-Newton covariance when
    # residuals are noise of unit sigma and the model is nearly linear in them
    assert nt.sigma == pytest.approx(gn.sigma, rel=0.25)
    assert nt.hessian.shape == (2, 2) and np.all(np.linalg.eigvalsh(nt.hessian) > 0)


def test_numerical_hessian_crosses_a_noise_valley_that_gauss_newton_creeps_along():
    # residuals that are mostly rough noise: J carries the noise's slope, so
    # J^T J is ~100x the true curvature and Gauss-Newton steps are ~100x short
    rng = np.random.default_rng(1)
    k = rng.uniform(20, 36, 20000)
    phase = rng.uniform(0, 2 * np.pi, k.size)

    def r(p):
        return (p[0] - 5.0) + 0.5 * np.sin(k * p[0] + phase)

    def j(p):
        return (1.0 + 0.5 * k * np.cos(k * p[0] + phase))[:, None]

    grid = np.linspace(4.9, 5.1, 2001)
    best = grid[np.argmin([np.sum(r([x]) ** 2) for x in grid])]
    nt = solve([Parameter("x", 0.0)], r, j, max_nfev=60, tol=1e-10, hessian="numerical")
    assert nt.success and nt.nfev < 30
    assert nt.x[0] == pytest.approx(best, abs=2e-4)
    gn = solve([Parameter("x", 0.0)], r, j, max_nfev=60, tol=1e-10)
    assert abs(gn.x[0] - best) > 1.0


def test_trust_step_stays_inside_and_descends_on_an_indefinite_hessian():
    H = np.diag([2.0, -1.0, 0.5])
    g = np.array([1.0, 0.3, -0.2])
    for radius in (0.1, 1.0, 10.0):
        d = _trust_step(g, H, radius)
        assert np.linalg.norm(d) <= radius * (1 + 1e-9)
        assert g @ d + 0.5 * d @ H @ d < 0
    # inside a positive definite model's reach: the Newton step itself
    Hp = np.diag([2.0, 1.0, 0.5])
    assert _trust_step(g, Hp, 10.0) == pytest.approx(-g / np.diag(Hp))


@pytest.mark.parametrize("loss", ["linear", "cauchy", "soft_l1", "huber"])
def test_robust_loss_derivative_matches_finite_differences(loss):
    z = np.array([0.01, 0.5, 0.99, 1.01, 4.0, 30.0])
    h = 1e-6
    fd = (robust_loss(z + h, loss)[0] - robust_loss(z - h, loss)[0]) / (2 * h)
    assert robust_loss(z, loss)[1] == pytest.approx(fd, rel=1e-5)


def test_unknown_hessian_mode_is_refused():
    with pytest.raises(ValueError, match="hessian"):
        solve([Parameter("x", 0.0)], lambda p: p - 1.0, lambda p: np.ones((1, 1)), hessian="bfgs")


def test_large_mode_levenberg_marquardt_agrees_with_the_trust_region(rng):
    r, j = _decay(rng)
    params = [Parameter("amplitude", 1.0, scale=0.1), Parameter("rate", 0.5, scale=0.1)]
    tr = solve(params, r, j, tol=1e-12)
    lm = solve(params, r, j, tol=1e-12, large=True)
    assert lm.success and lm.x == pytest.approx(tr.x, abs=1e-8)
    # covariance from the normal matrix's eigenvectors equals the SVD's
    assert lm.sigma == pytest.approx(tr.sigma, rel=1e-6)


def test_large_mode_levenberg_marquardt_stays_within_bounds_and_rests_on_one(rng):
    """The image level's fits: a bound the data push against is where the
    estimate rests (then reported as pinned), as scipy's trust region does."""
    r, j = _decay(rng)
    params = [Parameter("amplitude", 1.0, scale=0.1, lower=0.0, upper=1.5), Parameter("rate", 0.5, scale=0.1)]
    tr = solve(params, r, j, tol=1e-12)
    lm = solve(params, r, j, tol=1e-12, large=True)
    assert lm.x[0] == pytest.approx(1.5) and tr.x[0] == pytest.approx(1.5)
    assert lm.x[1] == pytest.approx(tr.x[1], abs=1e-6)
    free = [Parameter("amplitude", 1.0, scale=0.1, lower=0.0, upper=5.0), Parameter("rate", 0.5, scale=0.1)]
    assert solve(free, r, j, tol=1e-12, large=True).x == pytest.approx(solve(free, r, j, tol=1e-12).x, abs=1e-8)
