"""Image level: re-simulate every marker's shadow from the fitted scene and
compare it, pixel by pixel, with the recorded frame.

For each observation the sphere is placed (fitted geometry and motion, then
moved parallel to the detector so that its shadow sits where ``detect``
found it, then refined to 1e-3 px on the image) and its chord-length image
is rendered with ``simulate``'s renderer. The recorded attenuation of a
patch around it is modelled as

    A = b - ln(T + s' (1 - T)),
    T = (1 - lag r) G_sigma[exp(-(H(b0 + mu L) - b))] + lag T_prev

with ``b`` the patch's background (a quadratic surface fitted to the pixels outside
every shadow of this frame and the previous one), ``b0`` its value before
beam hardening ``H(a) = a / (1 + beta a)``, ``G_sigma`` a Gaussian blur on
the intensity, ``T_prev`` the previous recorded frame relative to the
background (the ghost that lag leaves; ``r = exp(b - b_prev)`` keeps the
background itself where it was recorded when the body behind the markers
moved between frames), and ``s' = s exp(b)`` the scattered intensity ``s``
(fraction of the open beam) relative to the background. Both terms leave
the background at ``b``: it was measured with the lag and the scatter in it.
Pixels are weighted by Poisson noise, ``sigma = sigma_air exp((A - b)/2)``,
``sigma_air`` measured on each patch's background.

The base model has the stated blur (``imaging.blur_px`` in ``scan.yaml``;
fitted when the scan does not state it) and a free attenuation
coefficient ``mu``; each candidate effect frees one more parameter. The
choice uses the same rules as the geometric level (:mod:`.select`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from ..effects.imaging import BeamHardening, Blur, DetectorLag, Scatter, beam_hardened, unhardened
from ..simulate.render import Sphere, render_line_integrals

KERNEL_RADIUS = 6          # px; the blur kernel's half width (sigma up to 2 px)
SIGMA_FLOOR = 1e-4         # attenuation; the noise of a noiseless (float32) image


@dataclass
class Patch:
    frame: int
    id: int
    parity: int             # frame order parity: the held-out folds
    box: tuple              # (r0, r1, c0, c1), inclusive-exclusive
    recorded: np.ndarray    # attenuation
    background: np.ndarray  # b, a quadratic surface
    chord: np.ndarray       # L, mm (all spheres of the frame, mu = 1)
    previous: np.ndarray | None   # previous frame's transmission relative to b
    previous_background: np.ndarray | None  # exp(b - b_prev): the previous frame's background relative to b
    radius_px: float
    centre: np.ndarray      # (2,) px
    sigma_air: float
    lab: np.ndarray = None        # (3,) the sphere's placed lab centre, mm
    sphere_radius: float = 0.0    # mm
    others: np.ndarray = None     # chord image of the frame's other spheres in the patch
    neighbours: list = None       # [(id, lab centre mm, radius mm)] of the other spheres reaching into it
    dchord: np.ndarray = None     # d(own chord image)/d(relative sphere radius)
    weight: np.ndarray = None     # 1 / sigma per pixel


def _kernel(sigma: float) -> np.ndarray:
    x = np.arange(-KERNEL_RADIUS, KERNEL_RADIUS + 1, dtype=float)
    if sigma < 1e-3:
        k = (x == 0).astype(float)
    else:
        k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def _background(img, mask):
    """The background under a patch: a quadratic surface fitted to the
    pixels ``mask`` (a ring around the shadows). A sample body behind the
    markers (a cylinder's chord profile) curves over a patch by a fair part
    of the noise, and a plane would leave that for the effects to explain."""
    rr, cc = np.nonzero(mask)
    r0, c0 = rr.mean(), cc.mean()
    s = max(img.shape) / 2.0

    def terms(r, c):
        y, x = (r - r0) / s, (c - c0) / s
        return [np.ones_like(x), x, y, x * x, x * y, y * y]

    coef, *_ = np.linalg.lstsq(np.column_stack(terms(rr, cc)), img[rr, cc], rcond=None)
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    return sum(c * t for c, t in zip(coef, terms(yy, xx)))


class ImageModel:
    """The recorded patches around every marker and their model."""

    PARAMS = ("mu", "size", "blur", "beam_hardening", "lag", "scatter")

    def __init__(self, model, scan, *, effects=(), base=None, max_frames: int = 48, progress=None):
        self.model = model
        self.scan = scan
        # the scene as the geometric level left it: its effects switched on, its parameters refitted
        self.effects = list(effects)
        self.base = np.zeros(model.n_base) if base is None else np.asarray(base, float)
        self.g = model.geometry_after(self.base)
        imaging = model.world(self.effects).imaging if self.effects else None
        # a detector warp the geometric level found: shadows are rendered through it
        self.imaging = imaging if imaging is not None and imaging.distorted else None
        spec = getattr(scan.config, "imaging", None)
        self.stated_blur = None if spec is None or spec.blur_px is None else float(spec.blur_px)
        self.patches: list[Patch] = []
        self.skipped: dict[str, int] = {}
        self._crops: dict = {}      # box -> (cropped detector, its warp)
        self._start_gradients: dict = {}   # (frame, id, h) -> (lab centre, own_gradient there)
        self._build(max_frames, progress)
        if not self.patches:
            raise ValueError("no marker patch is usable at the image level")
        self.sigma_air = float(np.median([p.sigma_air for p in self.patches]))

    # ----------------------------------------------------------- setup
    def _radii(self) -> dict:
        doc, cfg = self.model.doc, self.scan.config
        declared = (cfg.markers.diameter / 2) if cfg.markers is not None else 1.0
        out = {int(s["id"]): float(s.get("diameter", 2 * declared)) / 2 for s in doc.get("spheres", [])}
        return out or {int(i): declared for i in np.unique(self.model.obs.ids)}

    def _moved(self, X, d):
        """Lab points X (m, 3) moved parallel to the detector so that their projections move by d (m, 2) px."""
        g = self.g
        frac = ((X - g.source) @ g.normal) / ((g.detector_origin - g.source) @ g.normal)
        return X + (d[:, :1] * g.pixel_pitch[0] * g.u + d[:, 1:] * g.pixel_pitch[1] * g.v) * frac[:, None]

    def _placed(self, idx):
        """Lab centres of observations ``idx``, moved so their shadows sit at the measurements."""
        m = self.model
        X, pred = m.lab_centres(self.effects, self.base, idx)
        if self.imaging is not None:   # the prediction is distorted; the placement is not
            pred = self.imaging.undistort(pred, m.geometry.shape)
        xy = m.obs.xy[idx] if self.imaging is None else self.imaging.undistort(m.obs.xy[idx], m.geometry.shape)
        return self._moved(X, xy - pred)

    def _render_patch(self, box, X, r) -> np.ndarray:
        # a patch is rendered some 50 times (re-centring, neighbours, derivatives):
        # its cropped detector is made once
        crops = self._crops
        if box not in crops:
            g = self.g
            r0, r1, c0, c1 = box
            crop = g.replace(detector_origin=g.detector_point(c0, r0), shape=(r1 - r0, c1 - c0))
            warp = None if self.imaging is None else _CropWarp(self.imaging, g.shape, np.array([c0, r0], float))
            crops[box] = (crop, warp)
        crop, warp = crops[box]
        return render_line_integrals(crop, [Sphere(X, r, 1.0)], ss=3, distortion=warp)

    def _render(self, X, radii):
        g = self.g
        return render_line_integrals(g, [Sphere(x, r, 1.0) for x, r in zip(X, radii)], ss=3, distortion=self.imaging)

    def _build(self, max_frames, progress):
        m = self.model
        o = m.obs
        radius_of = self._radii()
        g = self.g
        rows_, cols_ = g.shape
        frames = np.unique(o.frame)
        order = np.argsort(m.times)
        prev_row = {int(order[i]): int(order[i - 1]) for i in range(1, len(order))}
        chosen = frames[np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))]
        row_of_frame = dict(zip(o.frame.tolist(), o.row.tolist()))
        frame_of_row = {r: f for f, r in row_of_frame.items()}
        blur_pad = 3 * max(self.stated_blur or 1.0, 1.0) + KERNEL_RADIUS
        for n_done, f in enumerate(chosen):
            idx = np.flatnonzero(o.frame == f)
            radii = np.array([radius_of.get(int(i), np.nan) for i in o.ids[idx]])
            if np.isnan(radii).any():
                self.skipped["unknown sphere size"] = self.skipped.get("unknown sphere size", 0) + len(idx)
                continue
            X = self._placed(idx)
            L = self._render(X, radii)
            rec = self.scan.stack.read(int(f)).astype(float)
            r_prev = prev_row.get(int(row_of_frame[f]))
            prev_rec, L_prev, prev_xy = None, None, {}
            if r_prev is not None and r_prev in frame_of_row:
                fp = frame_of_row[r_prev]
                jp = np.flatnonzero(o.frame == fp)
                rp = np.array([radius_of.get(int(i), np.nan) for i in o.ids[jp]])
                if not np.isnan(rp).any():
                    prev_rec = self.scan.stack.read(int(fp)).astype(float)
                    L_prev = self._render(self._placed(jp), rp)
                    prev_xy = {int(i): xy for i, xy in zip(o.ids[jp], o.xy[jp])}
            shadow = cv2.dilate((L > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
            if L_prev is not None:
                shadow |= cv2.dilate((L_prev > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
            for j, i_obs in enumerate(idx):
                xy = o.xy[i_obs]
                rpx = float(radii[j] * g.magnification(X[j]) / g.pixel_pitch[0])
                half = rpx + blur_pad + 3
                lo, hi = xy - half, xy + half
                pxy = prev_xy.get(int(o.ids[i_obs]))
                if pxy is not None and np.hypot(*(pxy - xy)) < 3 * rpx:
                    lo, hi = np.minimum(lo, pxy - half), np.maximum(hi, pxy + half)
                c0, r0 = np.floor(lo).astype(int)
                c1, r1 = np.ceil(hi).astype(int) + 1
                if c0 < 0 or r0 < 0 or c1 > cols_ or r1 > rows_:
                    self.skipped["near the detector edge"] = self.skipped.get("near the detector edge", 0) + 1
                    continue
                sl = (slice(r0, r1), slice(c0, c1))
                bg_mask = ~shadow[sl]
                if bg_mask.sum() < 40:
                    self.skipped["no background around it"] = self.skipped.get("no background around it", 0) + 1
                    continue
                A = rec[sl]
                b = _background(A, bg_mask)
                resid = (A - b)[bg_mask]
                sig = max(1.4826 * np.median(np.abs(resid - np.median(resid))), SIGMA_FLOOR)
                # structure the model cannot explain (clutter, another object) in the background
                if np.mean(np.abs(resid) > 5 * sig) > 0.02:
                    self.skipped["clutter in the background"] = self.skipped.get("clutter in the background", 0) + 1
                    continue
                prev, prev_bg = None, None
                if prev_rec is not None:
                    # bg_mask is clear of the previous frame's shadows too
                    prev = np.exp(-(prev_rec[sl] - b))
                    prev_bg = np.exp(b - _background(prev_rec[sl], bg_mask))
                box = (r0, r1, c0, c1)
                own = self._render_patch(box, X[j], radii[j])
                # each neighbour is rendered on its own, so that it can follow
                # its own patch when that is re-centred (refine_centres)
                reach = (radii * g.magnification(X) / g.pixel_pitch[0]) + 2
                near = [k for k in range(len(idx)) if k != j and np.all(o.xy[idx[k]] > lo - reach[k])
                        and np.all(o.xy[idx[k]] < hi + reach[k])]
                nbrs = [(int(o.ids[idx[k]]), X[k].copy(), float(radii[k])) for k in near]
                others = sum((self._render_patch(box, x_, r_) for _, x_, r_ in nbrs), np.zeros_like(own))
                self.patches.append(Patch(int(f), int(o.ids[i_obs]), int(row_of_frame[f]) % 2, box,
                                          A, b, own + others, prev, prev_bg, rpx, xy.copy(), float(sig),
                                          X[j].copy(), float(radii[j]), others, nbrs,
                                          self._dchord(box, X[j], radii[j], own)))
            if progress:
                progress(n_done + 1, len(chosen))

    # ----------------------------------------------------------- model
    def full(self, theta: dict) -> np.ndarray:
        """Parameter vector (5,) from a partial dict, the rest at their base values."""
        base = {"mu": 1.0, "size": 0.0, "blur": self.stated_blur if self.stated_blur is not None else 0.5,
                "beam_hardening": 0.0, "lag": 0.0, "scatter": 0.0}
        base.update(theta)
        return np.array([base[k] for k in self.PARAMS])

    def start(self) -> np.ndarray:
        """Base parameters with mu from a linear fit of the background-free attenuation to the chords."""
        x = self.full({})
        num = sum(float(((p.recorded - p.background) * p.chord).sum()) for p in self.patches)
        den = sum(float((p.chord ** 2).sum()) for p in self.patches)
        x[0] = max(num / max(den, 1e-12), 1e-3)
        return x

    def predict_patch(self, p: Patch, x, own_gradient=None):
        """Modelled attenuation of patch ``p`` under parameters ``x``; given
        ``own_gradient`` (:meth:`own_gradient`), also its spatial derivatives
        (px⁻¹, columns and rows) when only the patch's own shadow moves:
        neither the ghost of the previous frame nor the neighbours' shadows
        move with it (a gradient of the whole modelled image moves them too
        and so stops the re-centring short of the shadow)."""
        mu, size, blur, beta, lag, s = x
        b = p.background
        a = mu * (p.chord + size * p.dchord)
        lin = unhardened(b, beta) + a
        ps = beam_hardened(lin, beta) - b if beta else a
        T = np.exp(-ps)
        k = _kernel(abs(blur))

        def blurred(img):
            return cv2.sepFilter2D(img, -1, k, k, borderType=cv2.BORDER_REPLICATE)

        Tf, gain = blurred(T), 1.0
        if lag and p.previous is not None:
            gain = 1 - lag * p.previous_background
            Tf = gain * Tf + lag * p.previous
        if s:
            # the primary background is exp(-b) - s: the recorded one has the scatter in it
            sp = s * np.exp(b)
            Tf, gain = Tf + sp * (1 - Tf), gain * (1 - sp)
        Tf = np.maximum(Tf, 1e-9)
        A = b - np.log(Tf)
        if own_gradient is None:
            return A
        dT = (-T / (1 + beta * lin) ** 2 if beta else -T) * mu
        scale = -gain / Tf
        return A, scale * blurred(dT * own_gradient[0]), scale * blurred(dT * own_gradient[1])

    def own_gradient(self, p: Patch, h: float = 0.02):
        """Spatial derivatives (mm/px, columns and rows) of the patch's own
        chord image, by re-rendering its sphere moved ±h px (the chord is
        pixel-averaged over 3x3 rays: a finite difference of the image
        itself is 20 % off at 0.6 px blur)."""
        # every candidate's fit starts from the same placement: the first
        # position's derivatives are kept (exactly those; moved shadows re-render)
        key = (p.frame, p.id, h)
        kept = self._start_gradients.get(key)
        if kept is not None and np.array_equal(kept[0], p.lab):
            return kept[1]
        out = []
        for k in range(2):
            d = np.zeros((2, 2))
            d[:, k] = (h, -h)
            X = self._moved(np.repeat(p.lab[None], 2, axis=0), d)
            plus, minus = (self._render_patch(p.box, X[i], p.sphere_radius) for i in range(2))
            out.append(-(plus - minus) / (2 * h))     # the sphere moved +h: the image moved by -h
        if kept is None:
            self._start_gradients[key] = (p.lab.copy(), out)
        return out

    def set_weights(self, x) -> None:
        for p in self.patches:
            A = self.predict_patch(p, x)
            p.weight = 1.0 / (p.sigma_air * np.exp(0.5 * np.clip(A - p.background, 0, 20)))

    def residuals(self, x, select=None) -> np.ndarray:
        ps = self.patches if select is None else [p for p, s in zip(self.patches, select) if s]
        return np.concatenate([((p.recorded - self.predict_patch(p, x)) * p.weight).ravel() for p in ps])

    def refine_centres(self, x, iterations: int = 2) -> None:
        """Sub-pixel shift of each patch's chord image so the shadow sits where the image says
        (detect's centre is good to a few hundredths of a pixel; edges are steep)."""
        for _ in range(iterations):
            moved = set()
            for p in self.patches:
                A, gx, gy = self.predict_patch(p, x, self.own_gradient(p))
                w2 = p.weight ** 2
                J = np.column_stack([gx.ravel(), gy.ravel()])
                r = (p.recorded - A).ravel()
                H = J.T @ (J * w2.ravel()[:, None])
                d = -np.linalg.solve(H + 1e-9 * np.eye(2), J.T @ (r * w2.ravel()))
                if np.all(np.abs(d) < 2):
                    p.lab = self._moved(p.lab[None], d[None])[0]
                    p.centre = p.centre + d
                    moved.add((p.frame, p.id))
            self._follow(moved)

    def _follow(self, moved: set) -> None:
        """Re-render the patches whose own sphere or a neighbour moved, with
        each neighbour where its own patch now puts it (a neighbour 0.05 px
        off, on an edge 0.4 in attenuation per pixel, leaves twice the noise)."""
        lab = {(p.frame, p.id): p.lab for p in self.patches}
        for p in self.patches:
            if (p.frame, p.id) not in moved and not any((p.frame, i) in moved for i, _, _ in p.neighbours):
                continue
            own = self._render_patch(p.box, p.lab, p.sphere_radius)
            p.others = sum((self._render_patch(p.box, lab.get((p.frame, i), x_), r_) for i, x_, r_ in p.neighbours),
                           np.zeros_like(own))
            p.chord = own + p.others
            p.dchord = self._dchord(p.box, p.lab, p.sphere_radius, own)

    def _dchord(self, box, X, r, own, h: float = 0.01) -> np.ndarray:
        # the shadow's size is known only as well as the sphere's diameter and the magnification
        return (self._render_patch(box, X, r * (1 + h)) - own) / h

    def placement(self) -> list:
        return [(p.lab, p.chord, p.centre, p.dchord, p.others) for p in self.patches]

    def place(self, state) -> None:
        for p, (lab, chord, centre, dchord, others) in zip(self.patches, state):
            p.lab, p.chord, p.centre, p.dchord, p.others = lab, chord, centre, dchord, others

    @property
    def n_pixels(self) -> int:
        return int(sum(p.recorded.size for p in self.patches))


@dataclass(frozen=True)
class _CropWarp:
    """A detector distortion seen from a patch whose pixel (0, 0) is the detector's ``offset``."""

    imaging: object
    shape: tuple
    offset: np.ndarray
    distorted: bool = True

    def distort(self, xy, shape=None):
        return self.imaging.distort(np.asarray(xy, float) + self.offset, self.shape) - self.offset

    def undistort(self, xy, shape=None):
        return self.imaging.undistort(np.asarray(xy, float) + self.offset, self.shape) - self.offset


# ----------------------------------------------------------------- candidates
@dataclass(frozen=True)
class ImageCandidate:
    label: str
    free: tuple               # names in ImageModel.PARAMS freed by this candidate
    describe: object          # (values, sigmas, model) -> plain words
    build: object             # (values, model) -> Effect
    size: object = None       # values -> the effect's size in the units of ``floor``
    floor: float = 0.0        # the smallest size claimed (see FLOORS)

    @property
    def k(self) -> int:
        return len(self.free)

    def big_enough(self, v) -> bool:
        return self.size is None or abs(float(self.size(np.asarray(v, float)))) >= self.floor


# The smallest size the image level claims, about twice the largest that
# clean simulated scans show. The renderer reproduces the simulator's
# shadows only to a few parts in 1e4 of the noise-weighted chi^2, and with
# 1e6 pixels that alone "beats the noise": clean arm scans read blur
# 0.05 px (in quadrature) below the stated one, lag 0.03 %, beta 0.0025,
# scatter 0.3 %. None of these matter to a geometry.
FLOORS = {"blur": 0.1, "beam_hardening": 0.005, "detector_lag": 0.002, "scatter": 0.005}
# A second image effect is tried only when the first leaves chi^2/dof above
# 1 by more than this: clean scans read up to 1.02 (each patch's noise is
# measured on 100-700 background pixels, which alone inflates it by ~1 %),
# and with 1e6 pixels 5 sigma of chi^2/dof is only 0.003.
SECOND_EFFECT_EXCESS = 0.03


def image_candidates(im: ImageModel) -> list[ImageCandidate]:
    out = []
    if im.stated_blur is not None:
        nom = im.stated_blur

        def blur_words(v, s, im=im):
            extra = np.sign(v[0] ** 2 - nom ** 2) * np.sqrt(abs(v[0] ** 2 - nom ** 2))
            return (f"edges are blurred by sigma {v[0]:.4f} ± {s[0]:.4f} px, not the stated {nom:.3f} px "
                    f"({extra:+.3f} px in quadrature)")
        out.append(ImageCandidate("blur", ("blur",), blur_words,
                                  lambda v: Blur(float(np.sqrt(max(v[0] ** 2 - nom ** 2, 0.0)))),
                                  lambda v: np.sqrt(abs(v[0] ** 2 - nom ** 2)), FLOORS["blur"]))
    out.append(ImageCandidate("beam_hardening", ("beam_hardening",),
                              lambda v, s: f"attenuation grows less than path length: beta {v[0]:.4f} ± {s[0]:.4f} "
                                           f"(a chord of attenuation 1 reads {1 / (1 + v[0]):.3f})",
                              lambda v: BeamHardening(float(v[0])), lambda v: v[0], FLOORS["beam_hardening"]))
    out.append(ImageCandidate("detector_lag", ("lag",),
                              lambda v, s: f"each frame keeps {100 * v[0]:.2f} ± {100 * s[0]:.2f} % of the previous "
                                           "one (a ghost of the previous marker positions; it pulls detected "
                                           f"centres back: re-run `conecal detect --lag {v[0]:.4f}`)",
                              lambda v: DetectorLag(float(v[0])), lambda v: v[0], FLOORS["detector_lag"]))
    out.append(ImageCandidate("scatter", ("scatter",),
                              lambda v, s: f"an intensity of {100 * v[0]:.2f} ± {100 * s[0]:.2f} % of the open beam is "
                                           "added everywhere (scatter or a dark-offset error)",
                              lambda v: Scatter(float(v[0])), lambda v: v[0], FLOORS["scatter"]))
    return out


BOUNDS = {"mu": (1e-6, np.inf), "size": (-0.2, 0.2), "blur": (0.0, 3.0), "beam_hardening": (-0.5, 3.0), "lag": (-0.5, 0.95),
          "scatter": (-0.5, 2.0)}
SCALES = {"mu": 0.01, "size": 0.001, "blur": 0.05, "beam_hardening": 0.01, "lag": 0.01, "scatter": 0.005}


class ImageFitter:
    """Least squares over the base parameters plus a set of candidates'."""

    def __init__(self, im: ImageModel, start: np.ndarray):
        self.im = im
        self.start = start
        self.placement = im.placement()
        self.base_free = ("mu", "size") if im.stated_blur is not None else ("mu", "size", "blur")

    def fit(self, cands, select=None, x0=None):
        """Least squares over the base parameters (``mu``, the shadows'
        common size change: sphere diameters and magnification are known to
        a few 1e-3, and the blur when the scan does not state it) and the
        candidates'."""
        names = list(self.base_free) + [n for c in cands for n in c.free]
        idx = [ImageModel.PARAMS.index(n) for n in names]
        x_full = self.start.copy() if x0 is None else x0.copy()

        def full(z):
            x = x_full.copy()
            x[idx] = z
            return x

        lo = np.array([BOUNDS[n][0] for n in names])
        hi = np.array([BOUNDS[n][1] for n in names])
        z0 = np.clip(x_full[idx], lo + 1e-9, hi - 1e-9)
        res = least_squares(lambda z: self.im.residuals(full(z), select), z0, bounds=(lo, hi),
                            x_scale=np.array([SCALES[n] for n in names]), diff_step=1e-4,
                            xtol=1e-8, ftol=1e-10, max_nfev=60)
        J = res.jac
        chi2 = float(res.fun @ res.fun)
        dof = max(len(res.fun) - len(z0), 1)
        cov = np.linalg.pinv(J.T @ J) * max(chi2 / dof, 1.0)
        sig = np.sqrt(np.clip(np.diag(cov), 0, None))
        return full(res.x), dict(zip(names, sig)), chi2, len(res.fun)

    def evaluate(self, cands) -> dict:
        """Fit, re-centre every shadow under this model (an effect such as
        lag moves what the base model takes for the centre), fit again, and
        score on held-out frames (even against odd frame order)."""
        self.im.place(self.placement)
        x, *_ = self.fit(cands)
        for _ in range(3):     # lag's ghost: three passes take 5 % to 4.94 %, two to 4.87 %
            self.im.refine_centres(x, iterations=1)
            x, sig, chi2, n = self.fit(cands, x0=x)
        k = len(self.base_free) + sum(c.k for c in cands)
        fitted = self.im.placement()
        parity = np.array([p.parity for p in self.im.patches])
        r2 = np.zeros(len(parity))     # held-out chi^2 per patch
        for train in (parity == 0, parity == 1):
            if train.all() or not train.any():
                raise ValueError("held-out frames need both even and odd frames")
            xt, *_ = self.fit(cands, train, x0=x)
            for i in np.flatnonzero(~train):
                p = self.im.patches[i]
                r = (p.recorded - self.im.predict_patch(p, xt)) * p.weight
                r2[i] = float((r * r).sum())
            self.im.place(fitted)
        return {"cands": cands, "x": x, "sigma": sig, "chi2": chi2, "n": n, "bic": chi2 + k * np.log(n),
                "heldout": float(r2.sum()), "heldout_r2": r2, "placement": fitted}


def radial_profile(im: ImageModel, x, bins: int = 24) -> dict:
    """Mean recorded minus modelled attenuation against distance from the
    shadow centre, in shadow radii (0..2), and its standard error."""
    edges = np.linspace(0, 2, bins + 1)
    num, den, sq = np.zeros(bins), np.zeros(bins), np.zeros(bins)
    for p in im.patches:
        r = p.recorded - im.predict_patch(p, x)
        yy, xx = np.mgrid[p.box[0]:p.box[1], p.box[2]:p.box[3]]
        rho = np.hypot(xx - p.centre[0], yy - p.centre[1]) / p.radius_px
        k = np.digitize(rho.ravel(), edges) - 1
        ok = (k >= 0) & (k < bins)
        np.add.at(num, k[ok], r.ravel()[ok])
        np.add.at(sq, k[ok], r.ravel()[ok] ** 2)
        np.add.at(den, k[ok], 1)
    mean = num / np.maximum(den, 1)
    se = np.sqrt(np.maximum(sq / np.maximum(den, 1) - mean ** 2, 0) / np.maximum(den, 1))
    return {"radius": (0.5 * (edges[1:] + edges[:-1])).tolist(), "mean": mean.tolist(), "stderr": se.tolist()}


def _profile_at(im, e):
    im.place(e["placement"])
    return radial_profile(im, e["x"])


def diagnose_image(model, scan, *, geometric_effects=(), geometric_base=None, max_frames: int = 48,
                   progress=None) -> dict:
    """The image-level decision: which imaging effect (if any) the recorded
    marker shadows show beyond the line-integral model (and beyond what the
    geometric level found: a detector distortion it claimed is rendered).
    Returns a JSON-ready dict."""
    from .select import rank, score

    try:
        im = ImageModel(model, scan, effects=geometric_effects, base=geometric_base, max_frames=max_frames,
                        progress=progress)
    except ValueError as exc:
        return {"verdict": f"image level not run: {exc}", "effects": [], "candidates": []}
    x0 = im.start()
    fitter = ImageFitter(im, x0)
    im.set_weights(x0)
    x, *_ = fitter.fit([])
    im.set_weights(x)
    fitter.start = x
    base = fitter.evaluate([])
    im.set_weights(base["x"])      # weights from the base model, shared by every candidate
    base = fitter.evaluate([])
    cands = image_candidates(im)
    rows, evals = [], {}
    for c in cands:
        e = fitter.evaluate([c])
        evals[c.label] = e
        v = [float(e["x"][ImageModel.PARAMS.index(n)]) for n in c.free]
        sc = score(base, e, c.k)
        sc["above_floor"] = c.big_enough(v)
        sc["claimable"] = sc["claimable"] and sc["above_floor"]
        rows.append({"effect": c.label, "parameters": dict(zip(c.free, v)),
                     "sigma": {n: float(e["sigma"][n]) for n in c.free}, **sc})
    claimed, ambiguous = rank(rows, {k: e["heldout_r2"] for k, e in evals.items()})
    chosen = [claimed[0]["effect"]] if claimed else []
    final = evals[chosen[0]] if chosen else base
    n = base["n"]
    if claimed and final["chi2"] / n - 1 > max(5 * np.sqrt(2 / n), SECOND_EFFECT_EXCESS):
        # one effect leaves chi^2/dof well above 1: try a second, by the same rule
        by = {c.label: c for c in cands}
        best2, gain2 = None, 0.0
        for r in claimed[1:3]:
            e2 = fitter.evaluate([by[chosen[0]], by[r["effect"]]])
            sc = score(final, e2, by[r["effect"]].k)
            c2 = by[r["effect"]]
            v2 = [e2["x"][ImageModel.PARAMS.index(n)] for n in c2.free]
            if sc["claimable"] and c2.big_enough(v2) and sc["heldout_gain_chi2"] > gain2:
                best2, gain2 = (r["effect"], e2), sc["heldout_gain_chi2"]
        if best2 is not None:
            chosen.append(best2[0])
            final = best2[1]
            ambiguous = [a for a in ambiguous if a != best2[0]]
    by = {c.label: c for c in cands}
    found = []
    for label in chosen:
        c = by[label]
        v = np.array([final["x"][ImageModel.PARAMS.index(n)] for n in c.free])
        s = np.array([final["sigma"][n] for n in c.free])
        found.append({"effect": label, "level": "image", "parameters": dict(zip(c.free, v.tolist())),
                      "sigma": dict(zip(c.free, s.tolist())), "statement": c.describe(v, s),
                      "physics": c.build(v).physics})
    verdict = ("the marker shadows match the line-integral model to the noise" if not found else
               " and ".join(f["statement"] for f in found) +
               (f"; not distinguishable here from {', '.join(ambiguous)}" if ambiguous else ""))
    k_base = len(fitter.base_free)
    return {
        "verdict": verdict,
        "effects": found,
        "ambiguous_with": ambiguous,
        "candidates": rows,
        "stated_blur_px": im.stated_blur,
        "base_parameters": {"mu_per_mm": float(base["x"][0]), "shadow_size_change": float(base["x"][1]),
                            "blur_px": float(base["x"][2])},
        "chi2_per_dof_before": base["chi2"] / max(n - k_base, 1),
        "chi2_per_dof_after": final["chi2"] / max(n - k_base - sum(by[c].k for c in chosen), 1),
        "heldout_gain_chi2": float(base["heldout"] - final["heldout"]) if chosen else 0.0,
        "noise_floor_attenuation": im.sigma_air,
        "n_patches": len(im.patches),
        "n_pixels": n,
        "skipped": im.skipped,
        "radial_residual_before": _profile_at(im, base),
        "radial_residual_after": _profile_at(im, final),
    }


def scene_chi2(model, scan, evaluations: dict, *, max_frames: int = 24) -> dict:
    """For geometric candidates the marker positions cannot tell apart: chi^2
    of the recorded shadows rendered from each one's refitted scene (base
    image model), per marker patch that every scene could use (same order)."""
    per = {}
    for label, e in evaluations.items():
        im = ImageModel(model, scan, effects=e["effects"], base=e["x9"], max_frames=max_frames)
        x0 = im.start()
        im.set_weights(x0)
        fitter = ImageFitter(im, x0)
        x, *_ = fitter.fit([])
        im.refine_centres(x, iterations=2)
        x, *_ = fitter.fit([], x0=x)
        per[label] = {(p.frame, p.id): float((((p.recorded - im.predict_patch(p, x)) * p.weight) ** 2).sum())
                      for p in im.patches}
    common = sorted(set.intersection(*(set(v) for v in per.values())))
    return {label: np.array([v[k] for k in common]) for label, v in per.items()}
