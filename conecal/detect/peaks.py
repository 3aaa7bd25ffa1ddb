"""Where to look in a frame: its downsampled copy, the pixels that are no
measurement, and the candidate peaks (sphere-like, or short ridges that may
be merged shadows) that :func:`conecal.detect.frame.detect_blobs` measures.
Units: px, attenuation.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..stats import spread_sigma
from .noise import noise_small

# (``opt`` below is a :class:`conecal.detect.frame.DetectOptions`, not imported:
# frame imports this module)


def candidates(a: np.ndarray, opt, invalid: np.ndarray | None = None,
               small: np.ndarray | None = None, with_ridges: bool = False):
    """Candidates (x, y, height/noise) in full-resolution px, strongest first,
    and the pixel noise sigma of the (downsampled) frame; with ``with_ridges``
    also the peaks that curve down in every direction but too little along
    one to be a single sphere (merged shadows, rods)."""
    f = opt.factor
    rows, cols = a.shape
    if invalid is not None:
        # dead regions become plain background, so their borders raise no peaks
        a = np.where(invalid, np.float32(np.median(a[~invalid]) if (~invalid).any() else 0.0), a)
    if small is None:
        small = small_frame(a, opt)
    kd = int(np.ceil(opt.diameter_px[1] * 1.5 / f)) | 1
    # a square element is separable (fast) and removes any blob it covers
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (kd, kd))
    top = cv2.morphologyEx(small, cv2.MORPH_TOPHAT, kernel, borderType=cv2.BORDER_REPLICATE)
    s = max(opt.diameter_px[0] / f / 4.0, 0.7)
    sm = cv2.GaussianBlur(top, (0, 0), s)
    # the top-hat rectifies noise (the opening follows its minima), so the
    # threshold is taken against the smoothed top-hat's own robust spread
    # (on a JPEG's flat blocks, of the steps between them)
    sub = sm[::6, ::6]
    base = float(np.median(sub))
    noise = spread_sigma(sub) + 1e-7
    sm = sm - base
    k = max(int(opt.diameter_px[0] / f * 0.6), 1) * 2 + 1
    mx = cv2.dilate(sm, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    peaks = (sm >= mx) & (sm > opt.threshold * noise)
    peaks[0, :] = peaks[-1, :] = peaks[:, 0] = peaks[:, -1] = False
    ys, xs = np.nonzero(peaks)
    # a blob curves down in every direction, a ridge (rod, wall edge) along one only
    hxx = sm[ys, xs - 1] + sm[ys, xs + 1] - 2 * sm[ys, xs]
    hyy = sm[ys - 1, xs] + sm[ys + 1, xs] - 2 * sm[ys, xs]
    hxy = (sm[ys + 1, xs + 1] + sm[ys - 1, xs - 1] - sm[ys + 1, xs - 1] - sm[ys - 1, xs + 1]) / 4
    tr, det = hxx + hyy, hxx * hyy - hxy**2
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l_small, l_big = tr / 2 + disc, tr / 2 - disc   # both negative at a blob peak
    blobby = (l_big < 0) & (l_small < 0.25 * l_big)
    # a short ridge is what two merged shadows look like: kept apart, to be split or dropped
    elongated = (l_big < 0) & (l_small < 0) & ~blobby
    h = sm[ys, xs] / noise
    out, ridges = [], []
    for i in np.argsort(-h, kind="stable"):
        if blobby[i] or elongated[i]:
            (out if blobby[i] else ridges).append(((xs[i] + 0.5) * f - 0.5, (ys[i] + 0.5) * f - 0.5, float(h[i])))
    if with_ridges:
        return out, float(noise_small(small)), ridges
    return out, float(noise_small(small))


def small_frame(a: np.ndarray, opt) -> np.ndarray:
    """Frame ``a`` downsampled by ``opt.factor`` (area mean), where candidates are sought."""
    rows, cols = a.shape
    f = opt.factor
    return cv2.resize(a, (cols // f, rows // f), interpolation=cv2.INTER_AREA) if f > 1 else a


def invalid_mask(a: np.ndarray, opt) -> np.ndarray:
    """Pixels of frame ``a`` that are no measurement, widened by 2 px: the
    regions above ``opt.max_attenuation`` larger than twice the largest
    expected shadow (outside a circular field, dead columns) and dead pixels
    (over 2.0 above their 3 x 3 median). A shadow-sized region that dark is a
    sphere's core (a dense ball, or a display image windowed to black): it
    was masked, and the sphere lost or flagged truncated."""
    over = (a > opt.max_attenuation).astype(np.uint8)
    _, lab, stats, _ = cv2.connectedComponentsWithStats(over, connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] > 2 * np.pi * (opt.diameter_px[1] / 2) ** 2
    big[0] = False   # (the background label)
    # a dead pixel stands far above its neighbours; a dark core's pixels (an
    # 8-bit display's few grey levels there) only just cross the level
    dead = over.astype(bool) & (a - cv2.medianBlur(a, 3) > 2.0)
    return cv2.dilate((big[lab] | dead).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
