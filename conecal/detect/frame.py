"""Sphere markers in one attenuation frame: candidates, sub-pixel centres, checks.

What is measured: the centroid of the background-corrected attenuation of
each sphere shadow (pixel coordinates, column ``x`` and row ``y``). Blur and
pixel integration are symmetric and leave it unbiased; the cone-beam offset
from the projected sphere centre is predicted by
:func:`conecal.geometry.shadow_centroid`, so fits model exactly this point.

Steps: (1) on a frame downsampled by ``f``, a white top-hat removes the
background and every structure wider than the largest marker (plate edges,
field-of-view borders), Gaussian smoothing matched to the smallest marker
and a maximum filter give candidate peaks above ``threshold`` noise sigmas;
(2) per candidate at full resolution, a robust plane fitted on an annulus
is subtracted and the centroid and the second moment (radius, anisotropy)
are iterated; (3) shape, size and contrast tests reject rods, edges, blobs
and ghosts; (4) flags mark truncated and overlapping shadows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DetectOptions:
    """Settings of the detector (px unless stated).

    diameter_px : (min, max) expected shadow diameters, full-resolution px.
    threshold : candidate peak height in noise sigmas (downsampled top-hat).
    max_anisotropy : largest ratio of the principal second moments for a sphere.
    min_relative_contrast : fraction of the scan's median sphere attenuation
        coefficient below which a blob is a ghost or a faint blob, not a marker.
    blur_px : expected blur sigma of the system, widens the windows.
    max_attenuation : pixels above it are not measurements (outside a
        circular field of view, dead or saturated); shadows touching them
        are flagged truncated, or dropped when mostly hidden.
    """

    diameter_px: tuple[float, float]
    threshold: float = 6.0
    max_anisotropy: float = 1.25
    min_relative_contrast: float = 0.35
    blur_px: float = 1.0
    # attenuation beyond which a pixel is dead, saturated or outside a
    # circular field of view (transmission below 1.8 %)
    max_attenuation: float = 4.0

    @property
    def factor(self) -> int:
        """Downsampling factor: keep the smallest marker >= ~6 px across."""
        return int(np.clip(np.floor(self.diameter_px[0] / 6.0), 1, 8))


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


def candidates(a: np.ndarray, opt: DetectOptions, invalid: np.ndarray | None = None):
    """Candidates (x, y, height/noise) in full-resolution px, strongest first,
    and the pixel noise sigma of the (downsampled) frame."""
    f = opt.factor
    rows, cols = a.shape
    if invalid is not None:
        # dead regions become plain background, so their borders raise no peaks
        a = np.where(invalid, np.float32(np.median(a[~invalid]) if (~invalid).any() else 0.0), a)
    small = cv2.resize(a, (cols // f, rows // f), interpolation=cv2.INTER_AREA) if f > 1 else a
    kd = int(np.ceil(opt.diameter_px[1] * 1.5 / f)) | 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kd, kd))
    top = cv2.morphologyEx(small, cv2.MORPH_TOPHAT, kernel, borderType=cv2.BORDER_REPLICATE)
    s = max(opt.diameter_px[0] / f / 4.0, 0.7)
    sm = cv2.GaussianBlur(top, (0, 0), s)
    # the top-hat rectifies noise (the opening follows its minima), so the
    # threshold is taken against the smoothed top-hat's own robust spread
    sub = sm[::2, ::2]
    base = float(np.median(sub))
    noise = 1.4826 * float(np.median(np.abs(sub - base))) + 1e-12
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
    ys, xs = ys[blobby], xs[blobby]
    h = sm[ys, xs] / noise
    order = np.argsort(-h, kind="stable")
    out = []
    for i in order:
        out.append(((xs[i] + 0.5) * f - 0.5, (ys[i] + 0.5) * f - 0.5, float(h[i])))
    return out, float(noise_small(small))


def noise_small(img: np.ndarray) -> float:
    """Robust per-pixel noise sigma of an image (from neighbour differences)."""
    d = img[:, 1:] - img[:, :-1]
    med = np.median(d[::2, ::2])
    return 1.4826 * float(np.median(np.abs(d[::2, ::2] - med))) / np.sqrt(2.0) + 1e-12


def _background_design(X, Y, quadratic: bool):
    cols = [np.ones_like(X), X, Y]
    if quadratic:
        cols += [X * X, X * Y, Y * Y]
    return np.column_stack(cols)


def _plane_fit(X, Y, Z, iters=3, quadratic=False):
    """Robust background z = p0 + p1 x + p2 y (+ quadratic terms) by
    iterated rejection at 3.5 sigma; returns params, residual sigma, inliers, design."""
    A = _background_design(X, Y, quadratic)
    keep = np.ones(len(Z), bool)
    sig = np.inf
    p = np.zeros(A.shape[1])
    for _ in range(iters):
        if keep.sum() < 6:
            break
        p, *_ = np.linalg.lstsq(A[keep], Z[keep], rcond=None)
        r = Z - A @ p
        sig = 1.4826 * np.median(np.abs(r[keep])) + 1e-12
        keep = np.abs(r) < 3.5 * sig
    return p, float(sig), keep, A


def refine(a: np.ndarray, x0: float, y0: float, r0: float, opt: DetectOptions, others=(), noise: float = 0.0,
           invalid: np.ndarray | None = None) -> Blob | None:
    """Sub-pixel centroid of the sphere shadow near (x0, y0) with radius guess r0.

    ``others``: (x, y, r) of neighbouring candidates, masked out of the background annulus.
    Returns None when no sphere-like shadow is there.
    """
    rows, cols = a.shape
    x, y, r = x0, y0, r0
    flags = []
    blob = None
    sized = False
    for it in range(6):
        rw = 1.15 * r + 3 * opt.blur_px + 1.5      # centroid window
        r_in = rw + 1.0
        r_out = r_in + max(4.0, 0.4 * r)
        c0, c1 = int(np.floor(x - r_out)), int(np.ceil(x + r_out)) + 1
        q0, q1 = int(np.floor(y - r_out)), int(np.ceil(y + r_out)) + 1
        truncated = c0 < 0 or q0 < 0 or c1 > cols or q1 > rows
        c0, q0, c1, q1 = max(c0, 0), max(q0, 0), min(c1, cols), min(q1, rows)
        if c1 - c0 < 5 or q1 - q0 < 5:
            return None
        roi = a[q0:q1, c0:c1].astype(np.float64)
        yy, xx = np.mgrid[q0:q1, c0:c1]
        dx, dy = xx - x, yy - y
        rho2 = dx * dx + dy * dy
        ring = (rho2 >= r_in**2) & (rho2 <= r_out**2)
        masked = ring.copy()
        for ox, oy, orad in others:
            masked &= (xx - ox) ** 2 + (yy - oy) ** 2 > (1.15 * orad + 3 * opt.blur_px + 2) ** 2
        # neighbours are left out of the background unless that leaves too little of it
        full_ring = int(ring.sum())
        if masked.sum() >= 0.3 * full_ring:
            ring = masked
        hidden = 0.0
        if invalid is not None:
            inv = invalid[q0:q1, c0:c1]
            ring &= ~inv
            win0 = rho2 <= rw**2
            hidden = float(inv[win0].mean())
            if hidden > 0.2:
                return None  # mostly outside the field of view: not measurable
        if ring.sum() < 12:
            return None
        # a quadratic background extrapolates well only from a nearly whole ring
        quad = ring.sum() > 150 and ring.sum() >= 0.85 * full_ring
        p, sig_bg, keep, _ = _plane_fit(dx[ring], dy[ring], roi[ring], quadratic=quad)
        b = roi - (_background_design(dx.ravel(), dy.ravel(), quad) @ p).reshape(roi.shape)
        win = rho2 <= rw**2
        w = b[win]
        if not sized:
            # size first, from the half-maximum area: a chord profile exceeds
            # half its peak inside rho < R sqrt(3)/2, whatever the window
            sm = cv2.blur(b.astype(np.float32), (3, 3))
            near = rho2 <= (0.5 * r + 2) ** 2
            peak = float(sm[near].max()) if near.any() else 0.0
            if peak <= 0:
                return None
            hm = (sm > peak / 2).astype(np.uint8)
            n, lab = cv2.connectedComponents(hm)
            iy, ix = np.unravel_index(np.argmax(np.where(near, sm, -np.inf)), sm.shape)
            area = float((lab == lab[iy, ix]).sum())
            r_half = float(np.sqrt(area / (0.75 * np.pi)))
            sized = True
            r = float(np.clip(r_half, 0.25 * opt.diameter_px[0], opt.diameter_px[1]))
            x, y = c0 + (lab == lab[iy, ix]).nonzero()[1].mean(), q0 + (lab == lab[iy, ix]).nonzero()[0].mean()
            continue
        V = w.sum()
        if V <= 0:
            return None
        ddx, ddy = dx[win], dy[win]
        mx, my = (w * ddx).sum() / V, (w * ddy).sum() / V
        ex, ey = ddx - mx, ddy - my
        Mxx, Myy, Mxy = (w * ex * ex).sum() / V, (w * ey * ey).sum() / V, (w * ex * ey).sum() / V
        x, y = x + mx, y + my
        # second moment of a chord profile is 2/5 R^2 per radius^2; blur and
        # pixel integration add their variances
        m2 = Mxx + Myy - 2 * opt.blur_px**2 - 2 / 12
        if m2 <= 0:
            return None
        r_new = float(np.sqrt(2.5 * m2))
        tr, det = Mxx + Myy, Mxx * Myy - Mxy**2
        disc = np.sqrt(max(tr * tr / 4 - det, 0.0))
        l1, l2 = tr / 2 + disc, tr / 2 - disc
        aniso = float(np.sqrt(l1 / l2)) if l2 > 0 else np.inf
        converged = abs(mx) < 1e-3 and abs(my) < 1e-3 and abs(r_new - r) < 0.02 * r
        r = r_new
        if not (0.25 * opt.diameter_px[0] <= r <= 1.0 * opt.diameter_px[1]):
            return None
        # noise per pixel grows with attenuation: var ~ exp(a) / N0
        sig_pix = sig_bg * np.exp(np.clip(w, 0, 8) / 2)
        var_x = (sig_pix**2 * ex**2).sum() / V**2
        var_y = (sig_pix**2 * ey**2).sum() / V**2
        # uncertainty of the fitted background slope moves the centroid too
        nring = max(int(keep.sum()), 1)
        s_ring = np.sqrt((dx[ring][keep] ** 2).mean() + 1e-9)
        slope_sig = sig_bg / (np.sqrt(nring) * s_ring)
        var_bg = (slope_sig * (ex**2).sum() / V) ** 2
        sigma2 = (var_x + var_y) / 2 + var_bg
        clutter = noise > 0 and sig_bg > 1.5 * noise
        if clutter:
            # structure the background model cannot follow: treat its excess as a
            # coherent error over half the window
            excess = np.sqrt(sig_bg**2 - noise**2)
            sigma2 += (0.5 * excess * np.abs(ex).sum() / V) ** 2
        sigma = float(np.sqrt(sigma2))
        if converged or it == 5:
            # A sphere shadow is point-symmetric about its centroid; the odd part
            # under reflection measures what else lies in the window (a faint
            # blob, a ghost, a rod) and bounds the bias it causes.
            M = cv2.getRotationMatrix2D((float(x - c0), float(y - q0)), 180.0, 1.0)
            refl = cv2.warpAffine(b.astype(np.float32), M, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REPLICATE)
            win2 = (xx - x) ** 2 + (yy - y) ** 2 <= rw**2
            odd = 0.5 * (b - refl)[win2]
            s_odd = (sig_bg * np.exp(np.clip(b[win2], 0, 8) / 2)) / np.sqrt(2.0)
            rho = np.sqrt((xx - x) ** 2 + (yy - y) ** 2)[win2]
            excess = np.maximum(np.abs(odd) - 3 * s_odd, 0.0)
            asym = float((rho * excess).sum() / V)
            if asym > 3 * np.sqrt(sigma2) and asym > 0.02:
                clutter = True
                sigma2 += asym**2
                sigma = float(np.sqrt(sigma2))
        g = 2 * np.sqrt(np.maximum(r * r - (ex * ex + ey * ey), 0.0))
        gg = float((g * g).sum())
        misfit = float(np.sqrt(((w - (w @ g) / gg * g) ** 2).sum() / max((w * w).sum(), 1e-30))) if gg > 0 else 1.0
        peak = float(np.percentile(w, 99.5)) if w.size > 50 else float(w.max())
        mu_px = 1.5 * V / (np.pi * r * r) / (2 * r)   # V = 4/3 pi R^3 mu
        flags = ["truncated"] if truncated or hidden > 0 or rw > min(x, y, cols - 1 - x, rows - 1 - y) else []
        if clutter:
            flags.append("clutter")
        blob = Blob(float(x), float(y), r, sigma, float(mu_px), peak, aniso, flags, float(peak / sig_bg), misfit)
        if converged:
            break
    return blob


def detect_frame(a: np.ndarray, opt: DetectOptions) -> list[Blob]:
    """All sphere-like shadows in attenuation frame ``a`` (not yet filtered by contrast)."""
    invalid = a > opt.max_attenuation
    if not invalid.any():
        invalid = None
    else:
        invalid = cv2.dilate(invalid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    cands, noise = candidates(a, opt, invalid)
    noise *= opt.factor  # the downsampled frame averages factor**2 pixels
    r_guess = opt.diameter_px[0] / 2 if opt.diameter_px[1] / opt.diameter_px[0] < 1.6 else np.mean(opt.diameter_px) / 2
    blobs: list[Blob] = []
    rough = [(cx, cy, opt.diameter_px[0] / 2) for cx, cy, _ in cands]
    for i, (cx, cy, h) in enumerate(cands):
        # a candidate inside an accepted blob is the same sphere
        if any((cx - b.x) ** 2 + (cy - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in blobs):
            continue
        others = [o for j, o in enumerate(rough) if j != i and (o[0] - cx) ** 2 + (o[1] - cy) ** 2 < (4 * opt.diameter_px[1]) ** 2]
        others = [o for o in others if not any((o[0] - b.x) ** 2 + (o[1] - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in blobs)] + \
                 [(b.x, b.y, b.radius) for b in blobs]
        b = refine(a, cx, cy, r_guess, opt, others, noise, invalid)
        if b is None or b.snr < opt.threshold:
            continue
        if any((b.x - o.x) ** 2 + (b.y - o.y) ** 2 < (0.8 * o.radius) ** 2 for o in blobs):
            continue
        blobs.append(b)
    # overlap: centroid windows that meet
    for i, bi in enumerate(blobs):
        for bj in blobs[i + 1:]:
            reach = 1.15 * (bi.radius + bj.radius) + 6 * opt.blur_px + 3
            if (bi.x - bj.x) ** 2 + (bi.y - bj.y) ** 2 < reach**2:
                for b in (bi, bj):
                    if "overlap" not in b.flags:
                        b.flags.append("overlap")
    kept = []
    for b in blobs:
        if b.anisotropy > opt.max_anisotropy and not set(b.flags) & {"overlap", "truncated", "clutter"}:
            continue  # rods, edges, irregular blobs on a clean background
        if b.anisotropy > 2.0:
            continue  # not a sphere shadow even allowing for what lies across it
        if "clutter" in b.flags and b.profile_misfit > 0.2 + 1.5 / b.radius:
            continue  # a dense irregular blob (bone, debris), not a dome-shaped sphere shadow
        kept.append(b)
    return kept
