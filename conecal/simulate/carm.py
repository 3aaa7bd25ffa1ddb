"""A C-arm imaging a calibration phantom at free poses (``motion: free``).

An image-intensifier C-arm: the source and detector stay put in the lab
(the C-arm frame), the phantom is placed by hand at poses nobody logged.
The intensifier distorts the image: radial (pincushion) about a centre off
the principal point, a little decentring, and an S-shaped twist whose
strength follows the C-arm's orientation in the earth's magnetic field.
Sizes in mm, angles in degrees at the edges.
"""

from __future__ import annotations

import numpy as np

from ..effects import World
from ..geometry import ConeGeometry, RigidTransform, matrix_to_rotvec, rotvec_to_matrix
from ..geometry.distortion import Distortion, default_radius
from .render import Cylinder
from .scenarios import BUILDERS, Scenario, _config

PHANTOMS = ("grid", "grid_marked", "balls")


def grid_phantom(n: int = 5, pitch: float = 15.0, marked: bool = False) -> np.ndarray:
    """(n*n, 3) mm: an n x n grid in the phantom's z = 0 plane, ids row by row;
    ``marked`` leaves out one corner sphere, which breaks the square's symmetry."""
    a = (np.arange(n) - (n - 1) / 2) * pitch
    x, y = np.meshgrid(a, a)
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    return pts[1:] if marked else pts


def ball_phantom(rng, n: int = 24, radius: float = 30.0, height: float = 40.0, spacing: float = 8.0) -> np.ndarray:
    """(n, 3) mm: spheres at random in a cylinder (axis z), at least ``spacing`` apart."""
    pts = []
    while len(pts) < n:
        p = np.array([*rng.uniform(-radius, radius, 2), rng.uniform(-height / 2, height / 2)])
        if np.hypot(p[0], p[1]) <= radius and all(np.linalg.norm(p - q) >= spacing for q in pts):
            pts.append(p)
    return np.array(pts)


def random_poses(rng, n: int, max_tilt_deg: float, turn_deg: float, shift_mm: float) -> RigidTransform:
    """Phantom-to-lab poses near the isocentre (lab origin): the phantom's z
    axis tilted up to ``max_tilt_deg`` from the beam (+z) in a random
    direction, turned within +-``turn_deg`` about it, shifted within
    +-``shift_mm``."""
    R = np.empty((n, 3, 3))
    for k in range(n):
        spin = rotvec_to_matrix(np.array([0, 0, np.deg2rad(rng.uniform(-turn_deg, turn_deg))]))
        tilt = np.deg2rad(max_tilt_deg) * np.sqrt(rng.uniform(0, 1))
        az = rng.uniform(0, 2 * np.pi)
        R[k] = rotvec_to_matrix(tilt * np.array([np.cos(az), np.sin(az), 0.0])) @ spin
    return RigidTransform(R, rng.uniform(-shift_mm, shift_mm, (n, 3)))


def intensifier_warps(rng, shape, R: np.ndarray, edge_px: float = 3.0, twist_px: float = 1.0,
                      twist_change: float = 0.3) -> list[Distortion]:
    """Per-frame distortion of an image intensifier: radial k1, k2 (``edge_px``
    at the normalising radius), a small decentring, and an S twist of
    ``twist_px`` that changes by +-``twist_change`` with the orientation
    (the earth's field seen from the C-arm turns with it)."""
    rows, cols = shape
    centre = ((cols - 1) / 2 + rng.uniform(-30, 30), (rows - 1) / 2 + rng.uniform(-30, 30))
    k1 = edge_px * rng.uniform(0.6, 0.9)
    k2 = edge_px - k1
    p1, p2 = rng.normal(0, 0.15 * edge_px / 3, 2)
    s0 = twist_px * rng.choice([-1, 1])
    out = []
    for Rk in R:
        w = matrix_to_rotvec(Rk)
        s = s0 * (1 + twist_change * np.sin(np.arctan2(w[1], w[0])) * min(1.0, np.linalg.norm(w) / np.deg2rad(30)))
        out.append(Distortion.radial(shape, centre=centre, radius=default_radius(shape), k1=k1, k2=k2, p1=p1, p2=p2,
                                     s=s))
    return out


def free_scan(seed=0, *, rows=512, cols=512, pitch=0.45, sod=600.0, sdd=1000.0, n_frames=25, diameter=2.0,
              mu=0.8, phantom="grid", max_tilt_deg=55.0, turn_deg=8.0, shift_mm=15.0, distortion="intensifier",
              guess_error: tuple | None = None, plate: bool = True) -> Scenario:
    """A C-arm (nominal ``sod``, ``sdd``; the true sdd off by 1-2 %, the
    principal point by 5-15 px) imaging ``phantom`` at ``n_frames`` random
    poses. ``distortion``: 'intensifier' or 'none'. ``guess_error``: (deg,
    mm) of a rough pose guess written to log.csv (rx..tz), or None for no
    guess. ``plate``: the spheres sit in a PMMA plate (a grid) or block."""
    if phantom not in PHANTOMS:
        raise ValueError(f"phantom must be one of {PHANTOMS}, not {phantom!r}")
    if distortion not in ("intensifier", "none"):
        raise ValueError(f"distortion must be intensifier or none, not {distortion!r}")
    rng = np.random.default_rng(seed)
    nominal = ConeGeometry.nominal(sod=sod, sdd=sdd, shape=(rows, cols), pixel_pitch=(pitch, pitch))
    pp = np.array([(cols - 1) / 2, (rows - 1) / 2]) + rng.uniform(5, 15, 2) * rng.choice([-1, 1], 2)
    true_sdd = sdd * (1 + rng.uniform(0.01, 0.02) * rng.choice([-1, 1]))
    origin = np.array([-pp[0] * pitch, -pp[1] * pitch, true_sdd - sod])
    truth_geom = nominal.replace(detector_origin=origin)
    if phantom == "balls":
        cad = ball_phantom(rng)
        solid = Cylinder(np.zeros(3), np.array([0, 0, 1.0]), 34.0, 22.0, 0.02)
    else:
        cad = grid_phantom(pitch=15.0, marked=phantom == "grid_marked")
        solid = Cylinder(np.zeros(3), np.array([0, 0, 1.0]), 50.0, 3.0, 0.02)
    poses = random_poses(rng, n_frames, max_tilt_deg, turn_deg, shift_mm)
    times = np.arange(n_frames) * 2.0
    readings = np.zeros((n_frames, 0))
    if guess_error is not None:
        deg, mm = guess_error
        err = rotvec_to_matrix(np.deg2rad(deg) * _unit(rng.normal(size=(n_frames, 3))))
        readings = np.column_stack([np.rad2deg([matrix_to_rotvec(m) for m in err @ poses.R]),
                                    poses.t + mm * _unit(rng.normal(size=(n_frames, 3)))])
    world = World.start(times, readings, placement=poses)
    cfg = _config("free", rows, cols, pitch, sod, sdd, diameter, phantom="phantom.csv")
    ids = np.arange(1, len(cad) + 1)
    sc = Scenario("free", cfg, times, readings, world, truth_geom, ids, cad, np.full(len(cad), diameter / 2),
                  np.full(len(cad), mu), sample_solids=[solid] if plate else [], background=(0.1, 0.05, 0.0),
                  phantom=(ids, cad), photons=2e4, blur_px=0.7)
    if distortion == "intensifier":
        sc.frame_warps = intensifier_warps(rng, (rows, cols), poses.R)
    sc.truth_extra["free"] = {"phantom": phantom, "sdd": float(true_sdd), "principal_point": pp.tolist(),
                              "distortion": distortion}
    return sc


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


BUILDERS["free"] = free_scan
