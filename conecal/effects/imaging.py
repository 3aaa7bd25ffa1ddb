"""Effects of the detector and the beam: how line integrals become a recorded image.

The line-integral model (``simulate``'s renderer, and the fits' shadow
centroids) assumes a Gaussian blur of the stated width, attenuation
proportional to path length, frames independent of each other, no
scattered photons and a distortion-free detector. Each effect below breaks
one of these with one or two parameters; :class:`Imaging` collects them on
the :class:`~conecal.effects.World` so that ``simulate`` renders them and
``diagnose`` fits them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

import numpy as np

from ..errors import InputError
from .base import Effect, register
from .recording import Imaging, distortion_basis, distortion_displacement  # noqa: F401  (re-exported)


def beam_hardened(a, beta: float):
    """Recorded attenuation of a monochromatic line integral ``a`` under beam hardening."""
    return a / (1.0 + beta * a) if beta else a


def unhardened(p, beta: float):
    """Inverse of :func:`beam_hardened`."""
    return p / (1.0 - beta * p) if beta else p


def _nonneg(name, **kw):
    for k, v in kw.items():
        if not np.isfinite(v) or v < 0:
            raise InputError(f"effect {name}: {k} must be finite and >= 0, got {v}")


@register
@dataclass(frozen=True, eq=False)
class Blur(Effect):
    """Edges wider than the modelled blur."""

    sigma_px: float = 0.6
    name = "blur"
    physics = "the focal spot is larger (or the scintillator thicker) than stated, so edges are wider than modelled"
    units = {"sigma_px": "px (Gaussian sigma, added in quadrature)"}

    def apply(self, world):
        _nonneg(self.name, sigma_px=self.sigma_px)
        s = np.hypot(world.imaging.extra_blur_px, self.sigma_px)
        return world.replace(imaging=replace(world.imaging, extra_blur_px=float(s)))


class _ImagingTerm(Effect):
    """An effect whose one parameter adds to one field of :class:`Imaging`."""

    target: ClassVar[str]
    upper: ClassVar[float] = np.inf

    def apply(self, world):
        (f,) = fields(self)
        v = getattr(self, f.name)
        _nonneg(self.name, **{f.name: v})
        if v >= self.upper:
            raise InputError(f"effect {self.name}: {f.name} must be < {self.upper}, got {v}")
        return world.replace(imaging=world.imaging.add(**{self.target: v}))


@register
@dataclass(frozen=True, eq=False)
class BeamHardening(_ImagingTerm):
    """Attenuation grows less than proportionally with path length."""

    beta: float = 0.05
    name = "beam_hardening"
    target = "beam_hardening"
    physics = ("the polychromatic beam loses its soft photons first, so the effective attenuation falls along "
               "the path and thick chords read too thin (cupping)")
    units = {"beta": "(dimensionless, p = a / (1 + beta a))"}


@register
@dataclass(frozen=True, eq=False)
class DetectorLag(_ImagingTerm):
    """Each frame keeps a fraction of the previous one."""

    fraction: float = 0.05
    name = "detector_lag"
    target = "lag"
    upper = 1.0
    physics = "the scintillator's afterglow and the panel's charge trapping leave a ghost of the previous frame"
    units = {"fraction": "(of the previous frame's intensity)"}


@register
@dataclass(frozen=True, eq=False)
class Scatter(_ImagingTerm):
    """An intensity added everywhere, as a fraction of the open beam."""

    fraction: float = 0.03
    name = "scatter"
    target = "scatter"
    physics = ("photons scattered in the object (or a dark-offset error) add intensity that no line integral "
               "explains, so dense chords read too thin")
    units = {"fraction": "(of the open-beam intensity)"}


@register
@dataclass(frozen=True, eq=False)
class DetectorDistortion(Effect):
    """Radial (pincushion/barrel) and S-shaped distortion of the detector image."""

    radial_px: float = 0.5
    s_px: float = 0.0
    name = "detector_distortion"
    physics = ("the detector maps the beam onto its pixels with a non-linear warp: radial (pincushion) from its "
               "optics, S-shaped where a magnetic field bends an image intensifier's electrons")
    units = {"radial_px": "px at the detector corner", "s_px": "px at the detector corner"}

    def apply(self, world):
        if not (np.isfinite(self.radial_px) and np.isfinite(self.s_px)):
            raise InputError("effect detector_distortion: radial_px and s_px must be finite")
        return world.replace(imaging=world.imaging.add(radial_px=self.radial_px, s_px=self.s_px))


@dataclass(frozen=True, eq=False)
class DetectorWarp(Effect):
    """A detector distortion of any documented form (``geometry.distortion``):
    radial k1..k3 about a free centre, tangential, S-shaped, or a polynomial
    field. Not in the ``--effect`` registry (its parameters are a model)."""

    distortion: object
    name = "detector_distortion"
    physics = DetectorDistortion.physics

    def apply(self, world):
        w = world.imaging.warp
        if w is not None:
            raise InputError("effect detector_distortion: one general warp at a time")
        return world.replace(imaging=replace(world.imaging, warp=self.distortion))
