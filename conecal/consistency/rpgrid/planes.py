"""rp-grid, stage 2: the sample of redundant planes and which of them are usable.

A plane through two source positions is seen by both views; each view sees
it as a line (angle alpha, offset s in mm from the tables' origin) on its
detector. Here: the lab-frame detector quantities of a candidate geometry
(``_frame``), the random view pairs and the fan of planes through each
pair's baseline (``FAN_STEP_DEG`` apart), the selection of planes whose lines
stay on the region and clear of truncated borders and holders, and the
planes' look-up order, weights and smoothing along the fans (``_Planes``).

``_PlaneSample`` holds these methods of :class:`~.cost.RPProblem` (its base
class; it is not used alone): the problem's constructor, attributes and
look-ups (``_look``, ``_grangeat``) are in ``cost``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ...errors import FitError, InputError
from ...geometry import ConeGeometry
from ...geometry.misalignment import misaligned
from ..radon import KERNEL_REACH
from .options import FAN_STEP_DEG


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
    fan: object = None      # sparse smoothing along each pair's fan, or None
    fan2: object = None     # its elementwise square (for the noise variance)


class _PlaneSample:
    """The plane sample of :class:`~.cost.RPProblem`: candidates, selection, look-up arrays."""

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
        W = self._fan_matrix(idx) if fan and self.opt.fan_sigma_deg > 0 else None
        size = np.abs(self._look(f, vi, mi)[0])
        size[perm] += np.abs(self._look(f, vj, mj)[0])
        size *= 0.5
        # c: a typical signal level, not the median: with truncation most
        # planes may miss the object, and noise-only planes must not set the scale
        weight = 1.0 / (np.percentile(size, 75) + size) if size.size else 1.0
        if self.tab.variance is not None and self.opt.noise_weights:
            # weights from the noisy values themselves correlate with the
            # noise at the lines and bias the answer (v by 0.3 px with a dense
            # holder at 1e5 photons); the noise sigma weights instead
            weight = np.ones(len(vi))
        return _Planes(vi, mi, vj, mj, perm, weight, W, None if W is None else W.multiply(W).tocsr())

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

    def subset(self, n: int, seed: int = 0):
        """Look-up arrays of ``n`` of the kept planes at random (for the grids)."""
        kept = np.flatnonzero(self.keep)
        rng = np.random.default_rng(seed)
        return self._arrays(np.sort(rng.choice(kept, size=min(n, kept.size), replace=False)), self._p_sel, fan=False)
