"""The fixed source-detector pair of a C-arm or radiography station.

The lab frame of a free-pose calibration is the imaging system's own (a
gauge: no stage defines another): the source at ``(0, 0, -sod)`` with the
nominal ``sod``, the detector plane perpendicular to +z with ``u = +x``,
``v = +y``, as in the contract's nominal geometry. What is estimated is the
source-to-detector distance ``sdd`` (mm) and the principal point ``(c0,
r0)`` (px, the foot of the perpendicular from the source); aspect and skew
are those of the stated pixel pitch.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import distance_transform_edt

from ..geometry import ConeGeometry

INTRINSICS = ("sdd", "c0", "r0")
INTRINSIC_UNITS = {"sdd": "mm", "c0": "px", "r0": "px"}


@dataclass(frozen=True)
class Camera:
    """sdd (mm), principal point c0, r0 (px), nominal sod (mm; fixes the lab
    origin only), pixel pitch (pu, pv) mm, shape (rows, cols); ``field``:
    where the detector sees the beam (:class:`Field`), None: everywhere."""

    sdd: float
    c0: float
    r0: float
    sod: float
    pitch: tuple
    shape: tuple
    field: "Field | None" = None

    @classmethod
    def nominal(cls, geometry: ConeGeometry, sod: float) -> "Camera":
        c0, r0 = geometry.principal_point
        return cls(geometry.sdd, float(c0), float(r0), float(sod), tuple(geometry.pixel_pitch), tuple(geometry.shape))

    @classmethod
    def from_geometry(cls, geometry: ConeGeometry) -> "Camera":
        """A geometry in this frame's convention (source on the z axis, detector
        perpendicular to z, u = +x, v = +y)."""
        return cls.nominal(geometry, float(-geometry.source[2]))

    @property
    def source(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.sod])

    @property
    def focal_px(self) -> np.ndarray:
        return np.array([self.sdd / self.pitch[0], self.sdd / self.pitch[1]])

    def with_intrinsics(self, x) -> "Camera":
        return replace(self, sdd=float(x[0]), c0=float(x[1]), r0=float(x[2]))

    def intrinsics(self) -> np.ndarray:
        return np.array([self.sdd, self.c0, self.r0])

    def geometry(self) -> ConeGeometry:
        """The ideal (pinhole) ConeGeometry, lab frame."""
        pu, pv = self.pitch
        origin = np.array([-self.c0 * pu, -self.r0 * pv, self.sdd - self.sod])
        return ConeGeometry(source=self.source, detector_origin=origin, u=(1, 0, 0), v=(0, 1, 0),
                            pixel_pitch=self.pitch, shape=self.shape)

    def matrix(self) -> np.ndarray:
        """3x3 K mapping source-centred lab directions to homogeneous (c, r, 1)."""
        f = self.focal_px
        return np.array([[f[0], 0, self.c0], [0, f[1], self.r0], [0, 0, 1.0]])

    def project(self, X, offsets=None) -> np.ndarray:
        """Ideal pixel (c, r) of lab points (..., 3) -> (..., 2); ``offsets``
        (..., 3): each point's own (sdd mm, c0 px, r0 px) added to the shared ones."""
        d = np.asarray(X, float) - self.source
        K = self.intrinsics() if offsets is None else self.intrinsics() + offsets
        return np.stack([K[..., 1] + K[..., 0] / self.pitch[0] * d[..., 0] / d[..., 2],
                         K[..., 2] + K[..., 0] / self.pitch[1] * d[..., 1] / d[..., 2]], -1)

    def project_jacobians(self, X, offsets=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Projections (N, 2), d/dX (N, 2, 3) px/mm and d/d(sdd, c0, r0) (N, 2, 3).

        ``offsets`` (N, 3): each point's own (sdd mm, c0 px, r0 px) added to the
        shared ones (per-frame intrinsics; the derivatives are the same for
        shared and offset)."""
        d = np.asarray(X, float) - self.source
        K = np.broadcast_to(self.intrinsics(), d.shape) if offsets is None else self.intrinsics() + offsets
        fu, fv = K[:, 0] / self.pitch[0], K[:, 0] / self.pitch[1]
        iz = 1.0 / d[:, 2]
        xn, yn = d[:, 0] * iz, d[:, 1] * iz
        p = np.stack([K[:, 1] + fu * xn, K[:, 2] + fv * yn], -1)
        JX = np.zeros((len(d), 2, 3))
        JX[:, 0, 0] = fu * iz
        JX[:, 0, 2] = -fu * xn * iz
        JX[:, 1, 1] = fv * iz
        JX[:, 1, 2] = -fv * yn * iz
        JK = np.zeros((len(d), 2, 3))
        JK[:, 0, 0] = xn / self.pitch[0]
        JK[:, 1, 0] = yn / self.pitch[1]
        JK[:, 0, 1] = 1.0
        JK[:, 1, 2] = 1.0
        return p, JX, JK


@dataclass(frozen=True, eq=False)
class Field:
    """Where the detector sees the beam: ``dist`` (rows, cols), each pixel's
    distance (px) to the nearest pixel that does not (an image intensifier's
    black surround, as the flat shows it)."""

    dist: np.ndarray

    @classmethod
    def from_mask(cls, mask: np.ndarray | None) -> "Field | None":
        """From a (rows, cols) mask of the pixels that see the beam; None when
        there is none or every pixel does."""
        if mask is None or mask.all():
            return None
        return cls(distance_transform_edt(mask).astype(np.float32))

    def holds(self, xy, reach) -> np.ndarray:
        """Whether discs about ``xy`` (..., 2) px (c, r) of radius ``reach``
        (px, broadcast) lie where the beam is seen."""
        xy = np.asarray(xy, float)
        c, r = np.rint(xy[..., 0]), np.rint(xy[..., 1])
        rows, cols = self.dist.shape
        on = np.isfinite(c) & np.isfinite(r) & (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
        out = np.zeros(xy.shape[:-1], bool)
        out[on] = self.dist[r[on].astype(int), c[on].astype(int)] >= np.broadcast_to(reach, out.shape)[on]
        return out


class GeometryCamera:
    """Any :class:`ConeGeometry` (a tilted detector, a robot's lab frame) seen
    through the interface the pose search uses: exact projections and their
    point Jacobians; the pinhole numbers (focal length, principal point) only
    seed its hypotheses, which assume the beam along +z as the contract's
    nominal set-up has it."""

    def __init__(self, geometry: ConeGeometry):
        self.g = geometry
        self.shape = tuple(geometry.shape)
        self.pitch = tuple(geometry.pixel_pitch)
        self.c0, self.r0 = (float(v) for v in geometry.principal_point)
        self.source = np.asarray(geometry.source, float)
        self.sod = float(-self.source[2]) if self.source[2] < 0 else float(np.linalg.norm(self.source))

    @property
    def focal_px(self) -> np.ndarray:
        return np.array([self.g.sdd / self.pitch[0], self.g.sdd / self.pitch[1]])

    def project(self, X) -> np.ndarray:
        return self.g.project(X)

    def project_jacobians(self, X):
        p, J = self.g.project_jacobian(np.asarray(X, float))
        return p, J, None

    def matrix(self) -> np.ndarray:
        f = self.focal_px
        return np.array([[f[0], 0, self.c0], [0, f[1], self.r0], [0, 0, 1.0]])
