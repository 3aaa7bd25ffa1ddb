"""A planar grid's identities from its lattice in the image: grown from every
small cell of neighbouring detections (a homography follows the perspective
as the lattice grows), then every labelling by the phantom's lattice that
puts each found sphere on a phantom sphere is a candidate, posed by
Zhang's decomposition of the homography. Units: px, mm."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .camera import Camera
from .candidate import Candidate, relabel
from .phantom import LATTICE_MAPS, PhantomShape

# how a candidate relabelled by a turn of the lattice says so (``turned``)
TURNED = "its lattice turned"

_UNIMODULAR = tuple(M for M in (np.array(m).reshape(2, 2) - 1 for m in np.ndindex(3, 3, 3, 3))
                    if abs(round(np.linalg.det(M))) == 1)


def _fit_map(ij: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """3x3 homography (affine below 5 points) taking lattice ij to image xy."""
    if len(ij) < 5:
        A = np.column_stack([ij, np.ones(len(ij))])
        sol, *_ = np.linalg.lstsq(A, xy, rcond=None)
        return np.vstack([sol.T, [0, 0, 1]])
    return homography(ij, xy)


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised DLT: 3x3 H with dst ~ H src (both (n, 2), n >= 4), scaled
    to H[2, 2] = 1 where that is finite."""
    def norm(p):
        m = p.mean(0)
        s = np.sqrt(2) / max(np.mean(np.linalg.norm(p - m, axis=1)), 1e-12)
        return np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1]])
    Ts, Td = norm(src), norm(dst)
    s = np.column_stack([src, np.ones(len(src))]) @ Ts.T
    d = np.column_stack([dst, np.ones(len(dst))]) @ Td.T
    A = np.zeros((2 * len(s), 9))
    A[0::2, 0:3] = s
    A[0::2, 6:9] = -d[:, :1] * s
    A[1::2, 3:6] = s
    A[1::2, 6:9] = -d[:, 1:2] * s
    H = np.linalg.svd(A)[2][-1].reshape(3, 3)
    H = np.linalg.inv(Td) @ H @ Ts
    # (H is defined up to scale; H[2, 2] is 0 where the plane's origin maps to
    # infinity, as for a degenerate lattice of nearly collinear points)
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 * np.abs(H).max() else H / np.linalg.norm(H)


def _apply(H, ij):
    h = np.column_stack([ij, np.ones(len(ij))]) @ H.T
    return h[:, :2] / h[:, 2:3]


def grow_lattice(xy: np.ndarray, seed: int, a: int, b: int, gate_frac: float = 0.3, max_rounds: int = 12):
    """Lattice coordinates of detections reachable from the cell (seed, seed->a,
    seed->b): {detection index: (i, j)}; None if it does not grow."""
    found = {seed: (0, 0), a: (1, 0), b: (0, 1)}
    tree = cKDTree(xy)
    for _ in range(max_rounds):
        idx = np.array(list(found))
        ij = np.array([found[i] for i in idx], float)
        H = _fit_map(ij, xy[idx])
        lo, hi = ij.min(0) - 1, ij.max(0) + 1
        gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
        cells = np.column_stack([gi.ravel(), gj.ravel()])
        have = {tuple(v) for v in ij.astype(int)}
        new = np.array([c for c in cells if tuple(c.astype(int)) not in have])
        if len(new) == 0:
            break
        with np.errstate(all="ignore"):
            pred = _apply(H, new)
            step = np.minimum(np.linalg.norm(_apply(H, new + [1, 0]) - pred, axis=1),
                              np.linalg.norm(_apply(H, new + [0, 1]) - pred, axis=1))
        # a degenerate map (cells grown along one line) predicts nothing usable
        good = np.isfinite(pred).all(1) & np.isfinite(step)
        if not good.any():
            break
        new, pred, step = new[good], pred[good], step[good]
        dist, hit = tree.query(pred)
        added = False
        taken = set(found)
        for k in np.argsort(dist):
            if dist[k] <= gate_frac * step[k] and hit[k] not in taken:
                found[int(hit[k])] = tuple(int(v) for v in new[k])
                taken.add(int(hit[k]))
                added = True
        if not added:
            break
    return found if len(found) > 3 else None


def image_lattice(xy: np.ndarray, n_seeds: int = 6):
    """The largest lattice among the detections: (detection indices, ij (n, 2))."""
    if len(xy) < 4:
        return None
    tree = cKDTree(xy)
    centre = np.median(xy, 0)
    seeds = np.argsort(np.linalg.norm(xy - centre, axis=1))[:n_seeds]
    best = None
    for s in seeds:
        _, nb = tree.query(xy[s], k=min(6, len(xy)))
        nb = [int(j) for j in nb[1:]]
        for ia, a in enumerate(nb[:4]):
            va = xy[a] - xy[s]
            for b in nb[ia + 1:]:
                vb = xy[b] - xy[s]
                la, lb = np.linalg.norm(va), np.linalg.norm(vb)
                if abs(va[0] * vb[1] - va[1] * vb[0]) < 0.5 * la * lb or not 0.4 < la / lb < 2.5:
                    continue
                found = grow_lattice(xy, int(s), a, b)
                if found is not None and (best is None or len(found) > len(best)):
                    best = found
    if best is None:
        return None
    idx = np.array(sorted(best))
    return idx, np.array([best[i] for i in idx])


def pose_from_homography(cam: Camera, shape: PhantomShape, H: np.ndarray):
    """Pose (R, t) lab of a planar phantom from H mapping plane coordinates (mm,
    along e1, e2) to pixels, with the camera's K (Zhang's decomposition)."""
    B = np.linalg.solve(cam.matrix(), H)
    lam = 1.0 / np.linalg.norm(B[:, 0])
    if B[2, 2] * lam < 0:       # the phantom in front of the source
        lam = -lam
    r1, r2 = lam * B[:, 0], lam * B[:, 1]
    Rp = np.column_stack([r1, r2, np.cross(r1, r2)])
    U, _, Vt = np.linalg.svd(Rp)
    Rp = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    tc = lam * B[:, 2]
    # plane frame (e1, e2, n) -> phantom frame; camera -> lab
    F = np.column_stack([shape.e1, shape.e2, shape.n])
    R = Rp @ F.T
    t = tc + cam.source - R @ shape.origin
    return R, t


def planar_candidates(cam: Camera, shape: PhantomShape, xy: np.ndarray) -> list[Candidate]:
    found = image_lattice(xy)
    if found is None:
        return []
    idx, ij = found
    lat = shape.lattice_index()
    plane = shape.plane_xy
    out = []
    # image cells may have grown along a diagonal: any unimodular relabelling
    for mi, M in enumerate(_UNIMODULAR):
        m = ij @ M.T
        offsets = {tuple(p - m[0]) for p in shape.lattice}
        for o in offsets:
            keys = [tuple(v) for v in m + np.array(o)]
            inside = np.array([k in lat for k in keys])
            # one stray blob grown into the image lattice may fall outside the phantom
            if inside.sum() < len(keys) - (1 if len(keys) >= 10 else 0):
                continue
            sph = np.array([lat[k] for k, ok in zip(keys, inside) if ok])
            H = homography(plane[sph], xy[idx[inside]])
            R, t = pose_from_homography(cam, shape, H)
            out.append(Candidate(idx[inside], sph, R, t, how="lattice", lattice_map=(mi, o)))
    return out


def turned(shape: PhantomShape, points: np.ndarray, c: Candidate) -> list[Candidate]:
    """Candidate ``c`` relabelled by every turn of the phantom's whole lattice
    (a square grid's 90 deg turns and views from behind, a rectangle's half
    turns; about the lattice's bounding box): each detection keeps its place
    and takes the sphere its sphere turns onto (none where that is a hole),
    and the pose is turned alike, so that the relabelled spheres land where
    the detections are. Where shadows merge (a grid seen nearly edge-on) the
    image lattice grows wrong and the search may offer only a turned
    identification; the right one is among these. ``points`` (n, 3) mm."""
    if shape.lattice is None:
        return []
    G = shape.basis.T @ shape.basis
    lat = shape.lattice_index()
    out = []
    for M in LATTICE_MAPS:
        if np.array_equal(M, np.eye(2, dtype=int)) or \
                not np.allclose(M.T @ G @ M, G, rtol=0, atol=3e-3 * np.abs(G).max()):
            continue
        m = shape.lattice @ M.T
        o = shape.lattice.min(0) - m.min(0)
        if not np.array_equal(m.max(0) + o, shape.lattice.max(0)):
            continue
        to = [lat.get(tuple(int(v) for v in m[k] + o)) for k in range(len(shape.lattice))]
        moved = relabel(c, to, points, TURNED)
        if moved is not None:
            out.append(moved)
    return out
