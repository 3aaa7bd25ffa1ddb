"""Independent simulator of rotation-stage cone-beam CT marker scans with
"mismatch effects" (form variants).

Written against /work/shared/SCAN_FORMAT.md only, as an "other simulator"
independent of the conecal code.  Usage::

    from formvariants import CASES, make_case
    label = make_case("wobble_nod", seed=3, out=pathlib.Path("/tmp/x"))

``make_case`` writes ``out/scan/{scan.yaml,log.csv,projections.tif}``,
``out/geometry.json`` (the TRUE geometry at t=0), ``out/markers.json``
(noisy true marker centres, sigma 0.02 px) and ``out/effect.json`` (the
drawn effect parameters, for diagnostics only), and returns the label
``{"family", "variable", "nameable", "ambiguous_with"}``.

Cases (``CASES``): clean; wobble_nod (axis tilt about x ~ sin theta);
runout_h2 (axis point x-z at 2 theta); warmup_drift (source x, exponential
in time); latency_jitter (encoder lag, two forward speeds, jitter);
encoder_slip (angle step at one frame, unnameable); wobble_precess (axis
direction precessing against the stage's turn); runout_h3 (axis point at
harmonic 3 or 4); two_speed_fb (forward/back at two speeds with encoder
latency, ambiguous with backlash); backlash_fb (forward/back at one speed,
angle offset on the return leg, ambiguous with latency); intensifier
(static detector field: off-centre pincushion + decentring);
drift_plus_wobble (warm-up drift and nodding wobble); axis_knock (axis tilt
jumps at one frame, unnameable); encoder_eccentric (once-per-turn angle
error, unnameable).

Random streams: ``SeedSequence(seed)`` is split into independent streams for
the base geometry/phantom, the marker noise and the effect magnitudes, so for
one seed every case shares the same geometry, phantom and noise draws, and
a case's markers differ from "clean" only by its effect.

Deviation from the brief: with sod 100, sdd 500 (magnification ~5) and a
102.4 mm wide detector, spheres at radius 12 mm / |y| 10 mm would leave the
detector (12 mm near the source projects ~60 mm off centre), so the phantom
is drawn within radius 3..8.5 mm of the axis and |y| <= 7.5 mm, which keeps
every sphere image fully inside the 512x512 detector in every frame.
"""
from __future__ import annotations

import csv
import json
import os
import pathlib

import numpy as np

ROWS = COLS = 512
PITCH = 0.2          # mm
SOD, SDD = 100.0, 500.0
N_FRAMES = 90
STEP_DEG = 4.0       # 90 frames over 360 deg
DT = 1.0             # s per frame
N_SPHERES = 6
DIAMETER = 2.0       # mm
SIGMA_PX = 0.02      # px, 1 sigma marker noise
MU = 0.5             # 1/mm, attenuation coefficient used for images=True


# ---------------------------------------------------------------- geometry
def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def base_geometry(rng):
    """True source, detector (origin, u, v) and phantom for one seed."""
    d = rng.normal(size=3)
    source = np.array([0.0, 0.0, -SOD]) + 0.5 * rng.uniform() * d / np.linalg.norm(d)
    tilts = np.deg2rad(rng.uniform(-0.3, 0.3, size=3))
    R = rot_z(tilts[2]) @ rot_y(tilts[1]) @ rot_x(tilts[0])
    u, v = R[:, 0], R[:, 1]
    n = np.cross(u, v)
    # detector plane through (0, 0, SDD - SOD) (plus a small random shift
    # along z); the principal centre sits where the axis point projects,
    # moved by a few px so that the axis projects NEAR the centre column.
    centre_plane = np.array([0.0, 0.0, SDD - SOD + rng.uniform(-1.0, 1.0)])
    axis_on_det = _intersect(source, np.zeros(3), centre_plane, n)
    off = rng.uniform(-3.0, 3.0, size=2) * PITCH     # mm in-plane
    centre = axis_on_det + off[0] * u + off[1] * v
    half = (COLS - 1) / 2 * PITCH, (ROWS - 1) / 2 * PITCH
    origin = centre - half[0] * u - half[1] * v
    # phantom: spheres in the stage frame, well separated
    pts = []
    while len(pts) < N_SPHERES:
        r = np.sqrt(rng.uniform(3.0 ** 2, 8.5 ** 2))
        phi = rng.uniform(0, 2 * np.pi)
        p = np.array([r * np.cos(phi), rng.uniform(-7.5, 7.5), r * np.sin(phi)])
        if all(np.linalg.norm(p - q) > 3.0 for q in pts):
            pts.append(p)
    return dict(source=source, origin=origin, u=u, v=v, phantom=np.array(pts))


def _intersect(S, P, O, n):
    d = P - S
    t = np.dot(O - S, n) / np.dot(d, n)
    return S + t * d


def project(S, P, g):
    """Pinhole projection of lab points P (N,3) from source S -> (N,2) (c, r)."""
    n = np.cross(g["u"], g["v"])
    d = P - S
    t = ((g["origin"] - S) @ n) / (d @ n)
    X = S + t[:, None] * d - g["origin"]
    return np.stack([X @ g["u"] / PITCH, X @ g["v"] / PITCH], axis=1)


# ---------------------------------------------------------------- effects
# Each case maps (rng, k, t, theta_log_deg) -> per-frame perturbation arrays:
#   dtheta (deg added to the logged angle to give the true angle),
#   tilt_x (deg, tilt about lab x applied after R_y), shift (axis point, mm),
#   src (source displacement, mm), plus the label and the drawn parameters.
#   Added later (zero / None by default, so the first six cases are unchanged):
#   tilt_z (deg, tilt about lab z, applied after tilt_x), det_field (None or a
#   static detector displacement field f(uv (N,2) px) -> (N,2) px added to the
#   projected marker centres).
def _none(k):
    n = len(k)
    return dict(dtheta=np.zeros(n), tilt_x=np.zeros(n),
                shift=np.zeros((n, 3)), src=np.zeros((n, 3)),
                tilt_z=np.zeros(n), det_field=None)


def case_clean(rng, k, t, th):
    return _none(k), {}, dict(family="none", variable="none", nameable=True,
                              ambiguous_with=[])


def case_wobble_nod(rng, k, t, th):
    a = rng.uniform(0.02, 0.08)
    ph = rng.uniform(0, 2 * np.pi)
    e = _none(k)
    e["tilt_x"] = a * np.sin(np.deg2rad(th) + ph)
    return e, dict(amplitude_deg=a, phase_rad=ph), dict(
        family="rotary_wobble", variable="theta", nameable=True, ambiguous_with=[])


def case_runout_h2(rng, k, t, th):
    a = rng.uniform(0.005, 0.020)
    p1, p2 = rng.uniform(0, 2 * np.pi, size=2)
    e = _none(k)
    x = np.deg2rad(th)
    e["shift"][:, 0] = a * np.cos(2 * x + p1)
    e["shift"][:, 2] = a * np.sin(2 * x + p2)
    return e, dict(amplitude_mm=a, phase1_rad=p1, phase2_rad=p2), dict(
        family="rotary_runout", variable="theta", nameable=True, ambiguous_with=[])


def case_warmup_drift(rng, k, t, th):
    d = rng.uniform(0.020, 0.060)
    tau = rng.uniform(15.0, 40.0)
    e = _none(k)
    e["src"][:, 0] = d * (1.0 - np.exp(-t / tau))
    return e, dict(d_mm=d, tau_s=tau), dict(
        family="drift", variable="time", nameable=True, ambiguous_with=[])


def case_latency_jitter(rng, k, t, th):
    # A constant lag at one constant speed is a fixed angle offset of the
    # sample, which every rotation-stage fit absorbs in the sphere positions
    # (unobservable). The stage therefore runs at two speeds (see
    # TIMELINES): the lag's angle error changes where the speed does.
    L = rng.uniform(0.1, 0.3)
    omega = np.gradient(th, t)                     # deg/s, per frame (reported only)
    jit = rng.normal(0.0, 0.005, size=len(k))
    e = _none(k)
    # the stage is exposed where it stood L s before the encoders were read: the
    # logged (piecewise linear) path at t - L, continued before the first reading
    slope0 = (th[1] - th[0]) / (t[1] - t[0])
    true = np.where(t - L < t[0], th[0] + (t - L - t[0]) * slope0, np.interp(t - L, t, th))
    e["dtheta"] = true - th + jit
    return e, dict(latency_s=L, omega_deg_s=sorted(set(np.round(omega, 3).tolist())), jitter_deg=0.005), dict(
        family="encoder_latency", variable="time", nameable=True, ambiguous_with=[])


def two_speed_times(k):
    """Half the turn at 4 deg/s, the other half at 8 deg/s (s since start)."""
    dt = np.where(k < N_FRAMES // 2, DT, DT / 2)
    return np.concatenate([[0.0], np.cumsum(dt[:-1])])


TIMELINES = {"latency_jitter": two_speed_times}
THETAS = {}          # case name -> logged angle path th(k) (deg); default k * STEP_DEG


def case_encoder_slip(rng, k, t, th):
    k0 = int(rng.integers(30, 61))
    s = rng.uniform(0.05, 0.15)
    e = _none(k)
    e["dtheta"] = np.where(k >= k0, s, 0.0)
    return e, dict(slip_frame=k0, slip_deg=s), dict(
        family="none", variable="time", nameable=False, ambiguous_with=[])


def case_wobble_precess(rng, k, t, th):
    # The axis direction precesses: tilt about lab x ~ cos(theta+phi), about lab
    # z ~ sin(theta+phi). Only this sense is used: the other one (tilt_z ~
    # -sin) is a tilt that turns WITH the stage, i.e. R_y(theta) R0, a fixed
    # re-orientation of the phantom that no fit can see (checked: <3e-4 px
    # from a clean scan with a re-oriented phantom).  In the stage frame this
    # sense is a tilt turning at -2 theta.
    a = rng.uniform(0.02, 0.08)
    ph = rng.uniform(0, 2 * np.pi)
    x = np.deg2rad(th)
    e = _none(k)
    e["tilt_x"] = a * np.cos(x + ph)
    e["tilt_z"] = a * np.sin(x + ph)
    return e, dict(amplitude_deg=a, phase_rad=ph), dict(
        family="rotary_wobble", variable="theta", nameable=True, ambiguous_with=[])


def case_runout_h3(rng, k, t, th):
    # Axis point moving in the x-z plane at harmonic 3 or 4 of theta, one
    # amplitude, independent phases for x and z (harmonic 1 would be a
    # phantom shift, unobservable).
    m = int(rng.integers(3, 5))
    a = rng.uniform(0.005, 0.020)
    p1, p2 = rng.uniform(0, 2 * np.pi, size=2)
    x = np.deg2rad(th)
    e = _none(k)
    e["shift"][:, 0] = a * np.cos(m * x + p1)
    e["shift"][:, 2] = a * np.sin(m * x + p2)
    return e, dict(harmonic=m, amplitude_mm=a, phase1_rad=p1, phase2_rad=p2), dict(
        family="rotary_runout", variable="theta", nameable=True, ambiguous_with=[])


# Forward-back scans: the first half of the frames forward 0, 8, ..., 352 deg,
# the stage runs on to FB_TURN and reverses, the second half back 356, 348,
# ..., 4 deg (together every 4 deg once, as in the standard scan).  Angular
# speeds in deg/s; the first return frame is (FB_TURN - 356)/speed_back s after
# the reversal, longer than the largest latency drawn, so each leg is at one
# constant speed throughout.
FB_STEP = 8.0
FB_TURN = 360.0
FB_SPEEDS = {"two_speed_fb": (1.6, 0.8), "backlash_fb": (1.6, 1.6)}


def fb_angles(k):
    h = N_FRAMES // 2
    return np.where(k < h, FB_STEP * k, FB_TURN - FB_STEP / 2 - FB_STEP * (k - h))


def fb_times(k, w_fwd, w_back):
    th = fb_angles(k)
    t_turn = FB_TURN / w_fwd
    return np.where(k < N_FRAMES // 2, th / w_fwd, t_turn + (FB_TURN - th) / w_back)


def fb_path(tq, w_fwd, w_back):
    """Continuous angle of the forward-back motion at times tq (s); the
    forward motion is continued before t = 0 (the stage was already turning)."""
    t_turn = FB_TURN / w_fwd
    return np.where(tq <= t_turn, w_fwd * tq, FB_TURN - w_back * (tq - t_turn))


for _nm in FB_SPEEDS:
    THETAS[_nm] = fb_angles
    TIMELINES[_nm] = (lambda nm: lambda k: fb_times(k, *FB_SPEEDS[nm]))(_nm)


def case_two_speed_fb(rng, k, t, th):
    # Encoder latency L: the true angle is the logged path L s earlier.  With
    # one speed per direction this is -w_fwd*L on the way out, +w_back*L on
    # the way back: a constant offset (absorbed) plus a step at the reversal,
    # exactly what a backlash predicts.
    w_fwd, w_back = FB_SPEEDS["two_speed_fb"]
    L = rng.uniform(0.1, 0.3)
    e = _none(k)
    e["dtheta"] = fb_path(t - L, w_fwd, w_back) - th
    return e, dict(latency_s=L, speed_fwd_deg_s=w_fwd, speed_back_deg_s=w_back), dict(
        family="encoder_latency", variable="time", nameable=True, ambiguous_with=["backlash"])


def case_backlash_fb(rng, k, t, th):
    # Forward then back at the same speed; the encoder sits on the drive side,
    # so after the reversal the table trails the reading by the backlash b in
    # the direction of motion (moving towards smaller theta: true = logged + b).
    # The forward leg is taken up from the start (offset 0).  At one speed
    # per direction a latency L predicts -w*L out, +w*L back: the same
    # constant-plus-step, so the data cannot tell it from encoder_latency
    # (only a speed change within one direction could).
    b = rng.uniform(0.05, 0.2)
    # frames on the return leg: from the first frame after the turn at FB_TURN
    # (its logged angle is above the previous frame's, but the stage came to it
    # moving back; the backlash is taken up by then)
    back = k >= N_FRAMES // 2
    e = _none(k)
    e["dtheta"] = np.where(back, b, 0.0)
    w_fwd, w_back = FB_SPEEDS["backlash_fb"]
    return e, dict(backlash_deg=b, speed_deg_s=w_fwd), dict(
        family="backlash", variable="theta", nameable=True,
        ambiguous_with=["encoder_latency"])


def case_intensifier(rng, k, t, th):
    # Static image-intensifier-like field added to the projected centres (px),
    # about a centre c0 20-60 px off the detector centre, x = (c, r) - c0:
    #   radial (pincushion):  k1 |x|^2 x,          k1 > 0
    #   decentring:           |x|^2 p + 2 (p.x) x  (p a fixed 2-vector)
    # scaled so that the largest displacement over the four detector corners
    # is D (1-4 px) for the radial and T (0.3-1 px) for the decentring part.
    off = rng.uniform(20.0, 60.0)
    beta = rng.uniform(0, 2 * np.pi)
    D = rng.uniform(1.0, 4.0)
    T = rng.uniform(0.3, 1.0)
    gam = rng.uniform(0, 2 * np.pi)
    c0 = np.array([(COLS - 1) / 2, (ROWS - 1) / 2]) + off * np.array([np.cos(beta), np.sin(beta)])
    corners = np.array([[0, 0], [COLS - 1, 0], [0, ROWS - 1], [COLS - 1, ROWS - 1]], float)

    def radial(x, k1):
        return k1 * np.sum(x * x, axis=1)[:, None] * x

    def decentring(x, p):
        return np.sum(x * x, axis=1)[:, None] * p[None] + 2 * (x @ p)[:, None] * x

    xc = corners - c0
    k1 = D / np.linalg.norm(radial(xc, 1.0), axis=1).max()
    p_unit = np.array([np.cos(gam), np.sin(gam)])
    p = p_unit * T / np.linalg.norm(decentring(xc, p_unit), axis=1).max()

    def field(uv):
        x = uv - c0
        return radial(x, k1) + decentring(x, p)

    e = _none(k)
    e["det_field"] = field
    return e, dict(centre_px=[float(v) for v in c0], k1_px_per_px3=float(k1),
                   decentring_p=[float(v) for v in p], corner_radial_px=D,
                   corner_decentring_px=T), dict(
        family="detector_distortion", variable="detector", nameable=True, ambiguous_with=[])


def case_drift_plus_wobble(rng, k, t, th):
    # warm-up drift of the source (as case_warmup_drift) plus a nodding wobble
    # (as case_wobble_nod), from a fresh sub-stream so that the draws differ
    # from those of the two single-effect cases for the same seed.
    r = np.random.default_rng(rng.integers(0, 2 ** 63))
    d = r.uniform(0.020, 0.060)
    tau = r.uniform(15.0, 40.0)
    a = r.uniform(0.02, 0.08)
    ph = r.uniform(0, 2 * np.pi)
    e = _none(k)
    e["src"][:, 0] = d * (1.0 - np.exp(-t / tau))
    e["tilt_x"] = a * np.sin(np.deg2rad(th) + ph)
    return e, dict(d_mm=d, tau_s=tau, amplitude_deg=a, phase_rad=ph), dict(
        family="drift+rotary_wobble", variable="time", nameable=True, ambiguous_with=[])


def case_axis_knock(rng, k, t, th):
    # The stage is knocked at frame k0: from then on the axis direction is
    # tilted about lab x by s (either sign), and stays so.  A one-off event
    # that belongs to no family.
    k0 = int(rng.integers(30, 61))
    s = rng.uniform(0.03, 0.08) * (1.0 if rng.uniform() < 0.5 else -1.0)
    e = _none(k)
    e["tilt_x"] = np.where(k >= k0, s, 0.0)
    return e, dict(knock_frame=k0, tilt_x_deg=s), dict(
        family="none", variable="time", nameable=False, ambiguous_with=[])


def case_encoder_eccentric(rng, k, t, th):
    # The encoder scale is read off-centre: a once-per-turn angle error,
    # true angle = logged + e sin(theta + phi).  No family in the list.
    ecc = rng.uniform(0.02, 0.08)
    ph = rng.uniform(0, 2 * np.pi)
    e = _none(k)
    e["dtheta"] = ecc * np.sin(np.deg2rad(th) + ph)
    return e, dict(eccentric_deg=ecc, phase_rad=ph), dict(
        family="none", variable="theta", nameable=False, ambiguous_with=[])


CASES = {
    "clean": case_clean,
    "wobble_nod": case_wobble_nod,
    "runout_h2": case_runout_h2,
    "warmup_drift": case_warmup_drift,
    "latency_jitter": case_latency_jitter,
    "encoder_slip": case_encoder_slip,
    "wobble_precess": case_wobble_precess,
    "runout_h3": case_runout_h3,
    "two_speed_fb": case_two_speed_fb,
    "backlash_fb": case_backlash_fb,
    "intensifier": case_intensifier,
    "drift_plus_wobble": case_drift_plus_wobble,
    "axis_knock": case_axis_knock,
    "encoder_eccentric": case_encoder_eccentric,
}


# ---------------------------------------------------------------- simulate
def simulate(name, seed):
    """Return (geometry, per-frame sphere centres (F,N,3), sources (F,3),
    ideal projections (F,N,2), noisy projections, label, params, k, t, th)."""
    ss_geo, ss_noise, ss_eff = np.random.SeedSequence(seed).spawn(3)
    g = base_geometry(np.random.default_rng(ss_geo))
    noise = np.random.default_rng(ss_noise).normal(0.0, SIGMA_PX,
                                                   size=(N_FRAMES, N_SPHERES, 2))
    k = np.arange(N_FRAMES)
    t = TIMELINES[name](k) if name in TIMELINES else k * DT
    th = THETAS[name](k) if name in THETAS else k * STEP_DEG
    eff, params, label = CASES[name](np.random.default_rng(ss_eff), k, t, th)
    P = np.empty((N_FRAMES, N_SPHERES, 3))
    S = np.empty((N_FRAMES, 3))
    uv = np.empty((N_FRAMES, N_SPHERES, 2))
    for i in range(N_FRAMES):
        R = rot_x(np.deg2rad(eff["tilt_x"][i])) @ rot_y(np.deg2rad(th[i] + eff["dtheta"][i]))
        if eff["tilt_z"][i] != 0.0:          # skipped when zero: old cases stay bit-identical
            R = rot_z(np.deg2rad(eff["tilt_z"][i])) @ R
        P[i] = eff["shift"][i] + g["phantom"] @ R.T
        S[i] = g["source"] + eff["src"][i]
        uv[i] = project(S[i], P[i], g)
        if eff["det_field"] is not None:
            uv[i] = uv[i] + eff["det_field"](uv[i])
    if eff["det_field"] is not None:
        g["det_field"] = eff["det_field"]    # so that render() distorts the images too
    return g, P, S, uv, uv + noise, label, params, k, t, th


def render(S, P, g, sub=2):
    """Attenuation image (float) of spheres P seen from S: exact chord lengths,
    sub x sub supersampling, only in a box around each sphere.  With a
    detector field g["det_field"] (ideal -> measured px), each sample point is
    mapped back to its ideal position (fixed-point inversion) before tracing."""
    img = np.zeros((ROWS, COLS))
    R = DIAMETER / 2
    field = g.get("det_field")
    for p in P:
        c0, r0 = project(S, p[None], g)[0]
        if field is not None:
            c0, r0 = np.array([c0, r0]) + field(np.array([[c0, r0]]))[0]
        M = np.linalg.norm(_intersect(S, p, g["origin"], np.cross(g["u"], g["v"])) - S) \
            / np.linalg.norm(p - S)
        h = int(np.ceil(R * M / PITCH * 1.1)) + 2
        cs = np.arange(max(0, int(c0) - h), min(COLS, int(c0) + h + 1))
        rs = np.arange(max(0, int(r0) - h), min(ROWS, int(r0) + h + 1))
        off = (np.arange(sub) + 0.5) / sub - 0.5
        cc = (cs[:, None] + off[None]).ravel()
        rr = (rs[:, None] + off[None]).ravel()
        C, Rr = np.meshgrid(cc, rr)
        if field is not None:
            meas = np.stack([C.ravel(), Rr.ravel()], axis=1)
            ideal = meas.copy()
            for _ in range(6):
                ideal = meas - field(ideal)
            C, Rr = ideal[:, 0].reshape(C.shape), ideal[:, 1].reshape(C.shape)
        X = g["origin"] + (C[..., None] * g["u"] + Rr[..., None] * g["v"]) * PITCH
        d = X - S
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        w = p - S
        dist2 = np.sum(w * w) - (d @ w) ** 2
        chord = 2 * np.sqrt(np.clip(R * R - dist2, 0, None))
        box = chord.reshape(len(rs), sub, len(cs), sub).mean(axis=(1, 3))
        img[rs[0]:rs[-1] + 1, cs[0]:cs[-1] + 1] += box
    return img


# ---------------------------------------------------------------- writing
def _write_json(path, obj):
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, sort_keys=True, indent=1))
    os.replace(tmp, path)


def make_case(name: str, seed: int, out: pathlib.Path, images: bool = False) -> dict:
    import tifffile
    import yaml
    if name not in CASES:
        raise KeyError(f"unknown case {name!r}; known: {sorted(CASES)}")
    out = pathlib.Path(out)
    scan = out / "scan"
    scan.mkdir(parents=True, exist_ok=True)
    g, P, S, uv, meas, label, params, k, t, th = simulate(name, seed)

    margin = DIAMETER / 2 * 6 / PITCH      # sphere image radius bound, px
    if (uv.min() < margin) or (uv.max() > COLS - 1 - margin):
        raise RuntimeError("simulated sphere leaves the detector")

    axis = {"name": "theta", "type": "rotary", "direction": [0.0, 1.0, 0.0],
            "point": [0.0, 0.0, 0.0]}
    desc = {
        "format": "conecal-scan/1",
        "motion": "rotation",
        "projections": "projections.tif",
        "values": "attenuation",
        "log": "log.csv",
        "detector": {"rows": ROWS, "cols": COLS, "pixel_pitch": [PITCH, PITCH]},
        "nominal": {"sod": SOD, "sdd": SDD},
        "markers": {"diameter": DIAMETER},
        "axes": [dict(axis)],
    }
    (scan / "scan.yaml").write_text(yaml.safe_dump(desc, sort_keys=False))

    with open(scan / "log.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "time", "theta"])
        for i in range(N_FRAMES):
            w.writerow([int(k[i]), f"{t[i]:.3f}", f"{th[i]:.4f}"])

    with tifffile.TiffWriter(scan / "projections.tif") as tw:
        for i in range(N_FRAMES):
            if images:
                page = np.clip(np.rint(1000.0 * MU * render(S[i], P[i], g)), 0, 65535)
                page = page.astype(np.uint16)
            else:
                page = np.full((ROWS, COLS), 1000, np.uint16)
            tw.write(page, contiguous=True)

    geom = {
        "format": "conecal-geometry/1",
        "source": [float(x) for x in g["source"]],
        "detector": {"origin": [float(x) for x in g["origin"]],
                     "u": [float(x) for x in g["u"]],
                     "v": [float(x) for x in g["v"]],
                     "pixel_pitch": [PITCH, PITCH], "shape": [ROWS, COLS]},
        "axes": [dict(axis)],
    }
    _write_json(out / "geometry.json", geom)

    frames = [{"frame": int(i),
               "markers": [{"id": j, "x": float(meas[i, j, 0]), "y": float(meas[i, j, 1]),
                            "sigma": SIGMA_PX, "flags": []} for j in range(N_SPHERES)]}
              for i in range(N_FRAMES)]
    _write_json(out / "markers.json", {"format": "conecal-markers/1", "frames": frames})

    _write_json(out / "effect.json", {
        "case": name, "seed": int(seed), "label": label,
        "params": {a: (float(b) if isinstance(b, (float, np.floating)) else b)
                   for a, b in params.items()},
        "phantom_mm": g["phantom"].tolist(),
        "true_source_per_frame": S.tolist()})
    return dict(label)


if __name__ == "__main__":   # self-check: every case, seed 0, vs clean
    import sys
    import yaml
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/fv_test")
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0

    def load(d):
        yaml.safe_load((d / "scan" / "scan.yaml").read_text())
        with open(d / "scan" / "log.csv") as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == N_FRAMES and set(rows[0]) == {"frame", "time", "theta"}
        json.loads((d / "geometry.json").read_text())
        m = json.loads((d / "markers.json").read_text())
        return np.array([[[mk["x"], mk["y"]] for mk in fr["markers"]] for fr in m["frames"]])

    labels = {nm: make_case(nm, seed, root / nm) for nm in CASES}
    ref = load(root / "clean")
    for nm in CASES:
        r, note = ref, ""
        if nm in THETAS:     # own angle path: compare with an effect-free scan at those angles
            g, _, _, uv, meas, *_, th = simulate(nm, seed)
            ideal = np.array([project(g["source"], g["phantom"] @ rot_y(np.deg2rad(a)).T, g)
                              for a in th])
            r, note = ideal + (meas - uv), "  (vs effect-free at its own angles)"
        d = np.abs(load(root / nm) - r)
        print(f"{nm:17s} max|dx|={d[..., 0].max():.3f} px  max|dy|={d[..., 1].max():.3f} px"
              f"  label={labels[nm]}{note}")
