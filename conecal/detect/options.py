"""detect's settings (:class:`DetectOptions`) and what it measures of one
shadow (:class:`Blob`). Units: px and attenuation unless stated."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .noise import weights_kappa


@dataclass(frozen=True)
class DetectOptions:
    """Settings of the detector (px unless stated).

    diameter_px : (min, max) expected shadow diameters, full-resolution px.
    threshold : candidate peak height in noise sigmas (smoothed, downsampled top-hat).
    min_snr : smallest shadow peak over background noise (full resolution).
    max_anisotropy : largest ratio of the principal second moments for a sphere.
    min_relative_contrast : fraction of the scan's median sphere attenuation
        coefficient below which a blob is a ghost or a faint blob, not a marker.
    blur_px : expected blur sigma of the system, widens the windows.
    max_attenuation : pixels above it are not measurements (outside a
        circular field of view, dead or saturated); shadows touching them
        are flagged truncated, or dropped when mostly hidden.
    """

    diameter_px: tuple[float, float]
    threshold: float = 10.0
    min_snr: float = 5.0
    max_anisotropy: float = 1.25
    min_relative_contrast: float = 0.35
    blur_px: float = 1.0
    # attenuation beyond which a pixel is dead, saturated or outside a
    # circular field of view (transmission below 1.8 %)
    max_attenuation: float = 4.0
    # the scan's pixel noise with its correlated part (``noise_pixel``), measured
    # once per scan: the floor of the clutter test's reference noise
    pixel_noise: float = 0.0
    # the noise's correlation factor (``noise_correlation``): a centroid's
    # noise variance is this times the white-noise formula; measured once per scan
    noise_kappa: float = 1.0
    # the noise's autocorrelation (``noise.noise_autocorrelation``; (): not
    # measured): how much of kappa a small shadow's centre takes (``kappa_for``)
    noise_rho: tuple = ()
    # neighbour-difference noise (``noise_small`` at ``factor``, full-resolution
    # units) of the frame ``pixel_noise`` was measured on: a frame noisier than
    # that by 30 % measures its own pixel noise (0: never)
    noise_reference: float = 0.0
    # touching shadows fitted together, merged blobs split, a straight
    # background step beside a shadow removed (conecal.detect.crowded)
    joint_overlaps: bool = True
    # the declared spheres' shadow diameters (px) at the nominal magnification,
    # from which ``diameter_px`` was made; empty when the user gave the range
    shadow_px: tuple[float, ...] = ()
    # the phantom's extent about its centre over the nominal source distance (0:
    # unknown, then no sphere is judged by its attenuation alone: ``depth_ratio``)
    depth_extent: float = 0.0
    # measured over nominal shadow size (:mod:`conecal.detect.size`; 0: not measured)
    size_scale: float = 0.0
    # the image's response, measured once per scan (:func:`conecal.detect.gain.response_lambda`):
    # frames are measured in (1 - exp(-lambda a)) / lambda; 0: in attenuation a; None: not measured
    response_lambda: float | None = None

    @property
    def depth_ratio(self) -> float:
        """The largest ratio of two of the phantom's spheres' magnifications in one frame,
        (1 + e) / (1 - e), e its extent over the measured size's source distance (0: unknown)."""
        e = self.depth_extent * (self.size_scale or 1.0)
        return (1 + e) / (1 - e) if 0 < e < 0.95 else 0.0

    def kappa_for(self, kind: str, radius: float) -> float:
        """``noise_kappa`` as it applies to a centre measured by ``kind``
        (``model`` fit of a shadow of ``radius`` px, or ``centroid`` over a
        window of that radius): :func:`conecal.detect.noise.weights_kappa`."""
        return weights_kappa(self.noise_kappa, self.noise_rho, kind, radius, self.blur_px)

    @property
    def factor(self) -> int:
        """Downsampling factor: keep the smallest marker >= ~6 px across."""
        f = int(np.clip(np.floor(self.diameter_px[0] / 6.0), 1, 8))
        return 1 << (f.bit_length() - 1)  # a power of two: OpenCV's fast area path


@dataclass
class Blob:
    x: float
    y: float
    radius: float          # px, from the second moment of the chord profile
    sigma: float           # px, 1-sigma centre uncertainty (isotropic average)
    mu_px: float           # attenuation per px of chord (material contrast)
    peak: float            # peak attenuation above background
    anisotropy: float
    flags: list
    snr: float
    profile_misfit: float = 0.0   # |b - best chord profile| / |b| in the window
    pair: bool = False            # sigma covers a second sphere nearly on top (an unsplit or hidden pair)
    # the background under it (attenuation) and its slope (attenuation/px), from conecal.detect.gain
    bg: float | None = None
    bg_gx: float | None = None
    bg_gy: float | None = None
