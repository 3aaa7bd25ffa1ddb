"""Per-frame 6-DoF pose of a marker holder carried by a robot (Pekel et al.).

For each frame the holder's spheres (``phantom.csv``, holder frame, mm) are
projected from an initial pose (the robot's joint log through its DH model,
or the previous frame's fit), the image offset between prediction and
detections is found by voting, detections are given sphere ids by
assignment within a gate, and the pose (rotation vector and translation,
``P_lab = R p + t``) is fitted by least squares with analytic Jacobians on
the identified reprojection errors, weighted by ``detect``'s sigmas. A
frame that cannot be trusted is rejected with its reason, never returned
as ``ok``.

Correspondences are to sphere ids, not to the nearest point of the
analytic helix: a helix is nearly invariant under a small screw motion,
so a nearest-helix-point cost barely constrains one pose direction.
The same symmetry makes a start off by one sphere's screw step (about
18 deg for the usual holder) fit all but the end spheres; the prior rules
that out, and a frame whose screw neighbour explains more spheres than the
fitted pose is rejected as a prior violation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment

from ..documents import status
from ..documents.status import OK, Status
from ..geometry import ConeGeometry, RigidTransform, matrix_to_rotvec, rotvec_to_matrix
from ..geometry.cone import so3_left_jacobian
from ..geometry.rotations import skew
from ..geometry.sphere import hidden_behind, shadow_bias
from .core import Parameter, solve


@dataclass(frozen=True)
class PoseOptions:
    """max_rms_px: rejection threshold on the fitted frame's reprojection RMS.
    prior_mm, prior_deg: how far the true pose may be from the initial one.
    gate_px: assignment gate after the first fit. min_spheres: fewest
    identified spheres for a pose (and at least ``min_fraction`` of those
    predicted on the detector)."""

    max_rms_px: float = 0.5
    prior_mm: float = 3.0
    prior_deg: float = 2.0
    gate_px: float = 1.5
    min_spheres: int = 8
    min_fraction: float = 0.3
    # a frame the log cannot start is searched for from the pattern (within
    # 45 deg of the log's orientation) and fitted again from what is found
    rescue: bool = True


@dataclass
class FramePose:
    frame: int
    status: Status
    R: np.ndarray
    t: np.ndarray
    sigma_rotation_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    sigma_translation_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    rms_px: float = float("nan")
    n_spheres: int = 0
    ids: list = field(default_factory=list)
    residual_px: np.ndarray | None = None
    found_by: str = "log"          # where the fit started: the log, or the pattern search
    hidden: list = field(default_factory=list)   # [id, id hiding it] (geometry.sphere.hidden_behind)


class PoseProblem:
    """Projection of holder points under a pose perturbation (w, dt) of (R0, t0).

    The cone-beam shadow offset (a few thousandths of a px for holder spheres)
    is evaluated at the initial pose (``refresh``) and held fixed while the
    pose moves by at most millimetres (it changes by ~1e-4 px per mm).
    """

    def __init__(self, geometry: ConeGeometry, points: np.ndarray, radius: float, R0, t0):
        self.g, self.p, self.r = geometry, points, radius
        self.R0, self.t0 = np.asarray(R0), np.asarray(t0)
        self.bias = np.zeros((len(points), 2))

    def transform(self, x):
        R = rotvec_to_matrix(x[:3]) @ self.R0
        return R, self.t0 + x[3:]

    def refresh(self, x):
        # holder spheres are tiny against their distance to the source: the
        # 36-point rule is exact to ~1e-9 px here
        R, t = self.transform(x)
        self.bias = shadow_bias(self.g, self.p @ R.T + t, self.r, coarse=True)

    def predict(self, x, idx):
        R, t = self.transform(x)
        return self.g.project(self.p[idx] @ R.T + t) + self.bias[idx]

    def jacobian(self, x, idx):
        R, t = self.transform(x)
        Rp = self.p[idx] @ R.T
        _, Jx = self.g.project_jacobian(Rp + t)
        J = np.empty((len(idx), 2, 6))
        J[:, :, :3] = Jx @ (-skew(Rp) @ so3_left_jacobian(x[:3]))
        J[:, :, 3:] = Jx
        return J


POSE_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")


def _solve_stage(prob, x0, r, c, det_xy, det_sigma, loss, tol=1e-8):
    sig = det_sigma[c][:, None]

    def res_fn(x):
        return ((det_xy[c] - prob.predict(x, r)) / sig).ravel()

    def jac_fn(x):
        return -(prob.jacobian(x, r) / sig[:, :, None]).reshape(-1, 6)

    params = [Parameter(n, v, scale=s_, undetermined_sigma=np.inf)
              for n, v, s_ in zip(POSE_NAMES, x0, (1e-3, 1e-3, 1e-3, 0.01, 0.01, 0.01))]
    # 1e-8: a pose to ~1e-8 of its scale (nm, nrad) is far below the noise
    return solve(params, res_fn, jac_fn, loss=loss, f_scale=5.0, max_nfev=50, tol=tol)


def _vote_peaks(pred: np.ndarray, det: np.ndarray, max_shift: float, cell: float, k: int = 3):
    """Up to ``k`` well separated image offsets det - pred with the most
    votes (a 2D histogram of all pairs within ``max_shift``): (offset, votes)."""
    d = (det[:, None, :] - pred[None, :, :]).reshape(-1, 2)
    d = d[np.hypot(d[:, 0], d[:, 1]) <= max_shift]
    if len(d) == 0:
        return []
    nb = int(np.ceil(2 * max_shift / cell)) + 1
    H, xe, ye = np.histogram2d(d[:, 0], d[:, 1], bins=nb, range=[[-max_shift, max_shift]] * 2)
    # votes in 2x2 neighbourhoods: an offset on a cell border still counts once
    H2 = H[:-1, :-1] + H[1:, :-1] + H[:-1, 1:] + H[1:, 1:]
    out = []
    for _ in range(k):
        i, j = np.unravel_index(np.argmax(H2), H2.shape)
        if H2[i, j] <= 0:
            break
        sel = (d[:, 0] >= xe[i]) & (d[:, 0] < xe[i + 2]) & (d[:, 1] >= ye[j]) & (d[:, 1] < ye[j + 2])
        out.append((np.median(d[sel], axis=0), float(H2[i, j])))
        H2[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3] = 0
    return out


def _assign(pred, det, gate):
    cost = np.hypot(pred[:, None, 0] - det[None, :, 0], pred[:, None, 1] - det[None, :, 1])
    r, c = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
    ok = cost[r, c] <= gate
    return r[ok], c[ok]


def helix_screw(helix: dict) -> RigidTransform:
    """The holder-frame screw motion that carries each sphere of a uniform
    helix onto the next one (rotation by one step about the axis, rise by
    the pitch's share along it)."""
    d = np.asarray(helix["axis_direction"])
    c = np.asarray(helix["axis_point"])
    step = np.deg2rad(helix["step_deg"])
    R = rotvec_to_matrix(d * step)
    rise = (1 if helix["handedness"] == "right" else -1) * helix["pitch_mm_per_turn"] * step / (2 * np.pi)
    return RigidTransform(R, c - R @ c + rise * d)


def fit_frame(frame: int, geometry: ConeGeometry, points: np.ndarray, ids: np.ndarray, radius: float,
              det_xy: np.ndarray, det_sigma: np.ndarray, R0, t0, opt: PoseOptions,
              screw: RigidTransform | None = None) -> FramePose:
    """Pose of one frame from its detections, starting at (R0, t0).

    Up to three image offsets voted from all detection/prediction pairs are
    each carried through a robust fit, a tight re-assignment and a final
    fit; the hypothesis identifying most spheres wins. Two hypotheses that
    fit about as well with different poses make the frame ambiguous.
    """
    rejected = FramePose(frame, OK, np.asarray(R0), np.asarray(t0))
    if len(det_xy) < opt.min_spheres:
        rejected.status = status.rejected("few_markers", f"{len(det_xy)} markers detected, fewer than {opt.min_spheres}")
        return rejected
    prob = PoseProblem(geometry, points, radius, R0, t0)
    allidx = np.arange(len(points))
    prob.refresh(np.zeros(6))
    pred = prob.predict(np.zeros(6), allidx)
    rows, cols = geometry.shape
    mag = geometry.magnification(np.asarray(t0)) / geometry.pixel_pitch[0]
    m = 1.5 * radius * mag
    on_det = (pred[:, 0] > m) & (pred[:, 0] < cols - 1 - m) & (pred[:, 1] > m) & (pred[:, 1] < rows - 1 - m)
    n_vis = int(on_det.sum())
    # how far the image may move for the prior's pose error (px)
    reach = np.linalg.norm(points - points.mean(0), axis=1).max()
    max_shift = 1.5 * (opt.prior_mm + np.deg2rad(opt.prior_deg) * reach) * mag
    peaks = _vote_peaks(pred[on_det], det_xy, max_shift, cell=max(2.0, radius * mag))
    gate0 = max(4.0, 1.2 * radius * mag)

    def within_prior(x):
        dang = np.degrees(np.linalg.norm(x[:3]))
        return dang <= 1.5 * opt.prior_deg and np.linalg.norm(x[3:]) <= 1.5 * opt.prior_mm

    hyps, beyond = [], 0
    for shift, votes in peaks:
        if hyps and votes < 0.6 * peaks[0][1]:
            break  # a weak peak: the helix's screw neighbours, not a rival
        r, c = _assign(pred + shift, det_xy, gate0)
        if len(r) < 6:
            continue
        # the voted image offset, as a lateral move of the holder, is the start
        x = np.zeros(6)
        x[3:] = (shift[0] * geometry.u + shift[1] * geometry.v) / mag   # px -> mm at the holder
        # a rough robust fit: the tight one follows after re-assignment
        x = _solve_stage(prob, x, r, c, det_xy, det_sigma, "soft_l1", tol=1e-4).x
        if not within_prior(x):
            beyond += 1  # e.g. the helix shifted by one sphere: a screw motion of ~18 deg
            continue
        prev = None
        for _ in range(3):
            r, c = _assign(prob.predict(x, allidx), det_xy, opt.gate_px)
            if len(r) < 6 or (prev is not None and np.array_equal(prev, r)):
                break
            res = _solve_stage(prob, x, r, c, det_xy, det_sigma, "linear")
            x, prev = res.x, r
        if prev is None or len(r) < 6 or not within_prior(x):
            continue
        resid = det_xy[c] - prob.predict(x, r)
        hyps.append((len(r), float(np.sqrt(np.mean(resid**2))), x, res, r, c, resid))
    if not hyps:
        rejected.status = (status.rejected("beyond_prior", "only poses beyond the prior fit") if beyond else
                           status.rejected("no_pose", "no consistent set of spheres near the initial pose"))
        return rejected
    hyps.sort(key=lambda h: (-h[0], h[1]))
    n, rms, x, res, r, c, resid = hyps[0]
    for n2, rms2, x2, *_ in hyps[1:]:
        differs = np.degrees(np.linalg.norm(x2[:3] - x[:3])) > 0.05 or np.linalg.norm(x2[3:] - x[3:]) > 0.05
        if differs and n2 >= 0.8 * n and rms2 <= opt.max_rms_px:
            rejected.status = status.rejected(
                "ambiguous_identity", f"ambiguous, two poses within the prior fit {n} and {n2} spheres")
            return rejected
    if n < max(opt.min_spheres, opt.min_fraction * n_vis):
        rejected.status = status.rejected("few_identified", f"{n} spheres identified of {n_vis} on the detector")
        return rejected
    if screw is not None:
        # A helix is nearly invariant under its own screw: a start off by one
        # sphere's step gives a pose that fits all but the end spheres. The
        # neighbours along the screw must not explain the image better.
        Rb, tb = prob.transform(x)
        for k in (1, -1, 2, -2):
            S = screw if k > 0 else screw.inverse()
            for _ in range(abs(k) - 1):
                S = S @ (screw if k > 0 else screw.inverse())
            Xk = (S.apply(points)) @ Rb.T + tb
            rk, _ = _assign(geometry.project(Xk) + prob.bias, det_xy, opt.gate_px)
            # as many spheres: the prior decides (the neighbour is a whole step away);
            # more: the prior was wrong, and this pose with it
            if len(rk) > n:
                rejected.status = status.rejected("screw_shift", f"the helix fits better shifted by {k:+d} sphere(s): "
                                                  f"the initial pose is off by more than the prior")
                return rejected
    R, t = prob.transform(x)
    sd = res.sigma
    out = FramePose(frame, OK, R, t, np.degrees(sd[:3]), sd[3:], rms, n, [int(ids[i]) for i in r], resid)
    seen = np.zeros(len(points), bool)
    seen[r] = True
    out.hidden = hidden_behind(geometry, points @ R.T + t, radius, seen, ids)
    if rms > opt.max_rms_px:
        out.status = status.rejected("residual", f"reprojection RMS {rms:.3f} px above {opt.max_rms_px} px")
    return out


def fit_helix(points: np.ndarray) -> dict:
    """The helix that best fits the holder's CAD points (in id order).

    Parameters: axis (direction, a point), radius (mm), pitch (mm per turn),
    phase and angular step per sphere (deg). Returns them with the RMS and
    per-sphere 3D residuals (mm), to catch a mis-built holder.
    """
    P = np.asarray(points, float)
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c)
    # the axis is the direction along which the points do not lie on a circle: try the three principal axes
    best = None
    for d0 in vt:
        e1 = np.cross(d0, [1.0, 0, 0]) if abs(d0[0]) < 0.9 else np.cross(d0, [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d0, e1)
        a, b = (P - c) @ e1, (P - c) @ e2
        A = np.column_stack([a, b, np.ones_like(a)])
        sol = np.linalg.lstsq(A, a * a + b * b, rcond=None)[0]
        ca, cb = sol[0] / 2, sol[1] / 2
        rad = np.sqrt(sol[2] + ca * ca + cb * cb)
        misfit = np.std(np.hypot(a - ca, b - cb))
        if best is None or misfit < best[0]:
            best = (misfit, d0, e1, e2, ca, cb, rad)
    _, d0, e1, e2, ca, cb, rad = best
    centre = c + ca * e1 + cb * e2
    ang = np.unwrap(np.arctan2((P - centre) @ e2, (P - centre) @ e1))
    k = np.arange(len(P))
    step, phase = np.polyfit(k, ang, 1)
    z0 = (P - centre) @ d0
    zslope, zoff = np.polyfit(ang, z0, 1)

    def model(q):
        d = q[0:3] / np.linalg.norm(q[0:3])
        u1 = e1 - d * (d @ e1)
        u1 /= np.linalg.norm(u1)
        u2 = np.cross(d, u1)
        th = q[7] + q[8] * k
        return (q[3:6] + q[6] * (np.cos(th)[:, None] * u1 + np.sin(th)[:, None] * u2)
                + (q[9] * th + q[10])[:, None] * d)

    q0 = np.concatenate([d0, centre, [rad, phase, step, zslope, zoff]])
    sol = least_squares(lambda q: (model(q) - P).ravel(), q0)
    q = sol.x
    resid = np.linalg.norm(model(q) - P, axis=1)
    d = q[0:3] / np.linalg.norm(q[0:3])
    pitch = abs(q[9]) * 2 * np.pi
    return {"axis_direction": d.tolist(), "axis_point": q[3:6].tolist(), "radius_mm": float(abs(q[6])),
            "pitch_mm_per_turn": float(pitch), "phase_deg": float(np.degrees(q[7])),
            "step_deg": float(np.degrees(q[8])), "handedness": "right" if q[9] > 0 else "left",
            "rms_mm": float(np.sqrt(np.mean(resid**2))), "residual_mm": resid.tolist()}


def placement_errors(poses: list[FramePose], R_log: np.ndarray, t_log: np.ndarray) -> dict:
    """The robot's placement error per frame: calibrated pose against the
    joint-log pose (translation offset in mm, lab frame; rotation angle in
    deg), and its statistics over the ``ok`` frames."""
    per = []
    for p, Rl, tl in zip(poses, R_log, t_log):
        if not p.status.ok:
            per.append(None)
            continue
        dR = p.R @ Rl.T
        w = matrix_to_rotvec(dR)
        per.append({"offset_mm": (p.t - tl).tolist(), "rotation_deg": float(np.degrees(np.linalg.norm(w))),
                    "rotation_vector_deg": np.degrees(w).tolist()})
    return {"frames": per, "summary": placement_summary(per)}


def placement_summary(per: list[dict | None]) -> dict | None:
    """Statistics of the per-frame placement errors of the ``ok`` frames (None: no frame)."""
    ok = [e for e in per if e is not None]
    if not ok:
        return None
    off = np.array([e["offset_mm"] for e in ok])
    rot = np.array([e["rotation_deg"] for e in ok])
    return {"offset_mean_mm": off.mean(0).tolist(), "offset_std_mm": off.std(0).tolist(),
            "offset_max_mm": float(np.linalg.norm(off, axis=1).max()),
            "rotation_mean_deg": float(rot.mean()), "rotation_std_deg": float(rot.std()),
            "rotation_max_deg": float(rot.max())}


def fit_poses(scan, markers_doc: dict, geometry: ConeGeometry, opt: PoseOptions, *, initial: str = "log",
              use_flagged: bool = False, progress=None, frames: set[int] | None = None,
              rescue=None) -> tuple[list[FramePose], np.ndarray, np.ndarray]:
    """Poses of every frame of a robot scan. ``initial``: 'log' (the joint
    log through the DH model) or 'previous' (the last good frame's placement
    error carried to this frame's log pose; the log where there is none).
    ``frames``: only these frame numbers (a part of the scan). ``rescue``:
    what to try on a frame the log's pose could not start (with
    ``opt.rescue``; :func:`conecal.calib.rescue.rescue_frame`, the pattern
    search, given by the caller: ``fit`` does not depend on ``calib``).
    Returns the poses and the joint-log rotations and translations (of
    those frames)."""
    from ..errors import InputError
    from .markers import BIASING_FLAGS

    if scan.phantom is None:
        raise InputError(f"{scan.root / 'scan.yaml'}: markers.phantom: fit-pose needs the holder's phantom.csv")
    T = scan.nominal_transforms()
    pts, ids = scan.phantom.positions, scan.phantom.ids
    radius = scan.config.markers.diameter / 2
    by_frame = {int(f["frame"]): f["markers"] for f in markers_doc.get("frames", [])}
    order = np.argsort(ids)
    screw = helix_screw(fit_helix(pts[order]))
    poses = []
    carry = None  # (R_err, t_err): last good pose relative to its log pose
    rows = [k for k, f in enumerate(scan.log.frame) if frames is None or int(f) in frames]
    for n_done, k in enumerate(rows, 1):
        frame = scan.log.frame[k]
        ms = [m for m in by_frame.get(int(frame), []) if use_flagged or not set(m.get("flags", [])) & set(BIASING_FLAGS)]
        xy = np.array([[m["x"], m["y"]] for m in ms]).reshape(-1, 2)
        sg = np.array([m["sigma"] for m in ms])
        R0, t0 = T.R[k], T.t[k]
        if initial == "previous" and carry is not None:
            R0, t0 = carry[0] @ R0, carry[0] @ (t0 - carry[2]) + carry[2] + carry[1]
        p = fit_frame(int(frame), geometry, pts, ids, radius, xy, sg, R0, t0, opt, screw)
        if not p.status.ok and initial == "previous" and carry is not None:
            p = fit_frame(int(frame), geometry, pts, ids, radius, xy, sg, T.R[k], T.t[k], opt, screw)
        if not p.status.ok and opt.rescue and rescue is not None and len(xy) >= opt.min_spheres:
            p = rescue(int(frame), geometry, pts, ids, radius, xy, sg, T.R[k], T.t[k], opt, screw, p)
        if p.status.ok:
            dR = p.R @ T.R[k].T
            carry = (dR, p.t - T.t[k], T.t[k])
        poses.append(p)
        if progress:
            progress(n_done, len(rows))
    return poses, T.R[rows], T.t[rows]



def refine_geometry(geometry: ConeGeometry, poses: list[FramePose], points: np.ndarray, ids: np.ndarray,
                    radius: float, markers_by_frame: dict, gate_px: float = 1.5):
    """One bundle adjustment of the detector centre and every ok pose.

    A rigid motion of source, detector and all poses together changes no
    projection, so the lab frame stays where the given geometry puts it:
    source position and detector orientation are held, and the detector
    centre (principal point and source-to-detector distance, mm) is refined
    jointly with all poses. Returns (geometry, FitResult, refined poses).
    """
    from .detector_params import NAMES as DNAMES, DetectorParams

    dp = DetectorParams(geometry)
    ok = [p for p in poses if p.status.ok]
    obs_f, obs_s, obs_xy, obs_sig = [], [], [], []
    for f, p in enumerate(ok):
        ms = markers_by_frame[p.frame]
        xy = np.array([[m["x"], m["y"]] for m in ms]).reshape(-1, 2)
        pred = geometry.project(points @ p.R.T + p.t)
        r, c = _assign(pred, xy, gate_px)
        for ri, ci in zip(r, c):
            obs_f.append(f)
            obs_s.append(ri)
            obs_xy.append(xy[ci])
            obs_sig.append(ms[ci]["sigma"])
    obs_f, obs_s = np.array(obs_f), np.array(obs_s)
    obs_xy, obs_sig = np.array(obs_xy), np.array(obs_sig)
    nf = len(ok)
    R0 = np.array([p.R for p in ok])
    t0 = np.array([p.t for p in ok])
    bias = shadow_bias(geometry, np.einsum("mij,mj->mi", R0[obs_f], points[obs_s]) + t0[obs_f], radius)

    def unpack(x):
        g = dp.geometry(np.concatenate([np.zeros(3), x[:3], np.zeros(3)]))
        w = x[3:].reshape(nf, 6)
        R = np.einsum("nij,njk->nik", np.array([rotvec_to_matrix(v) for v in w[:, :3]]), R0)
        return g, R, t0 + w[:, 3:]

    def residuals(x):
        g, R, t = unpack(x)
        X = np.einsum("mij,mj->mi", R[obs_f], points[obs_s]) + t[obs_f]
        return ((obs_xy - g.project(X) - bias) / obs_sig[:, None]).ravel()

    def jacobian(x):
        g, R, t = unpack(x)
        Rp = np.einsum("mij,mj->mi", R[obs_f], points[obs_s])
        X = Rp + t[obs_f]
        _, Jx = g.project_jacobian(X)
        J = np.zeros((len(obs_f), 2, x.size))
        x9 = np.concatenate([np.zeros(3), x[:3], np.zeros(3)])
        J[:, :, :3] = dp.jacobian(g, X, x9)[:, :, 3:6]
        w = x[3:].reshape(nf, 6)
        Jl = so3_left_jacobian(w[:, :3])[obs_f]
        Jrot = Jx @ (-skew(Rp) @ Jl)
        for k in range(3):
            J[np.arange(len(obs_f)), :, 3 + 6 * obs_f + k] = Jrot[:, :, k]
            J[np.arange(len(obs_f)), :, 3 + 6 * obs_f + 3 + k] = Jx[:, :, k]
        return -(J / obs_sig[:, None, None]).reshape(-1, x.size)

    names = list(DNAMES[3:6]) + [f"frame{p.frame}_{n}" for p in ok for n in POSE_NAMES]
    params = [Parameter(n, 0.0, scale=0.01 if i < 3 else (1e-3 if (i - 3) % 6 < 3 else 0.01),
                        unit="mm" if i < 3 or (i - 3) % 6 >= 3 else "rad", undetermined_sigma=10.0)
              for i, n in enumerate(names)]
    res = solve(params, residuals, jacobian, tol=1e-10)
    g, R, t = unpack(res.x)
    refined = []
    it = iter(range(nf))
    for p in poses:
        if not p.status.ok:
            refined.append(p)
            continue
        f = next(it)
        sd = res.sigma[3 + 6 * f:9 + 6 * f]
        sel = obs_f == f
        resid = (residuals(res.x).reshape(-1, 2) * obs_sig[:, None])[sel]
        refined.append(FramePose(p.frame, OK, R[f], t[f], np.degrees(sd[:3]), sd[3:],
                                 float(np.sqrt(np.mean(resid**2))), int(sel.sum()), p.ids, resid, p.found_by))
    return g, res, refined
