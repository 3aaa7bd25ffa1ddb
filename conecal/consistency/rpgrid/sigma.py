"""rp-grid, stage 5: the answer's uncertainty and the result.

``finish`` makes the :class:`RPResult`: sigma is the largest of the robust
sandwich from the refinement's Hessian, a leave-views-out jackknife, the
spread of disjoint batches of view pairs refined alone and of their minima
along each whole range (held and along the profile), times
``RPOptions.sigma_factors``; parameters on their search bound (and those
strongly correlated with them) get an infinite sigma. Also the cost
slices through the answer. Units are those of the parameters: px for the
shifts, deg for the tilts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...geometry.misalignment import NAMES
from .cost import RPProblem
from .options import RPOptions
from .search import F_SCALE, _bilinear, _parameters, _solve


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


def _pair_batches(prob: RPProblem, x, seed: int, batches: int) -> list:
    """Look-up arrays of ``batches`` disjoint random groups of whole view pairs
    (the planes of one pair share their two views' errors); groups under 100
    planes are left out."""
    kept = np.flatnonzero(prob.keep)
    _, inverse = np.unique(prob.vi[kept] * len(prob.R) + prob.vj[kept], return_inverse=True)
    group = np.random.default_rng(seed).permutation(inverse.max() + 1)[inverse] % batches
    arrays = [prob._arrays(kept[group == b], x) for b in range(batches)]
    return [a for a in arrays if len(a[0]) >= 100]


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
    from ...fit.core import robust_loss

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
