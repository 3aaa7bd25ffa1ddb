"""fit-linear: Jacobians, recovery of the truth, identifiability."""

import json

import numpy as np
import pytest

from conecal.fit.core import Parameter, solve
from conecal.fit.linear import LinearModel, fit_linear
from conecal.fit.markers import Observations
from conecal.geometry import ConeGeometry
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


def test_converges_from_5mm_and_3deg_off(tmp_path, rng):
    """The issue's bound: nominal off by 5 mm (source, detector) and 3 deg (detector)."""
    from conecal.geometry import rotvec_to_matrix

    sc = linear_raster(9, rows=256, cols=256, counts=(3, 3, 2), steps=(3.0, 3.0, 10.0))
    nom = ConeGeometry.nominal(sod=100, sdd=500, shape=(256, 256), pixel_pitch=(0.2, 0.2))
    R = rotvec_to_matrix(np.deg2rad(3.0) * np.array([1.0, -1.0, 1.0]) / np.sqrt(3))
    centre = nom.detector_centre + np.array([3.0, -3.0, 2.65])      # |shift| = 5 mm
    u, v = R @ nom.u, R @ nom.v
    sc.geometry = nom.replace(source=nom.source + np.array([-3.0, 3.0, 2.65]), u=u, v=v,
                              detector_origin=centre - 127.5 * 0.2 * u - 127.5 * 0.2 * v)
    sc.photons = 0
    d = write_scan(sc, tmp_path / "far")
    obs, truth = exact_observations(d, 0.02, rng)
    fit = fit_linear(load_scan(d), obs)
    gt = ConeGeometry.from_dict(truth["geometry"])
    sig = dict(zip(fit.result.names, fit.result.sigma))
    assert np.sqrt(np.mean(fit.residual_px**2)) < 0.05          # converged to the noise floor
    for k, axis in enumerate("xyz"):
        assert abs(fit.geometry.source[k] - gt.source[k]) < 4 * sig[f"source_{axis}"] + 1e-3
    tilt_sigma = np.hypot(sig["detector_rx"], sig["detector_ry"])
    assert np.degrees(np.arccos(fit.geometry.normal @ gt.normal)) < 4 * tilt_sigma + 0.01


def test_axis_scale_and_tilt_are_recovered_or_reported(tmp_path, rng):
    from conecal.effects import parse_effect

    sc = linear_raster(4, rows=384, cols=384, counts=(3, 3, 3), steps=(4.0, 4.0, 8.0))
    sc.apply_effects([parse_effect("axis_scale:axis=y,scale=0.004"),
                      parse_effect("axis_nonorthogonality:axis=y,towards=x,angle=0.3")])
    sc.photons = 0
    d = write_scan(sc, tmp_path / "axes")
    obs, truth = exact_observations(d, 0.02, rng)
    fit = fit_linear(load_scan(d), obs, axis_scales=True, axis_tilts=True)
    res = fit.result
    sig = dict(zip(res.names, res.sigma))
    det = [n for n in ("scale_y", "tilt_y_to_x") if n not in res.undetermined]
    # whatever the scan determines must be right within 4 sigma; the rest must be named
    truth_vals = {"scale_y": 1.004, "tilt_y_to_x": np.degrees(np.tan(np.deg2rad(0.3)))}
    for n in det:
        assert abs(res.value(n) - truth_vals[n]) < 4 * sig[n] + 1e-4, (n, res.value(n), sig[n])
    assert set(det) | set(res.undetermined) >= {"scale_y", "tilt_y_to_x"}
