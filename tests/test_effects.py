"""Every registered effect changes the world the way its physics says."""

import numpy as np
import pytest

from conecal.effects import REGISTRY, World, parse_effect
from conecal.errors import InputError
from conecal.kinematics import Chain, LinearAxis, RotaryAxis


def world():
    chain = Chain((LinearAxis("x", [1, 0, 0]), LinearAxis("y", [0, 1, 0]), RotaryAxis("theta", [0, 1, 0], [0, 0, 0])))
    t = np.arange(10.0)
    q = np.column_stack([np.linspace(0, 9, 10), np.zeros(10), np.linspace(0, 90, 10)])
    return World.start(t, q, chain=chain)


def test_registry_has_the_required_effects():
    for name in ("focal_spot_drift", "axis_scale", "axis_nonorthogonality", "rotary_wobble", "encoder_latency"):
        assert name in REGISTRY
        assert REGISTRY[name].physics


def test_focal_spot_drift_grows_with_time():
    w = parse_effect("focal_spot_drift:velocity=0.01/0/0").apply(world())
    assert np.allclose(w.source_offsets[:, 0], 0.01 * np.arange(10))


def test_axis_scale_and_nonorthogonality_move_the_sample():
    w0 = world()
    w = parse_effect("axis_scale:axis=x,scale=0.01").apply(w0)
    assert np.allclose(w.transforms().t[:, 0], 1.01 * w0.readings[:, 0])
    w = parse_effect("axis_nonorthogonality:axis=y,towards=x,angle=1").apply(w0)
    d = w.chain.axes[1].direction
    assert np.degrees(np.arccos(d @ [0, 1, 0])) == pytest.approx(1.0)
    assert d[0] > 0


def test_latency_reads_the_log_later():
    w = parse_effect("encoder_latency:latency=0.5").apply(world())
    assert np.allclose(w.true_readings[:-1, 0], np.arange(9) + 0.5)


def test_rotary_wobble_tilts_the_axis():
    w0 = world()
    w = parse_effect("rotary_wobble:amplitude=0.1").apply(w0)
    R0, R = w0.transforms().R, w.transforms().R
    assert not np.allclose(R[1:], R0[1:])
    assert np.allclose(R[0], R0[0])  # zero angle: no rotation either way


def test_bad_effect_specs_are_input_errors():
    with pytest.raises(InputError, match="unknown effect"):
        parse_effect("gremlins")
    with pytest.raises(InputError, match="takes"):
        parse_effect("axis_scale:bogus=1")
    with pytest.raises(InputError, match="no axis"):
        parse_effect("axis_scale:axis=w").apply(world())
