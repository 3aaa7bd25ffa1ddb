"""The 9 numbers by which fits move a cone-beam geometry, with Jacobians.

source shift (3, mm), detector-centre shift (3, mm) and the detector's
rotation about its centre (3, deg, a rotation vector applied to the base
u, v). Rotating about the centre rather than pixel (0, 0) keeps the
parameters nearly uncorrelated and readable.
"""

from __future__ import annotations

import numpy as np

from ..geometry import ConeGeometry, matrix_to_rotvec, rotvec_to_matrix
from ..geometry.cone import so3_left_jacobian
from ..geometry.rotations import skew

DEG = np.pi / 180
NAMES = ("source_x", "source_y", "source_z", "detector_centre_x", "detector_centre_y", "detector_centre_z",
         "detector_rx", "detector_ry", "detector_rz")
UNITS = ("mm",) * 6 + ("deg",) * 3


class DetectorParams:
    """Maps 9 parameters to a geometry near ``base`` and back."""

    def __init__(self, base: ConeGeometry):
        self.base = base
        rows, cols = base.shape
        self._a = (cols - 1) / 2 * base.pixel_pitch[0]
        self._b = (rows - 1) / 2 * base.pixel_pitch[1]

    def geometry(self, x9) -> ConeGeometry:
        R = rotvec_to_matrix(np.asarray(x9[6:9], float) * DEG)
        u, v = R @ self.base.u, R @ self.base.v
        centre = self.base.detector_centre + x9[3:6]
        return self.base.replace(source=self.base.source + x9[0:3], detector_origin=centre - self._a * u - self._b * v,
                                 u=u, v=v)

    def vector(self, g: ConeGeometry) -> np.ndarray:
        """Parameters that reproduce ``g`` (same pitches and shape)."""
        x = np.zeros(9)
        x[0:3] = g.source - self.base.source
        x[3:6] = g.detector_centre - self.base.detector_centre
        R = np.column_stack([g.u, g.v, g.normal]) @ np.column_stack([self.base.u, self.base.v, self.base.normal]).T
        x[6:9] = matrix_to_rotvec(R) / DEG
        return x

    def jacobian(self, g: ConeGeometry, X: np.ndarray, x9) -> np.ndarray:
        """d project(X) / d(9 parameters) at ``g = geometry(x9)``; (m, 2, 9)."""
        w = np.asarray(x9[6:9], float) * DEG
        Jg = g.geometry_jacobian(X, rotvec=w)   # source, origin, rotation about the origin
        J = np.empty(Jg.shape)
        J[..., 0:6] = Jg[..., 0:6]              # the origin moves with the centre
        dO_dw = (self._a * skew(g.u) + self._b * skew(g.v)) @ so3_left_jacobian(w)
        J[..., 6:9] = (Jg[..., 6:9] + Jg[..., 3:6] @ dO_dw) * DEG
        return J
