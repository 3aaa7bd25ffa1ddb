"""Touching and overlapping sphere shadows, measured together.

A centroid window that holds part of a neighbour's shadow is pulled towards
it; two shadows merged into one blob fail the single-sphere tests and were
lost. Here each group of shadows that touch is fitted at once with a model
of its spheres (chord profiles ``2 mu sqrt(R^2 - rho^2)`` sampled 3x3 per
pixel, blurred by the system's Gaussian, on a plane background). Every
sphere is then measured as before, by its background-corrected centroid,
on the frame with the *other* spheres' models removed, so the measured
point keeps detect's definition (the attenuation centroid of that sphere's
own shadow). Its sigma also counts how far that centroid and the joint
model's centre disagree, which is how wrong the neighbours' models may be.

A blob rejected as elongated whose attenuation volume is that of 2 or 3 of
the frame's spheres is fitted with 1, 2 and 3 spheres; the count with the
lowest BIC is kept when its spheres have the frame's size and contrast.
Units: px (columns x, rows y), attenuation.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import FitError
from ..fit.core import Parameter, solve

_SS = 3     # samples per pixel and axis


def render(shape, spheres: np.ndarray, blur: float, jacobian: bool = False):
    """Model attenuation of ``spheres`` (k, 4: x, y, R px; mu per px of chord)
    on a patch of ``shape`` (rows, cols) px, pixel-integrated and blurred.
    With ``jacobian``: also d model / d(x, y, R, mu) per sphere, (rows*cols, 4k)."""
    h, w = shape
    o = (np.arange(_SS) + 0.5) / _SS - 0.5
    ys = (np.arange(h)[:, None] + o[None, :]).ravel()
    xs = (np.arange(w)[:, None] + o[None, :]).ravel()
    X, Y = np.meshgrid(xs, ys)

    def down(f):
        f = f.reshape(h, _SS, w, _SS).mean(axis=(1, 3)).astype(np.float32)
        return cv2.GaussianBlur(f, (0, 0), blur, borderType=cv2.BORDER_REPLICATE) if blur > 0.05 else f

    model = np.zeros((h, w), np.float32)
    cols = []
    for x, y, R, mu in spheres:
        dx, dy = X - x, Y - y
        q = R * R - dx * dx - dy * dy
        inside = q > 0
        s = np.sqrt(np.where(inside, q, 0.0))
        model += down(2 * mu * s)
        if jacobian:
            # the rim's 1/sqrt(q) is integrable over a pixel but not sampled:
            # kept finite at a fraction of a pixel inside the rim
            inv = np.where(inside, 1.0 / np.sqrt(np.maximum(q, 0.5 * abs(R) + 1e-6)), 0.0)
            cols += [down(2 * mu * dx * inv), down(2 * mu * dy * inv), down(2 * mu * R * inv), down(2 * s)]
    if not jacobian:
        return model
    return model, np.stack([c.ravel() for c in cols], axis=1).astype(np.float64)


def fit_group(a: np.ndarray, spheres: np.ndarray, blur: float, noise: float, mask_out=(), invalid=None):
    """Fit spheres (k, 4) jointly on ``a`` around them; returns (box, fitted
    (k, 4), sigma (k, 4), background plane (3,), chi2, n pixels) or None."""
    rows, cols = a.shape
    pad = 3 * blur + 4
    lo = np.floor(np.min(spheres[:, :2] - spheres[:, 2:3] - pad, axis=0)).astype(int)
    hi = np.ceil(np.max(spheres[:, :2] + spheres[:, 2:3] + pad, axis=0)).astype(int) + 1
    c0, q0 = max(lo[0], 0), max(lo[1], 0)
    c1, q1 = min(hi[0], cols), min(hi[1], rows)
    if c1 - c0 < 6 or q1 - q0 < 6:
        return None
    roi = a[q0:q1, c0:c1].astype(np.float64)
    h, w = roi.shape
    yy, xx = np.mgrid[0:h, 0:w]
    wgt = np.ones((h, w))
    for ox, oy, orad in mask_out:          # other markers' shadows are not this group's background
        wgt[(xx - (ox - c0)) ** 2 + (yy - (oy - q0)) ** 2 < (1.15 * orad + 3 * blur + 2) ** 2] = 0
    if invalid is not None:
        wgt[invalid[q0:q1, c0:c1]] = 0
    if wgt.sum() < 4 * len(spheres) + 10:
        return None
    s0 = spheres.copy()
    s0[:, 0] -= c0
    s0[:, 1] -= q0
    k = len(spheres)
    # the plane's start from the patch's border, where the spheres are not
    edge = np.zeros((h, w), bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    edge &= wgt > 0
    A = np.column_stack([np.ones(edge.sum()), xx[edge] - w / 2, yy[edge] - h / 2])
    plane = np.linalg.lstsq(A, roi[edge], rcond=None)[0] if edge.sum() > 3 else np.zeros(3)
    wv = np.sqrt(wgt.ravel()) / noise
    B = np.column_stack([np.ones(h * w), (xx - w / 2).ravel(), (yy - h / 2).ravel()])

    def unpack(p):
        return p[:4 * k].reshape(k, 4), p[4 * k:]

    def residuals(p):
        sph, bg = unpack(p)
        return wv * (render((h, w), sph, blur).ravel() + B @ bg - roi.ravel())

    def jacobian(p):
        sph, _ = unpack(p)
        _, J = render((h, w), sph, blur, jacobian=True)
        return wv[:, None] * np.hstack([J, B])

    params = []
    for i, (x, y, R, mu) in enumerate(s0):
        params += [Parameter(f"x{i}", x, scale=0.1), Parameter(f"y{i}", y, scale=0.1),
                   Parameter(f"R{i}", R, scale=0.1), Parameter(f"mu{i}", max(mu, 1e-6), scale=max(mu, 1e-6) * 0.05)]
    params += [Parameter("b0", plane[0]), Parameter("bx", plane[1]), Parameter("by", plane[2])]
    try:
        # unbounded, so the normal-equations path (an SVD of J per step cost 10x)
        res = solve(params, residuals, jacobian, max_nfev=60, tol=1e-8, scale_covariance=True, large=True)
    except (FitError, np.linalg.LinAlgError, ValueError):
        return None
    sph, bg = unpack(res.x)
    if not (np.all(sph[:, 2] > 0.5) and np.all(sph[:, 3] > 0)):
        return None
    sig = np.nan_to_num(res.sigma[:4 * k].reshape(k, 4), nan=np.inf)
    sph = sph.copy()
    sph[:, 0] += c0
    sph[:, 1] += q0
    return (c0, q0, c1, q1), sph, sig, bg, float(res.chi2), int((wgt > 0).sum())


def groups_of(blobs, blur: float) -> list[list[int]]:
    """Indices of blobs whose centroid windows meet, as connected groups of 2 or more."""
    n = len(blobs)
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            reach = 1.15 * (blobs[i].radius + blobs[j].radius) + 6 * blur + 3
            if (blobs[i].x - blobs[j].x) ** 2 + (blobs[i].y - blobs[j].y) ** 2 < reach**2:
                parent[root(i)] = root(j)
    out: dict[int, list[int]] = {}
    for i in range(n):
        out.setdefault(root(i), []).append(i)
    return [g for g in out.values() if len(g) > 1]


def fit_step(a: np.ndarray, x: float, y: float, R: float, mu: float, blur: float, noise: float, invalid=None):
    """A straight background step (a plate's or holder's edge) beside the
    sphere shadow at (x, y) of radius R: fitted on a patch of radius ~3R
    together with the sphere (chord profile) and a plane. Returns (box, step
    image over the box: the edge's part of the background only) or None when
    no step is there (its height under 5 sigma)."""
    from scipy.special import ndtr

    rows, cols = a.shape
    half = int(np.ceil(3 * R + 3 * blur + 4))
    c0, q0 = max(int(x) - half, 0), max(int(y) - half, 0)
    c1, q1 = min(int(x) + half + 1, cols), min(int(y) + half + 1, rows)
    roi = a[q0:q1, c0:c1].astype(np.float64)
    h, w = roi.shape
    if h < 8 or w < 8:
        return None
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    cx, cy = x - c0, y - q0
    outside = (xx - cx) ** 2 + (yy - cy) ** 2 > (1.2 * R + 3 * blur + 2) ** 2
    if invalid is not None:
        outside &= ~invalid[q0:q1, c0:c1]
    gx = cv2.Sobel(roi.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(roi.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    g2 = np.where(outside, gx * gx + gy * gy, 0.0)
    if g2.sum() <= 0:
        return None
    # the edge's normal from the structure tensor, its place from the strongest gradients
    Sxx, Syy, Sxy = (gx * gx * outside).sum(), (gy * gy * outside).sum(), (gx * gy * outside).sum()
    phi = 0.5 * np.arctan2(2 * Sxy, Sxx - Syy)
    n = np.array([np.cos(phi), np.sin(phi)])
    strong = g2 > 0.25 * g2.max()
    d0 = float(((xx * n[0] + yy * n[1])[strong] * g2[strong]).sum() / g2[strong].sum())
    side = (xx * n[0] + yy * n[1]) > d0
    if not (outside & side).any() or not (outside & ~side).any():
        return None
    s0 = float(np.median(roi[outside & side]) - np.median(roi[outside & ~side]))
    B = np.column_stack([np.ones(h * w), (xx - w / 2).ravel(), (yy - h / 2).ravel()])
    wv = np.ones(h * w) / noise
    sb = max(blur, 0.5)

    def step(p):
        t = (xx * np.cos(p[0]) + yy * np.sin(p[0]) - p[1]) / sb
        return t, p[2] * ndtr(t)

    def residuals(p):
        sph = np.array([[p[3], p[4], p[5], p[6]]])
        return wv * (render((h, w), sph, blur).ravel() + step(p)[1].ravel() + B @ p[7:] - roi.ravel())

    def jacobian(p):
        sph = np.array([[p[3], p[4], p[5], p[6]]])
        _, Js = render((h, w), sph, blur, jacobian=True)
        t, _ = step(p)
        pdf = np.exp(-0.5 * t * t) / np.sqrt(2 * np.pi) * p[2] / sb
        dphi = pdf * (-xx * np.sin(p[0]) + yy * np.cos(p[0]))
        return wv[:, None] * np.column_stack([dphi.ravel(), -pdf.ravel(), ndtr(t).ravel(), Js, B])

    bg = np.median(roi[outside & ~side])
    params = [Parameter("phi", phi, scale=0.01), Parameter("d", d0, scale=0.1), Parameter("s", s0, scale=0.01),
              Parameter("x", cx, scale=0.1), Parameter("y", cy, scale=0.1), Parameter("R", R, scale=0.1),
              Parameter("mu", mu, scale=0.05 * mu), Parameter("b0", bg), Parameter("bx", 0.0), Parameter("by", 0.0)]
    try:
        res = solve(params, residuals, jacobian, max_nfev=80, tol=1e-8, scale_covariance=True, large=True)
    except (FitError, np.linalg.LinAlgError, ValueError):
        return None
    p = res.x
    if not np.isfinite(res.sigma[2]) or abs(p[2]) < 5 * max(res.sigma[2], noise / np.sqrt(h)):
        return None
    return (c0, q0, c1, q1), step(p)[1].astype(np.float32), p[3] + c0, p[4] + q0
