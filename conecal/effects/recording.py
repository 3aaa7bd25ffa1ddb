"""What the detector records beyond the line-integral model: the imaging
state a :class:`~conecal.effects.World` carries (blur added, beam hardening,
lag, scatter, detector distortion), and the distortion fields (px).

Its own module so that ``World`` (effects.base) and the effects that change
it (effects.imaging) both import it, without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


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
