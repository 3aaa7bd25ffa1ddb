"""A robot frame whose joint-log pose is too far off to start fit-pose is
found by the pattern search of the free-pose calibration, then fitted again
under the same tests (``fit-pose`` passes :func:`rescue_frame` to
:func:`conecal.fit.pose.fit_poses`)."""

from __future__ import annotations

import numpy as np

from ..fit.pose import FramePose, fit_frame
from .camera import GeometryCamera
from .phantom import describe_phantom
from .search import SearchOptions, search_frame


def rescue_frame(frame, geometry, pts, ids, radius, xy, sg, R_log, t_log, opt, screw, failed: FramePose) -> FramePose:
    """The pattern search  for a frame the log's pose could not
    start; the frame is fitted again from what it finds, under the same tests.
    Identifications the pattern alone cannot tell apart (a helix shifted by a
    sphere) are decided by the log only when it is at least twice as close to
    one of them as to any other, in phantom-point RMS. Otherwise the first
    rejection stands."""
    found = search_frame(GeometryCamera(geometry), describe_phantom(pts, ids, radius=radius), xy, (R_log, t_log),
                         SearchOptions(min_spheres=opt.min_spheres))
    start = found.best if found.status.ok else _nearest_by_margin(found, pts, R_log, t_log)
    if start is None:
        return failed
    p = fit_frame(frame, geometry, pts, ids, radius, xy, sg, start.R, start.t, opt, screw)
    if not p.status.ok:
        return failed
    p.found_by = "pattern search (the log's pose was off)"
    return p


def _nearest_by_margin(found, pts, R_log, t_log, margin: float = 3.0):
    """The ambiguous search's candidate the log points to, or None. Distances
    are RMS displacements of the phantom's points (mm); the log must be within
    1/margin of the distance from that candidate to each rival, so it is at
    least (margin - 1) times closer to it than to any other."""
    if found.status.state != "ambiguous" or found.best is None:
        return None
    cands = [found.best] + list(found.alternatives)

    def d(Ra, ta, Rb, tb):
        return float(np.sqrt(np.mean(np.sum((pts @ (Ra - Rb).T + (ta - tb)) ** 2, axis=1))))

    near = min(cands, key=lambda c: d(c.R, c.t, R_log, t_log))
    dl = d(near.R, near.t, R_log, t_log)
    sep = min(d(near.R, near.t, c.R, c.t) for c in cands if c is not near)
    return near if dl * margin < sep else None
