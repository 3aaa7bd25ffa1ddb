"""Two or three spheres nearly on top of each other, in one shadow.

Where shadows overlap by more than half a diameter they make one round or
slightly elongated blob that the splits of :mod:`.split` do not separate. A
blob that may hide a second sphere is said to (its σ covers it: an unsplit
pair's elongation, a density beyond the frame's spheres', a stretch beyond
any sphere's), and where two or three spheres fitted jointly leave far less
misfit on their discs than one, with the markers pressed against it fitted
again with them, each sphere is measured by that joint fit
(:func:`fit_covered`). A blob that nothing measured is fitted the same way
where no sum of spheres fits it to the noise (an 8-bit log display), with
σ for the misfit left (:func:`on_top`'s ``lenient``). Units: px,
attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..stats import mad_sigma
from .frame import moment_trace
from .overlap import disc_misfit, fit_group, group_box, joint_sigma, neighbours
from .ring import ring_level
from .rod import line_of, run_on
from .size import class_radius, declared_radii, nearest_shadows, size_class, size_ratio
from .split import ADEQUATE

# a lone sphere's anisotropy is 1.03 median, 1.10 at the 95th percentile (an
# independent helix); one stretched by an intensifier's periphery read 1.07
_PAIR_ANISOTROPY = 1.1
# ... and across its long axis at least this fraction of one sphere's second
# moment: an 8-bit log display narrows two overlapping shadows to 0.56-0.72
# (an independent renderer's ball phantom)
_PAIR_NARROWEST = 0.5
# a blob this much denser (attenuation per px of chord) than the frame's spheres
# at its background's level may be two shadows nearly on top of each other: on
# an independent helix such pairs read 1.36-1.85, lone spheres 1.31 at most
# (3 of 1515 over 1.3); on log displays no lone sphere did, once the density's
# drift with the background is taken out (grid 1.09, ball phantom 1.2 at most)
_HIDDEN_DENSITY = 1.3
# ... holding at least this many of the frame's spheres' attenuation (its radius
# cubed, its excess density): a phantom's smaller spheres may read denser
_HIDDEN_ATTENUATION = 1.4
# a blob's background level (attenuation) is held when this close to three of
# the spheres the density's line was fitted on
_HIDDEN_LEVEL = 0.05
# ... unless so many blobs are that dense that they are a class of their own
# (spheres of a denser material)
_HIDDEN_RARE = 0.15
# a pair no split separates lies up to about this fraction of its radius
# from their midpoint (0.15-0.33 on the independent helix)
_HIDDEN_OFFSET = 0.25
# ... or a blob holding this many times one sphere's attenuation of its size
# class, and no declared sphere's (:func:`_heavy`)
_HEAVY = 1.45
# ... up to three spheres' (3 + noise): beyond it, one sphere of a larger size
# the declaration left out (a real box phantom's two large balls: 3.5-4.1)
_HEAVIEST = 3.2
# two spheres fitted where one marker's σ covered them (:func:`on_top`):
# at least this many of the frame's radii apart, explaining the blob this
# much better than one sphere, and off by this fraction of their radius
# beyond the joint fit's σ (the independent helix, seeds 2-3)
_TWO_APART = 0.15
_TWO_GAIN = 0.8
_TWO_MODEL = 0.02
# ... where the parts leave this many times less misfit on their discs than one
# sphere: pairs 0.2-0.5 of a diameter apart 1.7-12 on the helix (one sphere's
# misfit there 1.4-7.5x that around it, on the tube's curved background)
_ONE_MISFIT = 1.5
# where no sum of spheres fits a blob to the noise (an 8-bit log display), a
# third part must leave this many times less misfit on the discs than two
# (a chain of three 4.7; a pair's overlap, deeper than a sum, soaked up by a
# faint middle part 1.8-2.7: an independent renderer's ball phantom), and
# each part this much of the frame's contrast (such middle parts 0.62-0.95,
# a pair's part soaking up its partner 0.62; the right ones 0.83-1.2)
_THIRD = 3.5
_LENIENT_CONTRAST = 0.75
# an overlap marker whose σ exceeds this fraction of its radius may hide a
# second sphere beside it: fitted as two (a lone one's σ is 0.01-0.1 of it)
_COVERED = 0.2
# ... and the markers whose centres lie closer than this fraction of the
# radii's sum to it are fitted again with it (a pair beside a third sphere)
_PRESSED = 0.9
# a blob nothing measured holding this many of the frame's spheres'
# attenuation is fitted as two or three (:func:`fit_lost`), where the frame
# has this many shadows measured alone to say what its spheres are
_LOST_SPHERES = 1.4
_LOST_PEERS = 5
# a marker measured alone, elongated beyond a lone sphere (``_PAIR_ANISOTROPY``) and
# holding this many times the attenuation of its size class's nearest lone
# shadows may be two spheres 0.2-0.4 of a diameter apart, which no density or
# pair test sees: it is fitted as two (on the independent renderer's helix such
# markers read 1.19 and 1.3-1.4x and were 0.4-1.9 px off at σ 0.05-0.09; lone
# beads as elongated read 1.2x, and the fit as two refuses them)
_SUSPECT_ATTENUATION = 1.25
# ... or, with no lone shadow of its size class, this many times
# the frame's contrast per px of chord (the helix's pair of large beads 1.31)
_SUSPECT_DENSITY = 1.15
# the system's blur is known to about this fraction: parts nearly on top of each other
# trade their spacing for it at no cost in misfit (two large beads 0.3 of a diameter
# apart beside a third: 0.2-0.5 px for 25 %, chi-square within 10 %), so σ holds it
_BLUR_DOUBT = 0.25


def fit_covered(a, out: list, opt, noise: float, invalid, peaks, R1: float, mu1) -> list:
    """``out`` with each marker whose σ covers a second sphere (``pair``, or
    an overlap's σ over ``_COVERED`` of its radius) replaced by the two or
    three spheres :func:`on_top` fits, and the markers pressed against
    it (closer than ``_PRESSED`` of their radii's sum) by their refits, when
    no part falls on another marker; a part that holds two spheres' contrast
    is tried once more, beside its sibling. ``R1``, ``mu1``: the frame's
    sphere radius (px) and contrast."""
    res = list(out)
    lone, declared = _classes(out, opt)
    todo = [(b, True) for b in out
            if b.pair or ("overlap" in b.flags and b.sigma > _COVERED * b.radius) or _suspect(b, lone, mu1)]
    while todo:
        b, again = todo.pop(0)
        if not any(b is o for o in res):
            continue
        pressed = [o for o in res if o is not b and np.hypot(o.x - b.x, o.y - b.y) < _PRESSED * (o.radius + b.radius)]
        mask = [n for n in neighbours(b, res, peaks, opt)
                if all(np.hypot(n[0] - o.x, n[1] - o.y) > 0.5 * o.radius for o in pressed)]
        parts = on_top(a, b, (R1, class_radius(b, lone, R1, declared)), mu1, opt.blur_px, noise, _model_kappa(opt),
                       mask, invalid, pressed)
        rest = [o for o in res if o is not b and all(o is not q for q in pressed)]
        if parts and _clear(parts, rest, 0.5):
            res = rest + parts
            todo += [(p, False) for p in parts if p.pair and again]
    return res


def _classes(out: list, opt) -> tuple[list, list]:
    """The markers of ``out`` measured alone (unflagged) and the declared
    spheres' shadow radii (px) they show: what :func:`.size.class_radius`
    reads a blob's size class from."""
    return [b for b in out if not b.flags], declared_radii(out, opt.shadow_px)


def _model_kappa(opt):
    """The noise correlation factor of a sphere fit's centre, by its radius (px)."""
    return lambda R: opt.kappa_for("model", R)


def _suspect(b, lone: list, mu1) -> bool:
    """Whether marker ``b``, measured alone or beside a neighbour (flagged
    overlap or clutter or not), may be two spheres 0.2-0.4 of a diameter apart:
    elongated beyond a lone sphere and holding ``_SUSPECT_ATTENUATION`` of
    one sphere's attenuation of its size class (the median of its class's
    four nearest lone shadows, one or more: an intensifier magnifies its
    periphery, and a helix's large beads stand alone two to a frame), or,
    with none, ``_SUSPECT_DENSITY`` of the frame's contrast ``mu1`` (per px
    of chord)."""
    if mu1 is None or not np.isfinite(b.anisotropy) or not np.isfinite(b.sigma) or b.anisotropy <= _PAIR_ANISOTROPY:
        return False
    same = size_class(b, lone)
    if not same:
        return b.mu_px >= _SUSPECT_DENSITY * mu1
    near = nearest_shadows(b.x, b.y, same)
    return b.mu_px * b.radius**3 >= _SUSPECT_ATTENUATION * float(np.median([o.mu_px * o.radius**3 for o in near]))


def fit_lost(a, lost: list, out: list, opt, noise: float, invalid, peaks, R1: float, mu1, peers: int) -> list:
    """Markers for the blobs ``lost`` (misshapen or merged, which no window,
    split or pair measured) that hold ``_LOST_SPHERES`` or more of the
    frame's spheres' attenuation: the two or three spheres
    :func:`on_top` fits where no sum fits to the noise (``lenient``),
    with σ for the misfit that sum leaves, where no part falls on a marker
    of ``out``; each part has the frame's size or the blob's size class's
    (:func:`.size.class_radius`: two of a helix's large beads 0.65 of a diameter
    apart were lost against its small ones'). ``R1``, ``mu1``: the frame's
    sphere radius (px) and contrast, measured on ``peers`` shadows alone:
    none unless ``_LOST_PEERS`` or more (a real C-arm frame without the
    phantom took them from one blot, and a small elongated blot on the spine
    was two such spheres)."""
    new: list = []
    if peers < _LOST_PEERS or mu1 is None:
        return new
    lone, declared = _classes(out, opt)
    for b in lost:
        if b.mu_px * b.radius**3 < _LOST_SPHERES * mu1 * R1**3:
            continue
        parts = on_top(a, b, (R1, class_radius(b, lone, R1, declared)), mu1, opt.blur_px, noise, _model_kappa(opt),
                       neighbours(b, out + new + lost, peaks, opt), invalid, lenient=True)
        if parts and _clear(parts, out + new, 0.8):
            new += parts
    return new


def _clear(parts: list, others: list, share: float) -> bool:
    """Whether no part lies within ``share`` of the larger radius of any of ``others``."""
    return all(np.hypot(p.x - o.x, p.y - o.y) > share * max(p.radius, o.radius) for p in parts for o in others)


def _moments(m, blur: float) -> tuple[float, float]:
    """Blob ``m``'s principal second moments (px^2, major then minor), from
    its radius and anisotropy as :func:`conecal.detect.frame.refine` made them."""
    trace = moment_trace(m.radius, blur)
    minor = trace / (1 + m.anisotropy**2)
    return trace - minor, minor


def _stretch(m, blur: float, beyond: float = 1.0) -> float:
    """The half-separation h (px) that blob ``m``'s elongation beyond an
    anisotropy of ``beyond`` shows: two round shadows 2h apart along x have
    second moments c + h^2 and c."""
    major, minor = _moments(m, blur)
    lone = (major + minor) * (beyond**2 - 1) / (beyond**2 + 1)
    return float(np.sqrt(max(major - minor - lone, 0.0)))


def is_pair(m, R1: float, mu1, blur: float) -> bool:
    """Whether blob ``m`` (deep, or merged and no split found) is two of the
    frame's spheres (radius ``R1`` px, contrast ``mu1``; blur ``blur`` px)
    nearly on top of each other: across its long axis as narrow as one
    (``_PAIR_NARROWEST``-1.3x its second moment), holding 1.7-2.8 times one's
    attenuation, and elongated beyond a lone sphere (``_PAIR_ANISOTROPY``).
    A phantom's larger ball is as wide across as along; on an 8-bit log
    display a lone sphere on a thicker body holds up to 1.9x the attenuation
    (stretched to 1.07 by an intensifier's periphery); on a real intensifier
    recording lone spheres at the periphery read 1.5-1.56x at 1.11-1.18.
    A blob whose centroid has no sigma (a strong peak handed on unmeasured)
    says nothing of where a pair lies: never one."""
    if mu1 is None or m.anisotropy < _PAIR_ANISOTROPY or not np.isfinite(m.sigma):
        return False
    one = moment_trace(R1, blur) / 2
    return _PAIR_NARROWEST <= _moments(m, blur)[1] / one <= 1.3 and 1.7 <= m.mu_px * m.radius**3 / (mu1 * R1**3) <= 2.8


def unsplit_pair(m, blur: float):
    """Blob ``m``, the shadow of two spheres nearly on top of each other,
    flagged overlap, its sigma widened by the half-separation its elongation
    shows (:func:`_stretch`)."""
    return replace(m, sigma=float(np.hypot(m.sigma, _stretch(m, blur))), flags=sorted(set(m.flags) | {"overlap"}))


def elongation_bound(m, blur: float, most: float):
    """Blob ``m`` (flagged overlap: a neighbour's shadow within reach), more
    elongated than any sphere (anisotropy over ``most``), with its sigma at
    least the offset that its elongation beyond a lone sphere's
    (``_PAIR_ANISOTROPY``) shows (:func:`_stretch`). Two small spheres half
    overlapped hold one large sphere's attenuation on a phantom of two sizes,
    so no density test sees them; one such marker read sigma 0.5 px, 2.3 px
    from either sphere."""
    if not np.isfinite(m.anisotropy) or m.anisotropy <= most:
        return m
    h = _stretch(m, blur, _PAIR_ANISOTROPY)
    return replace(m, sigma=h) if h > m.sigma else m


def hidden_pairs(a: np.ndarray, blobs: list, blur: float, shadow_px=(), depth_ratio: float = 0.0) -> list:
    """``blobs`` with those that may be two shadows nearly on top of each
    other (a second sphere hidden within a fraction of the radius, which no
    split separates and no elongation shows) flagged overlap, their sigma at
    least their possible offset from either sphere (px): a blob far denser
    than the frame's spheres at its background's level, where few are; or,
    given the declared spheres' nominal shadow diameters ``shadow_px`` (px)
    and the phantom's ``depth_ratio`` (``DetectOptions.depth_ratio``), one
    holding more attenuation than one sphere of any declared size at any
    depth (:func:`_heavy`: spheres that lie a little apart make a wider,
    less dense shadow, which only its total attenuation tells from one).

    A blob's density (attenuation per px of chord) drifts with the
    background's level on a log or gamma display (1.4-1.7x on a plate's
    thick part): it is referred to a robust straight line of log density
    against the level (the median of a ring outside the shadow, other
    shadows left out), fitted over the frame's blobs, where spheres on a
    background of about its level hold the line."""
    if len(blobs) < 8:
        return blobs
    level = np.array([ring_level(a, b, blobs, blur) for b in blobs])
    dens = np.log(np.array([max(b.mu_px, 1e-12) for b in blobs]))
    ok = np.isfinite(level) & np.array([b.mu_px > 0 for b in blobs])
    if ok.sum() < 8:
        return blobs
    excess, held = _on_level_line(dens, level, ok)
    size = np.array([b.radius for b in blobs])
    dense = ok & held & (excess >= _HIDDEN_DENSITY) & (excess * (size / np.median(size)) ** 3 >= _HIDDEN_ATTENUATION)
    dense |= _heavy(blobs, level, ok, shadow_px, depth_ratio)
    if dense.sum() > _HIDDEN_RARE * len(blobs):
        return blobs
    out = list(blobs)
    for i in np.flatnonzero(dense):
        b = out[i]
        h = _stretch(b, blur) if np.isfinite(b.anisotropy) else 0.0
        out[i] = replace(b, sigma=float(np.hypot(b.sigma, max(h, _HIDDEN_OFFSET * b.radius))),
                         flags=sorted(set(b.flags) | {"overlap"}), pair=True)
    return out


def _on_level_line(v: np.ndarray, level: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """exp of each blob's ``v`` (a log quantity) over a robust straight line of
    ``v`` against the background's ``level`` (2.5 sigma MAD rejection; flat
    when the levels hardly differ), fitted on the ``ok`` blobs; and whether
    the line is held at the blob's level (three fitted blobs within
    ``_HIDDEN_LEVEL``). 0 and False where not ``ok``."""
    lv, dv = level[ok], v[ok]
    A = np.c_[np.ones(len(lv)), lv] if np.ptp(lv) > 0.02 else np.ones((len(lv), 1))
    keep = np.ones(len(lv), bool)
    for _ in range(3):
        line = np.linalg.lstsq(A[keep], dv[keep], rcond=None)[0]
        res = dv - A @ line
        keep_new = np.abs(res) <= 2.5 * mad_sigma(res) + 1e-9
        if keep_new.sum() < 8:
            break
        keep = keep_new
    line = np.r_[line, 0.0][:2]
    excess = np.where(ok, np.exp(v - line[0] - line[1] * np.where(ok, level, 0.0)), 0.0)
    # (no claim where the line is not held by spheres on a background of about
    # that level: a plate's thick part under two spheres, on a log display)
    held = np.array([np.sum(np.abs(lv[keep] - x) <= _HIDDEN_LEVEL) >= 3 if f else False for x, f in zip(level, ok)])
    return excess, held


def _heavy(blobs: list, level: np.ndarray, ok: np.ndarray, shadow_px, depth_ratio: float) -> np.ndarray:
    """Which blobs hold ``_HEAVY`` (at least 1.2 q^2, q = ``depth_ratio``:
    a sphere nearer the source casts a shadow q^2 times as heavy, its
    attenuation summed over pixels scaling with the shadow's area) to
    ``_HEAVIEST`` times the attenuation (density times radius cubed) of one
    sphere of their size class and not that of one sphere of any declared
    size at any depth (within 1/(1.4 q^2) to that): each blob is put in the
    class of the nearest nominal diameter
    ``shadow_px`` (px) at the frame's measured scale
    (:func:`.size.size_ratio`), and one sphere's attenuation is that of its
    four nearest shadows whose background's ``level`` is within
    ``_HIDDEN_LEVEL`` of its own (median; an intensifier magnifies its
    periphery, a log display deepens shadows on a thick background), scaled
    by the classes' diameters cubed; no claim with fewer than three. Beyond
    ``_HEAVIEST`` a blob is a larger sphere the declaration left out; a blob
    far stretched (anisotropy over 1.6) is left to the elongation's tests."""
    heavy = np.zeros(len(blobs), bool)
    d = np.unique(np.asarray(shadow_px, float))
    lo = max(_HEAVY, 1.2 * depth_ratio ** 2)
    if not d.size or ok.sum() < 8 or not depth_ratio or lo >= _HEAVIEST:
        return heavy
    r = np.array([b.radius for b in blobs])
    s = size_ratio(2 * r[ok], d) or 1.0
    c = np.abs(np.log(np.maximum(2 * r, 1e-9))[:, None] - np.log(s * d)[None, :]).argmin(1)
    unit = {id(b): max(b.mu_px, 1e-12) * b.radius ** 3 / d[k] ** 3 for b, k in zip(blobs, c)}
    ref = np.flatnonzero(ok)
    for i in ref:
        same = [blobs[j] for j in ref if j != i and abs(level[j] - level[i]) <= _HIDDEN_LEVEL]
        if len(same) < 3:
            continue
        near = nearest_shadows(blobs[i].x, blobs[i].y, same)
        # against one sphere of each class
        ratio = unit[id(blobs[i])] / np.median([unit[id(o)] for o in near]) * (d[c[i]] / d) ** 3
        one = np.any((ratio > 1 / (1.4 * depth_ratio ** 2)) & (ratio < lo))
        stretched = not np.isfinite(blobs[i].anisotropy) or blobs[i].anisotropy > 1.6
        heavy[i] = lo <= ratio[c[i]] <= _HEAVIEST and not one and not stretched
    return heavy


def on_top(a: np.ndarray, m, radii, mu1, blur: float, noise: float, kappa, mask_out, invalid,
           pressed=(), lenient: bool = False):
    """Blob ``m``, whose σ covers a second sphere nearly on top (``m.pair``) or
    beside it (an elongation beyond any sphere's), as two spheres, else three:
    fitted jointly, started evenly along four directions through its centre
    (a matched filter on the residual finds no second peak where two are
    0.2-0.5 of a diameter apart), with the markers ``pressed`` against it
    fitted again with them. The parts (Blobs flagged overlap, σ from the
    joint fit, correlated noise (``kappa``: its factor by a part's radius, px), ``_TWO_MODEL`` of the radius and
    how far the blur's doubt moves them (:func:`_blur_moves`) counted;
    ``m``'s first, then the pressed ones'), or None unless the parts leave
    ``_ONE_MISFIT`` times less misfit on their discs (:func:`disc_misfit`)
    than ``m`` fitted as one sphere, and no more than ``ADEQUATE`` or than
    around them, with chi-square ``_TWO_GAIN`` times one's or less (not
    asked with markers pressed against it: the patch around them all holds
    more background); each has a size of the frame's spheres (0.6-1.6 of
    one of ``radii``, px: the frame's and the blob's size class's,
    :func:`.size.class_radius`), lies ``_TWO_APART`` of the smallest
    or more from the others and holds the frame's contrast
    (0.6-1.6 ``mu1``) or, one at most, two spheres' (1.6-2.6); a part
    denser than ``_HIDDEN_DENSITY`` may hold one more hidden in it: flagged
    a pair, σ at least ``_HIDDEN_OFFSET`` of its radius. A lone sphere on a
    curved background gives parts on top of each other, or one of a few
    percent of its contrast soaking up the background: both refused.
    ``lenient``: for a blob nothing else measured, where no sum of spheres
    may fit (an 8-bit log display deepens overlaps):
    the parts need not fit to the noise, but each holds ``_LENIENT_CONTRAST``
    of the frame's contrast, three replace two only with ``_THIRD`` times less
    misfit, and σ grows with the square root of the misfit on the discs over
    that around them (everywhere, as the model's error)."""
    if mu1 is None or not np.isfinite(m.sigma):
        return None
    rest = np.array([[o.x, o.y, o.radius, o.mu_px] for o in pressed]).reshape(-1, 4)
    base = np.vstack([[[m.x, m.y, m.radius, m.mu_px]], rest])
    box = group_box(a.shape, base, blur) if len(rest) else None
    one = fit_group(a, base, blur, noise, mask_out, invalid, box=box, quadratic=True)
    if one is None:
        return None
    on1 = disc_misfit(a, one, blur, noise, mask_out, invalid)[0]
    major, minor = _moments(m, blur)
    found = None
    # k parts started evenly along a line at the spacing the elongation shows:
    # exact for two (major - minor = (spacing / 2)^2); three start 6 % closer
    # than three spheres evenly spaced would show (spacing^2 = 1.5 (major - minor))
    for k, spread in ((2, 1.0), (3, 1.5)):
        h = max(np.sqrt(max(major - minor, 0.0) / spread), 0.3 * m.radius)
        spacing = 2 * h / np.sqrt(k - 1)
        best = None
        for t in np.arange(4) * np.pi / 4:
            off = (np.arange(k) - (k - 1) / 2) * spacing
            start = np.c_[m.x + off * np.cos(t), m.y + off * np.sin(t), np.full(k, 0.85 * m.radius), np.full(k, mu1)]
            fit = fit_group(a, np.vstack([start, rest]), blur, noise, mask_out, invalid, box=one[0], quadratic=True)
            if fit is not None and (best is None or fit[4] < best[4]):
                best = fit
        got = _on_top_parts(a, [m] * k + list(pressed), best, one[4] if not len(rest) else None, on1, radii, mu1,
                            blur, noise, kappa, mask_out, invalid, lenient)
        # (two that fit to the noise are the answer; where no sum of spheres
        # does, three only if they leave _THIRD times less misfit than two)
        if got is not None and (found is None or got[1] * _THIRD <= found[1]):
            found = got
        if found is not None and not lenient:
            break
    if found is None:
        return None
    move = _blur_moves(a, found[0], blur, noise, mask_out, invalid, one[0])
    return [replace(p, sigma=float(np.hypot(p.sigma, d))) for p, d in zip(found[0], move)]


def _blur_moves(a, parts: list, blur: float, noise: float, mask_out, invalid, box) -> np.ndarray:
    """How far (px, RMS over the two) each of the jointly fitted ``parts``
    moves when they are fitted again on ``box`` with the blur ``_BLUR_DOUBT``
    smaller and larger: the part of their σ that the model's blur, known
    only so well, leaves. A fit that fails counts its parts as not moved."""
    start = np.array([[p.x, p.y, p.radius, p.mu_px] for p in parts])
    moves = np.zeros(len(parts))
    for f in (1 - _BLUR_DOUBT, 1 + _BLUR_DOUBT):
        fit = fit_group(a, start, blur * f, noise, mask_out, invalid, box=box, quadratic=True)
        if fit is not None:
            moves += np.sum((fit[1][:, :2] - start[:, :2]) ** 2, axis=1) / 2
    return np.sqrt(moves)


def _on_top_parts(a, was: list, fit, chi2_one, on_one: float, radii, mu1: float, blur, noise, kappa, mask_out,
                  invalid, lenient: bool = False):
    """:func:`on_top`'s parts from joint ``fit`` (each part from the
    marker ``was`` it stands for) and their misfit on the discs, or None
    when they fail its tests;
    ``chi2_one``, ``on_one``: the one-sphere fit's chi-square (None when
    markers were pressed against it) and misfit on the discs."""
    if fit is None:
        return None
    _, sph, sig, _, chi2, _ = fit
    dense = sph[:, 3] / mu1
    gaps = np.hypot(sph[:, None, 0] - sph[None, :, 0], sph[:, None, 1] - sph[None, :, 1])
    sizes = np.atleast_1d(np.asarray(radii, float))
    if (np.any(np.all((sph[:, 2, None] < 0.6 * sizes) | (sph[:, 2, None] > 1.6 * sizes), axis=1))
            or np.any((dense < (_LENIENT_CONTRAST if lenient else 0.6)) | (dense > 2.6))
            or np.sum(dense > 1.6) > 1 or np.min(gaps + np.eye(len(sph)) * 1e9) < _TWO_APART * sizes.min()
            or (chi2_one is not None and chi2 > _TWO_GAIN * chi2_one)):
        return None
    # (a part the joint fit cannot place within its own radius is no measurement:
    # beside an intensifier's dark surround a faint JPEG ripple was fitted as two
    # spheres of the frame's contrast that no pixel held, their σ 1e6 px)
    if not all(joint_sigma(s, kappa(R)) < R for (_, _, R, _), s in zip(sph, sig)):
        return None
    on, off = disc_misfit(a, fit, blur, noise, mask_out, invalid)
    if (on > max(ADEQUATE, off) and not lenient) or on * _ONE_MISFIT > on_one or _rod_part(a, sph, blur, invalid):
        return None
    # (the model's error grows with the misfit it leaves on the discs beyond that around them)
    misfit = max(on / max(off if np.isfinite(off) else 0.0, 1.0), 1.0)
    parts = []
    for (x, y, R, mu), s, d, w in zip(sph, sig, dense, was):
        sigma = float(np.hypot(joint_sigma(s, kappa(R)), _TWO_MODEL * R * np.sqrt(misfit)))
        # (a part denser than any one sphere may hold a second nearly on top:
        # under an intensifier's clipped core two balls 1.7 px apart read 1.42x,
        # one centre 0.6-1.1 px from each at σ 0.14)
        if d > _HIDDEN_DENSITY:
            sigma = float(np.hypot(sigma, _HIDDEN_OFFSET * R))
        parts.append(replace(w, x=float(x), y=float(y), radius=float(R), mu_px=float(mu), anisotropy=1.0,
                             sigma=sigma, flags=sorted(set(w.flags) | {"overlap"}), pair=bool(d > _HIDDEN_DENSITY)))
    return parts, on


def _rod_part(a: np.ndarray, sph: np.ndarray, blur: float, invalid) -> bool:
    """Whether joint parts ``sph`` (k, 4) lie along a rod: the shadow runs
    on past both ends of an outer part of their line (the first or last
    along it), at that part's level (:meth:`conecal.detect.rod.Run.runs_on`). A sphere lying on a wire,
    fitted with the wire's stretch beside it, gave parts of the frame's size
    and contrast along the wire (an independent renderer's ball phantom with
    wires); spheres overlapping, in a pair or a chain, end."""
    c, u = line_of(sph[:, :2])
    t = (sph[:, :2] - c) @ u
    # (along its own best direction: a sphere lying on the wire pulls the parts' line off it by 15 degrees)
    return any(run_on(a, sph[i:i + 1], blur, invalid).runs_on() for i in {int(np.argmin(t)), int(np.argmax(t))})
