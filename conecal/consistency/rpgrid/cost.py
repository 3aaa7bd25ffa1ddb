"""rp-grid, stage 3: the redundant-plane cost as a function of the five parameters.

Per plane, each view's value is Grangeat's factor (D^2 + s_pp^2)/D^2 times
its table at the plane's line; the residual is the two views'
disagreement, weighted (and divided by its noise sigma with noise tables),
and ``normalised_cost`` is c_RP, the squared disagreement over the planes'
squared values. The Jacobian is analytic along the lines' angle and offset
(the detector quantities' derivatives are numerical, ``_dframes``).
Parameters: shift u, v (px), eta, theta, phi (deg); lengths in mm.
"""

from __future__ import annotations

import numpy as np

from ...geometry import ConeGeometry
from .. import kernels
from ...geometry.misalignment import misaligned
from .options import RPOptions, _lookup
from .planes import _Frame, _frame, _Planes, _PlaneSample
from .tables import ViewTables


class RPProblem(_PlaneSample):
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

    # -- cost, residuals, Jacobian ------------------------------------------------------------------

    def _look(self, f: _Frame, views, m, dframes=None, variance=False):
        """Per plane of normals ``m`` seen by ``views``: the Grangeat factor
        times the table value, and with ``variance`` the noise variance of
        that value (F^2 times the noise table; the tables' global scale),
        both from one computation of the lines. With ``dframes`` also their
        derivatives along each parameter: returns (value, J, variance, J of
        the variance), else (value, variance); the variance's parts are None
        without ``variance``. The Grangeat factor follows the geometry
        (fixed at the selection geometry it pulled the tilts towards where the
        planes were chosen: benchmarks/RESULTS.md, tag rpgrid-experiments)."""
        a, b, c, h, alpha, s = self._lines(f, m)
        ca, sa, spp = self._from_principal_point(f, a, b, h, s)
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
            dF = self._grangeat_derivative(f, df, ca, sa, spp, dalpha, dsl)
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

    def _residuals(self, p, arrays: "_Planes", energy=False):
        A = arrays
        f = _frame(misaligned(self.nominal, p), self.tab.ref)
        weighted = self.noise_weighted and not energy
        a, Va = self._look(f, A.vi, A.mi, variance=weighted)
        b, Vb = self._look(f, A.vj, A.mj, variance=weighted)
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
        d, J, Vi, JVi = self._look(f, A.vi, A.mi, dfs, variance=weighted)
        b, Jj, Vj, JVj = self._look(f, A.vj, A.mj, dfs, variance=weighted)
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

    def cost(self, p) -> float:
        return self.normalised_cost(p)
