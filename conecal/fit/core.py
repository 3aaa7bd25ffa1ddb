"""One least-squares core for every fit.

A problem declares named :class:`Parameter` s (value, free or fixed, bounds,
unit) and supplies whitened residuals ``r(x)`` (residual / sigma) and their
analytic Jacobian ``J(x)`` over *all* parameters. :func:`solve` runs
scipy's trust-region least squares on the free ones and returns a
:class:`FitResult` with estimates, covariance, sigma, correlations,
residuals, iterations, robust-loss outliers and the parameters the data
cannot determine (found from the Jacobian's null space, not guessed).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
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
          scale_covariance: bool = False, tol: float = 1e-12) -> FitResult:
    """Minimise ``sum rho(r(x)^2)`` over the free parameters.

    ``residuals(x)`` and ``jacobian(x)`` take the full parameter vector.
    Residuals are whitened (divided by their sigma), so the covariance is
    ``(J^T J)^-1``; with ``scale_covariance`` it is multiplied by the reduced
    chi^2 (for when the sigmas are only relative). With a robust ``loss``
    ('soft_l1', 'huber', 'cauchy'), residuals beyond ``f_scale`` sigmas are
    reported as outliers and the covariance is computed from the inliers.
    ``tol``: scipy's xtol, ftol and gtol.
    """
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

    def jac(xf):
        return jacobian(full(xf))[:, free]

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
    gauge = null_directions(start)
    nfev = 0
    for attempt in range(2):
        def fun_g(xf, gauge=gauge):
            r = fun(xf)
            return r if not len(gauge) else np.concatenate([r, stiff * gauge @ ((xf - start) / scale)])

        def jac_g(xf, gauge=gauge):
            J = jac(xf)
            return J if not len(gauge) else np.vstack([J, stiff * gauge / scale])

        res = least_squares(fun_g, start, jac=jac_g, bounds=(lo, hi) if bounded else (-np.inf, np.inf),
                            method="trf", x_scale=scale, loss=loss, f_scale=f_scale, max_nfev=max_nfev,
                            xtol=tol, ftol=tol, gtol=tol)
        nfev += res.nfev
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
    r = fun(res.x)
    J = jac(res.x)
    outliers = np.abs(r) > f_scale if loss != "linear" else np.zeros(r.size, bool)
    Jin = J[~outliers]
    rin = r[~outliers]
    chi2 = float(rin @ rin)
    dof = int(rin.size - free.sum())
    # null space in the parameters' natural scales
    Js = Jin * scale
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
    cov = cov_s * np.outer(scale, scale)
    if scale_covariance and dof > 0:
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
                     units=[p.unit for p in parameters], history=history[:-1] if len(history) > 1 else history)
