"""pydantic models of ``scan.yaml`` (format ``conecal-scan/1``).

Frozen, unknown keys rejected. Units as in the file: mm and degrees.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..errors import FormatVersionError, InputError

SCAN_FORMAT = "conecal-scan/1"
# motion: free: rotation vector (deg) and translation (mm) of a rough pose guess
POSE_GUESS_COLUMNS = ("rx", "ry", "rz", "tx", "ty", "tz")

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class DetectorSpec(_Model):
    rows: Annotated[int, Field(gt=0)]
    cols: Annotated[int, Field(gt=0)]
    pixel_pitch: tuple[PositiveFloat, PositiveFloat]

    @model_validator(mode="after")
    def _size(self):
        # (a pitch of 1e306 mm passed the positive-number check, and the
        # detector's corner then sat at -inf)
        if min(self.pixel_pitch) < 1e-4:
            raise ValueError(f"pixel_pitch {list(self.pixel_pitch)}: below 0.1 micrometre; pixel_pitch is in mm")
        width, height = self.cols * self.pixel_pitch[0], self.rows * self.pixel_pitch[1]
        if max(width, height) > 1e4:
            raise ValueError(f"pixel_pitch {list(self.pixel_pitch)} makes the detector {width:.3g} x {height:.3g} mm; "
                             "pixel_pitch is in mm (a detector is at most a few hundred mm across)")
        return self


class NominalSpec(_Model):
    sod: PositiveFloat
    sdd: PositiveFloat
    principal_point: tuple[Finite, Finite] | None = None

    @model_validator(mode="after")
    def _order(self):
        if self.sdd > 1e5:
            raise ValueError(f"sdd {self.sdd} mm is over 100 m; sdd and sod are in mm")
        if self.sdd <= self.sod:
            raise ValueError(f"sdd ({self.sdd}) must exceed sod ({self.sod}): the object sits between source and detector")
        return self


class MarkerSpec(_Model):
    diameter: PositiveFloat
    phantom: str | None = None
    # optional extension: spheres of several sizes in one scan (mm)
    diameters: tuple[PositiveFloat, ...] | None = None


class ImagingSpec(_Model):
    """Optional extension: what the system's specification says about its image."""

    # Gaussian sigma (px) of focal-spot plus detector blur; diagnose compares
    # the recorded edges with it
    blur_px: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None


class AxisSpec(_Model):
    name: Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")]
    type: Literal["linear", "rotary"]
    direction: Vec3
    point: Vec3 | None = None

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v):
        if np.linalg.norm(v) == 0:
            raise ValueError("direction must be a non-zero vector")
        return v

    @model_validator(mode="after")
    def _point(self):
        if self.type == "linear" and self.point is not None:
            raise ValueError("a linear axis takes no 'point'")
        return self


Matrix4 = tuple[tuple[Finite, Finite, Finite, Finite], ...]


class RobotSpec(_Model):
    dh: tuple[tuple[Finite, Finite, Finite, Finite], ...]
    flange: Matrix4 = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
    base: Matrix4 = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))

    @field_validator("flange", "base")
    @classmethod
    def _rigid(cls, m):
        M = np.asarray(m, dtype=float)
        if M.shape != (4, 4):
            raise ValueError(f"must be a 4x4 matrix, got {M.shape[0]} rows")
        R = M[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(M[3], [0, 0, 0, 1]):
            raise ValueError("must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        return m

    @field_validator("dh")
    @classmethod
    def _rows(cls, dh):
        if len(dh) == 0:
            raise ValueError("needs at least one joint row")
        return dh


class ScanConfig(_Model):
    format: str
    motion: Literal["linear", "rotation", "robot", "circular", "free"]
    projections: str
    values: Literal["attenuation", "transmission", "raw"]
    flat: str | None = None
    dark: str | None = None
    log: str
    detector: DetectorSpec
    nominal: NominalSpec
    markers: MarkerSpec | None = None
    axes: tuple[AxisSpec, ...] = ()
    robot: RobotSpec | None = None
    imaging: ImagingSpec | None = None

    @field_validator("format")
    @classmethod
    def _format(cls, v):
        name, _, version = v.partition("/")
        if name != "conecal-scan":
            raise ValueError(f"must be {SCAN_FORMAT!r}, got {v!r}")
        if version != "1":
            raise ValueError(f"{v!r} is newer than this conecal reads ({SCAN_FORMAT}); upgrade conecal")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.values == "raw" and (self.flat is None or self.dark is None):
            raise ValueError("values: raw needs both 'flat' and 'dark'")
        if self.motion == "robot" and self.robot is None:
            raise ValueError("motion: robot needs a 'robot' section")
        if self.motion in ("linear", "rotation", "circular") and not self.axes:
            raise ValueError(f"motion: {self.motion} needs 'axes'")
        names = [a.name for a in self.axes]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"axis names must be unique, repeated: {dup}")
        if self.motion == "free":
            if self.axes or self.robot is not None:
                raise ValueError("motion: free takes no 'axes' and no 'robot' (every frame's pose is unknown)")
            if self.markers is None or self.markers.phantom is None:
                raise ValueError("motion: free needs markers.phantom (the known phantom the poses are found from)")
        if self.motion in ("rotation", "circular") and not any(a.type == "rotary" for a in self.axes):
            raise ValueError(f"motion: {self.motion} needs a rotary axis")
        return self

    @property
    def optional_log_columns(self) -> list[str]:
        """Log columns a scan may leave out: a free-pose scan's rough pose guess."""
        return list(POSE_GUESS_COLUMNS) if self.motion == "free" else []

    @property
    def joint_names(self) -> list[str]:
        """Log columns that carry readings: axis names, or q1..qn for a robot."""
        if self.motion == "robot":
            return [f"q{k + 1}" for k in range(len(self.robot.dh))]
        return [a.name for a in self.axes]


def _loc(err: dict) -> str:
    return ".".join(str(p) for p in err["loc"]) or "(top level)"


def load_config(path: str | Path) -> ScanConfig:
    """Read and validate ``scan.yaml``; raise :class:`InputError` with one line
    naming the file and the key on any problem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(f"{path}: not valid YAML{where}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of keys, got {type(data).__name__}")
    try:
        return ScanConfig.model_validate(data)
    except ValidationError as exc:
        e = exc.errors()[0]
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        elif e["type"] == "missing":
            msg = "required key is missing"
        if _loc(e) == "format" and "newer" in msg:
            raise FormatVersionError(f"{path}: format: {msg}") from None
        got = e.get("input")
        got_s = "" if e["type"] in ("missing", "extra_forbidden") or isinstance(got, dict) else f" (got {got!r})"
        raise InputError(f"{path}: {_loc(e)}: {msg}{got_s}") from None
