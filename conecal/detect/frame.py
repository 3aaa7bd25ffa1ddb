"""Sphere markers in one attenuation frame: candidates, sub-pixel centres, checks.

What is measured: the centroid of the background-corrected attenuation of
each sphere shadow (pixel coordinates, column ``x`` and row ``y``). Blur and
pixel integration are symmetric and leave it unbiased; the cone-beam offset
from the projected sphere centre is predicted by
:func:`conecal.geometry.shadow_centroid`, so fits model exactly this point.

Steps: (1) (:mod:`conecal.detect.peaks`) on a frame downsampled by a power of two, a white top-hat
removes the background and every structure wider than the largest marker
(plate edges, field-of-view borders); Gaussian smoothing matched to the
smallest marker and a maximum filter give candidate peaks above
``threshold`` robust sigmas, and a Hessian test drops ridges (rods, walls).
(2) Per candidate at full resolution: a size from the half-maximum area,
then a robust quadratic (or planar) background fitted on an annulus
(neighbours masked) and the centroid and second moment over an
anti-aliased window, iterated (numba kernels). (3) sigma propagates the
pixel noise, which grows with attenuation, and the background slope's
uncertainty; it grows, and the ``clutter`` flag is set, when the annulus
holds structure the background cannot follow, when the shadow's core and
whole window disagree, or when the shadow is not point-symmetric.
(4) Anisotropy, chord-profile misfit and SNR tests reject rods, merged
shadows and irregular blobs; ``truncated`` and ``overlap`` flags mark
shadows cut by the detector or field of view and shadows that touch. The
scan-level density test against the median marker (ghosts, faint spheres)
lives in :mod:`conecal.detect.pipeline`.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..stats import mad_sigma
from . import kernels
from .chain import anisotropy, chain_like, rough_blob
from .noise import noise_pixel
from .options import Blob, DetectOptions
from .peaks import candidates, invalid_mask, small_frame
from .ring import keep_out


def _rough_blob(a: np.ndarray, cx: float, cy: float, r: float, blur: float, noise: float, opt: DetectOptions):
    """A strong peak no window measured, as a rough blob when it may be a chain (:mod:`.chain`), else None."""
    f = rough_blob(a, cx, cy, r, blur, noise)
    ok = f is not None and chain_like(f["radius"], f["anisotropy"], opt.diameter_px[1], opt.max_anisotropy, blur)
    return Blob(**f) if ok else None


_EMPTY = np.zeros(0)
# A candidate that no shadow was found at is measured once more with its
# background's curvature fitted only where the ring shows it: its F ratio over
# a plane beyond this times the noise's correlation factor (a smooth pattern
# gathers kappa times a pixel's share of correlated noise; F(3, n) exceeds 4
# by chance 1 % of the time). On a noisy ring an unseen curvature moved the
# value extrapolated to the centre enough to lose faint spheres; as the first
# measurement it lost a helix's clusters (17 of 800 spheres), whose rings the
# neighbours really bend
_F_QUAD = 4.0
# a shadow's second-moment size below this share of its half-maximum size is
# the window's rim weighed negative, not the shadow's size
_MOAT_SHARE = 0.6
_NO_MASK = np.zeros((0, 0), np.bool_)


def moment_trace(radius: float, blur: float) -> float:
    """The trace (px^2) of a sphere shadow's second moments: a chord
    profile's 2/5 R^2, plus the blur's and the pixel's variances per axis
    (what :func:`refine` inverts for the radius)."""
    return radius**2 / 2.5 + 2 * blur**2 + 1 / 6


def refine(a: np.ndarray, x0: float, y0: float, r0: float, opt: DetectOptions, others=(), noise: float = 0.0,
           invalid: np.ndarray | None = None, first: bool = False, plane_test: bool = False) -> Blob | None:
    """Sub-pixel centroid of the sphere shadow near (x0, y0) with radius guess r0.

    ``others``: (x, y, r) of neighbouring candidates, kept out of the background
    annulus; ``noise``: the frame's pixel noise sigma (for the clutter test).
    ``first``: a candidate peak of the frame's first pass, which may be a lone
    shadow in a bright band (see below); ``plane_test``: its background's curvature kept
    only where the ring shows it (``_F_QUAD``). Returns None when no
    sphere-like shadow is there.
    """
    rows, cols = a.shape
    x, y, r = float(x0), float(y0), float(r0)

    def alone(x, y, reach):
        return all(np.hypot(o[0] - x, o[1] - y) > reach + o[2] for o in others)

    sized = False
    bounds = None
    fitted_at = None
    st = None
    for it in range(7):
        rw = window_radius(r, opt.blur_px)
        r_in = rw + 1.0
        # a neighbour's shadow inside the window pulls the centroid and swells
        # the size: the window (a disc about the centre, so a symmetric shadow's
        # centroid stays unbiased) stops short of it, and the size is kept
        capped = False
        for ox_, oy_, or_ in others:
            reach = np.hypot(ox_ - x, oy_ - y) - 1.15 * max(or_, r) - 2 * opt.blur_px - 1.0
            # shadows closer than that touch: measured together (detect.crowded)
            if r + 1.0 <= reach < rw:
                rw, capped = reach, True
        r_out = r_in + max(4.0, 0.4 * r)
        c0, c1 = int(np.floor(x - r_out)), int(np.ceil(x + r_out)) + 1
        q0, q1 = int(np.floor(y - r_out)), int(np.ceil(y + r_out)) + 1
        truncated = c0 < 0 or q0 < 0 or c1 > cols or q1 > rows
        c0, q0, c1, q1 = max(c0, 0), max(q0, 0), min(c1, cols), min(q1, rows)
        if c1 - c0 < 5 or q1 - q0 < 5:
            return None
        if (c0, q0, c1, q1) != bounds:
            bounds = (c0, q0, c1, q1)
            roi = a[q0:q1, c0:c1]
            inv = _NO_MASK
            if invalid is not None:
                inv = np.ascontiguousarray(invalid[q0:q1, c0:c1])
            elif opt.max_attenuation is not None:
                over = roi > opt.max_attenuation
                if over.any():  # hot or dead pixels inside this window
                    inv = cv2.dilate(over.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        cx, cy = x - c0, y - q0
        if (fitted_at is None or fitted_at[3] != bounds or abs(x - fitted_at[0]) > 0.5
                or abs(y - fitted_at[1]) > 0.5 or abs(r - fitted_at[2]) > 0.1 * fitted_at[2]):
            fitted_at = (x, y, r, bounds)
            ox = np.array([o[0] - c0 for o in others]) if others else _EMPTY
            oy = np.array([o[1] - q0 for o in others]) if others else _EMPTY
            orad = np.array([k[2] for k in keep_out(others, 0, 0, opt.blur_px)]) if others else _EMPTY
            coef, quad, sig_bg, n_in, s_ring, hidden = kernels.fit_background(
                roi, inv, cx, cy, r_in, r_out, rw, ox, oy, orad, 150,
                _F_QUAD * opt.noise_kappa if plane_test else 0.0)
            if hidden > 0.2 or n_in == 0:
                return None  # mostly outside the field of view, or no background to be had
            fx, fy = cx, cy
        if not sized:
            # size first, from the half-maximum area: a chord profile exceeds
            # half its peak inside rho < R sqrt(3)/2, whatever the window
            b = kernels.subtract_background(roi, coef, fx, fy).astype(np.float32)
            sm = cv2.blur(b, (3, 3))
            yy, xx = np.mgrid[0:b.shape[0], 0:b.shape[1]]
            near = (xx - cx) ** 2 + (yy - cy) ** 2 <= (0.5 * r + 2) ** 2
            if not near.any():
                return None
            iy, ix = np.unravel_index(np.argmax(np.where(near, sm, -np.inf)), sm.shape)
            peak = float(sm[iy, ix])
            if peak <= 0:
                return None
            _, lab = cv2.connectedComponents((sm > peak / 2).astype(np.uint8))
            comp = lab == lab[iy, ix]
            r = r_half = float(np.clip(np.sqrt(comp.sum() / (0.75 * np.pi)), 0.25 * opt.diameter_px[0],
                                       opt.diameter_px[1]))
            ys_, xs_ = comp.nonzero()
            x, y = c0 + xs_.mean(), q0 + ys_.mean()
            sized = True
            continue
        st = kernels.window_moments(roi, coef, fx, fy, cx, cy, rw)
        V, mx, my, Mxx, Myy, Mxy = st[:6]
        if V <= 0:
            return None
        x, y = x + mx, y + my
        # second moment of a chord profile is 2/5 R^2; blur and pixel
        # integration add their variances
        m2 = Mxx + Myy - 2 * opt.blur_px**2 - 2 / 12
        r_m2 = float(np.sqrt(2.5 * m2)) if m2 > 0 else 0.0
        if first and r_m2 < _MOAT_SHARE * r_half and alone(x, y, r_out):
            # A ring brighter than the background round the shadow (a display
            # chain's edge enhancement) counts against the moment at its rho^2
            # weight: a small sphere's moment came out negative. Taken for that
            # only for a shadow alone (a neighbour in the background's ring
            # makes the rim read low too: a helix's chains were lost) whose
            # own disc, inside the ring, has the half-maximum size; then that
            # size holds.
            rc = r_half + 2 * opt.blur_px
            core = kernels.window_moments(roi, coef, fx, fy, cx + mx, cy + my, rc) if rc < rw else None
            mc = core[3] + core[4] - 2 * opt.blur_px**2 - 2 / 12 if core is not None and core[0] > 0 else 0.0
            # (the ring seen: the window's rim outside that disc sums clearly below zero)
            rim = st[0] - core[0] if core is not None else 0.0
            n_rim = st[10] - core[10] if core is not None else 0
            seen = n_rim > 0 and rim < -2 * sig_bg * np.sqrt(opt.noise_kappa * n_rim)
            if seen and mc > 0 and np.sqrt(2.5 * mc) >= _MOAT_SHARE * r_half and \
                    anisotropy(core[3], core[4], core[5]) <= opt.max_anisotropy:
                r_m2 = r_half
        if r_m2 <= 0:
            return None
        r_new = r if capped else r_m2   # a cut window's moment is not the size
        converged = abs(mx) < 2e-3 and abs(my) < 2e-3 and abs(r_new - r) < 0.02 * r
        r = r_new
        if not (0.25 * opt.diameter_px[0] <= r <= opt.diameter_px[1]):
            return None
        if converged:
            break
    if st is None:
        return None
    V, _, _, Mxx, Myy, Mxy, Sxx_e, Syy_e, sum_e2, abs_ex, n_win = st
    aniso = anisotropy(Mxx, Myy, Mxy)
    # centroid noise: pixel noise grows with attenuation, var ~ exp(a) / N0
    sigma2 = sig_bg**2 * (Sxx_e + Syy_e) / 2 / V**2
    # the fitted background's slope uncertainty moves the centroid too
    slope_sig = sig_bg / (np.sqrt(max(n_in, 1)) * s_ring)
    sigma2 += (slope_sig * sum_e2 / V) ** 2
    kappa = opt.kappa_for("centroid", rw)
    sigma2 *= kappa   # noise correlated over a few px averages out less
    clutter = noise > 0 and sig_bg > 1.5 * noise + 1e-6
    if clutter:
        # structure the background model cannot follow: its excess taken as a
        # coherent error over half the window (over the frame's noise, not the
        # ring's own: at a real plate's edge the ring's read 2x the frame's and
        # left sigma 4x short of what fit-pose's residuals said)
        sigma2 += (0.5 * np.sqrt(max(sig_bg**2 - noise**2, 0.0)) * abs_ex / V) ** 2
    # The centroid of the shadow's core (rho < 0.75 r) must agree with the whole
    # window's: a faint blob, ghost or rod near the edge pulls them apart.
    core = kernels.window_moments(roi, coef, fx, fy, x - c0, y - q0, 0.75 * r)
    if core[0] > 0:
        dcx, dcy = core[1], core[2]
        var_core = sig_bg**2 * (core[6] + core[7]) / 2 / core[0] ** 2
        gap2 = (dcx * dcx + dcy * dcy) / 2
        if gap2 > 9 * (var_core + sigma2) and np.sqrt(gap2) > 0.03:  # cone-beam asymmetry is ~0.02 px
            clutter = True
            sigma2 += gap2
    # A sphere shadow is point-symmetric about its centroid; the odd part under
    # reflection measures what else lies in the window (a faint blob, a ghost,
    # a rod) and bounds the bias it causes.
    cx, cy = x - c0, y - q0
    b = kernels.subtract_background(roi, coef, fx, fy).astype(np.float32)
    yy, xx = np.mgrid[0:b.shape[0], 0:b.shape[1]]
    ddx, ddy = xx - cx, yy - cy
    win = ddx * ddx + ddy * ddy <= rw * rw
    if not win.any():
        return None   # the centroid walked out of its window's box
    M = cv2.getRotationMatrix2D((float(cx), float(cy)), 180.0, 1.0)
    refl = cv2.warpAffine(b, M, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    bw = b[win].astype(np.float64)
    odd = 0.5 * (bw - refl[win])
    s_odd = sig_bg * np.exp(np.clip(bw, 0, 8) / 2) / np.sqrt(2.0)
    # (or the shadow's own odd scatter, robustly: an 8-bit display's steps and
    # JPEG's ringing on its slopes are noise, not structure; against the ring's
    # noise alone 42 of 96 lone spheres of an 8-bit JPEG read clutter)
    s_odd = np.maximum(s_odd, float(mad_sigma(odd, centre=False)))
    rho = np.sqrt(ddx[win] ** 2 + ddy[win] ** 2)
    # The centroid's error is the sum of (x - c) times the odd part of the
    # noise, so the odd part seen in the window measures the noise this shadow
    # carries (8-bit steps in its dark core, glare, JPEG), whatever the noise
    # model says. A reflected pixel is interpolated between four, which
    # lowers its variance by w.
    fx, fy = (2 * cx) % 1.0, (2 * cy) % 1.0
    w = ((1 - fx) ** 2 + fx ** 2) * ((1 - fy) ** 2 + fy ** 2)
    own2 = kappa * float((rho * rho * 4 * odd * odd).sum()) / (1 + w) / 2 / V**2
    sigma2 = max(sigma2, own2)
    asym = float((rho * np.maximum(np.abs(odd) - 3 * s_odd, 0.0)).sum() / V)
    if asym > 3 * np.sqrt(sigma2) and asym > 0.02:
        clutter = True
        sigma2 += asym**2
    # how far the shadow is from an ideal chord profile 2 mu sqrt(r^2 - rho^2)
    g = 2 * np.sqrt(np.maximum(r * r - rho * rho, 0.0))
    gg = float(g @ g)
    misfit = float(np.sqrt(((bw - (bw @ g) / gg * g) ** 2).sum() / max(float(bw @ bw), 1e-30))) if gg > 0 else 1.0
    peak = float(cv2.blur(b, (3, 3))[win].max())  # a smoothed maximum: robust to one noisy pixel
    mu_px = 1.5 * V / (np.pi * r * r) / (2 * r)   # V = 4/3 pi R^3 mu
    flags = ["truncated"] if truncated or hidden > 0 or rw > min(x, y, cols - 1 - x, rows - 1 - y) else []
    if clutter:
        flags.append("clutter")
    return Blob(float(x), float(y), r, float(np.sqrt(sigma2)), float(mu_px), peak, aniso, flags,
                float(peak / sig_bg), misfit)


def window_radius(r, blur: float):
    """Radius (px) of :func:`refine`'s centroid window about a shadow of
    radius ``r``: the chord profile, its blur and a pixel's margin."""
    return 1.15 * r + 3 * blur + 1.5


def window_reach(r1, r2, blur: float):
    """Centre distance (px) under which two shadows of radii ``r1``, ``r2``
    have centroid windows that meet: measured together, flagged overlap."""
    return window_radius(r1, blur) + window_radius(r2, blur)


def chord_like(b: "Blob") -> bool:
    """Whether ``b``'s profile is as close to a sphere's chord profile as the
    clutter test asks of a shadow with structure across it."""
    return b.profile_misfit <= 0.2 + 1.5 / b.radius


# a shadow this round is one sphere's whatever its size: a shadow measured
# again twice as wide (detect_blobs), a merged blob of the neighbours'
# material (crowded._one_sphere; a box phantom's big balls read 1.02)
ROUND_ANISOTROPY = 1.1

# a sphere's candidate peak: on a real C-arm recording lone spheres read 51-61
# (noise sigmas), the noise on an intensifier's dark blot 10-27; a sphere
# overlapped by another reads more than alone
_SEED_STRENGTH = 0.5


class NonFiniteFrame(ValueError):
    """The frame holds NaN or inf pixels."""


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
        chain = (b is None or not np.isfinite(b.anisotropy)) and h > 3 * opt.threshold
        if chain:
            # a chain of touching shadows across a wall seen end-on: no background
            # ring to be had for one sphere's window (or one whose second moments
            # come out negative: no shape); its extent, to be split (however
            # long: :func:`.chain.chain_like` judged its width)
            b = _rough_blob(a, cx, cy, r_guess, opt.blur_px, noise, opt)
        # (clutter allowed: the neighbours that make a cluster disturb its background)
        if b is not None and b.snr >= opt.min_snr and (chain or b.anisotropy < 3.0) and "truncated" not in b.flags:
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
        # (one chain's strong peaks are one blob: a row of seven was split five times over)
        if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < b.radius**2 for b in blobs + merged):
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
    # a candidate peak as strong as half the frame's lone spheres' may be one;
    # weaker ones (noise on a broad blot, JPEG texture) are no sphere to look for
    alone = [h for cx, cy, h in cands if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < (0.8 * b.radius) ** 2
                                             for b in kept if not b.flags)]
    floor = _SEED_STRENGTH * float(np.median(alone)) if alone else 0.0
    return kept, merged, spoilt, noise, invalid, [(cx, cy) for cx, cy, _ in cands], \
        [(cx, cy) for cx, cy, h in cands if h >= floor]
