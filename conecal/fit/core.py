"""One least-squares core for every fit.

A problem declares named :class:`Parameter` s (value, free or fixed, bounds,
unit) and supplies whitened residuals ``r(x)`` (residual / sigma) and their
analytic Jacobian ``J(x)`` over *all* parameters. :func:`solve` runs
scipy's trust-region least squares on the free ones (or, for residuals
dominated by noise, a trust-region Newton method on a numerical Hessian:
see ``hessian``) and returns a
:class:`FitResult` with estimates, covariance, sigma, correlations,
residuals, iterations, robust-loss outliers and the parameters the data
cannot determine (found from the Jacobian's null space, not guessed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from ..errors import FitError


@dataclass(frozen=True)
class Parameter:
    name: str
    value: float
    free: bool = True
    lower: float = -np.inf
    upper: float = np.inf
    unit: str = ""
    # a change of this size is "meaningful" (the solver's step scale)
    scale: float = 1.0
    # a sigma beyond this means the data do not determine the parameter
    # (default: ``undetermined_factor`` times ``scale``)
    undetermined_sigma: float | None = None


@dataclass
class FitResult:
    names: list[str]
    initial: np.ndarray
    x: np.ndarray
    free: np.ndarray              # bool mask
    sigma: np.ndarray             # nan for fixed
    covariance: np.ndarray        # over free parameters
    correlation: np.ndarray       # over free parameters
    residuals: np.ndarray         # whitened, at the solution
    cost: float                   # 0.5 * sum(rho(r^2)) as scipy reports
    chi2: float                   # sum r^2
    dof: int
    nfev: int
    njev: int
    outliers: np.ndarray          # bool per residual: rejected by the robust loss
    undetermined: list[str]
    null_combinations: list[dict]
    success: bool
    message: str
    units: list[str] = field(default_factory=list)
    history: list[float] = field(default_factory=list)   # chi^2 at each function evaluation
    hessian: np.ndarray | None = None   # of the robust cost over free parameters (hessian="numerical" only)

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    def value(self, name: str) -> float:
        return float(self.x[self.names.index(name)])

    def parameters_dict(self) -> dict:
        out = {}
        for i, n in enumerate(self.names):
            out[n] = {"index": i, "initial": float(self.initial[i]), "value": float(self.x[i]), "free": bool(self.free[i]),
                      "sigma": None if not np.isfinite(self.sigma[i]) else float(self.sigma[i]),
                      "unit": self.units[i] if self.units else "", "determined": n not in self.undetermined}
        return out


def solve(parameters: list[Parameter], residuals: Callable[[np.ndarray], np.ndarray],
          jacobian: Callable[[np.ndarray], np.ndarray], *, loss: str = "linear", f_scale: float = 3.0,
          max_nfev: int = 200, undetermined_factor: float = 10.0, null_tol: float = 1e-7,
          scale_covariance: bool = False, tol: float = 1e-12, hessian: str = "gauss-newton",
          hessian_step: float = 2.0, large: bool = False, covariance: bool = True) -> FitResult:
    """Minimise ``sum rho(r(x)^2)`` over the free parameters.

    ``residuals(x)`` and ``jacobian(x)`` take the full parameter vector.
    Residuals are whitened (divided by their sigma), so the covariance is
    ``(J^T J)^-1``; with ``scale_covariance`` it is multiplied by the reduced
    chi^2 (for when the sigmas are only relative). With a robust ``loss``
    ('soft_l1', 'huber', 'cauchy'), residuals beyond ``f_scale`` sigmas are
    reported as outliers and the covariance is computed from the inliers.
    ``tol``: scipy's xtol, ftol and gtol.

    ``hessian="numerical"``: Gauss-Newton takes J^T J for the Hessian, which
    leaves out sum r_i d2r_i. That term is negligible when residuals are
    small, but not when they are mostly noise whose own slope enters J:
    then J^T J counts (dn/dx)^2 while the true curvature has it cancelled
    by n d2n/dx2 (on average, for stationary noise), and Gauss-Newton steps
    are too short by the ratio (rp-grid's tables: ~40x along the v shift,
    and trust-region least squares creeps for hundreds of evaluations).
    This mode minimises the same robust cost by trust-region Newton steps
    on the Hessian from central differences of its analytic gradient
    (steps of ``hessian_step`` Gauss-Newton standard deviations along the
    Gauss-Newton matrix's eigenvectors; 2n gradients per new Hessian), and
    the covariance is the M-estimator's sandwich H^-1 (sum g_i g_i^T) H^-1
    of per-residual gradients g_i over all residuals (the loss weights
    them; no chi^2 scaling).

    ``large``: for problems with hundreds of parameters (a bundle
    adjustment): no search for blind directions before and after solving
    (the problem must have no gauge freedom; a blind direction still shows
    in the final null space and sigmas); ``jacobian`` may then return a
    scipy.sparse matrix (a bundle's, mostly zeros).
    ``covariance=False`` skips that too (sigma, correlation: nan), for fits
    whose only use is their prediction (held-out scores).
    """
    if hessian not in ("gauss-newton", "numerical"):
        raise ValueError(f"hessian: {hessian!r}, expected 'gauss-newton' or 'numerical'")
    names = [p.name for p in parameters]
    x0 = np.array([p.value for p in parameters], float)
    free = np.array([p.free for p in parameters])
    if not free.any():
        raise FitError("no free parameters")
    lo = np.array([p.lower for p in parameters])[free]
    hi = np.array([p.upper for p in parameters])[free]
    scale = np.array([p.scale for p in parameters])[free]
    start = np.clip(x0[free], lo, hi)

    def full(xf):
        x = x0.copy()
        x[free] = xf
        return x

    history = []

    def fun(xf):
        r = residuals(full(xf))
        history.append(float(r @ r))     # chi^2 per evaluation: the report's convergence plot
        return r

    all_free = bool(free.all())

    def jac(xf):
        J = jacobian(full(xf))
        return J if all_free else J[:, free]

    r0 = fun(start)
    if r0.size < free.sum():
        raise FitError(f"{r0.size} residuals for {int(free.sum())} free parameters: too few observations")
    if not np.all(np.isfinite(r0)):
        raise FitError("the initial geometry gives non-finite residuals (a point behind the source?)")
    # Directions the data cannot see at all (a gauge freedom, such as the
    # scale along the beam when no sphere distance is known) are held at
    # their starting value by a stiff prior, so the solver does not wander;
    # they are reported as undetermined below.
    def null_directions(xf):
        _, sv, vt = np.linalg.svd(jac(xf) * scale, full_matrices=False)
        return vt[sv <= null_tol * sv[0]] if sv.size else np.zeros((0, xf.size))

    stiff = 1e3 * np.sqrt(max(r0.size, 1))
    bounded = np.isfinite(lo).any() or np.isfinite(hi).any()
    gauge = np.zeros((0, start.size)) if large else null_directions(start)
    nfev = 0
    for attempt in range(2):
        def fun_g(xf, gauge=gauge):
            r = fun(xf)
            return r if not len(gauge) else np.concatenate([r, stiff * gauge @ ((xf - start) / scale)])

        def jac_g(xf, gauge=gauge):
            J = jac(xf)
            return J if not len(gauge) else np.vstack([J, stiff * gauge / scale])

        if hessian == "numerical":
            res = _newton(fun_g, jac_g, start, lo, hi, scale, loss, f_scale, max_nfev, tol, hessian_step)
        elif large and loss == "linear":
            # (no gauge rows on this path: its start's residuals are r0)
            res = _levenberg_marquardt(fun_g, jac_g, start, scale, max_nfev, tol, lo, hi,
                                       r0=None if len(gauge) else r0)
            if not len(gauge):
                history.insert(1, history[0])   # the record as if the start were evaluated again
        else:
            res = least_squares(fun_g, start, jac=jac_g, bounds=(lo, hi) if bounded else (-np.inf, np.inf),
                                method="trf", x_scale=scale, loss=loss, f_scale=f_scale, max_nfev=max_nfev,
                                xtol=tol, ftol=tol, gtol=tol)
        nfev += res.nfev
        if large or not covariance:
            break
        # directions that turn out blind only away from the start: hold them too, and solve again
        late = null_directions(res.x)
        if not len(late):
            break
        if len(gauge):
            late = late - (late @ gauge.T) @ gauge
            late = late[np.linalg.norm(late, axis=1) > 1e-3]
        if not len(late):
            break
        q, _ = np.linalg.qr(np.vstack([gauge, late]).T) if len(gauge) else np.linalg.qr(late.T)
        gauge = q.T
    res.nfev = nfev
    x = full(res.x)
    if getattr(res, "r", None) is not None and not len(gauge):
        # the solver's last residuals and Jacobian at its answer (thousands of small fits per frame)
        r, J = res.r, res.jac_raw if res.jac_raw is not None else jac(res.x)
        history.append(float(r @ r))
    else:
        r = fun(res.x)
        J = jac(res.x)
    outliers = np.abs(r) > f_scale if loss != "linear" else np.zeros(r.size, bool)
    Jin = J[~outliers] if outliers.any() else J
    rin = r[~outliers]
    chi2 = float(rin @ rin)
    dof = int(rin.size - free.sum())
    if not covariance:
        nan = np.full((int(free.sum()),) * 2, np.nan)
        return FitResult(names=names, initial=x0, x=x, free=free, sigma=np.full(len(names), np.nan), covariance=nan,
                         correlation=nan, residuals=r, cost=float(res.cost), chi2=chi2, dof=dof, nfev=int(res.nfev),
                         njev=int(res.njev or 0), outliers=outliers, undetermined=[], null_combinations=[],
                         success=bool(res.status > 0), message=str(res.message), units=[p.unit for p in parameters])
    # null space in the parameters' natural scales
    Js = _scaled(Jin, scale)
    if large:
        # many parameters, few of them coupled: the normal matrix's eigenvectors
        # (s^2) are 5-10x cheaper than the SVD of J and as good at this conditioning
        ev, V = np.linalg.eigh(_dense(Js.T @ Js))
        order = np.argsort(ev)[::-1]
        s, Vt = np.sqrt(np.clip(ev[order], 0, None)), V[:, order].T
    else:
        U, s, Vt = np.linalg.svd(Js, full_matrices=False)
    smax = s[0] if s.size else 0.0
    null = [k for k in range(s.size) if s[k] <= null_tol * smax]
    free_names = [n for n, f in zip(names, free) if f]
    combos = []
    involved = set()
    for k in null:
        v = Vt[k] * scale
        v = v / np.abs(v).max()
        comp = {free_names[i]: round(float(v[i]), 4) for i in np.argsort(-np.abs(v)) if abs(v[i]) > 0.05}
        combos.append(comp)
        involved.update(comp)
    # covariance from the pseudo-inverse on the determined subspace
    keep = s > null_tol * smax
    Vk = Vt[keep].T
    cov_s = (Vk / s[keep] ** 2) @ Vk.T
    if hessian == "numerical":
        H = res.hessian
        Hk = Vk @ np.linalg.pinv(Vk.T @ H @ Vk) @ Vk.T
        g = (J * scale) * (robust_loss(r * r / f_scale**2, loss)[1] * r)[:, None]
        cov_s = Hk @ (g.T @ g) @ Hk
    cov = cov_s * np.outer(scale, scale)
    if scale_covariance and dof > 0 and hessian != "numerical":
        cov = cov * (chi2 / dof)
    sig_free = np.sqrt(np.clip(np.diag(cov), 0, None))
    for n in involved:
        sig_free[free_names.index(n)] = np.inf
    limit = np.array([p.undetermined_sigma if p.undetermined_sigma is not None else undetermined_factor * p.scale
                      for p in parameters])[free]
    weak = [free_names[i] for i in range(len(free_names)) if np.isfinite(sig_free[i]) and sig_free[i] > limit[i]]
    undetermined = sorted(involved) + weak
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(np.diag(cov))
        corr = cov / np.outer(d, d)
    sigma = np.full(len(names), np.nan)
    sigma[free] = sig_free
    return FitResult(names=names, initial=x0, x=x, free=free, sigma=sigma, covariance=cov, correlation=corr,
                     residuals=r, cost=float(res.cost), chi2=chi2, dof=dof, nfev=int(res.nfev),
                     njev=int(res.njev or 0), outliers=outliers, undetermined=undetermined,
                     null_combinations=combos, success=bool(res.status > 0), message=str(res.message),
                     units=[p.unit for p in parameters], history=history[:-1] if len(history) > 1 else history,
                     hessian=res.hessian / np.outer(scale, scale) if hessian == "numerical" else None)


# Levenberg-Marquardt: the damping's fall after a step that lowered the cost
_LM_SHRINK = 10.0


def _levenberg_marquardt(fun, jac, x0, scale, max_nfev, tol, lo=None, hi=None, r0=None):
    """Plain Levenberg-Marquardt on the normal equations (Cholesky), in the
    parameters' scales: for ``large`` problems, where an SVD of J per
    iteration (scipy's exact trust region) costs more than everything else,
    and for few parameters over millions of residuals (the image level).
    Steps are clipped to the bounds ``lo``, ``hi`` (a parameter may come to
    rest on one: the caller reports it as pinned). ``r0``: the residuals
    at ``x0`` when already known. Returns an object with scipy's result
    fields, plus ``r`` (the residuals at ``x``) and ``jac_raw`` (``jac(x)``
    as returned, or None when not evaluated there)."""
    from types import SimpleNamespace

    x = x0.copy()
    r = fun(x) if r0 is None else r0
    J_raw = None
    cost = 0.5 * float(r @ r)
    lam, nfev, njev, status, msg = 1e-3, 1, 0, 0, "maximum evaluations"
    while nfev < max_nfev:
        J_raw = jac(x)
        njev += 1
        if isinstance(J_raw, np.ndarray):
            # (the scales applied to the small products, not to J: thousands of small fits per frame)
            g = (J_raw.T @ r) * scale
            H = (J_raw.T @ J_raw) * np.outer(scale, scale)
        else:
            J = _scaled(J_raw, scale)
            g = J.T @ r
            H = _dense(J.T @ J)
        d = np.maximum(np.diag(H), 1e-12 * max(np.diag(H).max(), 1e-300))
        # a parameter resting on a bound that the gradient pushes beyond is held for this step
        held = np.zeros(len(x), bool) if lo is None else (((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
        if held.all():
            status, msg = 2, "every parameter rests on a bound"
            break
        if np.max(np.abs(g[~held])) <= tol * max(1.0, 2 * cost):
            status, msg = 1, "gradient below tolerance"
            break
        while nfev < max_nfev:
            try:
                A = H + np.diag(lam * d)
                if held.any():
                    step = np.zeros(len(x))
                    m = ~held
                    step[m] = -np.linalg.solve(A[np.ix_(m, m)], g[m])
                else:
                    step = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step * scale
            if lo is not None:
                x_new = np.clip(x_new, lo, hi)
                step = (x_new - x) / scale
                if not np.any(step):
                    status, msg = 2, "at a bound, the step points beyond it"
                    break
            r_new = fun(x_new)
            nfev += 1
            cost_new = 0.5 * float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                small = cost - cost_new <= tol * cost or np.linalg.norm(step) <= tol * (np.linalg.norm(x / scale) + tol)
                x, r, cost, J_raw = x_new, r_new, cost_new, None
                lam = max(lam / _LM_SHRINK, 1e-9)
                if small:
                    status, msg = 2, "cost or step below tolerance"
                break
            lam *= 10
            if lam > 1e12:
                status, msg = 3, "no step lowers the cost"
                break
        if status:
            break
    return SimpleNamespace(x=x, cost=cost, nfev=nfev, njev=njev, status=status if status else 0, message=msg,
                           hessian=None, r=r, jac_raw=J_raw)


def _scaled(J, scale):
    """J with its columns multiplied by ``scale``; J dense or scipy-sparse (a
    bundle adjustment's Jacobian, mostly zeros: only the ``large`` path takes it)."""
    if isinstance(J, np.ndarray):
        return J * scale
    J = sparse.csr_matrix(J, copy=True)
    J.data *= scale[J.indices]          # each stored entry times its column's scale
    return J


def _dense(M):
    return M if isinstance(M, np.ndarray) else M.toarray()


def robust_loss(z, loss: str):
    """scipy's robust losses rho(z) of z = (r / f_scale)^2 and rho'(z)."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    if loss == "soft_l1":
        t = np.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    if loss == "huber":
        big = z > 1.0
        zs = np.where(big, z, 1.0)
        return np.where(big, 2.0 * np.sqrt(zs) - 1.0, z), np.where(big, 1.0 / np.sqrt(zs), 1.0)
    raise ValueError(f"loss: {loss!r}, expected linear, cauchy, soft_l1 or huber")


def _newton(fun, jac, x0, lo, hi, scale, loss, f_scale, max_nfev, tol, step):
    """Trust-region Newton minimisation of scipy's robust cost
    0.5 f^2 sum rho((r / f)^2) within the bounds, in coordinates scaled by
    ``scale``. The Hessian comes from central differences of the analytic
    gradient J^T (rho' r) along the eigenvectors of the Gauss-Newton matrix
    J^T diag(rho') J, each ``step`` of its standard deviations long: a stiff
    direction (an in-plane rotation) needs steps thousands of times
    shorter than a shallow one (the valley of v against a tilt), and no
    one step per parameter suits both. Every gradient counts as one
    evaluation against ``max_nfev``. Returns what :func:`solve` reads of
    scipy's result, plus ``hessian`` (scaled coordinates) at the answer."""
    from types import SimpleNamespace

    f2 = f_scale**2
    counts = [0]

    def evaluate(z):
        """Cost, gradient, and (J, rho') for the Gauss-Newton matrix should a new Hessian be needed there."""
        x = x0 + z * scale
        # the Jacobian first: a problem may compute the residuals with it
        J = jac(x) * scale
        r = fun(x)
        counts[0] += 1
        rho, drho = robust_loss(r * r / f2, loss)
        return 0.5 * f2 * float(np.sum(rho)), J.T @ (drho * r), (J, drho)

    def gauss_newton(J_drho):
        J, drho = J_drho
        return (J * drho[:, None]).T @ J

    def hess(z, A):
        w, V = np.linalg.eigh(A)
        E = V * (step / np.sqrt(np.maximum(w, 1e-12 * w[-1])))
        G = np.column_stack([evaluate(np.clip(z + e, zlo, zhi))[1] - evaluate(np.clip(z - e, zlo, zhi))[1]
                             for e in E.T]) / 2.0
        H = G @ np.linalg.inv(E)
        return 0.5 * (H + H.T)

    zlo, zhi = (lo - x0) / scale, (hi - x0) / scale
    z = np.zeros(x0.size)
    c, g, J_drho = evaluate(z)
    H = hess(z, gauss_newton(J_drho))
    radius, status, message = 2.0, 0, "the maximum number of evaluations was reached"
    while counts[0] < max_nfev:
        d = _trust_step(g, H, radius)
        z_new = np.clip(z + d, zlo, zhi)
        d = z_new - z
        predicted = -(g @ d + 0.5 * d @ H @ d)
        c_new, g_new, J_drho = evaluate(z_new)
        ratio = (c - c_new) / predicted if predicted > 0 else -1.0
        if ratio > 0.1 and c_new < c:
            small = np.max(np.abs(d)) < tol**0.5 or (c - c_new) < tol * max(abs(c), 1.0)
            z, c, g = z_new, c_new, g_new
            if small:
                status, message = 2, "the step or the cost change fell below tol"
                break
            # a new Hessian only where the quadratic model mispredicted the
            # step's gain (2n gradients each)
            if not 0.8 < ratio < 1.25:
                H = hess(z, gauss_newton(J_drho))
            if ratio > 0.75 and np.linalg.norm(d) > 0.9 * radius:
                radius *= 2.0
        else:
            radius = 0.25 * np.linalg.norm(d)
            if radius < tol**0.5:
                status, message = 2, "the trust region shrank below tol: no step lowers the cost"
                break
    return SimpleNamespace(x=x0 + z * scale, cost=c, nfev=counts[0], njev=counts[0], status=status,
                           message=message, hessian=H)


def _trust_step(g, H, radius):
    """The step d minimising g.d + d.H.d/2 with |d| <= radius (H symmetric,
    possibly indefinite): -(H + lam I)^-1 g with the smallest lam >= 0
    (and above -min eigenvalue) that keeps the step inside, found by
    bisection on lam in H's eigenbasis."""
    w, Q = np.linalg.eigh(H)
    gq = Q.T @ g

    def step(lam):
        return -Q @ (gq / np.maximum(w + lam, 1e-300))

    lam_lo = max(0.0, -w[0] + 1e-12 * max(abs(w[-1]), 1.0))
    d = step(lam_lo)
    if np.linalg.norm(d) <= radius:
        return d
    lam_hi = lam_lo + np.linalg.norm(g) / radius + abs(w[-1])
    for _ in range(60):
        lam = 0.5 * (lam_lo + lam_hi)
        if np.linalg.norm(step(lam)) > radius:
            lam_lo = lam
        else:
            lam_hi = lam
    return step(lam_hi)
