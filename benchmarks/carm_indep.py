"""Independent marker-level simulator of a free-pose C-arm (image intensifier) calibration.

Written without reference to the conecal implementation: only the scan contract
(SCAN_FORMAT.md) is used.  No image rendering; markers.json is produced directly.
"""
import json
import pathlib

import numpy as np

from carm_files import write_free_scan
from scipy.spatial.transform import Rotation

CASES = ["grid_ii", "grid_brown", "grid_none", "ball_ii"]
ROWS = COLS = 512
PITCH = 0.45
SOD = 600.0
NFRAMES = 24
RADIUS = 1.0  # sphere radius, mm


# ---------------------------------------------------------------- phantom
def make_phantom(kind, seed, rng):
    if kind == "grid":
        p = 12.0 + seed % 4
        pts = [(i * 5 + j + 1, (j - 2) * p, (i - 2) * p, 0.0) for i in range(5) for j in range(5)]
        if seed % 2 == 1:
            pts = pts[1:]
        return [(int(a), float(x), float(y), float(z)) for a, x, y, z in pts]
    while True:  # ball phantom: rejection sampling in a cylinder r=30, h=40
        pts = []
        for _ in range(20000):
            q = np.array([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-20, 20)])
            if np.hypot(q[0], q[1]) > 30 or any(np.linalg.norm(q - o) < 8 for o in pts):
                continue
            pts.append(q)
            if len(pts) == 24:
                return [(k + 1, *map(float, q)) for k, q in enumerate(pts)]


# ---------------------------------------------------------------- geometry
def random_pose(rng):
    phi = rng.uniform(0, 2 * np.pi)            # tilt direction
    alpha = np.radians(rng.uniform(0, 55))     # tilt magnitude
    psi = np.radians(rng.uniform(-10, 10))     # in-plane turn
    axis = np.array([-np.sin(phi), np.cos(phi), 0.0])
    R = Rotation.from_rotvec(alpha * axis).as_matrix() @ Rotation.from_rotvec([0, 0, psi]).as_matrix()
    t = rng.uniform(-15, 15, 3)
    return R, t, phi


def project(X, sdd, pp):
    X = np.atleast_2d(X)
    k = sdd / PITCH / (X[:, 2] + SOD)
    return np.stack([pp[0] + k * X[:, 0], pp[1] + k * X[:, 1]], axis=1)


def shadow_centroid(Xc, offsets, sdd, pp):
    """Attenuation-weighted centroid of a sphere's shadow on a flat detector.

    Line integral * dA over the detector = integral over volume of (D/z)^2 / cos(gamma) dV,
    i.e. weight |X - S| / z^3 per volume element (z = depth along the detector normal)."""
    X = Xc[None, :] + offsets
    z = X[:, 2] + SOD
    w = np.linalg.norm(X + np.array([0, 0, SOD]), axis=1) / z ** 3
    return (project(X, sdd, pp) * w[:, None]).sum(0) / w.sum()


# ---------------------------------------------------------------- distortion
def make_distortion(kind, sdd, pp, rng):
    if kind == "none":
        return {"kind": "none"}, (lambda uv, frame: uv)
    if kind == "brown":
        f = sdd / PITCH
        k1 = rng.uniform(0.1, 0.3) * rng.choice([-1, 1])
        k2 = rng.uniform(-0.05, 0.05)
        p1, p2 = rng.normal(0, 1e-3, 2)

        def dist(uv, frame):
            x, y = (uv[:, 0] - pp[0]) / f, (uv[:, 1] - pp[1]) / f
            r2 = x * x + y * y
            rad = 1 + k1 * r2 + k2 * r2 * r2
            xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            return np.stack([pp[0] + f * xd, pp[1] + f * yd], axis=1)
        return {"kind": "brown", "f": f, "k1": k1, "k2": k2, "p1": p1, "p2": p2}, dist
    # image intensifier: pincushion + S-twist, twist strength depends on frame tilt direction
    centre = np.array([pp[0] + rng.uniform(-40, 40), pp[1] + rng.uniform(-40, 40)])
    a, b = rng.uniform(0.01, 0.02), rng.uniform(0, 0.005)
    s = rng.uniform(0.002, 0.006)
    field = rng.uniform(0, 2 * np.pi)
    s_frame = {}

    def dist(uv, frame):
        d = uv - centre
        rho = np.linalg.norm(d, axis=1) / 256.0
        sc = 1 + a * rho ** 2 + b * rho ** 4
        th = s_frame[frame] * rho ** 2
        c, sn = np.cos(th), np.sin(th)
        out = np.stack([c * d[:, 0] - sn * d[:, 1], sn * d[:, 0] + c * d[:, 1]], axis=1) * sc[:, None]
        return centre + out
    params = {"kind": "ii", "centre": centre.tolist(), "a": a, "b": b, "s": s, "field_dir": field,
              "s_frame": s_frame}
    return params, dist


# ---------------------------------------------------------------- case
def make_case(name, seed, out):
    out = pathlib.Path(out)
    kind, dkind = name.split("_")
    rng = np.random.default_rng(1000 * seed + CASES.index(name))
    (out / "scan").mkdir(parents=True, exist_ok=True)
    phantom = make_phantom(kind, seed, rng)
    P = np.array([q[1:] for q in phantom])
    ids = [q[0] for q in phantom]

    sdd = 1000.0 * (1 + rng.uniform(-0.03, 0.03))
    pp = np.array([255.5, 255.5]) + rng.uniform(-20, 20, 2)
    dparams, distort = make_distortion(dkind, sdd, pp, rng)
    sigma = float(rng.uniform(0.03, 0.08))
    v = rng.normal(size=(300, 3))
    v *= (RADIUS * rng.uniform(0, 1, 300) ** (1 / 3) / np.linalg.norm(v, axis=1))[:, None]
    offsets = np.vstack([v, -v])  # symmetric: zero sampling bias in the centroid

    frames, poses, id_lists, heldout, err = [], [], [], [], []
    for k in range(NFRAMES):
        R, t, phi = random_pose(rng)
        if dkind == "ii":
            dparams["s_frame"][k] = dparams["s"] * (1 + 0.3 * np.cos(phi - dparams["field_dir"]))
        X = P @ R.T + t
        ideal = np.array([shadow_centroid(x, offsets, sdd, pp) for x in X])
        clean = distort(ideal, k)
        rad_px = RADIUS * sdd / PITCH / (X[:, 2] + SOD) * 1.1
        inside = ((clean - rad_px[:, None] >= -0.5) & (clean + rad_px[:, None] <= 511.5)).all(1)
        keep = list(np.flatnonzero(inside))
        if rng.random() < 0.2 and keep:
            keep.pop(rng.integers(len(keep)))
        meas = clean[keep] + rng.normal(0, sigma, (len(keep), 2))
        err.append(meas - clean[keep])
        mk = [(float(m[0]), float(m[1]), ids[i]) for m, i in zip(meas, keep)]
        if rng.random() < 0.3:
            base = clean[rng.integers(len(clean))]
            ang, dd = rng.uniform(0, 2 * np.pi), rng.uniform(10, 30)
            mk.append((float(np.clip(base[0] + dd * np.cos(ang), 5, COLS - 6)),
                       float(np.clip(base[1] + dd * np.sin(ang), 5, ROWS - 6)), None))
        order = rng.permutation(len(mk))
        mk = [mk[i] for i in order]
        frames.append({"frame": k, "markers": [{"id": None, "x": x, "y": y, "sigma": sigma, "flags": []}
                                               for x, y, _ in mk]})
        id_lists.append([i for _, _, i in mk])
        poses.append({"frame": k, "R": R.tolist(), "t": t.tolist()})
        # held-out points (projected + distorted, no shadow bias)
        if kind == "grid":
            lo, hi = P.min(0), P.max(0)
            H = np.stack([rng.uniform(lo[0], hi[0], 40), rng.uniform(lo[1], hi[1], 40),
                          rng.choice([-1, 1], 40) * rng.uniform(5, 20, 40)], axis=1)
        else:
            rr, aa = 30 * np.sqrt(rng.uniform(0, 1, 40)), rng.uniform(0, 2 * np.pi, 40)
            H = np.stack([rr * np.cos(aa), rr * np.sin(aa), rng.uniform(-20, 20, 40)], axis=1)
        hp = distort(project(H @ R.T + t, sdd, pp), k)
        heldout.append({"frame": k, "points": H.tolist(), "pixels": hp.tolist()})

    write_free_scan(out, rows=ROWS, cols=COLS, pitch=PITCH, sod=SOD, sdd=1000.0, diameter=2 * RADIUS,
                    phantom=phantom, frames=frames)
    dp = {k: (v if k != "s_frame" else [v[i] for i in range(NFRAMES)]) for k, v in dparams.items()}
    truth = {"sdd": sdd, "principal_point": pp.tolist(), "source": [0.0, 0.0, -SOD], "poses": poses,
             "sigma_px": sigma, "ids_per_frame": id_lists, "heldout": heldout,
             "distortion_kind": dkind, "distortion_params": dp}
    (out / "truth.json").write_text(json.dumps(truth, sort_keys=True))

    # diagnostics (not part of the interface)
    g = np.stack(np.meshgrid(np.arange(COLS), np.arange(ROWS)), -1).reshape(-1, 2).astype(float)
    make_case.last_stats = {
        "per_frame": [len(f["markers"]) for f in frames],
        "max_disp": max(float(np.linalg.norm(distort(g, k) - g, axis=1).max()) for k in range(NFRAMES)),
        "rms": float(np.sqrt(np.mean(np.concatenate(err) ** 2)))}
    return {"name": name, "seed": seed, "sigma_px": sigma, "distortion_kind": dkind, "phantom": kind}


if __name__ == "__main__":
    for name in CASES:
        info = make_case(name, 1, pathlib.Path("/tmp/carm_indep") / name)
        s = make_case.last_stats
        print(f"{name:11s} markers/frame min {min(s['per_frame'])} max {max(s['per_frame'])}  "
              f"max distortion {s['max_disp']:.2f} px  noise RMS/axis {s['rms']:.4f} px  "
              f"(sigma {info['sigma_px']:.4f})")
