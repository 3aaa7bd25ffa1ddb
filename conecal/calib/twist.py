"""Where each frame's intensifier twist starts when its centre is fitted.

A twist ``s`` about a centre moved by ``delta`` (normalised) from the shared
one is, to first order, the twist about the shared centre plus the linear
decentring ``q = -s delta`` (``geometry.distortion``). Fitted per frame from
a zero twist at the shared centre, the exact form can slide to a false
minimum: a weak twist about a far centre (an independent renderer's frame
then left 0.16 px where the right centre leaves 0.09, and held-out points
0.6 px off). The linear form has no such minimum (it is linear in s and q
for a fixed pose), so it gives the start: ``delta = -q / s``, and the frame
keeps whichever start fits it better. Units: px, mm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .bundle import Bundle, Family, Observations
from .candidate import TWIST_REACH, refine_pose_and_terms


def seed_twists(b: Bundle, fam: Family, obs: Observations, points: np.ndarray) -> Bundle:
    """``b`` (a fit of a family nested in ``fam``, same frames) as a start for
    ``fam``, whose twist turns about a centre of its own per frame: each
    frame's twist, centre and pose from the better of two single-frame fits
    (shared terms held): from ``b``'s twist at the shared centre, and from the
    centre the linear decentring puts it at. ``points``: the phantom (P, 3)
    mm as given (``b`` adds its refinement)."""
    F = len(b.R)
    names = b.distortion.names
    i_s, i_q = names.index("s"), [names.index("q1"), names.index("q2")]
    pooled = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1))))
    gate = max(0.5, 3.0 * pooled)
    R, t = b.R.copy(), b.t.copy()
    s = np.zeros(F)
    twist = np.zeros((F, 2))
    pts = b.phantom(points)
    for k in range(F):
        sel = obs.slot == k
        if sel.sum() < 10:          # (the pose's 6, the twist's 3 and one to spare)
            s[k] = b.frame_distortion(k).coefficients[i_s]
            continue
        cam, dist = b.frame_camera(k), b.frame_distortion(k)
        P, xy = pts[obs.sph[sel]], obs.xy[sel]
        starts = [(dist, R[k], t[k])]
        Rl, tl, _, lin = refine_pose_and_terms(cam, P, xy, R[k], t[k], gate, dist, [i_s] + i_q)
        sk = lin.coefficients[i_s]
        if abs(sk) > 1e-6:
            delta = -(np.array(lin.coefficients)[i_q] - np.array(dist.coefficients)[i_q]) / sk
            delta *= min(1.0, TWIST_REACH / max(float(np.linalg.norm(delta)), 1e-12))
            k0 = np.array(dist.coefficients)
            k0[i_s] = sk
            starts.append((dist.with_coefficients(k0, twist_centre=tuple(np.array(dist.centre) + delta * dist.radius)),
                           Rl, tl))
        best = None
        for d0, R0, t0 in starts:
            Rk, tk, res, own = refine_pose_and_terms(cam, P, xy, R0, t0, gate, d0, [i_s], twist=True)
            cost = float(np.sum(np.minimum(np.sum(res ** 2, 1), gate ** 2)))
            if best is None or cost < best[0]:
                best = (cost, Rk, tk, own)
        _, R[k], t[k], own = best
        s[k] = own.coefficients[i_s]
        twist[k] = np.array(own.twist_centre) - np.array(own.centre)
    per = np.zeros((F, len(fam.per_frame)))
    for j, n in enumerate(fam.per_frame):
        per[:, j] = s if n == "s" else b.frame_distortion(None).coefficients[names.index(n)]
    return replace(b, family=fam, per_frame=per, twist=twist, R=R, t=t)
