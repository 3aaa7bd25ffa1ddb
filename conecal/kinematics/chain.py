"""Kinematic chains of linear and rotary axes: readings -> sample transforms.

Axes are listed from the lab outwards to the sample (``SCAN_FORMAT.md``).
With readings ``q1..qn`` a point ``p`` fixed to the sample is at
``P = A1(q1)(A2(q2)(...An(qn)(p)))``; a linear axis is ``p -> p + q*d``
(q in mm, optionally scaled), a rotary axis ``p -> c + R(d, q)(p - c)``
(q in degrees at the edge, radians inside ``transforms``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry.rotations import axis_angle, rot_x, rot_z
from ..geometry.transforms import RigidTransform


def _unit(d, name):
    d = np.array(d, dtype=float).reshape(3)
    n = np.linalg.norm(d)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"axis {name!r}: direction must be a non-zero vector, got {d.tolist()}")
    d = d / n
    d.setflags(write=False)
    return d


@dataclass(frozen=True, eq=False)
class LinearAxis:
    """Translation along unit ``direction`` by ``scale * q`` mm."""

    name: str
    direction: np.ndarray
    scale: float = 1.0
    type: str = field(default="linear", init=False)

    def __post_init__(self):
        object.__setattr__(self, "direction", _unit(self.direction, self.name))

    def transforms(self, q: np.ndarray) -> RigidTransform:
        q = np.asarray(q, dtype=float)
        return RigidTransform(np.broadcast_to(np.eye(3), q.shape + (3, 3)), (self.scale * q)[..., None] * self.direction)

    def to_dict(self) -> dict:
        d = {"name": self.name, "type": "linear", "direction": self.direction.tolist()}
        if self.scale != 1.0:
            d["scale"] = self.scale
        return d


@dataclass(frozen=True, eq=False)
class RotaryAxis:
    """Rotation by ``q`` degrees (right-hand rule) about the line through
    ``point`` (mm) along unit ``direction``."""

    name: str
    direction: np.ndarray
    point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    type: str = field(default="rotary", init=False)

    def __post_init__(self):
        object.__setattr__(self, "direction", _unit(self.direction, self.name))
        p = np.array(self.point, dtype=float).reshape(3)
        p.setflags(write=False)
        object.__setattr__(self, "point", p)

    def transforms(self, q_deg: np.ndarray) -> RigidTransform:
        q = np.deg2rad(np.asarray(q_deg, dtype=float))
        R = axis_angle(self.direction, q)
        t = self.point - (R @ self.point[:, None])[..., 0]
        return RigidTransform(R, t)

    def to_dict(self) -> dict:
        return {"name": self.name, "type": "rotary", "direction": self.direction.tolist(),
                "point": self.point.tolist()}


Axis = LinearAxis | RotaryAxis


@dataclass(frozen=True, eq=False)
class Chain:
    """Axes from the lab outwards; maps readings (n_frames, n_axes) to transforms."""

    axes: tuple

    def __post_init__(self):
        names = [a.name for a in self.axes]
        if len(set(names)) != len(names):
            raise ValueError(f"axis names must be unique, got {names}")
        object.__setattr__(self, "axes", tuple(self.axes))

    @property
    def names(self) -> list[str]:
        return [a.name for a in self.axes]

    def transforms(self, readings: np.ndarray) -> RigidTransform:
        """Sample-to-lab transforms, one per row of ``readings`` (mm / degrees)."""
        q = np.atleast_2d(np.asarray(readings, dtype=float))
        if q.shape[1] != len(self.axes):
            raise ValueError(f"readings have {q.shape[1]} columns, the chain has {len(self.axes)} axes")
        T = RigidTransform.identity(q.shape[0])
        for k, ax in enumerate(self.axes):
            T = T @ ax.transforms(q[:, k])
        return T

    def replace_axis(self, name: str, axis) -> "Chain":
        return Chain(tuple(axis if a.name == name else a for a in self.axes))

    def to_list(self) -> list[dict]:
        return [a.to_dict() for a in self.axes]

    @classmethod
    def from_list(cls, axes: list[dict]) -> "Chain":
        """Inverse of :meth:`to_list`: the ``axes`` of a geometry document (mm, unit
        directions; a linear axis' ``scale`` defaults to 1, a rotary ``point`` to 0)."""
        out = []
        for a in axes:
            if a.get("type") == "linear":
                out.append(LinearAxis(a["name"], a["direction"], float(a.get("scale") or 1.0)))
            elif a.get("type") == "rotary":
                out.append(RotaryAxis(a["name"], a["direction"], a.get("point") or (0.0, 0.0, 0.0)))
            else:
                raise ValueError(f"axis {a.get('name')!r}: unknown type {a.get('type')!r}")
        return cls(tuple(out))


def dh_modified(a: float, alpha_deg: float, d: float, theta_deg: np.ndarray) -> RigidTransform:
    """Craig's modified DH link ``RotX(alpha) TransX(a) RotZ(theta) TransZ(d)``."""
    th = np.deg2rad(np.asarray(theta_deg, dtype=float))
    Rx = rot_x(np.deg2rad(alpha_deg))
    Rz = rot_z(th)
    R = Rx @ Rz
    t = Rx @ np.array([a, 0.0, 0.0]) + (R @ np.array([0.0, 0.0, d]))
    return RigidTransform(R, t)


@dataclass(frozen=True, eq=False)
class DHRobot:
    """Serial robot in modified Denavit-Hartenberg form (``SCAN_FORMAT.md``).

    ``dh`` rows are ``[a (mm), alpha (deg), d (mm), theta offset (deg)]``;
    ``flange`` maps holder coordinates to the last link, ``base`` robot
    base to lab: ``P = base * DH(q) * flange * p``.
    """

    dh: np.ndarray
    flange: RigidTransform
    base: RigidTransform

    def __post_init__(self):
        dh = np.array(self.dh, dtype=float)
        if dh.ndim != 2 or dh.shape[1] != 4:
            raise ValueError(f"dh must have rows [a, alpha, d, theta], got shape {dh.shape}")
        dh.setflags(write=False)
        object.__setattr__(self, "dh", dh)

    @property
    def n_joints(self) -> int:
        return self.dh.shape[0]

    def transforms(self, q_deg: np.ndarray) -> RigidTransform:
        """Holder-to-lab transforms for joint readings (n_frames, n_joints) in degrees."""
        q = np.atleast_2d(np.asarray(q_deg, dtype=float))
        if q.shape[1] != self.n_joints:
            raise ValueError(f"joint readings have {q.shape[1]} columns, the robot has {self.n_joints} joints")
        frames = self.joint_frames(q)
        n = q.shape[0]
        flange = RigidTransform(np.broadcast_to(self.flange.R, (n, 3, 3)), np.broadcast_to(self.flange.t, (n, 3)))
        return frames[-1] @ flange

    def joint_frames(self, q_deg: np.ndarray) -> list[RigidTransform]:
        """Each joint's frame in the lab (n_joints transforms of n_frames each):
        its origin lies on the joint axis and its z axis is the axis
        (rotation by +q turns about +z)."""
        q = np.atleast_2d(np.asarray(q_deg, dtype=float))
        if q.shape[1] != self.n_joints:
            raise ValueError(f"joint readings have {q.shape[1]} columns, the robot has {self.n_joints} joints")
        n = q.shape[0]
        T = RigidTransform(np.broadcast_to(self.base.R, (n, 3, 3)), np.broadcast_to(self.base.t, (n, 3)))
        out = []
        for k, (a, alpha, d, theta) in enumerate(self.dh):
            T = T @ dh_modified(a, alpha, d, theta + q[:, k])
            out.append(T)
        return out
