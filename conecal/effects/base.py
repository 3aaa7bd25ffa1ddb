"""Physical effects that a model may leave out, as small model extensions.

Each effect is a frozen dataclass with a few parameters in physical units,
a one-sentence ``physics`` description, and ``apply(world)`` that returns
the world as the effect makes it. ``simulate`` switches effects on through
this registry; ``diagnose`` (later) fits the same parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from ..errors import InputError
from ..geometry.transforms import RigidTransform
from ..kinematics import Chain
from .recording import Imaging

REGISTRY: dict[str, type["Effect"]] = {}


def register(cls):
    REGISTRY[cls.name] = cls
    return cls


@dataclass(frozen=True, eq=False)
class World:
    """Everything that moves during a scan, as it truly happened.

    times : (n,) s since the start; readings : (n, k) what the controller
    logged; true_readings : (n, k) where the axes really stood while each
    frame was exposed; chain : the true axes (None for a robot);
    robot : the true arm (robot scans), posed by ``true_readings``;
    placement : (robot scans) per-frame lab-side error of the arm beyond its
    joints (repeatability, a registration error), applied after it;
    source_offsets : (n, 3) mm added to the true focal-spot position;
    detector_offsets : (n, 3) mm added to the true detector position;
    imaging : how the detector records (blur, beam hardening, lag, scatter,
    distortion) beyond the line-integral model.
    """

    times: np.ndarray
    readings: np.ndarray
    true_readings: np.ndarray
    chain: Chain | None
    robot: "DHRobot | None"
    source_offsets: np.ndarray
    detector_offsets: np.ndarray = None
    imaging: "Imaging" = None
    placement: RigidTransform | None = None

    @classmethod
    def start(cls, times, readings, chain=None, robot=None, placement=None) -> "World":
        times = np.asarray(times, dtype=float)
        readings = np.asarray(readings, dtype=float)
        return cls(times, readings, readings.copy(), chain, robot, np.zeros((len(times), 3)),
                   np.zeros((len(times), 3)), Imaging(), placement)

    @property
    def names(self) -> list[str]:
        """The readings' columns: axis names, or q1..qn for a robot."""
        if self.chain is not None:
            return list(self.chain.names)
        return [f"q{j + 1}" for j in range(self.readings.shape[1])]

    def transforms(self) -> RigidTransform:
        """True sample-to-lab transform per frame."""
        if self.robot is not None:
            T = self.robot.transforms(self.true_readings)
            return T if self.placement is None else self.placement @ T
        if self.chain is None:
            # free poses (a C-arm's phantom): the placement is the whole pose
            return self.placement
        return self.chain.transforms(self.true_readings)

    def replace(self, **kw) -> "World":
        return replace(self, **kw)


class Effect:
    """Base class: subclasses are frozen dataclasses registered by ``name``."""

    name: ClassVar[str]
    physics: ClassVar[str]
    units: ClassVar[dict[str, str]] = {}

    def apply(self, world: World) -> World:  # pragma: no cover - interface
        raise NotImplementedError

    def to_dict(self) -> dict:
        return {"name": self.name, **{f.name: getattr(self, f.name) for f in fields(self)}}

    def describe(self) -> str:
        args = ", ".join(f"{f.name}={getattr(self, f.name)} {self.units.get(f.name, '')}".strip() for f in fields(self))
        return f"{self.name}({args}): {self.physics}"


def parse_effect(spec: str) -> Effect:
    """``"name"`` or ``"name:key=value,key=value"`` -> an Effect.

    Vector values are written with ``/`` between components: ``velocity=0.001/0/0``.
    """
    name, _, rest = spec.partition(":")
    name = name.strip()
    if name not in REGISTRY:
        raise InputError(f"--effect {spec!r}: unknown effect {name!r}; known: {', '.join(sorted(REGISTRY))}")
    cls = REGISTRY[name]
    known = {f.name: f for f in fields(cls)}
    kw = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or key not in known:
            raise InputError(f"--effect {spec!r}: {name} takes {', '.join(known)}; got {item!r}")
        try:
            if "/" in value:
                kw[key] = tuple(float(x) for x in value.split("/"))
            else:
                try:
                    kw[key] = float(value)
                except ValueError:
                    kw[key] = value
        except ValueError:
            raise InputError(f"--effect {spec!r}: {key}: not a number ({value!r})") from None
    try:
        return cls(**kw)
    except (TypeError, ValueError) as exc:
        raise InputError(f"--effect {spec!r}: {exc}") from None
