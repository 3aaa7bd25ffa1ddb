"""A 3-D phantom's (or any off-lattice phantom's) identities by voting:
orientations sampled over SO(3) (or near a rough guess) times a few depths,
and for each the image offset that most detections agree on between them
and the projected phantom; the best votes are voted again finer about
themselves. Units: px, mm."""

from __future__ import annotations

import numpy as np
from ..jit import njit

from ..geometry import matrix_to_rotvec, rotvec_to_matrix
from .camera import Camera
from .candidate import Candidate, assign
from .phantom import PhantomShape

CELL_FRACTION = 0.5


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


@njit(cache=True)
def _offset_votes(Rs, P, det, f0, f1, depths, cell, nb):
    """For each orientation (n, 3, 3), depth and grid (0, then shifted half a
    cell): the most-voted offset cell of ``det`` (detections in cell units
    from the vote's corner, float32) minus the projected points ``P`` (mm,
    centred), and its votes; ties to the lowest cell index. One histogram,
    cleared only where voted: an orientation's det x spheres votes touch a
    few of its nb^2 cells (a 3-D phantom: ~1400 of 3600-10000)."""
    n, m, nd, nz = Rs.shape[0], P.shape[0], det.shape[0], depths.shape[0]
    votes = np.zeros((n, nz, 2), np.int64)
    best = np.zeros((n, nz, 2), np.int64)
    hist = np.zeros(nb * nb, np.int32)
    touched = np.empty(nd * m, np.int64)
    X = np.empty((m, 3))
    pred = np.empty((m, 2), np.float32)
    for k in range(n):
        for b in range(m):
            for i in range(3):
                X[b, i] = Rs[k, i, 0] * P[b, 0] + Rs[k, i, 1] * P[b, 1] + Rs[k, i, 2] * P[b, 2]
        for zi in range(nz):
            for b in range(m):
                w = depths[zi] + X[b, 2]
                pred[b, 0] = np.float32(f0 * X[b, 0] / w / cell)
                pred[b, 1] = np.float32(f1 * X[b, 1] / w / cell)
            for si in range(2):
                shift = np.float32(0.5 * si)
                nt = 0
                for a in range(nd):
                    for b in range(m):
                        qc = int(np.floor(det[a, 0] - pred[b, 0] + shift))
                        qr = int(np.floor(det[a, 1] - pred[b, 1] + shift))
                        if qc >= 0 and qc < nb and qr >= 0 and qr < nb:
                            key = qc * nb + qr
                            hist[key] += 1
                            touched[nt] = key
                            nt += 1
                top, at = 0, 0
                for t in range(nt):
                    key = touched[t]
                    c = hist[key]
                    if c > top or (c == top and key < at):
                        top, at = c, key
                for t in range(nt):
                    hist[touched[t]] = 0
                votes[k, zi, si] = top
                best[k, zi, si] = at
    return votes, best


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
    # (the ranking below goes by blocks of orientations, as an earlier vote did)
    chunk = max(1, 400000 // max(1, len(P) * len(xy)))
    # in cell units, float32: the vote only needs cell indices
    det = ((xy - mid) / cell + half / cell).astype(np.float32)                 # (det, 2)
    all_votes, all_best = _offset_votes(np.ascontiguousarray(Rs, float), np.ascontiguousarray(P, float), det,
                                        float(f[0]), float(f[1]), np.asarray(depths, float), float(cell), nb)
    for s0 in range(0, len(Rs), chunk):
        for zi, z in enumerate(depths):
            for si, shift in enumerate((0.0, 0.5)):
                votes, best = all_votes[s0:s0 + chunk, zi, si], all_best[s0:s0 + chunk, zi, si]
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
                     keep: int = 20, seed: int = 7, depth: float | None = None) -> list[Candidate]:
    """Orientation samples x depths (coarse), then a finer local vote about each
    of the ``keep`` best distinct coarse hypotheses. Depths: 0.85-1.17 of
    ``depth`` (mm from the source; default the nominal sod), or the guess's."""
    P = shape.points - shape.points.mean(0)
    pc = shape.points.mean(0)
    depth = cam.sod if depth is None else depth
    spacing_px = shape.spacing_mm * cam.focal_px.mean() / depth
    if guess is not None:
        Rs = _orientations(0, guess[0])
        depths = [float((guess[0] @ pc)[2] + guess[1][2] + cam.sod)]
    else:
        Rs = _orientations(n_orientations, seed=seed)
        depths = [depth * s for s in (0.85, 0.93, 1.0, 1.08, 1.17)]
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
