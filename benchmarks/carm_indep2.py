"""Second independent marker-level simulator of a free-pose C-arm (image intensifier) calibration.

Written from the scan contract (SCAN_FORMAT.md) and the *interface* of carm_indep.py only; physics,
phantoms, poses and noise are deliberately different from carm_indep.py.  No image rendering.

World (= truth) frame, identical to carm_indep.project: source S = (0, 0, -SOD), beam along +z, the
detector plane at z = sdd - SOD, u = +x (columns), v = +y (rows), so a point X projects to
    (c, r) = pp + sdd / (pitch * (X_z + SOD)) * (X_x, X_y);   X_world = R @ X_phantom + t.

Geometry: detector 768^2 (pitch 0.32-0.40 mm) or 1024^2 (0.25-0.30 mm): field <= 31 cm, an II's;
sdd 950-1250, SOD 550-800 mm, principal point = centre +- 25 px, nominal sdd within 2 % (rounded to 10 mm).
Sag (case pds_iisag): per-frame sdd_k = sdd0 + As*sin(lao)/sin(60), |As| 1-1.5 mm, and pp_k = pp0 +
(Pc*sin(lao)/sin(60), Pr*(1-cos(lao))/(1-cos(60)) + Pb*sin(cran)/sin(30)), |Pc| 1.3-2, Pr 1-1.6, Pb 0.6-1 px:
peak-to-peak over the orbit <= 3 mm in sdd and <= 4 px per axis in the principal point.
truth "sdd"/"principal_point" are then the frame means; "frame_sdd"/"frame_principal_point" hold the
per-frame values (keys present only in the sag case).

Poses (C-arm): the phantom lies on the table (table frame: x lateral, y head-foot, z up), turned by a
random yaw, tilted by a <= 4 deg wedge, its centre 0-35 mm laterally and 0-20 mm vertically off the
isocentre.  Each frame the C-arm is at LAO/RAO a in [-60, 60] (rotation about table y) and CRAN/CAUD b
in [-30, 30] (about the turned x): M = Ry(a) Rx(b) holds the world axes in table coordinates, so
R = M^T Rt, t = M^T c.  a sweeps -55..55 (+-5 jitter), b follows 1-2 sine cycles of 27 deg (+-3).
Planar phantoms never exceed a 68 deg tilt to the beam (edge-on > 70 deg cannot occur).

Phantoms (ids from 1, one sphere diameter each):
  biplane: plate z=-g/2 an n x n grid (n in {4,5}, pitch 8-15 mm); plate z=+g/2 a (9-n)^2 grid, own pitch,
           turned 12-35 deg and offset 2.5-6 mm per axis; g = 30-60 mm; steel spheres 1.8-2.5 mm.
  pds:     26-33 positions on a helix (radius 25-35 mm, 1-1.5 turns, length 40-70 mm along phantom y, i.e.
           lying along the table), 3-5 non-adjacent positions removed, not mirror-symmetric (breaks the
           helix's C2 symmetry); 2.0-3.0 mm spheres.
  grid7:   7 x 7 grid, pitch 5-8 mm, one corner missing, spheres 1.0-1.5 mm.

Shadow centre: the attenuation-weighted centroid of the sphere's shadow on the flat detector,
int p L(p) dA / int L(p) dA, L the chord length, computed in cone coordinates about the source->centre
axis: with sin(alpha) = (a/l) sin(tau), L = 2a cos(tau) and dA = sdd^2 / w_z^3 dOmega, the weight is
cos^2(tau) sin(tau) / (cos(alpha) w_z^3) dtau dphi; 12-node Gauss-Legendre in tau, 16-point trapezoid
in phi (converged to < 1e-10 px, checked against a brute-force detector integral in __main__).

Image-intensifier distortion ("ii"), ideal flat-detector pixel -> measured pixel, in this order:
 (a) spherical input phosphor: a sphere of radius Rs (250-400 mm, >= 1.6 x the corner radius), tangent
     to the detector plane at the II axis point A (pp0 + 5-30 px, fixed to the detector), centred behind it.
     The ray from S through the flat-plane point P hits the cap at X; the physical image of P is the
     point at ARC LENGTH s = Rs*psi (psi = angle of X from the pole) from A along X's azimuth (output
     proportional to the arc length, unit scale at the pole).  The electron optics compensate most of
     it: measured = P + lam*(A + s*e - P), lam (~0.08-0.22) drawn so that the pincushion at the farthest
     detector corner is 10-16 px.  Depends on the frame's sdd_k, pp_k (exact ray-sphere intersection).
 (b) Earth-field S-distortion: rotation about A by theta = beta_k rho^2 (1 + gamma rho), rho = |q-A| /
     |farthest corner - A|, gamma in [-0.3, 0.5]; beta_k = beta0 (B . n_k), n_k the beam direction in the table
     frame, B a fixed unit field vector (inclination +-30 deg: the room field bent by building steel),
     resampled until B . n_k changes sign over the orbit; beta0 gives 4-9 px at the corner for |B.n|=1.
     Plus an image shift kappa * (e_z x B_world), kappa 1.4-2.0 px (transverse field) -> 0.3-2 px.
 (c) output-screen tilt: q -> A + d / (1 + h.d), d = q - A, |h| * half-diagonal = 0.002-0.004.
 bump (grid7_bump only, after (c)): q += amp * dir * exp(-|q-p0|^2 / (2 sw^2)), amp 1-2 px, sw = W/2 with
     W 60-100 px, p0 on the distorted position of a random marker 40+ px off pp0, dir a random unit.
"none": identity.  distortion_params hold everything (per-frame beta, shift, sdd, pp).

Noise (per marker, isotropic Gaussian): sigma = clip(s0 (r_ref/r_app)^2 / V, 0.03, 0.15) px: a blob's
centroid error ~ 1/(contrast * sqrt(area)) ~ r_app^-2, and a camera-noise-limited contrast ~ V, the II
vignetting V = (1 + (rho_mm/fv)^2)^-2 about A (0.15-0.3 at the farthest corner); r_ref the nominal
apparent radius, s0 in 0.035-0.06. 2 % of markers get a gross error of 0.5-1.5 px (random direction)
with an unchanged sigma; every frame has a 50 % chance of losing 10-20 % of its markers; 0-3 spurious
blobs per frame near the pattern (>= 2 blob radii + 6 px off any marker), with their nearest marker's
sigma; shadows closer than 1.1 shadow radii to the border are dropped, and two shadows that touch (gap <
1 px) are both dropped (a merged blob). truth sigma_px = RMS of the per-marker sigmas (per axis). Extra
truth keys: clean_px (noise-free centres in markers.json order, None for spurious), gross (indices of
gross errors), carm (lao/cran per frame), tilt_deg, geometry.
"""
import json
import pathlib
import time

import numpy as np
import yaml

from carm_files import write_free_scan

CASES = ["biplane_ii", "pds_ii", "grid7_ii", "pds_iisag", "biplane_none", "grid7_bump"]
SPEC = {"biplane_ii": ("biplane", "ii", False), "pds_ii": ("pds", "ii", False),
        "grid7_ii": ("grid7", "ii", False), "pds_iisag": ("pds", "ii", True),
        "biplane_none": ("biplane", "none", False), "grid7_bump": ("grid7", "ii+bump", False)}
_GT, _GW = np.polynomial.legendre.leggauss(12)
TAU, WTAU = (_GT + 1) * np.pi / 4, _GW * np.pi / 4
PHI = 2 * np.pi * np.arange(16) / 16
m = 40                                   # held-out points drawn per frame (those on the detector kept)


# ---------------------------------------------------------------- phantoms
def _grid(n, p):
    g = (np.arange(n) - (n - 1) / 2) * p
    return np.array([(x, y) for y in g for x in g])


def phantom_biplane(rng):
    n1 = int(rng.choice([4, 5]))
    p1, p2, gap = rng.uniform(8, 15), rng.uniform(8, 15), rng.uniform(30, 60)
    a = np.radians(rng.uniform(12, 35)) * rng.choice([-1, 1])
    off = rng.uniform(2.5, 6, 2) * rng.choice([-1, 1], 2)
    g1 = np.column_stack([_grid(n1, p1), np.full(n1 * n1, -gap / 2)])
    q = _grid(9 - n1, p2) @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) + off
    g2 = np.column_stack([q, np.full(len(q), gap / 2)])
    return np.vstack([g1, g2]), rng.uniform(1.8, 2.5), {"kind": "biplane", "planes_z": [-gap / 2, gap / 2]}


def phantom_pds(rng):
    R, turns, L = rng.uniform(25, 35), rng.uniform(1, 1.5), rng.uniform(40, 70)
    npos = int(rng.integers(26, 34))
    while True:
        rem = np.sort(rng.choice(np.arange(1, npos - 1), int(rng.integers(3, 6)), replace=False))
        if np.diff(rem).min() > 1 and set(rem) != set(npos - 1 - rem):
            break
    j = np.setdiff1d(np.arange(npos), rem)
    th = 2 * np.pi * turns * j / (npos - 1)
    P = np.column_stack([R * np.cos(th), L * (j / (npos - 1) - 0.5), R * np.sin(th)])
    return P, rng.uniform(2.0, 3.0), {"kind": "pds", "radius": R, "length": L, "removed": rem.tolist()}


def phantom_grid7(rng):
    g = _grid(7, rng.uniform(5, 8))
    g = np.delete(g, [0, 6, 42, 48][int(rng.integers(4))], axis=0)
    return np.column_stack([g, np.zeros(len(g))]), rng.uniform(1.0, 1.5), {"kind": "grid7", "planes_z": [0.0]}


PHANTOMS = {"biplane": phantom_biplane, "pds": phantom_pds, "grid7": phantom_grid7}


# ---------------------------------------------------------------- C-arm poses
def carm_M(lao, cran):
    a, b = np.radians(lao), np.radians(cran)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return Ry @ Rx


def table_placement(rng):
    yaw = rng.uniform(0, 2 * np.pi)
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    ax, w = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(0, 4))
    k = np.array([np.cos(ax), np.sin(ax), 0.0])
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    Rw = np.eye(3) + np.sin(w) * K + (1 - np.cos(w)) * K @ K
    c = np.array([*rng.uniform(-35, 35, 2), rng.uniform(-20, 20)])
    return Rw @ Rz, c


# ---------------------------------------------------------------- projection / shadow
def project(X, sdd, pp, pitch, sod):
    X = np.atleast_2d(X)
    return np.asarray(pp) + (sdd / pitch / (X[:, 2] + sod))[:, None] * X[:, :2]


def shadow_centroid(X0, a, sdd, pp, pitch, sod, tau=TAU, wtau=WTAU, phi=PHI):
    """Attenuation-weighted shadow centroid (px) of spheres (n, 3) of radius a (cone-coordinate quadrature)."""
    V = np.atleast_2d(X0) + np.array([0.0, 0.0, sod])
    ell = np.linalg.norm(V, axis=1)
    w, e1 = V / ell[:, None], np.cross(V, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(w, e1)
    sa = (a / ell)[:, None] * np.sin(tau)[None, :]                      # (n, J)
    ca = np.sqrt(1 - sa * sa)
    dirn = np.cos(phi)[None, None, :, None] * e1[:, None, None, :] + np.sin(phi)[None, None, :, None] * e2[:, None, None, :]
    om = ca[:, :, None, None] * w[:, None, None, :] + sa[:, :, None, None] * dirn   # (n, J, M, 3)
    wz = om[..., 2]
    p = (sdd / wz)[..., None] * om[..., :2]
    wt = (wtau * np.cos(tau) ** 2 * np.sin(tau))[None, :, None] / ca[:, :, None] / wz ** 3
    return np.asarray(pp) + (wt[..., None] * p).sum((1, 2)) / wt.sum((1, 2))[:, None] / pitch


def shadow_bruteforce(X0, a, sdd, pp, pitch, sod, step=0.02):
    """Independent check: chord-length-weighted centroid summed on a fine detector grid (px)."""
    c0 = project(X0, sdd, pp, pitch, sod)[0]
    rad = a * sdd / pitch / (X0[2] + sod) * 1.3
    g = np.arange(-rad, rad + step, step)
    C, Rr = np.meshgrid(c0[0] + g, c0[1] + g)
    D = np.stack([(C - pp[0]) * pitch, (Rr - pp[1]) * pitch, np.full(C.shape, sdd)], -1)
    D /= np.linalg.norm(D, axis=-1)[..., None]
    V = X0 + np.array([0, 0, sod])
    d2 = V @ V - (D @ V) ** 2
    L = 2 * np.sqrt(np.clip(a * a - d2, 0, None))
    return np.array([(L * C).sum(), (L * Rr).sum()]) / L.sum()


# ---------------------------------------------------------------- distortion
def pincushion(uv, sdd, pp, A, Rs, lam, pitch):
    pp, A = np.asarray(pp, float), np.asarray(A, float)
    P = np.column_stack([(uv - pp) * pitch, np.full(len(uv), sdd)])
    Am = np.array([*((A - pp) * pitch), sdd])
    C = Am + np.array([0.0, 0.0, Rs])
    b, c0 = P @ C, C @ C - Rs * Rs
    with np.errstate(invalid="ignore"):                               # far outside the field: NaN
        t1 = c0 / (b + np.sqrt(b * b - (P * P).sum(1) * c0))          # near (cap) root
    X = t1[:, None] * P
    v, w = X - C, Am - C
    psi = np.arctan2(np.linalg.norm(np.cross(v, w), axis=1), v @ w)
    e = X[:, :2] - Am[:2]
    ne = np.linalg.norm(e, axis=1)
    Q = Am[:2] + (Rs * psi / np.where(ne > 0, ne, 1.0))[:, None] * e
    return pp + (P[:, :2] + lam * (Q - P[:, :2])) / pitch


def distort(uv, k, dp):
    uv = np.atleast_2d(np.asarray(uv, float))
    if dp["kind"] == "none":
        return uv.copy()
    A = np.array(dp["axis_px"])
    q = pincushion(uv, dp["sdd_frame"][k], dp["pp_frame"][k], A, dp["Rs"], dp["lam"], dp["pitch"])
    d = q - A
    rho = np.linalg.norm(d, axis=1) / dp["rho_norm"]
    th = dp["beta_frame"][k] * rho ** 2 * (1 + dp["gamma"] * rho)
    c, s = np.cos(th), np.sin(th)
    q = A + np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]]) + np.array(dp["shift_frame"][k])
    d = q - A
    q = A + d / (1 + d @ np.array(dp["tilt_h"]))[:, None]
    bp = dp.get("bump")
    if bp:
        g = np.exp(-((q - np.array(bp["centre_px"])) ** 2).sum(1) / (2 * bp["sigma_px"] ** 2))
        q = q + bp["amplitude_px"] * g[:, None] * np.array(bp["direction"])
    return q


def make_ii(rng, n, pitch, sdd_k, pp_k, Ms):
    pp0 = np.mean(pp_k, axis=0)
    ang = rng.uniform(0, 2 * np.pi)
    A = pp0 + rng.uniform(5, 30) * np.array([np.cos(ang), np.sin(ang)])
    corners = np.array([[0, 0], [n - 1, 0], [0, n - 1], [n - 1, n - 1]], float)
    rho_norm = float(np.linalg.norm(corners - A, axis=1).max())
    rho_mm = (rho_norm + np.abs(pp_k - A).max()) * pitch       # the cap must cover the whole field
    Rs, sdd0 = rng.uniform(max(250.0, 1.6 * rho_mm), 400), float(np.mean(sdd_k))
    raw = np.linalg.norm(pincushion(corners, sdd0, pp0, A, Rs, 1.0, pitch) - corners, axis=1).max()
    lam = rng.uniform(10, 16) / raw
    gamma = rng.uniform(-0.3, 0.5)
    beta0 = rng.uniform(4, 9) / rho_norm / (1 + gamma)
    nk = np.array([M[:, 2] for M in Ms])
    for _ in range(1000):
        inc, dec = np.radians(rng.uniform(-30, 30)), rng.uniform(0, 2 * np.pi)
        B = np.array([np.cos(inc) * np.cos(dec), np.cos(inc) * np.sin(dec), np.sin(inc)])
        if (nk @ B).min() < -0.05 < 0.05 < (nk @ B).max():
            break
    kappa = rng.uniform(1.4, 2.0)
    Bw = np.array([M.T @ B for M in Ms])
    ha = rng.uniform(0, 2 * np.pi)
    h = rng.uniform(0.002, 0.004) / rho_norm * np.array([np.cos(ha), np.sin(ha)])
    return {"kind": "ii", "pitch": pitch, "axis_px": A.tolist(), "Rs": Rs, "lam": float(lam), "rho_norm": rho_norm,
            "gamma": gamma, "beta0": beta0, "field_B": B.tolist(), "beta_frame": (beta0 * (nk @ B)).tolist(),
            "kappa_px": kappa, "shift_frame": (kappa * np.column_stack([-Bw[:, 1], Bw[:, 0]])).tolist(),
            "tilt_h": h.tolist(), "sdd_frame": [float(s) for s in sdd_k],
            "pp_frame": [list(map(float, p)) for p in pp_k], "bump": None}


# ---------------------------------------------------------------- case
def make_case(name, seed, out):
    out, (pk, dkind, sag) = pathlib.Path(out), SPEC[name]
    (out / "scan").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([int(seed), CASES.index(name), 2718])
    n = int(rng.choice([768, 1024]))
    pitch = rng.uniform(0.32, 0.40) if n == 768 else rng.uniform(0.25, 0.30)   # field <= 31 cm: an II
    sdd0, sod = rng.uniform(950, 1250), rng.uniform(550, 800)
    pp0 = np.full(2, (n - 1) / 2) + rng.uniform(-25, 25, 2)
    P, dia, pmeta = PHANTOMS[pk](rng)
    P, a = np.round(P, 6), dia / 2           # phantom.csv holds 6 decimals: use exactly those
    ids = list(range(1, len(P) + 1))
    nf = int(rng.integers(20, 31))
    lao = np.clip(np.linspace(-55, 55, nf) + rng.uniform(-5, 5, nf), -60, 60)
    cyc, ph0 = rng.uniform(1, 2), rng.uniform(0, 2 * np.pi)
    cran = np.clip(27 * np.sin(2 * np.pi * cyc * np.arange(nf) / nf + ph0) + rng.uniform(-3, 3, nf), -30, 30)
    Ms = [carm_M(x, y) for x, y in zip(lao, cran)]
    for _ in range(200):
        Rt, c_tab = table_placement(rng)
        Rs_ = [M.T @ Rt for M in Ms]
        tilt = np.degrees(np.arccos(np.clip([abs(R[2, 2]) for R in Rs_], 0, 1)))
        if pk == "pds" or tilt.max() <= 68:
            break
    ts = [M.T @ c_tab for M in Ms]
    sdd_k, pp_k = np.full(nf, sdd0), np.tile(pp0, (nf, 1))
    if sag:
        As = rng.uniform(1, 1.5) * rng.choice([-1, 1])          # peak-to-peak <= 3 mm, <= 4 px per axis
        Pc, Pr, Pb = rng.uniform(1.3, 2) * rng.choice([-1, 1]), rng.uniform(1, 1.6), rng.uniform(0.6, 1)
        sl = np.sin(np.radians(lao)) / np.sin(np.radians(60))
        sdd_k = sdd0 + As * sl
        pp_k = pp0 + np.column_stack([Pc * sl, Pr * (1 - np.cos(np.radians(lao))) / 0.5
                                      + Pb * np.sin(np.radians(cran)) / 0.5])
    dp = {"kind": "none"} if dkind == "none" else make_ii(rng, n, pitch, sdd_k, pp_k, Ms)
    # ideal shadow centres (flat detector), then the distortion (the bump is placed on them)
    Xw = [P @ R.T + t for R, t in zip(Rs_, ts)]
    ideal = [shadow_centroid(X, a, sdd_k[k], pp_k[k], pitch, sod) for k, X in enumerate(Xw)]
    if dkind == "ii+bump":
        allq = np.vstack([distort(q, k, dp) for k, q in enumerate(ideal)])
        allq = allq[(np.linalg.norm(allq - pp0, axis=1) > 40) & (np.abs(allq - (n - 1) / 2) < n / 2 - 80).all(1)]
        bd = rng.uniform(0, 2 * np.pi)
        dp["bump"] = {"centre_px": allq[rng.integers(len(allq))].tolist(), "amplitude_px": rng.uniform(1, 2),
                      "sigma_px": rng.uniform(60, 100) / 2, "direction": [np.cos(bd), np.sin(bd)]}
    r_ref = a * sdd0 / sod / pitch
    s0 = rng.uniform(0.035, 0.06)
    A = pp0 if dkind == "none" else np.array(dp["axis_px"])
    rho_c = np.linalg.norm(np.array([[0, 0], [n - 1, 0], [0, n - 1], [n - 1, n - 1]]) - A, axis=1).max() * pitch
    fv = rho_c / np.sqrt(rng.uniform(0.15, 0.3) ** -0.5 - 1)
    frames, id_lists, clean_lists, gross_lists, heldout, err, sig_all = [], [], [], [], [], [], []
    for k in range(nf):
        X, clean = Xw[k], distort(ideal[k], k, dp)
        rapp = a * sdd_k[k] / pitch / (X[:, 2] + sod)
        keep = (clean - 1.1 * rapp[:, None] >= -0.5).all(1) & (clean + 1.1 * rapp[:, None] <= n - 0.5).all(1)
        touch = np.linalg.norm(clean[:, None] - clean[None], axis=2) < rapp[:, None] + rapp[None] + 1.0
        np.fill_diagonal(touch, False)
        keep &= ~touch.any(1)
        idx = np.flatnonzero(keep)
        if rng.random() < 0.5 and len(idx):
            idx = np.sort(rng.choice(idx, len(idx) - int(round(rng.uniform(0.10, 0.20) * len(idx))), replace=False))
        V = (1 + (np.linalg.norm(clean[idx] - A, axis=1) * pitch / fv) ** 2) ** -2
        sig = np.clip(s0 * (r_ref / rapp[idx]) ** 2 / V, 0.03, 0.15)
        noise = rng.normal(size=(len(idx), 2)) * sig[:, None]
        gross = rng.random(len(idx)) < 0.02
        ga = rng.uniform(0, 2 * np.pi, len(idx))
        gmag = np.where(gross, rng.uniform(0.5, 1.5, len(idx)), 0.0)
        meas = clean[idx] + noise + gmag[:, None] * np.column_stack([np.cos(ga), np.sin(ga)])
        err.append(noise), sig_all.append(sig)
        recs = [(meas[j], sig[j], ids[i], clean[i], bool(gross[j])) for j, i in enumerate(idx)]
        if len(idx):
            lo, hi = clean[idx].min(0) - 30, clean[idx].max(0) + 30
            need, tries = int(rng.integers(0, 4)), 0
            while need and tries < 200:
                tries += 1
                s = rng.uniform(lo, hi)
                if np.linalg.norm(clean - s, axis=1).min() < 2 * rapp.max() + 6 or (s < 8).any() or (s > n - 9).any():
                    continue
                recs.append((s, sig[np.argmin(np.linalg.norm(clean[idx] - s, axis=1))], None, None, False))
                need -= 1
        recs = [recs[i] for i in rng.permutation(len(recs))]
        frames.append({"frame": k, "markers": [{"id": None, "x": float(m[0]), "y": float(m[1]), "sigma": float(s),
                                                "flags": []} for m, s, *_ in recs]})
        id_lists.append([r[2] for r in recs])
        clean_lists.append([None if r[3] is None else [float(r[3][0]), float(r[3][1])] for r in recs])
        gross_lists.append([j for j, r in enumerate(recs) if r[4]])
        # held-out points inside the phantom volume, off the grid planes
        if pk == "pds":
            rr = 0.9 * pmeta["radius"] * np.sqrt(rng.uniform(0, 1, m))
            aa = rng.uniform(0, 2 * np.pi, m)
            H = np.column_stack([rr * np.cos(aa), rng.uniform(-0.5, 0.5, m) * pmeta["length"], rr * np.sin(aa)])
        else:
            lo3, hi3 = P.min(0), P.max(0)
            zs = np.array(pmeta["planes_z"])
            pl = rng.integers(len(zs), size=m)
            into = np.where(zs[pl] < 0, 1.0, -1.0) if len(zs) > 1 else rng.choice([-1.0, 1.0], m)
            H = np.column_stack([rng.uniform(lo3[0], hi3[0], m), rng.uniform(lo3[1], hi3[1], m),
                                 zs[pl] + into * rng.uniform(5, 20, m)])
        hp = distort(project(H @ Rs_[k].T + ts[k], sdd_k[k], pp_k[k], pitch, sod), k, dp)
        ok = ((hp >= 0) & (hp <= n - 1)).all(1)
        heldout.append({"frame": k, "points": H[ok].tolist(), "pixels": hp[ok].tolist()})

    sdd_nom = float(np.round(sdd0 * (1 + rng.uniform(-0.02, 0.02)), -1))
    write_free_scan(out, rows=n, cols=n, pitch=float(pitch), sod=float(sod), sdd=sdd_nom, diameter=float(dia),
                    phantom=[(i, *map(float, p)) for i, p in zip(ids, P)], frames=frames)
    sig_all = np.concatenate(sig_all)
    sigma_px = float(np.sqrt(np.mean(sig_all ** 2)))     # RMS of the per-marker sigmas, per axis
    truth = {"sdd": float(np.mean(sdd_k)), "principal_point": np.mean(pp_k, axis=0).tolist(),
             "source": [0.0, 0.0, -float(sod)],
             "poses": [{"frame": k, "R": R.tolist(), "t": t.tolist()} for k, (R, t) in enumerate(zip(Rs_, ts))],
             "sigma_px": sigma_px, "ids_per_frame": id_lists, "heldout": heldout,
             "distortion_kind": dkind, "distortion_params": dp,
             "clean_px": clean_lists, "gross": gross_lists, "tilt_deg": tilt.tolist(),
             "carm": [{"frame": k, "lao": float(x), "cran": float(y)} for k, (x, y) in enumerate(zip(lao, cran))],
             "geometry": {"rows": n, "cols": n, "pixel_pitch": float(pitch), "sod": float(sod),
                          "sphere_diameter": float(dia), "phantom": pmeta}}
    if sag:
        truth["frame_sdd"] = [float(s) for s in sdd_k]
        truth["frame_principal_point"] = [list(map(float, p)) for p in pp_k]
    (out / "truth.json").write_text(json.dumps(truth, sort_keys=True))

    g = np.stack(np.meshgrid(np.linspace(0, n - 1, 33), np.linspace(0, n - 1, 33)), -1).reshape(-1, 2)
    e = np.concatenate(err)
    make_case.last_stats = {
        "per_frame": [len(f["markers"]) for f in frames],
        "max_disp": max(float(np.linalg.norm(distort(g, k, dp) - g, axis=1).max()) for k in range(nf)),
        "rms": float(np.sqrt(np.mean(e ** 2))), "sigma_range": (float(sig_all.min()), float(sig_all.max())),
        "max_tilt": float(tilt.max()), "n_gross": sum(map(len, gross_lists)),
        "n_spurious": sum(x is None for f in id_lists for x in f), "n_real": len(sig_all), "frames": nf,
        "shape": n, "pitch": float(pitch)}
    return {"name": name, "seed": seed, "sigma_px": sigma_px, "distortion_kind": truth["distortion_kind"], "phantom": pk}


# ---------------------------------------------------------------- self-check
def self_check(out):
    """Recompute from the written files alone (truth.json, phantom.csv, scan.yaml, markers.json)."""
    out = pathlib.Path(out)
    tr = json.loads((out / "truth.json").read_text())
    mk = json.loads((out / "markers.json").read_text())
    sc = yaml.safe_load((out / "scan" / "scan.yaml").read_text())
    ph = np.loadtxt(out / "scan" / "phantom.csv", delimiter=",", skiprows=1, ndmin=2)
    id2p = {int(r[0]): r[1:] for r in ph}
    a, pitch = sc["markers"]["diameter"] / 2, sc["detector"]["pixel_pitch"][0]
    sod, dp, n = -tr["source"][2], tr["distortion_params"], sc["detector"]["rows"]
    nf, w_clean, w_held, w_bias, z, off = len(tr["poses"]), 0.0, 0.0, 0.0, [], []
    sdd_k = tr.get("frame_sdd", [tr["sdd"]] * nf)
    pp_k = tr.get("frame_principal_point", [tr["principal_point"]] * nf)
    zs = tr["geometry"]["phantom"].get("planes_z")
    for k, (pose, ids, cl, fr, ho) in enumerate(zip(tr["poses"], tr["ids_per_frame"], tr["clean_px"],
                                                    mk["frames"], tr["heldout"])):
        R, t = np.array(pose["R"]), np.array(pose["t"])
        sel = [j for j, i in enumerate(ids) if i is not None]
        X = np.array([id2p[ids[j]] for j in sel]) @ R.T + t
        c = distort(shadow_centroid(X, a, sdd_k[k], pp_k[k], pitch, sod), k, dp)
        w_clean = max(w_clean, float(np.abs(c - np.array([cl[j] for j in sel])).max()))
        w_bias = max(w_bias, float(np.abs(distort(project(X, sdd_k[k], pp_k[k], pitch, sod), k, dp) - c).max()))
        mm = np.array([[fr["markers"][j]["x"], fr["markers"][j]["y"]] for j in sel])
        sg = np.array([fr["markers"][j]["sigma"] for j in sel])
        good = [q for q, j in enumerate(sel) if j not in tr["gross"][k]]
        z.append(((mm - c) / sg[:, None])[good])
        H = np.array(ho["points"])
        hp = distort(project(H @ R.T + t, sdd_k[k], pp_k[k], pitch, sod), k, dp)
        w_held = max(w_held, float(np.abs(hp - np.array(ho["pixels"])).max()))
        assert ((hp >= 0) & (hp <= n - 1)).all()
        if zs is not None:
            off.append(np.abs(H[:, 2][:, None] - np.array(zs)[None]).min(1))
    z = np.concatenate(z)
    res = {"clean_resid": w_clean, "held_resid": w_held, "shadow_bias_max": w_bias, "pull_rms": float(np.sqrt(np.mean(z ** 2)))}
    if off:
        off = np.concatenate(off)
        res["held_off_plane"] = (float(off.min()), float(off.max()))
    assert w_clean < 1e-9 and w_held < 1e-9, res
    return res


def check_shadow():
    """Quadrature converged, and equal to a brute-force detector-plane integral."""
    X0, a, sdd, pp, pitch, sod = np.array([95.0, -70.0, 40.0]), 1.25, 1100.0, [500.0, 510.0], 0.3, 650.0
    q = shadow_centroid(X0, a, sdd, pp, pitch, sod)[0]
    gt, gw = np.polynomial.legendre.leggauss(30)
    q2 = shadow_centroid(X0, a, sdd, pp, pitch, sod, (gt + 1) * np.pi / 4, gw * np.pi / 4, 2 * np.pi * np.arange(40) / 40)[0]
    qb = shadow_bruteforce(X0, a, sdd, np.array(pp), pitch, sod)
    bias = q - project(X0, sdd, pp, pitch, sod)[0]
    return float(np.abs(q - q2).max()), float(np.abs(q - qb).max()), float(np.linalg.norm(bias))


if __name__ == "__main__":
    conv, brute, bias = check_shadow()
    print(f"shadow quadrature: 12x16 vs 30x40 nodes {conv:.1e} px; vs brute force {brute:.1e} px; "
          f"bias at (95,-70,40) mm {bias:.2e} px")
    assert conv < 1e-10 and brute < 1e-3
    for seed in (1, 2):
        for name in CASES:
            t0 = time.perf_counter()
            info = make_case(name, seed, pathlib.Path("/tmp/carm_indep2") / f"seed{seed}" / name)
            dt = time.perf_counter() - t0
            s = make_case.last_stats
            chk = self_check(pathlib.Path("/tmp/carm_indep2") / f"seed{seed}" / name)
            print(f"s{seed} {name:12s} {s['shape']}px@{s['pitch']:.3f} {s['frames']}fr markers/frame "
                  f"{min(s['per_frame'])}-{max(s['per_frame'])} spur {s['n_spurious']} gross {s['n_gross']}/{s['n_real']} | "
                  f"max dist {s['max_disp']:5.2f}px | noise RMS {s['rms']:.4f} (sigma_px {info['sigma_px']:.4f}, "
                  f"{s['sigma_range'][0]:.3f}-{s['sigma_range'][1]:.3f}) pull {chk['pull_rms']:.3f} | "
                  f"tilt {s['max_tilt']:4.1f} | clean {chk['clean_resid']:.0e} held {chk['held_resid']:.0e} "
                  f"bias {chk['shadow_bias_max']:.1e} off-plane {chk.get('held_off_plane', '-')} | {dt:.2f}s")
