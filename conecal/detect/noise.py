"""The pixel noise of an attenuation frame, as detect's tests and sigmas need it.

Three estimates: the white part from neighbour differences
(:func:`noise_small`), the per-pixel scatter with its correlated part
(:func:`noise_pixel`: JPEG, 8-bit, a scintillator's spread) and the
correlation factor kappa a centroid's variance is multiplied by
(:func:`noise_correlation`). Units: attenuation.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from ..stats import spread_sigma
from .kernels import chord_patch


def noise_small(img: np.ndarray) -> float:
    """Robust per-pixel noise sigma of an image (from neighbour differences)."""
    # (an 8-bit JPEG's flat blocks difference to 0: their steps count)
    return spread_sigma(img[::4, 1::4] - img[::4, :-1:4]) / np.sqrt(2.0) + 1e-7


def _centre(img: np.ndarray) -> np.ndarray:
    """The frame as float32, its central 512 px square when larger (enough
    for the noise's statistics, and fast)."""
    a = np.ascontiguousarray(img, dtype=np.float32)
    if min(a.shape) > 512:
        r0, c0 = (a.shape[0] - 512) // 2, (a.shape[1] - 512) // 2
        a = a[r0:r0 + 512, c0:c0 + 512]
    return a


def _busy(d: np.ndarray, size: int) -> np.ndarray:
    """Where the high-passed frame ``d`` holds structure: its 5 px mean beyond
    4 robust sigmas of the median, and ``size`` px around that (a shadow and
    the halo the high-pass leaves around it)."""
    sm = cv2.blur(d, (5, 5))
    busy = np.abs(sm - np.median(sm)) > 4 * spread_sigma(sm)
    return cv2.dilate(busy.astype(np.uint8), np.ones((size, size), np.uint8)) > 0


def _block_ratio(d: np.ndarray, block: int, size: int) -> tuple[float, int]:
    """block**2 var(second differences of neighbouring block means of d) /
    var(d) over blocks free of structure (robustly, by MADs), and how many
    differences that was. A shadow and the halo the high-pass leaves around
    it (``size`` px) are kept out; the second difference removes what smooth
    background (a holder's curvature) the high-pass leaves."""
    h, w = (d.shape[0] // block) * block, (d.shape[1] // block) * block
    d = d[:h, :w]
    busy = _busy(d, size)
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


def noise_correlation(img: np.ndarray, blocks: tuple[int, ...] = (6, 10, 12), size: int = 31) -> float:
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
    a = _centre(img)
    if not np.isfinite(a).all():
        return 1.0
    hp = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
    ratios = []
    for b in blocks:
        k, n = _block_ratio(hp, b, size)
        if n < 50:
            return 1.0
        ratios.append(k / _white_ratio(a.shape, b, size))
    return float(np.clip(np.mean(ratios), 1.0, 100.0))


def noise_pixel(img: np.ndarray, size: int = 7, limit: float | None = None) -> float:
    """Robust per-pixel noise sigma including noise correlated over a few
    pixels (JPEG, a scintillator's spread, 8-bit quantisation): the MAD of the
    image minus its ``size`` x ``size`` box mean. Neighbour differences see
    only the uncorrelated part, which on such images is half the scatter a
    background fit meets.

    Pixels at or above ``limit`` (attenuation; ``DetectOptions.max_attenuation``:
    outside an intensifier's circular field, dead, burnt-in text), and those
    within ``size`` px of them, are no measurement and are left out: an
    uncropped intensifier frame is a third black, and counted, its noise read
    0.56 of the field's, so that 590 of 650 real markers were flagged clutter."""
    a = np.ascontiguousarray(img[::2, ::2] if min(img.shape) > 256 else img, dtype=np.float32)
    d = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
    if limit is not None:
        bad = ~(a < limit)   # (NaN counts as no measurement)
        if bad.any():
            ok = cv2.dilate(bad.astype(np.uint8), np.ones((size, size), np.uint8)) == 0
            # (a frame with almost nothing under the limit keeps every pixel)
            if ok.sum() >= 1000:
                d = d[ok]
    return spread_sigma(d.ravel()) / np.sqrt(1 - 1 / size**2) + 1e-7


# lags (px) over which the noise's autocorrelation is measured for a fit's weights
AUTOCORRELATION_LAGS = 16


def noise_autocorrelation(img: np.ndarray, lags: int = AUTOCORRELATION_LAGS, size: int = 61) -> tuple:
    """The noise's autocorrelation coefficients rho(dy, dx), |dx|, |dy| <=
    ``lags`` px, as a (2 lags + 1)-square tuple of tuples (centre = 1), on
    the frame's ``size`` px high-passed background away from any structure
    (31 px around what a 4-sigma test finds, as :func:`noise_correlation`
    keeps out); () when too little of the frame is free of structure (under
    a tenth) or it is not finite. (A 31 px high-pass puts negative lobes
    in rho at 8-12 px that read a small shadow's factor 10-30 % high on
    noise blurred by 2-3 px; at 61 px, 5-14 %.)"""
    a = _centre(img)
    if not np.isfinite(a).all() or min(a.shape) < 4 * lags:
        return ()
    hp = a - cv2.blur(a, (size, size), borderType=cv2.BORDER_REPLICATE)
    keep = (~_busy(hp, 31)).astype(np.float64)
    if keep.mean() < 0.1:
        return ()
    x = np.where(keep > 0, hp, 0.0).astype(np.float64)
    shape = (x.shape[0] + lags, x.shape[1] + lags)
    F, M = np.fft.rfft2(x, shape), np.fft.rfft2(keep, shape)
    num, den = np.fft.irfft2(F * np.conj(F), shape), np.fft.irfft2(M * np.conj(M), shape)
    idx = np.r_[0:lags + 1, -lags:0]
    C = num[np.ix_(idx, idx)] / np.maximum(den[np.ix_(idx, idx)], 1.0)
    if not C[0, 0] > 0:
        return ()
    rho = np.fft.fftshift(C / C[0, 0])
    return tuple(tuple(float(v) for v in row) for row in rho)


@functools.lru_cache(maxsize=4096)
def _weights_factor(rho: tuple, kind: str, radius: float, blur: float) -> float:
    """sum_d rho(d) A_w(d) / A_w(0) for the x weights ``w`` of a shadow of
    ``radius`` px: ``model``, a sphere fit's (d/dx of the disc's blurred chord
    profile), or ``centroid``, (x - c) over a window of that radius."""
    r = np.asarray(rho)
    L = r.shape[0] // 2
    n = 2 * int(np.ceil(radius + 3 * blur + L)) + 1
    c = n // 2 + 0.3     # (off the pixel grid, as a shadow's centre is)
    if kind == "model":
        J = chord_patch(np.array([[c, c, radius, 1.0]]), n, n, 3, True)[..., 0].astype(np.float64)
        w = cv2.GaussianBlur(J, (0, 0), blur) if blur > 0.05 else J
    else:
        yy, xx = np.mgrid[0:n, 0:n]
        w = np.where(np.hypot(xx - c, yy - c) <= radius, xx - c, 0.0)
    A = cv2.filter2D(w, -1, w[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)
    k = n // 2
    return float((r * A[k - L:k + L + 1, k - L:k + L + 1]).sum() / A[k, k])


def weights_kappa(kappa: float, rho: tuple, kind: str, radius: float, blur: float) -> float:
    """The factor a centre's white-noise variance is multiplied by, for its
    estimator's weights (``kind``: ``model`` fit of a shadow of ``radius``
    px, or ``centroid`` over a window of that radius): the frame's
    ``kappa`` (right for weights that vary slowly over the noise's
    correlation length), or less where the weights vary within it and
    ``rho`` (:func:`noise_autocorrelation`) says so; never below 1.

    A model fit's weights are two lobes at the shadow's rim, a centroid's
    change sign across it: noise correlated over more than a shadow's
    radius moves both less than kappa, measured on block means, says (an
    independent JPEG C-arm scan, kappa 24-28, spheres of 2-3 px radius:
    3.7-7.1 for a model fit). The factor is never above kappa: at wide
    weights the high-pass's negative lobes in rho read it high."""
    if not rho or not np.isfinite(radius) or radius <= 0:
        return kappa
    f = _weights_factor(rho, kind, round(float(radius) * 4) / 4, round(float(blur), 2))
    return float(min(kappa, max(1.0, f)))
