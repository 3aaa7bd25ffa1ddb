"""A second look, with the calibrated camera, at frames the pattern search
left ambiguous or got wrong.

The search compares identifications under the nominal camera, where an
intensifier's distortion leaves the right one several px off; so two that
differ by less than ``tie_px`` (1 px) tie there, and its orientation
samples (about 12 deg apart) can miss the right pose of a phantom with two
lattices (a biplane grid), leaving a wrong identification that the bundle
then rejects. Once the bundle has the camera and the distortion, such a
frame is searched again on its undistorted detections, three times denser,
and each candidate (the first search's and the new) is refitted with the
calibrated camera and compared at the scan's noise floor: one that
explains as many spheres and fits by more than ``mirror_chi2`` better than
every other, at the noise floor itself, is the frame's identity (a 3-D
phantom's with partial symmetries within ``_NEW_FLOOR`` of the scan's RMS).
Every other ok frame is also refitted from the poses its neighbouring
frames predict (and, when its pose jumps off the sweep, searched again near
them; a grid's also with its identity relabelled by the lattice's turns,
which doubt it only by explaining more detections at no more cost; a 3-D
phantom's with its identity moved by each partial symmetry, every
candidate fitting the frame's own distortion terms where the frame fits
above ``_OWN_ABOVE`` of the scan's RMS): when an identification found that
way explains as many detections and fits as well or better, the frame is ambiguous (its visible spheres
admit the phantom turned); an ok frame's identity is never replaced here.
A tied or unnamed frame of a phantom off a lattice is searched once more
near the pose its neighbouring frames predict (the data still decide), and
so is one whose new identification still leaves detections unexplained
before it is taken.
When identifications tie, the neighbouring frames' poses may break the
tie (``neighbours.py``); otherwise the frame keeps its status. Units: px, mm.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..documents.status import OK, ambiguous
from .bundle import Bundle
from .candidate import Candidate
from .lattice import TURNED, turned
from .neighbours import by_neighbours, conventional, guesses, jumps, predicted, same_pose
from .partial import SCREWED, carried_off, moved_poses, partial_maps, screw_tie
from .refit import MSAC_CAP, msac, named_from, own_terms, refit, worse_by
from .search import search_frame, unseen_spheres

# the statuses a second look may overturn: not a frame with too few markers
_LOOK_AGAIN = ("ambiguous_identity", "off_prediction", "residual", "no_pose")
# the most of the spheres a pose puts clear on the detector that may go unseen
# (an independent generator drops 10-20 % of the markers in half its frames)
_MISSING_SHARE = 0.25
# ... and at least this share of the frame's detections (at a steep tilt most
# shadows touch, and a wrong pose's unseen spheres are not counted: 13 of 45
# detections fitted within 0.3 px on an independent generator's 7x7 grid)
_EXPLAINED_SHARE = 0.5
# how much less a candidate must cost (MSAC, ``refit.msac``) than the one
# explaining the most detections to tie
_MSAC_MARGIN = 2 * MSAC_CAP
# a second look names a frame only within this many times the scan's RMS when
# the phantom has partial symmetries (right names: 0.5-1.2x)
_NEW_FLOOR = 1.5
# ... and doubts an ok frame fitting above this many times the scan's RMS with
# every rival fitting the frame's own distortion terms (right frames: 0.6-1.2x)
_OWN_ABOVE = 1.25


def second_look(b: Bundle, out: list, usable: list, dets: dict, shape, points: np.ndarray, opt):
    """Frames looked at again with the calibrated camera: those of ``out``
    (not in the bundle) whose status a second look may overturn, and those of
    ``usable`` (in the bundle, slot order) that leave more than a tenth of
    their detections, and 3 or more, unexplained (a phantom with a symmetric
    part, as a biplane's square grid, can be labelled with that part turned
    and fit within the noise on the spheres it keeps), and the other frames
    of ``usable`` refitted from their neighbours' poses (``_doubted``); ties
    go to ``by_neighbours``. Returns (frames that now have an identity,
    frames in the bundle that no longer have one, set ambiguous).
    ``shape``: the PhantomShape searched; ``points``: the phantom (P, 3) mm
    as the bundle has it; ``opt``: FreeOptions."""
    pooled = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1))))    # 2-D RMS, px
    gate = max(0.5, opt.outlier_factor * pooled)
    cam, dist = b.camera, b.frame_distortion(None)
    own_for = own_terms(b)
    won, lost, ties = [], [], {}
    pending = {}      # frame -> (fr, the denser search's verdict, its identity before or None)
    for fr in usable:
        s = fr["slot"]
        sig = dets[fr["frame"]][1]
        d, p = fr["pairs"]
        if not _unexplained(sig, d, gate):
            continue
        current = Candidate(np.asarray(d), np.asarray(p), b.R[s], b.t[s], how=fr["search"].best.how)
        verdict = _decide(cam, dist, shape, points, dets[fr["frame"]][0], [current], gate, pooled, opt,
                          own_for(dets[fr["frame"]][0]))
        if verdict is None or isinstance(verdict, Tie):
            fr["status"] = ambiguous("ambiguous_identity", verdict.sentence if verdict else "no identification "
                                     "explains this frame's markers at the noise floor with the calibrated camera")
            fr["slot"] = None
            lost.append(fr)
            ties[fr["frame"]] = (fr, verdict or Tie(fr["status"].detail, []))
            continue
        if shape.lattice is None and _unexplained(sig, verdict[0].det, gate):
            # still many detections unexplained: the denser search's 20 best
            # orientations can all be a symmetric part's turns (an independent
            # generator's biplane: 25 of 31 detections explained at 0.19 px,
            # every sphere named wrong; the right labelling, 31 at 0.19 px, was
            # never voted): searched near its neighbours' pose first
            pending[fr["frame"]] = (fr, verdict, current)
            ties[fr["frame"]] = (fr, Tie("", [verdict[0]], verdict[1]))
        elif _new(verdict[0], current):
            _identified(fr, *verdict)
            won.append(fr)
    for fr in out:
        res = fr["search"]
        if fr["status"].reason not in _LOOK_AGAIN:
            continue
        old = [res.best, *res.alternatives] if res.best is not None else []
        verdict = _decide(cam, dist, shape, points, dets[fr["frame"]][0], old, gate, pooled, opt,
                          own_for(dets[fr["frame"]][0]))
        if verdict is None or isinstance(verdict, Tie):
            ties[fr["frame"]] = (fr, verdict or Tie(fr["status"].detail, []))
        elif shape.lattice is None and _unexplained(dets[fr["frame"]][1], verdict[0].det, gate):
            pending[fr["frame"]] = (fr, verdict, None)
            ties[fr["frame"]] = (fr, Tie("", [verdict[0]], verdict[1]))
        else:
            _identified(fr, *verdict)
            won.append(fr)
    held = [fr for fr, _, _ in pending.values()]
    for fr, tie in list(_doubted(b, usable, lost + won + held, dets, shape, points, gate, pooled, opt)):
        fr["slot"] = None
        lost.append(fr)
        fr["status"] = ambiguous("ambiguous_identity", tie.sentence)
        ties[fr["frame"]] = (fr, tie)
    # (a frame identified anew is where its new identity puts it; one searched
    # again keeps its pose: a frame's own pose is never its guess, and its
    # neighbours' ties need it)
    posed = {fr["frame"]: (b.R[fr["slot"]], b.t[fr["slot"]]) for fr in usable if fr not in lost and fr not in won}
    posed.update({fr["frame"]: (fr["search"].best.R, fr["search"].best.t) for fr in won})
    for fr, verdict in _searched_near(cam, dist, shape, points, posed, ties, dets, gate, pooled, opt,
                                      own_for):
        ties.pop(fr["frame"])
        if fr["frame"] in pending and not _new(verdict[0], pending.pop(fr["frame"])[2]):
            continue
        _identified(fr, *verdict)
        if fr in lost:
            lost.remove(fr)
        won.append(fr)
        posed[fr["frame"]] = (fr["search"].best.R, fr["search"].best.t)
    for k, (fr, verdict, current) in pending.items():
        xy = dist.undistort(dets[k][0]) if dist is not None else dets[k][0]
        mine = verdict[0]
        if any(not _same(c, mine) and _doubts(cam, points, xy, c, mine, len(mine.sph), pooled)
               for c in ties[k][1].cands):
            # the search near its neighbours found rivals: ambiguous, unless they break the tie
            posed.pop(k, None)
            if current is not None:
                fr["slot"] = None
                lost.append(fr)
            continue
        ties.pop(k)
        fr["status"] = OK if current is not None else fr["status"]
        if _new(verdict[0], current):
            _identified(fr, *verdict)
            won.append(fr)
            posed[k] = (fr["search"].best.R, fr["search"].best.t)
    chosen = by_neighbours(cam, shape, points, posed, {k: v.cands for k, (_, v) in ties.items() if len(v.cands) > 1})
    for k, (c, why) in chosen.items():
        fr, verdict = ties[k]
        _identified(fr, c, verdict.convention)
        fr["identified_by"] = why
        if fr in lost:
            lost.remove(fr)
        won.append(fr)
    return won, lost


@dataclass
class Tie:
    """Identifications that fit a frame alike (best first), and why."""

    sentence: str
    cands: list
    convention: str = ""


def _identified(fr: dict, best: Candidate, convention: str) -> None:
    fr["search"] = replace(fr["search"], status=OK, best=best, alternatives=[], convention=convention)
    fr["status"] = OK
    fr["second_look"] = True
    # (the first identification's markers, gathered at its prediction, go with it)
    fr.pop("pairs", None)


def _searched_near(cam, dist, shape, points, posed: dict, ties: dict, dets: dict, gate, pooled, opt,
                   own_for=lambda raw: None):
    """Tied frames of a phantom off a lattice, and frames no candidate
    explains at the noise floor (an empty tie), searched again near the pose
    their ok neighbours predict (the orientations voted within 45 deg of it)
    and ranked with their tied identifications: the whole search keeps the
    20 best-voted orientations, and a helix's near-symmetric turns (each
    fitting the spheres it keeps at the noise) can fill them all, leaving the
    right one out (an independent generator's helix: three turned
    identifications of 18 spheres at 0.08-0.10 px tied in a frame whose 23
    detections the right one explains). The guess only says where to look:
    the data decide. Yields (frame, (winner, convention)); a tie that stays
    is updated in ``ties``."""
    if shape.lattice is not None or not ties:
        return
    near = guesses(cam, shape, points, posed, ties)
    for k, guess in near.items():
        fr, tie = ties[k]
        xy = dist.undistort(dets[k][0]) if dist is not None else dets[k][0]
        found = search_frame(cam, shape, xy, guess, opt.search)
        new = [c for c in [found.best, *found.alternatives] if c is not None]
        if not new:
            continue
        verdict = _rank(cam, shape, points, xy, tie.cands + new, gate, pooled, opt, tie.convention,
                        own_for(dets[k][0]))
        if isinstance(verdict, Tie):
            ties[k] = (fr, verdict)
            fr["status"] = ambiguous("ambiguous_identity", verdict.sentence)
        elif verdict is not None:
            yield fr, verdict


def _decide(cam, dist, shape, points, xy, old: list, gate: float, pooled: float, opt, own=None):
    """The frame searched again on its undistorted detections ``xy``; with
    ``old`` candidates and (a grid's) their relabellings by the turns of its
    lattice, all refitted with the calibrated camera.
    Returns (winner, convention), a Tie when identifications tie, or None
    when none is at the noise floor."""
    xy = dist.undistort(xy) if dist is not None else xy
    old = old + [c for o in old for c in turned(shape, points, o)]
    again = search_frame(cam, shape, xy, None, replace(opt.search, n_orientations=3 * opt.search.n_orientations))
    new = [again.best, *again.alternatives] if again.best is not None else []
    verdict = _rank(cam, shape, points, xy, old + new, gate, pooled, opt, again.convention, own)
    # (named at the noise floor itself where a 3-D phantom's partial symmetries
    # admit other names: an independent generator's biplane frame, named with
    # the phantom turned by 90 deg at 2.1x the scan's RMS, passed the 2.5x limit)
    if verdict is not None and not isinstance(verdict, Tie) and shape.lattice is None \
            and verdict[0].rms_px > _NEW_FLOOR * pooled and partial_maps(points):
        return None
    return verdict


def _rank(cam, shape, points, xy, cands: list, gate: float, pooled: float, opt, convention: str = "", own=None):
    """``cands`` refitted on undistorted detections ``xy`` with the calibrated
    camera and ranked: (winner, convention), a Tie, or None (see _decide)."""
    cands = [refit(cam, points, xy, c, gate, own) for c in cands]
    # (the gate here is the noise floor's, so a sphere a distortion the model
    # lacks moves by a px is not assigned; it is there all the same: under an
    # independent generator's unmodelled bump the right labelling of a grid
    # frame counted 13 spheres unseen, 4 of them inside their shadows)
    cands = [replace(c, missing=unseen_spheres(cam, shape, c.R, c.t, c.sph, xy if c.xy is None else c.xy))
             for c in cands
             if np.isfinite(c.rms_px) and len(c.sph) >= opt.search.min_spheres]
    # (a handful of spheres fits anywhere at the noise: a pose must explain
    # most of the spheres it puts clear on the detector)
    cands = [c for c in cands if c.missing <= _MISSING_SHARE * (len(c.sph) + c.missing)
             and len(c.sph) >= _EXPLAINED_SHARE * len(xy)]
    if not cands:
        return None
    cands.sort(key=lambda c: (-c.score, c.rms_px))
    best = cands[0]
    # a rival is out when it explains fewer spheres, or the same ones by
    # more than mirror_chi2 worse (chi-square in the scan's noise per axis)
    var = (pooled ** 2) / 2
    # (a candidate the phantom's symmetry relates to the best puts every sphere
    # in the same place: the same image and calibration, no rival; the best is
    # labelled by the search's convention among them. An independent
    # renderer's 6x6 grid with a corner missing: three such twins at one RMS
    # left 4 of 12 frames ambiguous)
    twin = [bool(shape.perms) and same_pose(cam, shape, points, c, best) for c in cands[1:]]
    if any(twin):
        best = conventional(shape, points, best)
    # (a labelling a partial symmetry of the phantom relates to the best --
    # a helix's screw by a bead -- ties on the detections it explains: the
    # unseen spheres that tell them apart are undetected ones as often)
    tied = [c for c, tw in zip(cands[1:], twin)
            if (c.score >= best.score - 1 or screw_tie(shape, best, c)) and not _same(c, best) and not tw
            and not carried_off(shape, best, c)
            and worse_by(cam, points, xy, c, best) / var < opt.mirror_chi2]
    if best.rms_px > opt.floor_factor * pooled:
        return None
    # Explaining the most detections within the floor's gate is not enough
    # where the model lacks a distortion: the right labelling loses the
    # spheres it moves beyond the gate, a turned one of a symmetric view bends
    # the fit to keep them (an independent generator's grid under an
    # unmodelled 2 px bump: 35 spheres at 0.14 px lost to 39 at 0.35 px, a
    # wrong ok). Scored as MSAC does, every detection costs its squared
    # residual over the floor's, at most 9, and an unexplained detection or
    # an unseen sphere 9: one that costs clearly less than the best ties.
    costs = [msac(cam, points, xy, c, pooled) for c in cands]
    lean = cands[int(np.argmin(costs))]
    if min(costs) < costs[0] - _MSAC_MARGIN and not _same(lean, best) and all(not _same(lean, c) for c in tied):
        tied.append(lean)
    if shape.lattice is not None:
        # (a grid's name that explains fewer but costs no more than one
        # detection's worth beyond the best ties too: an independent
        # generator's 7x7 grid under an unmodelled 2 px bump, a frame named
        # with the grid turned by 90 deg, 40 spheres at 0.21 px, where the
        # right name kept 36 at 0.14 px, MSAC 141.2 against 136.0: ok, turned)
        tied += [c for c, cost, tw in zip(cands[1:], costs[1:], twin)
                 if cost < costs[0] + MSAC_CAP and not tw and not _same(c, best)
                 and all(not _same(c, o) for o in tied)]
    if tied:
        return Tie(_tied(best, tied, "best "), [best] + tied, convention)
    return best, convention


def _doubts(cam, points, xy, c: Candidate, mine: Candidate, n_mine: int, pooled: float) -> bool:
    """Whether rival ``c`` doubts a frame's identification ``mine`` (``n_mine``
    spheres as it stands): it explains as many detections, or it costs
    clearly less as MSAC scores them (``_rank``). A rival explaining fewer
    at the same fit doubts nothing (turned helix labellings near the
    neighbours' pose, 13 spheres against 14 at 0.10 px, on an independent
    generator's right frames); one explaining one fewer far closer does
    (the right labelling of a grid under an unmodelled 2 px bump, 39
    spheres at 0.14 px, against a turned one's 40 at 0.23 px)."""
    if len(c.sph) >= n_mine:
        return True
    return msac(cam, points, xy, c, pooled) < msac(cam, points, xy, mine, pooled) - _MSAC_MARGIN


def _new(c: Candidate, current: Candidate | None) -> bool:
    """Whether ``c`` replaces a frame's identity ``current`` (None: it has
    none): another one, or the same with 2 or more spheres more."""
    return current is None or not _same(c, current) or len(c.sph) > len(current.sph) + 1


def _unexplained(sig: np.ndarray, explained, gate: float) -> bool:
    """Whether an identification explaining the detections ``explained``
    (indices) of a frame's (sigmas ``sig``, px) leaves more than a tenth of
    them, and 3 or more, unexplained. A detection whose 3 sigma exceeds
    ``gate`` (px) is not counted: its place cannot say which sphere, if any,
    it is (markers over two spheres nearly on top at sigma 1.5-1.9 px sent
    a ball phantom's right frame to a second look, where no identification
    was at the noise floor)."""
    out = np.ones(len(sig), bool)
    out[np.asarray(explained, int)] = False
    k = int(np.sum(out & (3 * np.asarray(sig) <= gate)))
    return k >= 3 and k > 0.1 * len(sig)


def _tied(first: Candidate, others: list, lead: str = "", tail: str = "") -> str:
    """The sentence of a tie between ``first`` and ``others`` (px)."""
    return (f"{len(others) + 1} identifications fit about equally with the calibrated camera ({lead}"
            f"{len(first.sph)} spheres at {first.rms_px:.2f} px; also " +
            ", ".join(f"{len(c.sph)} at {c.rms_px:.2f} px" for c in others[:3]) + f"){tail}")


def _doubted(b: Bundle, usable: list, settled: list, dets: dict, shape, points, gate, pooled, opt):
    """Ok frames that another identification fits as well or better, one
    found from the poses their neighbouring frames predict (a phantom whose
    visible spheres admit it turned by 180 deg, a marker lost where the turn
    would show), each frame with its own camera and distortion from the
    bundle. Yields (frame, Tie of the frame's identity and its rivals): such
    a frame is ambiguous unless its neighbours break the tie (an ok frame's
    identity is never replaced here: on a real intensifier recording a
    rival one column off beat the right one under the scan's median
    per-frame distortion). ``settled``: frames of ``usable`` already
    re-identified or set aside."""
    posed = {fr["frame"]: fr for fr in usable if fr not in settled}
    own_for = own_terms(b)
    poses_of = {k: (b.R[fr["slot"]], b.t[fr["slot"]]) for k, fr in posed.items()}
    preds = predicted(b.camera, shape, points, poses_of)
    off = jumps(b.camera, shape, points, poses_of, preds)
    for k, fr in posed.items():
        poses = preds.get(k, [])
        if not poses and shape.lattice is None and not partial_maps(points):
            continue
        cam, dist = b.frame_camera(fr["slot"]), b.frame_distortion(fr["slot"])
        d, p = fr["pairs"]
        current = Candidate(np.asarray(d), np.asarray(p), b.R[fr["slot"]], b.t[fr["slot"]], how=fr["search"].best.how)
        moved = moved_poses(shape, current)
        # (the frame's own terms were fitted to its identity, which a rival
        # moved by a partial symmetry doubts: where the frame fits above the
        # scan's RMS, every candidate fits its own; a turned biplane frame's
        # took up the turn at 2x the RMS)
        own = own_for(dets[k][0]) if moved and fr.get("rms_px", np.inf) > _OWN_ABOVE * pooled else None
        if own is not None:
            dist = b.frame_distortion(None)
        xy = dist.undistort(dets[k][0]) if dist is not None else dets[k][0]
        # (a grid's turns: where shadows merge, the search may have offered
        # only a turned labelling, and the right one explains more)
        starts = turned(shape, points, current)
        # (and a 3-D phantom's partial symmetries: the frame's identity moved
        # by one, every detection named again from there)
        named = set()
        for (R, t), how in [(p, "from the neighbouring frames' poses") for p in poses] + \
                [(p, SCREWED) for p in moved]:
            c = named_from(cam, points, xy, R, t, gate, opt, how)
            # (one naming once: a helix's screws by one bead or two name a frame alike)
            if c is not None and (key := (c.det.tobytes(), c.sph.tobytes())) not in named:
                named.add(key)
                starts.append(c)
        if k in off:
            # (its pose jumps off the sweep, as a turned phantom's does; a
            # neighbour's pose may be tens of px off, beyond the assignment
            # above: the identities are voted near it)
            near = search_frame(cam, shape, xy, poses[0], opt.search)
            starts += [c for c in [near.best, *near.alternatives] if c is not None]
        if not starts:
            continue
        verdict = _rank(cam, shape, points, xy, [current] + starts, gate, pooled, opt, fr["search"].convention, own)
        if verdict is None:
            continue
        cands = verdict.cands if isinstance(verdict, Tie) else [verdict[0]]
        others = [c for c in cands if not same_pose(cam, shape, points, c, current)]
        if not others:
            continue
        # (refitted only for a rival: most ok frames' ranking returns their own identity)
        mine = refit(cam, points, xy, current, gate, own)
        mine = replace(mine, missing=unseen_spheres(cam, shape, mine.R, mine.t, mine.sph,
                                                    xy if mine.xy is None else mine.xy))
        # (a grid's turn doubts only by explaining more detections at no more
        # cost: one that explains as many is its visible part's symmetry, which
        # the search's choice already met, and one bent to keep a sphere more
        # under a bump the model lacks costs more: a sweep's grid lost 4 ok
        # frames to such turns)
        others = [c for c in others if _doubts(cam, points, xy, c, mine, len(current.sph), pooled)
                  and (TURNED not in c.how or (len(c.sph) > len(mine.sph) and
                                                msac(cam, points, xy, c, pooled) <= msac(cam, points, xy, mine,
                                                                                           pooled)))]
        if others:
            tail = (", one of them the grid turned" if any(TURNED in c.how for c in others)
                    else ", one of them from the poses the neighbouring frames predict")
            yield fr, Tie(_tied(mine, others, tail=tail), [mine] + others, fr["search"].convention)


def _same(a: Candidate, b: Candidate) -> bool:
    """The same identification (every shared detection named alike)."""
    da, db = dict(zip(a.det.tolist(), a.sph.tolist())), dict(zip(b.det.tolist(), b.sph.tolist()))
    common = set(da) & set(db)
    return bool(common) and all(da[d] == db[d] for d in common) and len(common) >= 0.8 * min(len(da), len(db))
