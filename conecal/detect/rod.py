"""Lengths of a rod taken for spheres.

A wire, a screw's shank or a K-wire across the field makes a ridge whose
stretch inside one sphere's window reads as an elongated blob: the split
cuts it into sphere-sized parts of the frame's size and contrast, and the
peaks along it seed joint fits (an independent renderer's wires: 27 false
markers in 23 frames, every one such a length). A sphere's shadow ends one
radius plus the blur's reach past its centre, and dips between it and a
neighbour just touching; a rod's runs on past both ends, flat. What rises
out of the rod (a sphere lying on it) is not its length.

Locally a row of spheres overlapping at less than about 1.75 radii apart
(a grid seen steeply) is a rod too: its dips blur away. Such a row's
spheres are kept while a neighbour that ends the row, or rises out of it,
is measured (the rule below), and a row whose ripple shows is no rod.
Units: px, attenuation.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.ndimage import map_coordinates

# the lowest level along the parts and one radius past either end (beyond
# the blur's reach of the end spheres), as a fraction of the parts' level,
# that is a rod's: a sphere chain's falls to the blur's tail past its ends
# (< 0.05) and two spheres 2R apart dip to < 0.3 between them
_RUNS_ON = 0.6
# the scatter of that level along the line about a straight trend, as a
# fraction of the parts' level, that is a rod's: flat but for the noise (an
# intensifier's wires in an independent renderer 0.05-0.15, median 0.09),
# where a row of a grid's spheres seen steeply, their shadows overlapping
# and their dips blurred shallow, ripples (0.11-0.38, median 0.19)
_FLAT = 0.1
# the parts' largest distance from their common line, in radii
_ON_LINE = 0.35


class Run(NamedTuple):
    """How a shadow runs on along a line (:func:`run_on`)."""
    ratio: float       # lowest level along the stretch / the level at the centres
    ripple: float      # the level's scatter about a straight trend / the level at the centres
    u: np.ndarray      # the line's unit direction (x, y)
    ends: list         # the two end stretches' pixel positions, (x, y) arrays
    level: float       # the level at the centres (attenuation)

    def rod(self) -> bool:
        """Whether the shadow runs on as a rod's: on and flat."""
        return self.runs_on() and self.ripple <= _FLAT

    def runs_on(self) -> bool:
        """Whether the shadow runs on past both ends (flat or not: a sphere
        may lie on the rod)."""
        return self.ratio >= _RUNS_ON


_NONE = Run(0.0, np.inf, np.array([1.0, 0.0]), [], 0.0)


def run_on(a: np.ndarray, spheres: np.ndarray, blur: float, invalid=None, u=None, others=()) -> Run:
    """How frame ``a``'s shadow runs on along the line through shadows
    ``spheres`` (k rows x, y, R px, mu; on one line when k >= 2), from one
    radius past the blur's reach beyond one end to as far beyond the other.
    For one shadow the line is that of 12 directions (or ``u``) along which
    it runs on furthest. The level is the mean over a band 0.8 R wide along
    the line less the mean of two bands 1.6-2.2 R to either side (steps and
    gradients cancel), the side bands' pixels inside other shadows
    ``others`` (x, y, r px) left out (a grid's neighbouring rows); its lowest
    point is taken smoothed over 3 px (one noisy sample is no dip). Nothing
    (ratio 0) where the ends leave the frame or meet ``invalid``, or where
    the shadows around leave no side band for a third of the line."""
    sph = np.asarray(spheres, float).reshape(-1, 4)
    xy, R = sph[:, :2], float(np.median(sph[:, 2]))
    c = xy.mean(axis=0)
    if u is None and len(sph) >= 2:
        u = line_of(xy)[1]
    dirs = [np.asarray(u, float)] if u is not None else \
        [np.array([np.cos(th), np.sin(th)]) for th in np.arange(12) * np.pi / 12]
    gap = R + 2.5 * blur + 1
    rows, cols = a.shape
    reach = 2.2 * R + 1
    span = float(np.max(np.hypot(*(xy - c).T))) + 4.5 * R + 3 * blur + 2
    near = [(ox, oy, r + 2 * blur) for ox, oy, r in others if np.hypot(ox - c[0], oy - c[1]) < span + r]
    best = _NONE
    for u in dirs:
        n = np.array([-u[1], u[0]])
        t = np.sort((xy - c) @ u)

        def level(s: np.ndarray) -> np.ndarray:
            def band(lo: float, hi: float, side: bool) -> np.ndarray:
                w = np.linspace(lo, hi, max(int(hi - lo) + 1, 2))
                X = c[0] + s[:, None] * u[0] + w[None, :] * n[0]
                Y = c[1] + s[:, None] * u[1] + w[None, :] * n[1]
                v = map_coordinates(a, [Y.ravel(), X.ravel()], order=1, mode="nearest").reshape(X.shape)
                if side:
                    for ox, oy, r in near:
                        v[np.hypot(X - ox, Y - oy) < r] = np.nan
                return v
            sides = np.hstack([band(1.6 * R, 2.2 * R, True), band(-2.2 * R, -1.6 * R, True)])
            kept = np.sum(np.isfinite(sides), axis=1)
            bg = np.where(kept > 0, np.nansum(sides, axis=1) / np.maximum(kept, 1), np.nan)
            return band(-0.4 * R, 0.4 * R, False).mean(1) - bg

        ends = []
        for s in (np.arange(t[0] - gap - R, t[0] - gap + 0.5), np.arange(t[-1] + gap, t[-1] + gap + R + 0.5)):
            px, py = c[0] + s * u[0], c[1] + s * u[1]
            if np.any((px < reach) | (py < reach) | (px > cols - 1 - reach) | (py > rows - 1 - reach)):
                break
            if invalid is not None and np.any(invalid[np.round(py).astype(int), np.round(px).astype(int)]):
                break
            ends.append((px, py))
        if len(ends) < 2:
            continue
        own = np.array([np.mean(level(np.array([ti - 1, ti, ti + 1.0]))) for ti in t])
        if not np.all(np.isfinite(own)) or np.median(own) <= 0:
            continue
        own = float(np.median(own))
        s = np.arange(t[0] - gap - R, t[-1] + gap + R + 0.5)
        along = level(s)
        ok = np.isfinite(along)
        if ok.sum() < max(2 * len(s) / 3, 3):
            continue
        s, along = s[ok], along[ok]
        ratio = float(np.min(np.convolve(along, np.ones(3) / 3, mode="valid"))) / own
        if ratio > best.ratio:
            trend = np.polyval(np.polyfit(s, along, 1), s)
            best = Run(ratio, float(np.std(along - trend)) / own, u, ends, own)
    return best


def _runs_into(ends: list, others) -> list[int]:
    """Indices of shadows ``others`` (x, y, r px) that the end stretches
    ``ends`` of :func:`run_on` meet."""
    return [j for j, (ox, oy, r) in enumerate(others)
            if any(np.any(np.hypot(px - ox, py - oy) < r + 2) for px, py in ends)]


def line_of(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centroid (px) of points ``xy`` (k, 2) and the unit direction of
    their best line through it (the first right singular vector)."""
    c = xy.mean(axis=0)
    return c, np.linalg.svd(xy - c)[2][0]


def rod_like(a: np.ndarray, spheres: np.ndarray, blur: float, others=(), invalid=None) -> bool:
    """Whether split parts ``spheres`` (k >= 2 rows x, y, R px, mu) are
    lengths of a rod: on one line (within ``_ON_LINE`` radii), along which
    the shadow runs on flat (:meth:`Run.rod`) past both ends, where it meets
    none of the spheres measured alone ``others`` (x, y, r px)."""
    sph = np.asarray(spheres, float).reshape(-1, 4)
    if len(sph) < 2:
        return False
    c, u = line_of(sph[:, :2])
    if np.max(np.abs((sph[:, :2] - c) @ np.array([-u[1], u[0]]))) > _ON_LINE * float(np.median(sph[:, 2])):
        return False
    run = run_on(a, sph, blur, invalid, u, others)
    return run.rod() and not _runs_into(run.ends, others)


def on_rods(a: np.ndarray, blobs: list, blur: float, invalid=None) -> list[bool]:
    """For each of ``blobs`` (x, y, radius, flags), whether it is a rod's
    length taken for a sphere: flagged (clutter or overlap: a blob measured
    alone cleanly is no rod), the shadow runs on flat past it both ways
    along some line (:meth:`Run.rod`), and every other blob it runs into
    there is such a length too (a chain of spheres overlapping deeply runs
    on through its middle ones, but ends) or stands well out of it (a
    sphere lying on the rod)."""
    shadows = [(b.x, b.y, b.radius) for b in blobs]
    runs = [run_on(a, np.array([[b.x, b.y, b.radius, 0.0]]), blur, invalid, others=shadows[:i] + shadows[i + 1:])
            if b.flags else _NONE for i, b in enumerate(blobs)]
    rod = [r.rod() for r in runs]
    out = []
    for i, r in enumerate(runs):
        met = [j for j in _runs_into(r.ends, shadows) if j != i] if rod[i] else []
        out.append(rod[i] and all(rod[j] or _RUNS_ON * runs[j].level >= r.level for j in met))
    return out
