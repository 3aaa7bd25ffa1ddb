"""Image level: re-simulate every marker's shadow from the fitted scene and
compare it, pixel by pixel, with the recorded frame.

For each observation the sphere is placed (fitted geometry and motion, then
moved parallel to the detector so that its shadow sits where ``detect``
found it, then refined to 1e-3 px on the image) and its chord-length image
is rendered with ``simulate``'s renderer. The recorded attenuation of a
patch around it is modelled as

    A = b - ln(T + s' (1 - T)),
    T = (1 - lag r) G_sigma[exp(-(H(b0 + mu L) - b))] + lag T_prev

(with a lag decaying over frames, frame k back adds ``lag decay^(k-1)`` of its
own recorded transmission, k = 1..3)

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

from ..effects.imaging import beam_hardened, unhardened
from ..simulate.render import Sphere, render_line_integrals
from ..stats import mad_sigma

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
    m1: float = 0.0               # the sphere's magnification minus 1 (a focal spot's blur grows with it)
    spot_scale: float = 1.0       # m1 over the scan's mean m1
    extra_scatter: float = 0.0    # scatter fraction of the background added to this patch alone (a field)
    earlier: list = None          # [(transmission, background ratio)] of the frames 2 and 3 back, as ``previous``


def _kernel(sigma: float) -> np.ndarray:
    h = max(KERNEL_RADIUS, int(np.ceil(3.5 * sigma)))
    x = np.arange(-h, h + 1, dtype=float)
    if sigma < 1e-3:
        k = (x == 0).astype(float)
    else:
        k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def disc_kernel(radius: float) -> np.ndarray:
    """A uniform disc of ``radius`` px (a focal spot seen through a sphere),
    each pixel weighted by the part of it inside the disc, approximated by a
    one-pixel ramp across the rim so that the kernel changes smoothly with
    the radius (the fit differentiates it numerically). Sums to 1."""
    h = int(np.ceil(radius)) + 1
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    k = np.clip(radius + 0.5 - np.hypot(xx, yy), 0.0, 1.0)
    return k / k.sum()


def _quantum(A, mask) -> float:
    """The smallest positive step between the values recorded in a patch's
    background: 0 for continuous values, the quantisation step of an 8-bit
    or JPEG-compressed image."""
    v = np.unique(A[mask])
    d = np.diff(v)
    d = d[d > 0]
    return float(d.min()) if d.size else np.inf


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

    PARAMS = ("mu", "size", "blur", "beam_hardening", "lag", "scatter", "spot", "spot_gauss", "lag_decay")

    def __init__(self, model, scan, *, effects=(), base=None, max_frames: int = 48, progress=None,
                 margin_px: int = 3):
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
        self._levels: list[float] = []      # per patch: the smallest step between recorded values
        self._crops: dict = {}      # box -> (cropped detector, its warp)
        self._start_gradients: dict = {}   # (frame, id, h) -> (lab centre, own_gradient there)
        # px beyond the modelled shadows before the background ring starts: a wide blur needs more
        self.margin_px = int(margin_px)
        self._build(max_frames, progress)
        if not self.patches:
            raise ValueError("no marker patch is usable at the image level")
        self.mean_m1 = float(np.mean([p.m1 for p in self.patches]))
        for p in self.patches:
            p.spot_scale = p.m1 / self.mean_m1 if self.mean_m1 > 0 else 1.0
        self.sigma_air = float(np.median([p.sigma_air for p in self.patches]))
        self.value_step = float(np.median(self._levels)) if self._levels else 0.0
        self.stored_dtype = str(scan.stack.read_raw(int(self.patches[0].frame)).dtype)

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
            # the frames two and three back: a lag that decays over several frames leaves their ghosts too
            earlier_rec, r_e = [], r_prev if prev_rec is not None else None
            for _ in range(2):
                r_e = prev_row.get(r_e) if r_e is not None else None
                if r_e is None or r_e not in frame_of_row:
                    break
                earlier_rec.append(self.scan.stack.read(int(frame_of_row[r_e])).astype(float))
            ring = np.ones((2 * self.margin_px + 1,) * 2, np.uint8)
            shadow = cv2.dilate((L > 0).astype(np.uint8), ring) > 0
            if L_prev is not None:
                shadow |= cv2.dilate((L_prev > 0).astype(np.uint8), ring) > 0
            for j, i_obs in enumerate(idx):
                xy = o.xy[i_obs]
                rpx = float(radii[j] * g.magnification(X[j]) / g.pixel_pitch[0])
                half = rpx + blur_pad + self.margin_px
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
                if not np.isfinite(A).all() or (prev_rec is not None and not np.isfinite(prev_rec[sl]).all()):
                    self.skipped["non-finite pixels"] = self.skipped.get("non-finite pixels", 0) + 1
                    continue
                self._levels.append(_quantum(A, bg_mask))
                b = _background(A, bg_mask)
                resid = (A - b)[bg_mask]
                sig = max(float(mad_sigma(resid)), SIGMA_FLOOR)
                # structure the model cannot explain (clutter, another object) in the background
                if np.mean(np.abs(resid) > 5 * sig) > 0.02:
                    self.skipped["clutter in the background"] = self.skipped.get("clutter in the background", 0) + 1
                    continue
                prev, prev_bg = None, None
                if prev_rec is not None:
                    # bg_mask is clear of the previous frame's shadows too
                    prev = np.exp(-(prev_rec[sl] - b))
                    prev_bg = np.exp(b - _background(prev_rec[sl], bg_mask))
                earlier = [(np.exp(-(e[sl] - b)), np.exp(b - _background(e[sl], bg_mask)))
                           for e in earlier_rec if np.isfinite(e[sl]).all()]
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
                                          self._dchord(box, X[j], radii[j], own),
                                          m1=float(g.magnification(X[j]) - 1.0), earlier=earlier))
            if progress:
                progress(n_done + 1, len(chosen))

    # ----------------------------------------------------------- model
    def full(self, theta: dict) -> np.ndarray:
        """Parameter vector (5,) from a partial dict, the rest at their base values."""
        base = {"mu": 1.0, "size": 0.0, "blur": self.stated_blur if self.stated_blur is not None else 0.5,
                "beam_hardening": 0.0, "lag": 0.0, "scatter": 0.0, "spot": 0.0, "spot_gauss": 0.0, "lag_decay": 0.0}
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
        mu, size, blur, beta, lag, s, spot, spot_g, decay = x
        b = p.background
        a = mu * (p.chord + size * p.dchord)
        lin = unhardened(b, beta) + a
        ps = beam_hardened(lin, beta) - b if beta else a
        T = np.exp(-ps)
        # a Gaussian focal spot's blur grows with the sphere's magnification - 1; the detector's does not
        k = _kernel(np.hypot(blur, spot_g * p.spot_scale))
        disc = disc_kernel(abs(spot) * p.spot_scale) if spot else None

        def blurred(img):
            if disc is not None:
                img = cv2.filter2D(img, -1, disc, borderType=cv2.BORDER_REPLICATE)
            return cv2.sepFilter2D(img, -1, k, k, borderType=cv2.BORDER_REPLICATE)

        Tf, gain = blurred(T), 1.0
        if lag and p.previous is not None:
            gain = 1 - lag * p.previous_background
            ghost = lag * p.previous
            if decay:
                # frame k back keeps lag * decay^(k-1) (recorded frames: their own lag is second order)
                for k, (Te, be) in enumerate(p.earlier or (), start=1):
                    c = lag * decay ** k
                    gain = gain - c * be
                    ghost = ghost + c * Te
            Tf = gain * Tf + ghost
        if s or p.extra_scatter:
            # the primary background is exp(-b) - s: the recorded one has the scatter in it
            sp = s * np.exp(b) + p.extra_scatter
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
