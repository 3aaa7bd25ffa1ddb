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


def noise_small(img: np.ndarray) -> float:
    """Robust per-pixel noise sigma of an image (from neighbour differences)."""
    # (an 8-bit JPEG's flat blocks difference to 0: their steps count)
    return spread_sigma(img[::4, 1::4] - img[::4, :-1:4]) / np.sqrt(2.0) + 1e-7


def _block_ratio(d: np.ndarray, block: int, size: int) -> tuple[float, int]:
    """block**2 var(second differences of neighbouring block means of d) /
    var(d) over blocks free of structure (robustly, by MADs), and how many
    differences that was. A shadow and the halo the high-pass leaves around
    it (``size`` px) are kept out; the second difference removes what smooth
    background (a holder's curvature) the high-pass leaves."""
    h, w = (d.shape[0] // block) * block, (d.shape[1] // block) * block
    d = d[:h, :w]
    sm = cv2.blur(d, (5, 5))
    busy = np.abs(sm - np.median(sm)) > 4 * spread_sigma(sm)
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
    a = np.ascontiguousarray(img, dtype=np.float32)
    if min(a.shape) > 512:          # the centre is enough, and keeps it fast
        r0, c0 = (a.shape[0] - 512) // 2, (a.shape[1] - 512) // 2
        a = a[r0:r0 + 512, c0:c0 + 512]
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
