"""A shadow's contrast that depends on the background under it, and the
centroid error a slope of that background then causes.

A sphere's attenuation adds to the background's only where the values are
true transmission. In an image intensifier's display image stored as
transmission (a log window of I: conecal's attenuation is then
-ln(a + b ln I)), under veiling glare (an offset on I) or a polychromatic
beam (hardened behind thicker material), the same sphere's shadow is deeper
or shallower where the background attenuation is higher. Its gain then
varies across a shadow lying on a background slope ``g`` (attenuation/px),
as exp(eta g . (x - c)), and the attenuation centroid moves uphill by
eta M2 g, M2 the shadow's second moment per axis (px^2; 0.2 R^2 + blur^2 +
1/12 for a chord profile): 0.02-0.1 px on an intensifier's display image,
beside noise sigmas of 0.02-0.03 px.

Where eta is positive beyond doubt the image is first linearised
(:func:`response_lambda`): y = (1 - exp(-lambda a)) / lambda, the lambda
that leaves the central chord independent of the background level. On a
log display stored as transmission (T = 1 - k A, A the line integral)
lambda = 1 makes y = k A exactly; an independent renderer's intensifier
log display reads 0.80-0.95 (its glare and vignetting). Joint fits of overlapping shadows then add
spheres where their attenuations add. A real intensifier recording reads
eta 0.03 +- 0.02 and stays in attenuation.

``eta`` = d ln(contrast) / d(background attenuation) is measured per scan
from the markers measured alone, the contrast being the central chord
(mu_px R: free of the magnification, which across a tilted plate changes
with the background too), relative to their frame's spheres of the same
size (a display window changes from frame to frame). The shift is not
corrected: a slope fitted across a plate's edge or a hole is no gain's
gradient, and a correction moved centres there by 0.5 px and more. Each
sigma takes it, (|eta| + se) M2 |g|, as an uncertainty; eta from the
contrast is the deep core's, which a display's curve bends more than the
rim the centroid weighs, so the term is an upper bound (up to 2x).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..stats import mad_sigma
from .frame import window_radius
from .options import Blob, DetectOptions
from .ring import keep_out, ring_mask

MIN_ALONE = 30     # markers measured alone a scan needs before eta is trusted


@dataclass(frozen=True)
class Gain:
    """The scan's eta (1/attenuation), its standard error, the number of
    markers it came from, and whether it is 3 standard errors from 0."""
    eta: float = 0.0
    se: float = 0.0
    n: int = 0
    significant: bool = False

    def document(self) -> dict:
        return {"eta": round(self.eta, 4), "se": round(self.se, 4), "markers": self.n, "significant": self.significant,
                "meaning": "d ln(contrast) / d(background attenuation); each sigma includes (|eta| + se) * M2 * "
                           "|background slope|, M2 = 0.2 R^2 + blur^2 + 1/12 px^2"}


def with_background(a: np.ndarray, blobs: list[Blob], opt: DetectOptions) -> list[Blob]:
    """``blobs`` with the background level (attenuation) and slope
    (attenuation/px, along x and y) of a plane fitted to the ring just
    outside each one's window, other blobs' shadows and invalid pixels
    left out, two rounds of rejection at 3 sigma."""
    rows, cols = a.shape
    out = []
    for b in blobs:
        if not _finite(b.x, b.y, b.radius):
            out.append(b)
            continue
        r_in = window_radius(b.radius, opt.blur_px) + 1.0
        r_out = r_in + max(4.0, 0.4 * b.radius)
        c0, c1 = max(int(np.floor(b.x - r_out)), 0), min(int(np.ceil(b.x + r_out)) + 1, cols)
        q0, q1 = max(int(np.floor(b.y - r_out)), 0), min(int(np.ceil(b.y + r_out)) + 1, rows)
        roi = a[q0:q1, c0:c1].astype(np.float64)
        bad = ~np.isfinite(roi) if opt.max_attenuation is None else ~(roi <= opt.max_attenuation)
        others = keep_out([(o.x, o.y, o.radius) for o in blobs if o is not b and _finite(o.x, o.y, o.radius)],
                          c0, q0, opt.blur_px)
        use = ring_mask(roi.shape, b.x - c0, b.y - q0, r_in, r_out, others, bad)
        yy, xx = np.mgrid[q0:q1, c0:c1]
        dx, dy = xx - b.x, yy - b.y
        coef = None
        for _ in range(3):
            if use.sum() < 12:
                coef = None
                break
            A = np.stack([np.ones(use.sum()), dx[use], dy[use]], axis=1)
            coef = np.linalg.lstsq(A, roi[use], rcond=None)[0]
            res = roi - (coef[0] + coef[1] * dx + coef[2] * dy)
            use &= np.abs(res) <= 3 * mad_sigma(res[use]) + 1e-12
        out.append(b if coef is None else replace(b, bg=float(coef[0]), bg_gx=float(coef[1]), bg_gy=float(coef[2])))
    return out


def _finite(*v) -> bool:
    """All of ``v`` are numbers and finite (a part document read back holds null for NaN)."""
    return all(u is not None and np.isfinite(u) for u in v)


def _alone(b: Blob) -> bool:
    return set(b.flags) <= {"clutter"} and not b.pair and _finite(b.sigma, b.bg, b.bg_gx, b.bg_gy) \
        and b.mu_px > 0 and b.radius > 0


def _sizes(blobs: list[Blob]) -> list[list[Blob]]:
    """``blobs`` (sorted by radius) in groups of one sphere size: a new
    group where the radius jumps by over 25 % (a phantom's 2 and 1.2 mm
    balls; a central chord is the diameter's, so sizes are not compared)."""
    groups: list[list[Blob]] = []
    for b in blobs:
        if groups and b.radius <= 1.25 * groups[-1][-1].radius:
            groups[-1].append(b)
        else:
            groups.append([b])
    return groups


def _curve(a, lam: float):
    """(1 - exp(-lam a)) / lam in float64, for lam > 0."""
    return -np.expm1(-lam * np.asarray(a, np.float64)) / lam


def linearised(a: np.ndarray, lam: float) -> np.ndarray:
    """Attenuation ``a`` through the response (1 - exp(-lam a)) / lam: an
    image as float32, a number as float; ``a`` itself at lam = 0."""
    if not lam:
        return a
    y = _curve(a, lam)
    return float(y) if np.ndim(a) == 0 else y.astype(np.float32)


def _chords(grp: list[Blob], lam: float) -> np.ndarray:
    """(n, 2): background level and ln central chord (2 mu_px R above it) of
    ``grp`` as they read after :func:`linearised` at ``lam``."""
    bg = np.array([b.bg for b in grp])
    c = np.array([2 * b.mu_px * b.radius for b in grp])
    if not lam:
        return np.column_stack([bg, np.log(c)])
    return np.column_stack([_curve(bg, lam), np.log(_curve(bg + c, lam) - _curve(bg, lam))])


def measure_gain(results: list[list[Blob]], lam: float = 0.0) -> Gain:
    """eta from every frame's markers measured alone: ln of the central chord
    (mu_px R) regressed on the background level, both taken relative to
    their group's means (a frame's spheres of one size, groups of 3 or
    more), three rounds of rejection at 3 robust sigmas; 0 below
    ``MIN_ALONE`` markers. ``significant``: 3 standard errors from 0.
    ``lam``: both as they would read after :func:`linearised` at lam."""
    X, y = [], []
    for res in results:
        for grp in _sizes(sorted((b for b in res if _alone(b)), key=lambda b: b.radius)):
            if len(grp) >= 3:
                m = _chords(grp, lam)
                m -= m.mean(axis=0)
                X.append(m[:, 0])
                y.append(m[:, 1])
    if not X:
        return Gain()
    X, y = np.concatenate(X), np.concatenate(y)
    keep = np.ones(len(y), bool)
    eta = 0.0
    for _ in range(3):
        if keep.sum() < MIN_ALONE or float(X[keep] @ X[keep]) <= 0:
            return Gain(n=int(keep.sum()))
        eta = float(X[keep] @ y[keep] / (X[keep] @ X[keep]))
        r = y - eta * X
        keep = np.abs(r) <= 3 * mad_sigma(r[keep]) + 1e-12
    r = (y - eta * X)[keep]
    se = float(np.sqrt(float(r @ r) / max(keep.sum() - 1, 1) / float(X[keep] @ X[keep])))
    return Gain(eta, se, int(keep.sum()), abs(eta) > 3 * se)


_LAMBDA_MAX = 2.0


def response_lambda(results: list[list[Blob]]) -> float:
    """The response's lambda (1/attenuation) from the markers measured alone
    in ``results`` (blobs with their background, :func:`with_background`):
    the lambda at which eta is 0 (bisection; eta falls as lambda grows)
    when eta is positive and significant and such a lambda lies within
    ``_LAMBDA_MAX``; else 0. (A negative eta, a polychromatic beam hardened
    behind thicker material, is no display's curve, nor is a gain this
    family cannot take away -- an 8-bit JPEG cage on a log display read
    eta 19 +- 5 from a background that hardly varied, and 17 at lambda 2:
    measured through lambda 2 its noise read 1e-7 and 400 false shadows
    came in. Either stays a sigma term.)"""
    g = measure_gain(results)
    if g.n < MIN_ALONE or not g.significant or g.eta <= 0:
        return 0.0
    lo, hi = 0.0, _LAMBDA_MAX
    if measure_gain(results, hi).eta > 0:
        return 0.0
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if measure_gain(results, mid).eta > 0 else (lo, mid)
    return round(0.5 * (lo + hi), 3)


def with_gain_sigma(results: list[list[Blob]], opt: DetectOptions) -> tuple[list[list[Blob]], Gain]:
    """Every frame's blobs with sigma grown by the centroid shift the scan's
    gain may cause on their background's slope, (|eta| + se) M2 |g| (see the
    module); unchanged below ``MIN_ALONE`` markers."""
    gain = measure_gain(results)
    if gain.n < MIN_ALONE:
        return results, gain
    k = abs(gain.eta) + gain.se
    out = []
    for res in results:
        new = []
        for b in res:
            if not _finite(b.sigma, b.bg_gx, b.bg_gy):
                new.append(b)
                continue
            m2 = 0.2 * b.radius**2 + opt.blur_px**2 + 1 / 12
            u2 = (k * m2) ** 2 * (b.bg_gx**2 + b.bg_gy**2) / 2
            new.append(replace(b, sigma=float(np.sqrt(b.sigma**2 + u2))))
        out.append(new)
    return out, gain
