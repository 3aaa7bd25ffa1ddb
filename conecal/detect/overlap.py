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

A blob that holds several shadows is split into them by :mod:`.split`.
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
    With ``jacobian``: also d model / d(x, y, R, mu) per sphere, (rows*cols, 4k).
    Each sphere is sampled only over its own box (its disc plus 4 blur sigmas)."""
    h, w = shape
    o = (np.arange(_SS) + 0.5) / _SS - 0.5
    model = np.zeros((h, w), np.float32)
    J = np.zeros((h, w, 4 * len(spheres))) if jacobian else None
    m = 4 * blur + 2
    for n, (x, y, R, mu) in enumerate(spheres):
        c0, c1 = int(np.clip(np.floor(x - abs(R) - m), 0, w)), int(np.clip(np.ceil(x + abs(R) + m) + 1, 0, w))
        q0, q1 = int(np.clip(np.floor(y - abs(R) - m), 0, h)), int(np.clip(np.ceil(y + abs(R) + m) + 1, 0, h))
        if c1 <= c0 or q1 <= q0:
            continue
        bh, bw = q1 - q0, c1 - c0
        ys = (np.arange(q0, q1)[:, None] + o[None, :]).ravel()
        xs = (np.arange(c0, c1)[:, None] + o[None, :]).ravel()
        dx, dy = xs[None, :] - x, ys[:, None] - y
        q = R * R - dx * dx - dy * dy
        inside = q > 0
        s = np.sqrt(np.where(inside, q, 0.0))

        def down(f):
            # the mean over each pixel's samples (area resampling by a whole factor)
            f = cv2.resize(f.astype(np.float32), (bw, bh), interpolation=cv2.INTER_AREA)
            return cv2.GaussianBlur(f, (0, 0), blur, borderType=cv2.BORDER_REPLICATE) if blur > 0.05 else f

        model[q0:q1, c0:c1] += down(2 * mu * s)
        if jacobian:
            # the rim's 1/sqrt(q) is integrable over a pixel but not sampled:
            # kept finite at a fraction of a pixel inside the rim
            inv = np.where(inside, 1.0 / np.sqrt(np.maximum(q, 0.5 * abs(R) + 1e-6)), 0.0)
            for j, f in enumerate((2 * mu * dx * inv, 2 * mu * dy * inv, 2 * mu * R * inv, 2 * s)):
                J[q0:q1, c0:c1, 4 * n + j] = down(f)
    if not jacobian:
        return model
    return model, J.reshape(h * w, -1)


def render_box(box, spheres: np.ndarray, blur: float) -> np.ndarray:
    """:func:`render` of ``spheres`` (k, 4) given in frame px on the frame's
    patch ``box`` (c0, q0, c1, q1)."""
    c0, q0, c1, q1 = box
    local = np.asarray(spheres, float).reshape(-1, 4) - np.array([c0, q0, 0.0, 0.0])
    return render((q1 - q0, c1 - c0), local, blur)


def mask_weights(box, mask_out, blur: float, invalid=None) -> np.ndarray:
    """Weights over the frame's patch ``box``: 1, and 0 within reach of the
    shadows ``mask_out`` ((x, y, r) frame px: other markers are not this
    fit's background) and on ``invalid`` pixels."""
    c0, q0, c1, q1 = box
    yy, xx = np.mgrid[q0:q1, c0:c1]
    w = np.ones((q1 - q0, c1 - c0))
    for ox, oy, orad in mask_out:
        w[(xx - ox) ** 2 + (yy - oy) ** 2 < (1.15 * orad + 3 * blur + 2) ** 2] = 0
    if invalid is not None:
        w[invalid[q0:q1, c0:c1]] = 0
    return w


def group_box(shape, spheres: np.ndarray, blur: float, pad: float | None = None) -> tuple[int, int, int, int]:
    """The patch (c0, q0, c1, q1) a group of spheres (k, 4) is fitted on:
    their discs plus ``pad`` px (default 3 blur + 4), clipped to ``shape``."""
    rows, cols = shape
    pad = 3 * blur + 4 if pad is None else pad
    lo = np.floor(np.min(spheres[:, :2] - spheres[:, 2:3] - pad, axis=0)).astype(int)
    hi = np.ceil(np.max(spheres[:, :2] + spheres[:, 2:3] + pad, axis=0)).astype(int) + 1
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], cols), min(hi[1], rows)


def fit_group(a: np.ndarray, spheres: np.ndarray, blur: float, noise: float, mask_out=(), invalid=None,
              box=None):
    """Fit spheres (k, 4) jointly on ``a`` around them (on ``box``, else
    :func:`group_box`); returns (box, fitted (k, 4), sigma (k, 4), background
    plane (3,), chi2, n pixels) or None."""
    c0, q0, c1, q1 = box if box is not None else group_box(a.shape, spheres, blur)
    if c1 - c0 < 6 or q1 - q0 < 6:
        return None
    roi = a[q0:q1, c0:c1].astype(np.float64)
    h, w = roi.shape
    yy, xx = np.mgrid[0:h, 0:w]
    wgt = mask_weights((c0, q0, c1, q1), mask_out, blur, invalid)
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
