"""Kinematic chains and DH robots against hand-composed transforms."""

import numpy as np
import pytest

from conecal.geometry import RigidTransform, axis_angle
from conecal.kinematics import Chain, DHRobot, LinearAxis, RotaryAxis, dh_modified


def test_rotary_axis_right_hand_rule_about_its_point():
    ax = RotaryAxis("theta", [0, 1, 0], [1.0, 0, 0])
    T = ax.transforms(np.array([90.0]))
    # (2,0,0) is 1 mm from the axis along +x; +90 deg about +y takes +x to -z
    assert np.allclose(T.apply(np.array([[2.0, 0, 0]])), [[1.0, 0, -1.0]])


def test_chain_applies_axes_from_the_lab_outwards():
    chain = Chain((LinearAxis("x", [1, 0, 0]), RotaryAxis("theta", [0, 0, 1], [0, 0, 0])))
    p = np.array([[1.0, 0, 0]])
    T = chain.transforms(np.array([[5.0, 90.0]]))
    # P = A1(q1)(A2(q2)(p)): rotate first, then translate
    assert np.allclose(T.apply(p), [[5.0, 1.0, 0.0]])


def test_linear_axis_scale_and_chain_validation():
    ax = LinearAxis("x", [2, 0, 0], scale=1.01)
    assert np.allclose(ax.transforms(np.array([10.0])).t, [[10.1, 0, 0]])
    with pytest.raises(ValueError, match="unique"):
        Chain((LinearAxis("x", [1, 0, 0]), LinearAxis("x", [0, 1, 0])))
    with pytest.raises(ValueError, match="non-zero"):
        LinearAxis("x", [0, 0, 0])
    with pytest.raises(ValueError, match="columns"):
        Chain((LinearAxis("x", [1, 0, 0]),)).transforms(np.zeros((3, 2)))


def test_modified_dh_is_craigs_order(rng):
    a, alpha, d, theta = 30.0, -90.0, 120.0, 25.0
    T = dh_modified(a, alpha, d, np.array(theta))
    Rx = RigidTransform(axis_angle(np.array([1.0, 0, 0]), np.deg2rad(alpha)), np.zeros(3))
    Tx = RigidTransform(np.eye(3), np.array([a, 0, 0]))
    Rz = RigidTransform(axis_angle(np.array([0, 0, 1.0]), np.deg2rad(theta)), np.zeros(3))
    Tz = RigidTransform(np.eye(3), np.array([0, 0, d]))
    ref = Rx @ Tx @ Rz @ Tz
    assert np.allclose(T.matrix(), ref.matrix())


def test_robot_forward_kinematics_composes_base_links_flange(rng):
    dh = np.array([[0, 0, 340, 0], [0, -90, 0, 0], [50, 90, 400, 10]], float)
    base = RigidTransform(axis_angle(np.array([0, 0, 1.0]), 0.3), np.array([10.0, 20, 30]))
    flange = RigidTransform(np.eye(3), np.array([0, 0, 107.0]))
    robot = DHRobot(dh, flange, base)
    q = rng.uniform(-90, 90, (4, 3))
    T = robot.transforms(q)
    for k in range(4):
        ref = base
        for (a, al, d, th), qj in zip(dh, q[k]):
            ref = ref @ dh_modified(a, al, d, np.array(th + qj))
        ref = ref @ flange
        assert np.allclose(T[k].matrix(), ref.matrix())


def test_chain_to_list_and_from_list_round_trip():
    from conecal.kinematics import Chain, LinearAxis, RotaryAxis

    chain = Chain((LinearAxis("x", [1.0, 0.0, 0.0], 1.002), LinearAxis("y", [0.0, 1.0, 0.0]),
                   RotaryAxis("theta", [0.0, 0.6, 0.8], [1.0, 2.0, 3.0])))
    again = Chain.from_list(chain.to_list())
    q = np.array([[1.0, -2.0, 30.0], [0.5, 0.0, -170.0]])
    T1, T2 = chain.transforms(q), again.transforms(q)
    assert np.allclose(T1.R, T2.R) and np.allclose(T1.t, T2.t)
    assert again.to_list() == chain.to_list()
    with pytest.raises(ValueError, match="spiral"):
        Chain.from_list([{"name": "a", "type": "spiral", "direction": [1, 0, 0]}])
