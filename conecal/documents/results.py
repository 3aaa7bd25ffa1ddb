"""pydantic models of conecal's result documents (format ``<name>/1``).

Each model types and checks what a consumer reads; the documents carry
more (fit statistics, residuals, diagnostics), kept as they are. Units:
mm, degrees, pixels (column, row); lab frame unless a key says otherwise.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from .common import (Axis, ChosenDistortion, Detector, Distortion, Doc, Finite, Intrinsic, Matrix3, MaybeFinite,
                     NonNegative, Parameter, PositiveFloat, ScanFingerprint, Vec3, source_off_detector)
from .status import REASONS

FrameNumber = Annotated[int, Field(ge=0, description="page index in the projection stack")]
Sigma3 = Annotated[list[NonNegative | None], Field(min_length=3, max_length=3)]


class _Result(Doc):
    software: str | None = Field(None, description="the conecal that wrote it")
    scan: str | list[str] | None = Field(None, description="the scan folder(s) as given on the command line")
    scan_binding: ScanFingerprint | list[ScanFingerprint] | None = Field(
        None, description="the scan(s) the result was computed from: path relative to this file, and fingerprints")


# ---- markers ---------------------------------------------------------------

class Marker(Doc):
    id: Annotated[int, Field(ge=-1)] | None = Field(None, description="identity, stable across frames; null: unknown")
    x: Finite = Field(description="centre column, px")
    y: Finite = Field(description="centre row, px")
    sigma: PositiveFloat = Field(description="1-sigma of x and y, px")
    flags: list[str] = []
    radius: MaybeFinite = None


class MarkersFrame(Doc):
    frame: FrameNumber
    markers: list[Marker]
    missing: list[int] | None = None


class MarkersDetector(Doc):
    shape: tuple[Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]] | None = None


class MarkersDocument(_Result):
    """``conecal-markers/1``: sphere shadow centres per frame (``detect``)."""

    format: Literal["conecal-markers/1"]
    frames: list[MarkersFrame]
    detector: MarkersDetector | None = None
    frame_range: tuple[FrameNumber, FrameNumber] | None = Field(
        None, description="a partial document (detect --frames START:STOP): frames START <= k < STOP")

    @field_validator("frames")
    @classmethod
    def _unique(cls, frames):
        seen = set()
        for i, f in enumerate(frames):
            if f.frame in seen:
                raise ValueError(f"frame {f.frame} appears twice (frames[{i}])")
            seen.add(f.frame)
        return frames


# ---- geometry --------------------------------------------------------------

class Fit(Doc):
    parameters: dict[str, Parameter] = {}
    rms_px: MaybeFinite = None
    chi2_reduced: MaybeFinite = None
    undetermined: list = []


class Sphere(Doc):
    id: int
    position: Vec3
    reference: bool | None = None


class _HasGeometry(_Result):
    source: Vec3 = Field(description="X-ray source, lab mm")
    detector: Detector
    axes: list[Axis] = []
    distortion: Distortion | None = None

    @model_validator(mode="after")
    def _projectable(self):
        source_off_detector(self.source, self.detector)
        names = [a.name for a in self.axes]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"axis {sorted(dup)[0]!r} appears twice in axes")
        return self


class GeometryDocument(_HasGeometry):
    """``conecal-geometry/1``: source, detector and axes in the lab frame
    (``fit-linear``, ``fit-rotation``, ``rp-grid``; ``simulate`` truth)."""

    format: Literal["conecal-geometry/1"]
    stage: str | None = None
    fit: Fit | None = None
    misalignment: dict[str, Parameter] | None = None
    spheres: list[Sphere] | None = None


# ---- poses -----------------------------------------------------------------

class PoseFrame(Doc):
    frame: FrameNumber
    status: Annotated[str, Field(pattern=r"^(ok|ambiguous|rejected)(:|$)")] = Field(
        description="ok, 'ambiguous: <reason>' or 'rejected: <reason>'")
    reason: str | None = Field(None, description="why a frame is not ok: a key of conecal.documents.status.REASONS")
    R: Matrix3 | None = Field(None, description="rotation, P_lab = R p_phantom + t")
    t: Vec3 | None = Field(None, description="translation, mm")
    sigma_rotation_deg: Sigma3 | None = None
    sigma_translation_mm: Sigma3 | None = None
    rms_px: MaybeFinite = None
    sphere_ids: list[int] | None = None
    matched: list[Annotated[list[int], Field(min_length=2, max_length=2)]] | None = None
    hidden: list[Annotated[list[int], Field(min_length=2, max_length=2)]] | None = Field(
        None, description="[sphere id, id of the sphere whose shadow hides it]: not measurable, not missing")
    distortion: Distortion | None = None
    # source and detector freed per frame (motion: free, a sagging C-arm)
    intrinsics: dict[str, Intrinsic] | None = None
    source: Vec3 | None = Field(None, description="this frame's X-ray source, lab mm (when freed per frame)")
    detector: Detector | None = None

    @model_validator(mode="after")
    def _pose(self):
        if (self.source is None) != (self.detector is None):
            raise ValueError("a frame's own geometry needs both source and detector")
        if self.source is not None:
            source_off_detector(self.source, self.detector)
        if self.reason is not None:
            if self.reason not in REASONS:
                raise ValueError(f"reason: {self.reason!r} is not one of {', '.join(REASONS)}")
            if self.status == "ok":
                raise ValueError("an ok frame has no reason")
        if self.status == "ok":
            if self.R is None or self.t is None:
                raise ValueError("an ok frame needs R and t")
            R = np.asarray(self.R, float)
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
                raise ValueError("R must be a rotation matrix (orthonormal, determinant +1)")
        return self


class PosesSummary(Doc):
    frames: Annotated[int, Field(ge=0)] | None = None
    ok: Annotated[int, Field(ge=0)] | None = None
    rejected: Annotated[int, Field(ge=0)] | None = None
    ambiguous: Annotated[int, Field(ge=0)] | None = None
    reasons: dict[str, Annotated[int, Field(ge=0)]] | None = Field(
        None, description="frames per reason key (conecal.documents.status.REASONS)")


class PosesDocument(_HasGeometry):
    """``conecal-poses/1``: the phantom's pose per frame (``fit-pose``)."""

    format: Literal["conecal-poses/1"]
    motion: Literal["robot", "free"] | None = None
    frames: list[PoseFrame]
    summary: PosesSummary | None = None
    intrinsics: dict[str, Intrinsic] | None = None
    distortion: ChosenDistortion | Distortion | None = None
    frame_range: tuple[FrameNumber, FrameNumber] | None = None

    @model_validator(mode="after")
    def _free(self):
        if self.motion == "free":
            missing = [k for k in ("sdd", "c0", "r0") if k not in (self.intrinsics or {})]
            if missing:
                raise ValueError(f"a free-pose result needs intrinsics.{missing[0]}")
            if self.distortion is not None and not isinstance(self.distortion, ChosenDistortion):
                raise ValueError("distortion: a free-pose result's distortion names its family and "
                                 "max_displacement_px")
        return self


# ---- diagnosis -------------------------------------------------------------

class Claim(Doc):
    effect: Annotated[str, Field(min_length=1)]
    parameters: dict[str, MaybeFinite] = {}


class Located(Doc):
    variable: str
    component: str | None = None
    size: MaybeFinite = None


class PoseSpread(Doc):
    """The holder's pose against the arm's model (diagnose on a robot fit-pose)."""

    rms_translation_mm: NonNegative
    rms_rotation_deg: NonNegative
    repeatability: dict[str, Annotated[list[NonNegative], Field(min_length=3, max_length=3)]] | None = None


class ImageLevel(Doc):
    chi2_per_dof_before: MaybeFinite = None
    chi2_per_dof_after: MaybeFinite = None
    n_patches: Annotated[int, Field(ge=0)] | None = None
    candidates: list[dict] = []


class DiagnosisDocument(_Result):
    """``conecal-diagnosis/1``: where the model and the recording differ, and
    which left-out effect explains it (``diagnose``)."""

    format: Literal["conecal-diagnosis/1"]
    result: str = Field(description="the result file diagnosed")
    stage: str | None = None
    verdict: str
    effects: list[Claim] = []
    located: list[Located] = []
    rms_px_before: MaybeFinite = None
    rms_px_after: MaybeFinite = None
    noise_floor_px: MaybeFinite = None
    rms_px: MaybeFinite = None
    heldout_gain_chi2: MaybeFinite = None
    before: PoseSpread | None = None
    after: PoseSpread | None = None
    image_level: ImageLevel | None = None
    candidates: list[dict] = []
    refitted_geometry: GeometryDocument | None = None


# ---- simulate's truth ------------------------------------------------------

class TruthDocument(Doc):
    """``conecal-truth/1``: what ``simulate`` put into a scan (for tests and reports)."""

    format: Literal["conecal-truth/1"]
    software: str
    kind: str
    seed: int | None = None
    geometry: GeometryDocument | None = None
