"""Rotations as 3x3 matrices; vectorised over leading axes. Angles in radians."""

from __future__ import annotations

import numpy as np


def skew(w: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[w]_x`` with ``skew(w) @ p == cross(w, p)``; shape (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    return K


def axis_angle(direction: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rotation by ``angle`` (rad, right-hand rule) about unit ``direction``.

    ``direction`` (..., 3) and ``angle`` (...) broadcast; returns (..., 3, 3).
    """
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    a = np.asarray(angle, dtype=float)
    shape = np.broadcast_shapes(d.shape[:-1], a.shape)
    d = np.broadcast_to(d, shape + (3,))
    a = np.broadcast_to(a, shape)
    K = skew(d)
    s = np.sin(a)[..., None, None]
    c = np.cos(a)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of rotation vector ``w`` (axis * angle in rad); (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    if w.shape == (3,):  # the common single rotation, without the batch machinery
        th = float(np.sqrt(w @ w))
        K = skew(w)
        if th < 1e-8:
            return np.eye(3) + K + 0.5 * (K @ K)
        return np.eye(3) + (np.sin(th) / th) * K + ((1 - np.cos(th)) / th**2) * (K @ K)
    theta = np.linalg.norm(w, axis=-1)
    small = theta < 1e-12
    d = np.where(small[..., None], np.array([0.0, 0.0, 1.0]), w / np.where(small, 1.0, theta)[..., None])
    return axis_angle(d, np.where(small, 0.0, theta))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotvec_to_matrix` for a single rotation (angles < pi)."""
    R = np.asarray(R, dtype=float)
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-8:
        return v / 2
    if np.pi - theta < 1e-6:
        # Near pi the antisymmetric part vanishes; take the axis from R + I.
        B = (R + np.eye(3)) / 2
        axis = B[np.argmax(np.diag(B))]
        axis = axis / np.linalg.norm(axis)
        return axis * theta
    return v * theta / (2 * np.sin(theta))


def rot_x(a): return axis_angle(np.array([1.0, 0, 0]), a)
def rot_z(a): return axis_angle(np.array([0, 0, 1.0]), a)


def orthonormal_complement(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to unit ``d`` and to each other (deterministic)."""
    d = np.asarray(d, dtype=float) / np.linalg.norm(d)
    helper = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)
