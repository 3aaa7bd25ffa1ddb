"""What a calibration phantom's pattern offers for identification.

A planar phantom whose spheres sit on a lattice (a grid) is identified by
growing the lattice in the image; its own symmetries (the lattice maps that
carry the set of spheres onto itself, rigid in 3-D: a square grid turned
by 90 deg or seen from behind) are found here, so that two labellings they
relate are known to give the same calibration. Any other phantom is
identified by a pose search (``search.py``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from itertools import product

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import matrix_to_rotvec
from .candidate import rigid_fit

# the eight signed permutations of the lattice axes (a square lattice's point group)
LATTICE_MAPS = tuple(np.array(m) for m in
                     ([[a, 0], [0, b]] for a, b in product((1, -1), repeat=2)))
LATTICE_MAPS = LATTICE_MAPS + tuple(np.array(m) for m in ([[0, a], [b, 0]] for a, b in product((1, -1), repeat=2)))
# two spheres are the same place within this share of the phantom's spacing
_SAME = 0.05
# a rigid motion counts when it carries this share of the spheres onto spheres
_SHARE = 0.5
# 3-D phantoms with more spheres than this are not searched for rigid maps
_MOST = 200


@dataclass(frozen=True, eq=False)
class PhantomShape:
    """points (n, 3) mm in the phantom frame; ids (n,); ``planar``: all in one
    plane (``origin``, in-plane unit vectors ``e1``, ``e2``, normal ``n``);
    ``lattice`` (n, 2) integer coordinates along ``basis`` (2, 2) mm in the
    (e1, e2) plane, or None; ``symmetries``: lattice maps (M, o) with
    ``M @ ij + o`` carrying the phantom's lattice onto itself rigidly;
    ``perms``: the sphere index permutations of every rigid symmetry of the
    phantom (a lattice's, or a 3-D phantom's: a cube's 23 turns), not the
    identity, with ``perm_names`` describing each."""

    points: np.ndarray
    ids: np.ndarray
    planar: bool
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    n: np.ndarray
    lattice: np.ndarray | None = None
    basis: np.ndarray | None = None
    symmetries: list = field(default_factory=list)
    radius: float = 1.0        # sphere radius, mm
    perms: tuple = ()
    perm_names: tuple = ()

    @property
    def plane_xy(self) -> np.ndarray:
        """(n, 2) mm: the points in the (e1, e2) plane coordinates."""
        q = self.points - self.origin
        return np.column_stack([q @ self.e1, q @ self.e2])

    @property
    def spacing_mm(self) -> float:
        d = np.linalg.norm(self.points[:, None] - self.points[None], axis=-1)
        d[d == 0] = np.inf
        return float(np.median(d.min(1)))

    def lattice_index(self) -> dict:
        return {tuple(int(v) for v in ij): k for k, ij in enumerate(self.lattice)}


def describe_phantom(points, ids, plane_tol: float = 0.02, lattice_tol: float = 0.1,
                     radius: float = 1.0) -> PhantomShape:
    """Classify a phantom's sphere positions (mm, phantom frame): planar when
    every sphere is within ``plane_tol`` of the nearest-neighbour spacing of
    one plane (a measured grid is flat to a fraction of a mm, not exactly);
    on a lattice when every sphere is within ``lattice_tol`` cells of one."""
    P = np.asarray(points, float)
    origin = P.mean(0)
    _, s, Vt = np.linalg.svd(P - origin)
    e1, e2, n = Vt
    if np.linalg.det(Vt) < 0:
        n = -n
    # the normal along the phantom's own +z where it has one (conventions refer to it)
    if n @ [0, 0, 1] < 0 or (n @ [0, 0, 1] == 0 and n @ [0, 1, 0] < 0):
        n, e2 = -n, -e2
    dist = np.linalg.norm(P[:, None] - P[None], axis=-1)
    spacing = float(np.min(dist[dist > 0])) if len(P) > 1 else 1.0
    planar = len(P) >= 4 and float(np.abs((P - origin) @ n).max()) <= plane_tol * spacing
    shape = PhantomShape(P, np.asarray(ids), planar, origin, e1, e2, n, radius=radius)
    if not planar:
        perms = [p for p in (np.array(to) for to in point_maps(P) if -1 not in to) if _exact(P, p, spacing)]
        return PhantomShape(P, shape.ids, False, origin, e1, e2, n, radius=radius, perms=tuple(perms),
                            perm_names=tuple(_turn_name(P, p) for p in perms))
    q = shape.plane_xy
    diffs = (q[:, None] - q[None]).reshape(-1, 2)
    length = np.hypot(diffs[:, 0], diffs[:, 1])
    keep = length > 1e-6
    diffs, length = diffs[keep], length[keep]
    # nearest-neighbour steps, folded to one half-plane and grouped by direction;
    # the median of each group, so that one sphere off its place does not tilt the lattice
    near = diffs[length < 1.25 * length.min()]
    near = np.where((near[:, 1] < 0) | ((near[:, 1] == 0) & (near[:, 0] < 0)), -1, 1)[:, None] * near
    ang = np.arctan2(near[:, 1], near[:, 0])
    a = np.median(near[np.abs(ang - ang[np.argmin(np.abs(ang))]) < 0.2], axis=0)
    other = near[np.abs(np.abs(near @ a) / (np.linalg.norm(near, axis=1) * np.linalg.norm(a))) < 0.95]
    if len(other) == 0:
        return shape
    ang_b = np.arctan2(other[:, 1], other[:, 0])
    b = np.median(other[np.abs(ang_b - ang_b[0]) < 0.2], axis=0)
    B = np.column_stack([a, b])
    ij = np.linalg.solve(B, (q - q[0]).T).T
    if np.abs(ij - np.round(ij)).max() > lattice_tol:
        return shape
    ij = np.round(ij).astype(int)
    ij -= ij.min(0)
    # the basis from every sphere (least squares), not from the median step: a
    # measured grid's small errors average out, so its symmetries are found
    B = np.linalg.lstsq(np.column_stack([ij, np.ones(len(ij))]), q, rcond=None)[0][:2].T
    sym = _symmetries(ij, B)
    index = {tuple(int(v) for v in k): i for i, k in enumerate(ij)}
    perms = tuple(np.array([index[tuple(int(v) for v in M @ k + o)] for k in ij]) for M, o in sym)
    return PhantomShape(P, shape.ids, True, origin, e1, e2, n, ij, B, sym, radius, perms,
                        tuple(symmetry_name(M, B) for M, _ in sym))


def point_maps(points: np.ndarray) -> tuple:
    """Rigid motions (proper: a turn and a shift) that carry half of the
    spheres ``points`` (n, 3) mm or more, and 5 or more, onto spheres, not
    the identity: tuples ``to`` with ``to[i]`` the sphere that sphere i is
    carried onto, -1 where none (a partial symmetry, :mod:`.partial`); a
    tuple without -1 is a whole symmetry of the phantom. Empty for fewer
    than 5 or more than ``_MOST`` spheres."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    if len(P) < 5 or len(P) > _MOST:
        return ()
    return _maps(P.tobytes(), len(P))


@functools.lru_cache(maxsize=16)
def _maps(key: bytes, n: int) -> tuple:
    """(the search of :func:`point_maps`, cached by the points' bytes)"""
    P = np.frombuffer(key).reshape(n, 3)
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    off = D + np.diag(np.full(n, np.inf))
    spacing = float(np.median(off.min(1)))
    tol = _SAME * spacing
    found: dict = {}
    tree = cKDTree(P)
    # each sphere with its nearest neighbour and the next nearest (a triangle
    # that fixes a motion), and the triangles a found motion already carries:
    # refitted from each of its n triangles, a helix's every screw cost n^2
    # nearest-sphere searches more (a 200-bead helix: 65 s)
    order = np.argsort(off, axis=1)
    b_of, g_of = order[:, 0], order[:, 1]
    covered: set = set()
    for a in range(n):
        b, g = int(b_of[a]), int(g_of[a])
        for c in range(n):
            for e in np.flatnonzero(np.abs(D[c] - D[a, b]) < tol):
                if (c, int(e)) == (a, b) or c == e:
                    continue
                h = np.flatnonzero((np.abs(D[c] - D[a, g]) < tol) & (np.abs(D[e] - D[b, g]) < tol))
                for hh in h:
                    if len({c, int(e), int(hh)}) < 3 or (a, c, int(e), int(hh)) in covered:
                        continue
                    R, o = rigid_fit(P[[a, b, g]], P[[c, int(e), int(hh)]])
                    d, j = tree.query(P @ R.T + o)
                    hit = d < 2 * tol
                    if hit.sum() < max(5, _SHARE * n) or np.all(j[hit] == np.flatnonzero(hit)):
                        continue
                    to = tuple(int(j[i]) if hit[i] else -1 for i in range(n))
                    if to not in found:
                        found[to] = None
                        covered.update((k, to[k], to[b_of[k]], to[g_of[k]]) for k in range(n)
                                       if min(to[k], to[b_of[k]], to[g_of[k]]) >= 0)
    return tuple(found)


# a whole symmetry of a 3-D phantom holds within this share of its spacing
# (a file's rounding); one that holds only to the maps' tolerance (a tenth of
# the spacing) moves spheres by what the data can see: another geometry
_EXACT = 1e-3


def _exact(points: np.ndarray, perm: np.ndarray, spacing: float) -> bool:
    """Whether the rigid motion carrying ``points`` onto ``points[perm]``
    holds within ``_EXACT`` of the spacing (mm) for every sphere."""
    A, o = rigid_fit(points, points[perm])
    return float(np.abs(points @ A.T + o - points[perm]).max()) <= _EXACT * spacing


def _turn_name(points: np.ndarray, perm: np.ndarray) -> str:
    """A whole symmetry of a 3-D phantom as the turn it is (phantom frame)."""
    A, _ = rigid_fit(points, points[perm])
    w = matrix_to_rotvec(A)
    ang = float(np.degrees(np.linalg.norm(w)))
    axis = w / max(np.linalg.norm(w), 1e-12)
    return f"turned {ang:.0f} deg about the phantom's ({axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f}) axis"


def _symmetries(ij: np.ndarray, B: np.ndarray) -> list:
    """Lattice maps (M, o), not the identity, that carry the set ``ij`` onto
    itself and preserve distances (with the lattice ``basis`` B)."""
    G = B.T @ B
    have = {tuple(v) for v in ij}
    out = []
    for M in LATTICE_MAPS:
        if not np.allclose(M.T @ G @ M, G, rtol=0, atol=3e-3 * np.abs(G).max()):
            continue
        m = ij @ M.T
        o = ij.min(0) - m.min(0)
        if {tuple(v) for v in m + o} == have and not (np.array_equal(M, np.eye(2)) and not o.any()):
            out.append((M, o))
    return out


def symmetry_name(M: np.ndarray, B: np.ndarray) -> str:
    """A rigid 3-D description of a lattice map: a turn about the normal, or a
    half turn about an in-plane line (the plane seen from behind)."""
    A = B @ M @ np.linalg.inv(B)    # the map in plane coordinates (mm)
    if np.linalg.det(A) > 0:
        ang = np.degrees(np.arctan2(A[1, 0], A[0, 0]))
        return f"turned {ang:+.0f} deg about the phantom's normal"
    w, V = np.linalg.eig(A)
    axis = np.real(V[:, np.argmin(np.abs(w - 1))])
    ang = np.degrees(np.arctan2(axis[1], axis[0])) % 180
    return f"seen from behind (half turn about the in-plane line at {ang:.0f} deg)"
