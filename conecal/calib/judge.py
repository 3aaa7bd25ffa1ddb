"""The bundle's judgement of its frames: each frame's RMS against the scan's
median frame RMS (``judge``), and a planar phantom's mirror pose (``mirrors``).
``opt``: :class:`.run.FreeOptions`. Units: px, rad.
"""

from __future__ import annotations

import numpy as np

from ..documents.status import ambiguous, rejected
from ..geometry import rotvec_to_matrix
from .bundle import Bundle, Observations
from .candidate import refine_pose

# a frame the second look named, of a 3-D phantom with partial symmetries, is
# held to this many times the median frame RMS (right ones: 0.7-1.2x)
_ANEW_FACTOR = 1.5


def judge(b: Bundle, usable, obs: Observations, opt, bar: float = 0.0,
           overlap: np.ndarray | None = None, anew: bool = False) -> tuple[bool, float]:
    """Per-frame RMS against the scan's median frame RMS; returns whether any
    frame was rejected (then the bundle is solved again without it) and the
    limit (px). ``bar``: the limit of the judgement before, which this one
    does not go below: a rejected frame lowers the median it leaves, and a
    limit recomputed each time rejects the next frame in turn (the real
    intensifier recording: frame 11 at 0.388 px against 0.377, then frame 20
    at 0.365 against 0.356; carm_images grid_ii: frame 0, then frame 8).

    ``overlap`` (per bundle row): markers detect flagged as overlapping
    shadows. A frame with 6 or more others is judged on those (its RMS in
    the document stays over all): a ball phantom's frame whose few overlap
    markers sit at σ 0.3-0.6 px and fit within it was rejected at 0.27 px
    against 0.24 while its identity and pose were right. The limit still
    comes from the frames' whole RMS, so the judge only grows more lenient
    where the excess is the overlaps' (a frame made of them, as a grid seen
    edge-on, is judged on them all).

    ``anew``: a frame the second look named (a 3-D phantom with partial
    symmetries) is held to ``_ANEW_FACTOR`` of the median frame RMS: it was
    named at the floor on its markers within 3 median residuals, and a wrong
    name (an independent generator's biplane frame turned by 90 deg) sat in
    the bundle at 2.4x the median, over all its markers."""
    r2 = np.sum(b.residual_px ** 2, 1)
    per = np.array([np.sqrt(np.mean(r2[obs.slot == s])) for s in range(len(usable))])
    pooled = float(np.median(per))
    limit = min(opt.max_rms_px, max(opt.floor_factor * pooled, bar))
    judged = per.copy()
    if overlap is not None:
        for s in range(len(usable)):
            clear = (obs.slot == s) & ~overlap
            if clear.sum() >= 6:
                judged[s] = min(per[s], np.sqrt(np.mean(r2[clear])))
    dropped = False
    for s, fr in enumerate(usable):
        fr["rms_px"] = float(per[s])
        fr["slot"] = s
        mine = min(limit, _ANEW_FACTOR * pooled) if anew and fr.get("second_look") else limit
        if judged[s] > mine:
            fr["slot"] = None
            why = (f"{_ANEW_FACTOR:g}x the scan's median frame RMS {pooled:.3f} px, named by the second look"
                   if mine < limit else f"{opt.floor_factor:g}x the scan's median frame RMS {pooled:.3f} px"
                   if limit <= opt.floor_factor * pooled else
                   f"the limit before frames were rejected; the median frame RMS is now {pooled:.3f} px")
            aside = " (overlap markers aside)" if judged[s] != per[s] else ""
            fr["status"] = rejected("residual", f"residual {judged[s]:.3f} px RMS{aside}, above {mine:.3f} px "
                                    f"({why}{', capped by --max-rms' if limit == opt.max_rms_px else ''})")
            dropped = True
    return dropped, limit


def mirrors(b: Bundle, usable, obs: Observations, shape, radius, opt) -> None:
    """A planar phantom's second pose: its normal reflected about the line of
    sight through its centre. If that pose, refitted with the final camera
    and distortion, explains the frame within ``mirror_chi2``, the frame is
    ambiguous."""
    if not shape.planar:
        return
    pooled = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1)) / 2))
    for s, fr in enumerate(usable):
        if not fr["status"].ok:
            continue
        cam = b.frame_camera(s)
        sel = obs.slot == s
        P = b.phantom(shape.points)[obs.sph[sel]]
        dist = b.frame_distortion(s)
        xy = obs.xy[sel] if dist is None else dist.undistort(obs.xy[sel])
        R, t = b.R[s], b.t[s]
        c = R @ shape.origin + t
        v = (c - cam.source) / np.linalg.norm(c - cam.source)
        n = R @ shape.n
        n2 = 2 * (n @ v) * v - n
        axis = np.cross(n, n2)
        if np.linalg.norm(axis) < 1e-9:
            continue
        ang = np.arctan2(np.linalg.norm(axis), n @ n2)
        Q = rotvec_to_matrix(axis / np.linalg.norm(axis) * ang)
        R2 = Q @ R
        t2 = c - R2 @ shape.origin
        R2, t2, res2 = refine_pose(cam, P, xy, R2, t2, f_scale=50.0)
        _, _, res1 = refine_pose(cam, P, xy, R, t, f_scale=50.0)
        chi1 = float(np.sum(res1 ** 2)) / pooled ** 2
        chi2 = float(np.sum(res2 ** 2)) / pooled ** 2
        # a refit that slid back to this pose is no second solution
        apart = np.arccos(np.clip((R2 @ shape.n) @ n, -1, 1))
        if apart < ang / 2:
            continue
        fr["mirror_delta_chi2"] = chi2 - chi1
        # a near-frontal plate's mirror pose is turned by less than three times
        # this pose's own sigma about that axis: one broad solution, not two;
        # its sigma is widened by half the turn (document.py)
        unit = axis / np.linalg.norm(axis)
        if ang < 3 * _rotation_sigma(b, s, unit):
            fr["mirror_spread_rad"] = unit * ang / 2
            continue
        if chi2 - chi1 < opt.mirror_chi2:
            fr["status"] = ambiguous("mirror_pose", f"the mirror pose (normal turned {np.degrees(ang):.1f} deg about "
                                     f"the line of sight) fits within chi2 {chi2 - chi1:.1f} of this one")


def _rotation_sigma(b: Bundle, slot: int, axis: np.ndarray) -> float:
    """Sigma (rad) of frame ``slot``'s rotation about the lab ``axis`` (unit)."""
    C = b.covariance_of([f"frame{slot}_{n}" for n in ("rx", "ry", "rz")])
    return float(np.sqrt(max(axis @ C @ axis, 0.0)))
