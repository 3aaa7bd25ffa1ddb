"""A blob holding several sphere shadows, split into them.

Two or more shadows that overlap deeply, or a chain or cluster of them
(a helix seen along its axis, a ball phantom at an oblique view), make one
blob that is too big, too elongated or too misshapen to be one sphere. It
is fitted with one sphere, then one more at a time, each new one started
where the previous fit's residual holds the most attenuation of a sphere's
size (a matched filter on the residual, so it works for any arrangement,
not only along a line), all on one patch so the fits' chi-squares compare.
A sphere is added while the chi-square falls by more than BIC asks (with
the noise's pixel correlation counted) *and* by a fair share of the new
sphere's own model energy or most of the misfit left, or by bringing a
too-dense single fit back to the frame's contrast: a sphere that only soaks
up the others' model error explains little of either. The parts are kept only when each
has the frame's sphere size and contrast and together they explain the
blob to within twice the pixel noise. Units: px, attenuation.
"""

from __future__ import annotations

import cv2
import numpy as np

from .background import fit_profile, structured
from .chain import weighted_moments
from .overlap import background_basis, disc_misfit, fit_group, group_box, group_model, mask_weights, render_box

# the chi-square fall a new sphere must give, as a fraction of its own model
# energy: a real shadow's is most of it (0.5-1 for overlaps up to 60 %)
_EARN = 0.15
_MAX_PARTS = 6
# ... and in a long chain (a grid's row seen edge-on holds seven; allowed
# in any blob, a dense ball phantom's pair came out as three, two on one sphere)
_MAX_CHAIN = 9
# the split parts that give a frame with no shadow alone its spheres' contrast
_CONTRAST_PARTS = 3
# a sphere added to a group lies at least this fraction of the radii's sum
# from each member (a grid's row seen edge-on: 0.67-0.8; pairs a split
# cannot separate: 0.3-0.4)
_BESIDE = 0.5
# ... and only to a group misfitting its discs this many times ``ADEQUATE`` (or
# the misfit around): a sphere left out (a grid's rows seen edge-on: 3.4-19);
# less, and the misfit may be spheres nearly on top of each other, the pairs'
# to fit (:mod:`.pairs`), which spheres added beside them hid (a coded helix's
# pair of large beads beside a third: 1.4; a chain of three on a tube: 2.0)
_LEFT_OUT = 3.0
ADEQUATE = 4.0   # chi2 per pixel, in units of the pixel noise's variance
# a blob this elongated is a long chain, its parts started at once (:func:`_long_chain`)
LONG_CHAIN = 4.0


def peaks_in(m, peaks) -> list:
    """Candidate peaks (x, y) inside blob ``m``'s extent."""
    return [p for p in peaks if (p[0] - m.x) ** 2 + (p[1] - m.y) ** 2 < (1.5 * m.radius + 2) ** 2]


def split(a: np.ndarray, m, R1: float, mu1, blur: float, noise: float, kappa: float, mask_out, invalid,
          peaks=()) -> tuple[np.ndarray, bool] | None:
    """Spheres (k, 4: x, y, R px, mu per px of chord) that blob ``m`` holds,
    k >= 2, and whether they lie across an edge (see below); or None when
    one sphere explains it as well or the parts are not
    of the frame's spheres (radius ``R1`` px, contrast ``mu1``, None when
    unknown). ``mask_out``: (x, y, r) of shadows around it, not fitted.

    A blob whose background was disturbed (flagged clutter: a holder's wall
    under it) is split on the frame with the wall's profile across its edge
    removed (:func:`conecal.detect.background.fit_profile`, pinned by the
    level lines' pixels outside the blob): first the profile fitted with one
    sphere, then again with the parts that split found. A plane or a
    quadratic leaves such an edge, and extra spheres then soak it up."""
    inside = [p for p in peaks_in(m, peaks)
              if all((p[0] - ox) ** 2 + (p[1] - oy) ** 2 > (0.8 * orad) ** 2 for ox, oy, orad in mask_out)]
    ratio = m.mu_px * m.radius**3 / (mu1 * R1**3) if mu1 is not None else 2.0
    # (a blob whose background was disturbed holds some of what disturbed it: a
    # tube's wall under three touching spheres read 6.7 spheres' attenuation)
    most = max(_parts_cap(m) + 0.6, 3.6 * len(inside)) * (2 if "clutter" in m.flags else 1)
    if not 1.4 <= ratio <= most:
        return None
    mu0 = mu1 if mu1 is not None else m.mu_px
    grow = dict(m=m, R1=R1, mu1=mu1, mu0=mu0, ratio=ratio, blur=blur, noise=noise, kappa=max(kappa, 1.0),
                mask_out=mask_out, invalid=invalid)
    # (a crowd flags its blobs clutter too: only a background a quadratic does
    # not follow, its neighbours masked, is an edge)
    if "clutter" not in m.flags or not structured(a, m.x, m.y, m.radius, blur, noise, invalid, mask_out):
        parts = _grow(a, **grow)
        return None if parts is None else (parts, False)
    start = np.array([[m.x, m.y, m.radius, mu0]])
    for _ in range(2):
        prof = fit_profile(a, start, blur, noise, invalid, mask_out)
        if prof is None:   # no edge beside it: a curved background (a tube seen along its wall)
            parts = _grow(a, quadratic=True, **grow)
            return None if parts is None else (parts, False)
        (c0, q0, c1, q1), bg, _ = prof
        clean = a.copy()
        clean[q0:q1, c0:c1] -= bg
        parts = _grow(clean, keep_inadequate=True, **grow)
        if parts is None:
            return None
        best, adequate = parts
        if adequate:
            return best, True
        # the parts of a sphere's size and contrast start the profile again
        start = best[_plausible(best, R1, mu1)]
        if len(start) < 2:
            return None
    return None


def split_all(a: np.ndarray, ms: list, classes, mu1, blur: float, noise: float, kappa: float, invalid, peaks,
              near_of) -> dict:
    """Blobs ``ms`` each :func:`split` (tried at each sphere radius of
    ``classes`` px, the first that splits it): id(blob) -> (the shadows
    around it, ``near_of(blob)``; the split or None). With no shadow
    measured alone (``mu1`` None: a grid's rows seen edge-on, every sphere
    overlapping) the splits that explained their blobs give the frame's
    contrast, with which the others are split again: without it a split may
    hold only twice one sphere's attenuation (a row of seven came out in
    threes, most of it lost); a long chain waits for that contrast, and
    when every blob is one, their peaks guess it for a first pass."""
    nears: dict = {}

    def splits(group: list, mu) -> dict:
        out = {}
        for m in group:
            # (a blob split again keeps the neighbours found the first time)
            near = nears[id(m)] = nears[id(m)] if id(m) in nears else near_of(m)
            found = None
            for Rc in classes:
                found = split(a, m, Rc, mu, blur, noise, kappa, near, invalid, peaks)
                if found is not None:
                    break
            out[id(m)] = near, found
        return out

    def contrasts(split_of: dict) -> list:
        """The contrasts (mu per px of chord) of the parts of the splits had."""
        return [p[3] for _, f in split_of.values() if f is not None for p in f[0]]

    split_of = splits([m for m in ms if mu1 is not None or m.anisotropy < LONG_CHAIN], mu1)
    if mu1 is None:
        wait = [m for m in ms if id(m) not in split_of]
        mus = contrasts(split_of)
        if len(mus) < _CONTRAST_PARTS and wait:
            # (nothing but long chains, every sphere in one: their peaks guess the
            # contrast, a sphere's central chord 2 R mu, or up to 1.5x that where two
            # overlap; the parts of the splits it allows give it. A frame of three
            # rows seen edge-on kept one of them)
            first = splits(wait, float(np.median([m.peak for m in wait])) / (2 * classes[0]))
            mus = contrasts(first)
            if len(mus) >= _CONTRAST_PARTS:
                split_of.update(first)
                wait = [m for m in wait if first[id(m)][1] is None]
        if len(mus) >= _CONTRAST_PARTS:
            again = wait + [m for m in ms if id(m) in split_of and split_of[id(m)][1] is None]
            split_of.update(splits(again, float(np.median(mus))))
        else:
            split_of.update(splits(wait, None))
    return split_of


def _parts_cap(m) -> int:
    """The most spheres blob ``m`` is split into: more in a long chain."""
    return _MAX_CHAIN if m.anisotropy >= LONG_CHAIN else _MAX_PARTS


def _plausible(sph: np.ndarray, R1: float, mu1) -> np.ndarray:
    """Which spheres (k, 4) have the frame's size (0.6-1.6 ``R1``) and contrast (0.5-2 ``mu1``)."""
    ok = (sph[:, 2] > 0.6 * R1) & (sph[:, 2] < 1.6 * R1)
    return ok if mu1 is None else ok & (sph[:, 3] > 0.5 * mu1) & (sph[:, 3] < 2.0 * mu1)


def _grow(a, m, R1, mu1, mu0, ratio, blur, noise, kappa, mask_out, invalid, keep_inadequate=False, quadratic=False):
    """One sphere, then one more at a time (see the module docstring): the
    parts (k, 4), or None; with ``keep_inadequate`` (parts, adequate) when
    some were found, even if they do not explain the blob."""
    box = group_box(a.shape, np.array([[m.x, m.y, 1.5 * m.radius + 2, 0.0]]), blur)
    c0, q0, c1, q1 = box
    reach = 1.5 * m.radius + 2
    fit = fit_group(a, np.array([[m.x, m.y, m.radius, mu0]]), blur, noise, mask_out, invalid, box=box,
                    quadratic=quadratic)
    if fit is None:
        return None
    wgt = mask_weights(box, mask_out, blur, invalid)
    yy, xx = np.mgrid[q0:q1, c0:c1]
    disc = _disc(R1)
    best, steps = None, []
    if m.anisotropy >= LONG_CHAIN and mu1 is not None:
        whole, seed = _long_chain(a, fit, box, wgt, m, R1, mu0, ratio, blur, noise, kappa, mask_out, invalid, reach,
                                  quadratic)
        if whole is not None:
            return (whole, True) if keep_inadequate else whole
        # (growing a row of eight from one sphere again took eight steps of
        # several fits each, 2-3 s; from the start's spheres, one or two)
        if seed is not None:
            fit = seed
            best = fit[1]
            steps.append(fit)
    while len(fit[1]) < min(_parts_cap(m), int(np.ceil(ratio)) + 1):
        _, sph, _, bg, chi2, n = fit
        # the next part inside the blob or touching a part found: beyond, the
        # residual's peak is a wall's or a neighbour's, and a part started there wanders off
        new = np.array([[*_residual_peak(a, fit, blur, wgt, disc, _within(xx, yy, m, reach, sph, R1)), R1, mu0]])
        start = np.vstack([sph, new])
        start[:, 2] = np.minimum(start[:, 2], 1.3 * R1)
        starts = [start]
        if len(sph) == 1:
            # two shadows nearly on top of each other: the one sphere sits between
            # them, so the second start is symmetric about it
            twin = start.copy()
            twin[0, :2] = 2 * sph[0, :2] - new[0, :2]
            twin[0, 2:] = R1, mu0
            starts.append(twin)
        # (a chain seen along its axis: k started evenly along the blob's long axis,
        # where a greedy start beside a first sphere swollen over two goes astray)
        chain = _axis_chain(a, box, bg, quadratic, wgt, m, R1, mu0, len(sph) + 1)
        nxt = _best_within(a, starts + ([chain] if chain is not None else []) + _halves(sph, R1, mu0), m, reach,
                           R1, blur, noise, mask_out, invalid, box, quadratic)
        if nxt is None:
            break
        nxt = _new_last(nxt, sph)
        gain = (chi2 - nxt[4]) / kappa
        energy = float(np.sum((render_box(box, nxt[1][-1:], blur) * wgt / noise) ** 2)) / kappa
        # (two shadows nearly on top of each other share most of their energy
        # with the one sphere fitted first; their pair takes most of its misfit)
        if gain < 4 * np.log(n) + 10 or (gain < _EARN * energy and nxt[4] > 0.25 * chi2
                                          and not _contrast_restored(sph, nxt[1], mu1, nxt[4] / chi2)):
            break
        fit = nxt
        best = nxt[1]
        steps.append(nxt)
    if best is None:
        return None
    if not np.all(_plausible(best, R1, mu1)):
        # parts fainter or larger than any of the frame's spheres that soaked up
        # the background after the last step whose parts are all spheres (a
        # holder's wall beside a pair: faint discs of 2-3x the radius)
        ok = [f for f in steps if np.all(_plausible(f[1], R1, mu1))]
        if ok:
            fit, best = ok[-1], ok[-1][1]
    # the parts must explain the blob to within twice the pixel noise (a
    # rod or a plate's corner is no sum of spheres; on an independent helix
    # every right split reached chi2/n = 0.9-1.7), or, on a background that
    # holds structure of its own (a wall's edge the profile follows only
    # roughly), as well as the background model explains the patch around them
    plausible = bool(np.all(_plausible(best, R1, mu1)))
    adequate = plausible and fit[4] / fit[5] <= ADEQUATE
    if plausible and not adequate:
        adequate = _misfit_over(a, fit, blur, noise, mask_out, invalid) <= 1.0
    if keep_inadequate:
        return best, adequate
    return best if adequate else None


def _long_chain(a, fit, box, wgt, m, R1: float, mu1: float, ratio: float, blur: float, noise: float, kappa: float,
                mask_out, invalid, reach: float, quadratic: bool) -> tuple:
    """A long chain's parts (k, 4) started at once along its axis
    (:func:`_axis_chain`), for the k its attenuation holds (``ratio``) and
    one either side, the k that BIC prefers (the growth's bar per sphere):
    (parts, None) when those parts are the frame's spheres (:func:`_plausible`)
    and explain the blob (as :func:`_grow` asks); else (None, the fit the
    growth goes on from: that k's, or the spheres of the start that held
    most, refitted; None when no start held two). A grid's row of seven
    seen edge-on grown one sphere at a time took seven steps of several
    fits each (2-3 s a row)."""
    bg = fit[3]
    best, score, seed = None, np.inf, (0, None)
    for k in range(max(int(round(ratio)) - 1, 2), min(int(round(ratio)) + 1, _MAX_CHAIN) + 1):
        start = _axis_chain(a, box, bg, quadratic, wgt, m, R1, mu1, k)
        f = None if start is None else fit_group(a, start, blur, noise, mask_out, invalid, box=box, quadratic=quadratic)
        if f is None or not _anchored(f[1], m, reach, R1):
            continue
        # (a part that swelled faint over the background is no sphere: an eighth on a row of seven)
        ok = _plausible(f[1], R1, mu1)
        if ok.sum() > seed[0]:
            seed = int(ok.sum()), f
        if not np.all(ok):
            continue
        sc = f[4] / kappa + (4 * np.log(f[5]) + 10) * k
        if sc < score:
            best, score = f, sc
    if best is not None and (best[4] / best[5] <= ADEQUATE
                             or _misfit_over(a, best, blur, noise, mask_out, invalid) <= 1.0):
        return best[1], None
    if best is None and seed[1] is not None and seed[0] >= 2:
        # the spheres of the start that came closest, refitted without its strays
        f = seed[1]
        best = fit_group(a, f[1][_plausible(f[1], R1, mu1)], blur, noise, mask_out, invalid, box=box,
                         quadratic=quadratic)
    return None, best


def grow_group(a, fit, R1: float, mu1, mu0: float, blur: float, noise: float, kappa: float, mask_out, invalid,
               quadratic: bool, most: int):
    """A group's joint ``fit`` (:func:`fit_group`) with up to ``most`` spheres
    added, one at a time, where the model does not explain the group's
    shadows (misfit on the discs over ``ADEQUATE`` and over that around
    them): each at the matched filter's peak of the residual touching a
    member, kept when it earns its place as a split's part must (chi-square
    falls by ``_EARN`` of its own model's energy and beyond chance) and has
    a sphere's size and contrast (:func:`_plausible`; ``mu0`` starts it).
    A grid's row seen edge-on, seven shadows a third overlapping, had
    candidate peaks for four: its fit misfitted 33x the noise, the
    centres 2-5 px off at σ 0.5. The added spheres are its last members;
    unless they bring the misfit down to ``ADEQUATE`` (or that around,
    :func:`_misfit_over`), as a split's parts must, none is added (an intensifier's profile, which no
    sphere model follows to the noise, had a sphere added between three,
    its neighbours moved 2.4-3.7 px)."""
    if _misfit_over(a, fit, blur, noise, mask_out, invalid) <= _LEFT_OUT:
        return fit
    first, disc = fit, _disc(R1)
    for _ in range(most):
        box, sph, _, bg, chi2, n = fit
        c0, q0, c1, q1 = box
        wgt = mask_weights(box, mask_out, blur, invalid)
        yy, xx = np.mgrid[q0:q1, c0:c1]
        near = np.zeros(wgt.shape, bool)
        for x, y, R, _ in sph:
            near |= (xx - x) ** 2 + (yy - y) ** 2 <= (R + R1) ** 2
        start = np.vstack([sph, [[*_residual_peak(a, fit, blur, wgt, disc, near), R1, mu0]]])
        nxt = fit_group(a, start, blur, noise, mask_out, invalid, box=box, quadratic=quadratic)
        if nxt is None:
            break
        gain = (chi2 - nxt[4]) / kappa
        energy = float(np.sum((render_box(box, nxt[1][-1:], blur) * wgt / noise) ** 2)) / kappa
        # (beside its members, not in one's shadow: spheres nearly on top of each
        # other are the pairs' to fit (:mod:`.pairs`), which a part added there hid)
        gaps = np.hypot(*(nxt[1][:-1, :2] - nxt[1][-1, :2]).T) / (nxt[1][:-1, 2] + nxt[1][-1, 2])
        if (gain < 4 * np.log(n) + 10 or gain < _EARN * energy or not _plausible(nxt[1][-1:], R1, mu1)[0]
                or np.min(gaps) < _BESIDE):
            break
        fit = nxt
        if _misfit_over(a, fit, blur, noise, mask_out, invalid) <= 1.0:
            return fit
    return first


def _misfit_over(a, fit, blur: float, noise: float, mask_out, invalid) -> float:
    """A joint fit's misfit on its discs (:func:`disc_misfit`) over what
    explains them: ``ADEQUATE``, or the misfit around them where more."""
    on, off = disc_misfit(a, fit, blur, noise, mask_out, invalid)
    return on / max(ADEQUATE, off if np.isfinite(off) else 0.0)


def _residual_peak(a, fit, blur: float, wgt, disc, allowed) -> tuple[float, float]:
    """Where (x, y frame px) the matched filter ``disc`` peaks on what the
    joint ``fit`` leaves of ``a`` (pixels weighed by ``wgt``), among the
    ``allowed`` pixels of its patch: the next sphere's start."""
    box, sph, _, bg, _, _ = fit
    c0, q0, c1, q1 = box
    resid = (a[q0:q1, c0:c1] - group_model(box, sph, bg, blur)) * wgt
    score = cv2.filter2D(resid.astype(np.float32), -1, disc, borderType=cv2.BORDER_CONSTANT)
    score[~allowed] = -np.inf
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return float(c0 + ix), float(q0 + iy)


def _halves(sph: np.ndarray, R1: float, mu0: float) -> list:
    """Starts (k + 1, 4) in which a part too wide or too faint for one of
    the frame's spheres (radius over 1.3 ``R1``, contrast under half
    ``mu0``) is two, placed along the line from its nearest part: two
    spheres of a chain seen along its axis, which one disc covered (the
    residual's peak then lies elsewhere, on a wall)."""
    out = []
    if len(sph) < 2:
        return out
    for w in np.flatnonzero((sph[:, 2] > 1.3 * R1) | (sph[:, 3] < 0.5 * mu0)):
        rest = np.delete(sph, w, axis=0)
        near = rest[np.argmin(np.hypot(rest[:, 0] - sph[w, 0], rest[:, 1] - sph[w, 1]))]
        u = sph[w, :2] - near[:2]
        if not np.any(u):
            continue
        d = max(sph[w, 2] - R1, 0.5 * R1) * u / np.hypot(*u)
        out.append(np.vstack([rest, [*(sph[w, :2] + d), R1, mu0], [*(sph[w, :2] - d), R1, mu0]]))
    return out


def _best_within(a, starts, m, reach: float, R1: float, blur, noise, mask_out, invalid, box, quadratic: bool):
    """The lowest-chi2 joint fit from ``starts`` whose parts all stay within
    ``reach`` px of blob ``m`` or touch one that does (:func:`_anchored`; a
    part that wandered out went to fit something else), or None."""
    best = None
    for st in starts:
        f = fit_group(a, st, blur, noise, mask_out, invalid, box=box, quadratic=quadratic)
        if f is not None and _anchored(f[1], m, reach, R1) and (best is None or f[4] < best[4]):
            best = f
    return best


def _within(xx, yy, m, reach: float, sph: np.ndarray, R1: float) -> np.ndarray:
    """Where the next part may start: inside the blob's reach, or touching a
    part already found (a chain seen along a helix's axis runs beyond the
    one peak it was found by)."""
    ok = (xx - m.x) ** 2 + (yy - m.y) ** 2 <= reach**2
    for x, y, R, _ in sph:
        if R <= 1.6 * R1:
            ok |= (xx - x) ** 2 + (yy - y) ** 2 <= (R + R1) ** 2
    return ok


def _anchored(sph: np.ndarray, m, reach: float, R1: float) -> bool:
    """Whether every part lies within ``reach`` of blob ``m`` or touches,
    through a chain of touching parts of a sphere's size (radius at most
    1.6 ``R1``), one that does."""
    d = np.hypot(sph[:, 0] - m.x, sph[:, 1] - m.y)
    reached = d <= reach
    gap = np.hypot(sph[:, None, 0] - sph[None, :, 0], sph[:, None, 1] - sph[None, :, 1])
    r = np.where(sph[:, 2] <= 1.6 * R1, sph[:, 2], -np.inf)
    touch = gap <= r[:, None] + r[None, :] + 1.0
    for _ in range(len(sph)):
        reached = reached | np.any(touch & reached[None, :], axis=1)
    return bool(np.all(reached))


def _new_last(fit, before: np.ndarray):
    """``fit`` with its parts ordered so that the one farthest from every
    sphere of ``before`` (the one added) is last."""
    sph = fit[1]
    d = np.min(np.hypot(sph[:, None, 0] - before[None, :, 0], sph[:, None, 1] - before[None, :, 1]), axis=1)
    order = np.r_[np.delete(np.arange(len(sph)), int(np.argmax(d))), int(np.argmax(d))]
    return (fit[0], sph[order], fit[2][order], *fit[3:])


def _axis_chain(a, box, bg, quadratic: bool, wgt, m, R1: float, mu0: float, k: int) -> np.ndarray | None:
    """``k`` spheres (k, 4) started evenly along blob ``m``'s long axis, from
    the second moments of what stands above the fit's background ``bg``: k
    equal discs a distance s apart add s^2 (k^2 - 1) / 12 to the variance
    along their axis only. A start that does not rest on the spheres fitted
    so far, which a background they cannot follow (a tube's end beside a
    pair) or a first sphere swollen over two pulls aside. A long chain's
    moments are taken over its own shadow only (:func:`_own_shadow`; on a
    shorter blob that moved a helix bead 0.4 px)."""
    c0, q0, c1, q1 = box
    h, w = q1 - q0, c1 - c0
    yy, xx = np.mgrid[q0:q1, c0:c1]
    p = (a[q0:q1, c0:c1] - (background_basis(h, w, quadratic) @ bg).reshape(h, w)) * wgt
    p = np.where((xx - m.x) ** 2 + (yy - m.y) ** 2 <= (m.radius + R1 * k) ** 2, np.maximum(p, 0.0), 0.0)
    if m.anisotropy >= LONG_CHAIN:
        p = p * _own_shadow(p, m.x - c0, m.y - q0, m.radius, R1 * mu0)
    W = float(p.sum())
    if W <= 0:
        return None
    cx, cy, cov = weighted_moments(p, xx, yy)
    ev, evec = np.linalg.eigh(cov)
    s = float(np.sqrt(max(12 * (ev[1] - ev[0]) / (k * k - 1), 0.0)))
    if s < 1.0:
        return None
    e = evec[:, 1]
    off = (np.arange(k) - (k - 1) / 2) * s
    return np.column_stack([cx + off * e[0], cy + off * e[1], np.full(k, R1), np.full(k, mu0)])


def _own_shadow(p: np.ndarray, x: float, y: float, radius: float, level: float) -> np.ndarray:
    """Where a blob's own shadow lies (bool, shaped like ``p``): the connected
    region of ``p`` over ``level`` (half a sphere's central chord) that
    holds most of ``p`` within ``radius`` of (x, y), patch px. A long
    chain's circle reaches the neighbouring rows of a grid seen edge-on,
    whose moments turned its axis across the rows (the start diverged)."""
    yy, xx = np.mgrid[0:p.shape[0], 0:p.shape[1]]
    near = (xx - x) ** 2 + (yy - y) ** 2 <= radius**2
    # (and over half the blob's highest: a plate's band under a row, which a
    # plane left, joined it over a sphere's half chord)
    level = max(level, 0.5 * float(p[near].max(initial=0.0)))
    n, lab = cv2.connectedComponents((p > level).astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.ones(p.shape, bool)
    mass = np.bincount(lab[near].ravel(), weights=p[near].ravel(), minlength=n)
    mass[0] = 0.0
    return lab == int(np.argmax(mass)) if mass.max() > 0 else np.ones(p.shape, bool)


def _disc(R: float) -> np.ndarray:
    """A sphere's chord profile of radius ``R`` px, unit sum (the matched filter)."""
    r = int(np.ceil(R))
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    k = np.sqrt(np.maximum(R * R - xx * xx - yy * yy, 0.0)).astype(np.float32)
    return k / k.sum()


def _contrast_restored(before: np.ndarray, after: np.ndarray, mu1, chi2_ratio: float) -> bool:
    """A single sphere fitted to two deeply overlapping shadows is too dense
    (their chords add up): the split is earned when it also takes most of the
    fit's misfit and brings every part (of one blob, or of a chain holding
    such a pair) back to the frame's contrast ``mu1``."""
    if mu1 is None or chi2_ratio > 0.7:
        return False
    return bool(np.any(before[:, 3] > 1.3 * mu1) and np.all((after[:, 3] > 0.75 * mu1) & (after[:, 3] < 1.3 * mu1)))
