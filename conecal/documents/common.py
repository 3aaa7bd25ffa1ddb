"""Building blocks of conecal's result documents: finite numbers, vectors,
the detector, axes and fitted parameters, with the physical checks a reader
needs (unit directions, positive pitch, a rotation matrix that is one).

Units as in the files: mm, degrees, pixels (column, row). Every model keeps
keys it does not know (``extra="allow"``): a document may carry more than
its consumers read, and a later minor addition does not break an older
reader. What a consumer reads is typed and checked here.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

Finite = Annotated[float, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
# JSON has no NaN: conecal writes null for a value it could not determine
MaybeFinite = Finite | None
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Vec2 = Annotated[list[Finite], Field(min_length=2, max_length=2)]
Matrix3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]

UNIT_TOLERANCE = 1e-3   # |direction| may differ from 1 by rounding, not by a unit mistake


class Doc(BaseModel):
    """A part of a document: extra keys kept, nothing coerced from strings."""

    model_config = ConfigDict(extra="allow", strict=False, frozen=True)


def unit(v: list[float], what: str = "direction") -> list[float]:
    n = float(np.linalg.norm(v))
    if abs(n - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f"{what} must be a unit vector (its length is {n:.6g})")
    return v


class Detector(Doc):
    """Flat detector: pixel (c, r) sits at ``origin + c*pu*u + r*pv*v`` (lab mm)."""

    origin: Vec3 = Field(description="lab position of pixel (0, 0), mm")
    u: Vec3 = Field(description="unit vector along a row (increasing column)")
    v: Vec3 = Field(description="unit vector along a column (increasing row)")
    pixel_pitch: tuple[PositiveFloat, PositiveFloat] = Field(description="(pu, pv) mm")
    shape: tuple[Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]] = Field(description="(rows, cols)")

    @field_validator("u", "v")
    @classmethod
    def _unit(cls, v):
        return unit(v)

    @model_validator(mode="after")
    def _not_parallel(self):
        if abs(float(np.dot(self.u, self.v))) > 0.1:
            raise ValueError("u and v must be (nearly) perpendicular: they are the detector's row and column directions")
        return self


class Axis(Doc):
    """A manipulator axis: linear ``p -> p + q*scale*direction`` (mm) or rotary
    about the line through ``point`` along ``direction`` (degrees)."""

    name: Annotated[str, Field(min_length=1)]
    type: Literal["linear", "rotary"]
    direction: Vec3
    point: Vec3 | None = None
    scale: PositiveFloat | None = None

    @field_validator("direction")
    @classmethod
    def _unit(cls, v):
        return unit(v)


class Parameter(Doc):
    """A fitted parameter: value and 1-sigma in ``unit`` (null: not determined)."""

    value: MaybeFinite = None
    sigma: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None
    unit: str | None = None
    free: bool | None = None
    determined: bool | None = None


class Distortion(Doc):
    """Detector distortion: ideal pinhole (c, r) -> measured (c + dc, r + dr), px;
    coefficients in px of displacement at ``radius_px`` from ``centre``."""

    model: Literal["radial_tangential", "polynomial"]
    parameters: dict[str, Finite]
    centre: Vec2
    radius_px: PositiveFloat
    degree: Annotated[int, Field(ge=0)] | None = None
    twist_centre: Vec2 | None = None
    sigma: dict[str, Annotated[float, Field(ge=0, allow_inf_nan=False)] | None] | None = None

    @model_validator(mode="after")
    def _terms(self):
        from ..geometry.distortion import missing_terms

        missing = missing_terms(self.model, self.degree or 0, self.parameters)
        if missing:
            raise ValueError(f"parameters: the {self.model} model needs {missing[0]!r}")
        return self


class ChosenDistortion(Distortion):
    """A free-pose result's distortion: the family chosen on held-out markers."""

    family: Annotated[str, Field(min_length=1)]
    max_displacement_px: NonNegative


class Intrinsic(Parameter):
    """A free-pose intrinsic (sdd mm, c0/r0 px): value, total 1-sigma and its parts."""

    value: Finite
    sigma: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    unit: str
    sigma_statistical: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None
    sigma_model: Annotated[float, Field(ge=0, allow_inf_nan=False)] | None = None


class ScanFingerprint(Doc):
    """What a result was computed from, so that a consumer can tell the scan apart."""

    path: str = Field(description="the scan folder, relative to the result file's folder (or absolute)")
    scan_yaml_sha256: Annotated[str, Field(min_length=64, max_length=64)]
    log_sha256: Annotated[str, Field(min_length=64, max_length=64)] | None = None
    projections_bytes: Annotated[int, Field(ge=0)] | None = None
    projections_sha256_sampled: Annotated[str, Field(min_length=64, max_length=64)] | None = None


def source_off_detector(source, det: Detector) -> None:
    """The source must not lie in the detector's plane (no projection exists)."""
    n = np.cross(det.u, det.v)
    if abs(float(np.dot(np.subtract(source, det.origin), n))) < 1e-6:
        raise ValueError("the source lies in the detector plane")


def _where(loc) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def validation_message(exc: ValidationError) -> str:
    """One line: the first problem's key path and what is wrong with it."""
    errors = exc.errors()
    e = errors[0]
    msg = e["msg"].removeprefix("Value error, ")
    if e["type"] == "extra_forbidden":
        msg = "unknown key"
    elif e["type"] == "missing":
        msg = "required key is missing"
    got = e.get("input")
    got_s = "" if e["type"] in ("missing", "extra_forbidden") or isinstance(got, (dict, list)) else f" (got {got!r})"
    more = f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})" if len(errors) > 1 else ""
    return f"{_where(e['loc'])}: {msg}{got_s}{more}"
