"""Exact line integrals of simple solids on a cone-beam detector.

Every pixel value is the mean over ``ss x ss`` sub-pixel rays of the
attenuation line integral ``sum(mu * chord)`` (``mu`` in 1/mm, chords in mm),
computed in closed form per solid: sphere, ellipsoid, finite cylinder. Work
is restricted to each solid's bounding box on the detector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import ConeGeometry


@dataclass(frozen=True, eq=False)
class Sphere:
    centre: np.ndarray  # (3,) lab mm
    radius: float       # mm
    mu: float           # 1/mm


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    centre: np.ndarray      # (3,) lab mm
    semi_axes: np.ndarray   # (3,) mm
    rotation: np.ndarray    # (3, 3): columns are the ellipsoid's axes in the lab
    mu: float


@dataclass(frozen=True, eq=False)
class Cylinder:
    centre: np.ndarray      # (3,) lab mm
    direction: np.ndarray   # (3,) unit
    radius: float
    half_length: float
    mu: float


def _bbox_corners(obj) -> np.ndarray:
    if isinstance(obj, Sphere):
        e = np.full(3, obj.radius)
        R = np.eye(3)
    elif isinstance(obj, Ellipsoid):
        e, R = np.asarray(obj.semi_axes, float), np.asarray(obj.rotation, float)
    else:
        d = np.asarray(obj.direction, float)
        from ..geometry.rotations import orthonormal_complement
        e1, e2 = orthonormal_complement(d)
        R = np.column_stack([e1, e2, d])
        e = np.array([obj.radius, obj.radius, obj.half_length])
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return np.asarray(obj.centre, float) + (signs * e) @ R.T


def _chord(obj, S: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Chord lengths (mm) of rays from S along unit directions w (N, 3)."""
    if isinstance(obj, Sphere):
        oc = np.asarray(obj.centre) - S
        tc = w @ oc
        d2 = oc @ oc - tc**2
        return 2 * np.sqrt(np.maximum(obj.radius**2 - d2, 0.0))
    if isinstance(obj, Ellipsoid):
        R = np.asarray(obj.rotation, float)
        a = np.asarray(obj.semi_axes, float)
        o = (R.T @ (S - obj.centre)) / a
        ww = (w @ R) / a
        A = np.einsum("ij,ij->i", ww, ww)
        B = ww @ o
        C = o @ o - 1.0
        disc = B**2 - A * C
        return 2 * np.sqrt(np.maximum(disc, 0.0)) / A
    d = np.asarray(obj.direction, float)
    o = S - obj.centre
    od, wd = o @ d, w @ d
    op = o - od * d
    wp = w - wd[:, None] * d
    A = np.einsum("ij,ij->i", wp, wp)
    B = wp @ op
    C = op @ op - obj.radius**2
    disc = B**2 - A * C
    ok = (disc > 0) & (A > 1e-15)
    sq = np.sqrt(np.maximum(disc, 0.0))
    Asafe = np.where(ok, A, 1.0)
    t1, t2 = (-B - sq) / Asafe, (-B + sq) / Asafe
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (-obj.half_length - od) / wd
        tb = (obj.half_length - od) / wd
    t3 = np.where(np.abs(wd) > 1e-15, np.minimum(ta, tb), -np.inf)
    t4 = np.where(np.abs(wd) > 1e-15, np.maximum(ta, tb), np.inf)
    L = np.minimum(t2, t4) - np.maximum(t1, t3)
    return np.where(ok, np.maximum(L, 0.0), 0.0)


def render_line_integrals(geometry: ConeGeometry, solids, ss: int = 3, out: np.ndarray | None = None,
                          margin: float = 2.0, distortion=None) -> np.ndarray:
    """Add ``mu * chord`` of every solid, pixel-averaged over ss x ss rays, to ``out``
    (float64 (rows, cols), created if None) and return it.

    ``distortion``: an :class:`~conecal.effects.Imaging` whose detector
    distortion warps the image (each pixel sees the ray of its undistorted
    position)."""
    warp = distortion is not None and distortion.distorted
    rows, cols = geometry.shape
    if out is None:
        out = np.zeros((rows, cols))
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    S = geometry.source
    for obj in solids:
        corners = geometry.project(_bbox_corners(obj))
        if warp:
            corners = distortion.distort(corners, geometry.shape)
        c0 = int(max(np.floor(corners[:, 0].min() - margin), 0))
        c1 = int(min(np.ceil(corners[:, 0].max() + margin), cols - 1))
        r0 = int(max(np.floor(corners[:, 1].min() - margin), 0))
        r1 = int(min(np.ceil(corners[:, 1].max() + margin), rows - 1))
        if c1 < c0 or r1 < r0:
            continue
        cc = (np.arange(c0, c1 + 1)[:, None] + sub[None, :]).reshape(-1)
        rr = (np.arange(r0, r1 + 1)[:, None] + sub[None, :]).reshape(-1)
        # rays in row-major order over the (rows*ss, cols*ss) sub-grid
        if warp:
            grid = np.stack(np.broadcast_arrays(cc[None, :], rr[:, None]), axis=-1)
            ideal = distortion.undistort(grid, geometry.shape)
            D = geometry.detector_point(ideal[..., 0], ideal[..., 1]).reshape(-1, 3)
        else:
            D = geometry.detector_point(cc[None, :], rr[:, None]).reshape(-1, 3)
        w = D - S
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        L = obj.mu * _chord(obj, S, w)
        L = L.reshape(r1 - r0 + 1, ss, c1 - c0 + 1, ss).mean(axis=(1, 3))
        out[r0:r1 + 1, c0:c1 + 1] += L
    return out
