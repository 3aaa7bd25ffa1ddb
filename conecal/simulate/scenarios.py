"""Simulated scans for every motion type, with their true geometry.

A :class:`Scenario` holds what the scan directory will say (the nominal
``config`` and the logged readings) and what really happened (true
geometry, the :class:`~conecal.effects.World` after effects, the sample).
All sizes in mm, angles in degrees at the edges.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..effects import World
from ..geometry import ConeGeometry, RigidTransform, rotvec_to_matrix
from ..geometry.misalignment import misaligned
from ..geometry.sphere import shadow_centroid, shadow_diameter_px
from ..kinematics import Chain, DHRobot, LinearAxis, RotaryAxis
from .render import Cylinder, Ellipsoid, Sphere

KINDS = ("linear", "rotation", "robot", "circular", "free")


@dataclass(eq=False)
class Scenario:
    kind: str
    config: dict
    times: np.ndarray
    readings: np.ndarray
    world: World
    geometry: ConeGeometry                 # true geometry at t = 0
    sphere_ids: np.ndarray                  # (m,)
    sphere_positions: np.ndarray            # (m, 3) sample frame
    sphere_radii: np.ndarray                # (m,)
    sphere_mu: np.ndarray                   # (m,)
    sample_solids: list = field(default_factory=list)  # move with the sample
    lab_solids: list = field(default_factory=list)     # fixed in the lab
    background: tuple = (0.0, 0.0, 0.0)     # attenuation a0 + gc*c/cols + gr*r/rows
    photons: float = 3e4                    # per pixel at I0; 0 = noiseless
    blur_px: float = 0.5                    # focal-spot/detector blur, Gaussian sigma in px
    supersample: int = 3
    phantom: tuple | None = None            # (ids, CAD positions) for a holder
    truth_extra: dict = field(default_factory=dict)
    effects: list = field(default_factory=list)
    fov_radius: float | None = None         # circular field of view, px
    jpeg_quality: int | None = None
    lag: float = 0.0                        # fraction of the previous frame left on the detector
    frame_warps: list | None = None         # per-frame detector distortion (C-arm), on top of the world's

    def imaging_at(self, k: int):
        """How the detector records frame ``k``: the world's imaging, with the
        frame's own distortion where it has one."""
        im = self.world.imaging
        if self.frame_warps is None or self.frame_warps[k] is None:
            return im
        if im.warp is not None:
            raise ValueError("a per-frame distortion and a detector_distortion effect cannot be combined")
        return replace(im, warp=self.frame_warps[k])

    @property
    def n_frames(self) -> int:
        return len(self.times)

    def apply_effects(self, effects) -> None:
        for e in effects:
            self.world = e.apply(self.world)
            self.effects.append(e)

    def frame_geometry(self, k: int) -> ConeGeometry:
        off = self.world.source_offsets[k]
        det = self.world.detector_offsets[k] if self.world.detector_offsets is not None else np.zeros(3)
        if not np.any(off) and not np.any(det):
            return self.geometry
        return self.geometry.replace(source=self.geometry.source + off,
                                     detector_origin=self.geometry.detector_origin + det)

    def solids(self, k: int, T: RigidTransform) -> list:
        out = [Sphere(T.apply(p), r, mu) for p, r, mu in zip(self.sphere_positions, self.sphere_radii, self.sphere_mu)]
        for s in self.sample_solids:
            if isinstance(s, Ellipsoid):
                out.append(Ellipsoid(T.apply(s.centre), s.semi_axes, T.R @ s.rotation, s.mu))
            elif isinstance(s, Cylinder):
                out.append(Cylinder(T.apply(s.centre), T.R @ s.direction, s.radius, s.half_length, s.mu))
            else:
                out.append(Sphere(T.apply(s.centre), s.radius, s.mu))
        return out + list(self.lab_solids)


def _perturbed_geometry(nominal: ConeGeometry, rng, src_mm, det_mm, rot_deg) -> ConeGeometry:
    delta = np.concatenate([rng.normal(0, src_mm, 3), rng.normal(0, det_mm, 3),
                            np.deg2rad(rng.normal(0, rot_deg, 3))])
    # rotate the detector about its centre, not about pixel (0, 0)
    R = rotvec_to_matrix(delta[6:9])
    centre = nominal.detector_centre
    u, v = R @ nominal.u, R @ nominal.v
    rows, cols = nominal.shape
    pu, pv = nominal.pixel_pitch
    new_centre = centre + delta[3:6]
    origin = new_centre - (cols - 1) / 2 * pu * u - (rows - 1) / 2 * pv * v
    return nominal.replace(source=nominal.source + delta[:3], detector_origin=origin, u=u, v=v)


def _config(kind, rows, cols, pitch, sod, sdd, diameter, axes=None, robot=None, phantom=None):
    cfg = {"format": "conecal-scan/1", "motion": kind, "projections": "projections.tif",
           "values": "attenuation", "log": "log.csv",
           "detector": {"rows": rows, "cols": cols, "pixel_pitch": [pitch, pitch]},
           "nominal": {"sod": sod, "sdd": sdd}}
    if diameter is not None:
        cfg["markers"] = {"diameter": diameter}
        if phantom:
            cfg["markers"]["phantom"] = phantom
    if axes is not None:
        cfg["axes"] = axes
    if robot is not None:
        cfg["robot"] = robot
    return cfg


XYZ_AXES = [{"name": "x", "type": "linear", "direction": [1.0, 0.0, 0.0]},
            {"name": "y", "type": "linear", "direction": [0.0, 1.0, 0.0]},
            {"name": "z", "type": "linear", "direction": [0.0, 0.0, 1.0]}]


def linear_raster(seed=0, *, rows=512, cols=512, pitch=0.2, sod=100.0, sdd=500.0, diameter=2.0, mu=0.5,
                  steps=(5.0, 5.0, 8.0), counts=(3, 3, 3), dt=2.0, misalign=(0.5, 2.0, 0.5),
                  true_geometry: ConeGeometry | None = None) -> Scenario:
    """One sphere moved through a raster by three linear axes (Blumensath et al.).

    ``counts`` positions per axis centred on zero, ``steps`` apart (mm);
    the sphere sits at the lab origin when every axis reads zero.
    ``misalign`` = (source sigma mm, detector sigma mm, detector rotation sigma deg);
    ``true_geometry`` replaces that draw (the same system scanned twice).
    """
    rng = np.random.default_rng(seed)
    nominal = ConeGeometry.nominal(sod=sod, sdd=sdd, shape=(rows, cols), pixel_pitch=(pitch, pitch))
    truth_geom = _perturbed_geometry(nominal, rng, *misalign)
    if true_geometry is not None:
        truth_geom = true_geometry
    grids = [(np.arange(n) - (n - 1) / 2) * s for n, s in zip(counts, steps)]
    # serpentine raster: the order a stage controller would drive
    pts = []
    for iz, z in enumerate(grids[2]):
        for iy, y in enumerate(grids[1] if iz % 2 == 0 else grids[1][::-1]):
            xs = grids[0] if (iy + iz) % 2 == 0 else grids[0][::-1]
            pts.extend((x, y, z) for x in xs)
    readings = np.array(pts)
    times = np.arange(len(readings)) * dt
    chain = Chain(tuple(LinearAxis(a["name"], a["direction"]) for a in XYZ_AXES))
    world = World.start(times, readings, chain=chain)
    cfg = _config("linear", rows, cols, pitch, sod, sdd, diameter, axes=XYZ_AXES)
    return Scenario("linear", cfg, times, readings, world, truth_geom, np.array([0]), np.zeros((1, 3)),
                    np.array([diameter / 2]), np.array([mu]), background=(0.3, 0.15, -0.1))


def rotation_scan(seed=0, *, rows=512, cols=512, pitch=0.2, sod=150.0, sdd=600.0, diameters=(2.0,), mu=0.5,
                  n_spheres=5, n_frames=72, dt=1.0, axis_tilt_deg=0.3, axis_offset_mm=0.3,
                  misalign=(0.5, 2.0, 0.5), true_geometry: ConeGeometry | None = None,
                  schedule: str = "uniform") -> Scenario:
    """Several spheres on a sample rotated by a rotary axis on top of x, y, z stages.

    ``schedule``: "uniform" steps the axis evenly through one turn;
    "sweep" swings it back and forth at varying speed (30..330 deg), as a
    scan that must tell latency (error ~ velocity) from backlash (error ~
    sign of velocity) needs.

    The reference sphere (id 0) sits at the lab origin at zero readings; the
    others are spread over heights so that their shadows rarely overlap.
    """
    rng = np.random.default_rng(seed)
    nominal = ConeGeometry.nominal(sod=sod, sdd=sdd, shape=(rows, cols), pixel_pitch=(pitch, pitch))
    truth_geom = _perturbed_geometry(nominal, rng, *misalign)
    if true_geometry is not None:
        truth_geom = true_geometry
    nominal_point = np.zeros(3)
    tilt = rng.normal(size=3)
    tilt -= tilt[1] * np.array([0, 1.0, 0])
    tilt *= np.deg2rad(axis_tilt_deg) / np.linalg.norm(tilt)
    true_dir = rotvec_to_matrix(tilt) @ np.array([0, 1.0, 0])
    off = rng.normal(size=3)
    off[1] = 0
    true_point = nominal_point + off / np.linalg.norm(off) * axis_offset_mm + np.array([2.0, 0, 1.0])
    heights = np.linspace(-1, 1, n_spheres) * min(8.0, 0.35 * rows * pitch * sod / sdd)
    rng.shuffle(heights)
    pos = [np.zeros(3)]
    # the reference sphere's height decides where the others go
    others = [h for h in heights if abs(h) > 1e-9][: n_spheres - 1] if 0.0 in heights else list(heights[1:])
    for h in others:
        ang = rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(3.0, 7.0)
        pos.append(np.array([rad * np.cos(ang), h, rad * np.sin(ang)]))
    pos = np.array(pos)
    radii = np.array([diameters[k % len(diameters)] / 2 for k in range(n_spheres)])
    if schedule == "uniform":
        theta = np.arange(n_frames) * 360.0 / n_frames
    elif schedule == "sweep":
        ph = np.linspace(0, 3 * np.pi, n_frames)
        theta = 180.0 + 150.0 * np.sin(ph) * (0.75 + 0.25 * np.cos(ph / 3))
    else:
        raise ValueError(f"schedule must be uniform or sweep, not {schedule!r}")
    readings = np.column_stack([np.zeros((n_frames, 3)), theta])
    times = np.arange(n_frames) * dt
    axes = XYZ_AXES + [{"name": "theta", "type": "rotary", "direction": [0.0, 1.0, 0.0], "point": [2.0, 0.0, 1.0]}]
    chain = Chain(tuple(LinearAxis(a["name"], a["direction"]) for a in XYZ_AXES) + (RotaryAxis("theta", true_dir, true_point),))
    world = World.start(times, readings, chain=chain)
    cfg = _config("rotation", rows, cols, pitch, sod, sdd, float(diameters[0]), axes=axes)
    if len(set(diameters)) > 1:
        cfg["markers"]["diameters"] = [float(d) for d in diameters]
    sc = Scenario("rotation", cfg, times, readings, world, truth_geom, np.arange(n_spheres), pos, radii,
                  np.full(n_spheres, mu), background=(0.3, 0.1, 0.1))
    sc.truth_extra["rotary_axis"] = {"direction": true_dir.tolist(), "point": true_point.tolist()}
    return sc


# A 7-joint arm in Craig's modified DH form (rows a, alpha, d, theta; mm, deg),
# shaped like common collaborative arms.
ROBOT_DH = [[0, 0, 340, 0], [0, -90, 0, 0], [0, 90, 400, 0], [0, 90, 0, 0],
            [0, -90, 400, 0], [0, -90, 0, 0], [0, 90, 126, 0]]
ROBOT_HOME = np.array([10.0, 35.0, -5.0, -70.0, 8.0, 55.0, 0.0])


def _elbow_sweep(robot: DHRobot, q: np.ndarray, amplitude_deg: float) -> np.ndarray:
    """Joint readings that hold each frame's holder pose of ``q`` while joint
    3 swivels the elbow through one period of +-``amplitude_deg`` (the arm's
    self-motion: seven joints, six pose constraints)."""
    from scipy.optimize import least_squares

    from ..geometry import matrix_to_rotvec

    target = robot.transforms(q)
    free = [0, 1, 3, 4, 5, 6]
    out = q.copy()
    prev = q[0].copy()
    n = len(q)
    for k in range(n):
        q3 = q[k, 2] + amplitude_deg * np.sin(2 * np.pi * k / n)

        def pose_error(x):
            qq = prev.copy()
            qq[free], qq[2] = x, q3
            T = robot.transforms(qq[None])[0]
            return np.concatenate([100.0 * matrix_to_rotvec(T.R @ target.R[k].T), T.t - target.t[k]])

        x0 = prev[free].copy()
        if k:
            x0[5] += q[k, 6] - q[k - 1, 6]
        sol = least_squares(pose_error, x0, xtol=1e-12, ftol=1e-12)
        prev = prev.copy()
        prev[free], prev[2] = sol.x, q3
        out[k] = prev
    return out


def helix_phantom(n=50, radius=12.0, height=30.0, turns=2.5):
    """CAD positions (n, 3) mm of a helix of spheres about the holder's z axis."""
    s = np.linspace(0, 1, n)
    ang = 2 * np.pi * turns * s
    return np.column_stack([radius * np.cos(ang), radius * np.sin(ang), (s - 0.5) * height])


def robot_helix(seed=0, *, rows=640, cols=640, pitch=0.2, sod=250.0, sdd=750.0, diameter=0.8, mu=0.5,
                n_frames=120, dt=0.5, n_spheres=50, offset_mm=1.0, offset_deg=0.5, jitter_mm=0.02,
                clusters=3, dense_holder=False, body="solid", max_offset: tuple | None = None,
                trajectory: str = "turntable", sweep_deg: float = 60.0) -> Scenario:
    """A robot arm carrying a holder with a helix of spheres (Pekel et al.).

    The flange joint turns the holder through 360 deg while the other joints
    wiggle slightly; true poses deviate from the joint log by a few pose
    clusters (``offset_mm``, ``offset_deg``; or norms of 70-97 % of
    ``max_offset`` = (mm, deg)) plus frame jitter. ``body``:
    'solid' (a PMMA cylinder enclosing the helix), 'tube' (a thin-walled tube
    inside the helix: strong ridges, a clutter test) or 'none'.
    ``trajectory``: 'turntable' (the other joints only wiggle) or 'sweep':
    the elbow swivels once through +-``sweep_deg`` about the shoulder-wrist
    line (joint 3 leads, the others follow by inverse kinematics) while the
    holder turns in place, so the arm's configuration, its gravity load,
    its joint speeds and their directions all change during the scan -
    what robot errors need to be told apart; its one pose cluster is a
    registration error of the arm's base.
    """
    rng = np.random.default_rng(seed)
    nominal = ConeGeometry.nominal(sod=sod, sdd=sdd, shape=(rows, cols), pixel_pitch=(pitch, pitch))
    truth_geom = _perturbed_geometry(nominal, rng, 0.3, 1.0, 0.2)
    flange = RigidTransform(np.eye(3), np.array([0.0, 0.0, 107.0]))
    robot0 = DHRobot(np.array(ROBOT_DH, float), flange, RigidTransform.identity())
    T_home = robot0.transforms(ROBOT_HOME[None])[0]
    target = RigidTransform(np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]), np.zeros(3))
    base = target @ T_home.inverse()
    robot = DHRobot(robot0.dh, flange, base)
    q = np.tile(ROBOT_HOME, (n_frames, 1))
    q[:, 6] = np.arange(n_frames) * 360.0 / n_frames
    ph = rng.uniform(0, 2 * np.pi, 6)
    if trajectory == "sweep":
        q = _elbow_sweep(robot, q, sweep_deg)
    elif trajectory == "turntable":
        for j in range(6):
            q[:, j] += 0.15 * np.sin(2 * np.pi * np.arange(n_frames) / n_frames * (j % 3 + 1) + ph[j])
    else:
        raise ValueError(f"trajectory must be turntable or sweep, not {trajectory!r}")
    times = np.arange(n_frames) * dt
    T_log = robot.transforms(q)
    # pose clusters: the arm settles into one of a few repeatable errors
    # (a sweep has one: the base's registration error)
    if trajectory == "sweep":
        clusters = 1
    cl_t = rng.normal(0, offset_mm, (clusters, 3))
    cl_r = np.deg2rad(rng.normal(0, offset_deg, (clusters, 3)))
    if max_offset is not None:
        # clusters near a bound (mm, deg): a stress test of the prior
        for arr, bound in ((cl_t, max_offset[0]), (cl_r, np.deg2rad(max_offset[1]))):
            arr /= np.linalg.norm(arr, axis=1, keepdims=True)
            arr *= rng.uniform(0.7, 0.97, (clusters, 1)) * bound
    which = rng.integers(0, clusters, n_frames)
    dR = rotvec_to_matrix(cl_r[which] + np.deg2rad(0.01) * rng.normal(size=(n_frames, 3)))
    dt_ = cl_t[which] + jitter_mm * rng.normal(size=(n_frames, 3))
    # each error turns the holder about its own (logged) position, then shifts it
    centre = T_log.t
    placement = RigidTransform(dR, centre + dt_ - (dR @ centre[..., None])[..., 0])
    world = World.start(times, q, robot=robot, placement=placement)
    cad = helix_phantom(n_spheres)
    robot_cfg = {"dh": ROBOT_DH, "flange": flange.matrix().tolist(), "base": base.matrix().tolist()}
    cfg = _config("robot", rows, cols, pitch, sod, sdd, diameter, robot=robot_cfg, phantom="phantom.csv")
    ids = np.arange(1, n_spheres + 1)
    zaxis = np.array([0, 0, 1.0])
    solids = {"solid": [Cylinder(np.zeros(3), zaxis, 15.0, 19.0, 0.02)],
              "tube": [Cylinder(np.zeros(3), zaxis, 9.0, 20.0, 0.02), Cylinder(np.zeros(3), zaxis, 7.0, 20.0, -0.02)],
              "none": []}[body]
    if dense_holder:
        solids.append(Cylinder(np.array([0, 0, 22.0]), np.array([0, 0, 1.0]), 6.0, 4.0, 0.6))
    sc = Scenario("robot", cfg, times, q, world, truth_geom, ids, cad, np.full(n_spheres, diameter / 2),
                  np.full(n_spheres, mu), sample_solids=solids, background=(0.2, 0.1, 0.05), phantom=(ids, cad))
    return sc


def circular_scan(seed=0, *, rows=256, cols=256, pitch=0.4, sod=300.0, sdd=600.0, n_frames=360,
                  shift_px=(6.0, -4.0), rotation_deg=(1.0, 1.5, -1.0), dense_holder=False,
                  random_misalignment=False, truncation: str | None = None) -> Scenario:
    """A circular scan of an ellipsoid phantom with a misaligned detector.

    Misalignment relative to the nominal geometry: detector shift along u
    and v (px), in-plane rotation ``eta`` about the detector normal, and
    tilts ``theta`` about u and ``phi`` about v (deg), all about the
    detector centre. ``rotation_deg = (eta, theta, phi)`` (see
    :mod:`conecal.geometry.misalignment`). ``truncation``: ``"axial"``
    makes the object taller than the detector sees, ``"transaxial"`` wider.
    """
    rng = np.random.default_rng(seed)
    nominal = ConeGeometry.nominal(sod=sod, sdd=sdd, shape=(rows, cols), pixel_pitch=(pitch, pitch))
    if random_misalignment:
        shift_px = tuple(rng.uniform(-15, 15, 2))
        rotation_deg = tuple(rng.uniform(-3, 3, 3))
    truth_geom = misaligned(nominal, (*shift_px, *rotation_deg))
    fov = 0.45 * min(rows, cols) * pitch * sod / sdd
    body = {None: [0.8, 0.9, 0.75], "axial": [0.8, 1.6, 0.75], "transaxial": [1.25, 0.9, 1.15]}
    if truncation not in body:
        raise ValueError(f"truncation must be axial or transaxial, not {truncation!r}")
    solids = [Ellipsoid(np.zeros(3), np.array(body[truncation]) * fov, np.eye(3), 0.02)]
    for _ in range(10):
        c = rng.uniform(-0.45, 0.45, 3) * fov
        ax = rng.uniform(0.05, 0.25, 3) * fov
        Rr = rotvec_to_matrix(rng.normal(0, 1, 3))
        solids.append(Ellipsoid(c, ax, Rr, float(rng.choice([-1, 1]) * rng.uniform(0.005, 0.03))))
    if dense_holder:
        solids.append(Cylinder(np.array([0.0, 1.1 * fov, 0.0]), np.array([0, 1.0, 0]), 0.35 * fov, 0.4 * fov, 0.15))
    theta = np.arange(n_frames) * 360.0 / n_frames
    axes = [{"name": "theta", "type": "rotary", "direction": [0.0, 1.0, 0.0], "point": [0.0, 0.0, 0.0]}]
    chain = Chain((RotaryAxis("theta", [0, 1.0, 0], [0, 0, 0]),))
    times = np.arange(n_frames) * 0.1
    world = World.start(times, theta[:, None], chain=chain)
    cfg = _config("circular", rows, cols, pitch, sod, sdd, None, axes=axes)
    sc = Scenario("circular", cfg, times, theta[:, None], world, truth_geom, np.zeros(0, int), np.zeros((0, 3)),
                  np.zeros(0), np.zeros(0), sample_solids=solids, photons=1e5, blur_px=0.3, supersample=2)
    sc.truth_extra["truncation"] = truncation
    sc.truth_extra["misalignment"] = {"shift_u_px": float(shift_px[0]), "shift_v_px": float(shift_px[1]),
                                      "eta_deg": float(rotation_deg[0]), "theta_deg": float(rotation_deg[1]),
                                      "phi_deg": float(rotation_deg[2])}
    return sc


BUILDERS = {"linear": linear_raster, "rotation": rotation_scan, "robot": robot_helix, "circular": circular_scan}


def marker_truth(sc: Scenario, k: int, T: RigidTransform) -> list[dict]:
    """Exact per-frame marker records: what ``detect`` should measure."""
    g = sc.frame_geometry(k)
    im = sc.imaging_at(k)
    out = []
    rows, cols = g.shape
    for sid, p, r in zip(sc.sphere_ids, sc.sphere_positions, sc.sphere_radii):
        X = T.apply(p)
        # distortion moves the shadow as a whole to first order
        cen = im.distort(shadow_centroid(g, X, r), g.shape)
        proj = im.distort(g.project(X), g.shape)
        dpx = float(shadow_diameter_px(g, X, r))
        rad = dpx / 2
        inside = bool(rad <= cen[0] <= cols - 1 - rad and rad <= cen[1] <= rows - 1 - rad)
        out.append({"id": int(sid), "lab": X.tolist(), "centroid": cen.tolist(), "projection": proj.tolist(),
                    "diameter_px": dpx, "inside": inside})
    return out
