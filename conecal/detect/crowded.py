"""One frame's markers, touching and merged shadows included.

:func:`detect_frame` measures every shadow alone (:mod:`.frame`), then
groups the shadows whose centroid windows meet and measures each again on
the frame with its neighbours' fitted models removed (:mod:`.overlap`),
splits a blob that holds several shadows into them (:mod:`.split`), and
measures candidate peaks a neighbour spoilt together with it. A shadow flagged clutter is
measured again with the background across an edge beside it (a plate's
step, a holder's wall: :mod:`.background`) fitted and removed. Units: px,
attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .frame import Blob, DetectOptions, detect_blobs, refine
from .background import fit_profile, structured
from .overlap import fit_group, groups_of, render_box
from .split import peaks_in, split

# the cone-beam shadow's centroid and the model circle's centre differ by
# ~0.02 px; a larger disagreement is the neighbours' models' error
_CONE_OFFSET_PX = 0.03
# a lone sphere's shadow: anisotropy 1.03 median, 1.10 at the 95th percentile
# on an independent helix; two shadows overlapping by 60-90 % read 1.08-1.5
_DEEP_ANISOTROPY = 1.06
# ... and its contrast per px of chord under 1.35x the frame's median; two
# shadows nearly on top of each other look like one sphere of up to 2x
_DEEP_DENSITY = 1.35


def detect_frame(a: np.ndarray, opt: DetectOptions) -> list[Blob]:
    """All sphere-like shadows in attenuation frame ``a`` (not yet filtered by
    contrast). Raises :class:`conecal.detect.frame.NonFiniteFrame` on NaN/inf."""
    kept, merged, spoilt, noise, invalid, peaks = detect_blobs(a, opt)
    if not opt.joint_overlaps or not (kept or merged or spoilt):
        return kept
    # a misshapen blob holding two or more candidate peaks is merged shadows
    two = [b for b in spoilt if len(peaks_in(b, peaks)) >= 2]
    merged = merged + two
    spoilt = [b for b in spoilt if b not in two]
    R1, mu1 = _typical(kept, opt)
    # a round-enough blob holding the attenuation of 1.4+ of the frame's spheres,
    # a little elongated or too dense, may be two shadows almost on top of each other
    # (a spoilt one too: its neighbour is what spoilt it)
    deep = [b for b in kept + spoilt if mu1 is not None and b.mu_px * b.radius**3 > 1.4 * mu1 * R1**3
            and (b.anisotropy > _DEEP_ANISOTROPY or b.mu_px > _DEEP_DENSITY * mu1)]
    seeds = _crowd_seeds(peaks, kept, R1, opt)
    spoilt = [b for b in spoilt if not any((b.x - x) ** 2 + (b.y - y) ** 2 < b.radius**2 for x, y in seeds)]
    out = measure_crowded(a, kept, merged, opt, noise, invalid, peaks, seeds, deep, spoilt) if kept or merged or seeds else []
    spoilt = [b for b in spoilt if not any(np.hypot(o.x - b.x, o.y - b.y) < b.radius for o in out)]
    # a misshapen clutter blob is kept only if removing an edge's background beside
    # it leaves a clean sphere shadow, away from every marker already found
    for b in spoilt:
        b2 = _beside_edge(a, b, opt, noise, invalid, _neighbours(b, out + spoilt, peaks, opt))
        if (b2 is not b and b2.anisotropy <= opt.max_anisotropy
                and all(np.hypot(b2.x - o.x, b2.y - o.y) > 0.8 * max(o.radius, b2.radius) for o in out)):
            out.append(b2)
    return out


def _typical(kept: list[Blob], opt: DetectOptions):
    """The frame's sphere radius (px) and contrast (attenuation per px of
    chord, None when no sphere stands alone): from its separate shadows, else
    the nominal size the options were made from."""
    ref = [b for b in kept if not b.flags] or kept
    if ref:
        return float(np.median([b.radius for b in ref])), float(np.median([b.mu_px for b in ref]))
    return float(np.sqrt(opt.diameter_px[0] * opt.diameter_px[1] / 0.96)) / 2, None


def _crowd_seeds(peaks, kept: list[Blob], R1: float, opt: DetectOptions) -> list:
    """Candidate peaks (x, y) that no shadow measured alone accounts for and
    that lie within touching reach of another shadow or such peak: shadows
    spoilt by a neighbour, to be measured with it (one per 0.8 R1)."""
    free: list = []
    for px, py in peaks:
        if any((px - b.x) ** 2 + (py - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in kept):
            continue
        if any((px - q[0]) ** 2 + (py - q[1]) ** 2 < (0.8 * R1) ** 2 for q in free):
            continue
        free.append((px, py))
    reach = 1.15 * 2 * R1 + 6 * opt.blur_px + 3
    pts = [(b.x, b.y) for b in kept] + free
    return [p for p in free if any(0 < (p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 < reach**2 for q in pts)]


def _unearned(a, sph: np.ndarray, idx: list, box, opt: DetectOptions, noise: float, others, invalid, chi2: float,
              R1: float, mu1) -> int | None:
    """Of the group's members ``idx`` not yet measured alone, the one the
    joint fit does not need: outside the frame's sphere sizes and contrasts,
    or whose removal raises chi-square by less than 0.3 of its own model's
    energy (a genuine shadow's is most of it; a phantom made of its
    neighbours' misfit explains little the neighbours do not). None when
    every one earns its place."""
    worst, worst_r = None, np.inf
    for n_i in idx:
        R, mu = sph[n_i, 2], sph[n_i, 3]
        if not (0.6 * R1 < R < 1.6 * R1) or (mu1 is not None and not 0.5 * mu1 < mu < 2.0 * mu1):
            return n_i
        rest = np.delete(sph, n_i, axis=0)
        fit0 = fit_group(a, rest, opt.blur_px, noise, others, invalid, box=box)
        energy = float(np.sum((render_box(box, sph[n_i:n_i + 1], opt.blur_px) / noise) ** 2))
        gain = (fit0[4] - chi2) if fit0 is not None else np.inf
        r = gain / max(energy, 1e-30)
        if r < worst_r:
            worst, worst_r = n_i, r
    return worst if worst_r < 0.3 else None


def measure_crowded(a: np.ndarray, kept: list[Blob], merged: list[Blob], opt: DetectOptions, noise: float,
                    invalid=None, peaks=(), seeds=(), deep=(), around=()) -> list[Blob]:
    """``kept`` with touching shadows re-measured together, merged blobs
    split, and the shadows at ``seeds`` (x, y: peaks a neighbour spoilt)
    measured with their neighbours; each re-measured blob carries the
    ``overlap`` flag. ``deep``: kept blobs that may be two shadows nearly on
    top of each other, replaced by their parts when a joint fit says so;
    ``around``: other blobs, kept out of the splits' backgrounds."""
    R1, mu1 = _typical(kept, opt)
    seeds = list(seeds)
    parts, gone = [], set()
    for m in list(merged) + list(deep):
        near = _neighbours(m, [*kept, *merged, *deep, *around], peaks, opt, 1.5 * m.radius + 2, 1.2 * R1)
        sph = split(a, m, R1, mu1, opt.blur_px, noise, opt.noise_kappa, near, invalid, peaks)
        if sph is None:
            continue
        gone.add(id(m))
        seeds = [p for p in seeds if (p[0] - m.x) ** 2 + (p[1] - m.y) ** 2 > (1.5 * m.radius + 2) ** 2]
        for x, y, R, mu in sph:
            parts.append(Blob(float(x), float(y), float(R), 0.0, float(mu), 0.0, 1.0, ["overlap"], 0.0))
    kept = [b for b in kept if id(b) not in gone]
    # two blobs' splits, or a split and a shadow measured alone, may hold the same sphere
    unique: list = []
    for p in parts:
        if all(np.hypot(p.x - o.x, p.y - o.y) > 0.6 * min(p.radius, o.radius) for o in kept + unique):
            unique.append(p)
    parts = unique
    blobs = kept + parts
    mu0 = mu1 if mu1 is not None else float(np.median([b.mu_px for b in kept])) if kept else None
    if mu0 is not None:
        blobs += [Blob(float(x), float(y), R1, 0.0, mu0, 0.0, 1.0, ["overlap"], 0.0) for x, y in seeds]
    out: list = list(blobs)
    new = set(range(len(kept), len(blobs)))     # split parts and seeds: kept only once measured
    trial = set(range(len(kept) + len(parts), len(blobs)))   # seeds: kept only if the joint fit needs them
    for g in groups_of(blobs, opt.blur_px):
        members = [blobs[i] for i in g]
        s0 = np.array([[b.x, b.y, b.radius, b.mu_px] for b in members])
        gx, gy = s0[:, 0].mean(), s0[:, 1].mean()
        reach = np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]) + 6 * opt.blur_px + 10
        others = [(b.x, b.y, b.radius) for j, b in enumerate(blobs)
                  if j not in g and (b.x - gx) ** 2 + (b.y - gy) ** 2 < (reach + 3 * b.radius) ** 2]
        ag = a
        ext = float(np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]))
        # an edge's background across a small group (a holder's wall), which the
        # joint fit's plane cannot follow, removed first (over a long chain one
        # direction of level lines does not hold, and the fit costs seconds)
        # (only where a member measured alone was disturbed: in a plain crowd the
        # neighbours' own misfit reads as structure and the profile takes it up)
        if len(g) <= 5 and ext <= 5 * np.max(s0[:, 2]) and any("clutter" in m.flags for m in members) \
                and structured(a, gx, gy, ext, opt.blur_px, noise, invalid, others):
            prof = fit_profile(a, s0, opt.blur_px, noise, invalid, others)
            if prof is not None:
                (pc0, pq0, pc1, pq1), bg, s0 = prof
                ag = a.copy()
                ag[pq0:pq1, pc0:pc1] -= bg
        fit = fit_group(ag, s0, opt.blur_px, noise, others, invalid)
        # a member never measured alone must earn its place in the joint fit
        while fit is not None and any(i in trial for i in g):
            drop = _unearned(ag, fit[1], [n for n, i in enumerate(g) if i in trial], fit[0], opt, noise, others,
                             invalid, fit[4], R1, mu1)
            if drop is None:
                break
            out[g[drop]] = None
            g = g[:drop] + g[drop + 1:]
            fit = fit_group(ag, np.delete(fit[1], drop, axis=0), opt.blur_px, noise, others, invalid) if g else None
        if fit is None:
            continue
        (c0, q0, c1, q1), sph, sig, _, _, _ = fit
        models = [render_box(fit[0], sph[i:i + 1], opt.blur_px) for i in range(len(g))]
        total = np.sum(models, axis=0)
        work = ag.copy()
        for n_i, i in enumerate(g):
            work[q0:q1, c0:c1] = ag[q0:q1, c0:c1] - (total - models[n_i])
            b = refine(work, sph[n_i, 0], sph[n_i, 1], sph[n_i, 2], opt, others, noise, invalid)
            x_fit, y_fit = sph[n_i, :2]
            # the joint fit treats pixels as independent: correlated noise scales it
            # px; an undetermined joint fit's sigma can be 1e200, whose square overflows
            s_fit = float(min(np.hypot(*np.minimum(np.abs(sig[n_i, :2]), 1e6)) / np.sqrt(2) * np.sqrt(opt.noise_kappa),
                              1e6))
            if b is not None and "clutter" in blobs[i].flags and np.hypot(b.x - x_fit, b.y - y_fit) <= 0.5 * sph[n_i, 2]:
                # an edge's background beside it (its neighbours' models removed):
                # the joint fit's plane did not follow it, so its centre is no check
                b2 = _beside_edge(work, b, opt, noise, invalid, others)
                if b2 is not b:
                    b2.flags = sorted(set(b2.flags) | {"overlap"})
                    out[i] = b2
                    new.discard(i)
                    continue
            if b is None or np.hypot(b.x - x_fit, b.y - y_fit) > 0.5 * sph[n_i, 2]:
                # the centroid cannot be had: the joint model's centre stands
                if not np.isfinite(s_fit) or s_fit > 0.5:
                    out[i] = None if i in new else blobs[i]
                    continue
                b = replace(blobs[i], x=float(x_fit), y=float(y_fit), radius=float(sph[n_i, 2]),
                            mu_px=float(sph[n_i, 3]), sigma=float(np.hypot(s_fit, _CONE_OFFSET_PX)))
            else:
                gap2 = (b.x - x_fit) ** 2 + (b.y - y_fit) ** 2
                excess = max(gap2 / 2 - b.sigma**2 - s_fit**2 - _CONE_OFFSET_PX**2, 0.0)
                b.sigma = float(np.sqrt(b.sigma**2 + excess))
            b.flags = sorted(set(b.flags) | {"overlap"})
            out[i] = b
            new.discard(i)
    out = [b for i, b in enumerate(out) if b is not None and i not in new]
    return [_beside_edge(a, b, opt, noise, invalid, _neighbours(b, out, peaks, opt)) if "overlap" not in b.flags
            else b for b in out]


def _neighbours(b: Blob, blobs: list[Blob], peaks, opt: DetectOptions, inside: float | None = None,
                r_peak: float | None = None) -> list:
    """(x, y, r) of the shadows and unmeasured candidate peaks near ``b``
    (within reach of its background patch), ``b`` itself excluded; peaks
    closer than ``inside`` px (default 0.8 of its radius; shadows: half of
    it) are its own, a
    peak's shadow is taken of radius ``r_peak`` px (default the largest
    nominal) and no shadow as larger than 1.5 times that (a misshapen
    blob's moment radius is no shadow's size)."""
    reach = 5 * b.radius + 6 * opt.blur_px + 8
    r_peak = opt.diameter_px[1] / 2 if r_peak is None else r_peak
    near = [(o.x, o.y, min(o.radius, 1.5 * r_peak)) for o in blobs
            if o is not b and (0.5 * b.radius if inside is None else inside) < np.hypot(o.x - b.x, o.y - b.y) < reach]
    own = 0.8 * b.radius if inside is None else inside
    return near + [(px, py, r_peak) for px, py in peaks
                   if own < np.hypot(px - b.x, py - b.y) < reach
                   and all(np.hypot(px - o[0], py - o[1]) > 0.8 * o[2] for o in near)]


def _beside_edge(a, b: Blob, opt: DetectOptions, noise: float, invalid, others=()) -> Blob:
    """A shadow flagged clutter measured again with the background across an
    edge beside it (a plate's step, a tube's wall) fitted and removed, when
    one is there and the centroid then passes the clutter tests; otherwise
    ``b`` as it was. ``others``: (x, y, r) of the shadows around it."""
    if "clutter" not in b.flags and not structured(a, b.x, b.y, b.radius, opt.blur_px, noise, invalid, others):
        return b
    fit = fit_profile(a, np.array([[b.x, b.y, b.radius, b.mu_px]]), opt.blur_px, noise, invalid, others)
    if fit is None:
        return b
    (c0, q0, c1, q1), bg, sph = fit
    x_fit, y_fit = sph[0, :2]
    work = a.copy()
    work[q0:q1, c0:c1] -= bg
    b2 = refine(work, b.x, b.y, b.radius, opt, others, noise, invalid)
    if b2 is None or "clutter" in b2.flags or np.hypot(b2.x - b.x, b2.y - b.y) > b.radius:
        return b
    gap2 = (b2.x - x_fit) ** 2 + (b2.y - y_fit) ** 2
    b2.sigma = float(np.sqrt(b2.sigma**2 + max(gap2 / 2 - b2.sigma**2 - _CONE_OFFSET_PX**2, 0.0)))
    return b2
