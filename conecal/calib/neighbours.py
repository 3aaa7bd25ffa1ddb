"""An identity a frame's own pattern leaves open, taken from its neighbours.

A C-arm sweep or a turntable records its views in order, each a few
degrees from the last; a phantom with a symmetry the view does not break
(a grid whose missing corner is among the spheres lost in that frame) fits
two or more identifications equally, and they differ by a symmetry's
displacement (a quarter turn, one pitch), which the neighbouring frames'
poses can tell apart. Whether the scan is such a sequence is measured, not
assumed: each ok frame's pose is predicted from its ok neighbours the same
way, and the largest miss among the ok frames near it is the scale. A tie
is broken only when one candidate lies within twice that scale of its
prediction and every other one three times as far as the scale and as the
one: were a rival the truth, the prediction would have missed by three
times more than at any ok frame nearby. A scan of hand-placed, unordered
poses has a large scale and breaks no tie.
Units: px (the calibrated camera's projections of the whole phantom).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np

from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from .candidate import Candidate, rigid_fit
from .phantom import PhantomShape
from .search import by_convention

# the farthest (in frame numbers) a neighbour may be from the frame it predicts
MAX_GAP = 3
# the ok frames within this many frame numbers measure a frame's scale
LOCAL = 2 * MAX_GAP
# the fewest ok frames that measure a scale
MIN_SAMPLES = 4
# how far beyond the ok frames' largest miss the chosen one may lie (it is one
# more sample of the same misses)
WITHIN = 2.0
# how much farther than the scale (and than the chosen one) every rival must be
SEPARATION = 3.0
# two candidates whose projections differ by less than this (px RMS) are one pose
SAME_PX = 1.0
# an ok frame this many sweep steps from every neighbour's pose is searched again near them
JUMP = 2.5


def _predict(poses: dict, k: int):
    """(R, t, kind, frames used) for frame ``k`` from the nearest posed frames
    within MAX_GAP on each side: interpolated along the geodesic between two
    ('both'), or the one neighbour's pose ('one'); None without any."""
    before = [j for j in poses if k - MAX_GAP <= j < k]
    after = [j for j in poses if k < j <= k + MAX_GAP]
    if before and after:
        a, b = max(before), min(after)
        f = (k - a) / (b - a)
        (Ra, ta), (Rb, tb) = poses[a], poses[b]
        return Ra @ rotvec_to_matrix(f * matrix_to_rotvec(Ra.T @ Rb)), ta + f * (tb - ta), "both", [a, b]
    if before or after:
        j = max(before) if before else min(after)
        return (*poses[j], "one", [j])
    return None


@lru_cache(maxsize=8)
def _relabellings(shape: PhantomShape) -> list:
    """Sphere index permutations the phantom's own symmetries make (the
    identity first): labellings that give the same image. (Cached: every
    pose comparison asks for them; a PhantomShape is immutable.)"""
    return [np.arange(len(shape.points)), *shape.perms]


def _twins(points: np.ndarray, perms: list, R, t) -> list:
    """The poses that put the same spheres in the same places under each
    relabelling: with A p_j + a = p_perm(j) (rigid), R' = R A^T, t' = t - R' a."""
    out = []
    for p in perms:
        A, a = rigid_fit(points, points[p])
        out.append((R @ A.T, t - R @ A.T @ a))
    return out


def _consistent(cam, points, perms, posed: dict) -> dict:
    """The ok frames' poses, each labelled as the one before it is (among the
    labellings its symmetry allows), so that neighbours can be interpolated."""
    out, last = {}, None
    for k in sorted(posed):
        twins = _twins(points, perms, *posed[k])
        out[k] = twins[0] if last is None else min(twins, key=lambda p: _miss(cam, points, perms[:1], *p, last))
        last = out[k]
    return out


def _conventional(points, perms, shape: PhantomShape, c: Candidate) -> Candidate:
    """``c`` relabelled as the search labels a symmetric phantom (the normal
    towards the detector, then the smallest turn), its pose moved alike."""
    twins = [replace(c, sph=p[c.sph], R=R, t=t) for p, (R, t) in zip(perms, _twins(points, perms, c.R, c.t))]
    return by_convention(twins, shape)


def in_sequence(cam, shape: PhantomShape, frames: list) -> None:
    """The ok frames (``frames`` in scan order, each with its ``search``
    result and perhaps ``pairs``) of a 3-D phantom with whole symmetries
    relabelled in turn, each among the poses its symmetry makes identical as
    the one nearest the ok frame before it (the first: the smallest turn),
    in place. Every labelling is right (the same
    image, the same calibration), but a reconstruction takes all frames'
    poses in one phantom frame: labelled one by one by the smallest turn, a
    sweep's poses jump by the symmetry (a cube's quarter turn, a helix's
    half turn) where it passes half of one. Grids keep their convention
    (normal towards the detector)."""
    if shape.planar or not shape.perms:
        return
    perms, points = _relabellings(shape), shape.points
    sentence = (f"labelled in scan order, each frame as near as the phantom's symmetry allows to the ok frame "
                f"before it (the first by the smallest turn), among the {len(perms)} poses the phantom's "
                f"{len(perms) - 1} turns onto itself make identical")
    last = None
    for fr in frames:
        c = fr["search"].best
        if not fr["status"].ok or c is None:
            continue
        if fr.get("sequenced") is c:
            # (labelled on an earlier look: kept, so that a frame named anew
            # between two does not relabel those after it and the bundle
            # restarted from the last look's poses finds them as it left them)
            last = (c.R, c.t)
            continue
        twins = [replace(c, sph=p[c.sph], R=R, t=t) for p, (R, t) in zip(perms, _twins(points, perms, c.R, c.t))]
        if last is None:
            first = by_convention(twins, shape)
            k = next(i for i, w in enumerate(twins) if w is first)
        else:
            k = int(np.argmin([_miss(cam, points, perms[:1], w.R, w.t, last) for w in twins]))
        if k and fr.get("pairs") is not None:
            d, sph = fr["pairs"]
            fr["pairs"] = (d, perms[k][np.asarray(sph, int)])
        fr["search"] = replace(fr["search"], best=twins[k], convention=sentence)
        fr["sequenced"] = twins[k]
        last = (twins[k].R, twins[k].t)


def conventional(shape: PhantomShape, points: np.ndarray, c: Candidate) -> Candidate:
    """``c`` labelled by the search's convention among the labellings the
    phantom's symmetry makes identical (its pose moved alike)."""
    return _conventional(points, _relabellings(shape), shape, c)


def _miss(cam, points, perms, R, t, pred) -> float:
    """RMS px between the phantom projected at (R, t) and at the prediction,
    the least over labellings the phantom's symmetry makes identical."""
    a = cam.project(points @ R.T + t)
    b = cam.project(points @ pred[0].T + pred[1])
    return min(float(np.sqrt(np.mean(np.sum((a - b[p]) ** 2, 1)))) for p in perms)


def predicted(cam, shape: PhantomShape, points: np.ndarray, posed: dict) -> dict:
    """frame -> [(R, t), ...]: each ok frame's pose as its ok neighbours (not
    itself) predict it, in their labelling: interpolated, and each
    neighbour's own pose within MAX_GAP (one neighbour labelled wrongly
    spoils the interpolation, not the others)."""
    perms = _relabellings(shape)
    posed = _consistent(cam, points, perms, posed)
    out = {}
    for k in posed:
        others = {j: p for j, p in posed.items() if j != k}
        pred = _predict(others, k)
        if pred is not None:
            out[k] = [pred[:2]] + [others[j] for j in sorted(others) if abs(j - k) <= MAX_GAP]
    return out


def guesses(cam, shape: PhantomShape, points: np.ndarray, posed: dict, frames) -> dict:
    """frame -> (R, t): each of ``frames``' pose as the ok frames ``posed``
    (frame -> (R, t)) nearest it predict, labelled alike; a frame with no ok
    frame within MAX_GAP has none."""
    posed = _consistent(cam, points, _relabellings(shape), posed)
    out = {}
    for k in frames:
        pred = _predict(posed, k)
        if pred is not None:
            out[k] = pred[:2]
    return out


def jumps(cam, shape: PhantomShape, points: np.ndarray, posed: dict, preds: dict, factor: float = JUMP) -> set:
    """Ok frames farther from every neighbouring frame's pose than ``factor``
    times the median such distance (one step of the sweep): a frame labelled
    with the phantom turned jumps off its sweep. ``preds``: from
    ``predicted`` (its first entry, the interpolation, is not used: one
    turned frame spoils it for the frames beside it). ``posed``: frame ->
    (R, t). An unordered scan's misses are all large, so few of its frames
    stand out."""
    perms = _relabellings(shape)
    miss = {k: min(_miss(cam, points, perms, *posed[k], p) for p in preds[k][1:]) for k in preds}
    if len(miss) < MIN_SAMPLES:
        return set()
    step = float(np.median(list(miss.values())))
    return {k for k, v in miss.items() if v > factor * step}


def same_pose(cam, shape: PhantomShape, points: np.ndarray, a: Candidate, b: Candidate) -> bool:
    """Two candidates that put the phantom in one place (within SAME_PX),
    however the phantom's symmetry labels it."""
    return _miss(cam, points, _relabellings(shape), a.R, a.t, (b.R, b.t)) <= SAME_PX


def by_neighbours(cam, shape: PhantomShape, points: np.ndarray, posed: dict, ties: dict):
    """Ties broken by the neighbouring frames. ``posed``: frame -> (R, t) of
    the ok frames (lab mm, the calibrated bundle's); ``ties``: frame -> the
    tied candidates (calibrated camera); ``cam`` the calibrated camera,
    ``points`` the phantom (P, 3) mm. Returns frame -> (candidate, sentence)."""
    perms = _relabellings(shape)
    posed = _consistent(cam, points, perms, posed)
    scale = {"both": {}, "one": {}}
    for k, (R, t) in posed.items():
        pred = _predict({j: p for j, p in posed.items() if j != k}, k)
        if pred is not None:
            scale[pred[2]][k] = _miss(cam, points, [np.arange(len(points))], R, t, pred)
    out = {}
    for k, cands in ties.items():
        pred = _predict(posed, k)
        if pred is None:
            continue
        # the ok frames nearest this one measure its scale (a stretch of the
        # sweep elsewhere that jumps says nothing of this one), all of them
        # when too few are near
        near = [v for j, v in scale[pred[2]].items() if abs(j - k) <= LOCAL]
        pool = near if len(near) >= MIN_SAMPLES else list(scale[pred[2]].values())
        if len(pool) < MIN_SAMPLES:
            continue
        s = max(pool)
        miss = np.array([_miss(cam, points, perms, c.R, c.t, pred) for c in cands])
        order = np.argsort(miss)
        best = miss[order[0]]
        # (a rival within a px of the chosen pose is the same pose, found twice)
        w = cands[order[0]]
        rest = np.array([miss[j] for j in order[1:] if not same_pose(cam, shape, points, cands[j], w)] + [np.inf])
        if best <= WITHIN * s and (rest >= SEPARATION * max(s, best)).all():
            used = " and ".join(str(j) for j in pred[3])
            out[k] = (_conventional(points, perms, shape, w),
                      f"of {len(cands)} identifications that fit alike, the one within {best:.1f} px of the pose "
                      f"neighbouring frame(s) {used} predict (ok frames near it: within {s:.1f} px; the others "
                      f"{rest.min():.0f} px or more)")
    return out
