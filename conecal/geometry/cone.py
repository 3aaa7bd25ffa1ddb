"""Cone-beam geometry of one flat detector and a point source, in the lab frame.

Conventions (``SCAN_FORMAT.md``): pixel coordinates ``(c, r)`` are continuous,
the centre of ``img[0, 0]`` is ``(0, 0)``; the lab point of ``(c, r)`` is
``detector_origin + c*pu*u + r*pv*v``. A lab point ``X`` projects to the
intersection of the line from ``source`` through ``X`` with the detector plane.

With ``B = [pu*u | pv*v | detector_origin - source]`` (columns), every ray
satisfies ``X - S = lam * B @ (c, r, 1)``, hence ``h = B^-1 (X - S)`` and
``(c, r) = (h0 / h2, h1 / h2)``. The 3x4 projection matrix is
``P = B^-1 [I | -S]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rotations import rotvec_to_matrix, skew


def _vec(a, n=3, name="vector") -> np.ndarray:
    a = np.array(a, dtype=float).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{name} must have {n} elements, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    a.setflags(write=False)
    return a


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``d(exp([w]) x)/dw = -[exp([w]) x]_x J_l(w)``;
    ``w`` (..., 3) rad -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-7
    t = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t**3)
    return np.eye(3) + a * K + b * (K @ K)


@dataclass(frozen=True, eq=False)
class ConeGeometry:
    """Immutable cone-beam geometry in lab coordinates (mm).

    Parameters (keyword-only)
    -------------------------
    source : (3,) mm, the focal spot.
    detector_origin : (3,) mm, lab position of the centre of pixel ``[0, 0]``.
    u, v : (3,) unit vectors along increasing column / row.
    pixel_pitch : (pu, pv) mm.
    shape : (rows, cols).
    """

    source: np.ndarray
    detector_origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    pixel_pitch: tuple[float, float]
    shape: tuple[int, int]

    def __init__(self, *, source, detector_origin, u, v, pixel_pitch, shape):
        u = _vec(u, name="u")
        v = _vec(v, name="v")
        nu, nv = np.linalg.norm(u), np.linalg.norm(v)
        if nu == 0 or nv == 0:
            raise ValueError("u and v must be non-zero")
        u, v = u / nu, v / nv
        u.setflags(write=False)
        v.setflags(write=False)
        if np.linalg.norm(np.cross(u, v)) < 1e-6:
            raise ValueError(f"u {u.tolist()} and v {v.tolist()} are parallel")
        pitch = tuple(float(p) for p in pixel_pitch)
        if len(pitch) != 2 or min(pitch) <= 0:
            raise ValueError(f"pixel_pitch must be two positive numbers, got {pixel_pitch}")
        shp = tuple(int(s) for s in shape)
        if len(shp) != 2 or min(shp) <= 0:
            raise ValueError(f"shape must be (rows, cols) > 0, got {shape}")
        object.__setattr__(self, "source", _vec(source, name="source"))
        object.__setattr__(self, "detector_origin", _vec(detector_origin, name="detector_origin"))
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "v", v)
        object.__setattr__(self, "pixel_pitch", pitch)
        object.__setattr__(self, "shape", shp)
        B = np.column_stack([pitch[0] * u, pitch[1] * v, self.detector_origin - self.source])
        if abs(np.linalg.det(B)) < 1e-12:
            raise ValueError("the source lies in the detector plane")
        Binv = np.linalg.inv(B)
        B.setflags(write=False)
        Binv.setflags(write=False)
        object.__setattr__(self, "_B", B)
        object.__setattr__(self, "_Binv", Binv)

    # ------------------------------------------------------------------ builders
    @classmethod
    def nominal(cls, *, sod: float, sdd: float, shape, pixel_pitch, principal_point=None) -> "ConeGeometry":
        """The scan format's nominal geometry: source ``(0,0,-sod)``, detector
        plane ``z = sdd - sod`` with ``u = +x``, ``v = +y`` and the principal
        point (foot of the source on the detector, px) at the detector centre
        unless given."""
        rows, cols = int(shape[0]), int(shape[1])
        pu, pv = float(pixel_pitch[0]), float(pixel_pitch[1])
        c0, r0 = ((cols - 1) / 2, (rows - 1) / 2) if principal_point is None else principal_point
        origin = np.array([-c0 * pu, -r0 * pv, sdd - sod])
        return cls(source=[0, 0, -sod], detector_origin=origin, u=[1, 0, 0], v=[0, 1, 0],
                   pixel_pitch=(pu, pv), shape=(rows, cols))

    def replace(self, **changes) -> "ConeGeometry":
        kw = dict(source=self.source, detector_origin=self.detector_origin, u=self.u, v=self.v,
                  pixel_pitch=self.pixel_pitch, shape=self.shape)
        kw.update(changes)
        return ConeGeometry(**kw)

    # ------------------------------------------------------------------ derived
    @property
    def normal(self) -> np.ndarray:
        """Unit normal ``u x v`` of the detector (points away from the source nominally)."""
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    @property
    def sdd(self) -> float:
        """Distance from the source to the detector plane, mm."""
        return float(abs(np.dot(self.detector_origin - self.source, self.normal)))

    @property
    def principal_point(self) -> np.ndarray:
        """Pixel coordinates (c, r) of the foot of the perpendicular from the source."""
        foot = self.source + np.dot(self.detector_origin - self.source, self.normal) * self.normal
        return self.pixel_of_plane_point(foot)

    @property
    def detector_centre(self) -> np.ndarray:
        """Lab point of pixel coordinates ((cols-1)/2, (rows-1)/2)."""
        rows, cols = self.shape
        return self.detector_point((cols - 1) / 2, (rows - 1) / 2)

    def detector_point(self, c, r) -> np.ndarray:
        """Lab position (mm) of pixel coordinates (c, r); broadcasts, returns (..., 3)."""
        c = np.asarray(c, dtype=float)[..., None]
        r = np.asarray(r, dtype=float)[..., None]
        return self.detector_origin + c * self.pixel_pitch[0] * self.u + r * self.pixel_pitch[1] * self.v

    def pixel_of_plane_point(self, X) -> np.ndarray:
        """(c, r) of a lab point lying in the detector plane."""
        h = (np.asarray(X, dtype=float) - self.detector_origin) @ np.linalg.pinv(self._B[:, :2]).T
        return h

    def magnification(self, points) -> np.ndarray:
        """Local magnification ``sdd / depth`` of lab points (...,3)."""
        depth = (np.asarray(points, dtype=float) - self.source) @ self.normal
        return self.sdd / depth

    # ------------------------------------------------------------------ projection
    def project(self, points) -> np.ndarray:
        """Pixel coordinates (c, r) of lab points; (..., 3) -> (..., 2)."""
        h = (np.asarray(points, dtype=float) - self.source) @ self._Binv.T
        return h[..., :2] / h[..., 2:3]

    def project_jacobian(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Projections and their derivative with respect to the points.

        Returns ``(cr, J)`` with ``cr`` (..., 2) and ``J = d(c, r)/dX`` (..., 2, 3), px/mm.
        """
        h = (np.asarray(points, dtype=float) - self.source) @ self._Binv.T
        cr = h[..., :2] / h[..., 2:3]
        Bi = self._Binv
        J = (Bi[None, :2, :] - cr[..., :, None] * Bi[None, 2:3, :]) / h[..., 2, None, None]
        return cr, J.reshape(cr.shape[:-1] + (2, 3))

    # The fits perturb a geometry through 9 numbers: source shift (3, mm),
    # detector origin shift (3, mm), detector rotation vector (3, rad) applied
    # to (u, v) about the detector origin. Pitches and shape stay fixed.
    PARAMETERS = ("source_x", "source_y", "source_z", "detector_x", "detector_y", "detector_z",
                  "detector_rx", "detector_ry", "detector_rz")

    def perturbed(self, delta) -> "ConeGeometry":
        """Geometry with ``delta`` (9,) applied: see ``PARAMETERS``."""
        delta = np.asarray(delta, dtype=float)
        R = rotvec_to_matrix(delta[6:9])
        return self.replace(source=self.source + delta[0:3], detector_origin=self.detector_origin + delta[3:6],
                            u=R @ self.u, v=R @ self.v)

    def geometry_jacobian(self, points, base: "ConeGeometry | None" = None, rotvec=None) -> np.ndarray:
        """Derivative of ``project(points)`` with respect to the 9 ``PARAMETERS``.

        If this geometry is ``base.perturbed(delta)``, pass ``base`` and
        ``rotvec = delta[6:9]`` to get the derivative with respect to ``delta``
        itself (the rotation enters through the SO(3) left Jacobian).
        Returns (..., 2, 9) in px/mm and px/rad.
        """
        X = np.asarray(points, dtype=float)
        Bi = self._Binv
        d = X - self.source
        h = d @ Bi.T
        cr = h[..., :2] / h[..., 2:3]
        # dcr/dh, (..., 2, 3)
        dcr_dh = np.zeros(cr.shape[:-1] + (2, 3))
        dcr_dh[..., 0, 0] = 1.0 / h[..., 2]
        dcr_dh[..., 1, 1] = 1.0 / h[..., 2]
        dcr_dh[..., :, 2] = -cr / h[..., 2:3]
        out = np.zeros(cr.shape[:-1] + (2, 9))
        # source: dh/dS = Bi (e_j) (h2 - 1)... derived from B's third column O - S.
        dh_dS = Bi[None, :, :] * (h[..., 2] - 1.0)[..., None, None]
        out[..., 0:3] = dcr_dh @ dh_dS
        # detector origin: dB/dO_j puts e_j in column 2: dh = -Bi e_j h2
        dh_dO = -Bi[None, :, :] * h[..., 2][..., None, None]
        out[..., 3:6] = dcr_dh @ dh_dO
        # detector rotation about the origin: du = -[u]x dw (times J_l if given),
        # dB col0 = pu du, col1 = pv dv; dh = -Bi dB h
        pu, pv = self.pixel_pitch
        Ju = -skew(self.u)
        Jv = -skew(self.v)
        if rotvec is not None:
            Jl = so3_left_jacobian(rotvec)
            Ju, Jv = Ju @ Jl, Jv @ Jl
        # dB h = pu h0 du + pv h1 dv  -> (..., 3, 3) w.r.t. w
        dBh = pu * h[..., 0, None, None] * Ju + pv * h[..., 1, None, None] * Jv
        dh_dw = -np.einsum("ij,...jk->...ik", Bi, dBh)
        out[..., 6:9] = dcr_dh @ dh_dw
        return out

    # ------------------------------------------------------------------ converters
    def projection_matrix(self) -> np.ndarray:
        """3x4 matrix mapping homogeneous lab points to homogeneous (c, r, 1),
        scaled so that the third coordinate is positive in front of the source."""
        return self._Binv @ np.column_stack([np.eye(3), -self.source])

    @classmethod
    def from_projection_matrix(cls, P, *, pixel_pitch, shape) -> "ConeGeometry":
        """Inverse of :meth:`projection_matrix` (any positive scale of ``P``)."""
        P = np.asarray(P, dtype=float)
        M = P[:, :3]
        S = -np.linalg.solve(M, P[:, 3])
        B = np.linalg.inv(M)
        k = float(pixel_pitch[0]) / np.linalg.norm(B[:, 0])
        B = B * k
        u = B[:, 0] / pixel_pitch[0]
        v = B[:, 1] / pixel_pitch[1]
        return cls(source=S, detector_origin=S + B[:, 2], u=u, v=v, pixel_pitch=pixel_pitch, shape=shape)

    def to_astra_vec(self) -> np.ndarray:
        """ASTRA ``cone_vec`` row (12,): source, detector centre, u*pu, v*pv."""
        return np.concatenate([self.source, self.detector_centre,
                               self.u * self.pixel_pitch[0], self.v * self.pixel_pitch[1]])

    @classmethod
    def from_astra_vec(cls, vec, *, shape) -> "ConeGeometry":
        vec = np.asarray(vec, dtype=float)
        rows, cols = shape
        pu, pv = np.linalg.norm(vec[6:9]), np.linalg.norm(vec[9:12])
        u, v = vec[6:9] / pu, vec[9:12] / pv
        origin = vec[3:6] - (cols - 1) / 2 * pu * u - (rows - 1) / 2 * pv * v
        return cls(source=vec[0:3], detector_origin=origin, u=u, v=v, pixel_pitch=(pu, pv), shape=shape)

    def to_dict(self) -> dict:
        """The scan format's geometry record (lab frame, mm)."""
        return {"source": self.source.tolist(),
                "detector": {"origin": self.detector_origin.tolist(), "u": self.u.tolist(), "v": self.v.tolist(),
                             "pixel_pitch": list(self.pixel_pitch), "shape": list(self.shape)}}

    @classmethod
    def from_dict(cls, d: dict) -> "ConeGeometry":
        det = d["detector"]
        return cls(source=d["source"], detector_origin=det["origin"], u=det["u"], v=det["v"],
                   pixel_pitch=det["pixel_pitch"], shape=det["shape"])

    def transformed(self, T) -> "ConeGeometry":
        """This geometry seen from another frame: ``T`` maps lab points to that frame."""
        return self.replace(source=T.apply(self.source), detector_origin=T.apply(self.detector_origin),
                            u=T.R @ self.u, v=T.R @ self.v)

    def __repr__(self) -> str:
        return (f"ConeGeometry(source={np.round(self.source, 4).tolist()}, "
                f"detector_origin={np.round(self.detector_origin, 4).tolist()}, u={np.round(self.u, 6).tolist()}, "
                f"v={np.round(self.v, 6).tolist()}, pixel_pitch={self.pixel_pitch}, shape={self.shape})")
