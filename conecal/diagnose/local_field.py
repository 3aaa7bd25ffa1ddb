"""A displacement confined to one place on the detector: a dent in an
intensifier's input screen, a damaged scintillator, a burnt-in mark that
moves every centre near it.

The polynomial field (``locate.detector_field``) holds what varies smoothly
over the whole detector; a bump a few marker spacings wide is spread thin by
it and its markers are the ones a fit sets aside. Here the residuals
(measured - predicted, px) near a point are compared with those around
it: for each centre of a grid of spacing ``h`` (three scales), the
Gaussian (``h``) weighted mean residual within 2.5 h minus the weighted
plane fitted to the ring 2 h-4 h, at the inner mean's centroid. Under pure noise the squared difference over its
variance (from the stated σ) is chi-square with 2 degrees of freedom, once
divided by that scale's inflation: the median over every centre tried
over the null's median (2 ln 2), at least 1. σ stated too small, or errors
shared by a frame's markers, raise every centre alike; a place raises
only its own. The p-value is Bonferroni-adjusted over every (centre,
scale) tested; among the significant, the largest displacement is the
place (the scale at which a bump stands out most from its ring). A place
must also be seen in three frames or more and stay significant with any
one of its frames left out (one frame's wrong sphere, inside or in the
ring, is a frame's fault, not the detector's).

Units: px (column, row) on the detector; residuals in px.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# scales h as fractions of the detector's larger side (768 px: 10, 19, 38 px);
# at 1/10 (a ring 0.4 of the side across) a smooth field's curvature read as
# places (a mean for the ring, no inflation); wider than 1/20 is the field's
SCALES = (1 / 80, 1 / 40, 1 / 20)
# a place's markers: its Gaussian's weight at least this (2.5 h)
_INNER = 2.5
# the ring it is compared with (in h)
_RING = (2.0, 4.0)
# effective markers inside and in the ring, and distinct frames inside, for a test
MIN_MARKERS = 5
MIN_FRAMES = 3


def _sf2(x):
    """The chi-square survival function for 2 degrees of freedom: exp(-x/2)."""
    return np.exp(-0.5 * np.asarray(x, float))


def _n_eff(W):
    """Effective count (c,) of markers under kernel weights ``W`` (c, n)."""
    return W.sum(1) ** 2 / np.maximum((W * W).sum(1), 1e-300)


def _inner(W, xy, r, w):
    """The Gaussian side, over each centre's markers (``xy`` (c, n, 2) px,
    ``r`` (c, n, 2), ``w`` (c, n), kernel ``W`` (c, n)): weighted means
    (c, 2), the weighted centroid they hold at (c, 2) px, their variance
    from the stated σ (c,) and the effective count (c,)."""
    Kw = W * w
    s1 = Kw.sum(1)
    s1 = np.where(s1 > 0, s1, 1.0)    # (no marker: invalid, n_eff 0)
    m = np.einsum("cn,cnk->ck", Kw, r) / s1[:, None]
    at = np.einsum("cn,cnk->ck", Kw, xy) / s1[:, None]
    n_eff = _n_eff(W)
    return m, at, (W * W * w).sum(1) / s1 ** 2, n_eff


def _ring(W, xy, r, w, at):
    """The ring's weighted plane (per component) evaluated at ``at`` (c, 2)
    px (arrays as ``_inner``'s): value (c, 2), its variance from the stated
    σ (c,), the effective count (c,) and whether the plane is determined
    (c,). A plane, not a mean: at the detector's edge the ring lies on one
    side, where a smooth field's slope would read as a place."""
    U = np.concatenate([np.ones(W.shape + (1,)), xy - at[:, None]], -1)             # (c, n, 3)
    UtK = (U * (W * w)[..., None]).transpose(0, 2, 1)                                 # (c, 3, n)
    M = UtK @ U
    good = np.linalg.cond(M) < 1e10
    M[~good] = np.eye(3)
    Minv = np.linalg.inv(M)
    coef = Minv @ (UtK @ r)                                                           # (c, 3, 2)
    return coef[:, 0, :], Minv[:, 0, 0], _n_eff(W), good


def _place_tests(xy, r, w, frame, centres, h, chunk: int = 256):
    """For each centre (C, 2): chi-square (2 dof, from the stated σ) of the
    inner mean minus the ring's plane there, the difference (C, 2) and
    validity (C,). Each centre sees only its markers within the ring (a k-d
    tree's lists, padded with a weightless marker far away)."""
    n = len(xy)
    frames, fidx = np.unique(frame, return_inverse=True)
    xy_p = np.vstack([xy, [[1e6, 1e6]]])
    r_p = np.vstack([r, [[0.0, 0.0]]])
    w_p = np.append(w, 0.0)
    f_p = np.append(fidx, len(frames))
    lists = cKDTree(xy).query_ball_point(centres, _RING[1] * h)
    c2s, diffs, valids = [], [], []
    for k in range(0, len(centres), chunk):
        part = lists[k:k + chunk]
        idx = np.full((len(part), max(1, max(len(li) for li in part))), n)
        for i, li in enumerate(part):
            idx[i, :len(li)] = li
        X, Rr, Wt = xy_p[idx], r_p[idx], w_p[idx]
        d2 = ((X - centres[k:k + chunk, None, :]) ** 2).sum(-1)
        inner = np.exp(-d2 / (2 * h * h)) * (d2 <= (_INNER * h) ** 2) * (Wt > 0)
        ring = ((d2 >= (_RING[0] * h) ** 2) & (d2 < (_RING[1] * h) ** 2) & (Wt > 0)).astype(float)
        F = f_p[idx]
        mi, at, vi, ni = _inner(inner, X, Rr, Wt)
        mr, vr, nr, good = _ring(ring, X, Rr, Wt, at)
        diff = mi - mr
        with np.errstate(invalid="ignore", divide="ignore"):
            c2 = (diff ** 2).sum(1) / (vi + vr)
        seen = np.where(inner > np.exp(-0.5 * 1.5 ** 2), F, len(frames))
        frames_in = np.array([len(set(row.tolist()) - {len(frames)}) for row in seen])
        valid = (ni >= MIN_MARKERS) & (nr >= MIN_MARKERS) & (frames_in >= MIN_FRAMES) & good & np.isfinite(c2)
        c2s.append(np.where(valid, c2, 0.0))
        diffs.append(diff)
        valids.append(valid)
    return np.concatenate(c2s), np.concatenate(diffs), np.concatenate(valids)


def _without_any_frame(xy, r, w, frame, centre, h):
    """The place's smallest chi-square with any one of its frames (inside or
    in its ring) left out: one frame's wrong sphere among the ring's markers
    moves the ring's plane as much as one inside moves the mean."""
    near = ((xy - centre) ** 2).sum(-1) < (_RING[1] * h) ** 2
    worst = np.inf
    for f in np.unique(frame[near]):
        keep = frame != f
        c2, _, valid = _place_tests(xy[keep], r[keep], w[keep], frame[keep], centre[None], h)
        worst = min(worst, float(c2[0]) if valid[0] else 0.0)
    return worst


def local_displacements(xy, residual, sigma, frame, shape, alpha: float = 0.01, max_places: int = 3) -> tuple:
    """Places on the detector whose markers are displaced from those around
    them. ``xy`` (N, 2) measured centres px, ``residual`` (N, 2) px,
    ``sigma`` (N,) px (each marker's, scaled to the fit's scatter), ``frame``
    (N,), ``shape`` (rows, cols). Returns (located entries, markers within
    any place's ring (N,) bool, tests: how many places were tried)."""
    xy, r = np.asarray(xy, float), np.asarray(residual, float)
    w = 1.0 / np.asarray(sigma, float) ** 2
    frame = np.asarray(frame)
    rows, cols = shape
    side = float(max(rows, cols))
    grids = []
    for f in SCALES:
        h = f * side
        gu = np.arange(h / 2, cols, h)
        gv = np.arange(h / 2, rows, h)
        grids.append((h, np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)))
    inside = np.zeros(len(r), bool)
    found, n_tests, inflation = [], None, {}
    for _ in range(max_places):
        cands = []
        tested = 0
        for h, centres in grids:
            # (markers in a place already found are out of the next search)
            c2, diff, valid = _place_tests(xy[~inside], r[~inside], w[~inside], frame[~inside], centres, h)
            tested += int(valid.sum())
            if h not in inflation and valid.any():
                # the first search's median chi-square over the null's (2 ln 2):
                # sigma stated too small, or shared within frames, raise every
                # place alike, a place raises only its own
                inflation[h] = max(1.0, float(np.median(c2[valid])) / (2 * np.log(2)))
            lam = inflation.get(h, 1.0)
            p1 = _sf2(c2 / lam)
            cands += [(float(p1[i]), h, centres[i], diff[i], lam) for i in np.flatnonzero(valid)]
        if n_tests is None:
            n_tests = tested    # the first search's count adjusts every p-value
        if not cands:
            break
        place = None
        # among the significant, the largest displacement: the scale at which
        # a bump stands out most from its ring (a finer one's ring is still on
        # the bump's flank; the smallest p-value went to the finest scale and
        # split one dent into two places)
        for p1, h, centre, diff, lam in sorted(cands, key=lambda t: -np.hypot(*t[3])):
            p = min(1.0, n_tests * p1)
            if p >= alpha:
                continue
            if any(np.hypot(*(centre - f["centre_px"])) < f["radius_px"] + _INNER * h for f in found):
                continue   # the tail of a place already found, seen at another scale
            rest = _without_any_frame(xy[~inside], r[~inside], w[~inside], frame[~inside], centre, h)
            if min(1.0, n_tests * float(_sf2(rest / lam))) < alpha:
                place = (h, centre, diff, p)
                break
        if place is None:
            break
        h, centre, diff, p = place
        d2 = ((xy - centre) ** 2).sum(-1)
        members = (d2 <= (_INNER * h) ** 2) & ~inside
        size = float(np.hypot(*diff))
        found.append({
            "component": "local displacement on the detector", "unit": "px", "variable": "detector position",
            "shape": (f"a place {2 * _INNER * h:.0f} px across about ({centre[0]:.0f}, {centre[1]:.0f}) px, "
                      f"displaced ({diff[0]:+.2f}, {diff[1]:+.2f}) px from around it; "
                      f"{int(members.sum())} markers in {len(np.unique(frame[members]))} frames"),
            "size": size, "size_px": size, "p_adjusted": p, "also_follows": [],
            "centre_px": [float(centre[0]), float(centre[1])], "radius_px": float(_INNER * h),
            "displacement_px": [float(diff[0]), float(diff[1])], "n_markers": int(members.sum()),
            "n_frames": int(len(np.unique(frame[members])))})
        # (its markers and those of the ring it was compared with stay out of
        # the next searches and the other tests: a bump's tail reaches the ring)
        inside |= d2 < (_RING[1] * h) ** 2
    return found, inside, int(n_tests or 0)
