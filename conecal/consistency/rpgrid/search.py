"""rp-grid, stage 4: the search for the five parameters.

2D grids over correlated pairs (``STAGES``) on a quarter of the planes,
joint local refinements from a 3x3 pattern of tilts, the grids again
(narrower), then the joint robust Newton refinement of the core
(``refine``) and restarts along v (``restart_along_v``). Parameters:
shift u, v (px), eta, theta, phi (deg); bounds at 1.5x ``RPOptions.ranges``.
"""

from __future__ import annotations

import contextlib

import numpy as np

from ...geometry.misalignment import NAMES, UNITS
from .cost import RPProblem
from .options import RPOptions
from ...stats import mad_sigma

# -- the search ------------------------------------------------------------------------------------

# v, theta and phi are correlated (a wrong phi is partly taken up by theta,
# and theta by v), so each correlated pair shares a grid, and (v, theta)
# is looked at again after (theta, phi)
STAGES = (("shift_u_px", "eta_deg"), ("shift_v_px", "theta_deg"), ("theta_deg", "phi_deg"), ("shift_v_px", "theta_deg"))


def _grid(prob: RPProblem, p, names, centre_range, steps, subset):
    """Best point of a grid over ``names`` (others held at ``p``), by the
    normalised cost sum (a-b)^2 / sum (a^2+b^2) (the plain sum of squares
    lost its benchmark: benchmarks/RESULTS.md, tag rpgrid-experiments)."""
    idx = [NAMES.index(n) for n in names]
    axes = [c + np.arange(-np.floor(w / steps[n] + 1e-9), np.floor(w / steps[n] + 1e-9) + 1) * steps[n]
            for n, (c, w) in zip(names, centre_range)]
    best, best_q = np.inf, None
    n = 0
    for combo in np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(idx)):
        q = np.array(p, float)
        q[idx] = combo
        # (no BLAS here: its threads, left spinning, slow the numba look-ups tenfold)
        c = prob.normalised_cost(q, subset)
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
            p, n = _grid(prob, p, names, cr, opt.grid_steps, subset)
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
    from ...fit.core import Parameter

    return [Parameter(n, float(p[k]), lower=-1.5 * opt.ranges[n], upper=1.5 * opt.ranges[n], unit=u,
                      scale=opt.grid_steps[n], undetermined_sigma=opt.undetermined_sigma[n] if undetermined else None)
            for k, (n, u) in enumerate(zip(NAMES, UNITS))]


# residuals (in units of their median level) beyond which the robust loss flattens
F_SCALE = 3.0


def _solve(prob: RPProblem, opt: RPOptions, parameters, scale: float, arrays=None, **kw):
    """The core's robust Newton fit of the residuals (of ``arrays``, or the
    kept planes) divided by ``scale``."""
    from ...fit.core import solve

    return solve(parameters, lambda x: prob.residuals(x, arrays) / scale, lambda x: prob.jacobian(x, arrays) / scale,
                 loss=opt.loss, f_scale=F_SCALE, hessian="numerical", hessian_step=opt.hessian_step, **kw)


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
    scale = float(mad_sigma(r)) or 1.0
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
