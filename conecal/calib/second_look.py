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
every other, at the noise floor itself, is the frame's identity; otherwise
the frame keeps its status. Units: px, mm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..documents.status import OK, ambiguous
from .bundle import Bundle
from .candidate import Candidate, assign, refine_pose
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


def _frame_model(b: Bundle):
    """The camera and a distortion for a frame outside the bundle: the shared
    part, and each per-frame term at its median over the bundle's frames."""
    dist = b.distortion
    if dist is not None and b.family.per_frame:
        k = list(dist.coefficients)
        for j, n in enumerate(b.family.per_frame):
            k[dist.names.index(n)] = float(np.median(b.per_frame[:, j]))
        dist = dist.with_coefficients(k)
    return b.camera, dist


def _refit(cam, points: np.ndarray, xy: np.ndarray, c: Candidate, gate: float) -> Candidate:
    """Candidate ``c`` refitted on undistorted detections ``xy`` with the
    calibrated camera, its spheres re-assigned within ``gate`` px."""
    R, t, sph, det = c.R, c.t, c.sph, c.det
    for _ in range(3):
        if len(sph) < 4:
            return replace(c, rms_px=np.inf)
        R, t, _ = refine_pose(cam, points[sph], xy[det], R, t, f_scale=gate)
        new_sph, new_det = assign(cam.project(points @ R.T + t), xy, gate)
        if np.array_equal(new_sph, sph) and np.array_equal(new_det, det):
            break
        sph, det = new_sph, new_det
    if len(sph) < 4:
        return replace(c, rms_px=np.inf)
    # spheres and RMS over the markers within 3 median residuals (a gross error
    # counts for neither: 3.5 sigma of a 2-D Gaussian)
    r = np.linalg.norm(cam.project(points[sph] @ R.T + t) - xy[det], axis=1)
    keep = r <= 3 * np.median(r)
    return Candidate(det[keep], sph[keep], R, t, float(np.sqrt(np.mean(r[keep] ** 2))), c.how + ", second look")


def second_look(b: Bundle, out: list, usable: list, dets: dict, shape, points: np.ndarray, opt):
    """Frames looked at again with the calibrated camera: those of ``out``
    (not in the bundle) whose status a second look may overturn, and those of
    ``usable`` (in the bundle, slot order) that leave more than a tenth of
    their detections, and 3 or more, unexplained (a phantom with a symmetric
    part, as a biplane's square grid, can be labelled with that part turned
    and fit within the noise on the spheres it keeps). Returns (frames that
    now have an identity, frames in the bundle that no longer have one,
    set ambiguous). ``shape``: the PhantomShape searched; ``points``: the
    phantom (P, 3) mm as the bundle has it; ``opt``: FreeOptions."""
    pooled = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1))))    # 2-D RMS, px
    gate = max(0.5, opt.outlier_factor * pooled)
    cam, dist = _frame_model(b)
    won, lost = [], []
    for fr in usable:
        s = fr["slot"]
        n = len(dets[fr["frame"]][0])
        d, p = fr["pairs"]
        if n - len(d) < 3 or n - len(d) <= 0.1 * n:
            continue
        current = Candidate(np.asarray(d), np.asarray(p), b.R[s], b.t[s], how=fr["search"].best.how)
        verdict = _decide(cam, dist, shape, points, dets[fr["frame"]][0], [current], gate, pooled, opt)
        if verdict is None or isinstance(verdict, str):
            fr["status"] = ambiguous("ambiguous_identity", verdict or "no identification explains this frame's "
                                     "markers at the noise floor with the calibrated camera")
            fr["slot"] = None
            lost.append(fr)
        elif not _same(verdict[0], current) or len(verdict[0].sph) > len(current.sph) + 1:
            _identified(fr, *verdict)
            won.append(fr)
    for fr in out:
        res = fr["search"]
        if fr["status"].reason not in _LOOK_AGAIN:
            continue
        old = [res.best, *res.alternatives] if res.best is not None else []
        verdict = _decide(cam, dist, shape, points, dets[fr["frame"]][0], old, gate, pooled, opt)
        if verdict is not None and not isinstance(verdict, str):
            _identified(fr, *verdict)
            won.append(fr)
    return won, lost


def _identified(fr: dict, best: Candidate, convention: str) -> None:
    fr["search"] = replace(fr["search"], status=OK, best=best, alternatives=[], convention=convention)
    fr["status"] = OK
    fr["second_look"] = True
    # (the first identification's markers, gathered at its prediction, go with it)
    fr.pop("pairs", None)


def _decide(cam, dist, shape, points, xy, old: list, gate: float, pooled: float, opt):
    """The frame searched again on its undistorted detections ``xy``; with
    ``old`` candidates, all refitted with the calibrated camera. Returns
    (winner, convention), a sentence when identifications tie, or None when
    none is at the noise floor."""
    xy = dist.undistort(xy) if dist is not None else xy
    again = search_frame(cam, shape, xy, None, replace(opt.search, n_orientations=3 * opt.search.n_orientations))
    new = [again.best, *again.alternatives] if again.best is not None else []
    cands = [_refit(cam, points, xy, c, gate) for c in old + new]
    cands = [replace(c, missing=unseen_spheres(cam, shape, c.R, c.t, c.sph)) for c in cands
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
    tied = [c for c in cands[1:] if c.score >= best.score - 1 and not _same(c, best)
            and len(c.sph) * (c.rms_px ** 2 - best.rms_px ** 2) / var < opt.mirror_chi2]
    if best.rms_px > opt.floor_factor * pooled:
        return None
    if tied:
        return (f"{len(tied) + 1} identifications fit about equally with the calibrated camera (best "
                f"{len(best.sph)} spheres at {best.rms_px:.2f} px; also " +
                ", ".join(f"{len(c.sph)} at {c.rms_px:.2f} px" for c in tied[:3]) + ")")
    return best, again.convention


def _same(a: Candidate, b: Candidate) -> bool:
    """The same identification (every shared detection named alike)."""
    da, db = dict(zip(a.det.tolist(), a.sph.tolist())), dict(zip(b.det.tolist(), b.sph.tolist()))
    common = set(da) & set(db)
    return bool(common) and all(da[d] == db[d] for d in common) and len(common) >= 0.8 * min(len(da), len(db))
