"""Effects of the source and the manipulator: each a model extension with a few parameters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..geometry.rotations import axis_angle, orthonormal_complement, rotvec_to_matrix
from ..geometry.transforms import RigidTransform
from ..kinematics import LinearAxis, RotaryAxis
from .base import Effect, World, register


def _ramp(world: World, velocity) -> np.ndarray:
    """(n, 3) offsets growing linearly from the scan's start at ``velocity`` (mm/s)."""
    return (world.times - world.times[0])[:, None] * np.asarray(velocity, dtype=float).reshape(3)


def _axis(world: World, name: str):
    if world.chain is None:
        raise InputError(f"effect needs a chain of axes; this scan has none (axis {name!r})")
    for a in world.chain.axes:
        if a.name == name:
            return a
    raise InputError(f"effect: no axis named {name!r} (axes: {', '.join(world.chain.names)})")


@register
@dataclass(frozen=True, eq=False)
class FocalSpotDrift(Effect):
    """Linear drift of the focal spot over time."""

    velocity: tuple = (0.0005, 0.0, 0.0)
    name = "focal_spot_drift"
    physics = "the anode heats up and the focal spot moves steadily while the tube warms"
    units = {"velocity": "mm/s"}

    def apply(self, world):
        return world.replace(source_offsets=world.source_offsets + _ramp(world, self.velocity))


@register
@dataclass(frozen=True, eq=False)
class AxisScale(Effect):
    """A linear axis moves (1 + scale) times what its encoder reports."""

    axis: str = "x"
    scale: float = 0.002
    name = "axis_scale"
    physics = "the lead of a linear stage's screw or its encoder scale differs from nominal"
    units = {"scale": "(dimensionless)"}

    def apply(self, world):
        a = _axis(world, self.axis)
        if not isinstance(a, LinearAxis):
            raise InputError(f"effect axis_scale: axis {self.axis!r} is not linear")
        return world.replace(chain=world.chain.replace_axis(self.axis, LinearAxis(a.name, a.direction, a.scale * (1 + self.scale))))


@register
@dataclass(frozen=True, eq=False)
class AxisNonOrthogonality(Effect):
    """A linear axis is tilted by ``angle`` towards another axis."""

    axis: str = "y"
    towards: str = "x"
    angle: float = 0.1
    name = "axis_nonorthogonality"
    physics = "stacked stages are mounted not quite at right angles to each other"
    units = {"angle": "deg"}

    def apply(self, world):
        a, b = _axis(world, self.axis), _axis(world, self.towards)
        if not isinstance(a, LinearAxis):
            raise InputError(f"effect axis_nonorthogonality: axis {self.axis!r} is not linear")
        n = np.cross(a.direction, b.direction)
        if np.linalg.norm(n) < 1e-9:
            raise InputError(f"effect axis_nonorthogonality: {self.axis!r} and {self.towards!r} are parallel")
        d = axis_angle(n, np.deg2rad(self.angle)) @ a.direction
        return world.replace(chain=world.chain.replace_axis(self.axis, LinearAxis(a.name, d, a.scale)))


@dataclass(frozen=True, eq=False)
class WobblingRotaryAxis(RotaryAxis):
    """A rotary axis whose direction precesses once per turn by ``amplitude`` rad."""

    amplitude: float = 0.0
    phase: float = 0.0

    def transforms(self, q_deg):
        q = np.deg2rad(np.asarray(q_deg, dtype=float))
        e1, e2 = orthonormal_complement(self.direction)
        tilt = self.amplitude * (np.cos(q + self.phase)[..., None] * e1 + np.sin(q + self.phase)[..., None] * e2)
        d = (rotvec_to_matrix(tilt) @ self.direction[:, None])[..., 0]
        R = axis_angle(d, q)
        t = self.point - (R @ self.point[:, None])[..., 0]
        return RigidTransform(R, t)


@register
@dataclass(frozen=True, eq=False)
class RotaryWobble(Effect):
    """The rotary axis direction tilts by ``amplitude`` with the angle (once per turn)."""

    axis: str = "theta"
    amplitude: float = 0.02
    phase: float = 0.0
    name = "rotary_wobble"
    physics = "a rotation stage's bearing is not perfectly true, so its axis precesses as it turns"
    units = {"amplitude": "deg", "phase": "deg"}

    def apply(self, world):
        a = _axis(world, self.axis)
        if not isinstance(a, RotaryAxis):
            raise InputError(f"effect rotary_wobble: axis {self.axis!r} is not rotary")
        w = WobblingRotaryAxis(a.name, a.direction, a.point, amplitude=np.deg2rad(self.amplitude),
                               phase=np.deg2rad(self.phase))
        return world.replace(chain=world.chain.replace_axis(self.axis, w))


@dataclass(frozen=True, eq=False)
class RunoutRotaryAxis(RotaryAxis):
    """A rotary axis whose line moves sideways ``harmonic`` times per turn.

    At reading q the axis is displaced, perpendicular to its direction, by
    ``forward * (cos(k q + fp) e1 + sin(k q + fp) e2) + backward * (cos(k q + bp) e1 - sin(k q + bp) e2)``
    (mm; e1, e2 from :func:`orthonormal_complement`): a forward and a
    backward whirl, together any ellipse traced k times per turn.
    """

    harmonic: int = 2
    forward: float = 0.0
    forward_phase: float = 0.0     # rad
    backward: float = 0.0
    backward_phase: float = 0.0    # rad

    def transforms(self, q_deg):
        T = RotaryAxis.transforms(self, q_deg)
        q = np.deg2rad(np.asarray(q_deg, dtype=float))
        e1, e2 = orthonormal_complement(self.direction)
        kf, kb = self.harmonic * q + self.forward_phase, self.harmonic * q + self.backward_phase
        d = (self.forward * np.cos(kf) + self.backward * np.cos(kb))[..., None] * e1 \
            + (self.forward * np.sin(kf) - self.backward * np.sin(kb))[..., None] * e2
        return RigidTransform(T.R, T.t + d)


@register
@dataclass(frozen=True, eq=False)
class RotaryRunout(Effect):
    """The rotary axis' line moves sideways, ``harmonic`` times per turn
    (radial error motion; amplitudes in mm, phases in deg).

    Once per turn (harmonic 1) a forward whirl turns with the table: it is a
    fixed offset of everything on the table, which the fitted sphere
    positions take up exactly (ISO 230-7 removes this fundamental as a
    centring error for the same reason); only its backward part, and the
    higher harmonics, show.
    """

    axis: str = "theta"
    amplitude: float = 0.005
    phase: float = 0.0
    harmonic: int = 2
    backward: float = 0.0
    backward_phase: float = 0.0
    name = "rotary_runout"
    physics = ("a rotation stage's bearing is not round (its balls or races are lobed), so the axis of "
               "rotation moves sideways as the table turns, a few times per turn")
    units = {"amplitude": "mm", "phase": "deg", "harmonic": "per turn", "backward": "mm", "backward_phase": "deg"}

    def __post_init__(self):
        if int(self.harmonic) != self.harmonic or self.harmonic < 1:
            raise ValueError(f"harmonic must be a whole number >= 1, not {self.harmonic}")

    def apply(self, world):
        a = _axis(world, self.axis)
        if not isinstance(a, RotaryAxis):
            raise InputError(f"effect rotary_runout: axis {self.axis!r} is not rotary")
        r = RunoutRotaryAxis(a.name, a.direction, a.point, harmonic=int(self.harmonic), forward=self.amplitude,
                             forward_phase=np.deg2rad(self.phase), backward=self.backward,
                             backward_phase=np.deg2rad(self.backward_phase))
        return world.replace(chain=world.chain.replace_axis(self.axis, r))


@register
@dataclass(frozen=True, eq=False)
class EncoderLatency(Effect):
    """Frames are exposed ``latency`` s after the encoders were read."""

    latency: float = 0.05
    name = "encoder_latency"
    physics = "encoders and detector are not triggered together, so a moving axis is logged where it was, not where it is"
    units = {"latency": "s"}

    def apply(self, world):
        t = world.times
        q = np.column_stack([np.interp(t + self.latency, t, world.readings[:, k]) for k in range(world.readings.shape[1])])
        return world.replace(true_readings=q)


@register
@dataclass(frozen=True, eq=False)
class DetectorDrift(Effect):
    """Linear drift of the detector over time."""

    velocity: tuple = (0.0005, 0.0, 0.0)
    name = "detector_drift"
    physics = "the detector's mount warms and creeps, so the panel moves slowly during the scan"
    units = {"velocity": "mm/s"}

    def apply(self, world):
        return world.replace(detector_offsets=world.detector_offsets + _ramp(world, self.velocity))


@register
@dataclass(frozen=True, eq=False)
class Backlash(Effect):
    """An axis lags its encoder by half the backlash in the direction of motion."""

    axis: str = "theta"
    amount: float = 0.05
    name = "backlash"
    physics = ("play in a stage's drive: after each reversal the encoder (on the motor) runs ahead of the "
               "carriage by the backlash, so the error follows the sign of the velocity")
    units = {"amount": "mm or deg (the axis' unit)"}

    def apply(self, world):
        if world.chain is not None:
            _axis(world, self.axis)
        elif self.axis not in world.names:
            raise InputError(f"effect backlash: no joint named {self.axis!r} (joints: {', '.join(world.names)})")
        k = world.names.index(self.axis)
        q = world.readings[:, k]
        v = np.gradient(q, world.times) if len(q) > 1 else np.zeros_like(q)
        true = world.true_readings.copy()
        true[:, k] = true[:, k] - 0.5 * self.amount * np.sign(v)
        return world.replace(true_readings=true)
