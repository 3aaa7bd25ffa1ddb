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


@dataclass(frozen=True)
class Imaging:
    """How the detector records, beyond the modelled blur and geometry.

    extra_blur_px : Gaussian sigma (px) added in quadrature to the modelled blur;
    beam_hardening : beta (dimensionless) in ``p = a / (1 + beta a)``, ``a``
        the monochromatic line integral, ``p`` the recorded attenuation;
    lag : fraction of the previous frame's intensity left in each frame;
    scatter : intensity added to every pixel, as a fraction of the open beam;
    radial_px, s_px : detector distortion, the radial (pincushion > 0) and
        tangential (S-shaped, counter-clockwise > 0) displacement (px) at the
        detector corner; both grow as the cube of the distance from the
        detector centre.
    """

    extra_blur_px: float = 0.0
    beam_hardening: float = 0.0
    lag: float = 0.0
    scatter: float = 0.0
    radial_px: float = 0.0
    s_px: float = 0.0
    warp: object = None        # a geometry.distortion.Distortion, on top of radial_px and s_px

    def add(self, **kw) -> "Imaging":
        return replace(self, **{k: getattr(self, k) + v for k, v in kw.items()})

    @property
    def distorted(self) -> bool:
        return bool(self.radial_px or self.s_px or self.warp is not None)

    def displacement(self, xy, shape) -> np.ndarray:
        """Distortion displacement (..., 2) px at ideal pixel coordinates ``xy`` (..., 2)."""
        d = distortion_displacement(xy, shape, self.radial_px, self.s_px)
        return d if self.warp is None else d + self.warp.displacement(xy)

    def distort(self, xy, shape) -> np.ndarray:
        """Where the detector records (..., 2) px what ideally falls at ``xy``."""
        xy = np.asarray(xy, float)
        return xy + self.displacement(xy, shape) if self.distorted else xy

    def undistort(self, xy, shape, iterations: int = 6) -> np.ndarray:
        """Inverse of :meth:`distort` by fixed-point iteration (displacements are small)."""
        xy = np.asarray(xy, float)
        if not self.distorted:
            return xy
        x = xy.copy()
        for _ in range(iterations):
            x = xy - self.displacement(x, shape)
        return x


def distortion_basis(xy, shape) -> tuple[np.ndarray, np.ndarray]:
    """Unit-corner radial and tangential displacement fields (..., 2) at ``xy``:
    ``rho^2 (x - c) / R`` and its 90-degree rotation, ``c`` the detector
    centre, ``R`` the half-diagonal, ``rho = |x - c| / R``."""
    rows, cols = shape
    c = np.array([(cols - 1) / 2, (rows - 1) / 2])
    R = 0.5 * np.hypot(cols - 1, rows - 1)
    d = (np.asarray(xy, float) - c) / R
    rho2 = np.sum(d * d, axis=-1, keepdims=True)
    radial = rho2 * d
    tangential = rho2 * np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return radial, tangential


def distortion_displacement(xy, shape, radial_px, s_px) -> np.ndarray:
    radial, tangential = distortion_basis(xy, shape)
    return radial_px * radial + s_px * tangential


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
