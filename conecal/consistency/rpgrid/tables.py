"""rp-grid, stage 1: each view's table d/ds R[g_w](alpha, s) and what else is read off the frames.

Per view: the pixel-driven Radon transform of the cosine-weighted
projection on ``n_angles`` angles over [0, pi) and offsets s (mm, from the
tables' origin pixel, every ``offset_step_px`` pixels), differentiated
along s with a Gaussian of ``smooth_px`` pixels (float32; B-spline
coefficients along s for spline look-ups); optionally its noise variance
(arbitrary global scale, coarser); the region's truncated border stretches
and the convex hull of a dense holder (mm from the tables' origin). Frames
are read one at a time: memory is the tables, never the stack.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import correlate1d, spline_filter1d

from ...errors import InputError
from ...geometry import ConeGeometry
from .. import kernels
from ..radon import KERNEL_REACH, derivative_kernel, s_derivative
from .options import RPOptions, _lookup
from ...stats import difference_sigma


@dataclass
class ViewTables:
    """Per-view Radon-derivative tables of one scan."""

    tables: np.ndarray          # (n_views, n_a, n_s) float32
    s0: float                   # mm
    ds: float                   # mm
    ref: tuple                  # pixel coordinates (c, r) of the tables' origin
    rect: tuple                 # (c0, c1, r0, r1) region used, inclusive pixel indices
    edge_flags: np.ndarray      # (n_views, perimeter) bool: object at the region's border
    seconds: float
    holder_hulls: np.ndarray = None   # (n_views, V, 2) mm from ref; NaN where no holder
    # the tables' noise variance (arbitrary global scale), coarser: every
    # NOISE_ANGLE_STEP-th angle, every NOISE_S_STEP-th offset; None when not made
    variance: np.ndarray = None
    var_ds: float = 0.0

    @property
    def holder_views(self) -> int:
        return 0 if self.holder_hulls is None else int(np.isfinite(self.holder_hulls[:, 0, 0]).sum())

    @property
    def n_a(self) -> int:
        return self.tables.shape[1]

    @property
    def nbytes(self) -> int:
        return int(self.tables.nbytes + self.edge_flags.nbytes + (0 if self.variance is None else self.variance.nbytes))


def _view_table(img, g_weights: ConeGeometry, ref, rect, angles, s0, ds, n_s, smooth_px, order=2):
    c0, c1, r0, r1 = rect
    sub = np.ascontiguousarray(img[r0:r1 + 1, c0:c1 + 1], dtype=np.float32)
    pu, pv = g_weights.pixel_pitch
    pp = g_weights.principal_point
    D = abs(float(np.dot(g_weights.detector_origin - g_weights.source, g_weights.normal)))
    cr, rr = ref[0] - c0, ref[1] - r0
    weighted = kernels.cosine_weight(sub, pu, pv, cr, rr, (pp[0] - ref[0]) * pu, (pp[1] - ref[1]) * pv, D)
    radon = kernels.radon_joseph(weighted, pu, pv, cr, rr, np.cos(angles), np.sin(angles), s0, ds, n_s)
    return s_derivative(radon, ds, smooth_px * min(pu, pv) / ds, order)


NOISE_ANGLE_STEP, NOISE_S_STEP = 4, 2


def _view_variance(img, g_weights: ConeGeometry, ref, rect, angles, s0, ds, n_s, smooth_px, order=2):
    """Noise variance of one view's table, up to a global factor.

    Quantum-limited: a pixel's line integral p = -ln(I/I0) has variance
    proportional to 1/I = exp(p). The cosine weights enter squared, the
    Radon sums with squared weights and the covariance of neighbouring
    offsets' sums (:func:`kernels.radon_joseph_variance`), both through the
    s-derivative's taps. It varies slowly, so every NOISE_ANGLE_STEP-th angle
    and NOISE_S_STEP-th offset are kept.
    """
    c0, c1, r0, r1 = rect
    sub = np.asarray(img[r0:r1 + 1, c0:c1 + 1], np.float32)
    var = np.exp(np.clip(sub, -2.0, 20.0)).astype(np.float32)
    pu, pv = g_weights.pixel_pitch
    pp = g_weights.principal_point
    D = abs(float(np.dot(g_weights.detector_origin - g_weights.source, g_weights.normal)))
    cr, rr = ref[0] - c0, ref[1] - r0
    args = (pu, pv, cr, rr, (pp[0] - ref[0]) * pu, (pp[1] - ref[1]) * pv, D)
    var = kernels.cosine_weight(kernels.cosine_weight(var, *args), *args)
    a = angles[::NOISE_ANGLE_STEP]
    V, C = kernels.radon_joseph_variance(var, pu, pv, cr, rr, np.cos(a), np.sin(a), s0, ds, n_s)
    taps = derivative_kernel(smooth_px * min(pu, pv) / ds, order)
    # sum_j t_j R_(k+j): sum t_j^2 Var(R_(k+j)) + 2 sum t_j t_(j+1) Cov(R_(k+j), R_(k+j+1))
    lag = np.append(taps[:-1] * taps[1:], 0.0)
    out = (correlate1d(V, taps**2, axis=-1, mode="constant")
           + 2 * correlate1d(C, lag, axis=-1, mode="constant")) / ds**2
    return np.maximum(out[:, ::NOISE_S_STEP], 0.0)


def _edge_flags(img, rect, level):
    """Object present along the region's border: top, bottom (by column),
    left, right (by row), dilated by a few pixels."""
    c0, c1, r0, r1 = rect
    sub = img[r0:r1 + 1, c0:c1 + 1]
    ref = float(np.percentile(sub, 99.5))
    band = 3
    # mean over a few border pixels, against the noise of that mean: even a
    # faint cut (the thin tip of an object reaching out) makes lines inconsistent
    edges = [sub[:band].mean(axis=0), sub[-band:].mean(axis=0), sub[:, :band].mean(axis=1), sub[:, -band:].mean(axis=1)]
    border = np.concatenate(edges)
    noise = float(difference_sigma(np.diff(border), centre=False)) + 1e-12
    flags = border > max(level * ref, 4 * noise)
    # a few pixels of margin: a line grazing a flagged stretch is suspect
    k = 4
    return np.convolve(flags.astype(float), np.ones(2 * k + 1), mode="same") > 0


HULL_VERTICES = 32


def _holder_hull(img, rect, ratio: float):
    """Convex hull (pixel coordinates, region-relative) of a dense holder, or None.

    A holder is a part of the image that touches the region's border and is
    much denser than everything else: a border-touching connected region of
    pixels above half the view's high percentile whose median is at least
    ``ratio`` times the 99th percentile of the rest of the object.
    """
    import cv2

    c0, c1, r0, r1 = rect
    sub = np.asarray(img[r0:r1 + 1, c0:c1 + 1], np.float32)
    top = float(np.percentile(sub, 99.9))
    if top <= 0:
        return None
    dense = (sub > 0.5 * top).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(dense, connectivity=8)
    border = np.zeros(n, bool)
    for edge in (labels[0], labels[-1], labels[:, 0], labels[:, -1]):
        border[np.unique(edge)] = True
    border[0] = False
    if not border.any():
        return None
    holder = np.isin(labels, np.flatnonzero(border))
    if holder.sum() < 0.002 * holder.size:
        return None
    noise = float(difference_sigma(np.diff(sub[:4], axis=1), centre=False)) + 1e-12
    rest = sub[~cv2.dilate(holder.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)]
    rest = rest[rest > 5 * noise]
    # nothing else left: the object itself reaches the border (truncation, not a holder)
    if rest.size < 0.002 * sub.size or np.median(sub[holder]) < ratio * np.percentile(rest, 99):
        return None
    pts = cv2.findNonZero(holder.astype(np.uint8))
    hull = cv2.convexHull(pts)[:, 0, :].astype(float)
    if len(hull) > HULL_VERTICES:
        hull = hull[np.linspace(0, len(hull) - 1, HULL_VERTICES).round().astype(int)]
    return hull


def build_tables(images, n_views: int, g_weights: ConeGeometry, opt: RPOptions, progress=None,
                 noise: bool = False, keep_every: int = 1) -> ViewTables:
    """Tables for ``n_views`` frames yielded one at a time by ``images``
    (and their noise variance, with ``noise``). ``keep_every``: each view's
    table is made every ``offset_step_px`` and smoothed there, then every
    k-th offset kept (a third of the memory at k = 3; the 3 px smoothing
    leaves nothing a B-spline would miss between samples 2 px apart)."""
    if opt.kernel_order not in KERNEL_REACH:
        raise InputError(f"rp-grid: kernel_order must be 2 or 4, not {opt.kernel_order!r}")
    if not opt.offset_step_px > 0:
        raise InputError(f"rp-grid: offset_step_px must be positive, not {opt.offset_step_px!r}")
    _lookup(opt)  # bad input before any table is made
    rows, cols = g_weights.shape
    rect = tuple(int(x) for x in opt.crop) if opt.crop is not None else (0, cols - 1, 0, rows - 1)
    c0, c1, r0, r1 = rect
    if not (0 <= c0 < c1 < cols and 0 <= r0 < r1 < rows):
        raise InputError(f"crop {rect}: must satisfy 0 <= col0 < col1 < {cols} and 0 <= row0 < row1 < {rows}")
    pu, pv = g_weights.pixel_pitch
    ref = ((cols - 1) / 2, (rows - 1) / 2)
    ds = float(min(pu, pv)) * opt.offset_step_px
    half = np.hypot(max(ref[0] - c0, c1 - ref[0]) * pu, max(ref[1] - r0, r1 - ref[1]) * pv) + 4 * ds
    k = int(keep_every)
    n_half = int(np.ceil(half / ds / k)) * k   # s = 0 stays a kept sample
    n_s = 2 * n_half + 1
    s0 = -n_half * ds
    n_kept = len(range(0, n_s, k))
    angles = np.arange(opt.n_angles) * np.pi / opt.n_angles
    t0 = time.perf_counter()
    tables = np.empty((n_views, opt.n_angles, n_kept), np.float32)
    flags = np.empty((n_views, 2 * (c1 - c0 + 1) + 2 * (r1 - r0 + 1)), bool)
    # holder hulls in mm from the tables' origin, padded by repeating the last vertex
    hulls = np.full((n_views, HULL_VERTICES, 2), np.nan)
    variance = None
    if noise:
        n_av = len(angles[::NOISE_ANGLE_STEP])
        variance = np.empty((n_views, n_av, len(range(0, n_s, NOISE_S_STEP))), np.float32)
    for v, img in enumerate(images):
        table = _view_table(img, g_weights, ref, rect, angles, s0, ds, n_s, opt.smooth_px, opt.kernel_order)[:, ::k]
        tables[v] = spline_filter1d(table, 3, axis=-1, mode="mirror") if opt.interpolation == "spline" else table
        if noise:
            variance[v] = _view_variance(img, g_weights, ref, rect, angles, s0, ds, n_s, opt.smooth_px,
                                             opt.kernel_order)
        flags[v] = _edge_flags(img, rect, opt.truncation_level)
        if opt.exclude_holder:
            hull = _holder_hull(img, rect, opt.holder_ratio)
            if hull is not None:
                mm = np.column_stack([(hull[:, 0] + c0 - ref[0]) * pu, (hull[:, 1] + r0 - ref[1]) * pv])
                hulls[v, :len(mm)] = mm
                hulls[v, len(mm):] = mm[-1]
        if progress:
            progress(v + 1, n_views)
    if noise:
        variance /= np.median(variance[variance > 0])
    return ViewTables(tables, s0, ds * k, ref, rect, flags, time.perf_counter() - t0, hulls, variance,
                      ds * NOISE_S_STEP)
