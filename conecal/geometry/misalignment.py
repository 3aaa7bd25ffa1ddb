"""The five detector misalignment parameters of a circular scan.

All relative to the nominal geometry and about the nominal detector centre
(pixel coordinates ((cols-1)/2, (rows-1)/2)):

- ``shift_u_px``, ``shift_v_px``: shift of the detector along its nominal
  column (u) and row (v) directions, in pixels;
- ``eta_deg``: in-plane rotation about the detector normal;
- ``theta_deg``: out-of-plane tilt about the nominal u direction (the top
  and bottom rows move towards / away from the source);
- ``phi_deg``: out-of-plane tilt about the nominal v direction (the left
  and right columns move towards / away from the source).

The detector is rotated by ``R = R(n, eta) R(u, theta) R(v, phi)`` and its
centre shifted; the source stays at its nominal position.
"""

from __future__ import annotations

import numpy as np

from ..geometry import ConeGeometry
from ..geometry.rotations import axis_angle

NAMES = ("shift_u_px", "shift_v_px", "eta_deg", "theta_deg", "phi_deg")
UNITS = ("px", "px", "deg", "deg", "deg")


def misaligned(nominal: ConeGeometry, p) -> ConeGeometry:
    """The geometry of ``nominal`` moved by the five parameters ``p``."""
    du, dv, eta, th, phi = np.asarray(p, float)
    R = (axis_angle(nominal.normal, np.deg2rad(eta)) @ axis_angle(nominal.u, np.deg2rad(th))
         @ axis_angle(nominal.v, np.deg2rad(phi)))
    u, v = R @ nominal.u, R @ nominal.v
    rows, cols = nominal.shape
    pu, pv = nominal.pixel_pitch
    centre = nominal.detector_centre + du * pu * nominal.u + dv * pv * nominal.v
    origin = centre - (cols - 1) / 2 * pu * u - (rows - 1) / 2 * pv * v
    return nominal.replace(detector_origin=origin, u=u, v=v)


def as_dict(p, sigma=None) -> dict:
    out = {}
    for i, (n, unit) in enumerate(zip(NAMES, UNITS)):
        out[n] = {"value": float(p[i]), "unit": unit}
        if sigma is not None:
            out[n]["sigma"] = None if not np.isfinite(sigma[i]) else float(sigma[i])
    return out
