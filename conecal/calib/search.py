"""Pose search without a log: which detection is which sphere, and a first pose.

A planar grid's candidates come from its lattice in the image
(``lattice.py``); any other phantom's (3-D, or planar off a lattice) from
voting sampled orientations (``vote.py``). Candidates are refined to poses
with the nominal camera and a robust loss (the distortion is not yet
known: several px).

Two candidates that fit about equally are one pose when the phantom's own
symmetry relates them (the same calibration: resolved by convention), and
make the frame ``ambiguous`` otherwise (say, a grid with a column off the
detector, which can be labelled with a shift of one pitch). A rough guess
breaks such a tie only when exactly one candidate agrees with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..documents.status import OK, Status, ambiguous, rejected
from ..geometry import matrix_to_rotvec
from .camera import Camera
from .candidate import Candidate, assign, refine_pose
from .lattice import planar_candidates, turned
from .partial import moved, screw_tie
from .phantom import PhantomShape
from .vote import voted_candidates


@dataclass
class SearchResult:
    status: Status
    best: Candidate | None = None
    alternatives: list = field(default_factory=list)
    convention: str = ""       # a phantom symmetry resolved by convention


@dataclass(frozen=True)
class SearchOptions:
    """min_spheres: fewest identified spheres for a pose; gate_px: final
    assignment gate (px; distortion is not modelled yet); gate_floor_px:
    the least common gate when candidates compete; tie_px: two
    candidates whose RMS differ by less than this tie; guess_deg, guess_mm:
    how far a rough guess may be off; n_orientations: samples of SO(3) for
    a full search (about 12 deg apart at 8000); retry_px: when no candidate
    of a 3-D phantom fits better than this, search again three times denser;
    depth_mm: the phantom's distance from the source about which a full
    orientation search tries depths (None: the nominal sod)."""

    min_spheres: int = 6
    gate_px: float = 6.0
    tie_px: float = 1.0
    gate_floor_px: float = 2.0
    retry_px: float = 1.0
    guess_deg: float = 40.0
    guess_mm: float = 25.0
    n_orientations: int = 8000
    depth_mm: float | None = None


def _polish(cam: Camera, shape: PhantomShape, xy: np.ndarray, cand: Candidate, gates=(12.0, 6.0)) -> Candidate:
    """Refine, re-assign every phantom sphere within shrinking gates (the last
    one until the assignment settles), refine."""
    R, t = cand.R, cand.t
    sph, det = cand.sph, cand.det
    schedule = list(gates) + [gates[-1]] * 3
    for gate in schedule:
        if len(sph) < 4:
            break
        R, t, _ = refine_pose(cam, shape.points[sph], xy[det], R, t)
        new_sph, new_det = assign(cam.project(shape.points @ R.T + t), xy, gate)
        settled = gate == gates[-1] and np.array_equal(new_sph, sph) and np.array_equal(new_det, det)
        sph, det = new_sph, new_det
        if settled:
            break
    if len(sph) >= 4:
        R, t, res = refine_pose(cam, shape.points[sph], xy[det], R, t)
        rms = float(np.sqrt(np.mean(np.sum(res ** 2, 1))))
    else:
        rms = np.inf
    return Candidate(det, sph, R, t, rms, cand.how, cand.lattice_map, unseen_spheres(cam, shape, R, t, sph))


def unseen_spheres(cam: Camera, shape: PhantomShape, R, t, sph, xy: np.ndarray | None = None) -> int:
    """Phantom spheres this pose puts well inside the detector, clear of every
    other sphere's shadow, that no detection was assigned to: evidence
    against the pose (a labelling one pitch off predicts a column where the
    image has none). With the detections ``xy`` (n, 2) px, a sphere with one
    inside its predicted shadow is seen, only fitted beyond a tight gate (a
    distortion the model lacks), not missing."""
    return shadow_tally(cam, shape, R, t, sph, None, xy)[1]


def shadow_tally(cam: Camera, shape: PhantomShape, R, t, sph, det=None, xy: np.ndarray | None = None):
    """(seen, missing) of the spheres no detection was assigned to: ``seen``
    those with a detection no other sphere took (``det``: the assigned
    detections' indices) inside their predicted shadow, ``missing`` those
    put well inside the detector and clear of every other shadow with no
    detection in it (see ``unseen_spheres``)."""
    pred = cam.project(shape.points @ R.T + t)
    rows, cols = cam.shape
    f = cam.focal_px.mean()
    depth = (shape.points @ R.T + t - cam.source)[:, 2]
    margin = 2.0 + 2 * f * shape.radius / depth     # a shadow's diameter, px
    inside = ((pred[:, 0] > margin) & (pred[:, 0] < cols - 1 - margin) & (pred[:, 1] > margin)
              & (pred[:, 1] < rows - 1 - margin))
    if getattr(cam, "field", None) is not None:
        # (a sphere whose shadow reaches an intensifier's black surround is
        # not unseen: an independent renderer's coded helix, spheres predicted
        # there counted against the right labelling, which lost to one moved
        # by two beads, ok and wrong)
        inside &= cam.field.holds(pred, margin / 2)
    d = np.linalg.norm(pred[:, None] - pred[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    clear = d.min(1) > 2 * margin if len(pred) > 1 else np.ones(len(pred), bool)
    found = np.zeros(len(pred), bool)
    found[np.asarray(sph, int)] = True
    seen = 0
    if xy is not None and len(xy):
        near = np.linalg.norm(pred[:, None] - xy[None], axis=-1) <= margin[:, None] / 2
        if det is not None:
            free = np.ones(len(xy), bool)
            free[np.asarray(det, int)] = False
            seen = int(np.sum(~found & clear & (near & free[None]).any(1)))
        found |= near.any(1)
    return seen, int(np.sum(inside & clear & ~found))


def _tighten(cam: Camera, shape: PhantomShape, xy: np.ndarray, cands: list, floor_px: float) -> list:
    """Re-assign every candidate within one common gate: four times the best
    candidate's median residual (at least ``floor_px``), so that a wrong pose
    cannot count detections that the right one explains far more closely."""
    med = []
    for c in cands:
        r = np.linalg.norm(cam.project(shape.points[c.sph] @ c.R.T + c.t) - xy[c.det], axis=1)
        med.append(float(np.median(r)))
    gate = max(floor_px, 4 * min(med))
    out = []
    for c in cands:
        t = _polish(cam, shape, xy, c, gates=(gate,))
        out.append(t if len(t.sph) >= 4 else c)
    return out


# ----------------------------------------------------------------------------- one frame
def _same_pose(a: Candidate, b: Candidate, deg: float = 3.0, mm: float = 2.0) -> bool:
    return (np.linalg.norm(matrix_to_rotvec(a.R @ b.R.T)) < np.deg2rad(deg)
            and np.linalg.norm(a.t - b.t) < mm)


def _agrees(c: Candidate, guess, opt: SearchOptions) -> bool:
    return (np.linalg.norm(matrix_to_rotvec(c.R @ guess[0].T)) <= np.deg2rad(opt.guess_deg)
            and np.linalg.norm(c.t - guess[1]) <= opt.guess_mm)


def search_frame(cam: Camera, shape: PhantomShape, xy: np.ndarray, guess=None,
                 opt: SearchOptions = SearchOptions()) -> SearchResult:
    """Identify the phantom's spheres among detections ``xy`` (n, 2) px of one
    frame and find a first pose; ``guess``: (R, t) lab or None."""
    if len(xy) < opt.min_spheres:
        return SearchResult(rejected("few_markers", f"{len(xy)} markers usable, fewer than {opt.min_spheres}"))
    raw = planar_candidates(cam, shape, xy) if shape.lattice is not None else []
    voted_grid = shape.lattice is not None and not raw
    if not raw:
        raw = voted_candidates(cam, shape, xy, guess, opt.n_orientations, depth=opt.depth_mm)
        if guess is not None and not raw:
            raw = voted_candidates(cam, shape, xy, None, opt.n_orientations, depth=opt.depth_mm)
    def polished(found):
        return [c for c in (_polish(cam, shape, xy, c, gates=(3 * opt.gate_px, opt.gate_px)) for c in found)
                if len(c.sph) >= 4 and np.isfinite(c.rms_px)]

    cands = polished(raw)
    if shape.lattice is None and (not cands or min(c.rms_px for c in cands) > opt.retry_px):
        # nothing fits well (a crowded view of a 3-D phantom): a denser second search
        more = voted_candidates(cam, shape, xy, None, 3 * opt.n_orientations, seed=11, depth=opt.depth_mm)
        cands += polished(more)
    if voted_grid and cands:
        # (a grid seen nearly edge-on, whose image lattice did not grow: the
        # turns of its lattice map it onto itself, so the vote may find only
        # a turned labelling of the right pose -- an independent renderer's
        # grid with 3 holes at 81 deg, 54 spheres all named wrong at 0.44 px;
        # the right one, among its turns, names 56)
        top = min(cands, key=lambda c: (-c.score, c.rms_px))
        cands += polished(turned(shape, shape.points, top))
    if shape.lattice is None and cands:
        # (a partial symmetry of a 3-D phantom -- a helix's screw by a bead --
        # images it alike in two poses where the frame does not see what
        # breaks it: the moved labelling is offered, to tie where it does)
        top = min(cands, key=lambda c: (-c.score, c.rms_px))
        cands += polished(moved(shape, top))
    if cands:
        cands = _tighten(cam, shape, xy, cands, opt.gate_floor_px)
    cands = [c for c in cands if len(c.sph) >= opt.min_spheres and np.isfinite(c.rms_px)]
    if not cands:
        return SearchResult(rejected("no_pose", f"no pose explains {opt.min_spheres} or more of {len(xy)} markers"))
    # most spheres explained, then the lowest residual
    cands.sort(key=lambda c: (-c.score, c.rms_px))
    best = cands[0]
    rivals = []
    for c in cands[1:]:
        if _same_pose(c, best):
            continue
        if any(_same_pose(c, r) for r in rivals):
            continue
        if (c.score >= best.score - 1 or screw_tie(shape, best, c)) and c.rms_px <= best.rms_px + opt.tie_px:
            rivals.append(c)
    convention = ""
    if shape.perms and rivals:
        twins, maps, rivals = _by_symmetry(shape, best, rivals)
        if twins:
            best = by_convention([best] + twins, shape, guess, opt)
            convention = _by_convention_sentence(shape, maps)
    if rivals and shape.lattice is not None:
        best, rivals, convention = _explains_most(cam, shape, xy, best, rivals, convention, guess, opt)
    if rivals and guess is not None:
        agree = [c for c in [best] + rivals if _agrees(c, guess, opt)]
        if len(agree) == 1:
            best, rivals = agree[0], []
    if rivals:
        what = ", ".join(f"{len(c.sph)} spheres at {c.rms_px:.2f} px" for c in rivals[:3])
        return SearchResult(ambiguous("ambiguous_identity", f"{len(rivals) + 1} identifications fit about equally "
                                      f"(best {len(best.sph)} spheres at {best.rms_px:.2f} px; also {what})"),
                            best, rivals, convention)
    return SearchResult(OK, best, [], convention)


def held_back(results: list, n_dets: list, share: float = 0.5, least: int = 3) -> list:
    """Per frame, None or a ``no_pose`` status for an ``ok`` search result
    (``results``: SearchResult per frame; ``n_dets``: each frame's detection
    count) whose identification explains fewer than ``share`` of its own
    frame's detections and of the median ok frame's spheres: left out of the
    first bundle for the second look, with the calibrated camera, to take or
    refuse. Nothing is held back when fewer than ``least`` frames would stay.

    (The nominal camera leaves an intensifier's edge several px off, so a
    frame whose right pose was not voted can be "explained" by a handful of
    spheres at 2-3 px: the third renderer's cage, 28 beads, 6-9 spheres at
    2.3-3.5 px in 6 of 22 frames, nearly all named wrong. The bundle's
    re-gathering usually rejects them, but one that kept 6 markers entered
    the first bundle at 0.75 px and bent its fit before it was rejected.)"""
    n = [len(r.best.sph) if r.status.ok and r.best is not None else 0 for r in results]
    strong = [k for k in n if k]
    if not strong:
        return [None] * len(results)
    median = float(np.median(strong))
    out = [rejected("no_pose", f"the nominal camera's best identification explains {k} of {d} markers "
                    f"({r.best.rms_px:.2f} px RMS) against a median of {median:.0f} spheres in this scan's "
                    f"frames, and none did better with the calibrated camera")
           if k and k < share * d and k < share * median else None
           for r, k, d in zip(results, n, n_dets)]
    return out if sum(k > 0 for k in n) - sum(o is not None for o in out) >= least else [None] * len(results)


def _explains_most(cam: Camera, shape: PhantomShape, xy: np.ndarray, best: Candidate, rivals: list,
                   convention: str, guess, opt: SearchOptions):
    """Tied labellings of a grid told apart by the detections they explain:
    a sphere assigned, or one whose predicted shadow holds a detection no
    other sphere took (that lattice site's sphere, moved beyond the gate by
    the distortion the nominal camera lacks), less the spheres it puts
    clear on the detector with nothing there. One pose (up to the
    phantom's symmetry) explaining 2 or more than every other wins; else
    the tie stands. Returns (best, rivals, convention).

    (An independent renderer's 6x6 grid with a corner missing: the right
    labelling lost a corner 4.5 px off and tied with two turns at 34
    spheres, one of which put the missing corner on a detection and a
    sphere where the image has none. Counted in the ranking itself, such
    spheres let a 7x7 grid's labelling at 0.81 px beat ones at 0.23 px, and
    a helix's turned labellings, whose spheres fall near the right ones'
    shadows, outrank its right one: hence only between ties, only a grid's.)"""
    cands = [best] + rivals
    score = []
    for c in cands:
        seen, missing = shadow_tally(cam, shape, c.R, c.t, c.sph, c.det, xy)
        score.append(len(c.sph) + seen - missing)
    top = max(score)
    lead = [c for c, v in zip(cands, score) if v == top]
    rest = [v for v in score if v != top]
    if not rest or top < max(rest) + 2:
        return best, rivals, convention
    twins, maps, others = _by_symmetry(shape, lead[0], lead[1:])
    if others:
        return best, rivals, convention
    if twins:
        return by_convention(lead, shape, guess, opt), [], _by_convention_sentence(shape, maps)
    return lead[0], [], convention


def _by_convention_sentence(shape: PhantomShape, names: list) -> str:
    if not shape.planar:
        # (a cube's 23 turns, named one by one in every frame, drown the sentence)
        return (f"labelled by convention (the smallest turn) among the {len(shape.perms) + 1} poses the "
                f"phantom's {len(shape.perms)} turns onto itself make identical")
    return ("labelled by convention (phantom normal towards the detector, then the smallest turn) among poses "
            "its symmetry makes identical: " + "; ".join(sorted(set(names))))


def by_convention(twins: list, shape: PhantomShape, guess=None, opt: SearchOptions = SearchOptions()) -> Candidate:
    """One of poses the phantom's symmetry makes identical: the one a guess
    agrees with, else (a planar phantom) the normal towards +z, then the
    smallest turn (a 3-D phantom's "normal", its thinnest axis, is no
    convention: a cube has none)."""
    if guess is not None:
        agree = [c for c in twins if _agrees(c, guess, opt)]
        if len(agree) == 1:
            return agree[0]
    return min(twins, key=lambda c: (float(shape.planar and (c.R @ shape.n)[2] < 0),
                                     float(np.linalg.norm(matrix_to_rotvec(c.R)))))


def _by_symmetry(shape: PhantomShape, best: Candidate, rivals: list):
    """Split rivals into those a phantom symmetry relates to ``best`` (same
    image, same calibration) and the rest; returns (twins, names of the
    symmetries, rest)."""
    twins, used, rest = [], [], []
    for c in rivals:
        hit = None
        for perm, name in zip(shape.perms, shape.perm_names):
            mapping = dict(zip(best.det.tolist(), perm[best.sph].tolist()))
            theirs = dict(zip(c.det.tolist(), c.sph.tolist()))
            common = set(mapping) & set(theirs)
            if common and all(mapping[d] == theirs[d] for d in common):
                hit = name
                break
        if hit is None:
            rest.append(c)
        else:
            twins.append(c)
            used.append(hit)
    return twins, used, rest
