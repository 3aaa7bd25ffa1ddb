"""Laws of the detector distortion models and the drift / wobble families."""

import numpy as np
import pytest

from conecal.effects.motion import (DriftPath, RotaryTiltSeries, TiltSeriesRotaryAxis, WobblingRotaryAxis,
                                    time_basis)
from conecal.errors import InputError
from conecal.geometry.distortion import Distortion, poly_terms

SHAPE = (300, 400)


def _random(rng, model):
    if model == "radial_tangential":
        return Distortion.radial(SHAPE, centre=(210.0, 140.0), **dict(zip(("k1", "k2", "k3", "p1", "p2", "s", "q1",
                                                                           "q2"), rng.normal(0, 0.8, 8))))
    return Distortion.polynomial(SHAPE, 3, rng.normal(0, 0.5, 2 * len(poly_terms(3))))


@pytest.mark.parametrize("model", ["radial_tangential", "polynomial"])
def test_round_trips(model):
    rng = np.random.default_rng(3)
    d = _random(rng, model)
    xy = rng.uniform(0, 300, (50, 2))
    assert np.allclose(d.undistort(d.distort(xy)), xy, atol=1e-6)
    back = Distortion.from_dict(d.to_dict())
    assert back.model == d.model and np.allclose(back.coefficients, d.coefficients)
    assert np.allclose(back.displacement(xy), d.displacement(xy))


@pytest.mark.parametrize("model", ["radial_tangential", "polynomial"])
def test_basis_is_the_displacement_and_centre_jacobian_matches(model):
    rng = np.random.default_rng(4)
    d = _random(rng, model)
    xy = rng.uniform(0, 300, (20, 2))
    assert np.allclose(d.basis(xy) @ np.asarray(d.coefficients), d.displacement(xy))
    J = d.centre_jacobian(xy)
    eps = 1e-5
    for k in range(2):
        c = np.array(d.centre)
        c[k] += eps
        hi = d.with_coefficients(d.coefficients, tuple(c)).displacement(xy)
        c[k] -= 2 * eps
        lo = d.with_coefficients(d.coefficients, tuple(c)).displacement(xy)
        assert np.allclose(J[..., k], (hi - lo) / (2 * eps), atol=1e-6)
    # the basis' own gradient, term by term
    G = d.basis_gradient(xy)
    for k in range(2):
        step = np.zeros(2)
        step[k] = eps
        num = (d.basis(xy + step) - d.basis(xy - step)) / (2 * eps)
        assert np.allclose(G[..., k], num, atol=1e-7)


def test_named_coefficients_are_px_at_the_radius():
    d = Distortion.radial(SHAPE, k1=0.7)
    c = np.array(d.centre)
    corner = c + d.radius * np.array([1.0, 0.0])
    assert np.allclose(d.displacement(corner), [0.7, 0.0])
    s = Distortion.radial(SHAPE, s=0.4)
    assert np.allclose(s.displacement(corner), [0.0, 0.4])   # counter-clockwise in (c, r): +r at +c


def test_twist_decentring_is_the_first_order_of_a_moved_twist():
    # an S twist about a centre moved by delta (normalised) = the twist about
    # the old centre + q = -s delta, up to terms of order s delta^2
    s = 2.0
    base = Distortion.radial(SHAPE, s=s)
    xy = np.random.default_rng(5).uniform(0, 300, (40, 2))
    for delta in ([0.01, 0.0], [0.0, -0.02], [0.015, 0.01]):
        delta = np.array(delta)
        moved = Distortion.radial(SHAPE, s=s, centre=tuple(np.array(base.centre) + delta * base.radius))
        q1, q2 = -s * delta
        first = base.displacement(xy) + Distortion.radial(SHAPE, q1=q1, q2=q2).displacement(xy)
        assert np.abs(moved.displacement(xy) - first).max() < 4 * s * float(delta @ delta)
        # and the terms matter at that order: leaving them out errs by far more
        assert np.abs(moved.displacement(xy) - base.displacement(xy)).max() > 10 * s * float(delta @ delta)


def test_an_entry_written_before_the_twist_decentring_reads_it_as_zero():
    old = {"model": "radial_tangential", "centre": [200.0, 150.0], "radius_px": 250.0,
           "parameters": dict(zip(("k1", "k2", "k3", "p1", "p2", "s"), (0.5, 0.0, 0.0, 0.1, 0.0, 0.2)))}
    d = Distortion.from_dict(old)
    assert d.coefficients[d.names.index("q1")] == 0.0 and d.coefficients[d.names.index("q2")] == 0.0
    from conecal.documents.common import Distortion as DistortionDoc
    DistortionDoc.model_validate(old)


def test_field_samples_every_pixel_centre():
    d = Distortion.radial(SHAPE, k1=0.5, p1=0.2)
    dc, dr = d.field(SHAPE)
    assert dc.shape == SHAPE and dc.dtype == np.float32
    assert np.isclose(dc[17, 250], d.displacement([250.0, 17.0])[0], atol=1e-5)
    assert np.isclose(dr[17, 250], d.displacement([250.0, 17.0])[1], atol=1e-5)


@pytest.mark.parametrize("bad", [{"model": "fisheye", "centre": [0, 0], "radius_px": 1, "parameters": {}},
                                 {"model": "radial_tangential", "centre": [0, 0], "radius_px": 0, "parameters":
                                  dict.fromkeys(("k1", "k2", "k3", "p1", "p2", "s"), 0.0)},
                                 {"model": "radial_tangential", "centre": [0, 0], "radius_px": 1, "parameters": {}},
                                 {"model": "polynomial", "degree": 1, "centre": [0, 0], "radius_px": 1,
                                  "parameters": {}},
                                 {"model": "radial_tangential", "radius_px": 1, "parameters": {}}])
def test_bad_documents_are_input_errors(bad):
    with pytest.raises(InputError):
        Distortion.from_dict(bad)


def test_time_basis_vanishes_at_start_and_spans_a_line():
    t = np.linspace(10, 110, 40)
    for form, order, tau in (("poly", 2, 0), ("warmup", 1, 30.0), ("spline", 5, 0)):
        B = time_basis(t, form, order, tau)
        assert B.shape == (40, order) and np.allclose(B[0], 0)
    B = time_basis(t, "spline", 5)
    line = (t - t[0]) / 100
    coef, *_ = np.linalg.lstsq(B, line, rcond=None)
    assert np.allclose(B @ coef, line, atol=1e-9)      # cubic splines hold a line


def test_drift_path_moves_the_named_part():
    from conecal.effects import World

    w = World.start(np.linspace(0, 100, 5), np.zeros((5, 1)))
    d = DriftPath("detector", "poly", 1, 0.0, (0.1, 0.0, -0.2))
    w2 = d.apply(w)
    assert np.allclose(w2.detector_offsets[-1], [0.1, 0.0, -0.2]) and np.allclose(w2.source_offsets, 0)


def test_tilt_series_holds_the_precession_and_a_nod():
    A, p = 0.01, 0.3
    axis = np.array([0.0, 1.0, 0.0])
    w = WobblingRotaryAxis("theta", axis, np.zeros(3), amplitude=A, phase=p)
    s = TiltSeriesRotaryAxis("theta", axis, np.zeros(3),
                             coefficients=(A * np.cos(p), -A * np.sin(p), A * np.sin(p), A * np.cos(p)))
    q = np.linspace(0, 360, 13)
    assert np.allclose(w.transforms(q).R, s.transforms(q).R, atol=1e-15)
    nod = TiltSeriesRotaryAxis("theta", axis, np.zeros(3), coefficients=(0.01, 0.0, 0.0, 0.0))
    d = nod.transforms(np.array([0.0, 90.0, 180.0]))
    # a nod in one plane: the axis tilts one way, back to true, then the other way
    assert not np.allclose(d.R[0], d.R[2])
    assert RotaryTiltSeries("theta", (0.0,) * 4).name == "rotary_wobble"
