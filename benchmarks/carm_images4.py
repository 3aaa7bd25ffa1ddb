"""Independent test-data generator: free-pose (C-arm / radiography) marker scans.

Writes ``motion: free`` scan directories in the ``conecal-scan/1`` format
(``/work/shared/SCAN_FORMAT.md``) plus a ``truth.json``, for five cases whose
imaging physics deliberately departs from the textbook pinhole + radial model.
Written from first principles, independently of the tool under test.

Interface
---------
``CASES``                      name -> one-line description
``make_case(name, seed, out)`` writes ``out/scan/`` and ``out/truth.json``
                               (atomic: temporary file, then ``os.replace``) and
                               returns a summary dict (case, seed, frames,
                               spheres_per_frame, overlaps, truncated,
                               noise_sigma, seconds).  Deterministic in
                               (name, seed): the RNG is
                               ``numpy.random.default_rng([crc32(name), seed])``.
``python carm_images4.py``     self-check (seed 0, temporary directory).

Conventions (all cases)
-----------------------
* Lab frame as in the contract: source ``S = (0, 0, -sod)``; the detector is
  nominally the plane ``z = sdd - sod`` with ``u = +x`` (columns), ``v = +y``
  (rows).  The lab origin is the nominal phantom centre, so the true ``sod``
  is ``|S|``.  Pixel ``(c, r)`` is at ``origin + c*pu*u + r*pv*v``; the centre
  of ``img[0, 0]`` is ``(0, 0)``.
* Poses: ``P_lab = R p_phantom + t`` (truth ``poses``, one per frame, never
  logged: ``log.csv`` has only ``frame,time``).
* 3-D phantoms (cylinders, axis = phantom z): ``R = Rz(g) Rx(b) Rx(-90 deg)
  Rz(a)`` -- ``a`` in [0, 360) spin about the phantom axis, ``Rx(-90)`` lays the
  axis along lab +y (side view), ``b`` uniform in [-50, 50] deg tilt of the axis
  towards the beam, ``g`` in [0, 360) in-plane angle.
  Planar phantoms (plate in the phantom xy-plane): ``R = Rz(g) Rot(a, b)
  [Rx(180)]`` with ``a = (cos p, sin p, 0)``, ``p`` in [0, 180), ``b`` in
  [5, 60] deg; about 1/4 of the frames are seen from behind (``Rx(180)``
  appended); 2 or 3 "steep" frames use ``b`` in [80, 83] deg with ``p`` within
  5 deg of a grid axis -- at <= 60 deg no two shadows of these grids can touch
  (pitch*cos(b) > bead diameter), so the overlapping frames have to be steeper.
* Translations ``t = (N(0,5), N(0,5), U(-20,20))`` mm; 3 frames
  are pushed along x or y by ``H - U(0.1, 0.5) r_cloud`` (random sign), H the
  half-extent of the detector (or field) in the object plane, r_cloud the
  largest bead distance from the phantom origin, so part of the bead set
  leaves the image / field.
* Exact chord lengths along each point-source ray: spheres (closed form),
  PMMA cylinder / plate and lead boxes (slab method in their own frames),
  steel wires (infinite cylinders: ``2 sqrt(rho^2 - D^2) / sin(angle)``).
  PMMA path excludes the steel beads embedded in it.  Materials: steel
  ``mu = 0.45 /mm``, PMMA ``0.02 /mm``, lead ``5.0 /mm``.
* Rendering: every pixel whose box can contain part of a sphere shadow is
  integrated on 8x8 sub-samples (box aperture: pixel value = mean of
  ``exp(-A)`` over its sub-samples); elsewhere the line integral is traced
  exactly on a 2-px grid and interpolated bilinearly, except pixels where its
  second difference exceeds 0.004 (PMMA / lead edges) or within 2.5 pixel
  footprints of a wire, which are integrated on 4x4 sub-samples (background
  error < 5e-4 in transmission).  Then Gaussian blur (``blur_px``, 1 sigma,
  true value; ``scan.yaml imaging.blur_px`` is the true value times
  U(0.9, 1.1)), then the case's chain below.
* Distortion maps IDEAL pinhole coordinates ``p`` to MEASURED ones ``q``; the
  image is rendered in measured coordinates by inverting it numerically
  (radial: Newton on the radius; general: exact fixed point on a 4-px grid,
  bilinear interpolation, plus one fixed-point refinement step for the
  sphere sub-samples: error < 1e-3 px).
* Field of view (intensifiers), in measured pixels: inside ``rho <= 1`` the
  response is full; outside a raised-cosine taper falls to 0 over ``w`` px
  (distance beyond the edge measured as ``(rho - 1) * minor semi-axis``) and
  the image is black beyond.  "Inside the field" in the truth means
  ``rho <= 1``.
* Noise: Poisson quanta (on the blurred expected quanta) + Gaussian
  electronic noise; quantised as each case says.

Truth (``truth.json``)
----------------------
* ``centres[f]``: every sphere with any visible shadow (inside image and
  field): ``id``, ``x``, ``y`` = centroid of the sphere's OWN shadow weighted by
  its own chord length, over its 8x8 sub-samples that are inside the image
  and the field, before blur, in MEASURED coordinates of the WRITTEN image
  (after the left-right flip of ``mirror_helix``); ``diameter_px`` =
  ``2 sqrt(area/pi)`` of the visible part; ``truncated`` (a silhouette point,
  96 per sphere, lies off the image ``[-0.5, n-0.5]`` or outside the field);
  ``overlap`` (its shadow shares a pixel with another listed sphere's);
  extras ``diameter_mm``, ``clutter`` (a wire/lead path crosses its shadow).
* ``heldout[f]``: ``{frame, points, pixels}`` -- 30 fixed points in the phantom
  frame inside its bounding volume (planar: plate footprint, z within
  +-30 mm), at >= 4 mm from every bead surface, projected through the true
  geometry + distortion (+ flip), kept if inside image and field.
* ``sdd`` = perpendicular distance from S to the detector plane,
  ``principal_point`` = foot of that perpendicular in (c, r) px, ``geometry``
  (source, detector origin/u/v/pitch/shape), ``poses``, ``noise_sigma`` per
  frame (1.4826 * MAD of written minus noise-free written image, inside the
  field, in written units), ``distortion_kind``, ``distortion`` (per-frame
  parameters), ``bead_diameters_mm``, ``nominal``, ``description``,
  ``symmetry`` where the bead set (with sizes) maps onto itself under a proper
  rotation (``id_permutations[k][i]`` = id that bead i lands on; identity
  first; ``rotations`` in the phantom frame), ``expect``.

Summary and self-check
----------------------
``overlaps`` / ``truncated`` in the summary count listed sphere instances over
all frames; ``spheres_per_frame`` is the mean number listed; ``noise_sigma``
the mean per-frame sigma.  The self-check flat-fields every frame
(``(raw - mean dark)/(mean flat - mean dark)``, ``exp(-attenuation)`` or the
transmission), and requires at every non-truncated truth centre a dip below
the 90th percentile of a ring (radius + 2..6 px) larger than
max(5 sigma_noise, 5 % of that level).  For isolated, clutter-free spheres it
also prints the distance between the truth centre and the centroid of the
line-integral excess over a plane fitted on the ring (noise-free renders
agree to ~0.005-0.02 px median).

Cases and parameter ranges (U = uniform, per seed)
--------------------------------------------------
1. ``tilt_fp`` -- flat panel, 960 rows x 1240 cols, pitch [pu, pv] =
   [0.148, 0.152] mm (declared, true).  ``values: raw``, uint16; flat.tif and
   dark.tif are 4-page noisy stacks.  sdd along z to the detector centre
   U(960, 1100), sod U(680, 800); detector centre offset U(-3, 3) mm in x, y;
   detector TILTED by U(2, 4) deg (random sign) about an in-plane axis through
   its centre at angle U(0, 180) deg from u (re-drawn until the principal
   point stays within 85 % of the half-size).  NOTE: a point source on a
   tilted plane is still an exact pinhole camera whose axis is the plane
   normal: the tilt shows up as a principal point shifted by ~sdd*tan(tilt)
   (250-500 px) and a slightly different sdd; truth gives those (and
   ``detector_tilt_deg``, ``tilt_axis``).  No lens distortion.
   Beam hardening per material: ``A = mu0 L / (1 + L/L0)``, L0 steel U(6, 10)
   mm, PMMA U(150, 300) mm (steel path includes all beads on the ray).
   Heel effect: ``I0 = 1 + h * xi``, ``xi`` in [-1, 1] the normalised
   coordinate along a random image direction, h U(0.10, 0.15).  Scatter:
   ``s * lowpass_sigma(heel * T)`` with s U(0.05, 0.10), sigma U(60, 120) px
   (object scatter: absent from the flat).  Quanta N0 U(6000, 12000)/px,
   ADU = dark + gain_map * g * counts + N(0, se), g U(2, 3), dark U(800, 1200)
   + column pattern N(0, 8), gain_map 1 + N(0, 0.02) per pixel, se U(3, 6);
   blur U(0.6, 0.9) px.  Phantom: PMMA cylinder radius 45, height 90; 18 steel
   beads of 2.0 mm + one of 4.0 mm (random id) irregularly inside r <= 36,
   |z| <= 36 (centres >= 8 mm apart).  ``markers.diameter = 2.0``.
2. ``barrel_ii`` -- image intensifier, 1024 x 1024, square pitch U(0.22, 0.24),
   ``values: raw``, uint16 holding 12-bit values 0..4095, single-page flat
   (mean of 16 exposures) and dark.  sdd U(950, 1050), sod U(600, 700),
   principal point = centre + U(-25, 25) px.  Distortion (ideal p -> q):
   ``q = C + Rot(th_f) [(p - C)(1 - k |p - C|^2)] + F(p)``; C = principal point
   + 10-30 px (random direction); ``k = D / A^3`` with D U(8, 15) px, A the
   field's major semi-axis; ``th_f = sgn * (th0 + th1 * (view_f . b))`` with
   th0 U(0.6, 0.7) deg, th1 U(0.25, 0.30) deg (|th_f| in [0.35, 1.0] deg),
   ``view_f = R_f^T z`` the beam direction in the phantom (room) frame, b a
   fixed random unit vector ("earth field"); F = sum of M U{6..10} modes
   ``a_m cos(2 pi (fx x/W + fy y/H) + phi_m)`` (fx, fy in [-2, 2] cycles per
   image, half-integers, vector amplitudes), scaled so max |F| = U(0.5, 1.2) px,
   same for all frames.  Elliptical field: semi-axes A U(0.45, 0.48)*1024,
   B U(0.39, 0.43)*1024, tilted U(-8, 8) deg, centre = image centre +
   U(-12, 12) px, soft edge w U(6, 12) px.  Chain: quanta Q = Poisson(N0*T)/N0
   (N0 U(1500, 3000)); ``L = taper * V * (Q + g * lowpass(taper*Q))``, veiling
   glare g U(0.05, 0.10) with sigma U(40, 80) px, vignetting
   ``V = 1 - v (r/A)^2`` about the field centre, v U(0.20, 0.35); ADU = dark
   U(40, 80) + Gc*L + N(0, U(1.5, 3)); flat centre ~ U(3000, 3500) ADU; blur
   U(0.9, 1.3) px.  Phantom: 9 x 9 grid, pitch 8 mm, steel spheres 1.5 mm,
   one corner replaced by a 3.0 mm sphere, mid-plane of a 88 x 88 x 4 mm PMMA
   plate.  Clutter in round(n/3) frames: lead boxes 1 mm thick lying on the
   plate (z = 2..3 mm): a ruler of 13 ticks (0.6 mm wide, 3 or 5 mm long, 5 mm
   apart) 6-8 mm outside one side of the bead grid and/or letters "L", "R"
   (strokes 1.2 mm wide, 8 mm tall) 7-10 mm outside another side.  Symmetry: the 180-deg turn about the in-plane diagonal through
   the big sphere maps the plate onto itself (truth ``symmetry``).
   ``markers.diameter = 1.5``.
3. ``mirror_helix`` -- flat panel 1024 x 1024, pitch 0.25, ``values:
   attenuation`` float32 ``-ln(counts/N0)``, N0 U(8000, 20000), electronic
   U(5, 15) quanta, blur U(0.6, 1.0); no distortion; sdd U(1000, 1200), sod
   U(650, 800); principal point = centre + U(-20, 20) px.  Phantom: 24 steel
   beads of 2 mm on a right-handed helix ``(40 cos th, 40 sin th, -60 +
   120 th / 3pi)``, th in [0, 3pi] (1.5 turns), at jittered parameters (+-0.25
   of the spacing, which also breaks the helix's 2-fold symmetry), in a PMMA
   cylinder radius 50, height 140.  Every image is MIRRORED left-right before
   writing (column c -> cols-1-c); scan.yaml says nothing.  Truth centres and
   held-out pixels are in the written (flipped) image; poses, sdd and
   ``principal_point`` are the true unflipped ones (``principal_point_written``
   = flipped).  ``expect = {no_ok_frames: true, ...}``; truth also gives per
   frame the RMS of the best PROPER-pose fit to the mirrored centres with the
   true (flipped) intrinsics (``mirror_best_proper_rms_px``): under
   orthographic projection a mirror equals a 180-deg turn, only perspective
   exposes it.
4. ``dense_ball_ii`` -- intensifier 800 x 800, square pitch U(0.27, 0.30),
   ``values: raw`` uint8 written through a LOG display LUT
   ``W = round(255 clip(ln(I/Imin) / ln(Imax/Imin), 0, 1))`` applied to the
   linear camera signal I (projections, flat and dark alike; flat and dark are
   2-page stacks); Imax = 1.3 x flat centre level, Imin = U(0.01, 0.03) x flat
   centre level, camera dark 0.004 x level (-> 0 after the LUT), electronic
   0.002 x level.  So (raw - dark)/(flat - dark) is ``ln(I/Imin)/ln(I0/Imin)``,
   monotone in, but not equal to, the transmission.  sdd U(950, 1100), sod
   U(600, 750); principal point = centre + U(-20, 20) px.  PINCUSHION:
   ``q = C_f + (p - C_f)(1 + k1 r^2 + k2 r^4)``, r = |p - C_f| (ideal), total
   D U(10, 20) px at r = field radius, fraction U(0.3, 0.5) of it from k2;
   ``C_f = pp + c0 + s (g_x, g_y)``, |c0| U(10, 25) px, s U(3, 8) px, ``g =
   R_f gdown`` the lab image of a fixed "down" direction (sag).  Circular
   field radius U(0.44, 0.47)*800, centre image centre + U(-10, 10), edge w
   U(6, 10); glare g U(0.04, 0.08), sigma U(30, 60); vignetting v U(0.15,
   0.30); N0 U(1000, 2500); blur U(0.8, 1.2).  Phantom: PMMA cylinder radius
   35, height 70, 36 steel beads (12 of 2.5 mm, 24 of 1.5 mm, fixed random
   pattern) inside r <= 30, |z| <= 30, placed in clumps (each new bead after
   the first 10 sits at surface gap U(0.3, 2.5) mm from a random earlier
   bead; all surface gaps >= 0.3 mm) so shadows touch and overlap.  Two
   steel wires (0.3 mm) per frame, new each frame: infinite lines through
   ``t + U(-25, 25)^3`` mm, direction ``(cos a, sin a, U(-0.2, 0.2))``
   normalised, a in [0, 180) deg.
   ``markers.diameter = 1.5``.  Nominal magnification is 20 % too high:
   ``sdd_nom = sdd (1 + e)``, ``sod_nom = sod (1 + e) / 1.2``, e U(-0.01, 0.01).
5. ``plain_grid_fp`` -- control: flat panel 1024 x 1024, square pitch 0.2 mm,
   detector exactly perpendicular (u = x, v = y), no distortion; ``values:
   transmission`` float32 ``(Poisson(N0 T) + N(0, se))/N0``, N0 U(10000,
   30000), se U(3, 10); sdd U(1000, 1200), sod U(600, 800), principal point =
   centre + U(-15, 15) px; blur U(0.6, 0.9).  Phantom: 7 x 7 grid of 2.0 mm
   steel spheres at 10 mm pitch, one missing (position not on a mid-line or
   diagonal: no symmetry), mid-plane of an 80 x 80 x 5 mm PMMA plate.
   ``expect = {no_distortion: true}``.

Nominal values (scan.yaml) except case 4: sod, sdd = truth x (1 + U(-0.015,
0.015)) independently.  No nominal principal point is given (default: image
centre).  Frames per scan: U{18..26}; ``time`` = cumulative U(0.8, 2.5) s.
"""
from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import tifffile
import yaml
from scipy import ndimage, optimize

CASES = {
    "tilt_fp": "flat panel, raw 16-bit + 4-page flat/dark, detector tilted 2-4 deg, "
               "rectangular pixels, heel/scatter/beam hardening, 3-D phantom 18x2mm + 1x4mm",
    "barrel_ii": "image intensifier 12-bit raw, barrel + per-frame rotation + smooth residual, "
                 "elliptical soft field, glare, vignetting, 9x9 grid with 3mm corner, lead clutter",
    "mirror_helix": "flat panel attenuation, left-right mirrored images, chiral 24-bead helix: "
                    "no rigid pose fits (expect no ok frames)",
    "dense_ball_ii": "intensifier 8-bit log display raw, pincushion with sagging centre, circular "
                     "field, 36 clumped beads of 1.5/2.5 mm, two wires, nominal magnification +20%",
    "plain_grid_fp": "control: flat panel transmission, no distortion, perpendicular detector, "
                     "7x7 grid of 2mm with one missing",
}

MU_STEEL = 0.45
MU_PMMA = 0.02
MU_LEAD = 5.0
SUB = 8          # sub-samples per pixel axis near spheres
SUB_DETAIL = 4   # near clutter / body edges


# --------------------------------------------------------------------------- helpers
def _rot(axis, ang):
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _rand_unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _offsets(n):
    return (np.arange(n) + 0.5) / n - 0.5


def _lowpass(img, sigma):
    """Broad Gaussian low-pass (sigma in px) via down-sampling; normalised."""
    f = max(1, int(sigma // 8))
    h, w = img.shape
    small = cv2.resize(img.astype(np.float32), (max(1, w // f), max(1, h // f)),
                       interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma / f, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float64)


def _robust_sigma(x):
    x = np.asarray(x, float).ravel()
    if x.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if math.isfinite(v) else None
    return o


def _write_json_atomic(path, obj):
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=str(path.parent))
    with os.fdopen(fd, "w") as fh:
        json.dump(_jsonable(obj), fh, indent=1, sort_keys=True)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- geometry
class _Geom:
    def __init__(self, S, O, u, v, pu, pv, rows, cols):
        self.S = np.asarray(S, float)
        self.O = np.asarray(O, float)
        self.u = _unit(u)
        self.v = _unit(v)
        self.pu, self.pv = float(pu), float(pv)
        self.rows, self.cols = int(rows), int(cols)
        self.n = _unit(np.cross(self.u, self.v))

    def dirs(self, c, r):
        """Unit ray directions from S through ideal pixel coords (flat arrays)."""
        X = (self.O[None, :] + (c * self.pu)[:, None] * self.u[None, :]
             + (r * self.pv)[:, None] * self.v[None, :])
        d = X - self.S[None, :]
        d /= np.linalg.norm(d, axis=1)[:, None]
        return d

    def project(self, P):
        P = np.atleast_2d(P)
        d = P - self.S[None, :]
        s = ((self.O - self.S) @ self.n) / (d @ self.n)
        X = self.S[None, :] + s[:, None] * d
        rel = X - self.O[None, :]
        return rel @ self.u / self.pu, rel @ self.v / self.pv

    @property
    def sdd(self):
        return float((self.O - self.S) @ self.n)

    @property
    def principal_point(self):
        F = self.S + self.sdd * self.n
        rel = F - self.O
        return [float(rel @ self.u / self.pu), float(rel @ self.v / self.pv)]

    def as_dict(self):
        return {"source": self.S, "detector": {"origin": self.O, "u": self.u, "v": self.v,
                                               "pixel_pitch": [self.pu, self.pv],
                                               "shape": [self.rows, self.cols]}}


def _make_geom(sod, sdd_axis, rows, cols, pu, pv, det_offset_mm=(0.0, 0.0),
               tilt_deg=0.0, tilt_axis_deg=0.0):
    S = np.array([0.0, 0.0, -sod])
    Dc = np.array([det_offset_mm[0], det_offset_mm[1], sdd_axis - sod])
    Rt = _rot([math.cos(math.radians(tilt_axis_deg)), math.sin(math.radians(tilt_axis_deg)), 0],
              math.radians(tilt_deg))
    u = Rt @ np.array([1.0, 0, 0])
    v = Rt @ np.array([0, 1.0, 0])
    O = Dc - (cols - 1) / 2 * pu * u - (rows - 1) / 2 * pv * v
    return _Geom(S, O, u, v, pu, pv, rows, cols)


# --------------------------------------------------------------------------- distortions
class _NoDist:
    kind = "none"

    def fwd(self, c, r):
        return np.asarray(c, float), np.asarray(r, float)

    def inv(self, c, r, refine=False):
        return np.asarray(c, float), np.asarray(r, float)

    def params(self):
        return {}


class _Pincushion:
    kind = "radial_pincushion_k1_k2_centre_sag"

    def __init__(self, centre, k1, k2):
        self.cx, self.cy = map(float, centre)
        self.k1, self.k2 = float(k1), float(k2)

    def fwd(self, c, r):
        x = np.asarray(c, float) - self.cx
        y = np.asarray(r, float) - self.cy
        rr = x * x + y * y
        s = 1 + self.k1 * rr + self.k2 * rr * rr
        return self.cx + x * s, self.cy + y * s

    def inv(self, c, r, refine=False):
        x = np.asarray(c, float) - self.cx
        y = np.asarray(r, float) - self.cy
        rm = np.hypot(x, y)
        rho = rm.copy()
        act = np.arange(rm.size)
        rho_f = rho.ravel()
        rm_f = rm.ravel()
        for _ in range(60):  # Newton from the right on a convex increasing function
            r_ = rho_f[act]
            r2 = r_ * r_
            f = r_ * (1 + r2 * (self.k1 + self.k2 * r2)) - rm_f[act]
            fp = 1 + r2 * (3 * self.k1 + 5 * self.k2 * r2)
            step = f / fp
            rho_f[act] = r_ - step
            act = act[np.abs(step) > 1e-9]
            if act.size == 0:
                break
        rho = rho_f.reshape(rm.shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            sc = np.where(rm > 0, rho / np.where(rm > 0, rm, 1), 1.0)
        return self.cx + x * sc, self.cy + y * sc

    def params(self):
        return {"model": "q = C + (p-C)(1 + k1 r^2 + k2 r^4), r = |p-C| ideal px",
                "centre": [self.cx, self.cy], "k1": self.k1, "k2": self.k2}


class _BarrelRotResid:
    kind = "radial_barrel_plus_rotation_plus_fourier_residual"

    def __init__(self, centre, k, theta, modes, W, H):
        self.cx, self.cy = map(float, centre)
        self.k = float(k)
        self.theta = float(theta)
        self.modes = modes  # list of (fx, fy, phase, ac, ar)
        self.W, self.H = float(W), float(H)
        self._grid = None

    def resid(self, c, r):
        fc = np.zeros_like(c, dtype=float)
        fr = np.zeros_like(c, dtype=float)
        for fx, fy, ph, ac, ar in self.modes:
            cs = np.cos(2 * np.pi * (fx * c / self.W + fy * r / self.H) + ph)
            fc += ac * cs
            fr += ar * cs
        return fc, fr

    def fwd(self, c, r):
        c = np.asarray(c, float)
        r = np.asarray(r, float)
        x = c - self.cx
        y = r - self.cy
        s = 1 - self.k * (x * x + y * y)
        xb, yb = x * s, y * s
        ct, st = math.cos(self.theta), math.sin(self.theta)
        fc, fr = self.resid(c, r)
        return self.cx + ct * xb - st * yb + fc, self.cy + st * xb + ct * yb + fr

    def inv_exact(self, cm, rm):
        pc, pr = np.array(cm, float), np.array(rm, float)
        for _ in range(80):
            qc, qr = self.fwd(pc, pr)
            ec, er = cm - qc, rm - qr
            pc += ec
            pr += er
            if max(np.max(np.abs(ec)), np.max(np.abs(er))) < 1e-10:
                break
        return pc, pr

    def build_grid(self, rows, cols, h=4.0):
        self._h = h
        self._c0 = -12.0
        self._r0 = -12.0
        gc = self._c0 + h * np.arange(int((cols + 24) / h) + 2)
        gr = self._r0 + h * np.arange(int((rows + 24) / h) + 2)
        C, R = np.meshgrid(gc, gr)
        self._grid = self.inv_exact(C, R)

    def inv(self, cm, rm, refine=False):
        """Bilinear interpolation of the exact inverse on a 4-px grid (error
        < 2e-3 px); ``refine`` adds one fixed-point step (error x ~0.2)."""
        cm = np.asarray(cm, float)
        rm = np.asarray(rm, float)
        gx = (cm - self._c0) / self._h
        gy = (rm - self._r0) / self._h
        ny, nx = self._grid[0].shape
        ix = np.clip(np.floor(gx).astype(np.int64), 0, nx - 2)
        iy = np.clip(np.floor(gy).astype(np.int64), 0, ny - 2)
        fx = gx - ix
        fy = gy - iy
        res = []
        for G in self._grid:
            res.append((1 - fy) * ((1 - fx) * G[iy, ix] + fx * G[iy, ix + 1])
                       + fy * ((1 - fx) * G[iy + 1, ix] + fx * G[iy + 1, ix + 1]))
        pc, pr = res
        if refine:
            qc, qr = self.fwd(pc, pr)
            pc = pc + (cm - qc)
            pr = pr + (rm - qr)
        return pc, pr

    def params(self):
        return {"model": "q = C + Rot(theta)[(p-C)(1 - k|p-C|^2)] + sum_m (ac_m, ar_m) "
                         "cos(2pi(fx c/W + fy r/H) + phase), p ideal (c, r) px",
                "centre": [self.cx, self.cy], "k": self.k, "theta_deg": math.degrees(self.theta),
                "W": self.W, "H": self.H,
                "modes": [{"fx": m[0], "fy": m[1], "phase": m[2], "ac": m[3], "ar": m[4]}
                          for m in self.modes]}


# --------------------------------------------------------------------------- field
class _Field:
    def __init__(self, centre, a, b, phi_deg, w):
        self.cx, self.cy = map(float, centre)
        self.a, self.b = float(a), float(b)
        self.phi = math.radians(phi_deg)
        self.w = float(w)

    def rho(self, c, r):
        x = np.asarray(c, float) - self.cx
        y = np.asarray(r, float) - self.cy
        cp, sp = math.cos(self.phi), math.sin(self.phi)
        xr = cp * x + sp * y
        yr = -sp * x + cp * y
        return np.sqrt((xr / self.a) ** 2 + (yr / self.b) ** 2)

    def inside(self, c, r):
        return self.rho(c, r) <= 1.0

    def taper(self, c, r):
        e = (self.rho(c, r) - 1.0) * min(self.a, self.b)
        t = np.clip(e / self.w, 0, 1)
        return np.where(e <= 0, 1.0, 0.5 * (1 + np.cos(np.pi * t)))

    def radius_norm(self, c, r):
        x = np.asarray(c, float) - self.cx
        y = np.asarray(r, float) - self.cy
        return np.hypot(x, y) / max(self.a, self.b)

    def params(self):
        return {"centre": [self.cx, self.cy], "semi_axes_px": [self.a, self.b],
                "angle_deg": math.degrees(self.phi), "soft_edge_px": self.w,
                "inside": "rho <= 1, rho = |Rot(-angle)(q - centre) / (a, b)|"}


class _NoField:
    def inside(self, c, r):
        return np.ones(np.shape(c), bool)

    def taper(self, c, r):
        return np.ones(np.shape(c))

    def rho(self, c, r):
        return np.zeros(np.shape(c))


# --------------------------------------------------------------------------- bodies
def _slab_len(o, d, half):
    """Path length of lines o + s d (o (3,), d (N,3)) through box |x_i| <= half_i."""
    tmin = np.full(d.shape[0], -np.inf)
    tmax = np.full(d.shape[0], np.inf)
    for i in range(3):
        di = d[:, i]
        di = np.where(np.abs(di) < 1e-15, 1e-15, di)
        t1 = (-half[i] - o[i]) / di
        t2 = (half[i] - o[i]) / di
        tmin = np.maximum(tmin, np.minimum(t1, t2))
        tmax = np.minimum(tmax, np.maximum(t1, t2))
    return np.clip(tmax - tmin, 0, None)


def _cyl_len(o, d, radius, half_h):
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (o[0] * d[:, 0] + o[1] * d[:, 1])
    c = o[0] ** 2 + o[1] ** 2 - radius ** 2
    disc = b * b - 4 * a * c
    ok = (disc > 0) & (a > 1e-15)
    sq = np.sqrt(np.where(ok, disc, 0))
    aa = np.where(ok, a, 1)
    s1 = np.where(ok, (-b - sq) / (2 * aa), 0)
    s2 = np.where(ok, (-b + sq) / (2 * aa), 0)
    dz = np.where(np.abs(d[:, 2]) < 1e-15, 1e-15, d[:, 2])
    z1 = (-half_h - o[2]) / dz
    z2 = (half_h - o[2]) / dz
    lo = np.maximum(s1, np.minimum(z1, z2))
    hi = np.minimum(s2, np.maximum(z1, z2))
    return np.where(ok, np.clip(hi - lo, 0, None), 0.0)


class _Body:
    """PMMA body in the phantom frame: ('cyl', radius, half_h) or ('box', hx, hy, hz)."""

    def __init__(self, kind, *dims):
        self.kind = kind
        self.dims = dims

    def path(self, o, d):
        if self.kind == "cyl":
            return _cyl_len(o, d, self.dims[0], self.dims[1])
        return _slab_len(o, d, self.dims)

    def as_dict(self):
        if self.kind == "cyl":
            return {"kind": "cylinder", "radius": self.dims[0], "height": 2 * self.dims[1],
                    "axis": "phantom z", "material": "PMMA"}
        return {"kind": "plate", "size": [2 * x for x in self.dims], "material": "PMMA"}


def _hard(mu, L, L0):
    if L0 is None:
        return mu * L
    return mu * L / (1 + L / L0)


# --------------------------------------------------------------------------- scene / frame
class _Scene:
    def __init__(self, cfg):
        self.cfg = cfg
        self.g = cfg["geom"]
        self.beads = np.asarray(cfg["beads"], float)
        self.diam = np.asarray(cfg["diam"], float)
        self.body = cfg["body"]
        self.field = cfg.get("field") or _NoField()
        self.L0s = cfg.get("L0_steel")
        self.L0p = cfg.get("L0_pmma")

    def paths(self, f, dirs):
        """Body (PMMA, beads not removed), wire (steel) and lead path lengths."""
        g = self.g
        R, t = self.cfg["poses"][f]
        o = R.T @ (g.S - t)
        dp = dirs @ R
        Lb = self.body.path(o, dp)
        Lw = np.zeros(dirs.shape[0])
        for (W0, wd, wr) in self.cfg["wires"][f]:
            m = np.cross(dirs, wd[None, :])
            sm = np.linalg.norm(m, axis=1)
            D = np.abs(m @ (W0 - g.S)) / np.maximum(sm, 1e-12)
            Lw += 2 * np.sqrt(np.clip(wr * wr - D * D, 0, None)) / np.maximum(sm, 1e-6)
        Lpb = np.zeros(dirs.shape[0])
        for (cb, Qb, hb) in self.cfg["lead"][f]:
            Lpb += _slab_len(Qb @ (o - cb), dp @ Qb.T, hb)
        return Lb, Lw, Lpb

    def combine(self, Ls, Lb, Lw, Lpb):
        """Attenuation from steel-bead path Ls and the other paths (per material
        beam hardening where configured; beads displace PMMA)."""
        Lp = np.clip(Lb - Ls, 0, None)
        return (_hard(MU_STEEL, Ls + Lw, self.L0s) + _hard(MU_PMMA, Lp, self.L0p)
                + _hard(MU_LEAD, Lpb, None))

    def atten(self, f, dirs):
        Lb, Lw, Lpb = self.paths(f, dirs)
        return self.combine(0.0, Lb, Lw, Lpb)

    def chord(self, j, dirs, centres_lab):
        w = centres_lab[j] - self.g.S
        b = dirs @ w
        q = w @ w - b * b
        rho = self.diam[j] / 2
        return 2 * np.sqrt(np.clip(rho * rho - q, 0, None))

    def sample_dirs(self, f, cm, rm, refine=False):
        dist = self.cfg["dist"][f]
        pc, pr = dist.inv(cm, rm, refine=refine)
        return self.g.dirs(pc.ravel(), pr.ravel())

    def render(self, f):
        g = self.g
        rows, cols = g.rows, g.cols
        R, t = self.cfg["poses"][f]
        dist = self.cfg["dist"][f]
        C_lab = self.beads @ R.T + t[None, :]
        # 1) background (body, lead, wires) on a 2-px coarse grid, bilinear up
        cs_ = np.arange(0, cols + 1, 2, dtype=float)
        rs_ = np.arange(0, rows + 1, 2, dtype=float)
        Cm, Rm = np.meshgrid(cs_, rs_)
        d = self.sample_dirs(f, Cm.ravel(), Rm.ravel())
        Ac = self.atten(f, d).reshape(Cm.shape)
        near = np.zeros(Cm.shape, bool)
        for (W0, wd, wr) in self.cfg["wires"][f]:
            m = np.cross(d, wd[None, :])
            D = np.abs(m @ (W0 - g.S)) / np.linalg.norm(m, axis=1)
            foot = max(g.pu, g.pv) * np.linalg.norm(W0 - g.S) / g.sdd
            near |= (D < wr + 2.5 * foot).reshape(Cm.shape)
        del d
        jc = np.arange(cols) // 2
        fc_ = (np.arange(cols) % 2) / 2.0
        jr = np.arange(rows) // 2
        fr_ = (np.arange(rows) % 2) / 2.0
        Ar = (1 - fr_)[:, None] * Ac[jr] + fr_[:, None] * Ac[jr + 1]
        Abg = (1 - fc_)[None, :] * Ar[:, jc] + fc_[None, :] * Ar[:, jc + 1]
        T = np.exp(-Abg)
        # 2) detail pixels (edges of body/lead, wires) on SUB_DETAIL^2 samples
        # (bilinear interpolation is exact for linear variation: flag curvature)
        cm_ = near.copy()
        dx = np.abs(np.diff(Ac, 2, axis=1)) > 0.004
        dy = np.abs(np.diff(Ac, 2, axis=0)) > 0.004
        for k in range(3):
            cm_[:, k:k + dx.shape[1]] |= dx
            cm_[k:k + dy.shape[0], :] |= dy
        cmr = cm_[jr] | cm_[jr + 1]
        gx = cmr[:, jc] | cmr[:, jc + 1]
        gx = ndimage.binary_dilation(gx, iterations=1)
        rr_, cc_ = np.nonzero(gx)
        off = _offsets(SUB_DETAIL)
        n2 = SUB_DETAIL * SUB_DETAIL
        oc = np.tile(off, SUB_DETAIL)
        orr = np.repeat(off, SUB_DETAIL)
        for k0 in range(0, rr_.size, 40000):
            pr = rr_[k0:k0 + 40000]
            pc = cc_[k0:k0 + 40000]
            sc = (pc[:, None] + oc[None, :]).ravel()
            sr = (pr[:, None] + orr[None, :]).ravel()
            d = self.sample_dirs(f, sc, sr)
            A = self.atten(f, d)
            T[pr, pc] = np.exp(-A).reshape(-1, n2).mean(1)
        # 3) spheres: silhouettes -> boxes
        nb = len(self.beads)
        ang = np.linspace(0, 2 * np.pi, 96, endpoint=False)
        boxes = np.zeros((nb, 4), int)
        trunc = np.zeros(nb, bool)
        valid = np.zeros(nb, bool)
        for j in range(nb):
            w = C_lab[j] - g.S
            D = np.linalg.norm(w)
            rho = self.diam[j] / 2
            e1 = _unit(np.cross(w, [0.3, 0.5, 0.8]))
            e2 = _unit(np.cross(w, e1))
            ctr = g.S + w * (1 - rho * rho / D / D)
            a = rho * math.sqrt(1 - rho * rho / D / D)
            P = ctr[None, :] + a * (np.cos(ang)[:, None] * e1[None, :] + np.sin(ang)[:, None] * e2[None, :])
            pc, pr = g.project(P)
            qc, qr = dist.fwd(pc, pr)
            out = ((qc < -0.5) | (qc > cols - 0.5) | (qr < -0.5) | (qr > rows - 0.5)
                   | ~self.field.inside(qc, qr))
            trunc[j] = bool(out.any())
            b = [int(math.floor(qc.min())) - 2, int(math.ceil(qc.max())) + 2,
                 int(math.floor(qr.min())) - 2, int(math.ceil(qr.max())) + 2]
            boxes[j] = b
            valid[j] = not (b[1] < 0 or b[0] > cols - 1 or b[3] < 0 or b[2] > rows - 1)
        cl = boxes.copy()
        cl[:, 0] = np.clip(cl[:, 0], 0, cols - 1)
        cl[:, 1] = np.clip(cl[:, 1], 0, cols - 1)
        cl[:, 2] = np.clip(cl[:, 2], 0, rows - 1)
        cl[:, 3] = np.clip(cl[:, 3], 0, rows - 1)
        # union of the sphere boxes: every pixel there on SUB x SUB samples, once
        off = _offsets(SUB)
        ns = SUB * SUB
        oc = np.tile(off, SUB)
        orr = np.repeat(off, SUB)
        vidx = np.nonzero(valid)[0]
        umask = np.zeros((rows, cols), bool)
        for j in vidx:
            c0, c1, r0, r1 = cl[j]
            umask[r0:r1 + 1, c0:c1 + 1] = True
        pr_, pc_ = np.nonzero(umask)
        npx = pr_.size
        pix_index = np.full((rows, cols), -1, np.int64)
        pix_index[pr_, pc_] = np.arange(npx)
        Sc = (pc_[:, None] + oc[None, :]).ravel()
        Sr = (pr_[:, None] + orr[None, :]).ravel()
        ntot = Sc.size
        dirs = np.empty((ntot, 3))
        Lb = np.empty(ntot)
        Lw = np.empty(ntot)
        Lpb = np.empty(ntot)
        chunk = 400000
        for k0 in range(0, ntot, chunk):
            sl = slice(k0, min(ntot, k0 + chunk))
            dirs[sl] = self.sample_dirs(f, Sc[sl], Sr[sl], refine=True)
            Lb[sl], Lw[sl], Lpb[sl] = self.paths(f, dirs[sl])
        Ls = np.zeros(ntot)
        own = {}
        for j in vidx:
            c0, c1, r0, r1 = cl[j]
            ks = pix_index[r0:r1 + 1, c0:c1 + 1].ravel()
            sidx = (ks[:, None] * ns + np.arange(ns)[None, :]).ravel()
            ch = self.chord(j, dirs[sidx], C_lab)
            Ls[sidx] += ch
            own[j] = (sidx, ch, (r1 - r0 + 1, c1 - c0 + 1))
        A = self.combine(Ls, Lb, Lw, Lpb)
        T[pr_, pc_] = np.exp(-A).reshape(npx, ns).mean(1)
        clutter = (Lw > 0) | (Lpb > 0)
        del dirs, Lb, A
        info = {}
        count = np.zeros((rows, cols), np.int16)
        masks = {}
        for j in vidx:
            sidx, ch, (nr, nc) = own[j]
            c0, c1, r0, r1 = cl[j]
            Cs = Sc[sidx]
            Rs = Sr[sidx]
            inside = self.field.inside(Cs, Rs)
            wgt = ch * inside
            if wgt.sum() <= 0:
                continue
            pixmask = (ch > 0).reshape(nr, nc, ns).any(2)
            n_vis = int(np.count_nonzero(wgt > 0))
            area = n_vis / ns
            info[j] = {"id": int(j), "x": float((wgt * Cs).sum() / wgt.sum()),
                       "y": float((wgt * Rs).sum() / wgt.sum()),
                       "diameter_px": float(2 * math.sqrt(area / math.pi)),
                       "truncated": bool(trunc[j]), "overlap": False,
                       "diameter_mm": float(self.diam[j]),
                       "clutter": bool(np.any(clutter[sidx] & (ch > 0))),
                       "clutter_near": bool(np.any(clutter[sidx]))}
            masks[j] = (r0, c0, pixmask)
            count[r0:r1 + 1, c0:c1 + 1] += pixmask
        for j, (r0, c0, pm) in masks.items():
            sub = count[r0:r0 + pm.shape[0], c0:c0 + pm.shape[1]]
            info[j]["overlap"] = bool(np.any(sub[pm] >= 2))
        return T, [info[j] for j in sorted(info)]


# --------------------------------------------------------------------------- poses
def _push(rng, half, r_cloud):
    return rng.choice([-1, 1]) * max(0.0, half - rng.uniform(0.1, 0.5) * r_cloud)


def _poses_3d(rng, n, half_obj, r_cloud):
    poses = []
    push = set(rng.choice(n, size=3, replace=False).tolist())
    for f in range(n):
        a = rng.uniform(0, 2 * np.pi)
        b = math.radians(rng.uniform(-50, 50))
        gm = rng.uniform(0, 2 * np.pi)
        R = _rot([0, 0, 1], gm) @ _rot([1, 0, 0], b) @ _rot([1, 0, 0], -np.pi / 2) @ _rot([0, 0, 1], a)
        t = np.array([rng.normal(0, 5), rng.normal(0, 5), rng.uniform(-20, 20)])
        if f in push:
            ax = rng.integers(2)
            t[ax] += _push(rng, half_obj[ax], r_cloud)
        poses.append((R, t))
    return poses


def _poses_planar(rng, n, half_obj, r_cloud):
    poses = []
    idx = rng.permutation(n)
    steep = set(idx[:rng.integers(2, 4)].tolist())
    push = set(idx[-3:].tolist())
    for f in range(n):
        gm = rng.uniform(0, 2 * np.pi)
        if f in steep:
            p = rng.choice([0.0, 90.0]) + rng.uniform(-5, 5)
            b = rng.uniform(80, 83)
        else:
            p = rng.uniform(0, 180)
            b = rng.uniform(5, 60)
        ax = [math.cos(math.radians(p)), math.sin(math.radians(p)), 0]
        R = _rot([0, 0, 1], gm) @ _rot(ax, math.radians(b))
        if rng.random() < 0.25:
            R = R @ _rot([1, 0, 0], np.pi)
        t = np.array([rng.normal(0, 5), rng.normal(0, 5), rng.uniform(-20, 20)])
        if f in push:
            k = rng.integers(2)
            t[k] += _push(rng, half_obj[k], r_cloud)
        poses.append((R, t))
    return poses


def _planar_symmetries(beads, diam):
    """Proper rotations of the plate (in-plane quarter turns, in-plane flips) mapping
    the bead set (with sizes) onto itself.  Beads lie in z = 0, plate centred."""
    ops = []
    for k in range(4):
        ops.append(_rot([0, 0, 1], k * np.pi / 2))
    for a in (0, 45, 90, 135):
        ops.append(_rot([math.cos(math.radians(a)), math.sin(math.radians(a)), 0], np.pi))
    perms, rots = [], []
    for Rm in ops:
        q = beads @ Rm.T
        dd = np.linalg.norm(q[:, None, :] - beads[None, :, :], axis=2)
        j = dd.argmin(1)
        if np.all(dd[np.arange(len(beads)), j] < 1e-6) and len(set(j.tolist())) == len(beads) \
                and np.allclose(diam[j], diam):
            perms.append(j.tolist())
            rots.append(np.round(Rm, 12))
    return perms, rots


def _heldout_points(rng, beads, diam, kind, dims, n=30):
    pts = []
    tries = 0
    while len(pts) < n and tries < 100000:
        tries += 1
        if kind == "cyl":
            rad, hh = dims
            rr = rad * math.sqrt(rng.random())
            ph = rng.uniform(0, 2 * np.pi)
            p = np.array([rr * math.cos(ph), rr * math.sin(ph), rng.uniform(-hh, hh)])
        else:
            hx, hy, hz = dims
            p = np.array([rng.uniform(-hx, hx), rng.uniform(-hy, hy), rng.uniform(-hz, hz)])
        if np.all(np.linalg.norm(beads - p[None, :], axis=1) - diam / 2 >= 4.0):
            pts.append(p)
    return np.array(pts)


# --------------------------------------------------------------------------- case set-ups
def _common_wires_lead(n):
    return [[] for _ in range(n)], [[] for _ in range(n)]


def _setup_tilt_fp(rng):
    rows, cols, pu, pv = 960, 1240, 0.148, 0.152
    sod = rng.uniform(680, 800)
    sdd_axis = rng.uniform(960, 1100)
    off = rng.uniform(-3, 3, 2)
    tilt = rng.uniform(2, 4) * rng.choice([-1, 1])
    for _ in range(1000):
        tax = rng.uniform(0, 180)
        geom = _make_geom(sod, sdd_axis, rows, cols, pu, pv, off, tilt, tax)
        pp = geom.principal_point
        if abs(pp[0] - (cols - 1) / 2) < 0.85 * cols / 2 and abs(pp[1] - (rows - 1) / 2) < 0.85 * rows / 2:
            break
    n = int(rng.integers(18, 27))
    beads = []
    while len(beads) < 19:
        rr = 36 * math.sqrt(rng.random())
        ph = rng.uniform(0, 2 * np.pi)
        p = np.array([rr * math.cos(ph), rr * math.sin(ph), rng.uniform(-36, 36)])
        if all(np.linalg.norm(p - q) >= 8 for q in beads):
            beads.append(p)
    beads = np.array(beads)
    diam = np.full(19, 2.0)
    big = int(rng.integers(19))
    diam[big] = 4.0
    mag = geom.sdd / sod
    half_obj = (cols * pu / 2 / mag, rows * pv / 2 / mag)
    poses = _poses_3d(rng, n, half_obj, float(np.linalg.norm(beads, axis=1).max()))
    wires, lead = _common_wires_lead(n)
    blur = rng.uniform(0.6, 0.9)
    heel_dir = rng.uniform(0, 2 * np.pi)
    chain = {"kind": "fp_raw16", "N0": rng.uniform(6000, 12000), "gain": rng.uniform(2, 3),
             "dark": rng.uniform(800, 1200), "sigma_e": rng.uniform(3, 6),
             "heel": rng.uniform(0.10, 0.15), "heel_dir_deg": math.degrees(heel_dir),
             "scatter": rng.uniform(0.05, 0.10), "scatter_sigma_px": rng.uniform(60, 120),
             "flat_pages": 4, "dark_pages": 4}
    return dict(geom=geom, beads=beads, diam=diam, body=_Body("cyl", 45.0, 45.0), poses=poses,
                dist=[_NoDist()] * n, field=None, wires=wires, lead=lead, blur=blur, chain=chain,
                L0_steel=rng.uniform(6, 10), L0_pmma=rng.uniform(150, 300), values="raw",
                marker_diameter=2.0, mirror=False, held_kind=("cyl", (45.0, 45.0)),
                extra={"detector_tilt_deg": abs(tilt), "tilt_signed_deg": tilt,
                       "tilt_axis": [math.cos(math.radians(tax)), math.sin(math.radians(tax)), 0.0],
                       "big_bead_id": big},
                expect={})


def _lead_items(rng, half_grid, z_top):
    """Lead ruler ticks and/or letters in the phantom frame, outside the bead grid."""
    items = []
    what = rng.choice(["ruler", "letters", "both"])
    sides = rng.permutation(4)
    th = 1.0
    zc = z_top + th / 2
    def side_frame(s, dist_out):
        # returns (origin of the strip centre line, along axis, outward axis)
        if s == 0:
            return np.array([0, half_grid + dist_out, zc]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
        if s == 1:
            return np.array([0, -half_grid - dist_out, zc]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0])
        if s == 2:
            return np.array([half_grid + dist_out, 0, zc]), np.array([0, 1.0, 0]), np.array([1.0, 0, 0])
        return np.array([-half_grid - dist_out, 0, zc]), np.array([0, 1.0, 0]), np.array([-1.0, 0, 0])

    def box(centre, along, outw, len_along, len_out):
        Q = np.vstack([along, outw, np.cross(along, outw)])
        return (centre, Q, np.array([len_along / 2, len_out / 2, th / 2]))

    if what in ("ruler", "both"):
        o, al, ou = side_frame(sides[0], rng.uniform(6, 8))
        shift = rng.uniform(-8, 8)
        for k in range(-6, 7):
            L = 5.0 if k % 2 == 0 else 3.0
            items.append(box(o + al * (shift + 5.0 * k) + ou * (L / 2), al, ou, 0.6, L))
    if what in ("letters", "both"):
        o, al, ou = side_frame(sides[1], rng.uniform(7, 10))
        x0 = rng.uniform(-20, 10)
        # "L": vertical stroke + foot
        base = o + al * x0
        items.append(box(base + ou * 4.0, al, ou, 1.2, 8.0))
        items.append(box(base + al * 2.4 + ou * 0.6, al, ou, 4.8, 1.2))
        # "R": stem, top bar, middle bar, bowl side, leg (approximated by strokes)
        b2 = o + al * (x0 + 10)
        items.append(box(b2 + ou * 4.0, al, ou, 1.2, 8.0))
        items.append(box(b2 + al * 2.0 + ou * 7.4, al, ou, 4.0, 1.2))
        items.append(box(b2 + al * 2.0 + ou * 3.8, al, ou, 4.0, 1.2))
        items.append(box(b2 + al * 3.8 + ou * 5.6, al, ou, 1.2, 3.6))
        legd = _unit(al * 0.45 - ou * 1.0)
        nrm = np.cross(al, ou)
        items.append((b2 + al * 3.0 + ou * 1.9,
                      np.vstack([legd, _unit(np.cross(nrm, legd)), nrm]),
                      np.array([2.1, 0.6, th / 2])))
    return items


def _setup_barrel_ii(rng):
    N = 1024
    pitch = rng.uniform(0.22, 0.24)
    sod = rng.uniform(600, 700)
    sdd = rng.uniform(950, 1050)
    ppo = rng.uniform(-25, 25, 2)
    geom = _make_geom(sod, sdd, N, N, pitch, pitch, (-ppo[0] * pitch, -ppo[1] * pitch))
    pp = np.array(geom.principal_point)
    n = int(rng.integers(18, 27))
    field = _Field(((N - 1) / 2 + rng.uniform(-12, 12), (N - 1) / 2 + rng.uniform(-12, 12)),
                   rng.uniform(0.45, 0.48) * N, rng.uniform(0.39, 0.43) * N, rng.uniform(-8, 8),
                   rng.uniform(6, 12))
    # grid phantom
    ii, jj = np.meshgrid(np.arange(9), np.arange(9), indexing="ij")
    beads = np.column_stack([(ii.ravel() - 4) * 8.0, (jj.ravel() - 4) * 8.0, np.zeros(81)])
    diam = np.full(81, 1.5)
    corner = int(rng.choice([0, 8, 72, 80]))
    diam[corner] = 3.0
    mag = geom.sdd / sod
    half_obj = (field.a * pitch / mag, field.b * pitch / mag)
    poses = _poses_planar(rng, n, half_obj, float(np.linalg.norm(beads, axis=1).max()))
    # distortion
    dang = rng.uniform(0, 2 * np.pi)
    C = pp + rng.uniform(10, 30) * np.array([math.cos(dang), math.sin(dang)])
    Dk = rng.uniform(8, 15)
    k = Dk / field.a ** 3
    th0, th1 = rng.uniform(0.6, 0.7), rng.uniform(0.25, 0.30)
    sgn = rng.choice([-1, 1])
    bdir = _rand_unit(rng)
    M = int(rng.integers(6, 11))
    modes = []
    for _ in range(M):
        while True:
            fx, fy = rng.integers(-4, 5, 2) / 2.0
            if fx != 0 or fy != 0:
                break
        modes.append([float(fx), float(fy), rng.uniform(0, 2 * np.pi), rng.normal(), rng.normal()])
    tmp = _BarrelRotResid(C, k, 0.0, modes, N, N)
    gc, gr = np.meshgrid(np.linspace(0, N - 1, 129), np.linspace(0, N - 1, 129))
    fc, fr = tmp.resid(gc, gr)
    amp = rng.uniform(0.5, 1.2)
    sc = amp / np.max(np.hypot(fc, fr))
    for m in modes:
        m[3] *= sc
        m[4] *= sc
    dists = []
    thetas = []
    for (R, t) in poses:
        view = R.T @ np.array([0, 0, 1.0])
        th = sgn * (th0 + th1 * float(view @ bdir))
        thetas.append(th)
        d = _BarrelRotResid(C, k, math.radians(th), modes, N, N)
        d.build_grid(N, N)
        dists.append(d)
    wires = [[] for _ in range(n)]
    lead = [[] for _ in range(n)]
    for f in rng.choice(n, size=int(round(n / 3)), replace=False):
        lead[int(f)] = _lead_items(rng, 32.0 + 0.75, 2.0)
    chain = {"kind": "ii_raw12", "N0": rng.uniform(1500, 3000), "flat_level": rng.uniform(3000, 3500),
             "dark": rng.uniform(40, 80), "sigma_e": rng.uniform(1.5, 3.0),
             "glare": rng.uniform(0.05, 0.10), "glare_sigma_px": rng.uniform(40, 80),
             "vignetting": rng.uniform(0.20, 0.35), "flat_exposures": 16, "flat_pages": 1,
             "dark_pages": 1}
    perms, rots = _planar_symmetries(beads, diam)
    return dict(geom=geom, beads=beads, diam=diam, body=_Body("box", 44.0, 44.0, 2.0), poses=poses,
                dist=dists, field=field, wires=wires, lead=lead, blur=rng.uniform(0.9, 1.3),
                chain=chain, L0_steel=None, L0_pmma=None, values="raw", marker_diameter=1.5,
                mirror=False, held_kind=("box", (44.0, 44.0, 30.0)),
                extra={"barrel_edge_px": Dk, "distortion_centre_offset_px": float(np.linalg.norm(C - pp)),
                       "rotation_deg": thetas, "rotation_law": {"th0_deg": th0, "th1_deg": th1,
                                                                 "sign": int(sgn), "b": bdir},
                       "residual_max_px": amp, "big_bead_id": corner,
                       "lead_frames": [f for f in range(n) if lead[f]]},
                symmetry=(perms, rots), expect={})


def _setup_mirror_helix(rng):
    N, pitch = 1024, 0.25
    sod = rng.uniform(650, 800)
    sdd = rng.uniform(1000, 1200)
    ppo = rng.uniform(-20, 20, 2)
    geom = _make_geom(sod, sdd, N, N, pitch, pitch, (-ppo[0] * pitch, -ppo[1] * pitch))
    n = int(rng.integers(18, 27))
    k = np.arange(24) + rng.uniform(-0.25, 0.25, 24)
    th = 3 * np.pi * np.clip(k, 0, 23) / 23
    beads = np.column_stack([40 * np.cos(th), 40 * np.sin(th), -60 + 120 * th / (3 * np.pi)])
    diam = np.full(24, 2.0)
    mag = geom.sdd / sod
    half_obj = (N * pitch / 2 / mag, N * pitch / 2 / mag)
    poses = _poses_3d(rng, n, half_obj, float(np.linalg.norm(beads, axis=1).max()))
    wires, lead = _common_wires_lead(n)
    chain = {"kind": "fp_atten", "N0": rng.uniform(8000, 20000), "sigma_e": rng.uniform(5, 15)}
    return dict(geom=geom, beads=beads, diam=diam, body=_Body("cyl", 50.0, 70.0), poses=poses,
                dist=[_NoDist()] * n, field=None, wires=wires, lead=lead, blur=rng.uniform(0.6, 1.0),
                chain=chain, L0_steel=None, L0_pmma=None, values="attenuation", marker_diameter=2.0,
                mirror=True, held_kind=("cyl", (50.0, 70.0)),
                extra={"helix": {"radius": 40.0, "turns": 1.5, "length": 120.0, "handedness": "right",
                                 "param_rad": th}},
                expect={"no_ok_frames": True, "why": "image mirrored; chiral phantom"})


def _setup_dense_ball_ii(rng):
    N = 800
    pitch = rng.uniform(0.27, 0.30)
    sod = rng.uniform(600, 750)
    sdd = rng.uniform(950, 1100)
    ppo = rng.uniform(-20, 20, 2)
    geom = _make_geom(sod, sdd, N, N, pitch, pitch, (-ppo[0] * pitch, -ppo[1] * pitch))
    pp = np.array(geom.principal_point)
    n = int(rng.integers(18, 27))
    Rf = rng.uniform(0.44, 0.47) * N
    fcen = ((N - 1) / 2 + rng.uniform(-10, 10), (N - 1) / 2 + rng.uniform(-10, 10))
    field = _Field(fcen, Rf, Rf, 0.0, rng.uniform(6, 10))
    # clumped beads
    diam = np.full(36, 1.5)
    diam[rng.choice(36, 12, replace=False)] = 2.5
    beads = []
    guard = 0
    while len(beads) < 36 and guard < 200000:
        guard += 1
        i = len(beads)
        if i < 10:
            rr = 30 * math.sqrt(rng.random())
            ph = rng.uniform(0, 2 * np.pi)
            p = np.array([rr * math.cos(ph), rr * math.sin(ph), rng.uniform(-30, 30)])
        else:
            j = int(rng.integers(i))
            p = beads[j] + _rand_unit(rng) * ((diam[i] + diam[j]) / 2 + rng.uniform(0.3, 2.5))
            if math.hypot(p[0], p[1]) > 30 or abs(p[2]) > 30:
                continue
        if all(np.linalg.norm(p - beads[m]) >= (diam[i] + diam[m]) / 2 + 0.3 for m in range(i)):
            beads.append(p)
    beads = np.array(beads)
    mag = geom.sdd / sod
    half_obj = (Rf * pitch / mag, Rf * pitch / mag)
    poses = _poses_3d(rng, n, half_obj, float(np.linalg.norm(beads, axis=1).max()))
    c0a = rng.uniform(0, 2 * np.pi)
    c0 = rng.uniform(10, 25) * np.array([math.cos(c0a), math.sin(c0a)])
    sag = rng.uniform(3, 8)
    gdown = _rand_unit(rng)
    Dk = rng.uniform(10, 20)
    f4 = rng.uniform(0.3, 0.5)
    k1 = (1 - f4) * Dk / Rf ** 3
    k2 = f4 * Dk / Rf ** 5
    dists, centres = [], []
    for (R, t) in poses:
        gl = R @ gdown
        Cf = pp + c0 + sag * gl[:2]
        centres.append(Cf)
        dists.append(_Pincushion(Cf, k1, k2))
    wires = []
    for f in range(n):
        wl = []
        t = poses[f][1]
        for _ in range(2):
            W0 = t + np.array([rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(-25, 25)])
            a = rng.uniform(0, np.pi)
            wd = _unit([math.cos(a), math.sin(a), rng.uniform(-0.2, 0.2)])
            wl.append((W0, wd, 0.15))
        wires.append(wl)
    lead = [[] for _ in range(n)]
    chain = {"kind": "ii_log8", "N0": rng.uniform(1000, 2500), "level": 1000.0,
             "imin_frac": rng.uniform(0.01, 0.03), "imax_frac": 1.3,
             "dark": 4.0, "sigma_e": 2.0,
             "glare": rng.uniform(0.04, 0.08), "glare_sigma_px": rng.uniform(30, 60),
             "vignetting": rng.uniform(0.15, 0.30), "flat_exposures": 1, "flat_pages": 2,
             "dark_pages": 2}
    e = rng.uniform(-0.01, 0.01)
    return dict(geom=geom, beads=beads, diam=diam, body=_Body("cyl", 35.0, 35.0), poses=poses,
                dist=dists, field=field, wires=wires, lead=lead, blur=rng.uniform(0.8, 1.2),
                chain=chain, L0_steel=None, L0_pmma=None, values="raw", marker_diameter=1.5,
                mirror=False, held_kind=("cyl", (35.0, 35.0)),
                nominal_override={"sdd": geom.sdd * (1 + e), "sod": sod * (1 + e) / 1.2},
                extra={"pincushion_edge_px": Dk, "k2_fraction": f4, "sag_px": sag,
                       "centre_offset_px": c0, "gdown_phantom": gdown,
                       "distortion_centres": centres,
                       "nominal_magnification_factor": 1.2,
                       "wires": [[{"point": w[0], "dir": w[1], "radius": w[2]} for w in wl]
                                 for wl in wires]},
                expect={"nominal_magnification_error": 0.2})


def _setup_plain_grid_fp(rng):
    N, pitch = 1024, 0.2
    sod = rng.uniform(600, 800)
    sdd = rng.uniform(1000, 1200)
    ppo = rng.uniform(-15, 15, 2)
    geom = _make_geom(sod, sdd, N, N, pitch, pitch, (-ppo[0] * pitch, -ppo[1] * pitch))
    n = int(rng.integers(18, 27))
    cand = [(i, j) for i in range(7) for j in range(7)
            if i != j and i + j != 6 and i != 3 and j != 3]
    miss = cand[int(rng.integers(len(cand)))]
    pts = [((i - 3) * 10.0, (j - 3) * 10.0, 0.0) for i in range(7) for j in range(7) if (i, j) != miss]
    beads = np.array(pts)
    diam = np.full(len(beads), 2.0)
    mag = geom.sdd / sod
    half_obj = (N * pitch / 2 / mag, N * pitch / 2 / mag)
    poses = _poses_planar(rng, n, half_obj, float(np.linalg.norm(beads, axis=1).max()))
    wires, lead = _common_wires_lead(n)
    chain = {"kind": "fp_trans", "N0": rng.uniform(10000, 30000), "sigma_e": rng.uniform(3, 10)}
    perms, rots = _planar_symmetries(beads, diam)
    return dict(geom=geom, beads=beads, diam=diam, body=_Body("box", 40.0, 40.0, 2.5), poses=poses,
                dist=[_NoDist()] * n, field=None, wires=wires, lead=lead, blur=rng.uniform(0.6, 0.9),
                chain=chain, L0_steel=None, L0_pmma=None, values="transmission", marker_diameter=2.0,
                mirror=False, held_kind=("box", (40.0, 40.0, 30.0)),
                extra={"missing_grid_position": list(miss)},
                symmetry=(perms, rots), expect={"no_distortion": True})


_SETUPS = {"tilt_fp": _setup_tilt_fp, "barrel_ii": _setup_barrel_ii,
           "mirror_helix": _setup_mirror_helix, "dense_ball_ii": _setup_dense_ball_ii,
           "plain_grid_fp": _setup_plain_grid_fp}


# --------------------------------------------------------------------------- imaging chains
def _pixel_grids(rows, cols):
    return np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))


def _chain_images(cfg, rng, T_list):
    """Turn per-frame pixel transmissions into written frames; returns
    (frames, noisefree, flat, dark, dtype)."""
    g = cfg["geom"]
    rows, cols = g.rows, g.cols
    ch = cfg["chain"]
    kind = ch["kind"]
    Cg, Rg = _pixel_grids(rows, cols)
    field = cfg.get("field")
    blur = cfg["blur"]
    out, clean = [], []
    flat = dark = None
    if kind == "fp_raw16":
        th = math.radians(ch["heel_dir_deg"])
        proj = (Cg - (cols - 1) / 2) * math.cos(th) + (Rg - (rows - 1) / 2) * math.sin(th)
        heel = 1 + ch["heel"] * proj / np.abs(proj).max()
        dark_fpn = ch["dark"] + rng.normal(0, 8, cols)[None, :] + np.zeros((rows, 1))
        gain_map = 1 + rng.normal(0, 0.02, (rows, cols))
        gg, N0, se = ch["gain"], ch["N0"], ch["sigma_e"]
        for T in T_list:
            Tb = cv2.GaussianBlur(T.astype(np.float64), (0, 0), blur)
            P = heel * Tb
            E = N0 * (P + ch["scatter"] * _lowpass(P, ch["scatter_sigma_px"]))
            nf = dark_fpn + gain_map * gg * E
            img = dark_fpn + gain_map * gg * rng.poisson(E) + rng.normal(0, se, (rows, cols))
            out.append(np.clip(np.round(img), 0, 65535).astype(np.uint16))
            clean.append(nf)
        flat = np.stack([np.clip(np.round(dark_fpn + gain_map * gg * rng.poisson(N0 * heel)
                                          + rng.normal(0, se, (rows, cols))), 0, 65535).astype(np.uint16)
                         for _ in range(ch["flat_pages"])])
        dark = np.stack([np.clip(np.round(dark_fpn + rng.normal(0, se, (rows, cols))), 0, 65535)
                         .astype(np.uint16) for _ in range(ch["dark_pages"])])
        return out, clean, flat, dark
    if kind in ("ii_raw12", "ii_log8"):
        taper = field.taper(Cg, Rg)
        V = 1 - ch["vignetting"] * field.radius_norm(Cg, Rg) ** 2
        N0 = ch["N0"]

        def ii(Q):
            return taper * V * (Q + ch["glare"] * _lowpass(Q * taper, ch["glare_sigma_px"]))
        if kind == "ii_raw12":
            Gc = ch["flat_level"] / (1 + ch["glare"])
            def cam(L, noisy=True, exposures=1):
                x = ch["dark"] + Gc * L
                if noisy:
                    x = x + rng.normal(0, ch["sigma_e"] / math.sqrt(exposures), (rows, cols))
                return x
            def q12(x):
                return np.clip(np.round(x), 0, 4095).astype(np.uint16)
            for T in T_list:
                Tb = cv2.GaussianBlur(T.astype(np.float64), (0, 0), blur)
                out.append(q12(cam(ii(rng.poisson(N0 * Tb) / N0))))
                clean.append(cam(ii(Tb), noisy=False))
            m = ch["flat_exposures"]
            fl = cam(ii(rng.poisson(N0 * m * np.ones((rows, cols))) / (N0 * m)), exposures=m)
            flat = q12(fl)
            dark = q12(cam(np.zeros((rows, cols)), exposures=m))
            return out, clean, flat, dark
        lev = ch["level"]
        Gc = lev / (1 + ch["glare"])
        Imin, Imax = ch["imin_frac"] * lev, ch["imax_frac"] * lev
        def cam(L, noisy=True):
            x = ch["dark"] + Gc * L
            if noisy:
                x = x + rng.normal(0, ch["sigma_e"], (rows, cols))
            return x
        def lut(x):
            return 255 * np.clip(np.log(np.maximum(x, 1e-9) / Imin) / math.log(Imax / Imin), 0, 1)
        def q8(x):
            return np.clip(np.round(x), 0, 255).astype(np.uint8)
        for T in T_list:
            Tb = cv2.GaussianBlur(T.astype(np.float64), (0, 0), blur)
            out.append(q8(lut(cam(ii(rng.poisson(N0 * Tb) / N0)))))
            clean.append(lut(cam(ii(Tb), noisy=False)))
        flat = np.stack([q8(lut(cam(ii(rng.poisson(N0 * np.ones((rows, cols))) / N0))))
                         for _ in range(ch["flat_pages"])])
        dark = np.stack([q8(lut(cam(np.zeros((rows, cols))))) for _ in range(ch["dark_pages"])])
        return out, clean, flat, dark
    if kind == "fp_atten":
        N0, se = ch["N0"], ch["sigma_e"]
        for T in T_list:
            Tb = cv2.GaussianBlur(T.astype(np.float64), (0, 0), blur)
            cnt = rng.poisson(N0 * Tb) + rng.normal(0, se, (rows, cols))
            out.append((-np.log(np.maximum(cnt, 1.0) / N0)).astype(np.float32))
            clean.append(-np.log(Tb))
        return out, clean, None, None
    if kind == "fp_trans":
        N0, se = ch["N0"], ch["sigma_e"]
        for T in T_list:
            Tb = cv2.GaussianBlur(T.astype(np.float64), (0, 0), blur)
            cnt = rng.poisson(N0 * Tb) + rng.normal(0, se, (rows, cols))
            out.append((cnt / N0).astype(np.float32))
            clean.append(Tb)
        return out, clean, None, None
    raise ValueError(kind)


# --------------------------------------------------------------------------- mirror check
def _best_proper_fit(geom_m, beads, obs_xy, R0, t0):
    """Best proper rigid pose explaining observed (flipped) centres with the
    flipped-principal-point camera; returns RMS px."""
    def resid(x):
        R = _rot(x[:3], np.linalg.norm(x[:3])) if np.linalg.norm(x[:3]) > 0 else np.eye(3)
        P = beads @ R.T + x[3:]
        c, r = geom_m.project(P)
        return np.concatenate([c - obs_xy[:, 0], r - obs_xy[:, 1]])
    best = np.inf
    Ry = _rot([0, 1, 0], np.pi)
    for Rs in (R0, Ry @ R0):
        for tt in (t0, np.array([-t0[0], t0[1], t0[2]])):
            w = _rotvec(Rs)
            try:
                sol = optimize.least_squares(resid, np.concatenate([w, tt]), method="lm", max_nfev=3000)
                rms = math.sqrt(np.mean(sol.fun ** 2) * 2)
                best = min(best, rms)
            except Exception:
                pass
    return best


def _rotvec(R):
    ang = math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    if ang < 1e-9:
        return np.zeros(3)
    if ang > np.pi - 1e-6:
        w, V = np.linalg.eigh((R + R.T) / 2)
        ax = V[:, np.argmax(w)]
        return ax * ang
    ax = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * math.sin(ang))
    return ax * ang


# --------------------------------------------------------------------------- main entry
def make_case(name: str, seed: int, out) -> dict:
    if name not in _SETUPS:
        raise KeyError(f"unknown case {name!r}; known: {sorted(CASES)}")
    t_start = time.time()
    out = Path(out)
    scan = out / "scan"
    scan.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([zlib.crc32(name.encode()), int(seed)])
    cfg = _SETUPS[name](rng)
    g = cfg["geom"]
    rows, cols = g.rows, g.cols
    n = len(cfg["poses"])
    scene = _Scene(cfg)
    field = cfg.get("field") or _NoField()
    T_list, centres = [], []
    for f in range(n):
        T, info = scene.render(f)
        T_list.append(T)
        centres.append(info)
    frames, clean, flat, dark = _chain_images(cfg, rng, T_list)
    Cg, Rg = _pixel_grids(rows, cols)
    fmask = field.inside(Cg, Rg)
    noise = [_robust_sigma((fr.astype(np.float64) - cl)[fmask]) for fr, cl in zip(frames, clean)]
    if cfg["mirror"]:
        frames = [np.ascontiguousarray(fr[:, ::-1]) for fr in frames]
        for info in centres:
            for d in info:
                d["x"] = (cols - 1) - d["x"]
    # held-out points
    hk, hd = cfg["held_kind"]
    hp = _heldout_points(rng, cfg["beads"], cfg["diam"], hk, hd)
    heldout = []
    for f, (R, t) in enumerate(cfg["poses"]):
        P = hp @ R.T + t
        pc, pr = g.project(P)
        qc, qr = cfg["dist"][f].fwd(pc, pr)
        ok = ((qc >= -0.5) & (qc <= cols - 0.5) & (qr >= -0.5) & (qr <= rows - 0.5)
              & field.inside(qc, qr))
        if cfg["mirror"]:
            qc = (cols - 1) - qc
        heldout.append({"frame": f, "points": hp[ok], "pixels": np.column_stack([qc[ok], qr[ok]])})
    # ---- write scan
    tifffile.imwrite(scan / "projections.tif", np.stack(frames), photometric="minisblack")
    if cfg["values"] == "raw":
        tifffile.imwrite(scan / "flat.tif", flat, photometric="minisblack")
        tifffile.imwrite(scan / "dark.tif", dark, photometric="minisblack")
    with open(scan / "phantom.csv", "w") as fh:
        fh.write("id,x,y,z\n")
        for i, p in enumerate(cfg["beads"]):
            fh.write(f"{i},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}\n")
    tt = np.concatenate([[0.0], np.cumsum(rng.uniform(0.8, 2.5, n - 1))])
    with open(scan / "log.csv", "w") as fh:
        fh.write("frame,time\n")
        for f in range(n):
            fh.write(f"{f},{tt[f]:.3f}\n")
    sod_true = float(np.linalg.norm(g.S))
    nominal = cfg.get("nominal_override") or {
        "sod": sod_true * (1 + rng.uniform(-0.015, 0.015)),
        "sdd": g.sdd * (1 + rng.uniform(-0.015, 0.015))}
    nominal = {k: round(float(v), 3) for k, v in nominal.items()}
    sy = {"format": "conecal-scan/1", "motion": "free", "projections": "projections.tif",
          "values": cfg["values"], "log": "log.csv",
          "detector": {"rows": rows, "cols": cols, "pixel_pitch": [float(g.pu), float(g.pv)]},
          "nominal": nominal,
          "markers": {"diameter": float(cfg["marker_diameter"]), "phantom": "phantom.csv"},
          "imaging": {"blur_px": round(float(cfg["blur"] * rng.uniform(0.9, 1.1)), 2)}}
    if cfg["values"] == "raw":
        sy["flat"] = "flat.tif"
        sy["dark"] = "dark.tif"
    with open(scan / "scan.yaml", "w") as fh:
        yaml.safe_dump(sy, fh, sort_keys=False)
    # ---- truth
    truth = {"case": name, "seed": int(seed), "description": CASES[name],
             "frames": n, "centres": centres, "heldout": heldout,
             "sdd": g.sdd, "sod": sod_true, "principal_point": g.principal_point,
             "geometry": g.as_dict(),
             "poses": [{"frame": f, "R": R, "t": t} for f, (R, t) in enumerate(cfg["poses"])],
             "noise_sigma": noise, "noise_sigma_units": "written image units",
             "distortion_kind": cfg["dist"][0].kind,
             "distortion": [{"frame": f, **d.params()} for f, d in enumerate(cfg["dist"])],
             "bead_diameters_mm": cfg["diam"], "phantom_points": cfg["beads"],
             "body": cfg["body"].as_dict(), "nominal": nominal, "blur_px": cfg["blur"],
             "values": cfg["values"], "chain": cfg["chain"], "mirrored_lr": bool(cfg["mirror"]),
             "field": cfg["field"].params() if cfg.get("field") else None,
             "expect": cfg.get("expect", {})}
    if cfg.get("L0_steel") is not None:
        truth["beam_hardening"] = {"form": "A = mu0 L / (1 + L/L0)", "L0_steel": cfg["L0_steel"],
                                   "L0_pmma": cfg["L0_pmma"]}
    truth.update(cfg.get("extra", {}))
    perms, rots = cfg.get("symmetry", ([], []))
    if len(perms) > 1:
        truth["symmetry"] = {"id_permutations": perms, "rotations": rots,
                             "note": "proper rotations (phantom frame) mapping beads (with sizes) "
                                     "and plate onto themselves; identity first"}
    if cfg["mirror"]:
        pp = g.principal_point
        truth["principal_point_written"] = [(cols - 1) - pp[0], pp[1]]
        # honest residual of the best proper pose for the mirrored images
        Sm = g.S.copy()
        gm = _Geom(Sm, g.O, g.u, g.v, g.pu, g.pv, rows, cols)
        # camera whose principal point is flipped: shift detector origin along u
        shift = ((cols - 1) - 2 * pp[0]) * g.pu
        gm.O = g.O - shift * g.u
        rmss = []
        for f, (R, t) in enumerate(cfg["poses"]):
            obs = [(d["id"], d["x"], d["y"]) for d in centres[f] if not d["truncated"]]
            if len(obs) < 6:
                rmss.append(None)
                continue
            ids = np.array([o[0] for o in obs])
            xy = np.array([[o[1], o[2]] for o in obs])
            rmss.append(_best_proper_fit(gm, cfg["beads"][ids], xy, R, t))
        truth["mirror_best_proper_rms_px"] = rmss
    _write_json_atomic(out / "truth.json", truth)
    sec = time.time() - t_start
    return {"case": name, "seed": int(seed), "frames": n,
            "spheres_per_frame": float(np.mean([len(c) for c in centres])),
            "overlaps": int(sum(d["overlap"] for c in centres for d in c)),
            "truncated": int(sum(d["truncated"] for c in centres for d in c)),
            "noise_sigma": float(np.mean(noise)), "seconds": round(sec, 2)}


# --------------------------------------------------------------------------- self-check
def _flat_fielded(scan):
    sy = yaml.safe_load(open(scan / "scan.yaml"))
    stack = tifffile.imread(scan / "projections.tif").astype(np.float64)
    if stack.ndim == 2:
        stack = stack[None]
    if sy["values"] == "raw":
        fl = tifffile.imread(scan / "flat.tif").astype(np.float64)
        dk = tifffile.imread(scan / "dark.tif").astype(np.float64)
        fl = fl.mean(0) if fl.ndim == 3 else fl
        dk = dk.mean(0) if dk.ndim == 3 else dk
        den = fl - dk
        ok = den > 0.05 * np.percentile(den, 99)
        return np.where(ok[None], (stack - dk[None]) / np.where(ok, den, 1)[None], np.nan)
    if sy["values"] == "attenuation":
        return np.exp(-stack)
    return stack


def _check_case(out):
    truth = json.load(open(out / "truth.json"))
    ff = _flat_fielded(out / "scan")
    n_chk = n_fail = 0
    errs = []
    fails = []
    for f, cen in enumerate(truth["centres"]):
        P = np.array([[d["x"], d["y"], d["diameter_px"] / 2] for d in cen]).reshape(-1, 3)
        ffr = np.nan_to_num(ff[f], nan=0.0)
        img = cv2.GaussianBlur(ffr.astype(np.float32), (0, 0), 0.7)
        H, W = img.shape
        yy, xx = np.mgrid[0:H, 0:W]
        for d in cen:
            if d["truncated"]:
                continue
            n_chk += 1
            x, y, dp = d["x"], d["y"], d["diameter_px"]
            rad = dp / 2
            x0, x1 = int(max(0, x - rad - 8)), int(min(W, x + rad + 9))
            y0, y1 = int(max(0, y - rad - 8)), int(min(H, y + rad + 9))
            sub = img[y0:y1, x0:x1]
            rr = np.hypot(xx[y0:y1, x0:x1] - x, yy[y0:y1, x0:x1] - y)
            ring = sub[(rr > rad + 2) & (rr < rad + 6)]
            vc = ndimage.map_coordinates(img, [[y], [x]], order=1)[0]
            bg = np.percentile(ring, 90)
            raw = ffr[y0:y1, x0:x1]
            dd = (raw[:, 1:] - raw[:, :-1]).ravel() / math.sqrt(2)
            sig = _robust_sigma(dd[np.isfinite(dd)])
            dip = bg - vc
            ok = bool(dip > max(5 * sig, 0.05 * abs(bg)))
            if not ok:
                n_fail += 1
                fails.append((f, d["id"], round(x, 1), round(y, 1), float(dip), float(sig)))
            gap = np.hypot(P[:, 0] - x, P[:, 1] - y) - P[:, 2] - rad
            isolated = np.sum(gap < 8) <= 1  # itself only
            if isolated and not d.get("clutter_near"):
                # centroid of the line-integral excess over a plane fitted on a ring
                sub = -np.log(np.clip(sub, 1e-4, None))
                inn = rr < rad + 1.5
                rm = (rr > rad + 2) & (rr < rad + 6)
                X = np.column_stack([np.ones(rm.sum()), xx[y0:y1, x0:x1][rm] - x, yy[y0:y1, x0:x1][rm] - y])
                cf = np.linalg.lstsq(X, sub[rm], rcond=None)[0]
                plane = cf[0] + cf[1] * (xx[y0:y1, x0:x1] - x) + cf[2] * (yy[y0:y1, x0:x1] - y)
                w = np.clip(sub - plane, 0, None) * inn
                if w.sum() > 0:
                    cx = (w * xx[y0:y1, x0:x1]).sum() / w.sum()
                    cy = (w * yy[y0:y1, x0:x1]).sum() / w.sum()
                    errs.append(math.hypot(cx - x, cy - y))
    return n_chk, n_fail, errs, fails


def _main():
    names = sys.argv[1:] or list(CASES)
    print(f"{'case':15s} {'frames':>6s} {'sph/fr':>7s} {'overl':>6s} {'trunc':>6s} {'noise':>9s} "
          f"{'sec':>6s} {'checked':>7s} {'fail':>5s} {'cen_err med/p95':>16s}")
    all_ok = True
    with tempfile.TemporaryDirectory() as td:
        for name in names:
            out = Path(td) / name
            s = make_case(name, 0, out)
            n_chk, n_fail, errs, fails = _check_case(out)
            e = np.array(errs) if errs else np.zeros(1)
            print(f"{name:15s} {s['frames']:6d} {s['spheres_per_frame']:7.1f} {s['overlaps']:6d} "
                  f"{s['truncated']:6d} {s['noise_sigma']:9.4g} {s['seconds']:6.1f} {n_chk:7d} "
                  f"{n_fail:5d} {np.median(e):7.3f}/{np.percentile(e, 95):6.3f}", flush=True)
            for fl in fails[:5]:
                print("   FAIL frame/id/x/y/dip/sig", fl)
            all_ok &= n_fail == 0
    print("SELF-CHECK", "PASSED" if all_ok else "FAILED")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(_main())
