"""Independent synthetic cone-beam radiographs of a helix-of-steel-spheres phantom.

Written from the physics alone (no reference to the detector code) so that it can
serve as an independent test bed for sphere-marker detection.

Geometry (all lengths in mm, world frame = source frame):
  * point source at the origin, central ray along +z;
  * flat detector perpendicular to +z at z = SDD = 900 mm, 1024 x 1024 pixels of
    0.2 mm; pixel (row i, col j) centre at X = (j - 511.5)*p, Y = (i - 511.5)*p, so
    pixel coordinates have (0,0) at the centre of the first pixel, x along columns;
  * nominal object centre at (0, 0, SOD = 420 mm) -> magnification ~2.14.

Phantom (phantom frame, helix axis = z, centred at the origin):
  * 50 steel spheres, diameters 0.9 mm and 1.2 mm (fixed mixed pattern), centres on
    a helix of radius 10.5 mm, 3 turns over 40 mm (pitch 13.33 mm);
  * a PMMA-like holder tube, outer diameter 25 mm, inner diameter 17 mm, length
    50 mm, coaxial with the helix; the spheres are embedded in its wall (steel
    replaces plastic, so the sphere contribution uses mu_steel - mu_plastic).

Per frame the phantom gets a random 6-DoF pose (uniform random rotation, with
every 4th frame forced to have the helix axis within 8 deg of the beam, and
translation x,y in +-20 mm, z in +-20 mm around the nominal centre).

Attenuation image = sum over spheres of mu*chord (exact ray/sphere chord, 3x3
supersampling per pixel, each sphere rendered only in its bounding box) + holder
chord * mu_plastic (exact ray / finite hollow cylinder chord, at pixel centres).
Detector: I = I0*exp(-A), I0 = 5000, Poisson noise, Gaussian scintillator blur
(sigma 0.6-1.0 px) applied after the noise on even frames and before it on odd
frames; output attenuation = -ln(max(I,1)/I0), float32.
"""
from __future__ import annotations

import math
import time

import cv2
import numpy as np

# ----------------------------------------------------------------------------
# fixed set-up
SDD = 900.0          # source-detector distance, mm
SOD = 420.0          # source-object (nominal phantom centre) distance, mm
NPIX = 1024          # detector is NPIX x NPIX
PITCH = 0.2          # mm per pixel
I0 = 5000.0          # open-beam counts
MU_STEEL = 0.5       # 1/mm (effective)
MU_PLASTIC = 0.02    # 1/mm
SUPER = 3            # supersampling per pixel axis for the spheres

N_SPHERES = 50
HELIX_RADIUS = 10.5
HELIX_LENGTH = 40.0
HELIX_TURNS = 3.0
D_SMALL, D_LARGE = 0.9, 1.2

TUBE_R_OUT = 12.5
TUBE_R_IN = 8.5
TUBE_HALF_LEN = 25.0


def _phantom():
    """Sphere centres (N,3) and radii (N,) in the phantom frame (fixed design)."""
    k = np.arange(N_SPHERES)
    frac = k / (N_SPHERES - 1)
    phi = 2 * np.pi * HELIX_TURNS * frac
    z = (frac - 0.5) * HELIX_LENGTH
    centres = np.stack([HELIX_RADIUS * np.cos(phi), HELIX_RADIUS * np.sin(phi), z], 1)
    # fixed mixed size pattern: 17 large, 33 small, pseudo-random but seed-independent
    large = np.zeros(N_SPHERES, bool)
    large[np.random.default_rng(20240607).choice(N_SPHERES, 17, replace=False)] = True
    radii = np.where(large, D_LARGE / 2, D_SMALL / 2)
    # spheres completely inside the holder wall displace plastic
    rr = np.hypot(centres[:, 0], centres[:, 1])
    embedded = ((rr - radii >= TUBE_R_IN) & (rr + radii <= TUBE_R_OUT)
                & (np.abs(z) + radii <= TUBE_HALF_LEN))
    return centres, radii, embedded


PH_CENTRES, PH_RADII, PH_EMBEDDED = _phantom()


# ----------------------------------------------------------------------------
# poses
def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _axis_angle(axis, ang):
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def _pose(rng, frame_idx):
    if frame_idx % 4 == 1:
        # helix axis nearly along the beam: spin about z, flip or not, tilt <= 8 deg
        R = _axis_angle([0, 0, 1], rng.uniform(0, 2 * np.pi))
        if rng.random() < 0.5:
            R = _axis_angle([1, 0, 0], np.pi) @ R
        tilt_ax = rng.normal(size=3)
        tilt_ax[2] = 0
        R = _axis_angle(tilt_ax, np.deg2rad(rng.uniform(0, 8))) @ R
    else:
        R = _random_rotation(rng)
    t = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), SOD + rng.uniform(-20, 20)])
    return R, t


# ----------------------------------------------------------------------------
# detector geometry helpers
_C0 = (NPIX - 1) / 2.0


def _pix_to_xy(col, row):
    return (col - _C0) * PITCH, (row - _C0) * PITCH


def _proj(P):
    """3-D point(s) -> pixel (x=col, y=row)."""
    P = np.asarray(P, float)
    return P[..., 0] / P[..., 2] * SDD / PITCH + _C0, P[..., 1] / P[..., 2] * SDD / PITCH + _C0


def _ortho_basis(c):
    c = c / np.linalg.norm(c)
    a = np.array([1.0, 0, 0]) if abs(c[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(c, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(c, e1)


def _shadow_boundary(C, R, n=256):
    """Exact shadow outline (pixel coords) of a sphere: the tangent cone cut by the detector."""
    d = np.linalg.norm(C)
    c = C / d
    alpha = math.asin(R / d)
    e1, e2 = _ortho_basis(c)
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    dirs = (math.cos(alpha) * c[None, :]
            + math.sin(alpha) * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2))
    return np.stack(_proj(dirs), 1)


def _polygon_area(pts):
    x, y = pts[:, 0], pts[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _lens_area(r1, r2, d):
    if d >= r1 + r2:
        return 0.0
    if d <= abs(r1 - r2):
        return math.pi * min(r1, r2) ** 2
    a1 = math.acos(np.clip((d * d + r1 * r1 - r2 * r2) / (2 * d * r1), -1, 1))
    a2 = math.acos(np.clip((d * d + r2 * r2 - r1 * r1) / (2 * d * r2), -1, 1))
    return (r1 * r1 * (a1 - math.sin(2 * a1) / 2) + r2 * r2 * (a2 - math.sin(2 * a2) / 2))


def _slerp_dir(a, b, ang):
    """Unit vector at angle `ang` from unit a towards unit b on the great circle."""
    g = math.acos(np.clip(np.dot(a, b), -1, 1))
    if g < 1e-12:
        return a
    perp = b - math.cos(g) * a
    perp /= np.linalg.norm(perp)
    return math.cos(ang) * a + math.sin(ang) * perp


# ----------------------------------------------------------------------------
# rendering
def _render_holder(R, t):
    """mu_plastic * chord through the finite hollow tube, at pixel centres (H,W)."""
    ax = R[:, 2]                       # tube axis in world frame
    Q = t                              # tube centre
    cols = np.arange(NPIX, dtype=np.float64)
    X, Y = _pix_to_xy(cols[None, :], cols[:, None])
    X = np.broadcast_to(X, (NPIX, NPIX))
    Y = np.broadcast_to(Y, (NPIX, NPIX))
    nrm = np.sqrt(X * X + Y * Y + SDD * SDD)
    u = np.stack([X / nrm, Y / nrm, SDD / nrm], -1)   # (H,W,3)
    w = -Q                                             # source (origin) - Q
    ua = u @ ax
    wa = float(w @ ax)
    up = u - ua[..., None] * ax
    wp = w - wa * ax
    A = np.einsum('ijk,ijk->ij', up, up)
    B = up @ wp
    # slab along axis: |wa + t*ua| <= h
    with np.errstate(divide='ignore', invalid='ignore'):
        s1 = (-TUBE_HALF_LEN - wa) / ua
        s2 = (TUBE_HALF_LEN - wa) / ua
    smin = np.minimum(s1, s2)
    smax = np.maximum(s1, s2)
    par = np.abs(ua) < 1e-12
    inside_slab = abs(wa) <= TUBE_HALF_LEN
    smin = np.where(par, -np.inf if inside_slab else np.inf, smin)
    smax = np.where(par, np.inf if inside_slab else -np.inf, smax)

    def chord(rho):
        Cc = float(wp @ wp) - rho * rho
        disc = B * B - A * Cc
        ok = (disc > 0) & (A > 1e-15)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        Asafe = np.where(ok, A, 1.0)
        t1 = (-B - sq) / Asafe
        t2 = (-B + sq) / Asafe
        lo = np.maximum(np.maximum(t1, smin), 0.0)
        hi = np.minimum(t2, smax)
        return np.where(ok, np.maximum(hi - lo, 0.0), 0.0)

    return MU_PLASTIC * (chord(TUBE_R_OUT) - chord(TUBE_R_IN))


_SUB = (np.arange(SUPER) - (SUPER - 1) / 2.0) / SUPER    # sub-pixel offsets


def _render_sphere(C, R):
    """Pixel-averaged chord (mm) of one sphere in its bounding box.

    Returns (r0, c0, img, mask_ss, partial) where img is (h,w) float64 for pixel
    rows r0.. and cols c0.., and mask_ss the (h*S, w*S) supersample chord>0 mask.
    """
    xs, ys = _shadow_boundary(C, R, 64).T
    # bounding box (polygon of 64 tangent points is inscribed; pad 1.5 px)
    c_lo = int(math.floor(xs.min() - 1.5))
    c_hi = int(math.ceil(xs.max() + 1.5))
    r_lo = int(math.floor(ys.min() - 1.5))
    r_hi = int(math.ceil(ys.max() + 1.5))
    partial = c_lo < 0 or r_lo < 0 or c_hi > NPIX - 1 or r_hi > NPIX - 1
    c_lo, r_lo = max(c_lo, 0), max(r_lo, 0)
    c_hi, r_hi = min(c_hi, NPIX - 1), min(r_hi, NPIX - 1)
    if c_hi < c_lo or r_hi < r_lo:
        return None
    cols = (np.arange(c_lo, c_hi + 1)[:, None] + _SUB[None, :]).ravel()
    rows = (np.arange(r_lo, r_hi + 1)[:, None] + _SUB[None, :]).ravel()
    X, Y = _pix_to_xy(cols[None, :], rows[:, None])
    nrm = np.sqrt(X * X + Y * Y + SDD * SDD)
    cu = (C[0] * X + C[1] * Y + C[2] * SDD) / nrm          # C . u
    d2 = float(C @ C) - cu * cu                            # squared ray-centre distance
    ch = 2.0 * np.sqrt(np.maximum(R * R - d2, 0.0))        # chord length
    h, w = r_hi - r_lo + 1, c_hi - c_lo + 1
    img = ch.reshape(h, SUPER, w, SUPER).mean(axis=(1, 3))
    return r_lo, c_lo, img, ch > 0, partial


def _render_frame(R, t):
    centres = PH_CENTRES @ R.T + t
    radii = PH_RADII
    mu = np.where(PH_EMBEDDED, MU_STEEL - MU_PLASTIC, MU_STEEL)
    A = _render_holder(R, t)
    n = len(radii)
    info = []
    for k in range(n):
        C, Rk = centres[k], radii[k]
        rend = _render_sphere(C, Rk)
        bnd = _shadow_boundary(C, Rk, 256)
        area = _polygon_area(bnd)
        px, py = _proj(C)
        d = float(np.linalg.norm(C))
        e = dict(k=k, C=C, R=Rk, dirv=C / d, alpha=math.asin(Rk / d),
                 r_px=math.sqrt(area / math.pi), px=float(px), py=float(py),
                 rend=rend)
        if rend is not None:
            r0, c0, img, _, partial = rend
            A[r0:r0 + img.shape[0], c0:c0 + img.shape[1]] += mu[k] * img
            wsum = img.sum()
            yy, xx = np.mgrid[r0:r0 + img.shape[0], c0:c0 + img.shape[1]]
            e['cx'] = float((img * xx).sum() / wsum)
            e['cy'] = float((img * yy).sum() / wsum)
            e['partial'] = bool(partial)
        info.append(e)

    # pairwise gaps / overlaps (exact in cone-angle space, converted to pixels)
    gap = np.full((n, n), np.inf)
    ofrac = np.zeros((n, n))
    ofrac_px = np.zeros((n, n))
    dirs = np.array([e['dirv'] for e in info])
    alph = np.array([e['alpha'] for e in info])
    gam = np.arccos(np.clip(dirs @ dirs.T, -1, 1))
    for i in range(n):
        for j in range(i + 1, n):
            if gam[i, j] - alph[i] - alph[j] > 0.02:   # far apart: gap irrelevant
                continue
            # boundary points facing each other along the great circle through both axes
            pi_ = _slerp_dir(dirs[i], dirs[j], alph[i])
            pj_ = _slerp_dir(dirs[j], dirs[i], alph[j])
            qi = np.array(_proj(pi_))
            qj = np.array(_proj(pj_))
            s = 1.0 if gam[i, j] >= alph[i] + alph[j] else -1.0
            g = s * float(np.linalg.norm(qi - qj))
            gap[i, j] = gap[j, i] = g
            ri, rj = info[i]['r_px'], info[j]['r_px']
            lens = _lens_area(ri, rj, ri + rj + g)
            ofrac[i, j] = lens / (math.pi * ri * ri)
            ofrac[j, i] = lens / (math.pi * rj * rj)
            # cross-check from supersampled masks
            if g < 0 and info[i]['rend'] is not None and info[j]['rend'] is not None:
                ri0, ci0, _, mi, _ = info[i]['rend']
                rj0, cj0, _, mj, _ = info[j]['rend']
                # supersample grid index = pixel*S + sub
                a0 = (ri0 * SUPER, ci0 * SUPER)
                b0 = (rj0 * SUPER, cj0 * SUPER)
                r_a = max(a0[0], b0[0]); r_b = min(a0[0] + mi.shape[0], b0[0] + mj.shape[0])
                c_a = max(a0[1], b0[1]); c_b = min(a0[1] + mi.shape[1], b0[1] + mj.shape[1])
                if r_b > r_a and c_b > c_a:
                    inter = np.count_nonzero(
                        mi[r_a - a0[0]:r_b - a0[0], c_a - a0[1]:c_b - a0[1]]
                        & mj[r_a - b0[0]:r_b - b0[0], c_a - b0[1]:c_b - b0[1]])
                    ofrac_px[i, j] = inter / max(np.count_nonzero(mi), 1)
                    ofrac_px[j, i] = inter / max(np.count_nonzero(mj), 1)

    truth = []
    for e in info:
        k = e['k']
        if not (-0.5 <= e['px'] <= NPIX - 0.5 and -0.5 <= e['py'] <= NPIX - 0.5):
            continue
        if e['rend'] is None:
            continue
        g = gap[k].min()
        truth.append(dict(
            x=e['cx'], y=e['cy'], r_px=float(e['r_px']), id=int(k),
            overlap_frac=float(ofrac[k].max()),
            min_gap_diam=float(g / (2 * e['r_px'])) if np.isfinite(g) else float('inf'),
            overlap_frac_px=float(ofrac_px[k].max()),
            diam_mm=float(2 * e['R']), x_proj=e['px'], y_proj=e['py'],
            partial=e['partial']))
    return A, truth


def _detector(A, rng, sigma, blur_after_noise):
    I = I0 * np.exp(-A)
    if blur_after_noise:
        I = rng.poisson(I).astype(np.float64)
        I = cv2.GaussianBlur(I, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    else:
        I = cv2.GaussianBlur(I, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        I = rng.poisson(I).astype(np.float64)
    return (-np.log(np.maximum(I, 1.0) / I0)).astype(np.float32)


def make_frames(seed: int, n_frames: int = 24, return_meta: bool = False):
    """Generate `n_frames` noisy attenuation radiographs and per-frame truth.

    Returns (frames float32 (F,H,W), truth list-of-lists of dicts) and, when
    return_meta, a third element: list of per-frame dicts (R, t, sigma,
    blur_after_noise, clean attenuation not included).
    Truth dict keys: x, y (attenuation-weighted centroid of the sphere's own
    noiseless shadow, px), r_px (equivalent radius sqrt(area/pi) of the exact
    shadow), id (helix index 0..49), overlap_frac, min_gap_diam, plus extras
    overlap_frac_px (supersampled-mask cross-check), diam_mm, x_proj/y_proj
    (projected sphere centre), partial (shadow cut by the detector edge).
    min_gap_diam is +inf when no other shadow is within ~0.02 rad (~90 px).
    """
    rng = np.random.default_rng(seed)
    frames = np.empty((n_frames, NPIX, NPIX), np.float32)
    truth, meta = [], []
    for f in range(n_frames):
        R, t = _pose(rng, f)
        sigma = rng.uniform(0.6, 1.0)
        after = (f % 2 == 0)
        A, tr = _render_frame(R, t)
        frames[f] = _detector(A, rng, sigma, after)
        truth.append(tr)
        axis = R[:, 2]
        meta.append(dict(R=R, t=t, sigma=sigma, blur_after_noise=after,
                         axis_beam_angle_deg=float(np.degrees(np.arccos(abs(axis[2]))))))
    if return_meta:
        return frames, truth, meta
    return frames, truth


if __name__ == "__main__":
    t0 = time.perf_counter()
    frames, truth, meta = make_frames(0, return_meta=True)
    dt = time.perf_counter() - t0
    F = len(frames)
    print(f"geometry: SDD={SDD} SOD={SOD} mag={SDD/SOD:.3f} pitch={PITCH} mm "
          f"det={NPIX}x{NPIX}; spheres {N_SPHERES} (d={D_SMALL}/{D_LARGE} mm) on helix "
          f"r={HELIX_RADIUS} L={HELIX_LENGTH} turns={HELIX_TURNS}")
    print("frame in_field overlap near_touch(0<=g<0.5) partial ax-beam(deg) sigma blur  "
          "r_px[min,max]  max|ofrac-ofrac_px|")
    for f in range(F):
        tr = truth[f]
        n_ov = sum(d['overlap_frac'] > 0 for d in tr)
        n_nt = sum(0 <= d['min_gap_diam'] < 0.5 for d in tr)
        n_pa = sum(d['partial'] for d in tr)
        rp = [d['r_px'] for d in tr]
        dof = max(abs(d['overlap_frac'] - d['overlap_frac_px']) for d in tr)
        m = meta[f]
        print(f"{f:5d} {len(tr):8d} {n_ov:7d} {n_nt:10d} {n_pa:7d} {m['axis_beam_angle_deg']:11.1f} "
              f"{m['sigma']:5.2f} {'after ' if m['blur_after_noise'] else 'before'} "
              f"[{2*min(rp):5.1f},{2*max(rp):5.1f}]d   {dof:.3f}")
    print(f"total {dt:.2f} s for {F} frames = {dt/F*1000:.0f} ms/frame")
    a = frames[0]
    lo, hi = np.percentile(a, [0.5, 99.9])
    img = np.clip((a - lo) / (hi - lo), 0, 1)
    cv2.imwrite("/tmp/helix_indep_f0.png", (255 * (1 - img)).astype(np.uint8))
    print("saved /tmp/helix_indep_f0.png (display: dark = attenuating)")
