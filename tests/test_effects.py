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
    for name in ("focal_spot_drift", "axis_scale", "axis_nonorthogonality", "rotary_wobble", "encoder_latency",
                 "detector_drift", "backlash", "blur", "beam_hardening", "detector_lag", "scatter", "detector_distortion",
                 "joint_offset", "robot_deflection", "rotary_runout"):
        assert name in REGISTRY
        assert REGISTRY[name].physics


def test_rotary_runout_moves_the_axis_line_k_times_per_turn():
    """The table's centre (on the axis) traces the whirl: a forward whirl of
    harmonic 2 plus an equal backward one is a line along e1; harmonic 1
    forward is a point fixed on the table (a centring error)."""
    from conecal.geometry.rotations import orthonormal_complement

    chain = Chain((RotaryAxis("theta", [0, 0, 1], [1.0, 2.0, 0.0]),))
    q = np.linspace(0, 360, 73)[:, None]
    w0 = World.start(np.arange(73.0), q, chain=chain)
    e1, e2 = orthonormal_complement(np.array([0.0, 0, 1]))
    w = parse_effect("rotary_runout:amplitude=0.01,harmonic=2,backward=0.01").apply(w0)
    centre = w.transforms().apply(np.broadcast_to([1.0, 2.0, 0.0], (73, 3))) - [1.0, 2.0, 0.0]
    assert np.allclose(centre, 0.02 * np.cos(2 * np.deg2rad(q)) * e1, atol=1e-12)
    w = parse_effect("rotary_runout:amplitude=0.01,harmonic=1").apply(w0)
    T0, T = w0.transforms(), w.transforms()
    on_table = np.einsum("nji,nj->ni", T0.R, T.t - T0.t)       # the offset, carried back to the table
    assert np.allclose(on_table, on_table[0], atol=1e-12) and np.isclose(np.linalg.norm(on_table[0]), 0.01)
    with pytest.raises(InputError):
        parse_effect("rotary_runout:harmonic=0")
    with pytest.raises(InputError):
        parse_effect("rotary_runout:axis=x").apply(world())


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


def test_distortion_round_trip_and_rendered_shadow_moves_with_it():
    """undistort inverts distort; a rendered sphere's shadow centroid lands
    where Imaging.distort sends the undistorted one (the simulator's truth)."""
    from conecal.effects import Imaging
    from conecal.geometry import ConeGeometry
    from conecal.simulate.render import Sphere, render_line_integrals

    im = Imaging(radial_px=2.0, s_px=-1.5)
    shape = (200, 240)
    xy = np.random.default_rng(0).uniform(0, 200, (50, 2))
    assert np.abs(im.undistort(im.distort(xy, shape), shape) - xy).max() < 1e-6
    corner = np.array([0.0, 0.0])
    assert np.hypot(*(im.distort(corner, shape) - corner)) == pytest.approx(np.hypot(2.0, 1.5))
    g = ConeGeometry.nominal(sod=100, sdd=400, shape=shape, pixel_pitch=(0.2, 0.2))
    X = np.array([-4.0, 3.0, 0.0])
    img = render_line_integrals(g, [Sphere(X, 0.5, 1.0)], ss=4, distortion=im)
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]]
    centroid = np.array([(img * cc).sum(), (img * rr).sum()]) / img.sum()
    plain = render_line_integrals(g, [Sphere(X, 0.5, 1.0)], ss=4)
    c0 = np.array([(plain * cc).sum(), (plain * rr).sum()]) / plain.sum()
    assert np.abs(centroid - im.distort(c0, shape)).max() < 0.02
    assert np.abs(centroid - c0).max() > 0.3


def test_image_effects_set_the_imaging_record():
    w = world()
    for spec, field, value in [("blur:sigma_px=0.3", "extra_blur_px", 0.3), ("beam_hardening:beta=0.1", "beam_hardening", 0.1),
                               ("detector_lag:fraction=0.04", "lag", 0.04), ("scatter:fraction=0.02", "scatter", 0.02)]:
        assert getattr(parse_effect(spec).apply(w).imaging, field) == pytest.approx(value)
    with pytest.raises(InputError):
        parse_effect("detector_lag:fraction=1.5").apply(w)
    with pytest.raises(InputError):
        parse_effect("scatter:fraction=-0.1").apply(w)


def arm_world():
    from conecal.simulate.scenarios import ROBOT_DH, ROBOT_HOME
    from conecal.geometry import RigidTransform
    from conecal.kinematics import DHRobot

    robot = DHRobot(np.array(ROBOT_DH, float), RigidTransform(np.eye(3), np.array([0, 0, 107.0])),
                    RigidTransform(np.eye(3), np.array([5.0, -3.0, 20.0])))
    q = ROBOT_HOME + np.linspace(0, 1, 6)[:, None] * np.array([20, -15, 40, 10, -30, 25, 90.0])
    return World.start(np.arange(6.0), q, robot=robot)


def test_gravity_torque_is_minus_the_slope_of_potential_energy():
    """tau_j = -dU/dq_j with U = -m (g . p): the moment about each joint axis
    is what moving that joint does to the holder's height."""
    from conecal.effects.robot import GRAVITY, gravity_torques

    w = arm_world()
    tau = gravity_torques(w)
    down = -w.robot.base.R[:, 2] * GRAVITY
    h = 1e-6
    for j in range(w.robot.n_joints):
        dq = np.zeros(w.robot.n_joints)
        dq[j] = np.degrees(h)
        p1 = w.robot.transforms(w.readings + dq).t
        p0 = w.robot.transforms(w.readings - dq).t
        slope = ((p1 - p0) * 1e-3 @ down) / (2 * h)     # -dU/dq per kg: J/rad = N*m
        assert np.allclose(tau[:, j], slope, atol=1e-6)
    assert np.allclose(tau[:, 0], 0, atol=1e-9)          # the vertical first joint carries no moment


def test_robot_effects_move_the_joints():
    w = arm_world()
    off = parse_effect("joint_offset:joint=q3,offset=0.05").apply(w)
    assert np.allclose(off.true_readings - w.readings, np.eye(7)[2] * 0.05)
    sag = parse_effect("robot_deflection:compliance=0.001,payload_kg=2").apply(w)
    from conecal.effects.robot import gravity_torques
    assert np.allclose(sag.true_readings - w.readings, 0.002 * gravity_torques(w))
    bl = parse_effect("backlash:axis=q2,amount=0.01").apply(w)
    assert np.allclose(np.abs(bl.true_readings - w.readings)[:, 1], 0.005)
    assert np.allclose(w.transforms().t, w.robot.transforms(w.readings).t)
    with pytest.raises(InputError, match="no joint named 'q9'"):
        parse_effect("joint_offset:joint=q9").apply(w)
    with pytest.raises(InputError, match="robot arm"):
        parse_effect("robot_deflection").apply(world())
