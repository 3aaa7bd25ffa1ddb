"""Markerless detector misalignment of a circular scan from redundant plane integrals.

Every plane through two source positions of the trajectory is seen by both
views. By Grangeat's relation, the derivative of the object's plane
integral along the plane normal is, in each view,

    dRf/drho (m, m.S) = (D^2 + s_pp^2) / D^2 * d/ds R[g_w](alpha, s),

where ``g_w = g D / sqrt(D^2 + u^2 + v^2)`` is the cosine-weighted
projection, ``R`` its 2D Radon transform on the detector line where the
plane meets the detector, ``D`` the source-detector distance (along the
detector normal), ``s_pp`` the line's distance from the principal point and
``m`` the plane's unit normal (oriented towards the line's side). The two
views must agree; with a wrong detector geometry they map the plane to the
wrong lines and disagree. The cost ``c_RP`` is the sum of squared
disagreements over a fixed sample of planes.

How the work is split:

- each view's table ``d/ds R[g_w](alpha, s)`` is computed once (pixel-driven
  Radon transform, derivative of a Gaussian along s) with the nominal
  cosine weights and kept in float32; frames are read one at a time, so
  memory is the tables, never the stack;
- planes: random view pairs (at least ``min_separation_deg`` apart), and
  for each pair a fan of planes through both sources (rotating about the
  baseline), kept where they pass within the object's bounding sphere;
  planes whose line leaves either view's detector through a truncated edge
  (object present at the border: a long object, a wide object or a holder
  reaching out of the field of view) are dropped, automatically; where
  that leaves under half of them, pass 2 draws more pairs, and draws them
  at the separations where pass 1's planes survived (``separation_yield``);
- the five parameters are found by 2D grids over (shift u, eta),
  (shift v, theta), (theta, phi) and (shift v, theta) again, joint local
  refinements from a 3x3 pattern of tilts (the tilts barely change the
  cost and trade against the others), the 2D grids again, narrower, then a
  joint Newton refinement on the analytic gradient of the cost and its
  numerical Hessian (``refine``: Gauss-Newton's J^T J counts the noise's
  own slope and crept); sigma is the largest of the M-estimator's sandwich
  from that Hessian, a leave-views-out jackknife, the spread of disjoint
  batches of planes and of their minima along each range, times a factor
  per parameter calibrated on simulated scans (``SIGMA_FACTORS``).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy.ndimage import correlate1d, spline_filter1d

from ..errors import FitError, InputError
from ..geometry import ConeGeometry
from . import kernels
from .misalignment import NAMES, UNITS, misaligned
from .radon import KERNEL_REACH, derivative_kernel, s_derivative

FAN_STEP_DEG = 0.5     # the planes of a pair's fan: one every half degree about the baseline

# Each parameter's sigma is multiplied by this factor: the RMS of error/sigma
# over 20 simulated scans (seeds 200-219, four kinds) that are not the
# benchmark's 100-119. The sigma from the sandwich, jackknife, batches and
# profiles sees the noise of the planes but not the errors common to all of
# them (the tables' smoothing, cosine weights, truncation edges), which
# dominate: uncalibrated, the errors were 1.1-3.7 sigma RMS (u 3.70, v 1.06,
# eta 3.51, theta 2.40, phi 3.24; rounded up; measured with B-spline
# look-ups, Newton refinements and the restarts along v).
# `python benchmarks/bench_rpgrid.py --no-fdk --no-sharpness-search --first-seed 200 --uncalibrated-sigma`
SIGMA_FACTORS = {"shift_u_px": 3.7, "shift_v_px": 1.1, "eta_deg": 3.6, "theta_deg": 2.4, "phi_deg": 3.3}

DEFAULT_RANGES = {"shift_u_px": 20.0, "shift_v_px": 20.0, "eta_deg": 3.0, "theta_deg": 3.0, "phi_deg": 3.0}


@dataclass(frozen=True)
class RPOptions:
    n_angles: int = 360                 # table angles over [0, pi)
    offset_step_px: float = 1.0         # table offsets every this many pixels (0.5: twice the tables' time and size)
    smooth_px: float = 3.0              # Gaussian sigma of the s-derivative (px): less noise bias
    kernel_order: int = 2               # 4: the s-derivative's kernel also differentiates cubics exactly
    pairs: int = 1500                   # random view pairs (pass 2: more where truncation drops most planes)
    # Pass 2 draws more pairs (up to max_pairs_factor x) when pass 1 used
    # under this fraction of its candidate planes, and draws them at the
    # separations where pass 1's planes survived: transaxial truncation keeps
    # ~16 % of the planes, almost all from nearly opposite views, and drawn
    # uniformly a few hundred such pairs carried v, which then moved by half
    # a pixel with the draw (benchmark 16/20 -> 17/20, README "Which planes")
    min_used_fraction: float = 0.5
    max_pairs_factor: float = 4.0
    planes_per_pair: int = 48           # at most, evenly over the fan; its full step is FAN_STEP_DEG
    # Gaussian sigma (deg of the planes' angle about the pair's baseline) of a
    # smoothing along each pair's fan (0: off). Each view's table is smoothed
    # along its own pencil of planes, and the two views of one plane have
    # different pencils: on noiseless data that alone biases theta (-0.67 deg
    # at 3 px). Along the fan, both views average the same planes with the
    # same weights: with 1 px tables and 0.5-0.75 deg, theta is off by
    # < 0.06 deg (benchmarks/rpgrid_fan_smoothing.py). Off by default: at
    # 1e5 photons the thinner tables' noise outweighs it (RESULTS.md).
    fan_sigma_deg: float = 0.0
    min_separation_deg: float = 20.0
    ranges: dict = field(default_factory=lambda: dict(DEFAULT_RANGES))   # grid half-widths
    grid_steps: dict = field(default_factory=lambda: {"shift_u_px": 1.0, "shift_v_px": 1.0, "eta_deg": 0.25,
                                                      "theta_deg": 0.5, "phi_deg": 0.5})
    truncation_level: float = 0.005     # fraction of a view's high percentile marking "object at the border"
    crop: tuple | None = None           # manual (col0, col1, row0, row1), inclusive, optional
    exclude_truncated: bool = True
    exclude_holder: bool = True
    loss: str = "cauchy"                # planes near an edge the tables interpolate badly are outliers
    holder_ratio: float = 2.5           # a holder is this many times denser than the object
    motion_margin_px: float = 3.0       # lines this close to a truncated stretch or holder are dropped too
    grid_motion_px: tuple = (15.0, 8.0)  # the same margin during the two grid passes
    # Grangeat factors (D^2 + s^2)/D^2 fixed at the selection geometry
    # instead of following the candidate. s is measured from the principal
    # point, which a tilt of 1 deg moves by 10 mm, so fixed factors pull the
    # tilts towards where the planes were chosen (noiseless plain scan,
    # tables made 5 deg off in theta: theta -1.02 deg off fixed, -0.15
    # following; 20-scan benchmark with converged refinements, 1,500 pairs:
    # 15/20 following against 14/20 fixed).
    freeze_grangeat: bool = False
    # gradient evaluations allowed to each joint refinement (Newton steps on
    # a numerical Hessian, 11 evaluations each; see refine()); unconverged,
    # the CLI exits 1
    refine_max_nfev: int = 200
    # offsets (px) of v from which the final refinement starts again; the
    # lowest robust cost on one set of planes wins (see restart_along_v)
    v_restarts_px: tuple = (-0.5, -0.25, 0.25, 0.5)
    # the refinements' Hessian: "numerical" (Newton steps, see refine()) or
    # "gauss-newton" (J^T J, scipy's trust-region least squares; for
    # comparison: benchmarks/rpgrid_newton.py)
    hessian: str = "numerical"
    # the numerical Hessian's difference steps, in Gauss-Newton standard
    # deviations along the Gauss-Newton matrix's eigenvectors (core.solve)
    hessian_step: float = 2.0
    # table look-ups: cubic B-spline along s, prefiltered once (README
    # "Search"); or "cubic" (Catmull-Rom: its grids and whole-range scans
    # look up bilinearly, ~2x faster there, but its cost ripples along v),
    # "linear"
    interpolation: str = "spline"
    # divide each plane's disagreement by its noise sigma at the lines (see
    # RPProblem.noise_weighted); needs the second pass's noise tables
    noise_weights: bool = True
    grid_cost: str = "normalised"       # or "ssd"; normalised: sum (a-b)^2 / sum (a^2+b^2)
    sigma_factors: dict = field(default_factory=lambda: dict(SIGMA_FACTORS))   # see SIGMA_FACTORS
    undetermined_sigma: dict = field(default_factory=lambda: {"shift_u_px": 2.0, "shift_v_px": 2.0, "eta_deg": 0.5,
                                                              "theta_deg": 1.0, "phi_deg": 1.0})
    seed: int = 0


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
    noise = 1.4826 * float(np.median(np.abs(np.diff(border)))) / np.sqrt(2) + 1e-12
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
    noise = 1.4826 * float(np.median(np.abs(np.diff(sub[:4], axis=1)))) + 1e-12
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
                 noise: bool = False) -> ViewTables:
    """Tables for ``n_views`` frames yielded one at a time by ``images``
    (and their noise variance, with ``noise``)."""
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
    n_half = int(np.ceil(half / ds))
    n_s = 2 * n_half + 1
    s0 = -n_half * ds
    angles = np.arange(opt.n_angles) * np.pi / opt.n_angles
    t0 = time.perf_counter()
    tables = np.empty((n_views, opt.n_angles, n_s), np.float32)
    flags = np.empty((n_views, 2 * (c1 - c0 + 1) + 2 * (r1 - r0 + 1)), bool)
    # holder hulls in mm from the tables' origin, padded by repeating the last vertex
    hulls = np.full((n_views, HULL_VERTICES, 2), np.nan)
    variance = None
    if noise:
        n_av = len(angles[::NOISE_ANGLE_STEP])
        variance = np.empty((n_views, n_av, len(range(0, n_s, NOISE_S_STEP))), np.float32)
    for k, img in enumerate(images):
        tables[k] = _view_table(img, g_weights, ref, rect, angles, s0, ds, n_s, opt.smooth_px, opt.kernel_order)
        if opt.interpolation == "spline":
            tables[k] = spline_filter1d(tables[k], 3, axis=-1, mode="mirror")
        if noise:
            variance[k] = _view_variance(img, g_weights, ref, rect, angles, s0, ds, n_s, opt.smooth_px,
                                             opt.kernel_order)
        flags[k] = _edge_flags(img, rect, opt.truncation_level)
        if opt.exclude_holder:
            hull = _holder_hull(img, rect, opt.holder_ratio)
            if hull is not None:
                mm = np.column_stack([(hull[:, 0] + c0 - ref[0]) * pu, (hull[:, 1] + r0 - ref[1]) * pv])
                hulls[k, :len(mm)] = mm
                hulls[k, len(mm):] = mm[-1]
        if progress:
            progress(k + 1, n_views)
    if noise:
        variance /= np.median(variance[variance > 0])
    return ViewTables(tables, s0, ds, ref, rect, flags, time.perf_counter() - t0, hulls, variance,
                      ds * NOISE_S_STEP)


@dataclass
class _Frame:
    """Lab-frame detector quantities of one candidate geometry."""

    S: np.ndarray
    Q: np.ndarray       # lab point of the tables' origin pixel
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray       # unit normal, from the source towards the detector
    D: float
    pp: np.ndarray      # principal point, mm from the tables' origin along (u, v)


def _frame(g: ConeGeometry, ref) -> _Frame:
    Q = g.detector_point(*ref)
    w = g.normal
    D = float(np.dot(Q - g.source, w))
    if D < 0:
        w, D = -w, -D
    foot = g.source + D * w
    return _Frame(g.source, Q, g.u, g.v, w, D, np.array([np.dot(foot - Q, g.u), np.dot(foot - Q, g.v)]))


class _Planes(NamedTuple):
    """The planes of one evaluation, in look-up order (see RPProblem._arrays)."""

    vi: np.ndarray          # first view of each plane
    mi: np.ndarray          # its normal in that view's lab frame
    vj: np.ndarray          # second view, in its own look-up order
    mj: np.ndarray
    perm: np.ndarray        # second-view order -> residual order
    weight: np.ndarray
    Fi: np.ndarray | None   # frozen Grangeat factors
    Fj: np.ndarray | None
    fan: object = None      # sparse smoothing along each pair's fan, or None
    fan2: object = None     # its elementwise square (for the noise variance)


LOOKUPS = {"cubic": kernels.lookup_cubic, "spline": kernels.lookup_spline, "linear": kernels.lookup}


def _lookup(opt: RPOptions):
    """The refinements' table look-up of ``opt.interpolation``; InputError for an unknown one."""
    if opt.interpolation not in LOOKUPS:
        raise InputError(f"rp-grid: interpolation must be one of {sorted(LOOKUPS)}, not {opt.interpolation!r}")
    return LOOKUPS[opt.interpolation]


class RPProblem:
    """The redundant-plane cost of one scan as a function of the five parameters."""

    lookup = staticmethod(kernels.lookup_cubic)     # the tables' interpolation (see RPOptions.interpolation)
    coarse = False                                  # inside _bilinear: whole-range scans, unweighted

    def __init__(self, nominal: ConeGeometry, transforms, tables: ViewTables, axis_direction, opt: RPOptions,
                 pair_yield=None):
        """``pair_yield``: :meth:`separation_yield` of an earlier pass (bin
        edges in deg of the views' separation, used planes per pair, pairs);
        pairs are then drawn in proportion to the used planes per pair
        instead of uniformly."""
        self.nominal = nominal
        self.tab = tables
        self.opt = opt
        self.R = np.asarray(transforms.R, float)          # sample -> lab rotations per view
        Tinv = transforms.inverse()
        self.sources = Tinv.apply(np.broadcast_to(nominal.source, (len(self.R), 3)))   # sample frame
        self.axis = np.asarray(axis_direction, float) / np.linalg.norm(axis_direction)
        self.lookup = _lookup(opt)
        # B-spline tables hold coefficients, not samples: a bilinear look-up
        # of them would be a different (sharpened) function
        self.coarse_lookup = kernels.lookup_spline if opt.interpolation == "spline" else kernels.lookup
        self.pairs_by_yield = pair_yield is not None
        self._candidates(pair_yield)
        self.keep = np.ones(len(self.vi), bool)
        self._p_sel = np.zeros(5)
        self._kept = self._arrays(np.arange(len(self.vi)), self._p_sel)

    # -- the plane sample ------------------------------------------------------------------------------

    def _candidates(self, pair_yield=None):
        opt, g = self.opt, self.nominal
        rng = np.random.default_rng(opt.seed)
        n = len(self.R)
        rows, cols = g.shape
        sod = float(np.linalg.norm(g.source))
        # radius of the ball every view sees: the object's planes live inside it
        mag = g.sdd / max(sod, 1e-9)
        r_obj = np.hypot(cols * g.pixel_pitch[0], rows * g.pixel_pitch[1]) / 2 / mag
        self.r_obj = r_obj
        S = self.sources
        # weighted draws are thinned by each separation's yield over the
        # largest, so they start from 8x the uniform case's draws
        draws = 8 * opt.pairs if pair_yield is None else 64 * opt.pairs
        i = rng.integers(0, n, draws)
        j = rng.integers(0, n, draws)
        sep = self._separation(i, j)
        ok = sep >= opt.min_separation_deg
        if pair_yield is not None:
            # importance sampling: the pairs at separations whose planes
            # survive truncation (transaxial: nearly opposite views, whose
            # steep lines leave through untruncated edges) are the only ones
            # that inform, and the estimate's noise falls with their number
            edges, per_pair = pair_yield[:2]
            w = per_pair[np.clip(np.searchsorted(edges, sep, side="right") - 1, 0, len(per_pair) - 1)]
            ok &= rng.random(draws) * max(float(per_pair.max()), 1e-12) < w
        pairs = np.unique(np.stack([np.minimum(i, j)[ok], np.maximum(i, j)[ok]], axis=1), axis=0)
        pairs = pairs[rng.permutation(len(pairs))[:opt.pairs]]
        if len(pairs) == 0:
            raise InputError("rp-grid: no pair of views is far enough apart (is this a circular scan?)")
        i, j = pairs[:, 0], pairs[:, 1]
        b = S[j] - S[i]
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        e1 = self.axis - (b @ self.axis)[:, None] * b
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(b, e1)
        kappa = np.linspace(0, np.pi, round(180 / FAN_STEP_DEG), endpoint=False)
        normals = np.cos(kappa)[None, :, None] * e1[:, None] + np.sin(kappa)[None, :, None] * e2[:, None]
        rho = np.einsum("pkc,pc->pk", normals, S[i])
        vi, vj, ns, ks = [], [], [], []
        K = opt.planes_per_pair
        for p in range(len(pairs)):
            good = np.flatnonzero(np.abs(rho[p]) < r_obj)
            if good.size == 0:
                continue
            take = good[np.linspace(0, good.size - 1, min(K, good.size)).round().astype(int)]
            take = np.unique(take)
            vi.append(np.full(take.size, i[p]))
            vj.append(np.full(take.size, j[p]))
            ns.append(normals[p, take])
            ks.append(take)
        self.vi = np.concatenate(vi)
        self.vj = np.concatenate(vj)
        # the plane's step along its pair's fan (for the smoothing along it)
        self.fan_index = np.concatenate(ks)
        self.normals = np.concatenate(ns)
        self.n_pairs = len(pairs)
        # lab-frame normals per view are fixed: only the detector moves
        self.mi = np.einsum("pab,pb->pa", self.R[self.vi], self.normals)
        self.mj = np.einsum("pab,pb->pa", self.R[self.vj], self.normals)

    def _separation(self, i, j):
        """Angle (deg) between the sources of views ``i`` and ``j`` seen from the centre of their circle."""
        sod = float(np.linalg.norm(self.nominal.source))
        dist = np.linalg.norm(self.sources[j] - self.sources[i], axis=1)
        return 2 * np.degrees(np.arcsin(np.clip(dist / (2 * sod), 0, 1)))

    def separation_yield(self, bin_deg: float = 5.0):
        """(bin edges in deg, used planes per pair, pairs) in bins of the
        views' separation, for the current plane selection; bins without
        pairs read 0 planes per pair."""
        edges = np.arange(0.0, 180.0 + bin_deg, bin_deg)
        i, j = self.vi, self.vj
        pair = i * len(self.R) + j
        first = np.unique(pair, return_index=True)[1]
        sep_pair = self._separation(i[first], j[first])
        sep_used = self._separation(i[self.keep], j[self.keep])
        pairs = np.histogram(sep_pair, edges)[0]
        used = np.histogram(sep_used, edges)[0]
        return edges, np.where(pairs > 0, used / np.maximum(pairs, 1), 0.0), pairs

    def _lines(self, f: _Frame, m):
        a = m @ f.u
        b = m @ f.v
        c = m @ (f.Q - f.S)
        h = np.hypot(a, b)
        return a, b, c, h, np.arctan2(b, a), -c / h

    def select(self, p, motion_px: float | None = None, min_planes: int = 50) -> dict:
        """Keep the planes whose lines cross the region in both views and
        leave it through untruncated border stretches (at geometry ``p``)."""
        f = _frame(misaligned(self.nominal, p), self.tab.ref)
        keep = np.ones(len(self.vi), bool)
        truncated = np.zeros(len(self.vi), bool)
        # the derivative along s mixes lines up to 4-5 sigma away: they must be whole too
        # and as the search moves the geometry, lines move by a few pixels
        motion = self.opt.motion_margin_px if motion_px is None else motion_px
        margin = (KERNEL_REACH[self.opt.kernel_order] * self.opt.smooth_px + 1 + motion) * min(self.nominal.pixel_pitch)
        holder = np.zeros(len(self.vi), bool)
        for views, m in ((self.vi, self.mi), (self.vj, self.mj)):
            *_, alpha, s = self._lines(f, m)
            inside, trunc = self._exits(views, alpha, s)
            keep &= inside
            truncated |= trunc
            truncated |= self._band_truncated(views, alpha, s, margin)
            holder |= self._near_holder(views, alpha, s, margin)
        if self.opt.exclude_truncated:
            keep &= ~truncated
        if self.opt.exclude_holder:
            keep &= ~holder
        # planes that miss the object in both views carry only noise (and
        # noise whose size depends on where the lines fall: a bias)
        idx = np.flatnonzero(keep)
        empty = np.zeros(len(keep), bool)
        if idx.size:
            size = np.abs(self._look(f, self.vi[idx], self.mi[idx])[0]) + np.abs(self._look(f, self.vj[idx], self.mj[idx])[0])
            empty[idx[size < 0.01 * np.percentile(size, 99)]] = True
            keep &= ~empty
        self.keep = keep
        self._p_sel = np.array(p, float)
        self._kept = self._arrays(np.flatnonzero(keep), self._p_sel)
        if keep.sum() < min_planes:
            raise FitError(f"rp-grid: only {int(keep.sum())} usable planes after excluding truncated ones "
                           f"(of {len(keep)}); the object fills the field of view everywhere")
        self.last_selection = {"candidates": int(len(keep)), "used": int(keep.sum()),
                               "truncated": int(truncated.sum()), "holder": int(holder.sum()),
                               "empty": int(empty.sum()),
                               "holder_views": self.tab.holder_views}
        return self.last_selection

    def _near_holder(self, views, alpha, s, margin):
        """Whether each line passes within ``margin`` (mm) of its view's holder hull."""
        hulls = self.tab.holder_hulls
        if hulls is None:
            return np.zeros(len(s), bool)
        H = hulls[views]                                   # (n, V, 2)
        has = np.isfinite(H[:, 0, 0])
        if not has.any():
            return np.zeros(len(s), bool)
        d = H[has, :, 0] * np.cos(alpha[has])[:, None] + H[has, :, 1] * np.sin(alpha[has])[:, None] - s[has, None]
        out = np.zeros(len(s), bool)
        out[has] = (d.min(axis=1) < margin) & (d.max(axis=1) > -margin)
        return out

    def _exits(self, views, alpha, s):
        """Whether each line crosses the region, and whether it leaves through a flagged border stretch."""
        tab = self.tab
        c0, c1, r0, r1 = tab.rect
        pu, pv = self.nominal.pixel_pitch
        ca, sa = np.cos(alpha), np.sin(alpha)
        # the region's border in mm from the tables' origin
        ul, uh = (c0 - 0.5 - tab.ref[0]) * pu, (c1 + 0.5 - tab.ref[0]) * pu
        vl, vh = (r0 - 0.5 - tab.ref[1]) * pv, (r1 + 0.5 - tab.ref[1]) * pv
        ncol, nrow = c1 - c0 + 1, r1 - r0 + 1
        flags = tab.edge_flags[views]
        hits = np.zeros(len(s), int)
        trunc = np.zeros(len(s), bool)
        with np.errstate(divide="ignore", invalid="ignore"):
            # top (v = vl) and bottom (v = vh) edges: solve for u
            for vv, off in ((vl, 0), (vh, ncol)):
                uu = (s - vv * sa) / ca
                on = np.isfinite(uu) & (uu >= ul) & (uu <= uh)
                idx = np.clip(np.floor(np.nan_to_num((uu - ul) / pu)).astype(int), 0, ncol - 1)
                hits += on
                trunc |= on & flags[np.arange(len(s)), off + idx]
            for uu, off in ((ul, 2 * ncol), (uh, 2 * ncol + nrow)):
                vv = (s - uu * ca) / sa
                on = np.isfinite(vv) & (vv >= vl) & (vv <= vh)
                idx = np.clip(np.floor(np.nan_to_num((vv - vl) / pv)).astype(int), 0, nrow - 1)
                hits += on
                trunc |= on & flags[np.arange(len(s)), off + idx]
        return hits >= 2, trunc

    def _band_truncated(self, views, alpha, s, margin):
        """Whether any line parallel to each line within ``margin`` (mm)
        leaves the region through a flagged border stretch.

        The band's lines meet each side of the region in one interval; the
        flags within it are counted from per-view prefix sums, so the whole
        band costs what one line does."""
        tab = self.tab
        c0, c1, r0, r1 = tab.rect
        pu, pv = self.nominal.pixel_pitch
        ul, uh = (c0 - 0.5 - tab.ref[0]) * pu, (c1 + 0.5 - tab.ref[0]) * pu
        vl, vh = (r0 - 0.5 - tab.ref[1]) * pv, (r1 + 0.5 - tab.ref[1]) * pv
        ncol, nrow = c1 - c0 + 1, r1 - r0 + 1
        if getattr(self, "_flag_cum", None) is None:
            self._flag_cum = np.concatenate([np.zeros((len(tab.edge_flags), 1), np.int32),
                                             np.cumsum(tab.edge_flags, axis=1, dtype=np.int32)], axis=1)
        cum = self._flag_cum
        # a line parallel to a side meets it nowhere or all along it: a tiny
        # cosine sends the interval's ends far out, and the clip keeps the side
        ca = np.cos(alpha)
        sa = np.sin(alpha)
        ca = np.where(np.abs(ca) < 1e-12, 1e-12, ca)
        sa = np.where(np.abs(sa) < 1e-12, 1e-12, sa)
        out = np.zeros(len(s), bool)
        sides = ((vl, sa, ca, ul, uh, pu, 0, ncol), (vh, sa, ca, ul, uh, pu, ncol, ncol),
                 (ul, ca, sa, vl, vh, pv, 2 * ncol, nrow), (uh, ca, sa, vl, vh, pv, 2 * ncol + nrow, nrow))
        for fixed, k_fixed, k_free, lo, hi, pitch, off, n in sides:
            # side: coordinate `fixed` across it; the line meets it where the free coordinate is
            x1 = (s - margin - fixed * k_fixed) / k_free
            x2 = (s + margin - fixed * k_fixed) / k_free
            a, b = np.maximum(np.minimum(x1, x2), lo), np.minimum(np.maximum(x1, x2), hi)
            met = a <= b
            i0 = np.clip(np.floor((a - lo) / pitch), 0, n - 1).astype(int)
            i1 = np.clip(np.floor((b - lo) / pitch), 0, n - 1).astype(int)
            out |= met & (cum[views, off + i1 + 1] > cum[views, off + i0])
        return out

    # -- cost, residuals, Jacobian ------------------------------------------------------------------

    def _look(self, f: _Frame, views, m, F=None, dframes=None, variance=False):
        """Per plane of normals ``m`` seen by ``views``: the Grangeat factor
        times the table value, and with ``variance`` the noise variance of
        that value (F^2 times the noise table; the tables' global scale),
        both from one computation of the lines. With ``dframes`` also their
        derivatives along each parameter: returns (value, J, variance, J of
        the variance), else (value, variance); the variance's parts are None
        without ``variance``. With ``F`` given (frozen at the selection
        geometry, as the tables' cosine weights are), only the lines'
        positions depend on the geometry."""
        a, b, c, h, alpha, s = self._lines(f, m)
        ca, sa, spp = self._from_principal_point(f, a, b, h, s)
        frozen = F is not None
        if not frozen:
            F = self._grangeat_factor(f, spp)
        looks = [(self.lookup(self.tab.tables, views, alpha, s, self.tab.s0, self.tab.ds), F)]
        if variance:
            looks.append((kernels.lookup_cubic(self.tab.variance, views, alpha, s, self.tab.s0, self.tab.var_ds, 1.0),
                          F**2))
        vals = [w * T for (T, _, _), w in looks] + [None] * (2 - len(looks))
        if dframes is None:
            return vals[0], vals[1]
        Js = [np.empty((len(s), len(dframes))) for _ in looks] + [None] * (2 - len(looks))
        for k, df in enumerate(dframes):
            dalpha, dsl = self._line_derivatives(m, a, b, c, h, df)
            dF = 0.0 if frozen else self._grangeat_derivative(f, df, ca, sa, spp, dalpha, dsl)
            for power, ((T, T_a, T_s), w) in enumerate(looks, start=1):
                dw = dF if power == 1 else 2 * F * dF
                Js[power - 1][:, k] = dw * T + w * (T_a * dalpha + T_s * dsl)
        return vals[0], Js[0], vals[1], Js[1]

    @staticmethod
    def _grangeat_factor(f: _Frame, spp):
        """Grangeat's factor (D^2 + spp^2)/D^2 of lines ``spp`` (mm) from the principal point."""
        return 1.0 + spp**2 / f.D**2

    @staticmethod
    def _from_principal_point(f: _Frame, a, b, h, s):
        """cos and sin of the lines' normal angle, and their signed distance
        from the principal point (mm)."""
        ca, sa = a / h, b / h
        return ca, sa, s - (f.pp[0] * ca + f.pp[1] * sa)

    @staticmethod
    def _grangeat_derivative(f: _Frame, df: _Frame, ca, sa, spp, dalpha, dsl):
        """d/dparameter of the Grangeat factor 1 + spp^2/D^2 of lines at
        angle (cos, sin) = (ca, sa), ``spp`` from the principal point."""
        dspp = dsl - (df.pp[0] * ca + df.pp[1] * sa) - (-f.pp[0] * sa + f.pp[1] * ca) * dalpha
        return 2 * spp * dspp / f.D**2 - 2 * spp**2 * df.D / f.D**3

    @staticmethod
    def _line_derivatives(m, a, b, c, h, df: _Frame):
        """d(alpha), d(s) of the lines of normals ``m`` along one parameter
        (``df``: the detector quantities' derivatives)."""
        da = m @ df.u
        db = m @ df.v
        dc = m @ df.Q
        dh = (a * da + b * db) / h
        return (a * db - b * da) / h**2, -dc / h + c * dh / h**2

    def _dframes(self, p, f: _Frame, step=1e-6):
        """Derivatives of the lab detector quantities along each parameter."""
        out = []
        for k in range(5):
            q = np.array(p, float)
            q[k] += step
            fq = _frame(misaligned(self.nominal, q), self.tab.ref)
            out.append(_Frame(0, (fq.Q - f.Q) / step, (fq.u - f.u) / step, (fq.v - f.v) / step, 0,
                              (fq.D - f.D) / step, (fq.pp - f.pp) / step))
        return out

    def _arrays(self, idx, p, fan: bool = True) -> "_Planes":
        """Look-up order, weights and smoothing along the fans for the planes ``idx``.

        Residuals run in order of (view, angle) of their first view, and the
        second view's look-ups are made in their own (view, angle) order and
        put back: the tables are large, and walking them in order is several
        times faster than at random. Each plane is weighted by
        1 / (c + mean |value|) (values at ``p``; c their median): the
        interpolation error of a plane grows with its value, and a dense
        holder's planes would otherwise outweigh the object's. With ``fan``
        (whole pairs' planes; not the grids' random subsets) the
        disagreements are smoothed along each pair's fan (``_fan_matrix``)."""
        f = _frame(misaligned(self.nominal, p), self.tab.ref)
        key_i = self.vi[idx] * 4.0 * self.tab.n_a + (self._lines(f, self.mi[idx])[4] % (2 * np.pi))
        idx = idx[np.argsort(key_i, kind="stable")]
        key_j = self.vj[idx] * 4.0 * self.tab.n_a + (self._lines(f, self.mj[idx])[4] % (2 * np.pi))
        perm = np.argsort(key_j, kind="stable")
        vi, mi, vj, mj = self.vi[idx], self.mi[idx], self.vj[idx][perm], self.mj[idx][perm]
        Fi, Fj = (self._grangeat(f, mi), self._grangeat(f, mj)) if self.opt.freeze_grangeat else (None, None)
        W = self._fan_matrix(idx) if fan and self.opt.fan_sigma_deg > 0 else None
        size = np.abs(self._look(f, vi, mi, F=Fi)[0])
        size[perm] += np.abs(self._look(f, vj, mj, F=Fj)[0])
        size *= 0.5
        # c: a typical signal level, not the median: with truncation most
        # planes may miss the object, and noise-only planes must not set the scale
        weight = 1.0 / (np.percentile(size, 75) + size) if size.size else 1.0
        if self.tab.variance is not None and self.opt.noise_weights:
            # weights from the noisy values themselves correlate with the
            # noise at the lines and bias the answer (v by 0.3 px with a dense
            # holder at 1e5 photons); the noise sigma weights instead
            weight = np.ones(len(vi))
        return _Planes(vi, mi, vj, mj, perm, weight, Fi, Fj, W, None if W is None else W.multiply(W).tocsr())

    def _fan_matrix(self, idx):
        """Row-normalised Gaussian along each pair's fan over the planes ``idx``
        (in that order): sigma ``fan_sigma_deg`` of the planes' angle about
        the baseline; planes dropped by the selection are skipped, not filled."""
        from scipy import sparse

        sigma = self.opt.fan_sigma_deg
        reach = int(np.ceil(3 * sigma / FAN_STEP_DEG))
        pair = self.vi[idx].astype(np.int64) * len(self.R) + self.vj[idx]
        order = np.lexsort((self.fan_index[idx], pair))
        pair, k = pair[order], self.fan_index[idx][order]
        n = len(idx)
        rows, cols, vals = [np.arange(n)], [np.arange(n)], [np.ones(n)]
        for d in range(1, reach + 1):
            a = np.arange(n - d)
            dk = (k[a + d] - k[a]) * FAN_STEP_DEG
            ok = (pair[a + d] == pair[a]) & (dk <= 3 * sigma)
            w = np.exp(-0.5 * (dk[ok] / sigma) ** 2)
            rows += [a[ok], a[ok] + d]
            cols += [a[ok] + d, a[ok]]
            vals += [w, w]
        # positions in the sorted order -> positions in the residual order
        pos = np.asarray(order)
        W = sparse.csr_matrix((np.concatenate(vals), (pos[np.concatenate(rows)], pos[np.concatenate(cols)])),
                              shape=(n, n))
        return sparse.diags(1.0 / np.asarray(W.sum(axis=1)).ravel()) @ W

    def _grangeat(self, f: _Frame, m):
        a, b, _, h, _, s = self._lines(f, m)
        return self._grangeat_factor(f, self._from_principal_point(f, a, b, h, s)[2])

    def _residuals(self, p, arrays: "_Planes", energy=False):
        A = arrays
        f = _frame(misaligned(self.nominal, p), self.tab.ref)
        weighted = self.noise_weighted and not energy
        a, Va = self._look(f, A.vi, A.mi, F=A.Fi, variance=weighted)
        b, Vb = self._look(f, A.vj, A.mj, F=A.Fj, variance=weighted)
        out = a.copy()
        out[A.perm] -= b
        if A.fan is not None:
            out = A.fan @ out
        if not energy:
            if weighted:
                out /= np.sqrt(self._plane_variance(A, Va, Vb))
            return out * A.weight
        out *= A.weight
        bw = np.empty_like(b)
        bw[A.perm] = b
        if A.fan is not None:
            a, bw = A.fan @ a, A.fan @ bw
        return out, float(np.sum((a * A.weight) ** 2 + (bw * A.weight) ** 2))

    @property
    def noise_weighted(self) -> bool:
        """Whether residuals are divided by their noise sigma at the current lines.

        The expected squared disagreement of a plane is its signal part plus
        the two look-ups' noise variances, and those vary with where the
        lines fall (more attenuation, more noise): unweighted least squares
        move the lines towards quiet parts of the views, a bias of the order
        of the noise (0.5 px in v with a dense holder at 1e5 photons). Divided
        by the noise sigma at the lines themselves, every plane's noise part
        is 1 wherever they fall, and the bias is gone."""
        return (self.tab.variance is not None and self.opt.noise_weights and not self.coarse
                and self.lookup is not kernels.lookup)

    @staticmethod
    def _plane_variance(A: "_Planes", Vi, Vj, JVi=None, JVj=None):
        """Noise variance of each residual before weighting from the two
        look-ups' variances (and its Jacobian from theirs), through the
        smoothing along the fan (taken as independent between the fan's
        planes: their lines are pixels apart)."""
        Vi = Vi.copy()
        Vi[A.perm] += Vj
        if A.fan2 is not None:
            Vi = A.fan2 @ Vi
        if JVi is None:
            return np.maximum(Vi, 1e-12)
        JVi = JVi.copy()
        JVi[A.perm] += JVj
        if A.fan2 is not None:
            JVi = A.fan2 @ JVi
        return np.maximum(Vi, 1e-12), JVi

    def normalised_cost(self, p, arrays=None) -> float:
        """c_RP: the squared disagreement over the planes' squared values.

        Normalised, because a geometry that moves every line off the object
        makes both views read zero and agree perfectly; the grids must not
        find that."""
        r, e = self._residuals(p, self._kept if arrays is None else arrays, energy=True)
        return float(np.sum(r * r)) / e if e > 0 else np.inf

    def _residuals_key(self, p, A):
        # the planes by identity (held, so that no new arrays take their id)
        return np.asarray(p, float).tobytes(), A, self.lookup, self.coarse

    def residuals(self, p, arrays=None) -> np.ndarray:
        """Residuals at ``p``; after :meth:`jacobian` at the same ``p`` and
        planes, the ones it computed on the way (the Newton refinement asks
        for both at every point: core.solve evaluates the Jacobian first)."""
        A = self._kept if arrays is None else arrays
        key, r = self._last_residuals
        if key is not None and self._same_key(key, self._residuals_key(p, A)):
            return r.copy()
        return self._residuals(p, A)

    _last_residuals = (None, None)

    @staticmethod
    def _same_key(a, b):
        return a[0] == b[0] and a[1] is b[1] and a[2] is b[2] and a[3] == b[3]

    def jacobian(self, p, arrays=None) -> np.ndarray:
        A = self._kept if arrays is None else arrays
        f = _frame(misaligned(self.nominal, p), self.tab.ref)
        dfs = self._dframes(p, f)
        weighted = self.noise_weighted
        d, J, Vi, JVi = self._look(f, A.vi, A.mi, A.Fi, dfs, variance=weighted)
        b, Jj, Vj, JVj = self._look(f, A.vj, A.mj, A.Fj, dfs, variance=weighted)
        J[A.perm] -= Jj
        # the residuals, in the same operations as _residuals
        d[A.perm] -= b
        if A.fan is not None:
            d = A.fan @ d
            J = A.fan @ J
        if weighted:
            # r = d / sqrt(S): dr = dd / sqrt(S) - d dS / (2 S^1.5)
            S, JS = self._plane_variance(A, Vi, Vj, JVi, JVj)
            J = J / np.sqrt(S)[:, None] - (0.5 * d / S**1.5)[:, None] * JS
            d = d / np.sqrt(S)
        self._last_residuals = (self._residuals_key(p, A), d * A.weight)
        return J * np.reshape(A.weight, (-1, 1))

    def subset(self, n: int, seed: int = 0):
        """Look-up arrays of ``n`` of the kept planes at random (for the grids)."""
        kept = np.flatnonzero(self.keep)
        rng = np.random.default_rng(seed)
        return self._arrays(np.sort(rng.choice(kept, size=min(n, kept.size), replace=False)), self._p_sel, fan=False)

    def cost(self, p) -> float:
        return self.normalised_cost(p)


# -- the search ------------------------------------------------------------------------------------

# v, theta and phi are correlated (a wrong phi is partly taken up by theta,
# and theta by v), so each correlated pair shares a grid, and (v, theta)
# is looked at again after (theta, phi)
STAGES = (("shift_u_px", "eta_deg"), ("shift_v_px", "theta_deg"), ("theta_deg", "phi_deg"), ("shift_v_px", "theta_deg"))


@dataclass
class RPResult:
    x: np.ndarray
    fit: object                  # core.FitResult of the refinement
    grid_best: np.ndarray
    evaluations: int
    planes: dict
    slices: dict
    sigma_curvature: np.ndarray  # the sandwich H^-1 (sum g g^T) H^-1 of the fit (core.solve)
    sigma_jackknife: np.ndarray  # from leaving out blocks of views
    sigma: np.ndarray            # what is reported: sigma_uncalibrated times opt.sigma_factors
    cost_nominal: float
    cost_final: float
    seconds: dict
    pass1: np.ndarray = None     # estimate after the first pass (nominal cosine weights)
    sigma_slices: np.ndarray = None   # from batches' minima along each whole range
    sigma_batches: np.ndarray = None  # from disjoint batches of view pairs refined alone
    batch_estimates: np.ndarray = None
    at_bound: list = field(default_factory=list)
    restarted_from: np.ndarray | None = None   # pass 2's first answer, where a restart along v found a lower minimum
    sigma_uncalibrated: np.ndarray = None   # the largest of curvature, jackknife, batches and slices


def _grid(prob: RPProblem, p, names, centre_range, steps, subset, normalised=False):
    """Best point of a grid over ``names`` (others held at ``p``)."""
    idx = [NAMES.index(n) for n in names]
    axes = [c + np.arange(-np.floor(w / steps[n] + 1e-9), np.floor(w / steps[n] + 1e-9) + 1) * steps[n]
            for n, (c, w) in zip(names, centre_range)]
    best, best_q = np.inf, None
    n = 0
    for combo in np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(idx)):
        q = np.array(p, float)
        q[idx] = combo
        # (no BLAS here: its threads, left spinning, slow the numba look-ups tenfold)
        if normalised:
            c = prob.normalised_cost(q, subset)
        else:
            r = prob.residuals(q, subset)
            c = float(np.sum(r * r))
        n += 1
        if c < best:
            best, best_q = c, q
    return best_q, n


def _multistart(prob: RPProblem, opt: RPOptions, p, subset) -> tuple[np.ndarray, int]:
    from scipy.optimize import least_squares

    lo = np.array([-1.5 * opt.ranges[n] for n in NAMES])
    best, best_c, n = np.array(p, float), prob.normalised_cost(p, subset), 1
    steps = np.array([opt.grid_steps[x] for x in NAMES])
    for th in (-2 / 3, 0.0, 2 / 3):
        for ph in (-2 / 3, 0.0, 2 / 3):
            q0 = np.array(p, float)
            q0[3] = th * opt.ranges["theta_deg"]
            q0[4] = ph * opt.ranges["phi_deg"]
            r = least_squares(lambda q: prob.residuals(q, subset), q0, jac=lambda q: prob.jacobian(q, subset),
                              bounds=(lo, -lo), x_scale=steps, max_nfev=15, method="trf")
            n += r.nfev
            c = prob.normalised_cost(r.x, subset)
            if c < best_c:
                best, best_c = r.x, c
    return best, n


def grid_search(prob: RPProblem, opt: RPOptions, progress=None) -> tuple[np.ndarray, int]:
    """Grids over STAGES in turn, twice (the second pass narrower, around
    the first's answer), on a quarter of the planes: they only need the basin."""
    with _bilinear(prob):
        return _grid_passes(prob, opt, np.zeros(5), 0, progress)


@contextlib.contextmanager
def _bilinear(prob: RPProblem):
    """Bilinear look-ups (B-spline ones on B-spline tables) and no noise
    weights meanwhile: for scans of whole ranges, which need the cost's
    shape over pixels, not its smoothness within one."""
    final, prob.lookup, prob.coarse = prob.lookup, prob.coarse_lookup, True
    try:
        yield
    finally:
        prob.lookup, prob.coarse = final, False


def _grid_passes(prob: RPProblem, opt: RPOptions, p, evals, progress):
    for pass_ in range(2):
        # The grids move lines by up to the ranges: the first pass keeps well
        # clear of truncated borders and holders; the second, a narrower look
        # around the first's answer, chooses its planes there.
        prob.select(p, motion_px=opt.grid_motion_px[pass_])
        subset = prob.subset(max(2000, int(prob.keep.sum()) // 4), opt.seed + 1)
        for k, names in enumerate(STAGES):
            if pass_ == 0:
                cr = [(0.0, opt.ranges[n]) for n in names]
            else:
                cr = [(p[NAMES.index(n)], 6 * opt.grid_steps[n]) for n in names]
            p, n = _grid(prob, p, names, cr, opt.grid_steps, subset, opt.grid_cost == "normalised")
            evals += n
            if progress:
                progress(pass_ * len(STAGES) + k + 1, 2 * len(STAGES))
        if pass_ == 0:
            # The tilts barely change the cost and trade against v, u and eta:
            # grids one pair at a time can stall in a corner. Joint local
            # refinements from a 3x3 pattern of tilts pick the best basin.
            p, n = _multistart(prob, opt, p, subset)
            evals += n
    return p, evals


def _parameters(opt: RPOptions, p, undetermined: bool = True) -> list:
    """The five parameters for the least-squares core, bounded at 1.5x the grid ranges."""
    from ..fit.core import Parameter

    return [Parameter(n, float(p[k]), lower=-1.5 * opt.ranges[n], upper=1.5 * opt.ranges[n], unit=u,
                      scale=opt.grid_steps[n], undetermined_sigma=opt.undetermined_sigma[n] if undetermined else None)
            for k, (n, u) in enumerate(zip(NAMES, UNITS))]


def _pair_batches(prob: RPProblem, x, seed: int, batches: int) -> list:
    """Look-up arrays of ``batches`` disjoint random groups of whole view pairs
    (the planes of one pair share their two views' errors); groups under 100
    planes are left out."""
    kept = np.flatnonzero(prob.keep)
    _, inverse = np.unique(prob.vi[kept] * len(prob.R) + prob.vj[kept], return_inverse=True)
    group = np.random.default_rng(seed).permutation(inverse.max() + 1)[inverse] % batches
    arrays = [prob._arrays(kept[group == b], x) for b in range(batches)]
    return [a for a in arrays if len(a[0]) >= 100]


# residuals (in units of their median level) beyond which the robust loss flattens
F_SCALE = 3.0


def _solve(prob: RPProblem, opt: RPOptions, parameters, scale: float, arrays=None, **kw):
    """The core's robust Newton fit of the residuals (of ``arrays``, or the
    kept planes) divided by ``scale``."""
    from ..fit.core import solve

    return solve(parameters, lambda x: prob.residuals(x, arrays) / scale, lambda x: prob.jacobian(x, arrays) / scale,
                 loss=opt.loss, f_scale=F_SCALE, hessian=opt.hessian, hessian_step=opt.hessian_step,
                 scale_covariance=opt.hessian == "gauss-newton", **kw)


def refine(prob: RPProblem, opt: RPOptions, p):
    """Joint Newton refinement from ``p`` (planes chosen again at the start
    and once more at the answer, as truncated lines move with the
    geometry). Returns the core's FitResult and the residual scale used.

    The residuals are mostly noise, and the Jacobian carries the noise's own
    slope: Gauss-Newton's J^T J overstates the cost's curvature ~40x along
    the (v, theta) valley, and its steps crept there for hundreds of
    evaluations (plain scan 116: 200 evaluations, 29 s, unconverged). Newton
    steps on a numerical Hessian reach the same minimum in ~5 iterations
    (the same scan: 3.6 s; core.solve's ``hessian``)."""
    prob.select(p)
    r = prob.residuals(p)
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r)))) or 1.0
    fit = None
    for _ in range(2):
        fit = _solve(prob, opt, _parameters(opt, p), scale, max_nfev=opt.refine_max_nfev, tol=1e-10)
        p = fit.x
        prob.select(p)
    return fit, scale


def restart_along_v(prob: RPProblem, opt: RPOptions, fit, scale: float):
    """The lowest of the minima reached from the refinement's answer with v
    moved by ``opt.v_restarts_px``, all on the planes chosen at the answer;
    if one is lower than the answer's, the refinement runs again from it.
    Returns (fit, scale, evaluations spent here: the answer's own minimum
    on those planes, the restarts and any new refinement).

    Where truncation leaves few planes that see v (a transaxially truncated
    object: only near-vertical lines avoid both side borders, and they
    barely move with v), the cost along v has minima 0.4-1 px apart, and
    the refinement stops in whichever it reaches first: of three
    transaxial scans whose v missed by 0.5-1.2 px, two had a lower minimum
    near the truth (RESULTS.md).
    """
    if not opt.v_restarts_px:
        return fit, scale, 0
    k = NAMES.index("shift_v_px")
    fits = [_solve(prob, opt, _parameters(opt, fit.x), scale, max_nfev=opt.refine_max_nfev, tol=1e-10)]
    for dv in opt.v_restarts_px:
        q = np.array(fit.x, float)
        q[k] = np.clip(q[k] + dv, -1.5 * opt.ranges["shift_v_px"], 1.5 * opt.ranges["shift_v_px"])
        fits.append(_solve(prob, opt, _parameters(opt, q), scale, max_nfev=opt.refine_max_nfev, tol=1e-10))
    evals = sum(f.nfev for f in fits)
    best = min(fits[1:], key=lambda f: f.cost)
    # the same minimum reached twice differs in its cost by rounding only
    if best.cost >= fits[0].cost - 1e-6 * abs(fits[0].cost) or not best.success:
        return fit, scale, evals
    new, scale = refine(prob, opt, best.x)
    return new, scale, evals + new.nfev


def finish(prob: RPProblem, opt: RPOptions, fit, scale, grid_best, evals, seconds) -> RPResult:
    x = fit.x
    # A parameter on its search bound was not found, whatever its curvature
    # says; nor are those strongly correlated with it. The jackknife and
    # the profiles hold it where it is.
    at_bound = [k for k, n in enumerate(NAMES) if abs(x[k]) >= 1.5 * opt.ranges[n] * 0.999]
    interior = np.ones(5, bool)
    interior[at_bound] = False
    J, psi, w = _plane_gradients(prob, opt, x, scale)
    A = (J * w[:, None]).T @ J
    jack = jackknife_sigma(prob, A if fit.hessian is None else fit.hessian, J, psi, interior)
    # The Gauss-Newton covariance, not the sandwich, for which parameters
    # follow which: along an undetermined tilt the Hessian is nearly
    # singular, and its inverse ties every parameter to the tilt (holder
    # 117, theta on its bound: all five had |correlation| > 0.7; axial 118:
    # u's profile ran along theta's flat valley, u sigma 4.7 px for an
    # error of 0.01 px)
    gn = np.linalg.pinv(A)
    gn_interior = np.zeros((5, 5))
    gn_interior[np.ix_(interior, interior)] = np.linalg.pinv(A[np.ix_(interior, interior)])
    batch, spread = batch_sigma(prob, opt, x, scale)
    with _bilinear(prob):
        lumpy = slice_sigma(prob, opt, x, covariance=gn_interior)
        slices = cost_slices(prob, x, opt)
    raw = np.fmax(np.fmax(np.fmax(np.array(fit.sigma), jack), batch), lumpy)
    sigma = raw * np.array([opt.sigma_factors[n] for n in NAMES])
    res = RPResult(x=x, fit=fit, grid_best=grid_best, evaluations=evals + fit.nfev, planes=dict(prob.last_selection),
                   slices=slices, sigma_curvature=np.array(fit.sigma), sigma_jackknife=jack,
                   sigma=sigma, cost_nominal=prob.cost(np.zeros(5)), cost_final=prob.cost(x), seconds=seconds,
                   sigma_slices=lumpy, sigma_batches=batch, batch_estimates=spread, sigma_uncalibrated=raw)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.nan_to_num(gn / np.sqrt(np.outer(np.diag(gn), np.diag(gn))))
    lost = set(at_bound)
    for k in at_bound:
        lost.update(int(j) for j in np.flatnonzero(np.abs(corr[k]) > 0.7))
    res.at_bound = [NAMES[k] for k in at_bound]
    for k in lost:
        res.sigma[k] = np.inf
    return res


def slice_sigma(prob: RPProblem, opt: RPOptions, x, batches: int = 5, n: int = 41, covariance=None) -> np.ndarray:
    """Sigma from where disjoint batches of planes put each parameter's
    minimum along its whole search range.

    A local sigma cannot see a cost that is flat over many pixels with
    shallow spurious dips (a tilt or the v shift when truncation leaves few
    informative planes); batches of planes then put their minima far apart.
    Each minimum is refined by a parabola through its grid neighbours.

    With ``covariance`` (Gauss-Newton's at ``x``) each parameter is also moved
    along its profile, the line on which the others follow it as they would
    if refined (column k of the covariance over its diagonal entry), and
    the larger of the two spreads is returned. Theta and v are correlated
    (a tilt about u is to first order a v shift), and with v held the cost
    rises along theta at once: on benchmark scans whose theta missed by
    1-2.5 deg the held slices gave 0.003-0.19 deg and the profiles
    0.93-1.42 deg; on scans where theta was right both stayed at zero.
    """
    arrays = _pair_batches(prob, x, opt.seed + 11, batches)
    x0 = np.asarray(x, float)
    out = np.full(5, np.nan)
    if len(arrays) < 3:
        return out
    for k, name in enumerate(NAMES):
        grid = np.linspace(-1.5 * opt.ranges[name], 1.5 * opt.ranges[name], n)
        step = grid[1] - grid[0]
        directions = [np.eye(5)[k]]
        if covariance is not None and np.isfinite(covariance[k]).all() and covariance[k, k] > 0:
            directions.append(np.asarray(covariance[k], float) / covariance[k, k])
        for direction in directions:
            mins = []
            for arr in arrays:
                c = np.array([prob.normalised_cost(x0 + (val - x[k]) * direction, arr) for val in grid])
                i = int(np.argmin(c))
                m = grid[i]
                if 0 < i < n - 1:
                    den = c[i - 1] - 2 * c[i] + c[i + 1]
                    if den > 0:
                        m += 0.5 * step * (c[i - 1] - c[i + 1]) / den
                mins.append(m)
            mins = np.array(mins)
            # the grid's own resolution is not an uncertainty of the estimate
            out[k] = np.fmax(out[k], max(float(mins.std(ddof=1)) / np.sqrt(len(mins)) - 0.25 * step, 0.0))
    return out


def batch_sigma(prob: RPProblem, opt: RPOptions, x, scale: float, batches: int = 5):
    """Sigma from disjoint batches of view pairs, each refined on its own.

    Interpolation errors of the tables at strong edges are systematic
    within a plane but differ between planes, and can make the cost of a
    weak parameter (a tilt) lumpy; neither the curvature nor leaving out
    views sees that. The batch estimates' standard deviation, divided by
    sqrt(number of batches) for their mean, does.
    Returns (sigma, the batch estimates).
    """
    estimates = []
    for arrays in _pair_batches(prob, x, opt.seed + 7, batches):
        f = _solve(prob, opt, _parameters(opt, x, undetermined=False), scale, arrays, max_nfev=60, tol=1e-8)
        estimates.append(f.x)
    if len(estimates) < 3:
        return np.full(5, np.nan), np.zeros((0, 5))
    est = np.array(estimates)
    return est.std(axis=0, ddof=1) / np.sqrt(len(est)), est


def _plane_gradients(prob: RPProblem, opt: RPOptions, x, scale: float):
    """At ``x``, per kept plane: the Jacobian of the residuals divided by
    ``scale``, rho'(r) r (the plane's share of the robust cost's gradient
    is its row times this) and rho'(r) (its Gauss-Newton weight)."""
    from ..fit.core import robust_loss

    # the Jacobian first: the residuals then come from its pass
    J = prob.jacobian(x) / scale
    r = prob.residuals(x) / scale
    w = robust_loss(r * r / F_SCALE**2, opt.loss)[1]
    return J, w * r, w


def jackknife_sigma(prob: RPProblem, H, J, psi, free, groups: int = 12) -> np.ndarray:
    """Sigma from leaving out contiguous blocks of views in turn.

    The residuals of one view share its noise and its interpolation errors,
    so the curvature, which treats every plane as independent, is
    optimistic. Each block's estimate is one Newton step from the fit's
    answer on the robust cost's gradient without the planes that touch the
    block (``J``, ``psi``: :func:`_plane_gradients`) and the fit's Hessian
    ``H`` scaled by the fraction of planes kept, over the parameters
    ``free`` only. A Gauss-Newton step would take J^T J for the curvature,
    which the noise's own slope inflates (see refine()). A block whose
    planes carry a fraction f of the information moves the estimate with
    variance var * f / (1 - f).
    """
    vi, vj, perm = prob._kept.vi, prob._kept.vj, prob._kept.perm
    vj_res = np.empty_like(vj)
    vj_res[perm] = vj
    n_views = len(prob.R)
    block_i = vi * groups // n_views
    block_j = vj_res * groups // n_views
    Hf = H[np.ix_(free, free)]
    devs = []
    for g in range(groups):
        keep = (block_i != g) & (block_j != g)
        f = 1.0 - keep.mean()
        if f <= 0 or keep.sum() < 10 * J.shape[1]:
            continue
        step = np.zeros(J.shape[1])
        step[free] = -np.linalg.lstsq(Hf * (1.0 - f), (J[keep].T @ psi[keep])[free], rcond=None)[0]
        devs.append(step**2 * (1 - f) / f)
    if not devs:
        return np.full(5, np.nan)
    return np.sqrt(np.mean(devs, axis=0))


def cost_slices(prob: RPProblem, x, opt: RPOptions, n: int = 41) -> dict:
    """The cost along each parameter through ``x`` (the others held), over
    the grid range's width centred on ``x`` (the paper's Figures 7 and 8)."""
    out = {}
    for k, name in enumerate(NAMES):
        vals = x[k] + np.linspace(-opt.ranges[name], opt.ranges[name], n)
        costs = []
        for val in vals:
            q = np.array(x, float)
            q[k] = val
            costs.append(prob.cost(q))
        out[name] = {"values": vals.tolist(), "cost": costs}
    return out


# -- a scan in, a geometry document out ----------------------------------------------------------

def check_scan(scan) -> np.ndarray:
    """The rotary axis direction of a circular scan; InputError otherwise."""
    cfg = scan.config
    if cfg.motion != "circular":
        raise InputError(f"{scan.root / 'scan.yaml'}: motion: rp-grid needs a circular scan, not {cfg.motion!r}")
    rotary = [a for a in cfg.axes if a.type == "rotary"]
    if len(rotary) != 1 or len(cfg.axes) != 1:
        raise InputError(f"{scan.root / 'scan.yaml'}: axes: a circular scan has exactly one rotary axis")
    if scan.n_frames < 36:
        raise InputError(f"{scan.root / cfg.log}: {scan.n_frames} frames; rp-grid needs at least 36 views")
    return np.asarray(rotary[0].direction, float)


def sparse_selection(opt: RPOptions, selection: dict) -> bool:
    """Whether a pass used under ``min_used_fraction`` of its candidate planes."""
    return selection["used"] < opt.min_used_fraction * selection["candidates"]


def pass2_pairs(opt: RPOptions, selection: dict, pair_yield=None) -> int:
    """View pairs of pass 2: ``opt.pairs``, or more (at most
    ``max_pairs_factor`` times) so that the used planes reach
    ``min_used_fraction`` of pass 1's candidates. With ``pair_yield``
    (:meth:`RPProblem.separation_yield`), the pairs are drawn in proportion
    to their yield, and each brings sum(n y^2) / sum(n y) planes."""
    if not sparse_selection(opt, selection):
        return opt.pairs
    used, want = selection["used"], opt.min_used_fraction * selection["candidates"]
    if pair_yield is None:
        per_pair = used / opt.pairs
    else:
        _, y, n = pair_yield
        per_pair = float(np.sum(n * y * y) / max(np.sum(n * y), 1e-12))
    return int(min(np.ceil(want / max(per_pair, 1e-12)), opt.max_pairs_factor * opt.pairs))


def run(scan, opt: RPOptions, progress=None) -> tuple[RPResult, RPProblem]:
    """rp-grid on a loaded circular scan, in two passes over the stack.

    Pass 1: tables of every other view (at most ~180) with the nominal
    cosine weights; grids and a first refinement. Pass 2: tables of every
    view with the cosine weights of pass 1's geometry (a 2 deg tilt moves
    the principal point by ~20 mm, and the weights' error would mimic a
    tilt) and more view pairs where pass 1 used few of its planes
    (``pass2_pairs``), then the final refinement and sigma. Frames are read one at a
    time in each pass.
    """
    axis = check_scan(scan)
    nominal = scan.nominal_geometry()
    frames = [int(k) for k in scan.log.frame]
    n = len(frames)
    T_all = scan.nominal_transforms()
    step = max(1, n // 180)
    first = np.arange(0, n, step)
    total = len(first) + n + 20

    def images(idx):
        for k in idx:
            yield scan.stack.read(frames[k])

    def prog(offset):
        def cb(done, of):
            if progress:
                progress(offset + done, total)
        return cb

    # the cheap test first: a few views tell whether any plane is usable at all
    # (an object filling the field of view), before the tables of the whole scan
    probe = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(int))
    try:
        RPProblem(nominal, T_all[probe], build_tables(images(probe), len(probe), nominal, opt), axis,
                  opt).select(np.zeros(5), min_planes=1)
    except FitError as exc:
        raise FitError(f"{exc} (seen on {len(probe)} views, before the tables of all {n})") from None
    t0 = time.perf_counter()
    tab1 = build_tables(images(first), len(first), nominal, opt, progress=prog(0))
    prob1 = RPProblem(nominal, T_all[first], tab1, axis, opt)
    t1 = time.perf_counter()
    p_grid, evals = grid_search(prob1, opt, progress=lambda d, o: progress and progress(len(first) + round(10 * d / o), total))
    fit1, _ = refine(prob1, opt, p_grid)
    pair_yield = prob1.separation_yield() if sparse_selection(opt, prob1.last_selection) else None
    opt2 = replace(opt, pairs=pass2_pairs(opt, prob1.last_selection, pair_yield))
    del prob1, tab1
    t2 = time.perf_counter()
    tab2 = build_tables(images(range(n)), n, misaligned(nominal, fit1.x), opt, progress=prog(len(first) + 10),
                        noise=opt.noise_weights)
    prob = RPProblem(nominal, T_all, tab2, axis, opt2, pair_yield)
    t3 = time.perf_counter()
    fit, scale = refine(prob, opt2, fit1.x)
    before = fit
    fit, scale, restarts = restart_along_v(prob, opt2, fit, scale)
    res = finish(prob, opt2, fit, scale, p_grid, evals + fit1.nfev + restarts,
                 {"tables_pass1": t1 - t0, "search_pass1": t2 - t1, "tables_pass2": t3 - t2})
    res.seconds["refine_pass2"] = time.perf_counter() - t3
    res.seconds["total"] = time.perf_counter() - t0
    res.pass1 = fit1.x
    res.restarted_from = None if fit is before else np.array(before.x)
    if progress:
        progress(total, total)
    return res, prob


def document(res: RPResult, prob: RPProblem, scan, opt: RPOptions) -> dict:
    """The ``conecal-geometry/1`` document of an rp-grid run."""
    from ..fit.output import GEOMETRY_FORMAT
    from .. import __version__
    from ..jsonio import rounded

    g = misaligned(prob.nominal, res.x)
    undetermined = [n for n, s in zip(NAMES, res.sigma) if not np.isfinite(s) or s > opt.undetermined_sigma[n]]
    params = {}
    for k, (n, u) in enumerate(zip(NAMES, UNITS)):
        params[n] = {"index": k, "initial": 0.0, "free": True, "value": float(res.x[k]),
                     "sigma": float(res.sigma[k]) if np.isfinite(res.sigma[k]) else None, "unit": u,
                     "sigma_curvature": float(res.sigma_curvature[k]), "sigma_jackknife": float(res.sigma_jackknife[k]),
                     "sigma_batches": float(res.sigma_batches[k]), "sigma_slices": float(res.sigma_slices[k]),
                     "sigma_uncalibrated": float(res.sigma_uncalibrated[k]),
                     "sigma_factor": float(opt.sigma_factors[n]),
                     "grid": float(res.grid_best[k]), "determined": n not in undetermined}
    axes = [{"name": a.name, "type": a.type, "direction": list(a.direction),
             "point": list(a.point) if a.point is not None else [0.0, 0.0, 0.0]} for a in scan.config.axes]
    free = list(NAMES)
    corr = res.fit.correlation
    doc = {
        "format": GEOMETRY_FORMAT, "software": f"conecal {__version__}", "stage": "rp-grid", "scan": str(scan.root),
        **g.to_dict(), "axes": axes,
        "misalignment": params,
        "fit": {
            "method": "redundant plane integrals (Grangeat), grids then Newton",
            "parameters": params,
            "correlation": {"names": free, "matrix": np.where(np.isfinite(corr), corr, 0.0)},
            "undetermined": undetermined,
            "at_search_bound": list(res.at_bound),
            "cost_nominal": res.cost_nominal, "cost_final": res.cost_final,
            "cost_reduction": res.cost_nominal / res.cost_final if res.cost_final > 0 else None,
            "chi2_reduced": res.fit.reduced_chi2,
            "planes": {**res.planes, "pairs": prob.n_pairs, "planes_per_pair": opt.planes_per_pair,
                       "pairs_drawn": "by separation yield" if prob.pairs_by_yield else "uniformly",
                       "min_separation_deg": opt.min_separation_deg},
            "tables": {"views": int(prob.tab.tables.shape[0]), "angles": opt.n_angles,
                       "offsets": int(prob.tab.tables.shape[2]), "ds_mm": prob.tab.ds, "smooth_px": opt.smooth_px,
                       "kernel_order": opt.kernel_order, "fan_sigma_deg": opt.fan_sigma_deg,
                       "interpolation": opt.interpolation,
                       "region": list(prob.tab.rect), "megabytes": prob.tab.nbytes / 1e6},
            "ranges": dict(opt.ranges), "grid_steps": dict(opt.grid_steps),
            "evaluations": res.evaluations,
            "seconds": res.seconds,
            "converged": bool(res.fit.success),
            "grangeat_factors": "fixed" if opt.freeze_grangeat else "following",
            # a lower minimum found by a restart means the cost has several
            # along v (README "Restarts along v")
            "restarts_along_v": {"offsets_px": list(opt.v_restarts_px),
                                 "moved_from": None if res.restarted_from is None
                                 else dict(zip(NAMES, map(float, res.restarted_from)))},
        },
        "cost_slices": res.slices,
        "units": {"length": "mm", "angle": "deg", "shift": "px of the nominal detector"},
    }
    return rounded(doc)
