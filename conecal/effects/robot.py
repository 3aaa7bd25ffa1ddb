"""Effects of a serial robot arm: each a model extension with a few parameters.

They act on the joints (``World.true_readings``), so the arm's own
kinematics carries them to the holder: a joint error moves the holder by
the lever from that joint, differently in every configuration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .base import Effect, World, register

GRAVITY = 9.81  # m/s^2


def _joint(world: World, name: str) -> int:
    if world.robot is None:
        raise InputError(f"effect needs a robot arm; this scan has axes ({', '.join(world.names)})")
    if name not in world.names:
        raise InputError(f"effect: no joint named {name!r} (joints: {', '.join(world.names)})")
    return world.names.index(name)


def gravity_torques(world: World, readings: np.ndarray | None = None) -> np.ndarray:
    """(n, n_joints) N·m per kg of payload: the moment of the holder's weight
    about each joint axis. The holder's mass sits at its origin; gravity
    points along -z of the robot's base (the arm stands on its base)."""
    robot = world.robot
    q = world.true_readings if readings is None else readings
    frames = robot.joint_frames(q)
    holder = robot.transforms(q).t                       # (n, 3) mm, lab
    down = -robot.base.R[:, 2] * GRAVITY                # N per kg, lab
    out = np.empty((len(q), robot.n_joints))
    for j, F in enumerate(frames):
        lever = (holder - F.t) * 1e-3                   # m
        out[:, j] = np.einsum("ni,ni->n", F.R[:, :, 2], np.cross(lever, down))
    return out


@register
@dataclass(frozen=True, eq=False)
class JointOffset(Effect):
    """A joint stands ``offset`` deg away from what its encoder reports."""

    joint: str = "q2"
    offset: float = 0.02
    name = "joint_offset"
    physics = "a joint's encoder zero (or the DH angle offset) is off, so the joint stands a constant angle away"
    units = {"offset": "deg"}

    def apply(self, world):
        k = _joint(world, self.joint)
        true = world.true_readings.copy()
        true[:, k] += self.offset
        return world.replace(true_readings=true)


@register
@dataclass(frozen=True, eq=False)
class RobotDeflection(Effect):
    """Every joint yields ``compliance`` deg per N·m of the payload's gravity
    moment about its axis (``payload_kg`` at the holder's origin)."""

    compliance: float = 2e-3
    payload_kg: float = 2.0
    name = "robot_deflection"
    physics = ("the arm's gears and links are elastic: under the holder's weight each joint yields in "
               "proportion to the moment about its axis, which changes with the arm's configuration")
    units = {"compliance": "deg/(N·m)", "payload_kg": "kg"}

    def apply(self, world):
        if world.robot is None:
            raise InputError("effect robot_deflection needs a robot arm")
        tau = gravity_torques(world) * self.payload_kg
        return world.replace(true_readings=world.true_readings + self.compliance * tau)
