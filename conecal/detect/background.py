"""Structured background beside a sphere shadow: an edge, a ridge, a wall.

A plate's edge, a holder's wall or a tube seen side-on puts a background
into a shadow's window that no plane follows: a step, a cusp-shaped ridge
(the tangent rays through a tube's wall), a hump. What these share is that
the background is (nearly) constant along one direction across the patch.
:func:`fit_profile` models it so: a free 1-D profile ``f(s)`` of the
coordinate across the edge, ``s = u + kappa v^2`` (``u`` across, ``v`` along
it; ``kappa`` lets the level lines bend, as a tube seen end-on or an
intensifier's round field does), plus a slope along it, fitted jointly with
the sphere's chord profile. Every level line through the shadow also runs
outside it, which is what makes the profile under the shadow knowable.
The profile is piecewise linear on 1 px knots, lightly held smooth where
no pixel pins it. Units: px (columns x, rows y), attenuation.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import FitError
from ..fit.core import Parameter, solve
from .profile_kernels import profile_fit
from .overlap import group_box, mask_weights, render, render_jacobian

_KNOT_PX = 1.0
# curvatures (1/px) tried: level lines straight, or bent to circles of radius
# 25-400 px either way (a tube's wall seen end-on, an intensifier's field)
_KAPPAS = (-1 / 50, -1 / 100, -1 / 200, -1 / 400, 0.0, 1 / 400, 1 / 200, 1 / 100, 1 / 50)


def _hat(s: np.ndarray, s0: float, n: int):
    """Piecewise-linear basis on knots ``s0 + k`` (k < n): (index, weight of
    the left knot, slope sign domain) for every sample; ``s`` clamped."""
    t = np.clip((s - s0) / _KNOT_PX, 0, n - 1 - 1e-9)
    i = np.floor(t).astype(int)
    return i, t - i


def _patch(a, x, y, R, blur, others, invalid):
    """The box (c0, q0, c1, q1) of half-width ~3R about (x, y), its pixels
    (float64), and the weights (0 on other shadows and invalid pixels)."""
    rows, cols = a.shape
    half = int(np.ceil(3 * R + 3 * blur + 4))
    c0, q0 = max(int(x) - half, 0), max(int(y) - half, 0)
    c1, q1 = min(int(x) + half + 1, cols), min(int(y) + half + 1, rows)
    roi = a[q0:q1, c0:c1].astype(np.float64)
    h, w = roi.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    return (c0, q0, c1, q1), roi, mask_weights((c0, q0, c1, q1), others, blur, invalid), xx, yy


def structured(a: np.ndarray, x: float, y: float, R: float, blur: float, noise: float, invalid=None,
               others=()) -> bool:
    """Whether the background around the shadow at (x, y) holds more than a
    quadratic surface follows: the scatter of a quadratic fitted to the
    patch outside the shadow (half-width ~3R) over 1.3x the pixel noise
    ``noise``. Cheap; decides where :func:`fit_profile` is worth its cost."""
    (c0, q0, _, _), roi, wgt, xx, yy = _patch(a, x, y, R, blur, others, invalid)
    # every st-th pixel of a large shadow's patch (a 90 px shadow's holds 300k)
    st = max(1, int(R // 6))
    roi, wgt, xx, yy = roi[::st, ::st], wgt[::st, ::st], xx[::st, ::st], yy[::st, ::st]
    dx, dy = xx - (x - c0), yy - (y - q0)
    m = (dx * dx + dy * dy > (1.2 * R + 3 * blur + 2) ** 2) & (wgt > 0)
    if m.sum() < 40:
        return False
    X, Y = dx[m] / R, dy[m] / R
    A = np.column_stack([np.ones_like(X), X, Y, X * X, X * Y, Y * Y])
    # normal equations of 6 unknowns (an lstsq here woke BLAS's threads in every worker)
    N = A.T @ A
    c = np.linalg.solve(N + 1e-12 * np.trace(N) * np.eye(6), A.T @ roi[m])
    return float(np.std(roi[m] - A @ c)) > 1.3 * noise


def smooth_under(a: np.ndarray, box, discs, blur: float, scale: float, invalid=None) -> np.ndarray | None:
    """The background over the frame's patch ``box`` (c0, q0, c1, q1) where
    the shadows ``discs`` ((x, y, r) px) hide it, from the pixels around them:
    a Gaussian average (σ ``scale`` px) of the pixels outside every shadow's
    reach, normalised by the weight it found (normalised convolution). No
    surface is assumed, so it follows a tube's curved wall or a plate's
    ramp that a quadratic does not; it smooths a step. Attenuation, on the
    patch's pixels; None where the shadows leave too little around them
    (under 5 % of the kernel's weight at some pixel)."""
    rows, cols = a.shape
    c0, q0, c1, q1 = box
    pad = int(np.ceil(3 * scale))
    big = (max(c0 - pad, 0), max(q0 - pad, 0), min(c1 + pad, cols), min(q1 + pad, rows))
    w = mask_weights(big, discs, blur, invalid)
    roi = a[big[1]:big[3], big[0]:big[2]].astype(np.float64)
    num = cv2.GaussianBlur(w * roi, (0, 0), scale, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(w, (0, 0), scale, borderType=cv2.BORDER_CONSTANT)
    inner = (slice(q0 - big[1], q1 - big[1]), slice(c0 - big[0], c1 - big[0]))
    if den[inner].size == 0 or den[inner].min() < 0.05:
        return None
    return num[inner] / den[inner]


def fit_profile(a: np.ndarray, spheres: np.ndarray, blur: float, noise: float, invalid=None, others=()):
    """The background across an edge beside the sphere shadows ``spheres``
    (k, 4: x, y, R px, mu per px of chord; one, or a touching group):
    returns (box (c0, q0, c1, q1), background image over the box without
    the spheres, the spheres fitted on it (k, 4)) or None when the patch
    holds no structure beyond a plane (the profile's gain in chi-square
    under 3 per knot + 50) or the fit fails. ``others``: (x, y, r) of shadows
    kept out."""
    spheres = np.asarray(spheres, float).reshape(-1, 4)
    x, y = spheres[:, 0].mean(), spheres[:, 1].mean()
    R_ext = float(np.max(np.hypot(spheres[:, 0] - x, spheres[:, 1] - y) + spheres[:, 2]))
    R = float(np.median(spheres[:, 2]))
    box, roi_full, wgt, xx, yy = _patch(a, x, y, R_ext, blur, others, invalid)
    c0, q0, c1, q1 = box
    # large shadows: fitted on pixels binned fb x fb (the cost grows with the
    # patch's area and knots), in binned units until the background is made
    fb = max(1, int(R // 6))
    loc = spheres.copy()
    loc[:, 0] -= c0
    loc[:, 1] -= q0
    if fb > 1:
        hb, wb = roi_full.shape[0] // fb, roi_full.shape[1] // fb
        roi = roi_full[:hb * fb, :wb * fb].reshape(hb, fb, wb, fb).mean(axis=(1, 3))
        wgt = wgt[:hb * fb, :wb * fb].reshape(hb, fb, wb, fb).min(axis=(1, 3))
        yy, xx = np.mgrid[0:hb, 0:wb].astype(float)
        loc[:, :2] = (loc[:, :2] + 0.5) / fb - 0.5
        loc[:, 2] /= fb
        loc[:, 3] *= fb
        R, R_ext, noise = R / fb, R_ext / fb, noise / fb
        blur = np.sqrt(blur**2 + (fb * fb - 1) / 12.0) / fb
    else:
        roi = roi_full
    h, w = roi.shape
    if h < 8 or w < 8:
        return None
    cx, cy = loc[:, 0].mean(), loc[:, 1].mean()
    outside = wgt > 0
    for sx, sy, sR, _ in loc:
        outside &= (xx - sx) ** 2 + (yy - sy) ** 2 > (1.2 * sR + 3 * blur + 2) ** 2
    if outside.sum() < 40:
        return None
    gx = cv2.Sobel(roi.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(roi.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    Sxx, Syy, Sxy = (gx * gx * outside).sum(), (gy * gy * outside).sum(), (gx * gy * outside).sum()
    phi0 = 0.5 * np.arctan2(2 * Sxy, Sxx - Syy)
    dx, dy = xx - cx, yy - cy
    span = np.hypot(dx, dy).max()
    s_lo = -span - max(map(abs, _KAPPAS)) * span**2 - 2
    n_knots = int(np.ceil((2 * span + 2 * max(map(abs, _KAPPAS)) * span**2 + 4) / _KNOT_PX)) + 1
    wv = np.sqrt(wgt.ravel()) / noise
    y_obs = roi.ravel()
    n_pix = h * w
    reg_w = 0.05 / noise

    k = n_knots
    w2 = wv * wv
    dxr, dyr = dx.ravel(), dy.ravel()

    def profile(phi, kappa, extra, target):
        """Knot values and the ``extra`` columns' coefficients that best
        give ``target``, with chi-square and the model
        (``profile_kernels.profile_fit``: the basis's two non-zeros per pixel; a
        dense 2000 x 60 product cost 30x, and numpy's steps around it half
        the fit)."""
        return profile_fit(dxr, dyr, phi, kappa, s_lo, _KNOT_PX, k, w2,
                           np.column_stack(extra) if extra else np.zeros((n_pix, 0)), target, reg_w**2)

    # direction and bend first, from the background alone (sphere held at its
    # guess): the direction at straight level lines, then the bend (a tube's
    # wall end-on: 1/(2 x its radius)), then the direction again; then the
    # background and the sphere in turn, direction and bend held (the
    # background is linear given the sphere, the sphere has 4 parameters: one
    # joint fit with every knot free cost 0.2 s a shadow, 20x this); then the
    # direction and bend again about the sphere moved, and once more in turn
    sp = loc.copy()
    for rnd in range(2):
        sph0 = render((h, w), sp, blur).ravel()

        def best(pairs):
            """The (phi, kappa) of ``pairs`` whose profile fits best, and its (coef, chi2)."""
            fits = [(pk, profile(*pk, [sph0], y_obs)[:2]) for pk in pairs]
            return min(fits, key=lambda f: f[1][1])

        if rnd == 0:
            (phi, _), _ = best([(p, 0.0) for p in phi0 + np.array([-0.15, -0.075, 0.0, 0.075, 0.15])])
            (_, kappa), _ = best([(phi, q) for q in _KAPPAS])
        else:   # the sphere moved little: the bend's neighbours only
            j = _KAPPAS.index(kappa)
            (_, kappa), _ = best([(phi, q) for q in _KAPPAS[max(j - 1, 0):j + 2]])
        (phi, kappa), (coef, chi2_best) = best([(p, kappa) for p in phi + np.array([-0.04, 0.0, 0.04])])
        if rnd == 0:
            # a plane and the sphere alone: the profile must earn its knots
            P = np.column_stack([np.ones(n_pix), dx.ravel(), dy.ravel(), sph0]) * wv[:, None]
            cp, *_ = np.linalg.lstsq(P, wv * y_obs, rcond=None)
            chi2_plane = float(np.sum((P @ cp - wv * y_obs) ** 2))
            if chi2_plane - chi2_best < 3 * n_knots + 50:
                return None
        sp[:, 3] = np.maximum(sp[:, 3] * coef[-1], 1e-6)
        for _ in range(2):
            coef, _, bgv = profile(phi, kappa, [], y_obs - render((h, w), sp, blur).ravel())
            sp = _spheres((y_obs - bgv).reshape(h, w), sp, wv.reshape(h, w), blur)
            if sp is None:
                return None
    f, bt = coef[:k], coef[k]
    if not (np.all(sp[:, 2] > 0.5) and np.all(sp[:, 3] > 0)) or abs(kappa) > 1 / 30 \
            or np.any(np.hypot(sp[:, 0] - loc[:, 0], sp[:, 1] - loc[:, 1]) > loc[:, 2]):
        return None
    # the background at every pixel of the full-resolution box
    hf, wf = roi_full.shape
    yf, xf = np.mgrid[0:hf, 0:wf].astype(float)
    dxf, dyf = (xf + 0.5) / fb - 0.5 - cx, (yf + 0.5) / fb - 0.5 - cy
    u = dxf * np.cos(phi) + dyf * np.sin(phi)
    v = -dxf * np.sin(phi) + dyf * np.cos(phi)
    i, t = _hat(u + kappa * v * v, s_lo, k)
    bg = f[i] * (1 - t) + f[i + 1] * t + bt * v
    out = sp.copy()
    out[:, :2] = (sp[:, :2] + 0.5) * fb - 0.5 + np.array([c0, q0])
    out[:, 2] *= fb
    out[:, 3] /= fb
    return box, bg.astype(np.float32), out


def _spheres(img: np.ndarray, sp: np.ndarray, wv: np.ndarray, blur: float):
    """Spheres (k, 4: x, y, R, mu) fitted to a background-free patch, from
    ``sp``; None if it fails. ``wv``: per-pixel weights (patch-shaped). Only
    the box the spheres' shadows reach is used: elsewhere the residual does
    not depend on them."""
    c0, q0, c1, q1 = group_box(img.shape, sp, blur, pad=4 * blur + 4)
    img, wv = img[q0:q1, c0:c1], wv[q0:q1, c0:c1].ravel()
    sp = sp - np.array([c0, q0, 0.0, 0.0])
    h, w = img.shape
    y = img.ravel()
    k = len(sp)

    def residuals(p):
        return wv * (render((h, w), p.reshape(k, 4), blur).ravel() - y)

    def jacobian(p):
        return wv[:, None] * render_jacobian((h, w), p.reshape(k, 4), blur)

    params = []
    for j, (x, yv, R, mu) in enumerate(sp):
        params += [Parameter(f"x{j}", x, scale=0.1), Parameter(f"y{j}", yv, scale=0.1),
                   Parameter(f"R{j}", R, scale=0.1), Parameter(f"mu{j}", mu, scale=0.05 * mu)]
    try:
        # normal equations (an SVD of J per step cost 5x)
        res = solve(params, residuals, jacobian, max_nfev=20, tol=1e-6, covariance=False, large=True)
    except (FitError, np.linalg.LinAlgError, ValueError):
        return None
    return np.asarray(res.x).reshape(k, 4) + np.array([c0, q0, 0.0, 0.0])
