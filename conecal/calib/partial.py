"""A 3-D phantom's partial symmetries: rigid motions that carry half of its
spheres or more onto other spheres (a helix's screw by one bead: every bead
onto the next but the last). A frame that does not see what breaks one (the
helix's ends, or beads of the other size when sizes code the position, which
``phantom.csv`` does not hold) images the phantom identically in two poses,
so the search must offer the moved labelling as a rival and let the tie make
the frame ambiguous (an independent renderer's coded helix: three frames
named every bead one along, "ok", the pose screwed by 15 deg and 4.6 mm).
Whole symmetries (a grid's turns) are the lattice's (:mod:`.lattice`).
Units: mm, phantom frame.
"""

from __future__ import annotations

import functools

import numpy as np

from .candidate import Candidate, relabel, rigid_fit
from .phantom import PhantomShape

# two spheres are the same place within this share of the phantom's spacing
_SAME = 0.05
# a motion counts when it carries this share of the spheres onto spheres
_SHARE = 0.5
# phantoms with more spheres than this are not searched (a grid's are its lattice's)
_MOST = 200
SCREWED = "moved by a partial symmetry of the phantom"


@functools.lru_cache(maxsize=16)
def _maps(key: bytes, n: int) -> tuple:
    P = np.frombuffer(key).reshape(n, 3)
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    off = D + np.diag(np.full(n, np.inf))
    spacing = float(np.median(off.min(1)))
    tol = _SAME * spacing
    found: dict = {}
    # each sphere with its nearest neighbour and the next nearest not on their line
    order = np.argsort(off, axis=1)
    for a in range(n):
        b = int(order[a, 0])
        for c in range(n):
            for e in np.flatnonzero(np.abs(D[c] - D[a, b]) < tol):
                if (c, int(e)) == (a, b) or c == e:
                    continue
                for g in order[a, 1:4]:
                    if g == b:
                        continue
                    h = np.flatnonzero((np.abs(D[c] - D[a, g]) < tol) & (np.abs(D[e] - D[b, g]) < tol))
                    for hh in h:
                        if len({c, int(e), int(hh)}) < 3:
                            continue
                        R, o = rigid_fit(P[[a, b, g]], P[[c, int(e), int(hh)]])
                        Q = P @ R.T + o
                        d = np.linalg.norm(Q[:, None] - P[None], axis=-1)
                        j = d.argmin(1)
                        hit = d[np.arange(n), j] < 2 * tol
                        if hit.sum() < max(5, _SHARE * n) or np.all(j[hit] == np.flatnonzero(hit)):
                            continue
                        to = tuple(int(j[i]) if hit[i] else -1 for i in range(n))
                        found.setdefault(to, None)
                    break   # one third sphere fixes the motion
    # (a whole symmetry maps every sphere: that is a phantom symmetry, not partial)
    return tuple(t for t in found if -1 in t)


def partial_maps(points: np.ndarray) -> tuple:
    """The partial symmetries of ``points`` (n, 3) mm: tuples ``to`` with
    ``to[i]`` the sphere that sphere i is carried onto, -1 where none."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    if len(P) < 5 or len(P) > _MOST:
        return ()
    return _maps(P.tobytes(), len(P))


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
