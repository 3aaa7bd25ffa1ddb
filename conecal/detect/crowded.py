"""One frame's markers, touching and merged shadows included.

:func:`detect_frame` measures every shadow alone (:mod:`.frame`), then
groups the shadows whose centroid windows meet and measures each again on
the frame with its neighbours' fitted models removed (:mod:`.overlap`),
splits a blob that holds several shadows into them (:mod:`.split`),
measures candidate peaks a neighbour spoilt together with it, and a strong
peak that no window could measure by the joint model alone. Lengths of a
wire or a screw taken for spheres are dropped (:mod:`.rod`). A shadow
flagged clutter is measured again with the background across an edge
beside it (a plate's step, a holder's wall) fitted and removed
(:mod:`.edge`). A marker whose σ covers a second sphere nearly on top, and
a blob of several spheres that nothing measured, are fitted as two or
three (:mod:`.pairs`). Units: px, attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .frame import ROUND_ANISOTROPY, chord_like, detect_blobs, refine, window_reach
from .options import Blob, DetectOptions
from .background import fit_profile, structured
from .centre import model_centre
from .edge import CONE_OFFSET_PX, beside_edge
from .rod import on_rods, rod_like, run_on
from .overlap import fit_group, group_box, groups_of, joint_sigma, member_views, neighbours, render_box
from .size import like_neighbours, nearest_shadows, size_classes, typical_sphere
from .pairs import elongation_bound, fit_covered, fit_lost, hidden_pairs, is_pair, unsplit_pair
from .seeds import crowd_seeds
from .split import LONG_CHAIN, grow_group, peaks_in, split_all

# A joint model's centre that no centroid confirms (a seed, a split part, or a
# shadow whose centroid cannot be had beside its neighbours) is off by more
# than the fit's σ says: 0.4 px RMS per axis for 8-15 px shadows with σ 0.09
# on the independent helix (benchmarks/RESULTS.md, "the tails of the overlap
# classes"); neither a refit with another background nor the member fitted
# alone finds it. That error, as a fraction of the radius, is part of σ
# (measured on the helix's seeds 0-1, checked on seeds 2-3).
_MODEL_ONLY_FRACTION = 0.08
# a lone sphere's shadow: anisotropy 1.03 median, 1.10 at the 95th percentile
# on an independent helix; two shadows overlapping by 60-90 % read 1.08-1.5
_DEEP_ANISOTROPY = 1.06
# ... and its contrast per px of chord under 1.35x the frame's median; two
# shadows nearly on top of each other look like one sphere of up to 2x
_DEEP_DENSITY = 1.35
# a group's patch wider than this many of its radii gets a quadratic background
_QUADRATIC_SPAN = 6.0
# a member of a long chain across a wall is measured with at most this many nearest neighbours
_LOCAL_NEIGHBOURS = 3
# the most seeds a failed joint fit is tried without, one at a time: beyond,
# every seed is left out at once (speckle read as 130 touching shadows took
# 130 fits of 4.5 s each)
_MAX_SEED_TRIES = 12
# a blob set aside as merged that holds one sphere's attenuation (0.6-1.4x the
# frame's) is one shadow, stretched: an image intensifier's periphery reads
# 1.19 (and one sphere 1.25) on a real C-arm recording; two shadows that far
# apart would hold twice the attenuation
_ONE_SPHERE_ANISOTROPY = 1.5


def detect_frame(a: np.ndarray, opt: DetectOptions) -> list[Blob]:
    """All sphere-like shadows in attenuation frame ``a`` (not yet filtered by
    contrast). Raises :class:`conecal.detect.frame.NonFiniteFrame` on NaN/inf."""
    kept, merged, spoilt, noise, invalid, peaks, strong = detect_blobs(a, opt)
    if not opt.joint_overlaps or not (kept or merged or spoilt):
        return kept
    # a misshapen blob holding two or more candidate peaks is merged shadows
    two = [b for b in spoilt if len(peaks_in(b, peaks)) >= 2]
    merged = merged + two
    spoilt = [b for b in spoilt if b not in two]
    R1, mu1 = typical_sphere(kept, opt)
    # a round-enough blob holding the attenuation of 1.4+ of the frame's spheres,
    # a little elongated or too dense, may be two shadows almost on top of each other
    # (a spoilt one too: its neighbour is what spoilt it)
    deep = [b for b in kept + spoilt if mu1 is not None and b.mu_px * b.radius**3 > 1.4 * mu1 * R1**3
            and (b.anisotropy > _DEEP_ANISOTROPY or b.mu_px > _DEEP_DENSITY * mu1)]
    seeds = crowd_seeds(peaks, kept, R1, opt, strong)
    # a peak as strong as a sphere's that no window measured (a textured
    # background left the window's moment negative, or its size off): the
    # joint model measures it alone, where it must earn its place as any seed
    # (a long chain's blob covers its strong peaks only along its axis: should
    # its split fail, they are the seeds that measure it)
    taken = [(b.x, b.y, max(b.radius, R1) if b.anisotropy < LONG_CHAIN else R1) for b in kept + merged + spoilt] + \
        [(x, y, R1) for x, y in seeds]
    for px, py in strong:
        if all((px - x) ** 2 + (py - y) ** 2 >= r * r for x, y, r in taken):
            seeds.append((px, py))
            taken.append((px, py, R1))
    # a seed where a shadow measured alone was disturbed (flagged clutter) is
    # measured as one: on a wall's edge, the edge's profile is removed first
    disturbed = {(x, y) for x, y in seeds if any((b.x - x) ** 2 + (b.y - y) ** 2 < b.radius**2
                                                 for b in spoilt + merged if "clutter" in b.flags)}
    spoilt = [b for b in spoilt if not any((b.x - x) ** 2 + (b.y - y) ** 2 < b.radius**2 for x, y in seeds)]
    out = measure_crowded(a, kept, merged, opt, noise, invalid, peaks, seeds, deep, spoilt,
                          disturbed) if kept or merged or seeds else []
    spoilt = [b for b in spoilt if not any(np.hypot(o.x - b.x, o.y - b.y) < b.radius for o in out)]
    # a misshapen clutter blob is kept only if removing an edge's background beside
    # it leaves a clean sphere shadow, away from every marker already found
    for b in spoilt:
        b2 = beside_edge(a, b, opt, noise, invalid, neighbours(b, out + spoilt, peaks, opt))
        if (b2 is not b and b2.anisotropy <= opt.max_anisotropy
                and all(np.hypot(b2.x - o.x, b2.y - o.y) > 0.8 * max(o.radius, b2.radius) for o in out)):
            out.append(b2)
    # a misshapen blob holding two or three spheres' attenuation that nothing
    # above measured (an 8-bit log display deepens overlaps beyond a sum of spheres)
    lost = spoilt + [b for b in merged if not any(np.hypot(o.x - b.x, o.y - b.y) < b.radius for o in out)]
    out += fit_lost(a, lost, out, opt, noise, invalid, peaks, R1, mu1, len(kept))
    # (a wire's or a screw's length that a seed or a split took for a sphere)
    out = [b for b, rod in zip(out, on_rods(a, out, opt.blur_px, invalid)) if not rod]
    out = [elongation_bound(b, opt.blur_px, opt.max_anisotropy) if "overlap" in b.flags else b for b in out]
    # (a centre without a sigma made the whole scan's markers file invalid)
    out = [b for b in out if np.isfinite((b.x, b.y, b.sigma)).all()]
    # (one shadow, one marker: a helix's bead was measured twice 0.05 px apart;
    # the surer stays, then is judged for hidden spheres (judged before, three
    # spheres' shadow lost to a part of it, σ 0.016 px 1 px from each)
    one: list[Blob] = []
    for b in sorted(out, key=lambda b: b.sigma):
        if all(np.hypot(b.x - o.x, b.y - o.y) > 0.25 * min(b.radius, o.radius) for o in one):
            one.append(b)
    out = hidden_pairs(a, [b for b in out if any(b is o for o in one)], opt.blur_px, opt.shadow_px, opt.depth_ratio)
    # a marker whose σ covers a second sphere (on top of it, or beside it in an
    # elongated shadow) is fitted as two or three, where they explain it
    out = fit_covered(a, out, opt, noise, invalid, peaks, R1, mu1)
    # a shadow that stands apart: its centre from its fitted model, 2-3x surer than its centroid (.centre)
    return [model_centre(a, b, opt, noise, invalid, neighbours(b, out, peaks, opt), (R1, mu1)) for b in out]


def _unearned(a, sph: np.ndarray, idx: list, box, opt: DetectOptions, noise: float, others, invalid, chi2: float,
              R1: float, mu1, quadratic: bool) -> int | None:
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
        fit0 = fit_group(a, rest, opt.blur_px, noise, others, invalid, box=box, quadratic=quadratic)
        energy = float(np.sum((render_box(box, sph[n_i:n_i + 1], opt.blur_px) / noise) ** 2))
        gain = (fit0[4] - chi2) if fit0 is not None else np.inf
        r = gain / max(energy, 1e-30)
        if r < worst_r:
            worst, worst_r = n_i, r
    return worst if worst_r < 0.3 else None


def measure_crowded(a: np.ndarray, kept: list[Blob], merged: list[Blob], opt: DetectOptions, noise: float,
                    invalid=None, peaks=(), seeds=(), deep=(), around=(), disturbed=()) -> list[Blob]:
    """``kept`` with touching shadows re-measured together, merged blobs
    split, and the shadows at ``seeds`` (x, y: peaks a neighbour spoilt)
    measured with their neighbours; each re-measured blob carries the
    ``overlap`` flag. ``deep``: kept blobs that may be two shadows nearly on
    top of each other, replaced by their parts when a joint fit says so;
    ``around``: other blobs, kept out of the splits' backgrounds;
    ``disturbed``: the seeds where a shadow measured alone was flagged
    clutter (they carry the flag into the joint fit). A seed touching no
    other shadow is fitted by itself and kept only with one sphere's
    attenuation (flagged clutter, not overlap); a split whose parts are a
    rod's lengths (:func:`conecal.detect.rod.rod_like`) is dropped."""
    R1, mu1 = typical_sphere(kept, opt)
    # (a phantom of two sphere sizes: a split or joint fit judged against the
    # frame's typical size alone lost two of its few large spheres touching)
    classes = size_classes(kept, opt.shadow_px, R1)
    seeds = list(seeds)
    parts, gone, singles, unsplit = [], set(), [], []

    split_of = split_all(a, [*merged, *deep], classes, mu1, opt.blur_px, noise, opt.noise_kappa, invalid, peaks,
                         lambda m: neighbours(m, [*kept, *merged, *deep, *around], peaks, opt, 1.5 * m.radius + 2, 1.2 * R1))
    for m in list(merged) + list(deep):
        near, found = split_of[id(m)]
        if found is None:
            is_deep = any(m is d for d in deep)
            # two shadows nearly on top of each other that no split separates
            # (an 8-bit log display deepens their overlap beyond a sum of
            # spheres): one marker between them, said to be one
            pair = unsplit_pair(m, opt.blur_px) if is_pair(m, R1, mu1, opt.blur_px) else None
            if pair is not None and is_deep:
                kept = [pair if b is m else b for b in kept]
            # (a deep blob is kept as measured alone: it is its own single)
            one = m if _one_sphere(m, kept) else \
                None if is_deep else _one_on_structure(a, m, kept, opt, noise, invalid, near, peaks)
            # (nothing measured alone there: a seed's joint fit measures it, and keeps its sigma)
            if pair is not None and (is_deep or one is m or one is None):
                unsplit.append(pair)
                one = pair if one is m else one
            if one is not None:
                singles.append(one)
            elif pair is None and not is_deep and "clutter" not in m.flags and len(own := peaks_in(m, peaks)) <= 1 \
                    and not run_on(a, np.array([[m.x, m.y, R1, 0.0]]), opt.blur_px, invalid, others=near).rod():
                # one sphere's attenuation that no split, window or pair claimed
                # (a lone bead whose noisy moments read elongated; not a wire's
                # length, and not across an edge, which the edge's profile
                # measures better): its peak is a seed, which the joint model
                # measures and which must earn its place (once: two merged
                # blobs may hold it)
                p = own[0] if own else (m.x, m.y)
                if all((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 >= (0.8 * R1) ** 2 for q in seeds):
                    seeds.append(p)
            continue
        sph, on_edge = found
        if rod_like(a, sph, opt.blur_px, [(b.x, b.y, b.radius) for b in kept if b is not m], invalid):
            continue   # a wire's or a screw's length, cut into spheres' lengths
        gone.add(id(m))
        seeds = [p for p in seeds if (p[0] - m.x) ** 2 + (p[1] - m.y) ** 2 > (1.5 * m.radius + 2) ** 2]
        # (the parts of a blob across an edge: their group removes the edge's profile first)
        flags = ["clutter", "overlap"] if on_edge else ["overlap"]
        parts.append([Blob(float(x), float(y), float(R), 0.0, float(mu), 0.0, 1.0, list(flags), 0.0)
                      for x, y, R, mu in sph])
    kept = [b for b in kept if id(b) not in gone]
    split_parts = [p for own in parts for p in own]
    for m in singles:
        # (two merged blobs around one sphere give it twice; a split part there is
        # the same sphere, which this blob measured alone holds better; two parts
        # there are two spheres the split saw where one was measured: they stand)
        if id(m) in gone or any(np.hypot(m.x - o.x, m.y - o.y) <= 0.8 * max(m.radius, o.radius) for o in kept):
            continue
        same = [p for p in split_parts if np.hypot(m.x - p.x, m.y - p.y) <= 0.8 * max(m.radius, p.radius)]
        if len(same) <= 1:
            parts = [[p for p in own if not any(p is q for q in same)] for own in parts]
            split_parts = [p for own in parts for p in own]
            kept.append(m)
    # (a seed on a shadow now measured alone is that shadow)
    seeds = [p for p in seeds if all((p[0] - m.x) ** 2 + (p[1] - m.y) ** 2 > (0.8 * m.radius) ** 2 for m in singles)]
    # two blobs' splits, or a split and a shadow measured alone, may hold the same
    # sphere (one split's own parts may lie closer: shadows nearly on top of each other)
    unique: list = []
    for own in parts:
        unique += [p for p in own if all(np.hypot(p.x - o.x, p.y - o.y) > 0.6 * min(p.radius, o.radius)
                                         for o in kept + unique)]
    parts = unique
    blobs = kept + parts
    # (no shadow measured alone, as on a wall: the disturbed blobs' contrast starts the seeds)
    rough = kept or [b for b in [*merged, *around] if b.mu_px > 0]
    mu0 = mu1 if mu1 is not None else float(np.median([b.mu_px for b in rough])) if rough else None
    if mu0 is not None:
        blobs += [Blob(float(x), float(y), R1, 0.0, mu0, 0.0, 1.0, ["clutter", "overlap"] if (x, y) in disturbed
                       else ["overlap"], 0.0) for x, y in seeds]
    out: list = list(blobs)
    new = set(range(len(kept), len(blobs)))     # split parts and seeds: kept only once measured
    trial = set(range(len(kept) + len(parts), len(blobs)))   # seeds: kept only if the joint fit needs them

    def measure(g: list, only: int | None = None) -> bool:
        """Group ``g`` (indices into blobs) measured together; its members'
        outcomes written to ``out`` (with ``only``: that member's alone).
        Whether a joint fit was had."""
        writes = {}   # index -> (blob or None, measured)
        members = [blobs[i] for i in g]
        s0 = np.array([[b.x, b.y, b.radius, b.mu_px] for b in members])
        gx, gy = s0[:, 0].mean(), s0[:, 1].mean()
        reach = np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]) + 6 * opt.blur_px + 10
        others = [(b.x, b.y, b.radius) for j, b in enumerate(blobs)
                  if j not in g and (b.x - gx) ** 2 + (b.y - gy) ** 2 < (reach + 3 * b.radius) ** 2]
        ag = a
        ext = float(np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]))
        # an edge's background across a small group (a holder's wall), which the
        # joint fit's plane cannot follow, removed first (only where a member
        # measured alone was disturbed: in a plain crowd the neighbours' own
        # misfit reads as structure and the profile takes it up)
        if _small(g, s0) and any("clutter" in blobs[i].flags for i in g) \
                and structured(a, gx, gy, ext, opt.blur_px, noise, invalid, others):
            prof = fit_profile(a, s0, opt.blur_px, noise, invalid, others)
            if prof is not None:
                (pc0, pq0, pc1, pq1), bg, s0 = prof
                ag = a.copy()
                ag[pq0:pq1, pc0:pc1] -= bg
        c0, q0, c1, q1 = group_box(a.shape, s0, opt.blur_px)
        # a long chain lies on a holder's curved wall, which a plane under it misfits by
        # more than its spheres' contrast (the fit then swells a sphere to follow the wall)
        quad = max(c1 - c0, q1 - q0) > _QUADRATIC_SPAN * np.mean(s0[:, 2])

        def refit(start, keep_n):
            return fit_group(ag, start[keep_n], opt.blur_px, noise, others, invalid, quadratic=quad) if keep_n else None

        def dropped(g, gone_n):
            """``g`` without its members at positions ``gone_n``, written as not had."""
            for n in gone_n:
                writes[g[n]] = (None, False)
            return [i for n, i in enumerate(g) if n not in gone_n]

        fit = refit(s0, list(range(len(g))))
        if fit is None and any(i in trial for i in g):
            # a seed that is no sphere (it fades to nothing or to a negative contrast
            # on a wall) sinks the joint fit: the group without the seed whose absence
            # fits best (chi-square on the whole group's patch: the first that fits
            # may be a real sphere's), else without any
            box = group_box(a.shape, s0, opt.blur_px)
            seeds = [n for n, i in enumerate(g) if i in trial]
            tries = [(n, fit_group(ag, np.delete(s0, n, axis=0), opt.blur_px, noise, others, invalid, box=box,
                                   quadratic=quad)) for n in (seeds if len(seeds) <= _MAX_SEED_TRIES else [])]
            # (the winning try is the group's fit: refitted on its own smaller patch, a faint seed
            # could collapse and sink it; a large sphere and a small one touching it were lost so)
            best = min([(f[4], n, f) for n, f in tries if f is not None], key=lambda t: t[0], default=None)
            fit = best[2] if best else refit(s0, [n for n in range(len(g)) if n not in seeds])
            g = dropped(g, [best[1]] if best else seeds)
        # a member never measured alone must earn its place in the joint fit
        while fit is not None and any(i in trial for i in g):
            drop = _unearned(ag, fit[1], [n for n, i in enumerate(g) if i in trial], fit[0], opt, noise, others,
                             invalid, fit[4], R1, mu1, quad)
            if drop is None:
                break
            fit = refit(fit[1], [n for n in range(len(g)) if n != drop])
            g = dropped(g, [drop])
        while fit is not None and not np.all(sized := np.any((fit[1][:, 2, None] > 0.5 * classes)
                                                             & (fit[1][:, 2, None] < 2.0 * classes), axis=1)):
            # a member swelled or shrank beyond any sphere of the frame: the joint model
            # followed something else (a wall). A seed that did is no sphere (dropped, the
            # rest fitted again); any other, and none of the centres is trusted: the
            # shadows measured alone stand, the others are not had
            bad = [n for n in np.flatnonzero(~sized) if g[n] in trial]
            if len(bad) < int(np.sum(~sized)):
                fit = None
                break
            fit = refit(fit[1], [n for n in range(len(g)) if n not in bad])
            g = dropped(g, bad)
        if fit is not None and len(g) == 1 and g[0] in lone:
            # a seed with no neighbour claims one sphere, so it must carry one
            # sphere's attenuation: two shadows nearly on top of each other
            # fitted as one read 3.6 px from either (and with no shadow
            # measured alone to compare with, no claim)
            x, y, R, mu = fit[1][0]
            ref = [b for b in kept if not b.flags] or kept
            if not ref or not like_neighbours(R, mu, nearest_shadows(x, y, ref), sized=False):
                fit = None
        if fit is not None and len(g) >= 2 and mu0 is not None and only is None:
            # (spheres the group's peaks left out: each added member is measured as a split's part is)
            fit = grow_group(ag, fit, R1, mu1, mu0, opt.blur_px, noise, max(opt.noise_kappa, 1.0), others, invalid,
                             quad, len(g))
            extra = list(range(len(blobs), len(blobs) + len(fit[1]) - len(g)))
            # (in place: the groups' indices and the closure's lists stay theirs)
            blobs.extend(Blob(float(x), float(y), float(R), 0.0, float(mu), 0.0, 1.0, ["overlap"], 0.0)
                         for x, y, R, mu in fit[1][len(g):])
            out.extend(blobs[len(out):])
            new.update(extra)
            g = g + extra
        if fit is None:
            for i in g:
                writes[i] = (None, False) if i in new else (replace(blobs[i], flags=sorted(set(blobs[i].flags)
                                                                                         | {"overlap"})), True)
        else:
            (c0, q0, c1, q1), sph, sig, _, _, _ = fit
            models = [render_box(fit[0], sph[i:i + 1], opt.blur_px) for i in range(len(g))]
            work, views = ag.copy(), member_views(ag, fit, models)
            for n_i, i in enumerate(g):
                if only is not None and i != only:
                    continue
                work[q0:q1, c0:c1] = views[n_i]
                writes[i] = _member(work, blobs[i], sph[n_i], sig[n_i], opt, noise, invalid, others, i in new)
        for i, (b, measured) in writes.items():
            if only is None or i == only:
                out[i] = b
                if measured:
                    new.discard(i)
        return fit is not None

    def _on_structure(a, g, s0) -> bool:
        """Whether the background around the group (its shadows and their
        neighbours masked) holds more than a quadratic follows (a member's
        clutter flag says little here: in a crowd its neighbours raise it)."""
        gx, gy = s0[:, 0].mean(), s0[:, 1].mean()
        ext = float(np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]))
        mask = [(b.x, b.y, b.radius) for b in blobs if (b.x - gx) ** 2 + (b.y - gy) ** 2 < (ext + 4 * R1) ** 2]
        return structured(a, gx, gy, ext / 3, opt.blur_px, noise, invalid, mask)

    groups = groups_of(blobs, opt.blur_px)
    grouped = {i for g in groups for i in g}
    # (a seed touching nothing: measured as a group of one)
    lone = set(trial - grouped)
    groups += [[i] for i in sorted(lone)]
    for g in groups:
        s0 = np.array([[blobs[i].x, blobs[i].y, blobs[i].radius] for i in g])
        if _small(g, s0) or not _on_structure(a, g, s0):
            measure(g)
            continue
        # a long chain along a holder's wall: each member measured with its
        # nearest touching neighbours, where one edge's profile holds
        for n_i, i in enumerate(g):
            d = np.hypot(s0[:, 0] - s0[n_i, 0], s0[:, 1] - s0[n_i, 1])
            touch = window_reach(s0[:, 2], s0[n_i, 2], opt.blur_px)
            near = [g[j] for j in np.argsort(d) if j != n_i and d[j] < touch[j]][:_LOCAL_NEIGHBOURS]
            # (a fit that fails with its farthest neighbour may hold with the nearer
            # ones; not for a seed, which must earn its place among all of them)
            for k in range(len(near), -1, -1):
                if measure([i] + near[:k], only=i) or k <= 1 or i in trial:
                    break
    for i in lone:
        if out[i] is not None:
            # (no neighbour: the model stood in for a background the window could
            # not have, which is the clutter flag's meaning, not an overlap)
            out[i] = replace(out[i], flags=sorted((set(out[i].flags) - {"overlap"}) | {"clutter"}))
    out = [b for i, b in enumerate(out) if b is not None and i not in new]
    # (a pair measured again with its neighbours keeps what its elongation said)
    for p in unsplit:
        near = [n for n, b in enumerate(out) if np.hypot(b.x - p.x, b.y - p.y) < 0.5 * p.radius]
        for n in near:
            out[n] = replace(out[n], sigma=max(out[n].sigma, p.sigma), flags=sorted(set(out[n].flags) | {"overlap"}),
                             pair=True)
    return [beside_edge(a, b, opt, noise, invalid, neighbours(b, out, peaks, opt)) if "overlap" not in b.flags
            else b for b in out]


def _one_sphere(m: Blob, kept: list[Blob]) -> bool:
    """Whether a blob set aside as merged (too elongated, or a ridge-like
    peak) is one sphere's shadow after all, measured, not truncated and with
    a chord profile as good as the clutter test asks; either
    - the size (0.8-1.25x) and total attenuation (0.6-1.4x) of its four
      nearest shadows measured alone (near, because an intensifier magnifies
      its periphery), anisotropy at most ``_ONE_SPHERE_ANISOTROPY``; or
    - round (anisotropy at most ``ROUND_ANISOTROPY``) with their attenuation per px of
      chord (0.5-1.4x; a material's, whatever the size): a phantom's larger
      ball, whose flat top can read as a ridge. Two spheres on one line of
      sight that round would carry about twice that."""
    ref = [b for b in kept if not b.flags] or kept
    if len(ref) < 2 or "truncated" in m.flags or not np.isfinite(m.sigma) or m.snr <= 0:
        return False   # (a strong peak handed on unmeasured has no shape to judge)
    if not chord_like(m):
        return False
    near = nearest_shadows(m.x, m.y, ref)
    same = like_neighbours(m.radius, m.mu_px, near) and m.anisotropy <= _ONE_SPHERE_ANISOTROPY
    mu = m.mu_px / float(np.median([b.mu_px for b in near]))
    return same or (m.anisotropy <= ROUND_ANISOTROPY and 0.5 <= mu < 1.4)


def _one_on_structure(a, m: Blob, kept: list[Blob], opt: DetectOptions, noise: float, invalid, near,
                      peaks) -> Blob | None:
    """A blob set aside as merged that holds one candidate peak and no split,
    measured again with the background across an edge beside it removed (a
    holder's curved wall under a lone sphere leaves a plane's residual that
    the window's second moments weigh by rho^2: anisotropy 1.5-1.7 on shadows
    a quadratic background shows round); kept when it is then round, has a
    chord profile and :func:`_one_sphere`'s size and attenuation. Else None."""
    if len(peaks_in(m, peaks)) > 1 or "truncated" in m.flags:
        return None
    b = beside_edge(a, replace(m, flags=sorted(set(m.flags) | {"clutter"})), opt, noise, invalid, near)
    if b.anisotropy > opt.max_anisotropy or not np.isfinite(b.sigma) or not _one_sphere(b, kept):
        return None
    return b


def _small(g: list, s0: np.ndarray) -> bool:
    """A group of at most five shadows (x, y, R rows of ``s0``) within five
    radii: over a longer chain one direction of an edge's level lines does
    not hold, and the joint fit costs seconds."""
    gx, gy = s0[:, 0].mean(), s0[:, 1].mean()
    return len(g) <= 5 and float(np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2])) <= 5 * np.max(s0[:, 2])


def _member(work, b0: Blob, sph: np.ndarray, sig: np.ndarray, opt: DetectOptions, noise: float, invalid, others,
            unmeasured: bool) -> tuple:
    """One member of a joint fit measured on ``work`` (its neighbours' models
    removed): (blob or None, measured). ``b0``: the member as it was
    (measured alone, or a split part or seed when ``unmeasured``); ``sph``,
    ``sig``: its joint-fit sphere (x, y, R, mu) and σ."""
    b = refine(work, sph[0], sph[1], sph[2], opt, others, noise, invalid)
    x_fit, y_fit = sph[:2]
    s_fit = joint_sigma(sig, opt.kappa_for("model", sph[2]))
    if b is not None and "clutter" in b0.flags and np.hypot(b.x - x_fit, b.y - y_fit) <= 0.5 * sph[2]:
        # an edge's background beside it (its neighbours' models removed):
        # the joint fit's plane did not follow it, so its centre is no check
        b2 = beside_edge(work, b, opt, noise, invalid, others)
        if b2 is not b:
            b2.flags = sorted(set(b2.flags) | {"overlap"})
            return b2, True
    if b is None or np.hypot(b.x - x_fit, b.y - y_fit) > 0.5 * sph[2]:
        # the centroid cannot be had: the joint model's centre stands
        if not np.isfinite(s_fit) or s_fit > 0.5:
            return (None, False) if unmeasured else (b0, False)
        b = replace(b0, x=float(x_fit), y=float(y_fit), radius=float(sph[2]), mu_px=float(sph[3]),
                    sigma=float(np.sqrt(s_fit**2 + CONE_OFFSET_PX**2 + (_MODEL_ONLY_FRACTION * sph[2]) ** 2)))
    else:
        gap2 = (b.x - x_fit) ** 2 + (b.y - y_fit) ** 2
        excess = max(gap2 / 2 - b.sigma**2 - s_fit**2 - CONE_OFFSET_PX**2, 0.0)
        b.sigma = float(np.sqrt(b.sigma**2 + excess))
    b.flags = sorted(set(b.flags) | {"overlap"})
    return b, True
