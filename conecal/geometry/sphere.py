"""What a detector records of a sphere in a cone beam.

The shadow outline of a sphere is the section of the cone tangent to it: an
ellipse whose centre is *not* the projection of the sphere centre
(Clackdoyle & Mennessier 2011; the offset grows like ``e * A / (pi * f^2)``
with ``e`` the distance from the principal point, ``A`` the ellipse area
and ``f`` the source-to-detector distance). ``conecal detect`` measures the
centroid of the attenuation (line-integral) image of each sphere, which is
a third point; :func:`shadow_centroid` predicts it exactly (by quadrature
over the ball), so that fits compare like with like.
"""

from __future__ import annotations

import numpy as np

from .cone import ConeGeometry


def shadow_conic(geometry: ConeGeometry, centre, radius: float) -> np.ndarray:
    """Homogeneous conic ``Q`` (..., 3, 3) of the shadow outline in pixel
    coordinates: ``h^T Q h = 0`` for ``h = (c, r, 1)`` on the outline."""
    C = np.asarray(centre, dtype=float)
    d = C - geometry.source
    dist = np.linalg.norm(d, axis=-1)
    if np.any(radius >= dist):
        raise ValueError("the source lies inside a sphere")
    w = d / dist[..., None]
    cos2 = 1.0 - (radius / dist) ** 2
    B = geometry._B
    Bw = w @ B  # (..., 3) = B^T w
    Q = Bw[..., :, None] * Bw[..., None, :] - cos2[..., None, None] * (B.T @ B)
    return Q


def shadow_ellipse(geometry: ConeGeometry, centre, radius: float):
    """Centre (..., 2), semi-axes (..., 2) (major first) and angle (rad) of the outline, px."""
    Q = shadow_conic(geometry, centre, radius)
    A = Q[..., :2, :2]
    b = Q[..., :2, 2]
    ctr = -np.linalg.solve(A, b[..., None])[..., 0]
    # value of the conic at the centre: k = c + b.ctr
    k = Q[..., 2, 2] + np.einsum("...i,...i->...", b, ctr)
    evals, evecs = np.linalg.eigh(A)
    axes = np.sqrt(-k[..., None] / evals)
    axes = axes[..., ::-1]  # smaller eigenvalue -> major axis
    major = evecs[..., :, 0]
    angle = np.arctan2(major[..., 1], major[..., 0])
    return ctr, axes, angle


def _ball_rule(n_r: int = 4, n_polar: int = 6, n_az: int = 8):
    """Quadrature nodes (m, 3) in the unit ball and weights (m,), sum = 4/3 pi."""
    # radial: Gauss-Legendre on [0, 1] with the r^2 volume factor
    x, w = np.polynomial.legendre.leggauss(n_r)
    r = (x + 1) / 2
    wr = w / 2 * r**2
    ct, wt = np.polynomial.legendre.leggauss(n_polar)
    st = np.sqrt(1 - ct**2)
    phi = (np.arange(n_az) + 0.5) * 2 * np.pi / n_az
    wphi = np.full(n_az, 2 * np.pi / n_az)
    R, CT, PHI = np.meshgrid(r, ct, phi, indexing="ij")
    ST = np.sqrt(1 - CT**2)
    pts = np.stack([R * ST * np.cos(PHI), R * ST * np.sin(PHI), R * CT], -1).reshape(-1, 3)
    W = (wr[:, None, None] * wt[None, :, None] * wphi[None, None, :]).reshape(-1)
    del st
    return pts, W


_BALL = _ball_rule()
# a coarser rule for derivatives: 8e-5 px off on a 5 mm sphere 50 mm from the source
_BALL_COARSE = _ball_rule(3, 3, 4)


def shadow_centroid(geometry: ConeGeometry, centre, radius, coarse: bool = False) -> np.ndarray:
    """Centroid (c, r) of the attenuation image of a homogeneous sphere, px.

    With ``g = B^-1 (X - S)`` the weight of a volume element in the detector
    first moment is ``|X - S| / g2^3`` (derivation in ``docs``: the ray
    Jacobian ``lam^2 |det B|`` and the chord element ``|B h| dlam``), so the
    centroid is a weighted mean of the projections of the ball's points.
    Exact to ~1e-9 px for spheres small against their distance to the source.
    """
    C = np.asarray(centre, dtype=float)
    pts, W = _BALL_COARSE if coarse else _BALL
    rad = np.asarray(radius, dtype=float)[..., None, None]   # a scalar, or one per centre
    X = C[..., None, :] + rad * pts  # (..., m, 3)
    g = (X - geometry.source) @ geometry._Binv.T
    wt = W * np.linalg.norm(X - geometry.source, axis=-1) / g[..., 2] ** 3
    cr = g[..., :2] / g[..., 2:3]
    return np.einsum("...m,...mi->...i", wt, cr) / wt.sum(-1)[..., None]


def shadow_bias(geometry: ConeGeometry, centre, radius, coarse: bool = False) -> np.ndarray:
    """``shadow_centroid - project(centre)``, px: what a point model would miss.
    ``coarse``: a 36-point rule, for derivatives."""
    return shadow_centroid(geometry, centre, radius, coarse) - geometry.project(centre)


def shadow_diameter_px(geometry: ConeGeometry, centre, radius: float) -> np.ndarray:
    """Approximate shadow diameter in px (2 * radius * magnification / pitch)."""
    m = geometry.magnification(centre)
    return 2 * radius * m / np.sqrt(geometry.pixel_pitch[0] * geometry.pixel_pitch[1])


def hidden_behind(geometry: ConeGeometry, centres, radius: float, seen, ids) -> list[list[int]]:
    """``[[id, id of the sphere hiding it], ...]``: spheres (``centres`` (n, 3)
    lab mm, ``radius`` mm) not ``seen`` whose shadow centre falls on the
    detector inside another sphere's shadow: their shadows overlap by more
    than half, and no detector can measure them apart (reported as hidden,
    not missing). The other may be unseen too (a deep pair measured as
    neither: each is listed in the other's shadow); when it was seen, its
    measured centre may hold some of the hidden one's shadow."""
    centres = np.asarray(centres, float)
    seen = np.asarray(seen, bool)
    pred = geometry.project(centres)
    half = shadow_diameter_px(geometry, centres, radius) / 2
    rows, cols = geometry.shape
    on = (pred[:, 0] >= 0) & (pred[:, 0] <= cols - 1) & (pred[:, 1] >= 0) & (pred[:, 1] <= rows - 1)
    out = []
    for i in np.flatnonzero(~seen & on):
        d = np.hypot(*(pred - pred[i]).T)
        d[i] = np.inf
        j = int(np.argmin(d - half))
        if d[j] < half[j]:
            out.append([int(ids[i]), int(ids[j])])
    return out
