"""Rigid transforms ``P' = R P + t`` (mm), single or batched over frames."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class RigidTransform:
    """A rigid motion, or a batch of ``n`` of them.

    Attributes
    ----------
    R : (3, 3) or (n, 3, 3) rotation matrices.
    t : (3,) or (n, 3) translations in mm.

    ``T(p) = R p + t``; composition ``(A @ B)(p) == A(B(p))``.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        R, t = np.asarray(self.R, dtype=float), np.asarray(self.t, dtype=float)
        if R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,) or R.shape[:-2] != t.shape[:-1]:
            raise ValueError(f"RigidTransform: R has shape {R.shape} and t {t.shape}; expected (...,3,3) and (...,3)")
        object.__setattr__(self, "R", _frozen(R))
        object.__setattr__(self, "t", _frozen(t))

    @classmethod
    def identity(cls, n: int | None = None) -> "RigidTransform":
        if n is None:
            return cls(np.eye(3), np.zeros(3))
        return cls(np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> "RigidTransform":
        M = np.asarray(M, dtype=float)
        return cls(M[..., :3, :3], M[..., :3, 3])

    def matrix(self) -> np.ndarray:
        """Homogeneous 4x4 matrices, (..., 4, 4)."""
        M = np.zeros(self.R.shape[:-2] + (4, 4))
        M[..., :3, :3] = self.R
        M[..., :3, 3] = self.t
        M[..., 3, 3] = 1.0
        return M

    def __len__(self) -> int:
        return 1 if self.R.ndim == 2 else self.R.shape[0]

    def __getitem__(self, k) -> "RigidTransform":
        return RigidTransform(self.R[k], self.t[k])

    def __matmul__(self, other: "RigidTransform") -> "RigidTransform":
        return RigidTransform(self.R @ other.R, (self.R @ other.t[..., None])[..., 0] + self.t)

    def inverse(self) -> "RigidTransform":
        Rt = np.swapaxes(self.R, -1, -2)
        return RigidTransform(Rt, -(Rt @ self.t[..., None])[..., 0])

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3). A batched transform (n) maps points of shape
        (n, 3) frame by frame, or (n, m, 3) as m points per frame."""
        p = np.asarray(points, dtype=float)
        if self.R.ndim == 2:
            return p @ self.R.T + self.t
        if p.ndim == 2 and p.shape[0] == self.R.shape[0]:
            return np.einsum("nij,nj->ni", self.R, p) + self.t
        if p.ndim == 2:  # same m points in every frame
            return np.einsum("nij,mj->nmi", self.R, p) + self.t[:, None, :]
        return np.einsum("nij,nmj->nmi", self.R, p) + self.t[:, None, :]
