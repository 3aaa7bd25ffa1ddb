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


def refine_pose(cam: Camera, P: np.ndarray, xy: np.ndarray, R, t, f_scale: float = 2.0):
    """Pose minimising the robust reprojection error of points P (n, 3) phantom
    frame seen at xy (n, 2) px, camera fixed. Returns R, t, residuals (n, 2)."""
    return refine_pose_and_terms(cam, P, xy, R, t, f_scale)[:3]


def refine_pose_and_terms(cam: Camera, P: np.ndarray, xy: np.ndarray, R, t, f_scale: float = 2.0,
                          dist=None, free=()):
    """As ``refine_pose``; with ``dist`` (a Distortion) ``xy`` are measured
    positions, ``dist`` applied to the projection, and its coefficients at
    indices ``free`` are fitted with the pose (a frame's own twist, which
    trades with its pose). Returns R, t, residuals (n, 2), the distortion
    as fitted (None without one)."""
    R0 = np.asarray(R, float)
    free = list(free)
    k0 = np.asarray(dist.coefficients, float) if dist is not None else None

    def split(x):
        k = None
        if dist is not None:
            k = k0.copy()
            k[free] = x[6:]
        return rotvec_to_matrix(x[:3]) @ R0, np.asarray(t, float) + x[3:6], k

    def fun(x):
        Rk, tk, k = split(x)
        q = cam.project(P @ Rk.T + tk)
        if dist is not None:
            q = q + dist.basis(q) @ k
        return (q - xy).ravel()

    def jac(x):
        Rk, tk, k = split(x)
        Rp = P @ Rk.T
        q, JX, _ = cam.project_jacobians(Rp + tk)
        J = np.empty((len(P), 2, 6 + len(free)))
        if dist is not None:
            # d measured / d ideal = I + the displacement's gradient
            JX = (np.eye(2) + np.einsum("nitj,t->nij", dist.basis_gradient(q), k)) @ JX
            J[:, :, 6:] = dist.basis(q)[..., free]
        J[:, :, :3] = JX @ (-skew(Rp) @ so3_left_jacobian(x[:3]))
        J[:, :, 3:6] = JX
        return J.reshape(-1, 6 + len(free))

    x0 = np.concatenate([np.zeros(6), k0[free] if dist is not None else []])
    sol = least_squares(fun, x0, jac=jac, loss="soft_l1", f_scale=f_scale, max_nfev=50,
                        x_scale=np.concatenate([[1e-2, 1e-2, 1e-2, 1.0, 1.0, 1.0], np.full(len(free), 0.1)]))
    Rk, tk, k = split(sol.x)
    return Rk, tk, sol.fun.reshape(-1, 2), (dist.with_coefficients(k) if dist is not None else None)


def assign(pred: np.ndarray, xy: np.ndarray, gate: float):
    """Hungarian pairs (pred index, detection index) within ``gate`` px."""
    cost = np.linalg.norm(pred[:, None] - xy[None], axis=-1)
    r, c = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
    keep = cost[r, c] <= gate
    return r[keep], c[keep]
