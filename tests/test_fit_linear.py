"""fit-linear: Jacobians, recovery of the truth, identifiability."""

import json

import numpy as np
import pytest

from conecal.fit.core import Parameter, solve
from conecal.fit.linear import LinearModel, fit_linear
from conecal.fit.markers import Observations
from conecal.geometry import ConeGeometry
from conecal.geometry.sphere import shadow_centroid
from conecal.scan import load_scan
from conecal.simulate import linear_raster, write_scan


def test_linear_model_jacobian_matches_finite_differences(rng):
    base = ConeGeometry.nominal(sod=100, sdd=500, shape=(512, 512), pixel_pitch=(0.2, 0.2))
    q = rng.uniform(-5, 5, (20, 3))
    model = LinearModel(base, np.eye(3), ("x", "y", "z"), q, 1.0)
    x = model.nominal_vector() + np.concatenate([rng.normal(0, 1, 6), rng.normal(0, 1, 3),
                                                 rng.normal(0, 0.01, 3), rng.normal(0, 0.2, 3)])
    J = model.jacobian(x)
    for i in range(x.size):
        h = 1e-6 * max(1.0, abs(x[i]))
        e = np.zeros(x.size)
        e[i] = h
        fd = (model.predict(x + e) - model.predict(x - e)) / (2 * h)
        assert np.allclose(J[:, :, i], fd, rtol=1e-5, atol=1e-7), model.parameter_names()[i]


def exact_observations(scan_dir, sigma, rng):
    truth = json.loads((scan_dir / "truth.json").read_text())
    xy = np.array([f["markers"][0]["centroid"] for f in truth["frames"]])
    n = len(xy)
    return Observations(np.arange(n), np.arange(n), np.zeros(n, int), xy + rng.normal(0, sigma, xy.shape),
                        np.full(n, sigma)), truth


@pytest.fixture(scope="module")
def far_off_scan(tmp_path_factory):
    """Truth 5 mm / 3 deg away from the nominal geometry (noiseless images are not needed)."""
    sc = linear_raster(5, rows=256, cols=256, counts=(3, 3, 2), steps=(3.0, 3.0, 10.0), misalign=(2.5, 2.5, 1.5))
    sc.photons = 0
    return write_scan(sc, tmp_path_factory.mktemp("far") / "scan")


def test_recovers_truth_far_from_nominal(far_off_scan, rng):
    s = load_scan(far_off_scan)
    obs, truth = exact_observations(far_off_scan, 0.05, rng)
    gt = ConeGeometry.from_dict(truth["geometry"])
    assert np.linalg.norm(gt.source - s.nominal_geometry().source) > 2.0
    fit = fit_linear(s, obs)
    res = fit.result
    sig = dict(zip(res.names, res.sigma))
    errs = {"source_x": fit.geometry.source[0] - gt.source[0], "source_z": fit.geometry.source[2] - gt.source[2],
            "detector_centre_z": fit.geometry.detector_centre[2] - gt.detector_centre[2]}
    for k, e in errs.items():
        assert abs(e) < 5 * sig[k], (k, e, sig[k])
    assert np.sqrt(np.mean(fit.residual_px**2)) < 0.1
    assert res.undetermined == []


def test_planar_raster_reports_the_free_combination(tmp_path, rng):
    sc = linear_raster(2, rows=256, cols=256, counts=(3, 3, 1), steps=(3.0, 3.0, 1.0))
    sc.photons = 0
    d = write_scan(sc, tmp_path / "planar")
    obs, _ = exact_observations(d, 0.05, rng)
    fit = fit_linear(load_scan(d), obs)
    assert fit.result.undetermined, "a planar raster leaves one combination free"
    assert any("source_z" in c or "detector_centre_z" in c for c in fit.result.null_combinations)


def test_core_reports_outliers_with_a_robust_loss(rng):
    xs = np.linspace(0, 1, 50)
    y = 2 * xs + 1 + rng.normal(0, 0.01, 50)
    y[7] += 1.0
    params = [Parameter("a", 0.0), Parameter("b", 0.0)]

    def r(p):
        return (p[0] * xs + p[1] - y) / 0.01

    def j(p):
        return np.column_stack([xs, np.ones_like(xs)]) / 0.01

    res = solve(params, r, j, loss="soft_l1", f_scale=3.0)
    assert res.outliers[7] and res.outliers.sum() == 1
    assert res.value("a") == pytest.approx(2, abs=0.02)
    res = solve(params, r, j)
    assert np.isfinite(res.sigma).all()
