"""The scan's shadow size measured on its own images.

The sizes detect looks for come from ``markers.diameter(s)`` and the nominal
magnification the user typed; a wrong guess of it (a C-arm's or a hand-placed
grid's source distances are rarely known to 25 %) changed which peaks were
candidates, the background rings and the crowd tests, so the same images gave
other markers. Here the shadows of one frame measured with the typed size say
how far off it is, and the sizes looked for follow what was measured.
Within a frame, a shadow claimed as one sphere is judged against its
nearest neighbours measured alone (:func:`like_neighbours`), and a phantom
of two sphere sizes has a size class for each (:func:`size_classes`,
:func:`size_class`, :func:`class_radius`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .options import DetectOptions

# measured / typed shadow size within this factor either way: the typed size
# is kept (the search range is 0.6-1.6x wide; a blob's moment diameter reads
# 0.92-0.98 of its shadow's when the typed blur is the system's)
KEEP_WITHIN = 1.15
# fewer measured shadows than this: the typed size is kept
MIN_SHADOWS = 5
# ratios searched (measured / typed)
_RATIOS = np.exp(np.linspace(np.log(0.33), np.log(3.0), 600))


def size_ratio(diameters, shadow_px) -> float | None:
    """Measured over nominal shadow size: the factor s (unitless) that best
    puts each measured diameter (px) on one of the nominal ones ``shadow_px``
    (px, one per declared sphere diameter): least sum of |log d - log(s p)|
    over the nearest p, plus half a unit of |log s| so that with two declared
    sizes a set that fits either equally keeps the typed magnification.
    None for fewer than ``MIN_SHADOWS`` diameters."""
    d = np.log(np.asarray(diameters, float))
    d = d[np.isfinite(d)]
    if d.size < MIN_SHADOWS or not len(shadow_px):
        return None
    p = np.log(np.asarray(shadow_px, float))
    ls = np.log(_RATIOS)
    cost = np.abs(d[None, :, None] - ls[:, None, None] - p[None, None, :]).min(2).sum(1) + 0.5 * np.abs(ls)
    return float(_RATIOS[int(np.argmin(cost))])


def rescaled(s: float) -> bool:
    """Whether a measured over typed size ``s`` (0: not measured) is far
    enough off for the sizes looked for to follow it."""
    return bool(s) and abs(np.log(s)) > np.log(KEEP_WITHIN)


def measured_size(blobs: list, opt: DetectOptions) -> DetectOptions:
    """``opt`` with ``size_scale`` (the measured over typed shadow size, from
    ``blobs``: one frame's shadows found with ``opt``; its unflagged ones, or
    all when fewer than ``MIN_SHADOWS``) and, when that is beyond
    ``KEEP_WITHIN``, the search range and nominal sizes scaled by it. ``opt``
    unchanged when it has no nominal sizes (``--diameter-px`` given) or too
    few shadows were measured."""
    if not opt.shadow_px:
        return opt
    use = [b for b in blobs if not b.flags]
    use = use if len(use) >= MIN_SHADOWS else blobs
    d = [2.0 * b.radius for b in use]
    s = size_ratio(d, opt.shadow_px)
    if s is None:
        return opt
    # (a small bead's faint shadow on a phantom's body is often flagged clutter:
    # the classes are counted over every shadow measured whole)
    whole = [b for b in blobs if not {"overlap", "truncated"} & set(b.flags)]
    s2 = second_size([2.0 * b.radius for b in (whole if len(whole) >= MIN_SHADOWS else blobs)], opt.shadow_px, s)
    if s2 is not None:
        lo, hi = min(s, s2), max(s, s2)
        return replace(opt, size_scale=s, diameter_px=(float(opt.diameter_px[0] * lo), float(opt.diameter_px[1] * hi)),
                       shadow_px=tuple(sorted({float(p * f) for p in opt.shadow_px for f in (s, s2)})))
    if not rescaled(s):
        return replace(opt, size_scale=s)
    return replace(opt, size_scale=s, diameter_px=tuple(float(d * s) for d in opt.diameter_px),
                   shadow_px=tuple(float(d * s) for d in opt.shadow_px))


# a second size class: at least this share of the measured shadows (and
# MIN_SHADOWS) lie beyond _BEYOND of every declared size at the measured
# scale, and measure _APART or more from it
_SECOND_SHARE = 0.2
_BEYOND = 1.3
_APART = 1.4


def second_size(diameters, shadow_px, s: float) -> float | None:
    """A second measured over typed size ratio (unitless) when the shadows
    ``diameters`` (px) fall in two size classes and the declared sizes
    ``shadow_px`` (px) at the measured ratio ``s`` explain only one: a
    phantom of two bead sizes declared by one diameter (a coded helix's 1.6
    and 3.2 mm beads) was looked for at the larger size alone, and half its
    beads fell below the range. None when one class explains them."""
    d = np.asarray(diameters, float)
    d = d[np.isfinite(d) & (d > 0)]
    p = np.asarray(shadow_px, float) * s
    off = np.min(np.abs(np.log(d[:, None] / p[None, :])), axis=1) > np.log(_BEYOND)
    if off.sum() < max(MIN_SHADOWS, _SECOND_SHARE * d.size):
        return None
    s2 = size_ratio(d[off], shadow_px)
    return s2 if s2 is not None and abs(np.log(s2 / s)) >= np.log(_APART) else None


def nearest_shadows(x: float, y: float, ref: list) -> list:
    """The four shadows of ``ref`` nearest (x, y): an intensifier magnifies
    its periphery, so a shadow's size is judged against its neighbours'."""
    return sorted(ref, key=lambda b: (b.x - x) ** 2 + (b.y - y) ** 2)[:4]


def like_neighbours(R: float, mu: float, near: list, sized: bool = True) -> bool:
    """Whether a sphere of radius ``R`` px and contrast ``mu`` (per px of
    chord) has the total attenuation (0.6-1.4x) and, when ``sized``, the
    size (0.8-1.25x) of the shadows ``near`` measured alone: one sphere's,
    not two on one line of sight nor a fragment. (A joint model's radius is
    not a window's moment radius: compare only the attenuation then.)"""
    R0 = float(np.median([b.radius for b in near]))
    ratio = mu * R**3 / float(np.median([b.mu_px * b.radius**3 for b in near]))
    return (not sized or 0.8 * R0 <= R <= 1.25 * R0) and 0.6 <= ratio < 1.4


def declared_radii(blobs: list, shadow_px) -> np.ndarray:
    """The declared spheres' shadow radii (px) at the frame's measured scale
    (:func:`size_ratio` over ``blobs``' diameters), from their nominal
    diameters ``shadow_px`` (px); empty when none are declared."""
    d = np.asarray(shadow_px, float)
    if not d.size:
        return d
    return (size_ratio([2 * b.radius for b in blobs], d) or 1.0) * d / 2


# a size class apart from the frame's typical sphere: radius this far off it
_OTHER_CLASS = 1.4


def size_classes(blobs: list, shadow_px, R1: float) -> np.ndarray:
    """The frame's sphere radii (px): its typical ``R1``, then each declared
    size (:func:`declared_radii`) and the median of its lone shadows (``blobs``
    unflagged) beyond ``_OTHER_CLASS`` of ``R1`` either way. A helix of 0.9
    and 1.2 mm beads shows mostly small ones: two large ones touching were
    judged against the small ones' radius, swelled beyond it and lost."""
    out = [R1]
    lone = np.array([b.radius for b in blobs if not b.flags])
    for side in (lone[lone > _OTHER_CLASS * R1], lone[lone < R1 / _OTHER_CLASS]):
        if side.size:
            out.append(float(np.median(side)))
    out += [float(r) for r in declared_radii(blobs, shadow_px)]
    keep = [out[0]]
    for r in out[1:]:
        if all(abs(np.log(r / k)) > np.log(_OTHER_CLASS) for k in keep):
            keep.append(r)
    return np.array(keep)


# a size class: the lone shadows from a marker's radius over _CLASS_BELOW (two
# spheres half a diameter apart read 1.25x one's radius) to _CLASS times it; a
# declared diameter within _DECLARED_CLASS of it
_CLASS = 1.25
_CLASS_BELOW = 1.4
_DECLARED_CLASS = 1.6


def size_class(b, lone: list) -> list:
    """The lone shadows ``lone`` of blob ``b``'s size class (radius from its
    own over ``_CLASS_BELOW`` to ``_CLASS`` times it): a phantom of two
    sphere sizes has two."""
    return [o for o in lone if o is not b and b.radius / _CLASS_BELOW <= o.radius <= b.radius * _CLASS]


def class_radius(b, lone: list, R1: float, declared: np.ndarray) -> float:
    """The radius (px) of one sphere of blob ``b``'s size class: the median of
    three or more lone shadows of it, else the declared radius nearest its
    own (``declared``, px) when within ``_DECLARED_CLASS`` of it, else its
    own (a pair nearly on top reads 1.0-1.15x its larger sphere's). A
    helix's large beads stand alone two or three to a frame: the parts of a
    pair of them (5.8 and 6.7 px) were refused against the small ones' 3.3
    (the frame's ``R1``, kept where ``b`` has no radius)."""
    same = size_class(b, lone)
    if len(same) >= 3:
        return float(np.median([o.radius for o in same]))
    if declared.size:
        near = float(declared[np.argmin(np.abs(np.log(declared / b.radius)))])
        if abs(np.log(near / b.radius)) <= np.log(_DECLARED_CLASS):
            return near
    return float(b.radius) if np.isfinite(b.radius) and b.radius > 0 else R1


def typical_sphere(kept: list, opt: DetectOptions):
    """The frame's sphere radius (px) and contrast (attenuation per px of
    chord, None when no sphere stands alone): from its separate shadows, else
    the nominal size the options were made from."""
    ref = [b for b in kept if not b.flags] or kept
    if ref:
        return float(np.median([b.radius for b in ref])), float(np.median([b.mu_px for b in ref]))
    return float(np.sqrt(opt.diameter_px[0] * opt.diameter_px[1] / 0.96)) / 2, None
