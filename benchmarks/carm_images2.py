"""Independent C-arm / radiography test-data generator (conecal scan format 1, motion: free).

Frames: C-arm frame = the contract's lab frame: source S = (0, 0, -sod), detector plane z = sdd_k - sod,
u = +x (columns), v = +y (rows); img[r, c] is centred at pixel coordinates (c, r), img[0, 0] at (0, 0).
Phantom point p -> P = R_k p + t_k -> pinhole pixel c = ppc_k + sdd_k Px / (Pz + sod) / pu,
r = ppr_k + sdd_k Py / (Pz + sod) / pv (pp_k: foot of the perpendicular from S) -> measured D_k(c, r).
truth principal_point / sdd = means of frame_principal_point / frame_sdd (equal on flat panels).
Intensifier distortion D_k about c0 (10-25 px from the principal point), d = (c, r) - c0:
  rho' = kappa tan(|d| / kappa)  (curved input screen, pincushion 7-12 px at rn = field radius),
  theta' = atan2(d) + omega_k (|d| / rn)^2  (magnetic S-twist, omega_k rn = 4 px * (b . beam_k), b = earth
  field, so strength and sign follow the C-arm orientation);  D_k = c0 + rho' (cos theta', sin theta').
  Sag: the detector shifts by 2.5 px * gravity(u, v) and 1.5 mm * (1 + gravity(beam)) per frame (moves
  frame_principal_point / frame_sdd; c0 fixed in pixels).  Flat panels: D_k = identity.
Physics: steel beads mu 0.42 /mm (less the PMMA 0.022 /mm they displace) in a PMMA tube / plate / block;
exact chords of point-source rays, 6x6 sub-samples per pixel around beads, 2x2 (3x3 with clutter)
elsewhere, Beer-Lambert per sub-sample, pixel mean; Gaussian focal-spot blur (0.7 / 0.9 px); Poisson counts
(N0 per open pixel: helix_ff 10000, grid_sym_ff 6000, ii 1200); Gaussian blur after the noise (0.5 / 0.6 px).
Flat panel: ADU = 2 G(c,r) counts + dark(col) + N(0, 3) -> uint16 (counts carry cos^3 and a 4 % heel, also
in the flat).  helix_ff: projections use G (1 + eps), eps = 0.3 % smooth + 0.2 % column drift, the flat
holds G (imperfect correction); flat / dark are 4-page stacks.  grid_sym_ff: flat / dark = mean of 16.
Intensifier: counts / N0 -> glare 0.88 q + 0.12 LP_25px(q) -> vignetting 1 - 0.25 (rho/rf)^2 -> read noise
0.003 -> display -> circular field (0 outside) -> uint8.  helix_ii gamma 0.6, ball_clutter_ii gamma 0.5,
flat = the chain on an open field (mean of 8), dark = 0.  grid_holes_ii: log display, JPEG quality 85,
flat = constant 255, dark = 0 (so transmission = level / 255, not I / I0).
Truth centres: x, y = chord-weighted centroid of the bead's own shadow, 10x10 samples per pixel in measured
(distorted) coordinates over the whole shadow (off-image parts too); x_centre, y_centre = D_k(pinhole image
of the centre); diameter_px = equivalent-area diameter; overlap = its shadow cone meets another listed
bead's; truncated = part of the shadow outside image / field; listed = some part inside.  noise_sigma =
robust std of (written - noise-free written) inside the field (includes 8-bit / JPEG error).
grid_sym_ff is invariant under the 8 proper rotations of D4 (90 deg turns, seen from behind): identity is
ambiguous up to them (truth symmetry.id_permutations).  Coplanar grid beads cannot overlap at tilts <= 50
deg, so the grid cases' ~1/4 overlap frames are steep (68-82 deg) views with 8-70 % of beads overlapping.
"""
import json, time, zlib
from pathlib import Path
import numpy as np, yaml, tifffile, cv2
from scipy import optimize

MU_STEEL, MU_PMMA, MU_BONE = 0.42, 0.022, 0.055
CASES = {
    'helix_ff': 'PMMA tube, 27 steel beads (1.8 mm) on a helix + 3 of 3.5 mm; flat panel 1024x768 uint16 raw',
    'helix_ii': 'same helix phantom, image-intensifier C-arm (768 px, circular field, pincushion+twist, gamma, uint8)',
    'grid_holes_ii': '8x8 bead grid (8 mm, 2.5 mm beads), 3 holes; intensifier, log display, JPEG q85; 1/3 frames truncated',
    'grid_sym_ff': 'symmetric 6x6 bead grid (10 mm, 2.5 mm beads), flat panel 720x960 uint16; pose identity ambiguous (D4)',
    'ball_clutter_ii': 'two-plane ball phantom (25 beads) + wires, screw, bone, soft tissue; intensifier; nominal magnification +20 %',
}

def _rotv(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K

def _axis_frame(a):
    a = np.asarray(a, float) / np.linalg.norm(a)
    e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    return np.c_[e1, np.cross(a, e1), a]

def dist_fwd(c, r, d):
    if d is None:
        return c, r
    x, y = c - d['c0'][0], r - d['c0'][1]
    rho, th = np.hypot(x, y), np.arctan2(y, x)
    rp, th = d['kappa'] * np.tan(rho / d['kappa']), th + d['omega'] * (rho / d['rn']) ** 2
    return d['c0'][0] + rp * np.cos(th), d['c0'][1] + rp * np.sin(th)

def dist_inv(c, r, d):
    if d is None:
        return c, r
    x, y = c - d['c0'][0], r - d['c0'][1]
    rho = d['kappa'] * np.arctan(np.hypot(x, y) / d['kappa'])
    th = np.arctan2(y, x) - d['omega'] * (rho / d['rn']) ** 2
    return d['c0'][0] + rho * np.cos(th), d['c0'][1] + rho * np.sin(th)

def project(P, g):
    s = g['sdd'] / (P[:, 2] + g['sod'])
    return dist_fwd(g['pp'][0] + P[:, 0] * s / g['pu'], g['pp'][1] + P[:, 1] * s / g['pv'], g['dist'])

def _rays(c, r, g):
    c, r = dist_inv(c, r, g['dist'])
    X, Y = (c - g['pp'][0]) * g['pu'], (r - g['pp'][1]) * g['pv']
    n = np.sqrt(X * X + Y * Y + g['sdd'] ** 2)
    return X / n, Y / n, g['sdd'] / n

def _in_field(c, r, g):
    rows, cols = g['shape']
    ok = (c >= -0.5) & (c <= cols - 0.5) & (r >= -0.5) & (r <= rows - 0.5)
    if g['field'] is not None:
        ok &= np.hypot(c - g['field'][0], r - g['field'][1]) <= g['field'][2]
    return ok

def _chord_sphere(S, D, C, a):
    m = C - S
    t0 = D[0] * m[0] + D[1] * m[1] + D[2] * m[2]                   # distance along the ray to closest approach
    return 2 * np.sqrt(np.maximum(a * a - (m @ m - t0 * t0), 0))

def _chord_cyl(o, D, rad, h):                  # finite cylinder along local z, |z| <= h
    A, B = D[0] ** 2 + D[1] ** 2 + 1e-30, o[0] * D[0] + o[1] * D[1]
    disc = B * B - A * (o[0] ** 2 + o[1] ** 2 - rad * rad)
    sq, dz = np.sqrt(np.maximum(disc, 0)), np.where(np.abs(D[2]) < 1e-12, 1e-12, D[2])
    z1, z2 = (-h - o[2]) / dz, (h - o[2]) / dz
    lo, hi = np.maximum((-B - sq) / A, np.minimum(z1, z2)), np.minimum((-B + sq) / A, np.maximum(z1, z2))
    return np.where(disc > 0, np.maximum(hi - lo, 0), 0)

def _chord_box(o, D, half):
    lo, hi = -np.inf, np.inf
    for i in range(3):
        di = np.where(np.abs(D[i]) < 1e-12, 1e-12, D[i])
        t1, t2 = (-half[i] - o[i]) / di, (half[i] - o[i]) / di
        lo, hi = np.maximum(lo, np.minimum(t1, t2)), np.minimum(hi, np.maximum(t1, t2))
    return np.maximum(hi - lo, 0)

def _bg_L(D, objs, S):
    """Sum of mu * chord over objects (kind, mu, Rw, tw, par); Rw, tw map object-local to C-arm frame."""
    L = np.zeros(np.shape(D[0]))
    for kind, mu, Rw, tw, par in objs:
        o = Rw.T @ (S - tw)
        Dl = [Rw[0, i] * D[0] + Rw[1, i] * D[1] + Rw[2, i] * D[2] for i in range(3)]
        L += mu * (_chord_cyl(o, Dl, *par) if kind == 'cyl' else _chord_box(o, Dl, par))
    return L

def _helix():
    n, k = 27, np.arange(27)
    phi, z = 4 * np.pi * k / n, -55 + 110 * k / (n - 1)
    big = [(300, -20), (250, 8), (20, 43)]                 # (deg, mm): asymmetric heights
    p = np.r_[np.c_[45 * np.cos(phi), 45 * np.sin(phi), z],
              [[44 * np.cos(np.radians(q)), 44 * np.sin(np.radians(q)), zz] for q, zz in big]]
    return p, np.r_[np.full(n, 1.8), np.full(3, 3.5)]

def _grid(n, pitch, missing=()):
    return np.array([[(j - (n - 1) / 2) * pitch, (i - (n - 1) / 2) * pitch, 0.0]
                     for i in range(n) for j in range(n) if (i, j) not in missing])

def _scatter(rng, n, rad, sep, z):
    pts = []
    while len(pts) < n:
        q = rng.uniform(-rad, rad, 2)
        if np.hypot(*q) <= rad and all(np.hypot(*(q - p)) >= sep for p in pts):
            pts.append(q)
    return np.c_[np.array(pts), np.full(n, z)]

def _config(name, rng):
    C = dict(name=name, ii=name.endswith('_ii'), nominal_mag_err=0.0, steep=None, trunc=0.0,
             base=np.eye(3), roll=np.radians(15), clutter=False, offset=8.0)
    box = lambda h: [('box', MU_PMMA, np.eye(3), np.zeros(3), np.array(h, float))]
    if name.startswith('helix'):
        C['ph'], C['diam'] = _helix()
        C['holder'] = [('cyl', MU_PMMA, np.eye(3), np.zeros(3), (50.0, 72.0)),
                       ('cyl', -MU_PMMA, np.eye(3), np.zeros(3), (38.0, 72.0))]     # tube: outer minus bore
        C['base'], C['tilt'], C['vol'] = _rotv([1, 0, 0], np.pi / 2), np.radians(45), ('cyl', 50.0, 72.0, 6.0)
    elif name.startswith('grid'):
        holes = name == 'grid_holes_ii'
        C['ph'] = _grid(8, 8.0, {(0, 2), (3, 6), (5, 1)}) if holes else _grid(6, 10.0)
        C['diam'] = np.full(len(C['ph']), 2.5)
        hx, hz = (42.0, 6.0) if holes else (40.0, 5.0)
        C['holder'], C['vol'] = box([hx, hx, hz]), ('plate', hx - 2, hz)
        C['tilt'], C['steep'], C['trunc'] = np.radians(50), np.radians([68, 82]), 1 / 3 if holes else 0.0
    else:
        prng = np.random.default_rng(20240611)             # the physical phantom does not depend on seed
        C['ph'] = np.r_[_scatter(prng, 13, 38, 10, -25.0), _scatter(prng, 12, 38, 10, 25.0)]
        C['diam'], C['holder'], C['vol'] = np.full(25, 2.5), box([50, 50, 31]), ('ball',)
        C['tilt'], C['clutter'] = np.radians(55), True
    spec = {'helix_ff': ((1024, 768), 0.3, 700, 1100), 'helix_ii': ((768, 768), 0.40, 700, 1000, 370, 9, 'gamma0.6'),
            'grid_holes_ii': ((576, 576), 0.45, 650, 1000, 272, 7, 'log'), 'grid_sym_ff': ((720, 960), 0.2, 500, 900),
            'ball_clutter_ii': ((640, 640), 0.42, 700, 1050, 305, 12, 'gamma0.5')}[name]   # (+ field r, pincushion px)
    shape, C['pitch'], sod, sdd = spec[:4]
    C['shape'], C['sod'], C['sdd'] = shape, sod * (1 + rng.uniform(-.01, .01)), sdd * (1 + rng.uniform(-.005, .005))
    centre = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    C['pp0'], C['field'], C['dist0'] = centre + rng.uniform(-8, 8, 2), None, None
    if C['ii']:
        rf, pin, C['display'] = float(spec[4]), float(spec[5]), spec[6]
        C['field'] = tuple(centre + rng.uniform(-3, 3, 2)) + (rf,)
        kappa = optimize.brentq(lambda k: rf - k * np.arctan(rf / k) - pin, 100, 1e7)
        C['dist0'] = dict(c0=list(C['pp0'] + rng.uniform(10, 25, 2) * rng.choice([-1, 1], 2)),
                          kappa=kappa, rn=rf, pincushion_px_at_rn=pin)
        C['N0'], C['blur'], C['blur_post'] = 1200.0, 0.9, 0.6
    else:
        C['N0'], C['blur'], C['blur_post'] = (10000.0, 0.7, 0.5) if name == 'helix_ff' else (6000.0, 0.9, 0.5)
    return C

def _geo(C, Rc, rng):
    g = dict(sod=C['sod'], sdd=C['sdd'], pp=C['pp0'].copy(), pu=C['pitch'], pv=C['pitch'],
             shape=C['shape'], field=C['field'], dist=None, S=np.array([0, 0, -C['sod']]))
    if C['ii']:
        gc = Rc @ np.array([0, 0, -1.0])                  # gravity in the C-arm frame
        g['pp'] = C['pp0'] + 2.5 * gc[:2] + rng.normal(0, 0.15, 2)
        g['sdd'] = C['sdd'] + 1.5 * (1 + gc[2])
        b = np.array([0.75, 0.3, 0.55]) / np.linalg.norm([0.75, 0.3, 0.55])
        g['dist'] = dict(C['dist0'], omega=4.0 / C['field'][2] * float(b @ (Rc.T @ [0, 0, 1.0])))
    return g

def _cones(g, P, a):
    """Unit axes, half-angles and pairwise intersection of the beads' shadow cones (exact overlap test)."""
    v = P - g['S']
    dist = np.linalg.norm(v, axis=1)
    u, al = v / dist[:, None], np.arcsin(a / dist)
    return u, al, (np.arccos(np.clip(u @ u.T, -1, 1)) < al[:, None] + al[None, :]) & ~np.eye(len(a), dtype=bool)

def _quick(C, g, P, a):
    """Fast per-sphere flags from an upper-bound shadow radius (for pose acceptance)."""
    u, al, ovm = _cones(g, P, a)
    c, r = project(P, g)
    rpx = g['sdd'] * np.tan(al) / u[:, 2] ** 2 / g['pu'] * (1.12 if C['ii'] else 1.0) + 3
    rows, cols = g['shape']
    full = (c - rpx > -0.5) & (c + rpx < cols - 0.5) & (r - rpx > -0.5) & (r + rpx < rows - 0.5)
    anyin = (c + rpx > 0) & (c - rpx < cols) & (r + rpx > 0) & (r - rpx < rows)
    if g['field'] is not None:
        rho = np.hypot(c - g['field'][0], r - g['field'][1])
        full, anyin = full & (rho + rpx < g['field'][2]), anyin & (rho - rpx < g['field'][2])
    return full, (ovm & anyin[None, :]).any(1) & anyin

def _clutter_world(rng):
    wires = [('cyl', MU_STEEL, _axis_frame(np.r_[rng.normal(size=2), rng.normal(0, 0.3)]),
              np.r_[rng.uniform(-30, 30, 2), rng.choice([-1, 1]) * rng.uniform(42, 70)], (0.8, 110.0))
             for _ in range(3)]                                        # K-wires, steel 1.6 mm
    wires.append(('screw', MU_STEEL, _axis_frame(np.r_[rng.normal(size=2), rng.normal(0, 0.5)]),
                  np.r_[rng.uniform(-30, 30, 2), -55.0], None))     # shaft 4.5 x 36 mm + head 8 x 3 mm
    bone = [('cyl', MU_BONE, _axis_frame([1, 0.2, 0]), np.array([0, 10.0, 75.0]), (13.0, 200.0)),
            ('cyl', 0.02 - MU_BONE, _axis_frame([1, 0.2, 0]), np.array([0, 10.0, 75.0]), (8.0, 200.0))]
    return wires, bone

def _frame_objs(C, R, t, Rc, rng, cw):
    objs, clut = [(k, mu, R @ Rl, R @ tl + t, par) for k, mu, Rl, tl, par in C['holder']], []
    if C['clutter']:                                  # world-fixed clutter follows the C-arm rotation Rc
        objs += [(k, mu, Rc @ Rl, Rc @ tl + t, par) for k, mu, Rl, tl, par in cw[1]]
        for k, mu, Rl, tl, par in cw[0]:
            if rng.uniform() < 0.55:                      # present in ~55 % of frames each
                Rw, tw = Rc @ Rl, Rc @ tl + t
                clut += [('cyl', mu, Rw, tw, (2.25, 18.0)), ('cyl', mu, Rw, tw + Rw[:, 2] * 19.5, (4.0, 1.5))] \
                    if k == 'screw' else [(k, mu, Rw, tw, par)]
    return objs + clut, clut

def _sample_grid(cc, rr, ss):
    o = (np.arange(ss) + 0.5) / ss - 0.5
    ox, oy = np.meshgrid(o, o)
    return cc[:, None] + ox.ravel(), rr[:, None] + oy.ravel()

def _shadow_box(g, Pj, aj, c, r):
    dist = np.linalg.norm(Pj - g['S'])
    rpx = g['sdd'] * np.tan(np.arcsin(aj / dist)) / ((Pj[2] + g['sod']) / dist) ** 2 / g['pu']
    return int(np.ceil(1.25 * rpx * (1.1 if g['dist'] else 1.0) + 2)), int(round(c)), int(round(r))

def render_T(g, objs, sph, ss_bg=2, ss_sp=6):
    """Pixel-averaged transmission (no soft tissue, blur or noise); sph: list of (P, radius, mu)."""
    rows, cols = g['shape']
    T, vis = np.ones((rows, cols)), np.ones((rows, cols), bool)
    if g['field'] is not None:
        yy, xx = np.mgrid[0:rows, 0:cols]
        vis = np.hypot(xx - g['field'][0], yy - g['field'][1]) <= g['field'][2] + 3
    rr, cc = np.nonzero(vis & bool(objs))
    for sl in np.array_split(np.arange(len(rr)), len(rr) // 120000 + 1):
        T[rr[sl], cc[sl]] = np.exp(-_bg_L(_rays(*_sample_grid(cc[sl], rr[sl], ss_bg), g), objs, g['S'])).mean(1)
    mask, boxes = np.zeros((rows, cols), bool), []                # union of bead patches, 6x6 sub-samples
    cx, cy = project(np.array([s[0] for s in sph]), g)
    for j, (Pj, aj, mu) in enumerate(sph):
        h, c0, r0 = _shadow_box(g, Pj, aj, cx[j], cy[j])
        b = (j, max(r0 - h, 0), min(r0 + h + 1, rows), max(c0 - h, 0), min(c0 + h + 1, cols))
        if b[2] > b[1] and b[4] > b[3]:
            mask[b[1]:b[2], b[3]:b[4]] = True
            boxes.append(b)
    pr, pc = np.nonzero(mask)
    idx = np.full((rows, cols), -1)
    idx[pr, pc] = np.arange(len(pr))
    D = _rays(*_sample_grid(pc, pr, ss_sp), g)
    L = _bg_L(D, objs, g['S'])                                    # holder + clutter at the same sub-samples
    for j, r0, r1, c0, c1 in boxes:
        ids = idx[r0:r1, c0:c1].ravel()
        L[ids] += sph[j][2] * _chord_sphere(g['S'], [d[ids] for d in D], sph[j][0], sph[j][1])
    T[pr, pc] = np.exp(-L).mean(1)
    return T

def sphere_truth(g, Pj, aj, clut=(), ss=10):
    c, r = project(Pj[None], g)
    h, c0, r0 = _shadow_box(g, Pj, aj, c[0], r[0])
    yy, xx = np.mgrid[r0 - h:r0 + h + 1, c0 - h:c0 + h + 1]
    cs, rs = _sample_grid(xx.ravel().astype(float), yy.ravel().astype(float), ss)
    D = _rays(cs, rs, g)
    w = _chord_sphere(g['S'], D, Pj, aj)
    sup = w > 0                                               # the bead's own shadow (measured coords)
    inf, s2 = _in_field(cs[sup], rs[sup], g), sup.any(1).reshape(xx.shape)
    return dict(x=(cs * w).sum() / w.sum(), y=(rs * w).sum() / w.sum(), x_centre=c[0], y_centre=r[0],
                diameter_px=2 * np.sqrt(sup.sum() / ss ** 2 / np.pi), any=bool(inf.any()), all=bool(inf.all()),
                clutter=bool(clut) and bool((_bg_L([d[sup] for d in D], clut, g['S']) > 0).any()),
                edge=bool(s2[0].any() or s2[-1].any() or s2[:, 0].any() or s2[:, -1].any()), box=(h, c0, r0))

def _heldout(C, rng, n=40):
    pts, v = [], C['vol']
    while len(pts) < n:
        if v[0] == 'cyl':
            q = np.r_[rng.uniform(-v[1], v[1], 2), rng.uniform(-v[2], v[2])]
            ok = np.hypot(*q[:2]) <= v[1] and np.linalg.norm(C['ph'] - q, axis=1).min() > v[3]
        elif v[0] == 'plate':                                 # off the bead plane, inside the plate
            q, ok = np.r_[rng.uniform(-v[1], v[1], 2), rng.choice([-1, 1]) * rng.uniform(1.5, v[2])], True
        else:
            q = rng.uniform([-48, -48, -30], [48, 48, 30])
            ok = min(abs(q[2] - 25), abs(q[2] + 25)) > 4
        if ok:
            pts.append(q)
    return np.array(pts)

def build(name, seed):
    """Case configuration and per-frame geometry/scene (deterministic for (name, seed))."""
    rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
    C = _config(name, rng)
    nF, a = int(rng.integers(20, 25)), C['diam'] / 2
    want_ov, want_tr = np.zeros(nF, bool), np.zeros(nF, bool)
    want_ov[rng.choice(nF, int(round(nF / 4)), replace=False)] = True
    want_tr[rng.choice(np.flatnonzero(~want_ov), int(round(nF * C['trunc'])), replace=False)] = True
    cw = _clutter_world(rng) if C['clutter'] else None
    frames, warn = [], 0
    for k in range(nF):
        for _ in range(4000):
            steep = want_ov[k] and C['steep'] is not None
            th = rng.uniform(*C['steep']) if steep else C['tilt'] * np.sqrt(rng.uniform())
            beta = rng.uniform(0, 2 * np.pi)
            Rc = _rotv([np.cos(beta), np.sin(beta), 0], th) @ _rotv([0, 0, 1], rng.uniform(-C['roll'], C['roll']))
            R = Rc @ C['base'] @ _rotv([0, 0, 1], rng.uniform(0, 2 * np.pi))   # any turn about phantom z
            ang, rad = rng.uniform(0, 2 * np.pi), rng.uniform(25, 90)
            txy = rad * np.array([np.cos(ang), np.sin(ang)]) if want_tr[k] else rng.uniform(-C['offset'], C['offset'], 2)
            t = np.r_[txy, C['sod'] * rng.uniform(-0.05, 0.05)]
            g = _geo(C, Rc, rng)
            full, ov = _quick(C, g, C['ph'] @ R.T + t, a)
            okt = (0.12 <= 1 - full.mean() <= 0.6) if want_tr[k] else full.all()
            if okt and ov.any() == want_ov[k] and (not steep or 0.08 <= ov.mean() <= 0.7):
                break
        else:
            warn += 1
        objs, clut = _frame_objs(C, R, t, Rc, rng, cw)
        frames.append(dict(R=R, t=t, Rc=Rc, g=g, objs=objs, clut=clut))
    return C, frames, rng, warn

def _blur(img, s):
    return cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REFLECT) if s > 0 else img

def _ff_chain(C, T, G, dark_off, rng, I0):
    lam = C['N0'] * I0 * _blur(T, C['blur'])
    cnt = _blur(rng.poisson(lam).astype(float) if rng is not None else lam, C['blur_post'])
    return 2.0 * G * cnt + dark_off + (rng.normal(0, 3.0, T.shape) if rng is not None else 0)

def _ii_chain(C, T, rng, fm, rho2):
    q = C['N0'] * _blur(T, C['blur'])
    q = _blur((rng.poisson(q) if rng is not None else q) / C['N0'], C['blur_post'])
    q = (0.88 * q + 0.12 * _blur(q * fm, 25.0) / np.maximum(_blur(fm, 25.0), 1e-6)) * (1 - 0.25 * rho2)
    q = np.maximum(q + (rng.normal(0, 0.003, q.shape) if rng is not None else 0), 1e-6)
    if C['display'] == 'log':
        d = 255 * (np.log(q) - np.log(0.02)) / (np.log(1.25) - np.log(0.02))
    else:
        d = 255 * np.clip(q / (1.2 if C['display'] == 'gamma0.6' else 1.1), 0, 1) ** float(C['display'][5:])
    return np.clip(d, 0, 255) * fm

def _soft(rng, shape):                            # water-equivalent anatomy, 25 +- 8 mm
    f = cv2.resize(rng.normal(size=(shape[0] // 40 + 3, shape[1] // 40 + 3)), shape[::-1], interpolation=cv2.INTER_CUBIC)
    f = _blur(f, 20.0)
    return np.clip(0.02 * (25 + 8 * (f - f.mean()) / f.std()), 0.1, None)

def make_case(name, seed, out):
    t_start, (C, frames, rng, warn) = time.time(), build(name, seed)
    out, sd = Path(out), Path(out) / 'scan'
    sd.mkdir(parents=True, exist_ok=True)
    rows, cols = C['shape']
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    a, mu_s, ones = C['diam'] / 2, MU_STEEL - MU_PMMA, np.ones((rows, cols))
    if C['ii']:
        rho = np.hypot(xx - C['field'][0], yy - C['field'][1]) / C['field'][2]      # soft circular field edge
        fm, rho2 = np.clip((1 - rho) * C['field'][2] / 1.5 + 0.5, 0, 1), rho ** 2
    else:
        rr = np.sqrt(((xx - C['pp0'][0]) * C['pitch']) ** 2 + ((yy - C['pp0'][1]) * C['pitch']) ** 2 + C['sdd'] ** 2)
        I0 = (C['sdd'] / rr) ** 3 * (1 + 0.04 * (xx - cols / 2) / (cols / 2))
        G = rng.normal(1, 0.015, (rows, cols)) * (1 + rng.normal(0, 0.005, cols))[None, :]
        G[:, cols // 2:] *= 1.03                          # two read-out halves
        dark_off, Gp = 300 + rng.normal(0, 20, cols)[None, :] + np.zeros((rows, 1)), G.copy()
        if name == 'helix_ff':
            eps = cv2.resize(rng.normal(size=(6, 6)), (cols, rows), interpolation=cv2.INTER_CUBIC)
            Gp *= 1 + 0.003 * eps / np.abs(eps).max() + 0.002 * rng.normal(size=cols)[None, :]
    imgs, truth_c, noise, heldout, clut_ov, hp = [], [], [], [], [], _heldout(C, rng)
    for k, f in enumerate(frames):
        g, P = f['g'], C['ph'] @ f['R'].T + f['t']
        T = render_T(g, f['objs'], [(P[j], a[j], mu_s) for j in range(len(a))], ss_bg=3 if C['clutter'] else 2)
        if C['clutter']:
            T = T * np.exp(-_soft(rng, C['shape']))
        if C['ii']:
            clean, sel = _ii_chain(C, T, None, fm, rho2), fm > 0.99
            img = np.round(_ii_chain(C, T, rng, fm, rho2)).astype(np.uint8)
            if name == 'grid_holes_ii':
                img = cv2.imdecode(cv2.imencode('.jpg', img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1], cv2.IMREAD_GRAYSCALE)
        else:
            clean, sel = _ff_chain(C, T, Gp, dark_off, None, I0), ones > 0
            img = np.clip(np.round(_ff_chain(C, T, Gp, dark_off, rng, I0)), 0, 65535).astype(np.uint16)
        dif = (img.astype(float) - clean)[sel]
        noise.append(float(1.4826 * np.median(np.abs(dif - np.median(dif)))))
        imgs.append(img)
        tr = [s for s in (dict(id=j, **sphere_truth(g, P[j], a[j], f['clut'])) for j in range(len(a))) if s['any']]
        listed, ovm = np.zeros(len(a), bool), _cones(g, P, a)[2]
        listed[[s['id'] for s in tr]] = True
        truth_c.append([dict(id=s['id'], **{q: round(float(s[q]), 6) for q in ('x', 'y', 'x_centre', 'y_centre', 'diameter_px')},
                             overlap=bool((ovm[s['id']] & listed).any()), truncated=not s['all']) for s in tr])
        clut_ov.append([s['id'] for s in tr if s['clutter']])
        hc, hr = project(hp @ f['R'].T + f['t'], g)
        ok = _in_field(hc, hr, g)
        heldout.append(dict(frame=k, points=hp[ok].round(6).tolist(), pixels=np.c_[hc[ok], hr[ok]].round(6).tolist()))
    tifffile.imwrite(sd / 'projections.tif', np.stack(imgs))
    if C['ii']:
        flat = np.full((rows, cols), 255.0) if name == 'grid_holes_ii' else \
            np.mean([_ii_chain(C, ones, rng, fm, rho2) for _ in range(8)], 0)
        tifffile.imwrite(sd / 'flat.tif', np.round(flat).astype(np.uint8))
        tifffile.imwrite(sd / 'dark.tif', np.zeros((rows, cols), np.uint8))
    else:
        nfl = 4 if name == 'helix_ff' else 16
        fl = np.stack([np.clip(np.round(_ff_chain(C, ones, G, dark_off, rng, I0)), 0, 65535) for _ in range(nfl)])
        dk = np.stack([np.round(dark_off + rng.normal(0, 3.0, (rows, cols))) for _ in range(nfl)])
        for fn, st in (('flat.tif', fl), ('dark.tif', dk)):
            tifffile.imwrite(sd / fn, (st if nfl == 4 else np.round(st.mean(0))).astype(np.uint16))
    nF = len(frames)                               # log.csv: frame, time only (free motion)
    (sd / 'log.csv').write_text('frame,time\n' + ''.join(f'{k},{2.0 * k + 0.1 * rng.uniform():.3f}\n' for k in range(nF)))
    (sd / 'phantom.csv').write_text('id,x,y,z\n' + ''.join(f'{j},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f}\n' for j, p in enumerate(C['ph'])))
    vals, cnts = np.unique(C['diam'], return_counts=True)
    sdd_t = float(np.mean([f['g']['sdd'] for f in frames]))
    if name == 'ball_clutter_ii':                      # nominal magnification sdd/sod 20 % too large
        nom_sdd, nom_sod, C['nominal_mag_err'] = round(sdd_t, 1), round(C['sod'] / 1.2, 1), 0.20
    else:
        nom_sod, nom_sdd = round(C['sod'] * (1 + rng.uniform(-.03, .03)), 1), round(sdd_t * (1 + rng.uniform(-.02, .02)), 1)
    scan = {'format': 'conecal-scan/1', 'motion': 'free', 'projections': 'projections.tif', 'values': 'raw',
            'flat': 'flat.tif', 'dark': 'dark.tif', 'log': 'log.csv',
            'detector': {'rows': rows, 'cols': cols, 'pixel_pitch': [C['pitch'], C['pitch']]},
            'nominal': {'sod': float(nom_sod), 'sdd': float(nom_sdd)},
            'markers': {'diameter': float(vals[np.argmax(cnts)]), 'phantom': 'phantom.csv'}}
    (sd / 'scan.yaml').write_text(yaml.safe_dump(scan, sort_keys=False))
    fpp = [[float(v) for v in f['g']['pp']] for f in frames]
    truth = {'sdd': sdd_t, 'sod': float(C['sod']), 'pitch': C['pitch'], 'shape': [rows, cols],
             'principal_point': [float(v) for v in np.mean(fpp, 0)], 'frame_principal_point': fpp,
             'frame_sdd': [float(f['g']['sdd']) for f in frames], 'values': 'raw',
             'poses': [dict(frame=k, R=f['R'].tolist(), t=f['t'].tolist()) for k, f in enumerate(frames)],
             'centres': truth_c, 'heldout': heldout, 'noise_sigma': noise,
             'distortion_kind': 'curved-screen-tan-pincushion+radial-squared-twist' if C['ii'] else 'none',
             'distortion': [dict(f['g']['dist'], twist_px_at_rn=f['g']['dist']['omega'] * C['field'][2])
                            if C['ii'] else None for f in frames],
             'field_circle': [float(v) for v in C['field']] if C['ii'] else None,
             'sphere_diameters': C['diam'].tolist(), 'nominal': scan['nominal'],
             'nominal_magnification_error': C['nominal_mag_err'], 'display': C.get('display', 'linear-uint16'),
             'jpeg_quality': 85 if name == 'grid_holes_ii' else None, 'incident_counts': C['N0'],
             'blur_sigma_px': [C['blur'], C['blur_post']], 'clutter_overlap': clut_ov if C['clutter'] else None,
             'pose_sampling_failures': warn}
    if name == 'grid_sym_ff':
        ops = [_rotv([0, 0, 1], q * np.pi / 2) @ F for F in (np.eye(3), np.diag([1.0, -1, -1])) for q in range(4)]
        truth['symmetry'] = {'group': 'D4 (8 proper rotations)', 'id_permutations': [
            [int(np.argmin(np.linalg.norm(C['ph'] - x, axis=1))) for x in C['ph'] @ Rs.T] for Rs in ops]}
    (out / 'truth.json').write_text(json.dumps(truth))
    return dict(case=name, seed=seed, frames=nF, shape=[rows, cols], values='raw',
                overlap_frames=sum(any(s['overlap'] for s in fc) for fc in truth_c),
                truncated_frames=sum(any(s['truncated'] for s in fc) for fc in truth_c),
                noise_sigma_median=float(np.median(noise)), pose_sampling_failures=warn,
                seconds=round(time.time() - t_start, 2))

def _selfcheck(name, seed=0):
    """Independent checks (not a shipped test): pinhole matrices, image centroids, TIFF round trip."""
    import tempfile
    with tempfile.TemporaryDirectory() as td:
        summ = make_case(name, seed, td)
        tru, sd, (C, frames, _, _) = json.loads((Path(td) / 'truth.json').read_text()), Path(td) / 'scan', build(name, seed)
        proj = tifffile.imread(sd / 'projections.tif')
        fl, dk = (tifffile.imread(sd / n).astype(float).reshape((-1,) + proj.shape[1:]).mean(0) for n in ('flat.tif', 'dark.tif'))
        yy, xx = np.mgrid[0:fl.shape[0], 0:fl.shape[1]]
        ok = (fl - dk > 10) & _in_field(xx, yy, frames[0]['g'])
        tr = (proj.astype(float) - dk)[:, ok] / (fl - dk)[ok]
        pin, cone, img_err, cone0, edge = [], [], [], [], 0
        for k, f in enumerate(frames):
            g = f['g']
            K = np.array([[g['sdd'] / g['pu'], 0, g['pp'][0]], [0, g['sdd'] / g['pv'], g['pp'][1]], [0, 0, 1]])
            M = K @ np.c_[np.array(tru['poses'][k]['R']), np.array(tru['poses'][k]['t']) + [0, 0, g['sod']]]
            for s in tru['centres'][k]:
                h = M @ np.r_[C['ph'][s['id']], 1]
                ci, ri = dist_inv(np.array(s['x_centre']), np.array(s['y_centre']), g['dist'])
                pin.append(np.hypot(h[0] / h[2] - ci, h[1] / h[2] - ri))
                cone.append(np.hypot(s['x'] - s['x_centre'], s['y'] - s['y_centre']))
            if k >= 3:
                continue
            P = C['ph'] @ f['R'].T + f['t']
            for dist in (g['dist'], None):             # noise-, blur-, background-free single-sphere renders
                g2 = dict(g, dist=dist)
                for j in [s['id'] for s in tru['centres'][k] if not (s['overlap'] or s['truncated'])]:
                    st = sphere_truth(g2, P[j], C['diam'][j] / 2)
                    edge += st['edge']
                    A = -np.log(render_T(g2, [], [(P[j], C['diam'][j] / 2, MU_STEEL - MU_PMMA)]))
                    h_, c0, r0 = st['box']                 # centroid of -ln T over the shadow box
                    w, (wy, wx) = A[r0 - h_:r0 + h_ + 1, c0 - h_:c0 + h_ + 1], np.mgrid[r0 - h_:r0 + h_ + 1, c0 - h_:c0 + h_ + 1]
                    img_err.append(np.hypot((w * wx).sum() / w.sum() - st['x'], (w * wy).sum() / w.sum() - st['y']))
                    if dist is None:
                        cone0.append(np.hypot(st['x'] - st['x_centre'], st['y'] - st['y_centre']))
        mm = lambda v: [float(np.mean(v)), float(np.max(v))]
        rep = dict(summ, pinhole_vs_truth_max_px=float(np.max(pin)), image_centroid_vs_truth_px=mm(img_err),
                   cone_offset_nodist_px=mm(cone0), centroid_minus_centre_px=mm(cone), box_edge_hits=int(edge),
                   transmission_le0=float((tr <= 0).mean()), transmission_gt1=float((tr > 1).mean()),
                   transmission_p01_p50_p999=[float(np.percentile(tr, q)) for q in (0.1, 50, 99.9)],
                   stack=[list(proj.shape), str(proj.dtype)], spheres_listed=sum(len(c) for c in tru['centres']),
                   heldout_per_frame=float(np.mean([len(h['points']) for h in tru['heldout']])))
        print(json.dumps(rep))
        return rep

if __name__ == '__main__':
    import sys
    for n in (sys.argv[1:] or list(CASES)):
        _selfcheck(n)
