"""Independent marker-level simulator of a free-pose C-arm whose source and detector sag with the gantry angles.

Written without reference to the conecal implementation: only the scan contract (SCAN_FORMAT.md) and the
file interface of carm_indep.py are used.  No image rendering; markers.json is produced directly.

Room frame: X lateral, Y along the table, Z up; isocentre at the origin.  Gantry G = Ry(primary) Rx(secondary);
at (0, 0) the beam (gantry +z) points up.  Gravity in the gantry frame: g = G^T (0, 0, -1).
Sag (gantry frame, mm, linear elasticity: deflection = compliance @ load):
    source   S = (0, 0, -SOD) + As @ g
    detector translated by Ad @ g and tilted about its centre by the rotation vector -kappa * (z x g)
    (the detector's centre of mass sits in front of its mount, so its face droops; |tilt| <= kappa).
As, Ad: lateral droop (x, y) along gravity, detector more than source; axial rows: the C closes when the
beam is vertical (g_z term, opposite signs) and opens/closes with the in-plane load (g_y term, the C lying
in the gantry y-z plane); plus small random couplings.  Each frame's intrinsics follow exactly from that
geometry: sdd = distance from the source to the detector plane, (c0, r0) = foot of the perpendicular.
Poses are given in each frame's imaging frame (source at (0, 0, -SOD), u = +x, v = +y, detector normal +z).
"""
import json
import pathlib

import numpy as np

from carm_files import write_free_scan
from scipy.spatial.transform import Rotation

CASES = ["ball_sag", "ball_sag_ii", "grid_sag", "ball_nosag"]
ROWS = COLS = 512
SOD = 600.0
SDD_NOMINAL = 1000.0
NFRAMES = 24
RADIUS = 1.0          # sphere radius, mm
MAX_TILT = 55.0       # deg, phantom normal against the beam
CENTRE = np.array([(COLS - 1) / 2, (ROWS - 1) / 2])
EX, EY, EZ = np.eye(3)


def rot(axis, deg):
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float)).as_matrix()


# ---------------------------------------------------------------- phantom
def make_phantom(kind, seed, rng):
    if kind == "grid":    # 5x5 on a 12..15 mm pitch; odd seeds lack one corner (breaks the symmetry)
        p = 12.0 + seed % 4
        pts = [(5 * i + j + 1, (j - 2) * p, (i - 2) * p, 0.0) for i in range(5) for j in range(5)]
        return pts[1:] if seed % 2 else pts
    pts = []              # 24 balls in a cylinder r=30, h=40, >= 8 mm apart (dart throwing)
    while len(pts) < 24:
        r, a, z = 30 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi), rng.uniform(-20, 20)
        q = np.array([r * np.cos(a), r * np.sin(a), z])
        if all(np.linalg.norm(q - o) >= 8 for o in pts):
            pts.append(q)
    return [(k + 1, *map(float, q)) for k, q in enumerate(pts)]


# ---------------------------------------------------------------- gantry, sag, per-frame geometry
def gantry(primary, secondary):
    return rot(EY, primary) @ rot(EX, secondary)


def make_sag(rng, tilt):
    ls = rng.uniform(0.2, 0.5, 2)
    ld = ls + rng.uniform(0.3, 0.9, 2)
    a_s, a_d = rng.uniform(0.4, 1.0), rng.uniform(0.8, 1.8)
    o, share = rng.uniform(1.0, 2.2) * rng.choice([-1, 1]), rng.uniform(0.3, 0.7)
    As = np.diag([ls[0], ls[1], -a_s]) + rng.normal(0, 0.05, (3, 3))
    Ad = np.diag([ld[0], ld[1], a_d]) + rng.normal(0, 0.08, (3, 3))
    As[2, 1], Ad[2, 1] = -o * (1 - share), o * share
    return {"As": As, "Ad": Ad, "kappa": np.radians(rng.uniform(0.03, 0.08)) if tilt else 0.0}


def frame_geometry(G, sdd0, pp0, pitch, sag):
    """Physical source and detector (gantry frame) of one frame -> intrinsics and imaging frame."""
    S, u, v = np.array([0.0, 0.0, -SOD]), EX.copy(), EY.copy()
    O = np.array([-pp0[0] * pitch, -pp0[1] * pitch, sdd0 - SOD])     # centre of pixel [0, 0]
    tilt = np.zeros(3)
    if sag is not None:
        g = G.T @ np.array([0.0, 0.0, -1.0])
        C = O + CENTRE[0] * pitch * u + CENTRE[1] * pitch * v           # detector centre
        tilt = -sag["kappa"] * np.cross(EZ, g)
        Rt = Rotation.from_rotvec(tilt).as_matrix()
        S = S + sag["As"] @ g
        O, u, v = C + Rt @ (O - C) + sag["Ad"] @ g, Rt @ u, Rt @ v
    n = np.cross(u, v)
    sdd = float((O - S) @ n)
    F = S + sdd * n
    pp = np.array([(F - O) @ u, (F - O) @ v]) / pitch
    B = np.column_stack([u, v, n])              # imaging frame axes in gantry coordinates
    return {"S": S, "O": O, "u": u, "v": v, "sdd": sdd, "pp": pp, "B": B, "I": S + SOD * n,
            "tilt_deg": float(np.degrees(np.linalg.norm(tilt)))}


def project(X, sdd, pp, pitch):
    """Pinhole projection of imaging-frame points (source (0,0,-SOD), detector plane z = sdd - SOD)."""
    X = np.atleast_2d(X)
    return np.asarray(pp) + (sdd / pitch / (X[:, 2] + SOD))[:, None] * X[:, :2]


def shadow_centroids(X, sdd, pp, pitch, n=121):
    """Attenuation-weighted centroid of each sphere's shadow: detector-plane quadrature (midpoint rule on
    an n x n patch) of the analytic chord length of the ray through each detector point."""
    out = []
    for x in X:
        p0 = project(x, sdd, pp, pitch)[0]
        half = 1.3 * RADIUS * sdd / pitch / (x[2] + SOD)
        s = (np.arange(n) + 0.5) / n * 2 * half - half
        cr = np.stack(np.meshgrid(p0[0] + s, p0[1] + s), -1).reshape(-1, 2)
        Y = np.column_stack([(cr - pp) * pitch, np.full(len(cr), sdd)])   # detector point minus source
        d = Y / np.linalg.norm(Y, axis=1)[:, None]
        w = x + np.array([0, 0, SOD])
        L = np.sqrt(np.clip(RADIUS ** 2 - (w @ w - (d @ w) ** 2), 0, None))
        out.append((cr * L[:, None]).sum(0) / L.sum())
    return np.array(out)


# ---------------------------------------------------------------- distortion (fixed to the pixel grid)
def make_distortion(kind, rng):
    if kind == "none":
        return {"kind": "none"}
    # curved-input-screen pincushion r -> h tan(r / h) about an off-centre point + twist s tanh((r/R0)^2)
    return {"kind": "ii", "centre": (CENTRE + rng.uniform(-35, 35, 2)).tolist(), "h": rng.uniform(1150, 2000),
            "s": rng.uniform(0.009, 0.023) * rng.choice([-1, 1]), "R0": 256.0}


def distort(params, cr):
    """Ideal pinhole pixel (c, r) -> measured pixel, for a distortion_params dict from truth.json."""
    cr = np.atleast_2d(np.asarray(cr, float))
    if params["kind"] == "none":
        return cr
    e = np.array(params["centre"])
    d = cr - e
    r = np.linalg.norm(d, axis=1)
    scale = np.where(r > 0, params["h"] * np.tan(r / params["h"]) / np.maximum(r, 1e-12), 1.0)
    th = params["s"] * np.tanh((r / params["R0"]) ** 2)
    c, s = np.cos(th), np.sin(th)
    return e + np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], 1) * scale[:, None]


# ---------------------------------------------------------------- case
def make_case(name, seed, out):
    out = pathlib.Path(out)
    parts = name.split("_")
    kind, sag_on, dkind = parts[0], parts[1] == "sag", parts[2] if len(parts) > 2 else "none"
    tilt_on = sag_on and (kind == "grid" or dkind == "ii")         # ball_sag: translation-only sag
    rng = np.random.default_rng(7919 * seed + 31 * CASES.index(name) + 5)
    (out / "scan").mkdir(parents=True, exist_ok=True)
    phantom = make_phantom(kind, seed, rng)
    P, ids = np.array([q[1:] for q in phantom]), [q[0] for q in phantom]

    pitch = float(rng.uniform(0.3, 0.45))
    sdd0 = SDD_NOMINAL * (1 + rng.uniform(-0.03, 0.03))
    pp0 = CENTRE + rng.uniform(-20, 20, 2)
    sag = make_sag(rng, tilt_on) if sag_on else None
    dparams = make_distortion(dkind, rng)
    sigma = float(rng.uniform(0.03, 0.08))
    # phantom on the table: small wedge tilt, in-plane turn, then panned per frame
    w = rng.uniform(0, 2 * np.pi)
    R_tab = rot([np.cos(w), np.sin(w), 0], rng.uniform(0, 10)) @ rot(EZ, rng.uniform(-10, 10))
    t_tab = rng.uniform(-10, 10, 3)
    lose = set(rng.choice(NFRAMES, rng.integers(2, 6), replace=False).tolist())
    gain = set(rng.choice(NFRAMES, rng.integers(2, 6), replace=False).tolist())

    frames, poses, id_lists, heldout, err, geo, angles = [], [], [], [], [], [], []
    for k in range(NFRAMES):
        while True:
            a, b = rng.uniform(-90, 90), rng.uniform(-40, 40)
            G = gantry(a, b)
            if np.degrees(np.arccos(np.clip((G @ EZ) @ (R_tab @ EZ), -1, 1))) <= MAX_TILT:
                break
        f = frame_geometry(G, sdd0, pp0, pitch, sag)
        R = f["B"].T @ G.T @ R_tab
        t = f["B"].T @ (G.T @ (t_tab + rng.uniform(-15, 15, 3)) - f["I"])
        X = P @ R.T + t
        clean = distort(dparams, shadow_centroids(X, f["sdd"], f["pp"], pitch))
        rad = RADIUS * f["sdd"] / pitch / (X[:, 2] + SOD)
        ok = ((clean - 1.2 * rad[:, None] >= -0.5) & (clean + 1.2 * rad[:, None] <= [COLS - 0.5, ROWS - 0.5])).all(1)
        dist = np.linalg.norm(clean[:, None] - clean[None], axis=2) + 1e9 * np.eye(len(clean))
        ok &= (dist > 1.1 * (rad[:, None] + rad[None])).min(1)         # touching shadows: detector drops both
        keep = list(np.flatnonzero(ok))
        if k in lose and keep:
            keep.pop(rng.integers(len(keep)))
        noise = rng.normal(0, sigma, (len(keep), 2))
        err.append(noise)
        mk = [(*(clean[i] + e), ids[i]) for i, e in zip(keep, noise)]
        while k in gain:                                            # a stray blob clear of every sphere
            q = rng.uniform(10, [COLS - 11, ROWS - 11])
            if np.linalg.norm(clean - q, axis=1).min() > 12:
                mk.append((*q, None))
                break
        mk = [mk[i] for i in rng.permutation(len(mk))]
        frames.append({"frame": k, "markers": [{"id": None, "x": float(x), "y": float(y), "sigma": sigma,
                                                "flags": []} for x, y, _ in mk]})
        id_lists.append([i for _, _, i in mk])
        poses.append({"frame": k, "R": R.tolist(), "t": t.tolist()})
        if kind == "grid":
            lo, hi = P.min(0), P.max(0)
            H = np.column_stack([rng.uniform(lo[0], hi[0], 40), rng.uniform(lo[1], hi[1], 40),
                                 rng.choice([-1, 1], 40) * rng.uniform(5, 20, 40)])
        else:
            rr, aa = 30 * np.sqrt(rng.uniform(0, 1, 40)), rng.uniform(0, 2 * np.pi, 40)
            H = np.column_stack([rr * np.cos(aa), rr * np.sin(aa), rng.uniform(-20, 20, 40)])
        hp = distort(dparams, project(H @ R.T + t, f["sdd"], f["pp"], pitch))
        heldout.append({"frame": k, "points": H.tolist(), "pixels": hp.tolist()})
        geo.append(f)
        angles.append([a, b])

    write_free_scan(out, rows=ROWS, cols=COLS, pitch=pitch, sod=SOD, sdd=SDD_NOMINAL, diameter=2 * RADIUS,
                    phantom=phantom, frames=frames)
    fsdd = [f["sdd"] for f in geo]
    fpp = [f["pp"].tolist() for f in geo]
    truth = {"sdd": float(np.mean(fsdd)), "principal_point": np.mean(fpp, 0).tolist(), "source": [0.0, 0.0, -SOD],
             "poses": poses, "sigma_px": sigma, "ids_per_frame": id_lists, "heldout": heldout,
             "distortion_kind": dkind, "distortion_params": dparams,
             "frame_sdd": fsdd, "frame_principal_point": fpp, "sag": sag_on,
             "detector_tilt_deg": [f["tilt_deg"] for f in geo] if tilt_on else None,
             "pixel_pitch": pitch, "gantry_deg": angles, "base_sdd": sdd0, "base_principal_point": pp0.tolist(),
             "sag_params": None if sag is None else {"As": sag["As"].tolist(), "Ad": sag["Ad"].tolist(),
                                                     "kappa_deg": float(np.degrees(sag["kappa"]))}}
    (out / "truth.json").write_text(json.dumps(truth, sort_keys=True))

    # diagnostics (not part of the interface)
    g = np.stack(np.meshgrid(np.arange(COLS), np.arange(ROWS)), -1).reshape(-1, 2).astype(float)
    make_case.last_stats = {
        "per_frame": [len(fr["markers"]) for fr in frames], "sdd_spread": float(np.ptp(fsdd)),
        "pp_spread": np.ptp(np.array(fpp), axis=0).tolist(),
        "pp_dev": float(np.linalg.norm(np.array(fpp) - np.mean(fpp, 0), axis=1).max()),
        "max_disp": float(np.linalg.norm(distort(dparams, g) - g, axis=1).max()),
        "rms": float(np.sqrt(np.mean(np.concatenate(err) ** 2))), "max_tilt": max(f["tilt_deg"] for f in geo)}
    return {"name": name, "seed": seed, "sigma_px": sigma, "distortion_kind": dkind, "phantom": kind, "sag": sag_on}


if __name__ == "__main__":
    for name in CASES:
        info = make_case(name, 1, pathlib.Path("/tmp/carm_sag") / name)
        s = make_case.last_stats
        print(f"{name:12s} markers/frame {min(s['per_frame'])}-{max(s['per_frame'])}  "
              f"sdd spread {s['sdd_spread']:.2f} mm  pp spread {s['pp_spread'][0]:.2f},{s['pp_spread'][1]:.2f} px "
              f"(max dev {s['pp_dev']:.2f})  tilt <= {s['max_tilt']:.3f} deg  max distortion {s['max_disp']:.2f} px  "
              f"noise RMS/axis {s['rms']:.4f} px (sigma {info['sigma_px']:.4f})")
