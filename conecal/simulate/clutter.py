"""Hard radiographs for ``detect``: the clutter real scans have.

Adds to a scenario a plate with an edge across the field, a thin rod,
bone-like irregular blobs, faint spheres (lower density), detector lag
ghosts, an optional circular field of view and JPEG compression. The
faint spheres and ghosts must not be reported as markers.
"""

from __future__ import annotations

import numpy as np

from ..geometry import rotvec_to_matrix
from .render import Cylinder, Ellipsoid, Sphere
from .scenarios import Scenario


def add_clutter(sc: Scenario, rng: np.random.Generator, *, fov: bool = True, jpeg: int | None = 92,
                lag: float = 0.02, faint: int = 2) -> Scenario:
    g = sc.geometry
    rows, cols = g.shape
    # object-side half field of view at the lab origin, mm
    half = 0.5 * min(rows * g.pixel_pitch[1], cols * g.pixel_pitch[0]) / (g.sdd / -g.source[2])
    # a plate whose straight-ish edge crosses the field (a huge flat ellipsoid)
    sc.lab_solids.append(Ellipsoid(np.array([-60.0 - 0.2 * half, 0, -0.5 * half]), np.array([60.0, 80.0, 0.8]),
                                   rotvec_to_matrix(np.array([0, 0, 0.3])), 0.08))
    # a thin rod across the image
    sc.lab_solids.append(Cylinder(np.array([0.1 * half, 0.2 * half, 0.3 * half]), np.array([0.8, 0.6, 0.0]),
                                  0.25, 2 * half, 0.4))
    # bone-like: a cluster of overlapping ellipsoids of moderate density
    for _ in range(5):
        c = np.array([-0.55 * half, 0.55 * half, 0.0]) + rng.normal(0, 0.06 * half, 3)
        ax = rng.uniform(0.05, 0.15, 3) * half
        sc.lab_solids.append(Ellipsoid(c, ax, rotvec_to_matrix(rng.normal(0, 1, 3)), 0.06))
    # faint spheres: same size as markers, a tenth of the density
    for _ in range(faint):
        c = np.array([rng.uniform(-0.6, 0.6) * half, rng.uniform(-0.6, 0.6) * half, 0.0])
        sc.lab_solids.append(Sphere(c, float(sc.sphere_radii[0]), float(sc.sphere_mu[0]) * 0.08))
    sc.lag = lag
    if fov:
        sc.fov_radius = 0.49 * min(rows, cols)
    sc.jpeg_quality = jpeg
    return sc
