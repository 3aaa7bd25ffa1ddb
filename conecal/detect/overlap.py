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
from .frame import window_reach
from .kernels import chord_patch

_SS = 3     # samples per pixel and axis
# the most Jacobian entries a joint fit holds (160 MB as float64): a touching
# group of 60 spheres on a 230 px patch has 1.3e7; speckle read as hundreds of
# touching shadows across a frame asked for 1e9
_MAX_ENTRIES = 2e7


def render(shape, spheres: np.ndarray, blur: float, jacobian: bool = False):
    """Model attenuation of ``spheres`` (k, 4: x, y, R px; mu per px of chord)
    on a patch of ``shape`` (rows, cols) px, pixel-integrated (3x3 samples)
    and blurred. With ``jacobian``: also d model / d(x, y, R, mu) per
    sphere, (rows*cols, 4k) float32."""
    h, w = shape
    sph = np.ascontiguousarray(np.asarray(spheres, np.float64).reshape(-1, 4))
    if not jacobian:
        return _blur(chord_patch(sph, h, w, _SS, False), blur).reshape(h, w)
    J = render_jacobian(shape, sph, blur)
    f = J.reshape(h, w, -1)
    model = (f[..., 3::4] * sph[:, 3].astype(np.float32)).sum(axis=2) if len(sph) else np.zeros((h, w), np.float32)
    return model, J


def render_jacobian(shape, spheres: np.ndarray, blur: float) -> np.ndarray:
    """:func:`render`'s d model / d(x, y, R, mu) per sphere alone,
    (rows*cols, 4k) float32 (a fit's Jacobian: its model is not needed)."""
    h, w = shape
    sph = np.ascontiguousarray(np.asarray(spheres, np.float64).reshape(-1, 4))
    # the blur is linear: once over the patch, every sphere's derivatives as channels
    return _blur(chord_patch(sph, h, w, _SS, True), blur).reshape(h * w, -1)


# OpenCV filters at most this many channels at once (128 in OpenCV 5, 512 in
# 4.x): a group of more than 32 spheres has 4 derivative channels each
_CHANNELS = 128


def _blur(f: np.ndarray, blur: float) -> np.ndarray:
    """The system's Gaussian blur (sigma ``blur`` px) of pixel field(s) ``f``
    (rows, cols[, channels])."""
    if not (blur > 0.05 and f.size):
        return f
    if f.ndim < 3 or f.shape[2] <= _CHANNELS:
        return cv2.GaussianBlur(f, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
    return np.concatenate([cv2.GaussianBlur(np.ascontiguousarray(f[..., i:i + _CHANNELS]), (0, 0), blur,
                                            borderType=cv2.BORDER_REPLICATE).reshape(f.shape[0], f.shape[1], -1)
                           for i in range(0, f.shape[2], _CHANNELS)], axis=2)


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


# at least this many pixels of a patch sharing its highest value exactly: a
# clipped core
_CLIPPED_PIXELS = 4


def clipped(roi: np.ndarray) -> np.ndarray:
    """Pixels of the patch ``roi`` at a level its shadows were clipped to:
    the patch's highest value, where at least ``_CLIPPED_PIXELS`` share it
    exactly (a display's floor, an intensifier's saturation; noise makes
    exact ties elsewhere rare). Such a pixel says only that the attenuation
    there is at least that level, so :func:`fit_group` gives it no weight:
    weighed as a measurement, a pair's model misfit its clipped core and the
    pair was lost or left inside one marker's σ (the independent renderer's
    steel balls, cores at 3.46: 14 of 73 overlapping balls); so does
    :func:`disc_misfit` for a model of two or more. Whether one sphere
    explains its shadow (:func:`disc_misfit`, :func:`odd_misfit` of a
    one-sphere model) is still judged with it: a second sphere nearly on top
    shows in the core's extent only (two balls 1 px apart, half the disc
    clipped, were measured as one centre 0.9 px from either at σ 0.03 when
    the core was left out there too)."""
    at = roi >= roi.max()
    # (a patch mostly at its top level is flat, noiseless or all background: no core)
    return at if _CLIPPED_PIXELS <= at.sum() < at.size / 2 else np.zeros(roi.shape, bool)


def group_box(shape, spheres: np.ndarray, blur: float, pad: float | None = None) -> tuple[int, int, int, int]:
    """The patch (c0, q0, c1, q1) a group of spheres (k, 4) is fitted on:
    their discs plus ``pad`` px (default 3 blur + 4), clipped to ``shape``."""
    rows, cols = shape
    pad = 3 * blur + 4 if pad is None else pad
    lo = np.floor(np.min(spheres[:, :2] - spheres[:, 2:3] - pad, axis=0)).astype(int)
    hi = np.ceil(np.max(spheres[:, :2] + spheres[:, 2:3] + pad, axis=0)).astype(int) + 1
    return max(lo[0], 0), max(lo[1], 0), min(hi[0], cols), min(hi[1], rows)


def background_basis(h: int, w: int, quadratic: bool) -> np.ndarray:
    """Columns (h*w, 3 or 6) of a group patch's background: a plane about the
    patch centre, with ``quadratic`` also its squares and product (scaled by
    the patch size)."""
    yy, xx = np.mgrid[0:h, 0:w]
    u, v = (xx - w / 2).ravel(), (yy - h / 2).ravel()
    B = np.column_stack([np.ones(h * w), u, v])
    return np.column_stack([B, (u / w) ** 2, u * v / (w * h), (v / h) ** 2]) if quadratic else B


def fit_group(a: np.ndarray, spheres: np.ndarray, blur: float, noise: float, mask_out=(), invalid=None,
              box=None, quadratic: bool = False):
    """Fit spheres (k, 4) jointly on ``a`` around them (on ``box``, else
    :func:`group_box`); returns (box, fitted (k, 4), sigma (k, 4), background
    coefficients (a plane, or with ``quadratic`` a quadratic surface), chi2,
    n pixels) or None (also for a group too large to hold, ``_MAX_ENTRIES``)."""
    c0, q0, c1, q1 = box if box is not None else group_box(a.shape, spheres, blur)
    if c1 - c0 < 6 or q1 - q0 < 6 or (c1 - c0) * (q1 - q0) * (4 * len(spheres) + 6) > _MAX_ENTRIES:
        return None
    roi = a[q0:q1, c0:c1].astype(np.float64)
    h, w = roi.shape
    yy, xx = np.mgrid[0:h, 0:w]
    wgt = mask_weights((c0, q0, c1, q1), mask_out, blur, invalid)
    wgt[clipped(roi)] = 0
    if wgt.sum() < 4 * len(spheres) + 10:
        return None
    s0 = spheres.copy()
    s0[:, 0] -= c0
    s0[:, 1] -= q0
    k = len(spheres)
    # the background's start from the patch's border, where the spheres are not
    edge = np.zeros((h, w), bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    edge &= wgt > 0
    B = background_basis(h, w, quadratic)
    on = edge.ravel()
    bg0 = np.linalg.lstsq(B[on], roi.ravel()[on], rcond=None)[0] if on.sum() > 2 * B.shape[1] else \
        np.r_[np.median(roi), np.zeros(B.shape[1] - 1)]
    wv = np.sqrt(wgt.ravel()) / noise

    def unpack(p):
        return p[:4 * k].reshape(k, 4), p[4 * k:]

    def residuals(p):
        sph, bg = unpack(p)
        return wv * (render((h, w), sph, blur).ravel() + B @ bg - roi.ravel())

    # the background's columns do not change: weighted once
    Jw = np.empty((h * w, 4 * k + B.shape[1]))
    Jw[:, 4 * k:] = wv[:, None] * B

    def jacobian(p):
        sph, _ = unpack(p)
        np.multiply(render_jacobian((h, w), sph, blur), wv[:, None], out=Jw[:, :4 * k])
        # (not a copy: the solver reads each Jacobian before it asks for the next)
        return Jw

    params = []
    for i, (x, y, R, mu) in enumerate(s0):
        params += [Parameter(f"x{i}", x, scale=0.1), Parameter(f"y{i}", y, scale=0.1),
                   Parameter(f"R{i}", R, scale=0.1), Parameter(f"mu{i}", max(mu, 1e-6), scale=max(mu, 1e-6) * 0.05)]
    params += [Parameter(f"b{j}", float(c)) for j, c in enumerate(bg0)]
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


def group_model(box, sph: np.ndarray, bg: np.ndarray, blur: float) -> np.ndarray:
    """A :func:`fit_group` model on its patch ``box``: the spheres (k, 4,
    frame px) plus the background (plane or quadratic coefficients ``bg``)."""
    return render_box(box, sph, blur) + background_image(box, bg)


def member_views(a: np.ndarray, fit, models: list) -> list[np.ndarray]:
    """Frame ``a`` over a :func:`fit_group` result's patch as each member
    alone would cast it: less the other members' ``models`` (each member's
    shadow over the patch). A clipped core (:func:`clipped`) says only "at
    least", so there a member sees its own model on the fitted background:
    less its neighbours' models, the clipped level pulled each centroid of a
    pair 0.3-2 px towards the other."""
    c0, q0, c1, q1 = fit[0]
    patch = a[q0:q1, c0:c1]
    total = np.sum(models, axis=0)
    cut = clipped(patch)
    bg = background_image(fit[0], fit[3])[cut] if cut.any() else None
    views = []
    for model in models:
        view = patch - (total - model)
        if bg is not None:
            view[cut] = model[cut] + bg
        views.append(view)
    return views


def background_image(box, bg: np.ndarray) -> np.ndarray:
    """A :func:`fit_group` background (plane or quadratic coefficients
    ``bg``) over its patch ``box``."""
    c0, q0, c1, q1 = box
    return (background_basis(q1 - q0, c1 - c0, len(bg) > 3) @ bg).reshape(q1 - q0, c1 - c0)


def joint_sigma(sig: np.ndarray, kappa: float) -> float:
    """A joint fit's isotropic centre σ (px) from its x, y σ (``sig[:2]``):
    the fit treats pixels as independent, so correlated noise (``kappa``)
    scales it; an undetermined fit's σ can be 1e200, whose square overflows."""
    return float(min(np.hypot(*np.minimum(np.abs(sig[:2]), 1e6)) / np.sqrt(2) * np.sqrt(kappa), 1e6))


def disc_misfit(a: np.ndarray, fit, blur: float, noise: float, mask_out=(), invalid=None) -> tuple[float, float]:
    """Mean squared residual per pixel, in units of the pixel noise's
    variance, of a :func:`fit_group` result on ``a``: on the spheres' discs
    (R + 2 blur + 1) and on the rest of its patch (inf when under 20
    pixels). On a background with structure of its own (a wall's edge a
    profile follows only roughly) the spheres explain their shadows when the
    first is no worse than the second. Quantum noise's variance grows as
    exp(attenuation), so a residual on a sphere is weighed by exp(-its
    model's attenuation above the background) (a steel sphere of 0.4 on a
    tube's wall read 4.1 against 2.4 around it, at a centre 0.08 px off)."""
    box, sph, _, bg, _, _ = fit
    c0, q0, c1, q1 = box
    h, w = q1 - q0, c1 - c0
    wgt = mask_weights(box, mask_out, blur, invalid)
    if len(sph) > 1:
        # (a model of two or more spheres holds what a clipped core may hide)
        wgt[clipped(a[q0:q1, c0:c1])] = 0
    spheres = render_box(box, sph, blur)
    z2 = ((a[q0:q1, c0:c1] - spheres - background_image(box, bg)) / noise) ** 2 * wgt \
        * np.exp(-np.clip(spheres, 0.0, 8.0))
    yy, xx = np.mgrid[q0:q1, c0:c1]
    on = np.zeros((h, w), bool)
    for x, y, R, _ in sph:
        on |= (xx - x) ** 2 + (yy - y) ** 2 <= (R + 2 * blur + 1) ** 2
    off = ~on & (wgt > 0)
    return (float(z2[on].mean()) if on.any() else np.inf), (float(z2[off].mean()) if off.sum() >= 20 else np.inf)


def odd_misfit(a: np.ndarray, fit, blur: float, noise: float, mask_out=(), invalid=None) -> float:
    """Mean squared odd part (under a half turn about the sphere's fitted
    centre) of a one-sphere :func:`fit_group` result's residual on ``a``, on
    its disc (R + 2 blur + 1), in units of the pixel noise's variance and
    doubled so that white noise reads 1 (a pixel and its mirror interpolated
    between four read somewhat less). A second sphere in the shadow, or
    anything beside it, leaves an odd residual; a profile the model shapes
    a little wrong (a display's curve, an intensifier's glare about the
    shadow) leaves an even one, which :func:`disc_misfit` counts too."""
    box, sph, _, bg, _, _ = fit
    c0, q0, c1, q1 = box
    wgt = mask_weights(box, mask_out, blur, invalid)
    spheres = render_box(box, sph, blur)
    res = ((a[q0:q1, c0:c1] - spheres - background_image(box, bg)) / noise).astype(np.float32)
    x, y, R = float(sph[0, 0] - c0), float(sph[0, 1] - q0), float(sph[0, 2])
    turn = cv2.getRotationMatrix2D((x, y), 180.0, 1.0)
    mirror = cv2.warpAffine(res, turn, (res.shape[1], res.shape[0]), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    mw = cv2.warpAffine(wgt.astype(np.float32), turn, (res.shape[1], res.shape[0]), flags=cv2.INTER_NEAREST)
    yy, xx = np.mgrid[0:res.shape[0], 0:res.shape[1]]
    on = ((xx - x) ** 2 + (yy - y) ** 2 <= (R + 2 * blur + 1) ** 2) & (wgt > 0) & (mw > 0) & np.isfinite(mirror)
    if on.sum() < 20:
        return np.inf
    odd = 0.5 * (res[on] - mirror[on]) * np.exp(-0.5 * np.clip(spheres[on], 0.0, 8.0))
    return float(2 * np.mean(odd.astype(np.float64) ** 2))


def components(n: int, pairs) -> np.ndarray:
    """Connected-component label of each of ``n`` nodes joined by ``pairs`` (i, j)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ij = np.array(list(pairs), int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def groups_of(blobs, blur: float) -> list[list[int]]:
    """Indices of blobs whose centroid windows meet, as connected groups of 2
    or more (ordered by their first member)."""
    n = len(blobs)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)
             if (blobs[i].x - blobs[j].x) ** 2 + (blobs[i].y - blobs[j].y) ** 2
             < window_reach(blobs[i].radius, blobs[j].radius, blur) ** 2]
    out: dict[int, list[int]] = {}
    for i, c in enumerate(components(n, pairs)):
        out.setdefault(int(c), []).append(i)
    return [g for g in out.values() if len(g) > 1]


def neighbours(b, blobs: list, peaks, opt, inside: float | None = None,
               r_peak: float | None = None) -> list:
    """(x, y, r) px of the shadows ``blobs`` (detect's Blob) and unmeasured
    candidate ``peaks`` (x, y) within reach of ``b``'s background patch, to
    be left out of its fit; ``b`` itself excluded. Peaks closer than
    ``inside`` px (default 0.8 of its radius; shadows: half of it) are its
    own; a peak's shadow is taken of radius ``r_peak`` px (default the
    largest nominal, ``opt.diameter_px``) and no shadow as larger than 1.5
    times that (a misshapen blob's moment radius is no shadow's size)."""
    reach = 5 * b.radius + 6 * opt.blur_px + 8
    r_peak = opt.diameter_px[1] / 2 if r_peak is None else r_peak
    near = [(o.x, o.y, min(o.radius, 1.5 * r_peak)) for o in blobs
            if o is not b and (0.5 * b.radius if inside is None else inside) < np.hypot(o.x - b.x, o.y - b.y) < reach]
    own = 0.8 * b.radius if inside is None else inside
    return near + [(px, py, r_peak) for px, py in peaks
                   if own < np.hypot(px - b.x, py - b.y) < reach
                   and all(np.hypot(px - o[0], py - o[1]) > 0.8 * o[2] for o in near)]
