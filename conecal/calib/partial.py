"""A 3-D phantom's partial symmetries: rigid motions that carry half of its
spheres or more onto other spheres (a helix's screw by one bead: every bead
onto the next but the last). A frame that does not see what breaks one (the
helix's ends, or beads of the other size when sizes code the position, which
``phantom.csv`` does not hold) images the phantom identically in two poses,
so the search must offer the moved labelling as a rival and let the tie make
the frame ambiguous (an independent renderer's coded helix: three frames
named every bead one along, "ok", the pose screwed by 15 deg and 4.6 mm).
Whole symmetries (a grid's turns, a cube's corners) are the phantom's own
(:mod:`.phantom`): the same image, the same calibration. Units: mm,
phantom frame.
"""

from __future__ import annotations

import numpy as np

from .candidate import Candidate, relabel
from .phantom import PhantomShape, point_maps

SCREWED = "moved by a partial symmetry of the phantom"


def partial_maps(points: np.ndarray) -> tuple:
    """The partial symmetries of ``points`` (n, 3) mm: tuples ``to`` with
    ``to[i]`` the sphere that sphere i is carried onto, -1 where none."""
    return tuple(t for t in point_maps(points) if -1 in t)


def moved(shape: PhantomShape, c: Candidate, least: float | None = None) -> list[Candidate]:
    """Candidate ``c`` relabelled by each partial symmetry of a 3-D phantom
    (see the module's docstring): each detection keeps its place and takes
    the sphere its sphere is carried onto, and the pose moves alike so that
    the relabelled spheres land where the detections are; those keeping
    ``least`` spheres (default: three quarters of ``c``'s, 4 or more: a
    rival must explain about as many, a motion that keeps few is none)."""
    if shape.lattice is not None:
        return []
    least = max(4, 0.75 * len(c.sph)) if least is None else least
    out = []
    for to in partial_maps(shape.points):
        m = relabel(c, [None if v < 0 else v for v in to], shape.points, SCREWED, least)
        if m is not None:
            out.append(m)
    return out


def moved_poses(shape: PhantomShape, c: Candidate) -> list[tuple]:
    """Poses (R, t) of candidate ``c`` moved by each partial symmetry of a
    3-D phantom that keeps 4 or more of its spheres, so that those land
    where their detections are: starts from which every detection is named
    again (:func:`.second_look._doubted`). A biplane phantom whose one plane
    is a 5x5 grid and whose other is laid out otherwise: a frame named with
    the phantom turned by 90 deg fitted 0.158 px against its scan's 0.076
    (the other plane's 3 mm offset taken up by the pose and the frame's
    twist), ok and wrong, and only :func:`moved`'s rivals, which keep the
    carried spheres alone, were offered (too few to count)."""
    return [(m.R, m.t) for m in moved(shape, c, least=4)]


def related(points: np.ndarray, a: Candidate, b: Candidate) -> bool:
    """Whether labellings ``a`` and ``b`` of one frame's detections differ
    by a partial symmetry of the phantom (``points`` (n, 3) mm): on the
    detections both name, ``b``'s sphere is where the motion carries
    ``a``'s. Which of them the detector shows unseen spheres for says
    nothing then (a coded helix's undetected small beads leave both with
    as many), so they tie on what they explain."""
    maps = partial_maps(points)
    if not maps:
        return False
    sa = dict(zip(np.asarray(a.det).tolist(), np.asarray(a.sph).tolist()))
    pairs = [(sa[d], s) for d, s in zip(np.asarray(b.det).tolist(), np.asarray(b.sph).tolist()) if d in sa]
    if len(pairs) < 4:
        return False
    return any(all(to[i] == j for i, j in pairs) or all(to[j] == i for i, j in pairs) for to in maps)


def screw_tie(shape: PhantomShape, best: Candidate, c: Candidate) -> bool:
    """Whether ``c`` ties with ``best`` by a partial symmetry of a 3-D
    phantom (:func:`related`) and explains as many detections (one fewer is
    the end bead the motion carries off: the end, seen, tells them apart)."""
    return shape.lattice is None and len(c.sph) >= len(best.sph) and related(shape.points, best, c)


def carried_off(shape: PhantomShape, best: Candidate, c: Candidate) -> bool:
    """Whether rival ``c`` is ``best`` moved by a partial symmetry of a 3-D
    phantom that explains only detections ``best`` explains, and fewer: the
    ones it leaves are where the motion carries spheres off the phantom (a
    helix's end bead, seen), which ``best`` puts at the noise floor with the
    calibrated camera (the second look). No tie then, whatever the unseen spheres (the third
    renderer's coded helix: 28 against 27 spheres at 0.09 px, with small
    beads undetected, left frames ambiguous). Not a grid's: its turns are
    partial symmetries too where a corner is missing, and under a distortion
    the model lacks the right name is the one that explains fewer (the
    lattice's own rules judge those)."""
    return (shape.lattice is None and len(c.det) < len(best.det)
            and set(np.asarray(c.det).tolist()) <= set(np.asarray(best.det).tolist())
            and related(shape.points, best, c))
