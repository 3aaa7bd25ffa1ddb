"""Effects of the source and the manipulator: each a model extension with a few parameters."""

from __future__ import annotations

import functools

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


def _interp_extended(x, xp, fp):
    """Linear interpolation of the logged path, continued along its first and
    last segments outside it (a stage already moving when the log starts)."""
    x, xp, fp = (np.asarray(v, dtype=float) for v in (x, xp, fp))
    out = np.interp(x, xp, fp)
    if len(xp) > 1:
        lo, hi = x < xp[0], x > xp[-1]
        out[lo] = fp[0] + (x[lo] - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0])
        out[hi] = fp[-1] + (x[hi] - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2])
    return out


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
        q = np.column_stack([_interp_extended(t + self.latency, t, world.readings[:, k])
                             for k in range(world.readings.shape[1])])
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


@functools.lru_cache(maxsize=64)
def _spline_basis(s_bytes: bytes, order: int) -> np.ndarray:
    """Cubic B-splines on ``order - 3`` even interior knots at s in [0, 1]
    (given as float64 bytes), less their value at 0, the first dropped."""
    from scipy.interpolate import BSpline

    s = np.frombuffer(s_bytes, float)
    n_inner = max(order - 3, 0)
    knots = np.concatenate([[0.0] * 4, np.linspace(0, 1, n_inner + 2)[1:-1], [1.0] * 4])
    B = BSpline.design_matrix(s, knots, 3).toarray()                     # (n, n_inner + 4)
    B0 = BSpline.design_matrix(np.array([0.0]), knots, 3).toarray()
    return (B - B0)[:, 1:]                                               # B_0 is the constant's share


def time_basis(times, form: str, order: int, tau: float = 0.0) -> np.ndarray:
    """(n, order) functions of time (s), each zero at the scan's start, for a
    drift of the given ``form``:

    ``poly``: ``s, s^2, ...`` with ``s = (t - t0) / duration``;
    ``warmup``: ``1 - exp(-(t - t0) / tau)`` (``order`` 1; ``tau`` s), a tube or
    mount settling after switch-on;
    ``spline``: cubic B-splines on ``order - 3`` evenly spaced interior knots
    (``order`` >= 3),
    less their value at the start (the constant belongs to the geometry).
    """
    t = np.asarray(times, float)
    t0, dur = float(t.min()), max(float(np.ptp(t)), 1e-9)
    s = (t - t0) / dur
    if form == "poly":
        return np.column_stack([s ** (k + 1) for k in range(order)])
    if form == "warmup":
        if not tau > 0:
            raise InputError(f"drift: a warm-up needs tau > 0 s, not {tau}")
        return (1.0 - np.exp(-(t - t0) / tau))[:, None]
    if form == "spline":
        # diagnose evaluates it thousands of times at the same times
        return _spline_basis(np.clip(s, 0, 1).tobytes(), order).copy()
    raise InputError(f"drift: unknown form {form!r} (poly, warmup, spline)")


@dataclass(frozen=True, eq=False)
class DriftPath(Effect):
    """The focal spot (``part="source"``) or the detector (``"detector"``)
    moves along ``time_basis(form, order, tau) @ coefficients`` (mm; the
    coefficients an (order, 3) array flattened, lab x, y, z). Families of
    drift forms for ``diagnose``; not in the ``--effect`` registry."""

    part: str = "source"
    form: str = "poly"
    order: int = 1
    tau: float = 0.0
    coefficients: tuple = (0.0, 0.0, 0.0)
    name = "drift"
    physics = ("the tube's focal spot or the detector's mount moves while they warm up or creep, smoothly "
               "with time")

    def offsets(self, times) -> np.ndarray:
        C = np.asarray(self.coefficients, float).reshape(-1, 3)
        return time_basis(times, self.form, self.order, self.tau) @ C

    def apply(self, world):
        d = self.offsets(world.times)
        if self.part == "source":
            return world.replace(source_offsets=world.source_offsets + d)
        return world.replace(detector_offsets=world.detector_offsets + d)


@dataclass(frozen=True, eq=False)
class TiltSeriesRotaryAxis(RotaryAxis):
    """A rotary axis whose direction tilts as a Fourier series of its angle:
    at reading q it is turned by the small rotation vector
    ``sum_k (a_k cos kq + b_k sin kq) e1 + (c_k cos kq + d_k sin kq) e2`` (rad),
    ``coefficients`` (K, 4) rows ``(a_k, b_k, c_k, d_k)``. Order 1 holds a
    precession in either sense (a cone) and a nod in any plane (a line)."""

    coefficients: tuple = ()

    def transforms(self, q_deg):
        q = np.deg2rad(np.asarray(q_deg, dtype=float))
        e1, e2 = orthonormal_complement(self.direction)
        C = np.asarray(self.coefficients, float).reshape(-1, 4)
        k = np.arange(1, len(C) + 1)
        cs, sn = np.cos(q[..., None] * k), np.sin(q[..., None] * k)
        t1 = cs @ C[:, 0] + sn @ C[:, 1]
        t2 = cs @ C[:, 2] + sn @ C[:, 3]
        d = (rotvec_to_matrix(t1[..., None] * e1 + t2[..., None] * e2) @ self.direction[:, None])[..., 0]
        R = axis_angle(d, q)
        t = self.point - (R @ self.point[:, None])[..., 0]
        return RigidTransform(R, t)


@dataclass(frozen=True, eq=False)
class RotaryTiltSeries(Effect):
    """The rotary axis direction tilts as a Fourier series of the angle
    (``coefficients``: K rows of 4, deg; see :class:`TiltSeriesRotaryAxis`).
    The wobble family of ``diagnose``; not in the ``--effect`` registry."""

    axis: str = "theta"
    coefficients: tuple = (0.0, 0.0, 0.0, 0.0)
    name = "rotary_wobble"
    physics = RotaryWobble.physics

    def apply(self, world):
        a = _axis(world, self.axis)
        if not isinstance(a, RotaryAxis):
            raise InputError(f"effect rotary_wobble: axis {self.axis!r} is not rotary")
        w = TiltSeriesRotaryAxis(a.name, a.direction, a.point, coefficients=tuple(np.deg2rad(self.coefficients)))
        return world.replace(chain=world.chain.replace_axis(self.axis, w))
