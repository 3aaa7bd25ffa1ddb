"""Independent C-arm / radiography test-data generator (third, from-scratch version).

Writes scan directories in the `conecal-scan/1` format (`motion: free`, `values: raw`
with flat/dark) plus a `truth.json`, for five marker-phantom cases.  Physics below is
written from first principles; none of it is shared with the tool under test.

Geometry (lab frame = detector frame of SCAN_FORMAT.md, mm)
  * detector plane z = sdd - sod, u = +x (columns), v = +y (rows), square pixels `pitch`;
    the lab point of pixel (c, r) is O + (c*p, r*p, 0) with O the centre of pixel [0,0].
  * mean source (0, 0, -sod); principal point (foot of the perpendicular from the source) is
    placed 0-15 px from the detector centre.  Per frame the source sags relative to the detector:
    S_k = (0,0,-sod) + (1.2 sin a, 0.8 sin b, 0.6 cos a - 0.6) mm + N(0, 0.1 mm), a/b the orbit and
    angulation.  truth: frame_sdd = z_det - S_kz, frame_principal_point = foot of S_k; sdd and
    principal_point are their means, sod = |mean S_k|.
  * C-arm view k: Rc = Ry(orbit a) Rx(angulation b) Rz(in-plane g), a, b ~ U(-45, 45) deg,
    g ~ U(-180, 180) deg; the phantom sits fixed in the room at orientation Rph plus a random
    table shift s (N(0, 8 mm), or N(0, 40 mm) in ~25 % "edge" frames that truncate some shadows).
    Pose: P_lab = R p + t with R = Rc^T Rph, t = Rc^T s.  Planar phantoms: tilt <= 55 deg.
  * Earth field (room frame) B = unit(0.30, 0.80, 0.52); beta_k = B . (Rc e_z) drives the S-twist.
Attenuation (1/mm): steel 0.45, PMMA 0.02, aluminium 0.08.  Each sphere adds
  (0.45 - 0.02) * chord, chord = 2 sqrt(a^2 - h^2) exactly along the point-source ray (all beads
  are embedded in PMMA); plastic bodies are exact convex chords (half-space polytopes, a finite
  cylinder).  Background: Beer-Lambert at the 4 pixel corners, averaged; near each sphere
  (its exact silhouette-cone box + 2 px) 6x6 sub-samples per pixel, exp() per sub-sample,
  then the pixel mean.  Sub-sample positions are taken in MEASURED (distorted) coordinates and
  mapped to ideal ones (exact fixed-point inversion of the forward distortion at pixel corners,
  bilinear inside a pixel).  Focal-spot blur on the transmission image: Gaussian sigma
  (0.5-0.8 px) or, for grid_fp_step, a uniform disc of radius 1.1 px.
Distortion (ideal pinhole (c, r) -> measured (c + dc, r + dr), px), per case:
  pds_helix_ii  'poly3': full 2-D cubic, dc = sum_{i+j<=3} A_ij x^i y^j, dr = sum B_ij x^i y^j,
      x = (c - fc_c)/Rf, y = (r - fc_r)/Rf (fc, Rf = field centre/radius).  Per frame the 20
      coefficients are the least-squares projection (ideal points on a 16 px grid, rho <= 1.05 Rf)
      of a physical field: pincushion K q |q|^2 / Rf^3 (q = p - cd, K 8-15 px, cd 15-30 px from the
      principal point) + S-twist: rotation about cd by theta = beta_k (tau0 + tau1 |q|/Rf) (linear
      in radius) + shift beta_k * s.  The polynomial IS the truth (`fit_rms_px` = its deviation
      from the physical field).
  cage_ii_jpeg 'tan_twist': q = p - cd, rho' = L tan(|q|/L) (strong pincushion, 15-25 px at rho = Rf,
      cd 20-40 px from the pp), then rotation about cd by theta = beta_k (tau0 + tau2 (rho'/Rf)^2),
      then shift beta_k * s:  m = cd + Rot(theta) q rho'/|q| + beta_k s.
  grid_ii_local 'radial_dent' (static): m = p + q (k1 (|q|/Rf)^2 + k2 (|q|/Rf)^4)
      + A exp(-|p - pd|^2 / (2 sig^2)) e,  Rf (k1 + k2) = 5-8 px, A = 1.5-2.5 px, sig = 26 px
      (FWHM 61 px), e a fixed unit vector, pd ~70 px from the field centre (a dent in the screen).
  grid_fp_step, ball_sym_ff: 'none' (identity).
  `distortion_samples` lists ideal points (64 px grid inside the field) and per frame their
  measured positions, so a grader needs no code from here.
Imaging chains (X = blurred transmission; `field` = circle radius Rf about fc with an erf edge
  of width 4 px for intensifiers, the whole image for flat panels):
  intensifier: counts ~ Poisson(I0 X); Y = counts/I0 * field; veiling glare
      E = (1-g) Y + g lowpass(Y) (Gaussian ~80 px), vignetting E *= 1 - v (rho/Rf)^2, + black level,
      + N(0, se) electronic noise, then a display curve:
      gamma10  uint16 = round(1023 clip(E/(1+black))^0.7)          (pds_helix_ii)
      log8     uint8 = round(255 clip(ln(E/0.02)/ln(1.1/0.02))), then JPEG q70 (cage_ii_jpeg)
      lin8     uint8 = round(255 clip(E/(1+black)))              (grid_ii_local)
      flat = the chain with X = 1 and no noise; dark = the chain with X = 0 and no noise.
  flat panel raw: uint16 = dark(r, c) + gain(c) conv Poisson(I0 X) + N(0, se), dark = offset +
      column ripple + fixed pattern; grid_fp_step has a per-column gain (sd 4 %) and its flat.tif /
      dark.tif are 8-page noisy stacks (to be averaged); ball_sym_ff has single noiseless ones.
Phantoms (fixed per case; ids = row index of phantom.csv):
  pds_helix_ii: PMMA cylinder r 50 mm, 150 mm long (axis = phantom z); 30 beads on a helix r 44 mm,
      1.25 turns, z -66..66; binary code (1 = 3.2 mm, 0 = 1.6 mm): 110100111010001101100101110001.
      scan.yaml markers.diameter = 1.6 (the contract has a single diameter; sizes in truth).
  cage_ii_jpeg: two 110x110x6 mm PMMA plates, mid-planes z = -30 / +30, 14 irregular 2 mm beads each
      (min spacing 12 mm), ids 0 and 19 are 4 mm.
  grid_fp_step / grid_ii_local: 7x7 grid pitch 10 mm (x, y in -30..30) minus (20, -10): 48 beads of
      2 mm in a 5 mm PMMA plate (z = +-2.5).  fp_step: plate only x in [-35.5, 150], y in [-150, 32.5]
      (its edge passes 1.5 mm beside the y = 30 row) + a 0-2 mm Al wedge fixed 15 mm in front of the
      detector, thickness rising along (cos 30, sin 30).  ii_local: plate +-60 mm.
  ball_sym_ff: 8 beads of 3 mm at (+-25, +-25, +-25) in a PMMA cube of 62 mm; `symmetry` lists the
      24 proper rotations as id permutations (perm[i] = id that sphere i is carried onto).
Nominal geometry in scan.yaml: true sdd/sod each off by ~1 %, except cage_ii_jpeg whose nominal
  magnification sdd/sod is 20 % too low.  log.csv: frame, time; pds_helix_ii and cage_ii_jpeg also
  give rough pose guesses rx, ry, rz (rotation vector, deg), tx, ty, tz (error ~10 deg, ~15 mm).
truth.json centres: per frame every sphere whose shadow has any part inside image and field:
  (x, y) = chord-length-weighted centroid of that sphere's own shadow on a 10x10-per-pixel grid in
  measured coordinates (off-image parts included, no blur), diameter_px = 2 sqrt(area/pi),
  truncated = part of the shadow off the image or beyond Rf, overlap = shares pixels with another
  listed sphere's shadow.  heldout: 30 points in the phantom's bounding box (>= 4 mm from every bead;
  planar: z in +-30 mm) projected through the true geometry + distortion, kept if inside the field.
  noise_sigma: 1.4826 MAD of (written - noise-free written float image) inside the field.
Simplifications: blur and glare act on the measured image (locally-affine distortion); spectral
  effects (beam hardening, scatter from the body) are ignored; pixel pitch of intensifiers is a
  nominal input-screen equivalent.
"""
import itertools, json, math, os, sys, tempfile, time, zlib
from types import SimpleNamespace as NS
import numpy as np, cv2, tifffile, yaml
from scipy.optimize import brentq
from scipy.special import erf

MU_S, MU_P, MU_AL = 0.45, 0.02, 0.08
EARTH_B = np.array([0.30, 0.80, 0.52]) / np.linalg.norm([0.30, 0.80, 0.52])
HELIX_CODE = '110100111010001101100101110001'
CASES = {
    'pds_helix_ii': 'PMMA cylinder, 30 helix beads with a 1.6/3.2 mm binary code; intensifier with a per-frame '
                    'cubic warp (pincushion + earth-field S-twist and shift), gamma-0.7 10-bit display',
    'cage_ii_jpeg': 'two PMMA plates 60 mm apart, 2x14 beads (two 4 mm); intensifier with tan-pincushion + '
                    'S-twist; 8-bit log display, JPEG q70; nominal magnification 20 % low; many overlaps',
    'grid_fp_step': '7x7 grid (one bead missing) in a partial 5 mm PMMA plate + 2 mm Al wedge; flat panel, '
                    'no distortion; uint16 raw, per-column gain, dark offset, flat/dark stacks',
    'grid_ii_local': 'same 7x7 grid on an intensifier: moderate pincushion + a local Gaussian dent (~2 px, '
                     '~60 px wide) at one detector place; 8-bit linear display',
    'ball_sym_ff': '8 beads on the corners of a cube in a PMMA cube; flat panel 16-bit raw; identity '
                   'ambiguous up to the 24 proper rotations (symmetry given)',
}
CFG = dict(
    pds_helix_ii=dict(nf=24, rows=1024, cols=1024, pitch=0.40, sdd=(980, 1040), sod=(620, 680), blur=0.7,
                      chain='gamma10', I0=6000, g=0.07, vig=0.30, black=0.03, se=0.004, guess=True),
    cage_ii_jpeg=dict(nf=22, rows=896, cols=896, pitch=0.44, sdd=(1050, 1150), sod=(700, 780), blur=0.6,
                      chain='log8', I0=8000, g=0.06, vig=0.25, black=0.03, se=0.004, guess=True, magerr=0.8),
    grid_fp_step=dict(nf=24, rows=832, cols=1024, pitch=0.30, sdd=(1100, 1200), sod=(650, 750), blur=1.1,
                      chain='raw', I0=15000, conv=0.3, off=900, colgain=0.04, se=5.0, stack=8),
    grid_ii_local=dict(nf=26, rows=768, cols=768, pitch=0.45, sdd=(950, 1000), sod=(560, 620), blur=0.8,
                       chain='lin8', I0=5000, g=0.05, vig=0.20, black=0.04, se=0.004),
    ball_sym_ff=dict(nf=20, rows=1024, cols=1024, pitch=0.35, sdd=(1000, 1100), sod=(600, 700), blur=0.5,
                     chain='raw', I0=20000, conv=2.5, off=1000, colgain=0.0, se=4.0, stack=0),
)
MONO = [(i, n - i) for n in range(4) for i in range(n, -1, -1)]

def rot(ax, deg):
    k = np.asarray(ax, float) / np.linalg.norm(ax); a = math.radians(deg)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K

def box_hs(lo, hi):
    return np.vstack([np.eye(3), -np.eye(3)]), np.r_[hi, -np.asarray(lo, float)]

def hs_iv(o, d, A, h):   # ray o + s d inside {x : A x <= h}: (s_in, s_out)
    nd = d @ A.T; ho = h - o @ A.T
    with np.errstate(divide='ignore', invalid='ignore'):
        s = ho / nd
    lo = np.where(nd < 0, s, -np.inf).max(-1)
    hi = np.where(nd > 0, s, np.where((nd == 0) & (ho < 0), -np.inf, np.inf)).min(-1)
    return lo, hi

def cyl_iv(o, d, rad, hl):   # finite cylinder about z
    a = d[..., 0] ** 2 + d[..., 1] ** 2; b = o[0] * d[..., 0] + o[1] * d[..., 1]; c = o[0] ** 2 + o[1] ** 2 - rad ** 2
    disc = b * b - a * c; sq = np.sqrt(np.maximum(disc, 0)); ok = (disc > 0) & (a > 0)
    with np.errstate(divide='ignore', invalid='ignore'):
        lo = np.where(ok, (-b - sq) / a, np.inf); hi = np.where(ok, (-b + sq) / a, -np.inf)
    l2, h2 = hs_iv(o, d, np.array([[0, 0, 1.], [0, 0, -1.]]), np.array([hl, hl]))
    return np.maximum(lo, l2), np.minimum(hi, h2)

def sph_chord(d, w, a):
    tca = d @ w
    return 2 * np.sqrt(np.maximum(a * a - (w @ w - tca ** 2), 0))

def phantom(name):
    if name == 'pds_helix_ii':
        i = np.arange(30); ph = 2 * np.pi * 1.25 * i / 29
        P = np.c_[44 * np.cos(ph), 44 * np.sin(ph), -66 + 132 * i / 29]
        D = np.where(np.array(list(HELIX_CODE)) == '1', 3.2, 1.6)
        return NS(P=P, D=D, bodies=[('ph', MU_P, 'cyl', (50.0, 75.0))], hbox=([-50, -50, -75], [50, 50, 75]),
                  planar=False, Rph=rot([1, 0, 0], 90), dnom=1.6)
    if name == 'cage_ii_jpeg':
        rr = np.random.default_rng(11); pts = []
        while len(pts) < 28:
            p = rr.uniform(-40, 40, 2); base = 0 if len(pts) < 14 else 14
            if all(np.hypot(*(p - q)) >= 12 for q in pts[base:]): pts.append(p)
        P = np.c_[np.array(pts), np.r_[np.full(14, -30.), np.full(14, 30.)]]
        D = np.full(28, 2.0); D[[0, 19]] = 4.0
        bodies = [('ph', MU_P, 'hs', box_hs([-55, -55, z - 3], [55, 55, z + 3])) for z in (-30, 30)]
        return NS(P=P, D=D, bodies=bodies, hbox=([-55, -55, -33], [55, 55, 33]), planar=False, Rph=np.eye(3), dnom=2.0)
    if name.startswith('grid'):
        g = np.arange(-30, 31, 10.); X, Y = np.meshgrid(g, g)
        P = np.c_[X.ravel(), Y.ravel(), np.zeros(49)]; P = P[~((P[:, 0] == 20) & (P[:, 1] == -10))]
        plate = ([-35.5, -150, -2.5], [150, 32.5, 2.5]) if name == 'grid_fp_step' else ([-60, -60, -2.5], [60, 60, 2.5])
        return NS(P=P, D=np.full(48, 2.0), bodies=[('ph', MU_P, 'hs', box_hs(*plate))],
                  hbox=([-35, -35, -30], [35, 35, 30]), planar=True, Rph=np.eye(3), dnom=2.0)
    P = np.array(list(itertools.product([-25., 25.], repeat=3)))
    return NS(P=P, D=np.full(8, 3.0), bodies=[('ph', MU_P, 'hs', box_hs([-31] * 3, [31] * 3))],
              hbox=([-31] * 3, [31] * 3), planar=False, Rph=None, dnom=3.0)

def inverse(fwd, cm, rm, it=14):   # fixed point x <- x - (F(x) - m)
    if fwd is None: return cm, rm
    c, r = cm.copy(), rm.copy()
    for _ in range(it):
        fc, fr = fwd(c, r); c -= fc - cm; r -= fr - rm
        if max(np.abs(fc - cm).max(), np.abs(fr - rm).max()) < 1e-7: break
    return c, r

def fw(fwd, c, r):
    return (c, r) if fwd is None else fwd(c, r)

def poly_fwd(cf, ctr, s):
    def f(c, r):
        x, y = (c - ctr[0]) / s, (r - ctr[1]) / s; X, Y = [1, x, x * x, x * x * x], [1, y, y * y, y * y * y]
        M = [X[i] * Y[j] for i, j in MONO]
        return c + sum(a * m for a, m in zip(cf[:, 0], M)), r + sum(b * m for b, m in zip(cf[:, 1], M))
    return f

def make_distortion(name, G, rng):
    fc, Rf, pp = G.fc, G.Rf, G.pp0
    ang = rng.uniform(0, 2 * np.pi, 3); U = [np.array([math.cos(a), math.sin(a)]) for a in ang]
    if name == 'pds_helix_ii':
        cd = pp + rng.uniform(15, 30) * U[0]; K = rng.uniform(8, 15); sh = rng.uniform(2, 4) * U[1]
        t0, t1 = np.radians(rng.uniform(0.2, 0.5)), np.radians(rng.uniform(0.5, 1.0))
        gc, gr = np.meshgrid(np.arange(0, G.cols, 16.), np.arange(0, G.rows, 16.))
        keep = np.hypot(gc - fc[0], gr - fc[1]) <= 1.05 * Rf; gc, gr = gc[keep], gr[keep]
        x, y = (gc - fc[0]) / Rf, (gr - fc[1]) / Rf; M = np.stack([x ** i * y ** j for i, j in MONO], 1)
        qx, qy = gc - cd[0], gr - cd[1]; rho = np.hypot(qx, qy); kp = K * rho ** 2 / Rf ** 3
        out = []
        for b in G.beta:
            th = b * (t0 + t1 * rho / Rf); co, si = np.cos(th) - 1, np.sin(th)
            dd = np.c_[kp * qx + co * qx - si * qy + b * sh[0], kp * qy + si * qx + co * qy + b * sh[1]]
            cf = np.linalg.lstsq(M, dd, rcond=None)[0]; rms = float(np.sqrt(((M @ cf - dd) ** 2).sum(1).mean()))
            out.append((poly_fwd(cf, fc, Rf), dict(model='poly3', centre=fc, scale=Rf, monomials=MONO,
                        coef_c=cf[:, 0], coef_r=cf[:, 1], fit_rms_px=rms, physical=dict(
                        beta=b, pincushion_centre=cd, pincushion_edge_px=K, tau0_deg=np.degrees(t0),
                        tau1_deg=np.degrees(t1), shift_px_per_beta=sh))))
        return 'poly3', out
    if name == 'cage_ii_jpeg':
        cd = pp + rng.uniform(20, 40) * U[0]; K = rng.uniform(15, 25); sh = rng.uniform(2, 4) * U[1]
        L = brentq(lambda L: L * math.tan(Rf / L) - Rf - K, Rf / 1.4, 1e3 * Rf)
        t0, t2 = np.radians(rng.uniform(0.2, 0.5)), np.radians(rng.uniform(0.6, 1.2))
        out = []
        for b in G.beta:
            def f(c, r, b=b):
                x, y = c - cd[0], r - cd[1]; rho = np.hypot(x, y)
                s = np.where(rho > 1e-9, L * np.tan(rho / L) / np.maximum(rho, 1e-9), 1.0)
                x, y = x * s, y * s; th = b * (t0 + t2 * (rho * s / Rf) ** 2); co, si = np.cos(th), np.sin(th)
                return cd[0] + co * x - si * y + b * sh[0], cd[1] + si * x + co * y + b * sh[1]
            out.append((f, dict(model='tan_twist', centre=cd, L_px=L, edge_px=K, Rf=Rf, beta=b, tau0_deg=np.degrees(t0),
                                tau2_deg=np.degrees(t2), shift_px_per_beta=sh)))
        return 'tan_twist', out
    if name == 'grid_ii_local':
        cd = pp + rng.uniform(10, 20) * U[0]; E = rng.uniform(5, 8); k1, k2 = 0.7 * E / Rf, 0.3 * E / Rf
        pd = fc + 70 * U[1]; A = rng.uniform(1.5, 2.5); e = U[2]; sg = 26.0

        def f(c, r):
            x, y = c - cd[0], r - cd[1]; q2 = (x * x + y * y) / Rf ** 2; k = k1 * q2 + k2 * q2 * q2
            gb = A * np.exp(-((c - pd[0]) ** 2 + (r - pd[1]) ** 2) / (2 * sg * sg))
            return c + k * x + gb * e[0], r + k * y + gb * e[1]
        par = dict(model='radial_dent', centre=cd, Rf=Rf, k1=k1, k2=k2, dent_centre=pd, dent_amplitude_px=A,
                   dent_sigma_px=sg, dent_direction=e)
        return 'radial_dent', [(f, par)] * G.nf
    return 'none', [(None, dict(model='none'))] * G.nf

def proj(G, k, P):
    S = G.S[k]; lam = (G.O[2] - S[2]) / (P[:, 2] - S[2]); X = S + lam[:, None] * (P - S)
    return (X[:, 0] - G.O[0]) / G.p, (X[:, 1] - G.O[1]) / G.p

def rays(G, k, c, r):
    d = np.stack([G.O[0] + c * G.p, G.O[1] + r * G.p, np.full(np.shape(c), G.O[2])], -1) - G.S[k]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)

def background(G, k, d):
    S, R, t = G.S[k], G.R[k], G.t[k]; out = np.zeros(d.shape[:-1])
    for fr, mu, kind, par in G.bodies:
        o, dd = (R.T @ (S - t), d @ R) if fr == 'ph' else (S, d)
        lo, hi = cyl_iv(o, dd, *par) if kind == 'cyl' else hs_iv(o, dd, *par)
        out += mu * np.maximum(hi - np.maximum(lo, 0), 0)
    return out

def infield(G, c, r):
    ok = (c >= -0.5) & (c <= G.cols - 0.5) & (r >= -0.5) & (r <= G.rows - 0.5)
    return ok & (np.hypot(c - G.fc[0], r - G.fc[1]) <= G.Rf) if G.ii else ok

def setup(name, seed):
    cfg = CFG[name]; rng = np.random.default_rng([seed, zlib.crc32(name.encode())]); ph = phantom(name)
    G = NS(name=name, cfg=cfg, nf=cfg['nf'], rows=cfg['rows'], cols=cfg['cols'], p=cfg['pitch'], ii=cfg['chain'] != 'raw', **vars(ph))
    G.sdd, G.sod = rng.uniform(*cfg['sdd']), rng.uniform(*cfg['sod'])
    ctr = np.array([(G.cols - 1) / 2, (G.rows - 1) / 2]); G.pp0 = ctr + rng.uniform(-15, 15, 2)
    G.O = np.array([-G.pp0[0] * G.p, -G.pp0[1] * G.p, G.sdd - G.sod])
    G.fc = ctr + rng.uniform(-6, 6, 2) if G.ii else ctr; G.Rf = 0.46 * min(G.rows, G.cols) if G.ii else 1e9
    if G.Rph is None: G.Rph = rot(rng.normal(size=3), rng.uniform(0, 360))
    if name == 'grid_fp_step':   # Al wedge fixed to the detector (lab frame)
        e = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0]); zw, gr, e0, W = G.O[2] - 15, 2 / 400, -200, 400
        A = np.array([[0, 0, -1], [-gr * e[0], -gr * e[1], 1], -e, e]); h = np.array([-zw, zw - gr * e0, -e0, e0 + W])
        G.bodies = G.bodies + [('lab', MU_AL, 'hs', (A, h))]
    G.S, G.R, G.t, G.beta, G.angles = [], [], [], [], []
    for k in range(G.nf):
        need_ov, edge = name == 'cage_ii_jpeg' and rng.random() < 0.6, rng.random() < 0.25
        for tries in range(400):
            a, b = rng.uniform(-45, 45, 2); g = rng.uniform(-180, 180)
            Rc = rot([0, 1, 0], a) @ rot([1, 0, 0], b) @ rot([0, 0, 1], g)
            R = Rc.T @ G.Rph; t = Rc.T @ rng.normal(0, 40 if edge else 8, 3)
            if G.planar and abs(R[2, 2]) < math.cos(math.radians(55)): continue
            S = np.array([1.2 * math.sin(math.radians(a)), 0.8 * math.sin(math.radians(b)),
                          -G.sod + 0.6 * math.cos(math.radians(a)) - 0.6]) + rng.normal(0, 0.1, 3)
            G.S.append(S); C = G.P @ R.T + t; c, r = proj(G, k, C); G.S.pop(); c0, r0 = c - G.fc[0], r - G.fc[1]
            rp = G.D / 2 * (G.O[2] - S[2]) / (C[:, 2] - S[2]) / G.p
            din = np.minimum(np.minimum(G.cols / 2 - np.abs(c0), G.rows / 2 - np.abs(r0)), G.Rf - np.hypot(c0, r0))
            f, fi = np.mean(din > 25), np.mean(din > 0); cut = (np.abs(din) < 0.7 * rp).any()
            if need_ov and tries < 300:   # cage: ask for a front/back shadow overlap (ideal-shadow estimate)
                dm = np.hypot(c[:14, None] - c[None, 14:], r[:14, None] - r[None, 14:]) - rp[:14, None] - rp[None, 14:]
                if dm.min() > -0.5: continue
            if (edge and fi >= 0.6 and cut) or (not edge and f == 1) or (tries > 300 and f >= 0.6): break
        G.S.append(S); G.R.append(R); G.t.append(t); G.beta.append(float(EARTH_B @ Rc[:, 2])); G.angles.append((a, b, g))
    G.kind, dl = make_distortion(name, G, rng); G.fwd = [x[0] for x in dl]; G.dpar = [x[1] for x in dl]
    return G, rng

def render(G, k):
    rows, cols, S, fwd = G.rows, G.cols, G.S[k], G.fwd[k]
    cc, rr = np.meshgrid(np.arange(cols + 1) - 0.5, np.arange(rows + 1) - 0.5)
    ic, ir = inverse(fwd, cc, rr)
    E = np.exp(-background(G, k, rays(G, k, ic, ir)))
    T = 0.25 * (E[:-1, :-1] + E[1:, :-1] + E[:-1, 1:] + E[1:, 1:])
    C = G.P @ G.R[k].T + G.t[k]; W = C - S; a = G.D / 2; n = len(a)
    L = np.linalg.norm(W, axis=1); ax = W / L[:, None]
    e1 = np.cross(ax, [0, 1, 0]); e1 /= np.linalg.norm(e1, axis=1)[:, None]; e2 = np.cross(ax, e1)
    al = np.arcsin(a / L)[:, None, None]; ph = np.linspace(0, 2 * np.pi, 90, endpoint=False)[None, :, None]
    dirs = np.cos(al) * ax[:, None] + np.sin(al) * (np.cos(ph) * e1[:, None] + np.sin(ph) * e2[:, None])
    X = S + ((G.O[2] - S[2]) / dirs[..., 2])[..., None] * dirs
    mc, mr = fw(fwd, (X[..., 0] - G.O[0]) / G.p, (X[..., 1] - G.O[1]) / G.p)
    bb = np.c_[mc.min(1) - 1, mc.max(1) + 1, mr.min(1) - 1, mr.max(1) + 1]
    # --- truth: chord-weighted centroids on a 10x10-per-pixel grid in measured coordinates
    grids = []
    for j in range(n):
        c0, r0 = math.floor(bb[j, 0]), math.floor(bb[j, 2])
        gc, gr = np.meshgrid(c0 + (np.arange(10 * (math.ceil(bb[j, 1]) - c0)) + 0.5) / 10,
                             r0 + (np.arange(10 * (math.ceil(bb[j, 3]) - r0)) + 0.5) / 10)
        grids.append((gc.ravel(), gr.ravel()))
    cat = [np.concatenate([g[i] for g in grids]) for i in (0, 1)]; sp = np.cumsum([0] + [len(g[0]) for g in grids])
    icat, ircat = inverse(fwd, *cat); dcat = rays(G, k, icat, ircat)
    info = []
    for j in range(n):
        d = dcat[sp[j]:sp[j + 1]]; w = sph_chord(d, W[j], a[j]); inn = infield(G, *grids[j]); pos = w > 0
        info.append(dict(id=j, x=float((w * grids[j][0]).sum() / w.sum()), y=float((w * grids[j][1]).sum() / w.sum()),
                         diameter_px=float(2 * math.sqrt(pos.sum() / 100 / math.pi)),
                         truncated=bool((pos & ~inn).any()), listed=bool((pos & inn).any()), overlap=False))
    for i, j in itertools.permutations(range(n), 2):
        if info[i]['listed'] and info[j]['listed'] and bb[i, 0] < bb[j, 1] and bb[j, 0] < bb[i, 1] and bb[i, 2] < bb[j, 3] and bb[j, 2] < bb[i, 3]:
            d = dcat[sp[j]:sp[j + 1]]
            if ((sph_chord(d, W[j], a[j]) > 0) & (sph_chord(d, W[i], a[i]) > 0)).any(): info[j]['overlap'] = True
    cents = [{kk: v for kk, v in x.items() if kk != 'listed'} for x in info if x['listed']]
    # --- rendering: 6x6 sub-samples per pixel in the sphere patches
    pb = np.c_[np.floor(bb[:, 0]) - 2, np.ceil(bb[:, 1]) + 3, np.floor(bb[:, 2]) - 2, np.ceil(bb[:, 3]) + 3].astype(int)
    pb[:, :2] = pb[:, :2].clip(0, cols); pb[:, 2:] = pb[:, 2:].clip(0, rows)
    mask = np.zeros((rows, cols), bool)
    for c0, c1, r0, r1 in pb: mask[r0:r1, c0:c1] = True
    idx = np.flatnonzero(mask); pos = np.full(rows * cols, -1); pos[idx] = np.arange(len(idx)); pr, pcn = np.divmod(idx, cols)
    f = (np.arange(6) + 0.5) / 6; fy, fx = [v.ravel()[None] for v in np.meshgrid(f, f, indexing='ij')]
    bil = lambda Z: ((1 - fy) * ((1 - fx) * Z[pr, pcn][:, None] + fx * Z[pr, pcn + 1][:, None])
                     + fy * ((1 - fx) * Z[pr + 1, pcn][:, None] + fx * Z[pr + 1, pcn + 1][:, None]))
    d = rays(G, k, bil(ic), bil(ir)); A = background(G, k, d)
    for j, (c0, c1, r0, r1) in enumerate(pb):
        sel = pos.reshape(rows, cols)[r0:r1, c0:c1].ravel(); sel = sel[sel >= 0]
        if len(sel): A[sel] += (MU_S - MU_P) * sph_chord(d[sel], W[j], a[j])
    T.flat[idx] = np.exp(-A).mean(1)
    return T, cents

def blur(G, T):
    s = G.cfg['blur']; T = T.astype(np.float32)
    if G.name != 'grid_fp_step': return cv2.GaussianBlur(T, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    n = 2; yy, xx = np.mgrid[-n:n + 1, -n:n + 1]; o = (np.arange(8) + 0.5) / 8 - 0.5
    K = sum((np.hypot(xx + u, yy + v) <= s).astype(float) for u in o for v in o); K /= K.sum()
    return cv2.filter2D(T, -1, K.astype(np.float32), borderType=cv2.BORDER_REFLECT)

def chain(G, X, rng, noisy):
    """blurred transmission X -> (float value before rounding, written array)."""
    c = G.cfg; cnt = rng.poisson(c['I0'] * np.asarray(X, float)).astype(float) if noisy else c['I0'] * np.asarray(X, float)
    if c['chain'] == 'raw':
        v = G.dark + G.gain * c['conv'] * cnt + (rng.normal(0, c['se'], cnt.shape) if noisy else 0)
        return v, np.clip(np.round(v), 0, 65535).astype(np.uint16)
    Y = (cnt / c['I0'] * G.field).astype(np.float32)
    small = cv2.resize(Y, (G.cols // 8, G.rows // 8), interpolation=cv2.INTER_AREA)
    gl = cv2.resize(cv2.GaussianBlur(small, (0, 0), 10), (G.cols, G.rows), interpolation=cv2.INTER_LINEAR)
    E = ((1 - c['g']) * Y + c['g'] * gl) * G.vig + c['black'] + (rng.normal(0, c['se'], Y.shape) if noisy else 0)
    if c['chain'] == 'gamma10':
        v = 1023 * np.clip(E / (1 + c['black']), 0, 1) ** 0.7; return v, np.round(v).astype(np.uint16)
    if c['chain'] == 'lin8':
        v = 255 * np.clip(E / (1 + c['black']), 0, 1); return v, np.round(v).astype(np.uint8)
    v = 255 * np.clip(np.log(np.maximum(E, 1e-6) / 0.02) / math.log(1.1 / 0.02), 0, 1)
    w = np.round(v).astype(np.uint8)
    if noisy: w = cv2.imdecode(cv2.imencode('.jpg', w, [cv2.IMWRITE_JPEG_QUALITY, 70])[1], cv2.IMREAD_GRAYSCALE)
    return v, w

def J(x):
    if isinstance(x, dict): return {k: J(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)): return [J(v) for v in x]
    if isinstance(x, (np.ndarray, np.generic)): return J(x.tolist())
    return round(x, 6) if isinstance(x, float) else x

def make_case(name, seed, out):
    t0 = time.time(); G, rng = setup(name, seed); c = G.cfg; sd = os.path.join(out, 'scan'); os.makedirs(sd, exist_ok=True)
    yy, xx = np.mgrid[0:G.rows, 0:G.cols]; rho = np.hypot(xx - G.fc[0], yy - G.fc[1])
    if G.ii:
        G.field = 0.5 * (1 - erf((rho - G.Rf) / 4.0)); G.vig = 1 - c['vig'] * (rho / G.Rf) ** 2; inside = rho < G.Rf - 6
    else:
        cg = 1 + c['colgain'] * rng.normal(size=G.cols); G.gain = np.broadcast_to(cg, (G.rows, G.cols))
        G.dark = c['off'] + 30 * np.cos(2 * np.pi * xx / 97.0) + rng.normal(0, 4, (G.rows, G.cols)); inside = np.ones_like(rho, bool)
    # heldout points (phantom frame)
    lo, hi = map(np.asarray, G.hbox); H = []
    while len(H) < 30:
        q = rng.uniform(lo, hi)
        if np.linalg.norm(G.P - q, axis=1).min() >= 4: H.append(q)
    H = np.array(H)
    imgs, cents, held, sig = [], [], [], []
    for k in range(G.nf):
        T, cen = render(G, k); X = blur(G, T)
        v0, _ = chain(G, X, rng, False); _, w = chain(G, X, rng, True)
        imgs.append(w); cents.append(cen)
        dd = (w.astype(float) - v0)[inside]; sig.append(float(1.4826 * np.median(np.abs(dd - np.median(dd)))))
        hc, hr = fw(G.fwd[k], *proj(G, k, H @ G.R[k].T + G.t[k])); ok = infield(G, hc, hr)
        held.append(dict(frame=k, points=H[ok], pixels=np.c_[hc[ok], hr[ok]]))
    tifffile.imwrite(os.path.join(sd, 'projections.tif'), np.stack(imgs), photometric='minisblack')
    one, zero = np.ones((G.rows, G.cols)), np.zeros((G.rows, G.cols))
    if c.get('stack'):
        fl = np.stack([chain(G, one, rng, True)[1] for _ in range(c['stack'])]); dk = np.stack([chain(G, zero, rng, True)[1] for _ in range(c['stack'])])
    else:
        fl = chain(G, one, rng, False)[1]; dk = chain(G, zero, rng, False)[1]
    tifffile.imwrite(os.path.join(sd, 'flat.tif'), fl, photometric='minisblack')
    tifffile.imwrite(os.path.join(sd, 'dark.tif'), dk, photometric='minisblack')
    with open(os.path.join(sd, 'phantom.csv'), 'w') as fh:
        fh.write('id,x,y,z\n' + ''.join(f'{i},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}\n' for i, p in enumerate(G.P)))
    times = np.cumsum(np.r_[0, rng.uniform(0.7, 0.9, G.nf - 1)])
    with open(os.path.join(sd, 'log.csv'), 'w') as fh:
        fh.write('frame,time' + (',rx,ry,rz,tx,ty,tz' if c.get('guess') else '') + '\n')
        for k in range(G.nf):
            row = f'{k},{times[k]:.3f}'
            if c.get('guess'):
                Rg = rot(rng.normal(size=3), rng.normal(0, 10)) @ G.R[k]; rv = np.degrees(cv2.Rodrigues(Rg)[0].ravel())
                row += ''.join(f',{x:.3f}' for x in np.r_[rv, G.t[k] + rng.normal(0, 15, 3)])
            fh.write(row + '\n')
    mag = G.sdd / G.sod; sddn = round(G.sdd * (1 + rng.normal(0, 0.01)), 1)
    sodn = round(sddn / (c['magerr'] * mag), 1) if 'magerr' in c else round(G.sod * (1 + rng.normal(0, 0.01)), 1)
    blur_eq = c['blur'] / 2 if G.name == 'grid_fp_step' else c['blur']
    scan = {'format': 'conecal-scan/1', 'motion': 'free', 'projections': 'projections.tif', 'values': 'raw',
            'flat': 'flat.tif', 'dark': 'dark.tif', 'log': 'log.csv',
            'detector': {'rows': G.rows, 'cols': G.cols, 'pixel_pitch': [G.p, G.p]},
            'nominal': {'sod': sodn, 'sdd': sddn}, 'markers': {'diameter': G.dnom, 'phantom': 'phantom.csv'},
            'imaging': {'blur_px': round(blur_eq, 3)}}
    with open(os.path.join(sd, 'scan.yaml'), 'w') as fh: yaml.safe_dump(scan, fh, sort_keys=False)
    S = np.array(G.S); fsdd = G.O[2] - S[:, 2]; fpp = np.c_[(S[:, 0] - G.O[0]) / G.p, (S[:, 1] - G.O[1]) / G.p]
    gc, gr = np.meshgrid(np.arange(0, G.cols, 64.), np.arange(0, G.rows, 64.)); gk = infield(G, gc, gr)
    gc, gr = gc[gk], gr[gk]
    truth = dict(format='carm-images3-truth/1', case=name, seed=seed, description=CASES[name],
                 sdd=float(fsdd.mean()), sod=float(np.linalg.norm(S.mean(0))), principal_point=fpp.mean(0),
                 frame_sdd=fsdd, frame_principal_point=fpp, source=S,
                 detector=dict(origin=G.O, u=[1, 0, 0], v=[0, 1, 0], pixel_pitch=[G.p, G.p], shape=[G.rows, G.cols]),
                 nominal=dict(sdd=sddn, sod=sodn), sphere_diameters=G.D,
                 poses=[dict(frame=k, R=G.R[k], t=G.t[k]) for k in range(G.nf)],
                 carm_angles_deg=[dict(frame=k, orbit=a, angulation=b, inplane=g, beta=G.beta[k]) for k, (a, b, g) in enumerate(G.angles)],
                 centres=cents, heldout=held, noise_sigma=sig, distortion_kind=G.kind,
                 distortion=[dict(frame=k, **G.dpar[k]) for k in range(G.nf)],
                 distortion_samples=dict(ideal=np.c_[gc, gr], measured=[np.c_[fw(G.fwd[k], gc, gr)] for k in range(G.nf)]),
                 field=dict(kind='circle', centre=G.fc, radius=G.Rf, soft_edge_px=4.0) if G.ii else dict(kind='image'),
                 blur=dict(kind='disc', radius_px=c['blur']) if G.name == 'grid_fp_step' else dict(kind='gaussian', sigma_px=c['blur']),
                 chain={k2: v for k2, v in c.items() if k2 not in ('sdd', 'sod', 'nf', 'rows', 'cols', 'pitch')})
    if name == 'ball_sym_ff':
        perms = []
        for pm in itertools.permutations(range(3)):
            for sg in itertools.product([1, -1], repeat=3):
                M = np.zeros((3, 3)); M[range(3), pm] = sg
                if np.linalg.det(M) > 0:
                    perms.append([int(np.argmin(np.linalg.norm(G.P - q, axis=1))) for q in G.P @ M.T])
        truth['symmetry'] = dict(group='O (chiral octahedral, 24 proper rotations of the cube)', id_permutations=perms)
    tmp = os.path.join(out, 'truth.json.tmp')
    with open(tmp, 'w') as fh: json.dump(J(truth), fh, sort_keys=True)
    os.replace(tmp, os.path.join(out, 'truth.json'))
    return dict(case=name, seed=seed, frames=G.nf, spheres_per_frame=float(np.mean([len(x) for x in cents])),
                overlaps=sum(x['overlap'] for f in cents for x in f), truncated=sum(x['truncated'] for f in cents for x in f),
                noise_sigma=float(np.mean(sig)), seconds=round(time.time() - t0, 1))

def _check(out):
    sd = os.path.join(out, 'scan'); img = tifffile.imread(os.path.join(sd, 'projections.tif')).astype(float)
    fl, dk = [tifffile.imread(os.path.join(sd, f)).astype(float) for f in ('flat.tif', 'dark.tif')]
    fl, dk = (fl.mean(0) if fl.ndim == 3 else fl), (dk.mean(0) if dk.ndim == 3 else dk)
    tr = json.load(open(os.path.join(out, 'truth.json'))); den = fl - dk; den[den < 1] = np.nan
    ok = bad = 0; err = []
    for k, cen in enumerate(tr['centres']):
        F = np.nan_to_num((img[k] - dk) / den, nan=0.0).astype(np.float32)
        for m in cen:
            if m['truncated']: continue
            R = 0.5 * m['diameter_px'] + 3; th = np.linspace(0, 2 * np.pi, 32, endpoint=False)
            rx, ry = m['x'] + R * np.cos(th), m['y'] + R * np.sin(th)
            rv = np.array([cv2.getRectSubPix(F, (1, 1), (float(u), float(v)))[0, 0] for u, v in zip(rx, ry)]); ring = np.median(rv)
            pl = np.linalg.lstsq(np.c_[np.ones(32), rx - m['x'], ry - m['y']], rv, rcond=None)[0]   # plane background
            cv = cv2.getRectSubPix(F, (1, 1), (m['x'], m['y']))[0, 0]
            if cv < 0.93 * ring: ok += 1
            else: bad += 1
            h = int(R) + 1; x0, y0 = int(round(m['x'])), int(round(m['y']))
            if not m['overlap'] and h <= x0 < F.shape[1] - h and h <= y0 < F.shape[0] - h:
                win = F[y0 - h:y0 + h + 1, x0 - h:x0 + h + 1]; yy, xx = np.mgrid[y0 - h:y0 + h + 1, x0 - h:x0 + h + 1]
                wt = np.clip(np.log(np.maximum(pl[0] + pl[1] * (xx - m['x']) + pl[2] * (yy - m['y']), 1e-3) / np.maximum(win, 1e-3)), 0, None) * (np.hypot(xx - m['x'], yy - m['y']) <= R - 1.5)
                if wt.sum() > 0: err.append(math.hypot((wt * xx).sum() / wt.sum() - m['x'], (wt * yy).sum() / wt.sum() - m['y']))
    return ok, bad, float(np.median(err)) if err else float('nan')

if __name__ == '__main__':
    names = sys.argv[1:] or list(CASES)
    print(f"{'case':15s} {'frames':>6s} {'sph/fr':>7s} {'overlap':>7s} {'trunc':>6s} {'sigma':>7s} {'blob ok/bad':>11s} {'cen.err':>7s} {'sec':>6s}")
    for nm in names:
        with tempfile.TemporaryDirectory() as td:
            s = make_case(nm, 0, td); ok, bad, e = _check(td)
            print(f"{nm:15s} {s['frames']:6d} {s['spheres_per_frame']:7.1f} {s['overlaps']:7d} {s['truncated']:6d} "
                  f"{s['noise_sigma']:7.3f} {ok:5d}/{bad:<5d} {e:7.3f} {s['seconds']:6.1f}")
            assert bad == 0, f'{nm}: {bad} truth centres not on a dark blob'
