"""A strong peak that no sphere's window could measure, as a rough blob.

Three or four spheres touching in a line on a holder's wall seen end-on
make one peak whose window holds no background: the wall's band runs
through it, the background ring fitted across the band lies above the
chain's ends and the window's second moment comes out negative. What stands
above half the peak's height over the median of a ring 2.5-3 radii out is
the chain's extent, which :mod:`conecal.detect.split` fits sphere by sphere.
Units: px, attenuation.
"""

from __future__ import annotations

import cv2
import numpy as np


def rough_blob(a: np.ndarray, cx: float, cy: float, r: float, blur: float, noise: float) -> dict | None:
    """A :class:`conecal.detect.frame.Blob`'s fields (clutter-flagged, sigma
    inf) for the connected region about (cx, cy) above half the peak's
    height, or None.
    The radius is in :func:`conecal.detect.frame.refine`'s convention (a
    chord profile's second moment is 2/5 R^2, blur and pixel added), taking
    the region's moment as 2/3 of the whole shadow's; V likewise as 2/3 of
    its attenuation (the region holds a chord profile's first 2/3 of radius)."""
    rows, cols = a.shape
    L = int(4 * r)
    ix, iy = int(round(cx)), int(round(cy))
    c0, c1, q0, q1 = max(ix - L, 0), min(ix + L + 1, cols), max(iy - L, 0), min(iy + L + 1, rows)
    p = a[q0:q1, c0:c1].astype(np.float64)
    yy, xx = np.mgrid[q0:q1, c0:c1]
    d = np.hypot(xx - cx, yy - cy)
    ring = (d >= 2.5 * r) & (d <= 3 * r)
    if ring.sum() < 10 or not (c0 <= ix < c1 and q0 <= iy < q1):
        return None
    p = p - np.median(p[ring])
    top = float(p[iy - q0, ix - c0])
    if top <= 0:
        return None
    _, lab = cv2.connectedComponents((p > top / 2).astype(np.uint8))
    w = np.where(lab == lab[iy - q0, ix - c0], p, 0.0)
    V = float(w.sum())
    x, y, cov = weighted_moments(w, xx, yy)
    m2 = 1.5 * (cov[0, 0] + cov[1, 1]) - 2 * blur**2 - 2 / 12
    aniso = anisotropy(cov[0, 0], cov[1, 1], cov[0, 1])
    if m2 <= 0 or not np.isfinite(aniso):
        return None
    R = float(np.sqrt(2.5 * m2))
    return dict(x=x, y=y, radius=R, sigma=float("inf"), mu_px=1.5 * 1.5 * V / (np.pi * R * R) / (2 * R), peak=top,
                anisotropy=aniso, flags=["clutter"], snr=top / max(noise, 1e-12))


def anisotropy(Mxx: float, Myy: float, Mxy: float) -> float:
    """The square root of the ratio of the principal second moments of a
    2x2 moment matrix (px^2); inf when the smaller is not positive."""
    tr, det = Mxx + Myy, Mxx * Myy - Mxy**2
    disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 + disc, tr / 2 - disc
    return float(np.sqrt(l1 / l2)) if l2 > 0 else np.inf


def weighted_moments(w: np.ndarray, xx: np.ndarray, yy: np.ndarray):
    """Centroid (x, y px) and 2x2 second-moment matrix (px^2) of weights
    ``w`` >= 0 (positive sum) on pixel coordinates ``xx``, ``yy``."""
    W = float(w.sum())
    x, y = float((w * xx).sum() / W), float((w * yy).sum() / W)
    dx, dy = xx - x, yy - y
    cov = np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]) / W
    return x, y, cov


def chain_like(radius: float, anisotropy: float, widest: float, max_anisotropy: float, blur: float = 0.0) -> bool:
    """Whether a rough blob (:func:`rough_blob`'s radius px and anisotropy)
    may be a chain of touching shadows: a short one elongated beyond a
    sphere (``max_anisotropy``; three in a line read up to 3.8) and no
    wider than ``widest`` px, two of the largest spheres' radii (a wall or
    a plate's end is wider); or a longer one (a grid's row of seven seen
    edge-on read 4.5-7) across which it is no wider than one of the largest
    spheres (its minor axis's radius, in :func:`rough_blob`'s convention,
    at most ``widest`` / 2; blur ``blur`` px). A wire's length passes too:
    the split's parts are tested for being a rod's."""
    if radius <= widest and max_anisotropy < anisotropy < 4.5:
        return True
    if not 4.5 <= anisotropy <= _LONGEST or not np.isfinite(radius):
        return False
    # radius^2 = 2.5 (1.5 (M1 + M2) - 2 blur^2 - 2/12), per axis the same with one moment
    both = (radius**2 / 2.5 + 2 * blur**2 + 2 / 12) / 1.5
    minor = 5 * (1.5 * both / (1 + anisotropy**2) - blur**2 - 1 / 12)
    return bool(0 < minor <= (widest / 2) ** 2)


# the longest chain a rough blob is taken for (a row of ten spheres a third
# overlapping reads about 9)
_LONGEST = 10.0
