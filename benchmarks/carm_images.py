"""Independent image-level C-arm (image-intensifier) radiographs of sphere phantoms at free, unlogged
poses: a ``motion: free`` scan + ``truth.json`` for the marker detector, written from SCAN_FORMAT.md
alone (nothing under conecal/ or tests/ was read).

Geometry (truth = lab frame): world z along the central ray, source (0,0,-SOD), detector plane z =
SDD-SOD, u = +x, v = +y; pinhole c = pp_c + SDD X/((Z+SOD) pitch), r likewise with Y; pixel (0,0) =
centre of img[0,0], c = column.  X_world = R @ X_phantom + t.  768^2 at 0.30-0.40 mm (clutter case
1024^2 at 0.25), SDD 950-1150, SOD 550-750, principal point within 8 px of the centre; 12 frames,
phantom z tilted 0-55 deg from the beam about a random in-plane axis, any in-plane turn, t = (+-30,
+-30, +-25) mm.
Phantoms (steel spheres, one diameter each, PMMA holder):
  grid   6x6 spheres of 3 mm, pitch p 12-20 mm, z = 0, corner (i,j)=(5,5) missing (35 ids, row-major),
         in a PMMA box |x|,|y| <= 2.5p + (3..6) mm, 6-10 mm thick (its edges lie in the field).
  ball3d 20-30 spheres of 2-3 mm uniform in r <= R-d/2, |z| <= H/2-d/2 (R 30-40, H 40-60), 3-D
         separation >= 1.25 d except 3 planted pairs at 1.2-1.8 d; PMMA cylinder R+3, H/2+3.
  A = mu_PMMA chord(holder) + (mu_steel - mu_PMMA) sum chord(sphere_i) [+ clutter]; mu_steel 0.60-0.85,
  mu_PMMA 0.018-0.024 /mm; exact ray-sphere / -box / -finite-cylinder chords; spheres 8x8 sub-rays per
  pixel; holder and rods at pixel centres, 4x4 sub-rays where |Laplacian A| > 2e-3 (dilated 1 px; max
  error vs 4x4 everywhere ~7e-5).  clutter, per frame: 2 rods on the ray through an in-field sphere
  15-60 mm up/downstream of it (crossing its shadow) + 2 random; 60 % steel wires 0.4-1.0 mm, else Al
  rods 3-6 mm (0.08 /mm), 150-250 mm long; "anatomy" A += max(0, 0.7 + 0.3 f), f a unit-std smooth
  random field.
Chain, in order (p ideal, x measured pixels):
  1 distortion f = twist o pincushion, ideal -> measured (the contract's direction):  q = pc + (p-pc)
    (1 + k1 |p-pc|^2/Rn^2), k1 0.020-0.032 per case, pc near the FOV centre;  x = a + Rot(phi)(q-a),
    phi = s |q-a|^2/Rn^2, s = +-(0.008-0.020) rad and a 60-150 px (x n/768) off centre drawn per
    frame; Rn = cols/2; 9-22 px at the field edge.  Resampled: value at x = ideal chord image at
    f^-1(x) (fixed-point inverse; no intensity Jacobian).
  2 T = exp(-A) in a circular FOV (radius 0.46-0.49 cols, centre within 6 px), 0 outside; blur
    G(sqrt(sb^2 - 0.4^2)) (focal spot, input screen), sb 0.6-1.2 px in total;
  3 quanta T <- Poisson(N0 T)/N0, N0 log-uniform 500-3000 per case x 0.8-1.25 per frame;
  4 glare I <- (1-w) I + w G(sg)*I, w 3-8 %, sg 6-12 % of cols;  5 blur G(0.4) (camera);
  6 vignetting I *= 1 - v (rho/R_fov)^2, v 0.2-0.4; FOV mask;  7 display g = 8 + 242 clip((ln I - lo)
    /(hi - lo), 0, 1), lo/hi = 0.1/99.9 % of ln I in the FOV widened by 5 % (per-frame auto window),
    rounded to uint8;  *_jpeg: cv2 JPEG round trip at quality 75-90.
Stored: non-JPEG cases ``values: transmission``, float32 = grey/255 (display values, NOT physical
I/I0: a log window of it); JPEG cases uint8 frames with ``values: raw``, flat.tif = 255, dark.tif = 0
(uint8), as the contract requires for raw.  log.csv: frame,time only.
truth.json: sdd, sod, pitch, shape, principal_point [c,r], source, poses [{frame,R,t}]; centres[frame]
= [{id, x, y, diameter_px, overlap, hidden_fraction, truncated, crossed, x_proj, y_proj}] for each
sphere whose shadow centroid is in the FOV circle: (x, y) = centroid of its OWN chord image in
measured pixels, sum x L(f^-1(x)) / sum L(f^-1(x)) over 1/8-px sub-rays, NOT f(pinhole of the
centre) = (x_proj, y_proj) (<= ~0.01 px apart: perspective + curvature); diameter_px = equal-area
diameter of the support; hidden_fraction = share of it inside other spheres' supports; overlap =
shares support with / centre < mean diameter + 1 px from another; truncated = support crosses the
FOV circle or border; crossed = a rod's shadow crosses it.  overlap_pairs[frame] = [i, j, depth =
1 - dist/mean diameter] (< 0: gap < 1 px).  nominal_magnification_error = (sdd_nom/sod_nom)/(SDD/SOD)
- 1 (at the lab origin): -0.25/+0.25 for *_m25/*_p25 (sod changed), else within 2.5 % (sdd_nom
within 1.5 %).  noise_sigma[frame] = 1.4826 MAD of (stored - noise-free grey) in the FOV (grey
levels, incl. quantisation / JPEG).  distortion_params[frame] = k1, pc, s, a, rn (= Rn).
heldout[frame]: 16 points in the phantom volume, true pixels f(pinhole), kept in the FOV.  Also fov
[c, r, radius], blur_sigma_px, glare [w, sg], vignetting, N0, jpeg_quality, mu_*, rods (world).
"""
import itertools
import json
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import tifffile
import yaml
from scipy import ndimage
from scipy.spatial.transform import Rotation

CASES = ["grid_ii", "grid_ii_jpeg", "ball3d_ii", "ball3d_ii_m25", "ball3d_ii_p25", "ball3d_clutter_jpeg"]
NF, SUB = 12, 8


class Distortion:
    """Forward ideal -> measured: S-twist about a after pincushion about pc (module docstring)."""

    def __init__(self, k1=0.0, pc=(0.0, 0.0), s=0.0, a=(0.0, 0.0), rn=1.0):
        self.k1, self.pc, self.s, self.a, self.rn = k1, tuple(pc), s, tuple(a), rn

    def fwd(self, c, r):
        dc, dr = c - self.pc[0], r - self.pc[1]
        g = 1 + self.k1 * (dc * dc + dr * dr) / self.rn ** 2
        ec, er = self.pc[0] + dc * g - self.a[0], self.pc[1] + dr * g - self.a[1]
        co, si = np.cos(phi := self.s * (ec * ec + er * er) / self.rn ** 2), np.sin(phi)
        return self.a[0] + co * ec - si * er, self.a[1] + si * ec + co * er

    def inv(self, c, r, n=10):                  # fixed point; contraction ~0.15 per step
        x, y = c, r
        for _ in range(n):
            fc, fr = self.fwd(x, y)
            x, y = x - (fc - c), y - (fr - r)
        return x, y


def _rng(seed, name, k=None):
    return np.random.default_rng([seed, zlib.crc32(name.encode())] + ([] if k is None else [k]))


def _ball3d(g, sc):
    diam, R, H = round(g.uniform(2, 3), 2), g.uniform(30, 40), g.uniform(40, 60)
    nb, P, rm, zm = int(g.integers(20, 31)), [], R - diam / 2, H / 2 - diam / 2
    while len(P) < nb:
        q, u = np.array([*g.uniform(-rm, rm, 2), g.uniform(-zm, zm)]), g.normal(size=3)
        if len(P) < 6 and len(P) % 2 == 1:            # planted close pair
            q = P[-1] + u / np.linalg.norm(u) * diam * g.uniform(1.2, 1.8)
        sep = (1.2 if len(P) < 6 else 1.25) * diam
        if np.hypot(q[0], q[1]) <= rm and abs(q[2]) <= zm and all(np.linalg.norm(q - o) >= sep for o in P):
            P.append(q)
    sc.update(cyl=(R, H), holder=(R + 3, H / 2 + 3))
    return P, diam


def _rods(g, sc, k):
    R, t = sc["poses"][k]
    S, W = np.array([0, 0, -sc["sod"]]), sc["P"] @ R.T + t
    c, r = _project(sc, W)
    ok, out = np.flatnonzero(np.hypot(c - sc["fov"][0], r - sc["fov"][1]) < 0.8 * sc["fov"][2]), []
    for j in range(4):
        if j < 2 and len(ok):                          # on the ray through a sphere: crosses its shadow
            Ck = W[g.choice(ok)]
            A = Ck + (Ck - S) / np.linalg.norm(Ck - S) * g.choice([-1, 1]) * g.uniform(15, 60) \
                + g.normal(size=3) * sc["diam"] * 0.2
        else:
            A = np.array([g.uniform(-60, 60), g.uniform(-60, 60), g.uniform(-80, 80)])
        ax, wire = np.array([*g.normal(size=2), 0.3 * g.normal()]), g.random() < 0.6
        out.append((A, ax / np.linalg.norm(ax), g.uniform(0.2, 0.5) if wire else g.uniform(1.5, 3),
                    g.uniform(75, 125), sc["mu_s"] if wire else 0.08))
    return out


def _setup(name, seed):
    g = _rng(seed, name)
    sc = {"name": name, "seed": seed, "kind": "grid" if name.startswith("grid") else "ball3d",
          "clutter": "clutter" in name, "jpeg": name.endswith("_jpeg")}
    n = 1024 if sc["clutter"] else 768
    sc.update(n=n, pitch=0.25 if n == 1024 else round(g.uniform(0.30, 0.40), 4),
              sdd=g.uniform(950, 1150), sod=g.uniform(550, 750),
              pp=((n - 1) / 2 + g.uniform(-8, 8), (n - 1) / 2 + g.uniform(-8, 8)),
              mu_s=g.uniform(0.60, 0.85), mu_p=g.uniform(0.018, 0.024))
    if sc["kind"] == "grid":
        p, diam = g.uniform(12, 20), 3.0
        P = [((i - 2.5) * p, (j - 2.5) * p, 0.0) for j in range(6) for i in range(6) if (i, j) != (5, 5)]
        sc.update(gpitch=p, plate=(2.5 * p + g.uniform(3, 6), 2.5 * p + g.uniform(3, 6), g.uniform(3, 5)))
    else:
        P, diam = _ball3d(g, sc)
    sc["P"], sc["diam"] = np.array(P, float), diam
    tilts, c0 = np.clip(g.permutation(np.linspace(0, 55, NF)) + g.uniform(-2, 2, NF), 0, 55), (n - 1) / 2
    sc["fov"] = (c0 + g.uniform(-6, 6), c0 + g.uniform(-6, 6), g.uniform(0.46, 0.49) * n)
    k1, pc = g.uniform(0.02, 0.032), (sc["fov"][0] + g.uniform(-5, 5), sc["fov"][1] + g.uniform(-5, 5))
    sc["poses"], sc["dist"] = [], []
    for k in range(NF):
        psi, gam, ang = g.uniform(0, 2 * np.pi, 3)
        R = Rotation.from_rotvec(np.radians(tilts[k]) * np.array([np.cos(psi), np.sin(psi), 0])).as_matrix() \
            @ Rotation.from_rotvec([0, 0, gam]).as_matrix()
        sc["poses"].append((R, np.array([g.uniform(-30, 30), g.uniform(-30, 30), g.uniform(-25, 25)])))
        off = g.uniform(60, 150) * n / 768
        sc["dist"].append(Distortion(k1, pc, g.choice([-1, 1]) * g.uniform(0.008, 0.02),
                                     (c0 + off * np.cos(ang), c0 + off * np.sin(ang)), n / 2))
    n0 = np.exp(g.uniform(np.log(500), np.log(3000)))
    sc.update(N0=np.clip(n0 * g.uniform(0.8, 1.25, NF), 500, 5000), blur=g.uniform(0.6, 1.2),
              glare=(g.uniform(0.03, 0.08), g.uniform(0.06, 0.12) * n), vign=g.uniform(0.2, 0.4),
              q=int(g.integers(75, 91)))
    e = {"_m25": -0.25, "_p25": 0.25}.get(name[-4:], g.uniform(-0.025, 0.025))
    sdd_nom = sc["sdd"] * (1 + g.uniform(-0.015, 0.015))
    sc.update(mag_err=e, sdd_nom=sdd_nom, sod_nom=sdd_nom / (sc["sdd"] / sc["sod"] * (1 + e)))
    sc["rods"] = [_rods(g, sc, k) if sc["clutter"] else [] for k in range(NF)]
    return sc


def _project(sc, W):
    z = (W[:, 2] + sc["sod"]) * sc["pitch"]
    return sc["pp"][0] + sc["sdd"] * W[:, 0] / z, sc["pp"][1] + sc["sdd"] * W[:, 1] / z


def _dirs(sc, c, r):
    x, y = (c - sc["pp"][0]) * sc["pitch"], (r - sc["pp"][1]) * sc["pitch"]
    nrm = np.sqrt(x * x + y * y + sc["sdd"] ** 2)
    return x / nrm, y / nrm, sc["sdd"] / nrm


def _cyl_chord(o, dx, dy, dz, rad, hh):
    """Chord of rays o + s d (d unit) through {x^2+y^2 <= rad^2, |z| <= hh} (local frame)."""
    a, b = dx * dx + dy * dy, o[0] * dx + o[1] * dy
    disc = b * b - a * (o[0] ** 2 + o[1] ** 2 - rad * rad)
    sq, aa = np.sqrt(np.maximum(disc, 0)), np.maximum(a, 1e-18)
    dzs = np.where(np.abs(dz) > 1e-18, dz, 1e-18)
    z1, z2 = (-hh - o[2]) / dzs, (hh - o[2]) / dzs
    ch = np.minimum((-b + sq) / aa, np.maximum(z1, z2)) - np.maximum((-b - sq) / aa, np.minimum(z1, z2))
    return np.where(disc > 0, np.maximum(ch, 0), 0.0)


def _box_chord(o, dx, dy, dz, h):
    lo, hi = -np.inf, np.inf
    for oc, dc, hc in zip(o, (dx, dy, dz), h):
        ds = np.where(np.abs(dc) > 1e-18, dc, 1e-18)
        s1, s2 = (-hc - oc) / ds, (hc - oc) / ds
        lo, hi = np.maximum(lo, np.minimum(s1, s2)), np.minimum(hi, np.maximum(s1, s2))
    return np.maximum(hi - lo, 0)


def _local(o, d, R):
    """Point o (3,) and directions d (3 arrays) in the frame whose axes are the columns of R."""
    return R.T @ o, [R[0, i] * d[0] + R[1, i] * d[1] + R[2, i] * d[2] for i in range(3)]


def _rod_frame(ax):
    e1 = np.cross(ax, [0, 0, 1.0] if abs(ax[2]) < 0.9 else [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(ax, e1), ax])


def _bg_atten(sc, k, c, r, clutter=True):
    """Holder (+ rods) attenuation along the rays through ideal detector points (c, r)."""
    d, (R, t), S = _dirs(sc, c, r), sc["poses"][k], np.array([0.0, 0.0, -sc["sod"]])
    o, dl = _local(S - t, d, R)
    A = sc["mu_p"] * (_box_chord(o, *dl, sc["plate"]) if sc["kind"] == "grid" else _cyl_chord(o, *dl, *sc["holder"]))
    for (P0, ax, rad, hl, mu) in sc["rods"][k] if clutter else []:
        o, dl = _local(S - P0, d, _rod_frame(ax))
        A = A + mu * _cyl_chord(o, *dl, rad, hl)
    return A


def _background(sc, k, dist, clutter=True):
    """Holder/rod attenuation per measured pixel: the inverse distortion on a 4-px grid (cubic
    spline), exact chords at pixel centres, 4x4 sub-rays (local Jacobian) where |Laplacian| > 2e-3."""
    n, j = sc["n"], np.arange(-6, sc["n"] // 4 + 6) * 4 + 1.5
    Y, X = np.meshgrid(j, j, indexing="ij")
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    co = [(rr - 1.5) / 4 + 6, (cc - 1.5) / 4 + 6]
    ic, ir = (ndimage.map_coordinates(m, co, order=3, mode="nearest") for m in dist.inv(X, Y))
    A = _bg_atten(sc, k, ic, ir, clutter)
    jy, jx = np.nonzero(ndimage.binary_dilation(np.abs(ndimage.laplace(A)) > 2e-3))
    if len(jy):
        (ic_r, ic_c), (ir_r, ir_c) = np.gradient(ic), np.gradient(ir)
        acc, o = np.zeros(len(jy)), (np.arange(4) + 0.5) / 4 - 0.5
        for oy in o:
            for ox in o:
                acc += _bg_atten(sc, k, ic[jy, jx] + ic_c[jy, jx] * ox + ic_r[jy, jx] * oy,
                                 ir[jy, jx] + ir_c[jy, jx] * ox + ir_r[jy, jx] * oy, clutter)
        A[jy, jx] = acc / 16
    return A


def _spheres(sc, k, dist, A=None, clutter=True):
    """Own-shadow truth of frame k's spheres; adds their box-averaged (mu_s-mu_p)*chord to A if given."""
    (R, t), S, a, n, (fc, fr, fR) = sc["poses"][k], np.array([0, 0, -sc["sod"]]), sc["diam"] / 2, sc["n"], sc["fov"]
    W = sc["P"] @ R.T + t
    mc, mr = dist.fwd(*_project(sc, W))
    half = np.ceil(a * sc["sdd"] / ((W[:, 2] + sc["sod"]) * sc["pitch"]) * 1.3 + 2).astype(int)
    off, out, hit = (np.arange(SUB) + 0.5) / SUB - 0.5, [], set()
    for i in np.flatnonzero((mc > -half) & (mr > -half) & (mc < n - 1 + half) & (mr < n - 1 + half)):
        i0, j0, h = int(round(mc[i])) - half[i], int(round(mr[i])) - half[i], half[i]
        X, Y = np.meshgrid((np.arange(i0, i0 + 2 * h + 1)[:, None] + off).ravel(),
                           (np.arange(j0, j0 + 2 * h + 1)[:, None] + off).ravel())
        d = _dirs(sc, *dist.inv(X, Y, n=8))

        def chord(j):
            w = S - W[j]
            wd = w[0] * d[0] + w[1] * d[1] + w[2] * d[2]
            return 2 * np.sqrt(np.maximum(a * a - (w @ w - wd * wd), 0))
        L = chord(i)
        m = L > 0
        assert not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()), "box too small"
        x, y = (X * L).sum() / L.sum(), (Y * L).sum() / L.sum()
        if A is not None:
            pix = L.reshape(2 * h + 1, SUB, 2 * h + 1, SUB).mean((1, 3)) * (sc["mu_s"] - sc["mu_p"])
            a0, a1, b0, b1 = max(j0, 0), min(j0 + 2 * h + 1, n), max(i0, 0), min(i0 + 2 * h + 1, n)
            if a1 > a0 and b1 > b0:
                A[a0:a1, b0:b1] += pix[a0 - j0:a1 - j0, b0 - i0:b1 - i0]
        if np.hypot(x - fc, y - fr) > fR:
            continue
        cov = np.zeros_like(m)
        for j in np.flatnonzero(np.hypot(mc - mc[i], mr - mr[i]) < 2 * half.max() + 2):
            cj = (chord(j) > 0) & m
            if j != i and cj.any():
                cov |= cj
                hit.add((min(i, j), max(i, j)))
        crossed = False
        for (P0, ax, rad, hl, mu) in sc["rods"][k] if clutter else []:
            o, dl = _local(S - P0, d, _rod_frame(ax))
            crossed |= bool((_cyl_chord(o, *[v[m] for v in dl], rad, hl) > 0).any())
        Xm, Ym = X[m], Y[m]
        outside = (np.hypot(Xm - fc, Ym - fr) > fR) | (np.minimum(Xm, Ym) < -0.5) | (np.maximum(Xm, Ym) > n - .5)
        out.append({"id": int(i), "x": float(x), "y": float(y), "diameter_px": 2 * np.sqrt(m.sum() / np.pi) / SUB,
                    "hidden_fraction": float(cov.sum() / m.sum()), "truncated": bool(outside.any()),
                    "crossed": crossed, "x_proj": float(mc[i]), "y_proj": float(mr[i])})
    pairs = [[p["id"], q["id"], float(1 - dd / md)] for p, q in itertools.combinations(out, 2)
             for dd, md in [(np.hypot(p["x"] - q["x"], p["y"] - q["y"]), (p["diameter_px"] + q["diameter_px"]) / 2)]
             if dd < md + 1 or (p["id"], q["id"]) in hit]
    for p in out:
        p["overlap"] = p["hidden_fraction"] > 0 or any(p["id"] in pr[:2] for pr in pairs)
    return out, pairs


def _anatomy(sc, k):
    g, n = _rng(sc["seed"], sc["name"], 500 + k), sc["n"]
    f = sum(wt * cv2.resize(g.normal(size=(m, m)), (n, n), interpolation=cv2.INTER_CUBIC)
            for m, wt in ((12, 1.0), (32, 0.35)))
    f = cv2.GaussianBlur(f, (0, 0), n / 48)
    return np.maximum(0.7 + 0.3 * (f - f.mean()) / f.std(), 0)


def _chain(sc, k, T, noise_rng=None):
    n, (fc, fr, fR) = sc["n"], sc["fov"]
    rho = np.hypot(np.arange(n) - fc, np.arange(n)[:, None] - fr) / fR
    mask = rho <= 1
    I = cv2.GaussianBlur(T * mask, (0, 0), np.sqrt(sc["blur"] ** 2 - 0.16))
    if noise_rng is not None:
        I = noise_rng.poisson(I * sc["N0"][k]) / sc["N0"][k]
    (w, sg), small = sc["glare"], cv2.resize(I.astype(np.float32), (n // 4, n // 4), interpolation=cv2.INTER_AREA)
    I = (1 - w) * I + w * cv2.resize(cv2.GaussianBlur(small, (0, 0), sg / 4), (n, n), interpolation=cv2.INTER_LINEAR)
    return cv2.GaussianBlur(I, (0, 0), 0.4) * (1 - sc["vign"] * rho ** 2) * mask, mask


def _display(L, mask, lohi=None):
    if lohi is None:
        lo, hi = np.percentile(L[mask], [0.1, 99.9])
        lohi = (lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
    return np.where(mask, 8 + 242 * np.clip((L - lohi[0]) / (lohi[1] - lohi[0]), 0, 1), 0.0), lohi


def render_frame(sc, k, distort=True, effects=True, spheres=True):
    """(uint8 frame, centres, pairs, noise sigma); effects=False: (A before the chain w/o clutter, centres, pairs)."""
    dist = sc["dist"][k] if distort else Distortion()
    A = _background(sc, k, dist, clutter=effects)
    cen, pairs = _spheres(sc, k, dist, A if spheres else None, clutter=effects)
    if not effects:
        return A, cen, pairs
    T = np.exp(-(A + _anatomy(sc, k))) if sc["clutter"] else np.exp(-A)
    I, mask = _chain(sc, k, T, _rng(sc["seed"], sc["name"], 1000 + k))
    g, lohi = _display(np.log(np.maximum(I, 1e-5)), mask)
    g0, _ = _display(np.log(np.maximum(_chain(sc, k, T)[0], 1e-5)), mask, lohi)
    g8 = np.round(g).astype(np.uint8)
    if sc["jpeg"]:
        g8 = cv2.imdecode(cv2.imencode(".jpg", g8, [cv2.IMWRITE_JPEG_QUALITY, sc["q"]])[1], cv2.IMREAD_GRAYSCALE)
    dev = (g8 - g0)[ndimage.binary_erosion(mask, iterations=6)]
    return g8, cen, pairs, float(1.4826 * np.median(np.abs(dev - np.median(dev))))


def _heldout(sc, k):
    g = _rng(sc["seed"], sc["name"], 2000 + k)
    if sc["kind"] == "grid":
        pts = g.uniform(-1, 1, (16, 3)) * np.array(sc["plate"])
    else:
        rad, ang = sc["cyl"][0] * np.sqrt(g.random(16)), g.uniform(0, 2 * np.pi, 16)
        pts = np.column_stack([rad * np.cos(ang), rad * np.sin(ang), g.uniform(-0.5, 0.5, 16) * sc["cyl"][1]])
    R, t = sc["poses"][k]
    c, r = sc["dist"][k].fwd(*_project(sc, pts @ R.T + t))
    keep = np.hypot(c - sc["fov"][0], r - sc["fov"][1]) < sc["fov"][2]
    return {"frame": k, "points": pts[keep].tolist(), "pixels": np.column_stack([c, r])[keep].tolist()}


def make_case(name, seed, out):
    out, sc = Path(out), _setup(name, seed)
    (out / "scan").mkdir(parents=True, exist_ok=True)
    n, res = sc["n"], [render_frame(sc, k) for k in range(NF)]
    stack, raw = np.stack([r[0] for r in res]), sc["jpeg"]
    scan = {"format": "conecal-scan/1", "motion": "free", "projections": "projections.tif",
            "values": "raw" if raw else "transmission", "log": "log.csv",
            "detector": {"rows": n, "cols": n, "pixel_pitch": [sc["pitch"], sc["pitch"]]},
            "nominal": {"sod": round(float(sc["sod_nom"]), 3), "sdd": round(float(sc["sdd_nom"]), 3)},
            "markers": {"diameter": float(sc["diam"]), "phantom": "phantom.csv"}}
    tif = dict(photometric="minisblack")
    if raw:
        scan.update(flat="flat.tif", dark="dark.tif")
        tifffile.imwrite(out / "scan" / "flat.tif", np.full((n, n), 255, np.uint8), **tif)
        tifffile.imwrite(out / "scan" / "dark.tif", np.zeros((n, n), np.uint8), **tif)
    tifffile.imwrite(out / "scan" / "projections.tif", stack if raw else (stack / 255.0).astype(np.float32), **tif)
    (out / "scan" / "scan.yaml").write_text(yaml.safe_dump(scan, sort_keys=False))
    (out / "scan" / "phantom.csv").write_text(
        "id,x,y,z\n" + "".join(f"{i},{x:.6f},{y:.6f},{z:.6f}\n" for i, (x, y, z) in enumerate(sc["P"])))
    (out / "scan" / "log.csv").write_text("frame,time\n" + "".join(f"{k},{2.0 * k:.1f}\n" for k in range(NF)))
    dk = "ii_pincushion_stwist"
    truth = {"sdd": sc["sdd"], "sod": sc["sod"], "pitch": sc["pitch"], "shape": [n, n],
             "principal_point": list(sc["pp"]), "source": [0.0, 0.0, -sc["sod"]],
             "poses": [{"frame": k, "R": R.tolist(), "t": t.tolist()} for k, (R, t) in enumerate(sc["poses"])],
             "centres": [r[1] for r in res], "overlap_pairs": [r[2] for r in res],
             "nominal_magnification_error": sc["mag_err"], "noise_sigma": [r[3] for r in res],
             "distortion_kind": dk, "distortion_params": [dict(frame=k, **vars(d)) for k, d in enumerate(sc["dist"])],
             "heldout": [_heldout(sc, k) for k in range(NF)], "fov": list(sc["fov"]), "blur_sigma_px": sc["blur"],
             "glare": list(sc["glare"]), "vignetting": sc["vign"], "N0": sc["N0"].tolist(),
             "jpeg_quality": sc["q"] if raw else None, "mu_steel": sc["mu_s"], "mu_pmma": sc["mu_p"],
             "values": scan["values"], "phantom": sc["kind"],
             "rods": [[{"point": p.tolist(), "axis": a.tolist(), "radius": rd, "half_length": hl, "mu": mu}
                       for (p, a, rd, hl, mu) in rods] for rods in sc["rods"]]}
    (out / "truth.json").write_text(json.dumps(truth, default=float))
    return {"name": name, "seed": seed, "phantom": sc["kind"], "distortion_kind": dk, "nominal_error": sc["mag_err"]}


def _quad_centroids(sc, k, dist, ids, m=40):
    """Independent check: the chord-weighted shadow centroid as a 3-D integral over each sphere,
    sum f(p(X)) w / sum w, w = |det Df(p)| / (cos^3(theta) |X-S|^2), on a (2m)^3 voxel grid."""
    (R, t), a, S, h = sc["poses"][k], sc["diam"] / 2, np.array([0.0, 0.0, -sc["sod"]]), 0.5
    u = (np.arange(2 * m) + 0.5 - m) / m * a
    G = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3)
    G, res = G[(G ** 2).sum(1) <= a * a], {}
    for i in ids:
        X = G + sc["P"][i] @ R.T + t
        s = np.linalg.norm(X - S, axis=1)
        c, r = _project(sc, X)
        (a1, b1), (a2, b2) = dist.fwd(c + h, r), dist.fwd(c - h, r)
        (a3, b3), (a4, b4) = dist.fwd(c, r + h), dist.fwd(c, r - h)
        wt = ((a1 - a2) * (b3 - b4) - (a3 - a4) * (b1 - b2)) / (((X[:, 2] - S[2]) / s) ** 3 * s ** 2)
        fc, fr = dist.fwd(c, r)
        res[i] = ((fc * wt).sum() / wt.sum(), (fr * wt).sum() / wt.sum())
    return res


def _selfcheck(name, seed=1):
    sc = _setup(name, seed)
    own, cen, _ = render_frame(sc, 0, distort=False, effects=False)
    own = own - render_frame(sc, 0, distort=False, effects=False, spheres=False)[0]
    q = _quad_centroids(sc, 0, Distortion(), [c["id"] for c in cen])
    dq, dpix = max(np.hypot(c["x"] - q[c["id"]][0], c["y"] - q[c["id"]][1]) for c in cen), []
    for c in cen:            # isolated: no other centre within 2.5 diameters
        if c["truncated"] or sum(np.hypot(o["x"] - c["x"], o["y"] - c["y"]) < 2.5 * c["diameter_px"] for o in cen) > 1:
            continue
        h, r0, c0 = int(c["diameter_px"]), int(round(c["y"])), int(round(c["x"]))
        win, (rr, cc) = own[r0 - h:r0 + h + 1, c0 - h:c0 + h + 1], np.mgrid[r0 - h:r0 + h + 1, c0 - h:c0 + h + 1]
        dpix.append(np.hypot((cc * win).sum() / win.sum() - c["x"], (rr * win).sum() / win.sum() - c["y"]))
    cen_d, _ = _spheres(sc, 0, sc["dist"][0])
    qd = _quad_centroids(sc, 0, sc["dist"][0], [c["id"] for c in cen_d])
    dd = max(np.hypot(c["x"] - qd[c["id"]][0], c["y"] - qd[c["id"]][1]) for c in cen_d)
    dproj = max(np.hypot(c["x"] - c["x_proj"], c["y"] - c["y_proj"]) for c in cen_d)
    rr, cc = np.mgrid[0:sc["n"], 0:sc["n"]].astype(float)
    dm = np.hypot(*(np.array(sc["dist"][0].fwd(cc, rr)) - [cc, rr]))
    dmax = dm[np.hypot(cc - sc["fov"][0], rr - sc["fov"][1]) < sc["fov"][2]].max()
    print(f"  check {name}: undistorted truth vs 3-D quadrature max {dq:.4f} px; isolated spheres (n={len(dpix)}) "
          f"pixel-image own-shadow centroid vs truth max {max(dpix):.4f} px; distorted truth vs quadrature max "
          f"{dd:.4f} px; |truth - f(proj centre)| max {dproj:.4f} px; distortion in FOV max {dmax:.1f} px")
    return max(dq, max(dpix), dd)


if __name__ == "__main__":
    root = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/carm_images")
    for name in CASES:
        t0 = time.time()
        info = make_case(name, 1, root / name)
        dt, tr = time.time() - t0, json.loads((root / name / "truth.json").read_text())
        img = tifffile.imread(root / name / "scan" / "projections.tif")
        cv2.imwrite(str(root / f"{name}.png"), img[0] if img.dtype == np.uint8 else np.round(img[0] * 255).astype("u1"))
        allc, depth = [c for f in tr["centres"] for c in f], [p[2] for f in tr["overlap_pairs"] for p in f]
        dia = [c["diameter_px"] for c in allc]
        print(f"{name}: {info['phantom']}, {dt:.1f} s, {tr['shape']} px @ {tr['pitch']} mm, sdd {tr['sdd']:.0f} "
              f"sod {tr['sod']:.0f}, nominal mag error {tr['nominal_magnification_error']:+.3f}\n  spheres/frame "
              f"{[len(c) for c in tr['centres']]}\n  overlapping pairs/frame {[len(p) for p in tr['overlap_pairs']]} "
              f"(depth {min(depth, default=0):.2f}..{max(depth, default=0):.2f})\n  diameter px {min(dia):.1f}.."
              f"{max(dia):.1f}, noise sigma grey {np.round(tr['noise_sigma'], 2).tolist()}, N0 {tr['N0'][0]:.0f}, "
              f"blur {tr['blur_sigma_px']:.2f}, crossed {sum(c['crossed'] for c in allc)}, truncated "
              f"{sum(c['truncated'] for c in allc)}, overlapping spheres {sum(c['overlap'] for c in allc)}")
    worst = max(_selfcheck(n) for n in ("grid_ii", "ball3d_ii", "ball3d_clutter_jpeg"))
    print("centroid self-check", "OK" if worst < 0.01 else "FAILED", f"(worst {worst:.4f} px)")
