"""One frame's sphere shadows, each measured alone: every candidate peak
refined (:func:`conecal.detect.frame.refine`), touching windows flagged
``overlap``, elongated blobs handed on as merged shadows, misshapen ones
beside an edge as spoilt, and the candidate peaks strong enough to be a
sphere's. :func:`conecal.detect.crowded.detect_frame` goes on to measure
touching shadows together. Units: px, attenuation.
"""

from __future__ import annotations

import numpy as np

from .chain import chain_like, rough_blob
from .frame import ROUND_ANISOTROPY, Blob, DetectOptions, NonFiniteFrame, chord_like, refine, window_reach
from .noise import noise_pixel
from .peaks import candidates, invalid_mask, small_frame


def _rough_blob(a: np.ndarray, cx: float, cy: float, r: float, blur: float, noise: float, opt: DetectOptions):
    """A strong peak no window measured, as a rough blob when it may be a chain (:mod:`.chain`), else None."""
    f = rough_blob(a, cx, cy, r, blur, noise)
    ok = f is not None and chain_like(f["radius"], f["anisotropy"], opt.diameter_px[1], opt.max_anisotropy)
    return Blob(**f) if ok else None


# a sphere's candidate peak: on a real C-arm recording lone spheres read 51-61
# (noise sigmas), the noise on an intensifier's dark blot 10-27; a sphere
# overlapped by another reads more than alone
_SEED_STRENGTH = 0.5


def detect_blobs(a: np.ndarray, opt: DetectOptions):
    """Sphere-like shadows in attenuation frame ``a``, each measured alone
    (not yet filtered by contrast): (kept blobs, blobs rejected as elongated
    that may be merged shadows, clutter-flagged blobs rejected as misshapen
    that may be spheres beside an edge, the frame's noise sigma, the
    invalid-pixel mask or None, every candidate peak (x, y), and the peaks
    strong enough to be a sphere's: at least ``_SEED_STRENGTH`` of the
    median peak of the shadows measured alone unflagged). :func:`conecal.detect.crowded.detect_frame` goes on to
    measure touching shadows together.

    Raises :class:`NonFiniteFrame` if ``a`` holds NaN or inf pixels.
    """
    rows, cols = a.shape
    small = small_frame(a, opt)
    smax = float(small.max())
    if not np.isfinite(smax) or not np.isfinite(small.min()):
        raise NonFiniteFrame()
    invalid = None
    if opt.max_attenuation is not None and smax > opt.max_attenuation:
        invalid = invalid_mask(a, opt)
    cands, noise, ridges = candidates(a, opt, invalid, small if invalid is None else None, with_ridges=True)
    if not opt.joint_overlaps:
        ridges = []
    noise *= opt.factor  # the downsampled frame averages factor**2 pixels
    # the clutter test compares a background fit's scatter with the pixel noise
    # at the fit's own scale (correlated noise included)
    pixel = opt.pixel_noise
    if opt.noise_reference and noise > 1.3 * opt.noise_reference:
        # noisier than the frame the scan's noise was measured on (a frame of
        # another dose or gain): every shadow there read as clutter
        pixel = noise_pixel(a, limit=opt.max_attenuation)
    noise = max(noise, pixel)
    r_guess = opt.diameter_px[0] / 2 if opt.diameter_px[1] / opt.diameter_px[0] < 1.6 else np.mean(opt.diameter_px) / 2
    blobs: list[Blob] = []
    rough = [(cx, cy, opt.diameter_px[0] / 2) for cx, cy, _ in cands]
    strength = [h for _, _, h in cands]
    failed = []
    for i, (cx, cy, h) in enumerate(cands):
        # a candidate inside an accepted blob is the same sphere
        if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in blobs):
            continue
        # neighbours of comparable strength are likely markers: keep them out of
        # this one's background; faint ones are part of the background
        others = [o for j, o in enumerate(rough) if j != i and strength[j] >= 0.3 * h
                  and (o[0] - cx) ** 2 + (o[1] - cy) ** 2 < (4 * opt.diameter_px[1]) ** 2]
        others = [o for o in others if not any((o[0] - b.x) ** 2 + (o[1] - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in blobs)] + \
                 [(b.x, b.y, b.radius) for b in blobs]
        b = refine(a, cx, cy, r_guess, opt, others, noise, invalid, first=True)
        if b is None:
            b = refine(a, cx, cy, r_guess, opt, others, noise, invalid, first=True, plane_test=True)
        if b is None and h > 3 * opt.threshold and 2 * r_guess <= opt.diameter_px[1]:
            # a strong peak with no shadow of the expected size: the background
            # ring may lie inside a larger shadow (a big ball whose core an
            # 8-bit display flattens); once more, twice as wide, kept when it
            # is that: larger and round (not a blob over a crowd)
            b = refine(a, cx, cy, 2 * r_guess, opt, others, noise, invalid)
            if b is not None and (b.radius < 1.3 * r_guess or b.anisotropy > ROUND_ANISOTROPY):
                b = None
        if b is None and h > 3 * opt.threshold:
            failed.append((cx, cy))   # a strong peak whose background could not be had
        if b is None or b.snr < opt.min_snr:
            continue
        if any((b.x - o.x) ** 2 + (b.y - o.y) ** 2 < (0.8 * o.radius) ** 2 for o in blobs):
            continue
        blobs.append(b)
    # overlap: centroid windows that meet
    for i, bi in enumerate(blobs):
        for bj in blobs[i + 1:]:
            reach = window_reach(bi.radius, bj.radius, opt.blur_px)
            if (bi.x - bj.x) ** 2 + (bi.y - bj.y) ** 2 < reach**2:
                for b in (bi, bj):
                    if "overlap" not in b.flags:
                        b.flags.append("overlap")
    kept, merged = [], []
    for cx, cy, h in ridges:
        if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < b.radius**2 for b in blobs + merged):
            continue
        b = refine(a, cx, cy, r_guess, opt, [(o.x, o.y, o.radius) for o in blobs], noise, invalid)
        if (b is None or not np.isfinite(b.anisotropy)) and h > 3 * opt.threshold:
            # a chain of touching shadows across a wall seen end-on: no background
            # ring to be had for one sphere's window (or one whose second moments
            # come out negative: no shape); its extent, to be split
            b = _rough_blob(a, cx, cy, r_guess, opt.blur_px, noise, opt)
        # (clutter allowed: the neighbours that make a cluster disturb its background)
        if b is not None and b.snr >= opt.min_snr and b.anisotropy < 3.0 and "truncated" not in b.flags:
            merged.append(b)   # never a marker by itself: split into spheres or dropped
    spoilt = []
    for b in blobs:
        if b.anisotropy > opt.max_anisotropy and not set(b.flags) & {"truncated", "clutter"}:
            if b.anisotropy < 3.0:
                merged.append(b)   # perhaps two or three shadows merged into one blob
            continue  # rods, edges
        if b.anisotropy > 2.0 or ("clutter" in b.flags and not chord_like(b)):
            # not a sphere shadow even allowing for what lies across it (a dense
            # irregular blob, bone, debris) -- or a sphere beside a plate's edge
            # that spoilt its window: detect.crowded tries it with a step removed
            if "clutter" in b.flags and "truncated" not in b.flags:
                spoilt.append(b)
            continue
        kept.append(b)
    # a strong peak with no background to be had (a plate's edge across its
    # annulus): handed on as a spoilt blob of the expected size, unmeasured
    for cx, cy in failed:
        if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < b.radius**2 for b in blobs):
            continue
        # (one that is elongated is a chain, to be split like a merged blob)
        rough = _rough_blob(a, cx, cy, r_guess, opt.blur_px, noise, opt)
        if rough is not None:
            merged.append(rough)
            continue
        ix, iy = int(round(cx)), int(round(cy))
        ring = a[max(iy - int(2 * r_guess), 0):iy + int(2 * r_guess) + 1, max(ix - int(2 * r_guess), 0):ix + int(2 * r_guess) + 1]
        peak = float(a[iy, ix] - np.median(ring))
        if peak > 0:
            spoilt.append(Blob(cx, cy, r_guess, np.inf, peak / (2 * r_guess), peak, 1.0, ["clutter"], 0.0))
    # a candidate peak as strong as half the frame's weaker lone spheres' (their
    # lower quartile: a coded helix's 1.6 mm beads read 14-19, its 3.2 mm ones
    # 45-53) may be one; weaker ones (noise on a broad blot, JPEG texture) are
    # no sphere to look for
    alone = [h for cx, cy, h in cands if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < (0.8 * b.radius) ** 2
                                             for b in kept if not b.flags and not b.faint)]
    floor = _SEED_STRENGTH * float(np.quantile(alone, 0.25)) if alone else 0.0
    return kept, merged, spoilt, noise, invalid, [(cx, cy) for cx, cy, _ in cands], \
        [(cx, cy) for cx, cy, h in cands if h >= floor]
