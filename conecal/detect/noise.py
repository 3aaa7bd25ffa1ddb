"""The pixel noise of an attenuation frame, as detect's tests and sigmas need it.

Three estimates: the white part from neighbour differences
(:func:`noise_small`), the per-pixel scatter with its correlated part
(:func:`noise_pixel`: JPEG, 8-bit, a scintillator's spread) and the
correlation factor kappa a centroid's variance is multiplied by
(:func:`noise_correlation`); and how the noise grows with the background's
level (:func:`noise_slope`, applied by :func:`noise_at`). Units:
attenuation. Pixels at or above
``limit`` (``DetectOptions.max_attenuation``: outside an intensifier's
circular field, dead) are no measurement and are left out: their constant
value read as a fifth of the frame without noise, and an intensifier's
noise came out at 0.6 of what its shadows' rings showed, so that most of
its markers were flagged clutter.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from ..stats import spread_sigma


def _usable(img: np.ndarray, limit: float | None, grow: int = 1, invalid: np.ndarray | None = None) -> np.ndarray | None:
    """Pixels of ``img`` whose ``grow`` x ``grow`` neighbourhood is a
    measurement: finite, under ``limit`` and not ``invalid``; None when every
    pixel is (or no ``limit`` and no ``invalid`` were given)."""
    if limit is None and invalid is None:
        return None
    bad = ~np.isfinite(img)
    if limit is not None:
        bad |= img >= limit
    if invalid is not None:
        bad |= invalid
    if not bad.any():
        return None
    if grow > 1:
        bad = cv2.dilate(bad.astype(np.uint8), np.ones((grow, grow), np.uint8)) > 0
    return ~bad


def noise_small(img: np.ndarray, limit: float | None = None, invalid: np.ndarray | None = None) -> float:
    """Robust per-pixel noise sigma of an image (from neighbour differences),
    of the pixels under ``limit`` and not ``invalid`` (a mask of ``img``'s shape)."""
    # (an 8-bit JPEG's flat blocks difference to 0: their steps count)
    d = img[::4, 1::4] - img[::4, :-1:4]
    ok = _usable(img, limit, invalid=invalid)
    if ok is not None:
        d = d[ok[::4, 1::4] & ok[::4, :-1:4]]
    return spread_sigma(d) / np.sqrt(2.0) + 1e-7


def _block_ratio(d: np.ndarray, block: int, size: int, usable: np.ndarray | None = None) -> tuple[float, int]:
    """block**2 var(second differences of neighbouring block means of d) /
    var(d) over blocks free of structure (robustly, by MADs), and how many
    differences that was. A shadow and the halo the high-pass leaves around
    it (``size`` px) are kept out; the second difference removes what smooth
    background (a holder's curvature) the high-pass leaves."""
    h, w = (d.shape[0] // block) * block, (d.shape[1] // block) * block
    d = d[:h, :w]
    sm = cv2.blur(d, (5, 5))
    busy = np.abs(sm - np.median(sm)) > 4 * spread_sigma(sm)
    if usable is not None:
        busy |= ~usable[:h, :w]
    busy = cv2.dilate(busy.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
    blocks = d.reshape(h // block, block, w // block, block)
    ok = ~busy.reshape(h // block, block, w // block, block).any(axis=(1, 3))
    m = blocks.mean(axis=(1, 3))
    dd = []
    for M, K in ((m, ok), (m.T, ok.T)):
        D = M[:, 1:-1] - 0.5 * (M[:, :-2] + M[:, 2:])
        use = K[:, 1:-1] & K[:, :-2] & K[:, 2:]
        dd.append(D[use])
    dd = np.concatenate(dd)
    if len(dd) < 50:
        return 1.0, len(dd)
    pix = blocks.transpose(0, 2, 1, 3)[ok].ravel()
    return float(spread_sigma(dd) ** 2 * block**2 / (spread_sigma(pix) ** 2 + 1e-30)), len(dd)


@functools.lru_cache(maxsize=8)
def _white_ratio(shape: tuple[int, int], block: int, size: int) -> float:
    """``_block_ratio`` of white noise through the same high-pass (its bias)."""
    w = np.random.default_rng(0).normal(0, 1, shape).astype(np.float32)
    return _block_ratio(w - cv2.blur(w, (size, size), borderType=cv2.BORDER_REPLICATE), block, size)[0]


def noise_correlation(img: np.ndarray, blocks: tuple[int, ...] = (6, 10, 12), size: int = 31,
                      limit: float | None = None) -> float:
    """How much more a sum over a patch scatters than independent pixels would:
    kappa = sum of the noise's autocorrelation coefficients over all lags
    (1 for white noise; ~4 pi s^2 for noise blurred by a Gaussian of s px, as
    a scintillator does). Measured from the variance of block means of the
    high-passed image (their second differences, so a holder's curvature does
    not count) against its per-pixel variance, on blocks away from any
    structure, divided by the same statistic of white noise through the same
    filter, averaged over block sizes that are not multiples of JPEG's 8 px.
    A centroid's variance is kappa times the white-noise formula when its
    weights vary slowly over the correlation length. Never
    below 1: anti-correlated noise (JPEG's block quantisation) does not make a
    centroid better than white noise would, and 1 is returned when fewer than
    50 blocks are free of structure."""
    a = np.ascontiguousarray(img, dtype=np.float32)
    if min(a.shape) > 512:          # the centre is enough, and keeps it fast
        r0, c0 = (a.shape[0] - 512) // 2, (a.shape[1] - 512) // 2
        a = a[r0:r0 + 512, c0:c0 + 512]
    ok = _usable(a, limit)
    if ok is not None:
        # (the blur below must not spread what is no measurement)
        a = np.where(ok, a, np.float32(np.median(a[ok]) if ok.any() else 0.0))
    if not np.isfinite(a).all():
        return 1.0
    hp = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
    ratios = []
    for b in blocks:
        k, n = _block_ratio(hp, b, size, ok)
        if n < 50:
            return 1.0
        ratios.append(k / _white_ratio(a.shape, b, size))
    return float(np.clip(np.mean(ratios), 1.0, 100.0))


def noise_pixel(img: np.ndarray, size: int = 7, limit: float | None = None) -> float:
    """Robust per-pixel noise sigma including noise correlated over a few
    pixels (JPEG, a scintillator's spread, 8-bit quantisation): the MAD of the
    image minus its ``size`` x ``size`` box mean. Neighbour differences see
    only the uncorrelated part, which on such images is half the scatter a
    background fit meets."""
    a = np.ascontiguousarray(img[::2, ::2] if min(img.shape) > 256 else img, dtype=np.float32)
    d = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
    ok = _usable(a, limit, size)
    return spread_sigma(d if ok is None else d[ok]) / np.sqrt(1 - 1 / size**2) + 1e-7


# the background levels spanned (attenuation, 1st to 99th percentile) below
# which a slope of the noise over level is not measured (0 is kept)
_LEVEL_SPAN = 0.15


def noise_slope(frames: list, limit: float | None = None, size: int = 7) -> tuple[float, float]:
    """How the pixel noise grows with the background's level: (beta, level)
    with sigma(L) = sigma(level) exp(beta (L - level)), beta = d ln sigma /
    dL per unit attenuation (0.5 for quantum noise on a linear detector;
    a display's curve changes it), ``level`` the first frame's median
    background level, where :func:`noise_pixel` of that frame applies.

    Measured on ``frames`` (attenuation, the middle frame first): each
    pixel's deviation from its ``size`` x ``size`` mean against the 15 x 15
    mean around it, away from structure and from what is no measurement
    (``limit``), in ten bins of equal width between the levels' 1st and 99th
    percentiles (200 pixels or more each); a weighted least-squares line
    through the bins' log sigmas. beta = 0 when the levels span less than
    ``_LEVEL_SPAN``; clipped to [-1, 2]."""
    L_all, r_all, level = [], [], 0.0
    for n, img in enumerate(frames):
        a = np.ascontiguousarray(img[::2, ::2] if min(img.shape) > 256 else img, dtype=np.float32)
        ok = _usable(a, limit, 15)
        if ok is not None:
            a = np.where(ok, a, np.float32(np.median(a[ok]) if ok.any() else 0.0))
        if not np.isfinite(a).all():
            continue
        r = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
        L = cv2.blur(a, (15, 15), borderType=cv2.BORDER_REPLICATE)
        # structure: a 5 x 5 mean of the deviations beyond 0.8 of their local
        # RMS (white noise's is a fifth of it; judged locally, or a phantom's
        # darker, noisier levels would all read as structure)
        sm = cv2.blur(r, (5, 5))
        rms = np.sqrt(np.maximum(cv2.blur(r * r, (15, 15), borderType=cv2.BORDER_REPLICATE), 0.0))
        busy = np.abs(sm) > 0.8 * rms
        use = ~(cv2.dilate(busy.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0)
        if ok is not None:
            use &= ok
        if not use.any():
            continue
        if n == 0:
            level = float(np.median(L[use]))
        L_all.append(L[use])
        r_all.append(r[use])
    if not L_all:
        return 0.0, level
    L, r = np.concatenate(L_all), np.concatenate(r_all)
    lo, hi = np.quantile(L, [0.01, 0.99])
    if hi - lo < _LEVEL_SPAN:
        return 0.0, level
    # (bins of equal width: a phantom's darker levels are a small share of the pixels)
    edges = np.linspace(lo, hi, 11)
    pts = []
    for i in range(10):
        s = (L >= edges[i]) & (L <= edges[i + 1])
        if s.sum() >= 200:
            pts.append((float(np.median(L[s])), np.log(spread_sigma(r[s]) + 1e-12), np.sqrt(s.sum())))
    pts = np.array(pts)
    if len(pts) < 3 or np.ptp(pts[:, 0]) < _LEVEL_SPAN:
        return 0.0, level
    # (each bin's log sigma weighted by its standard error's inverse, ~sqrt(count))
    beta = float(np.polyfit(pts[:, 0], pts[:, 1], 1, w=pts[:, 2])[0])
    return float(np.clip(beta, -1.0, 2.0)), level


def noise_factor(level, opt):
    """How many times the noise at the scan's reference level
    ``opt.noise_level`` the noise at background level ``level`` (attenuation;
    a number or an array) is, by the scan's measured slope
    ``opt.noise_slope``: at most 4.5x either way."""
    return np.exp(np.clip(opt.noise_slope * (np.asarray(level) - opt.noise_level), -1.5, 1.5))


def noise_at(noise: float, level: float, opt) -> float:
    """The frame's pixel noise ``noise`` (at the scan's reference level) at
    background level ``level`` (attenuation): :func:`noise_factor`."""
    return float(noise * noise_factor(level, opt))
