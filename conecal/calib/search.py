"""Pose search without a log: which detection is which sphere, and a first pose.

A planar grid is found by growing its lattice in the image from every
small cell of neighbouring detections (a homography follows the
perspective as the lattice grows); each labelling of the image lattice by
the phantom's lattice that places every found sphere on a phantom sphere
is a candidate. Any other phantom (3-D, or planar off a lattice) is found
by sampling orientations (all of them, or near a rough guess) and voting
the image offset between detections and the projected phantom; the best
votes are refined. Candidates are refined to poses with the nominal
camera and a robust loss (the distortion is not yet known: several px).

Two candidates that fit about equally are one pose when the phantom's own
symmetry relates them (the same calibration: resolved by convention), and
make the frame ``ambiguous`` otherwise (say, a grid with a column off the
detector, which can be labelled with a shift of one pitch). A rough guess
breaks such a tie only when exactly one candidate agrees with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.spatial import cKDTree

from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from ..geometry.cone import so3_left_jacobian
from ..geometry.rotations import skew
from .camera import Camera
from .phantom import PhantomShape, symmetry_name


@dataclass
class Candidate:
    det: np.ndarray            # detection indices
    sph: np.ndarray            # phantom point indices, paired with det
    R: np.ndarray
    t: np.ndarray              # lab, mm: P_lab = R p + t
    rms_px: float = np.inf
    how: str = ""
    lattice_map: tuple | None = None
    missing: int = 0           # spheres predicted clear on the detector but not found

    @property
    def score(self) -> int:
        """Spheres explained, less those the pose says must be seen but are not."""
        return len(self.sph) - self.missing


@dataclass
class SearchResult:
    status: str                # ok | ambiguous: ... | rejected: ...
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
    of a 3-D phantom fits better than this, search again three times denser."""

    min_spheres: int = 6
    gate_px: float = 6.0
    tie_px: float = 1.0
    gate_floor_px: float = 2.0
    retry_px: float = 1.0
    guess_deg: float = 40.0
    guess_mm: float = 25.0
    n_orientations: int = 8000


# ----------------------------------------------------------------------------- pose refinement
def refine_pose(cam: Camera, P: np.ndarray, xy: np.ndarray, R, t, f_scale: float = 2.0):
    """Pose minimising the robust reprojection error of points P (n, 3) phantom
    frame seen at xy (n, 2) px, camera fixed. Returns R, t, residuals (n, 2)."""
    R0 = np.asarray(R, float)

    def split(x):
        return rotvec_to_matrix(x[:3]) @ R0, np.asarray(t, float) + x[3:]

    def fun(x):
        Rk, tk = split(x)
        return (cam.project(P @ Rk.T + tk) - xy).ravel()

    def jac(x):
        Rk, tk = split(x)
        Rp = P @ Rk.T
        _, JX, _ = cam.project_jacobians(Rp + tk)
        J = np.empty((len(P), 2, 6))
        J[:, :, :3] = JX @ (-skew(Rp) @ so3_left_jacobian(x[:3]))
        J[:, :, 3:] = JX
        return J.reshape(-1, 6)

    sol = least_squares(fun, np.zeros(6), jac=jac, loss="soft_l1", f_scale=f_scale, max_nfev=50,
                        x_scale=np.array([1e-2, 1e-2, 1e-2, 1.0, 1.0, 1.0]))
    Rk, tk = split(sol.x)
    return Rk, tk, sol.fun.reshape(-1, 2)


def assign(pred: np.ndarray, xy: np.ndarray, gate: float):
    """Hungarian pairs (pred index, detection index) within ``gate`` px."""
    cost = np.linalg.norm(pred[:, None] - xy[None], axis=-1)
    r, c = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
    keep = cost[r, c] <= gate
    return r[keep], c[keep]


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
    return Candidate(det, sph, R, t, rms, cand.how, cand.lattice_map, _missing(cam, shape, R, t, sph))


def _missing(cam: Camera, shape: PhantomShape, R, t, sph) -> int:
    """Phantom spheres this pose puts well inside the detector, clear of every
    other sphere's shadow, that no detection was assigned to: evidence
    against the pose (a labelling one pitch off predicts a column where the
    image has none)."""
    pred = cam.project(shape.points @ R.T + t)
    rows, cols = cam.shape
    f = cam.focal_px.mean()
    depth = (shape.points @ R.T + t - cam.source)[:, 2]
    margin = 2.0 + 2 * f * shape.radius / depth     # a shadow's diameter, px
    inside = ((pred[:, 0] > margin) & (pred[:, 0] < cols - 1 - margin) & (pred[:, 1] > margin)
              & (pred[:, 1] < rows - 1 - margin))
    d = np.linalg.norm(pred[:, None] - pred[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    clear = d.min(1) > 2 * margin if len(pred) > 1 else np.ones(len(pred), bool)
    found = np.zeros(len(pred), bool)
    found[np.asarray(sph, int)] = True
    return int(np.sum(inside & clear & ~found))


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


# ----------------------------------------------------------------------------- planar lattice
def _fit_map(ij: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """3x3 homography (affine below 5 points) taking lattice ij to image xy."""
    if len(ij) < 5:
        A = np.column_stack([ij, np.ones(len(ij))])
        sol, *_ = np.linalg.lstsq(A, xy, rcond=None)
        return np.vstack([sol.T, [0, 0, 1]])
    return homography(ij, xy)


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised DLT: 3x3 H with dst ~ H src (both (n, 2), n >= 4)."""
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
    return H / H[2, 2]


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


CELL_FRACTION = 0.5
_UNIMODULAR = tuple(M for M in (np.array(m).reshape(2, 2) - 1 for m in np.ndindex(3, 3, 3, 3))
                    if abs(round(np.linalg.det(M))) == 1)


# ----------------------------------------------------------------------------- orientation voting
def _orientations(n: int, around=None, radius_deg: float = 45.0, step_deg: float = 7.5, seed: int = 7) -> np.ndarray:
    """Rotation matrices: ``n`` uniform samples of SO(3), or a grid of rotation
    vectors (``step_deg``) within ``radius_deg`` of ``around``."""
    rng = np.random.default_rng(seed)
    if around is None:
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        w, x, y, z = q.T
        return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                         np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                         np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
    g = np.arange(-radius_deg, radius_deg + 1e-9, step_deg)
    W = np.deg2rad(np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3))
    W = W[np.linalg.norm(W, axis=1) <= np.deg2rad(radius_deg) + 1e-9]
    return np.array([rotvec_to_matrix(w) @ around for w in W])


def _vote(cam: Camera, P: np.ndarray, xy: np.ndarray, Rs: np.ndarray, depths, cell: float, keep: int):
    """Best (votes, orientation index, depth, offset c, offset r) per sampled
    orientation and depth: the image offset of the projected phantom (centred
    points P) that most detections agree on, in cells of ``cell`` px (two
    grids half a cell apart, so that an offset on a border counts once)."""
    f = cam.focal_px
    # the phantom's centre projects among its detections: offsets are voted
    # only over the detections' extent about their median
    mid = np.median(xy, 0)
    half = float(np.abs(xy - mid).max()) + 2 * cell
    nb = int(2 * half / cell) + 2
    hyps = []
    chunk = max(1, 400000 // max(1, len(P) * len(xy)))
    # in cell units, float32: the vote only needs cell indices (this loop is
    # most of a 3-D search's time)
    det = ((xy - mid) / cell + half / cell).astype(np.float32)                 # (det, 2)
    for s0 in range(0, len(Rs), chunk):
        Rc = Rs[s0:s0 + chunk]
        X = np.einsum("kij,nj->kni", Rc, P)
        row = (np.arange(len(Rc), dtype=np.int64) * nb * nb)[:, None, None]
        for zi, z in enumerate(depths):
            pred = (np.stack([f[0] * X[..., 0], f[1] * X[..., 1]], -1) / (z + X[..., 2:3]) / cell).astype(np.float32)
            rel = det[None, :, None, :] - pred[:, None, :, :]                  # (k, det, sph, 2)
            for si, shift in enumerate((0.0, 0.5)):
                q = np.floor(rel + np.float32(shift)).astype(np.int32)
                qc, qr = q[..., 0], q[..., 1]
                okq = (qc >= 0) & (qc < nb) & (qr >= 0) & (qr < nb)
                key = (row + (qc * nb + qr))[okq]
                counts = np.bincount(key, minlength=len(Rc) * nb * nb).reshape(len(Rc), -1)
                best = counts.argmax(1)
                votes = counts[np.arange(len(Rc)), best]
                for rank, k in enumerate(np.argsort(-votes)[:keep]):
                    oc = ((best[k] // nb) + 0.5 - shift) * cell - half + mid[0] - cam.c0
                    orr = ((best[k] % nb) + 0.5 - shift) * cell - half + mid[1] - cam.r0
                    hyps.append(((-int(votes[k]), zi, s0, si, rank), (int(votes[k]), s0 + int(k), z, oc, orr)))
    # ties in the order depth, orientation, grid, rank
    hyps.sort(key=lambda h: h[0])
    return [h for _, h in hyps]


def _hypothesis_pose(cam: Camera, R, z, oc, orr, pc):
    """The phantom's centre ``pc`` on the ray through (c0 + oc, r0 + orr) at depth z."""
    f = cam.focal_px
    return np.array([oc * z / f[0], orr * z / f[1], z]) + cam.source - R @ pc


def voted_candidates(cam: Camera, shape: PhantomShape, xy: np.ndarray, guess=None, n_orientations: int = 8000,
                     keep: int = 20, seed: int = 7) -> list[Candidate]:
    """Orientation samples x depths (coarse), then a finer local vote about each
    of the ``keep`` best distinct coarse hypotheses."""
    P = shape.points - shape.points.mean(0)
    pc = shape.points.mean(0)
    spacing_px = shape.spacing_mm * cam.focal_px.mean() / cam.sod
    if guess is not None:
        Rs = _orientations(0, guess[0])
        depths = [float((guess[0] @ pc)[2] + guess[1][2] + cam.sod)]
    else:
        Rs = _orientations(n_orientations, seed=seed)
        depths = [cam.sod * s for s in (0.85, 0.93, 1.0, 1.08, 1.17)]
    cell = max(6.0, CELL_FRACTION * spacing_px)
    hyps = _vote(cam, P, xy, Rs, depths, cell, keep)
    coarse, seen, out = [], [], []
    for votes, k, z, oc, orr in hyps:
        if any(np.linalg.norm(matrix_to_rotvec(Rs[k] @ Q.T)) < np.deg2rad(10) for Q in seen):
            continue
        seen.append(Rs[k])
        coarse.append((Rs[k], z))
        t = _hypothesis_pose(cam, Rs[k], z, oc, orr, pc)
        sph, det = assign(cam.project(shape.points @ Rs[k].T + t), xy, 2 * cell)
        if len(sph) >= 4:
            out.append(Candidate(det, sph, Rs[k], t, how="orientation search"))
        if len(coarse) >= keep:
            break
    fine_cell = max(3.0, 0.15 * spacing_px)
    for R, z in coarse:
        local = _orientations(0, R, radius_deg=8.0, step_deg=2.5)
        for votes, k, zz, oc, orr in _vote(cam, P, xy, local, [z * 0.96, z, z * 1.04], fine_cell, 1)[:1]:
            Rk = local[k]
            t = _hypothesis_pose(cam, Rk, zz, oc, orr, pc)
            sph, det = assign(cam.project(shape.points @ Rk.T + t), xy, 2 * fine_cell)
            if len(sph) >= 4:
                out.append(Candidate(det, sph, Rk, t, how="orientation search"))
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
        return SearchResult(f"rejected: {len(xy)} markers usable, fewer than {opt.min_spheres}")
    raw = planar_candidates(cam, shape, xy) if shape.lattice is not None else []
    if not raw:
        raw = voted_candidates(cam, shape, xy, guess, opt.n_orientations)
        if guess is not None and not raw:
            raw = voted_candidates(cam, shape, xy, None, opt.n_orientations)
    cands = [_polish(cam, shape, xy, c, gates=(3 * opt.gate_px, opt.gate_px)) for c in raw]
    cands = [c for c in cands if len(c.sph) >= 4 and np.isfinite(c.rms_px)]
    if shape.lattice is None and (not cands or min(c.rms_px for c in cands) > opt.retry_px):
        # nothing fits well (a crowded view of a 3-D phantom): a denser second search
        more = voted_candidates(cam, shape, xy, None, 3 * opt.n_orientations, seed=11)
        cands += [c for c in (_polish(cam, shape, xy, c, gates=(3 * opt.gate_px, opt.gate_px)) for c in more)
                  if len(c.sph) >= 4 and np.isfinite(c.rms_px)]
    if cands:
        cands = _tighten(cam, shape, xy, cands, opt.gate_floor_px)
    cands = [c for c in cands if len(c.sph) >= opt.min_spheres and np.isfinite(c.rms_px)]
    if not cands:
        return SearchResult(f"rejected: no pose explains {opt.min_spheres} or more of {len(xy)} markers")
    # most spheres explained, then the lowest residual
    cands.sort(key=lambda c: (-c.score, c.rms_px))
    best = cands[0]
    rivals = []
    for c in cands[1:]:
        if _same_pose(c, best):
            continue
        if any(_same_pose(c, r) for r in rivals):
            continue
        if c.score >= best.score - 1 and c.rms_px <= best.rms_px + opt.tie_px:
            rivals.append(c)
    convention = ""
    if shape.symmetries and rivals:
        twins, maps, rivals = _by_symmetry(shape, best, rivals)
        if twins:
            best = _by_convention([best] + twins, shape, guess, opt)
            convention = ("labelled by convention (phantom normal towards the detector, then the smallest turn) "
                          "among poses its symmetry makes identical: "
                          + "; ".join(sorted({symmetry_name(M, shape.basis) for M in maps})))
    if rivals and guess is not None:
        agree = [c for c in [best] + rivals if _agrees(c, guess, opt)]
        if len(agree) == 1:
            best, rivals = agree[0], []
    if rivals:
        what = ", ".join(f"{len(c.sph)} spheres at {c.rms_px:.2f} px" for c in rivals[:3])
        return SearchResult(f"ambiguous: {len(rivals) + 1} identifications fit about equally "
                            f"(best {len(best.sph)} spheres at {best.rms_px:.2f} px; also {what})",
                            best, rivals, convention)
    return SearchResult("ok", best, [], convention)


def _by_convention(twins: list, shape: PhantomShape, guess, opt: SearchOptions) -> Candidate:
    """One of poses the phantom's symmetry makes identical: the one a guess
    agrees with, else the phantom normal towards +z, then the smallest turn."""
    if guess is not None:
        agree = [c for c in twins if _agrees(c, guess, opt)]
        if len(agree) == 1:
            return agree[0]
    return min(twins, key=lambda c: (float((c.R @ shape.n)[2] < 0), float(np.linalg.norm(matrix_to_rotvec(c.R)))))


def _by_symmetry(shape: PhantomShape, best: Candidate, rivals: list):
    """Split rivals into those a phantom symmetry relates to ``best`` (same
    image, same calibration) and the rest; returns (twins, maps, rest)."""
    twins, used, rest = [], [], []
    for c in rivals:
        hit = None
        for M, o in shape.symmetries:
            moved = shape.lattice[best.sph] @ M.T + o
            mapping = dict(zip(best.det.tolist(), (tuple(v) for v in moved)))
            theirs = dict(zip(c.det.tolist(), (tuple(v) for v in shape.lattice[c.sph])))
            common = set(mapping) & set(theirs)
            if common and all(mapping[d] == theirs[d] for d in common):
                hit = M
                break
        if hit is None:
            rest.append(c)
        else:
            twins.append(c)
            used.append(hit)
    return twins, used, rest
