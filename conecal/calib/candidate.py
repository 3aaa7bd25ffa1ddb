"""A candidate identification of one frame's spheres, and the two steps every
search uses: the Hungarian assignment of predicted to detected centres and
the robust refinement of a pose with the camera fixed. Units: px, mm."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment

from ..geometry import rotvec_to_matrix
from ..geometry.cone import so3_left_jacobian
from ..geometry.rotations import skew
from .camera import Camera


# how far (normalised) a frame's twist centre may move in one refit
TWIST_REACH = 0.5


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
    xy: np.ndarray | None = None   # the frame's detections as its own distortion undistorts them (second look)

    @property
    def score(self) -> int:
        """Spheres explained, less those the pose says must be seen but are not."""
        return len(self.sph) - self.missing


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation A and shift o with A a + o = b in the least-squares sense
    (Kabsch; ``a``, ``b`` (k, 3) mm paired rows)."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((b - cb).T @ (a - ca))
    A = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return A, cb - A @ ca


def relabel(c: Candidate, to: list, points: np.ndarray, how: str, least: float = 4) -> Candidate | None:
    """Candidate ``c`` with each detection's sphere s renamed ``to[s]`` (None:
    no sphere there, the detection left unexplained) and the pose moved by
    the rigid motion carrying the old spheres onto the new (``points`` (n, 3)
    mm), so that the renamed spheres land where the detections are; None
    when fewer than ``least`` keep a sphere. ``how`` is appended to ``c.how``."""
    keep = np.array([to[s] is not None for s in c.sph], bool)
    if keep.sum() < least:
        return None
    old, new = c.sph[keep], np.array([to[s] for s in c.sph[keep]])
    Rg, og = rigid_fit(points[old], points[new])
    R = c.R @ Rg.T
    return Candidate(c.det[keep], new, R, c.t - R @ og, how=f"{c.how}, {how}")


def refine_pose(cam: Camera, P: np.ndarray, xy: np.ndarray, R, t, f_scale: float = 2.0):
    """Pose minimising the robust reprojection error of points P (n, 3) phantom
    frame seen at xy (n, 2) px, camera fixed. Returns R, t, residuals (n, 2)."""
    return refine_pose_and_terms(cam, P, xy, R, t, f_scale)[:3]


def refine_pose_and_terms(cam: Camera, P: np.ndarray, xy: np.ndarray, R, t, f_scale: float = 2.0,
                          dist=None, free=(), twist: bool = False):
    """As ``refine_pose``; with ``dist`` (a Distortion) ``xy`` are measured
    positions, ``dist`` applied to the projection, and its coefficients at
    indices ``free`` are fitted with the pose (a frame's own twist, which
    trades with its pose), and with ``twist`` its twist's centre (px) too.
    Returns R, t, residuals (n, 2), the distortion as fitted (None without
    one)."""
    R0 = np.asarray(R, float)
    free = list(free)
    nf = len(free)
    k0 = np.asarray(dist.coefficients, float) if dist is not None else None
    about0 = np.asarray(dist.twist_centre or dist.centre, float) if twist else None
    i_s = dist.names.index("s") if twist else None

    def split(x):
        k = None
        if dist is not None:
            k = k0.copy()
            k[free] = x[6:6 + nf]
        return rotvec_to_matrix(x[:3]) @ R0, np.asarray(t, float) + x[3:6], k, (about0 + x[6 + nf:] if twist else None)

    def fun(x):
        Rk, tk, k, about = split(x)
        q = cam.project(P @ Rk.T + tk)
        if dist is not None:
            q = q + dist.basis(q, about) @ k
        return (q - xy).ravel()

    def jac(x):
        Rk, tk, k, about = split(x)
        Rp = P @ Rk.T
        q, JX, _ = cam.project_jacobians(Rp + tk)
        J = np.empty((len(P), 2, len(x)))
        if dist is not None:
            grad = dist.basis_gradient(q, about)
            # d measured / d ideal = I + the displacement's gradient
            JX = (np.eye(2) + np.einsum("nitj,t->nij", grad, k)) @ JX
            J[:, :, 6:6 + nf] = dist.basis(q, about)[..., free]
            if twist:
                J[:, :, 6 + nf:] = -k[i_s] * grad[:, :, i_s, :]
        J[:, :, :3] = JX @ (-skew(Rp) @ so3_left_jacobian(x[:3]))
        J[:, :, 3:6] = JX
        return J.reshape(-1, len(x))

    x0 = np.concatenate([np.zeros(6), k0[free] if dist is not None else [], np.zeros(2 * twist)])
    # the twist's centre within TWIST_REACH of the normalising radius of where
    # it starts: where the twist is weak a far centre is a second, false minimum
    reach = np.full(2 * twist, TWIST_REACH * dist.radius if twist else 0.0)
    lo = np.concatenate([np.full(len(x0) - reach.size, -np.inf), -reach])
    sol = least_squares(fun, x0, jac=jac, loss="soft_l1", f_scale=f_scale, max_nfev=50, bounds=(lo, -lo),
                        x_scale=np.concatenate([[1e-2, 1e-2, 1e-2, 1.0, 1.0, 1.0], np.full(nf, 0.1),
                                                np.full(2 * twist, 10.0)]))
    Rk, tk, k, about = split(sol.x)
    return Rk, tk, sol.fun.reshape(-1, 2), \
        (dist.with_coefficients(k, twist_centre=tuple(about) if twist else None) if dist is not None else None)


def assign(pred: np.ndarray, xy: np.ndarray, gate: float):
    """Hungarian pairs (pred index, detection index) within ``gate`` px."""
    cost = np.linalg.norm(pred[:, None] - xy[None], axis=-1)
    r, c = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
    keep = cost[r, c] <= gate
    return r[keep], c[keep]
