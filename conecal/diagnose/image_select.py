"""Image level, the decision: which imaging effect (if any) the recorded
marker shadows show beyond the line-integral model of :mod:`.image`.

Each candidate frees one parameter of that model (blur beyond the stated
one, beam hardening, detector lag, scatter); the choice uses the same
rules as the geometric level (:mod:`.select`): held-out gain and BIC, a
physically possible value not pinned at a bound, a size above what clean
scans show, and a fit that brings chi^2/dof to the noise. Before any of
that, the recorded values must be intensities the model can follow (not
8-bit or coarsely quantised): otherwise the image level says it is not
trusted instead of claiming.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from ..effects.imaging import BeamHardening, Blur, DetectorLag, Scatter
from ..errors import FitError
from ..fit.core import Parameter, solve
from .image import ImageModel
from .image_families import field_candidate, lag_candidate, spot_candidates
from .image_locate import describe as describe_located
from .image_locate import locate_image


@dataclass(frozen=True)
class ImageCandidate:
    label: str
    free: tuple               # names in ImageModel.PARAMS freed by this candidate
    describe: object          # (values, sigmas, model) -> plain words
    build: object             # (values, model) -> Effect
    size: object = None       # values -> the effect's size in the units of ``floor``
    floor: float = 0.0        # the smallest size claimed (see FLOORS)
    impossible: object = None  # values -> why they cannot be physical, or None
    n_extra: int = 0          # parameters beyond ``free`` (a field's coefficients)
    prepare: object = None    # (model, x, train patches or None) -> None: sets per-patch terms before a fit
    state: dict = field(default_factory=dict)   # what ``prepare`` last fitted
    begin: object = None      # (parameter vector, model) -> a start for this candidate (a kernel fitted from 0 cannot move)

    @property
    def k(self) -> int:
        return len(self.free) + self.n_extra

    @property
    def family_key(self) -> str:
        return self.label.split(":")[0]

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
                                  lambda v: np.sqrt(abs(v[0] ** 2 - nom ** 2)), FLOORS["blur"],
                                  lambda v, nom=nom: (f"edges sharper than the stated blur {nom:.3f} px (blur in "
                                                      "quadrature < 0)") if v[0] < nom else None))
    out.append(ImageCandidate("beam_hardening", ("beam_hardening",),
                              lambda v, s: f"attenuation grows less than path length: beta {v[0]:.4f} ± {s[0]:.4f} "
                                           f"(a chord of attenuation 1 reads {1 / (1 + v[0]):.3f})",
                              lambda v: BeamHardening(float(v[0])), lambda v: v[0], FLOORS["beam_hardening"],
                              lambda v: "beam hardening cannot make attenuation grow faster than path length "
                                        "(beta < 0)" if v[0] < 0 else None))
    out.append(ImageCandidate("detector_lag", ("lag",),
                              lambda v, s: f"each frame keeps {100 * v[0]:.2f} ± {100 * s[0]:.2f} % of the previous "
                                           "one (a ghost of the previous marker positions; it pulls detected "
                                           f"centres back: re-run `conecal detect --lag {v[0]:.4f}`)",
                              lambda v: DetectorLag(float(v[0])), lambda v: v[0], FLOORS["detector_lag"],
                              lambda v: "a detector cannot keep a negative fraction of a frame (lag < 0)"
                              if v[0] < 0 else None))
    out.append(ImageCandidate("scatter", ("scatter",),
                              lambda v, s: f"an intensity of {100 * v[0]:.2f} ± {100 * s[0]:.2f} % of the open beam is "
                                           "added everywhere (scatter or a dark-offset error)",
                              lambda v: Scatter(float(v[0])), lambda v: v[0], FLOORS["scatter"],
                              lambda v: "scattered intensity cannot be negative (scatter < 0)" if v[0] < 0 else None))
    return out


BOUNDS = {"mu": (1e-6, np.inf), "size": (-0.2, 0.2), "blur": (0.0, 3.0), "beam_hardening": (-0.5, 3.0), "lag": (-0.5, 0.95),
          "scatter": (-0.5, 2.0), "spot": (0.0, 15.0), "spot_gauss": (0.0, 8.0), "lag_decay": (0.0, 0.95)}
SCALES = {"mu": 0.01, "size": 0.001, "blur": 0.05, "beam_hardening": 0.01, "lag": 0.01, "scatter": 0.005,
          "spot": 0.1, "spot_gauss": 0.05, "lag_decay": 0.05}


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
        params = [Parameter(n, v, lower=a, upper=b, scale=SCALES[n]) for n, v, a, b in zip(names, z0, lo, hi)]

        def residuals(z):
            return self.im.residuals(full(z), select)

        def jacobian(z):
            # forward differences: a few parameters over millions of pixels, each column one model evaluation
            r = residuals(z)
            J = np.empty((r.size, len(z)))
            for j in range(len(z)):
                h = 1e-4 * max(abs(z[j]), 1.0) * (1 if z[j] + 1e-4 * max(abs(z[j]), 1.0) <= hi[j] else -1)
                zj = z.copy()
                zj[j] += h
                J[:, j] = (residuals(zj) - r) / h
            return J

        # Levenberg-Marquardt on the normal equations: scipy's trust region took an SVD of the
        # (pixels x parameters) Jacobian per step, a third of the image level's time
        res = solve(params, residuals, jacobian, max_nfev=60, tol=1e-8, large=True)
        chi2 = float(res.chi2)
        dof = max(len(res.residuals) - len(z0), 1)
        sig = res.sigma * np.sqrt(max(chi2 / dof, 1.0))
        return full(res.x), dict(zip(names, sig)), chi2, len(res.residuals)

    def evaluate(self, cands) -> dict:
        """Fit, re-centre every shadow under this model (an effect such as
        lag moves what the base model takes for the centre), fit again, and
        score on held-out frames (even against odd frame order)."""
        self.im.place(self.placement)
        hooks = [c.prepare for c in cands if c.prepare is not None]

        def prepare(x, train=None):
            for p in self.im.patches:
                p.extra_scatter = 0.0
            for h in hooks:
                h(self.im, x, train)

        prepare(self.start)
        x0 = self.start.copy()
        for c in cands:
            if c.begin is not None:
                x0 = c.begin(x0, self.im)
        x, *_ = self.fit(cands, x0=x0)
        for _ in range(3):     # lag's ghost: three passes take 5 % to 4.94 %, two to 4.87 %
            self.im.refine_centres(x, iterations=1)
            prepare(x)
            x, sig, chi2, n = self.fit(cands, x0=x)
        k = len(self.base_free) + sum(c.k for c in cands)
        fitted = self.im.placement()
        parity = np.array([p.parity for p in self.im.patches])
        r2 = np.zeros(len(parity))     # held-out chi^2 per patch
        for train in (parity == 0, parity == 1):
            if train.all() or not train.any():
                raise ValueError("held-out frames need both even and odd frames")
            prepare(x, train)
            xt, *_ = self.fit(cands, train, x0=x)
            for i in np.flatnonzero(~train):
                p = self.im.patches[i]
                r = (p.recorded - self.im.predict_patch(p, xt)) * p.weight
                r2[i] = float((r * r).sum())
            self.im.place(fitted)
        prepare(x)
        extras = [p.extra_scatter for p in self.im.patches]
        states = {c.label: dict(c.state) for c in cands if c.prepare is not None}
        for p in self.im.patches:
            p.extra_scatter = 0.0
        return {"extras": extras, "states": states, "cands": cands, "x": x, "sigma": sig, "chi2": chi2, "n": n, "bic": chi2 + k * np.log(n),
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


def _at(im, e) -> None:
    """Put the image model in the state of evaluation ``e``: its shadow placement and per-patch terms."""
    im.place(e["placement"])
    for p, s in zip(im.patches, e["extras"]):
        p.extra_scatter = s


def _profile_at(im, e):
    _at(im, e)
    return radial_profile(im, e["x"])


def diagnose_image(model, scan, *, geometric_effects=(), geometric_base=None, max_frames: int = 48,
                   progress=None) -> dict:
    """The image-level decision: which imaging effect (if any) the recorded
    marker shadows show beyond the line-integral model (and beyond what the
    geometric level found: a detector distortion it claimed is rendered).
    Returns a JSON-ready dict."""
    try:
        im = ImageModel(model, scan, effects=geometric_effects, base=geometric_base, max_frames=max_frames,
                        progress=progress)
    except ValueError as exc:
        return {"verdict": f"image level not run: {exc}", "effects": [], "candidates": [], "status": "not run"}
    why = untrusted_values(im)
    if why:
        return {"verdict": f"image level not trusted: {why}; no image effect is claimed", "effects": [],
                "candidates": [], "status": "not trusted", "reason": why, "n_patches": len(im.patches),
                "skipped": im.skipped, "noise_floor_attenuation": im.sigma_air, "value_step": im.value_step,
                "stored_dtype": im.stored_dtype}
    try:
        wide = _wide_margin(im)
        if wide > im.margin_px:
            # a blur of several px reaches past the background ring: move the ring out beyond it
            im = ImageModel(model, scan, effects=geometric_effects, base=geometric_base, max_frames=max_frames,
                            margin_px=wide)
        return _decide(im)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError, FitError) as exc:
        # never an internal error on a recording the line-integral model cannot follow
        return {"verdict": f"image level not run: its fit failed on these images ({type(exc).__name__}: {exc})",
                "effects": [], "candidates": [], "status": "failed", "n_patches": len(im.patches),
                "skipped": im.skipped}


# The image level models intensities; values quantised in steps above this
# fraction of the noise (8-bit, JPEG) carry no trustworthy intensity shape.
MAX_VALUE_STEP = 0.5


def untrusted_values(im: ImageModel) -> str | None:
    """Why the recorded values cannot be modelled as line integrals, or None:
    integers of 8 bits or less, or values in steps coarser than the noise."""
    if np.dtype(im.stored_dtype).kind in "iu" and np.dtype(im.stored_dtype).itemsize == 1:
        return f"the projections are {im.stored_dtype} (256 levels at most), not measured intensities"
    if im.value_step > MAX_VALUE_STEP * im.sigma_air:
        return (f"the recorded values come in steps of {im.value_step:.4g}, {im.value_step / im.sigma_air:.1f}x "
                "their noise (quantised or compressed images)")
    return None


def _decide(im: ImageModel) -> dict:
    from .ranking import choose_members, not_worse, paired_behind
    from .select import ADEQUATE_RMS, rank, score

    x0 = im.start()
    fitter = ImageFitter(im, x0)
    im.set_weights(x0)
    x, *_ = fitter.fit([])
    im.set_weights(x)
    fitter.start = x
    base = fitter.evaluate([])
    im.set_weights(base["x"])      # weights from the base model, shared by every candidate
    base = fitter.evaluate([])
    _at(im, base)
    loc0 = locate_image(im, base["x"])
    cands = image_candidates(im) + _flexible(im, base["x"], loc0["located"])
    rows, evals = [], {}
    for c in cands:
        e = fitter.evaluate([c])
        evals[c.label] = e
        v = [float(e["x"][ImageModel.PARAMS.index(n)]) for n in c.free]
        if c.prepare is not None:
            c.state.clear()
            c.state.update(e["states"][c.label])
        sc = score(base, e, c.k)
        sc["above_floor"] = c.big_enough(v)
        sc["claimable"] = sc["claimable"] and sc["above_floor"]
        why = _unphysical(c, v)
        if why:
            sc.update(claimable=False, impossible=why)
        rows.append({"effect": c.label, "parameters": dict(zip(c.free, v)),
                     "sigma": {n: float(e["sigma"][n]) for n in c.free}, **sc,
                     **({"field": dict(c.state)} if c.prepare is not None else {})})
    choose_members(rows, cands, evals)
    claimed, ambiguous = rank(rows, {k: e["heldout_r2"] for k, e in evals.items()})
    chosen = [claimed[0]["effect"]] if claimed else []
    by = {c.label: c for c in cands}
    if chosen:
        # a member of the same family with as many parameters that held-out data cannot tell from the one
        # chosen (a detector's blur and a Gaussian focal spot on a scan of one magnification): ambiguous
        for r in rows:
            c, top = by[r["effect"]], by[chosen[0]]
            if (r["effect"] != top.label and c.family_key == top.family_key and c.k == top.k and r.get("not_chosen")
                    and not r.get("degenerate") and not r.get("impossible") and r["above_floor"]
                    and not_worse(*paired_behind(evals[c.label]["heldout_r2"], evals[top.label]["heldout_r2"]))):
                ambiguous.append(r["effect"])
    final = evals[chosen[0]] if chosen else base
    n = base["n"]
    if claimed and final["chi2"] / n - 1 > max(5 * np.sqrt(2 / n), SECOND_EFFECT_EXCESS):
        # one effect leaves chi^2/dof well above 1: try a second, by the same rule
        by = {c.label: c for c in cands}
        best2, gain2 = None, 0.0
        others = [r for r in claimed[1:] if _family(r["effect"]) != _family(chosen[0])]
        for r in others[:2]:
            e2 = fitter.evaluate([by[chosen[0]], by[r["effect"]]])
            sc = score(final, e2, by[r["effect"]].k)
            c2 = by[r["effect"]]
            v2 = [e2["x"][ImageModel.PARAMS.index(n)] for n in c2.free]
            if (sc["claimable"] and c2.big_enough(v2) and not _unphysical(c2, v2)
                    and sc["heldout_gain_chi2"] > gain2):
                best2, gain2 = (r["effect"], e2), sc["heldout_gain_chi2"]
        if best2 is not None:
            chosen.append(best2[0])
            final = best2[1]
            ambiguous = [a for a in ambiguous if a != best2[0]]
    by = {c.label: c for c in cands}
    found = []
    for label in chosen:
        c = by[label]
        if c.prepare is not None:
            c.state.clear()
            c.state.update(final["states"][label])
        v = np.array([final["x"][ImageModel.PARAMS.index(n)] for n in c.free])
        s = np.array([final["sigma"][n] for n in c.free])
        found.append({"effect": label, "level": "image", "parameters": dict(zip(c.free, v.tolist())),
                      "sigma": dict(zip(c.free, s.tolist())), "statement": c.describe(v, s),
                      "physics": c.build(v).physics, **({"field": dict(c.state)} if c.prepare is not None else {})})
    k_base = len(fitter.base_free)
    before = base["chi2"] / max(n - k_base, 1)
    after = final["chi2"] / max(n - k_base - sum(by[c].k for c in chosen), 1)
    # what the chosen model still leaves: the same tests as before any naming
    _at(im, final)
    remaining = locate_image(im, final["x"])["located"] if chosen else loc0["located"]
    partial = []
    if found and (after > ADEQUATE_RMS ** 2 or remaining):
        # the claim must bring the shadows to the noise and leave no structure
        partial, found = found, []
    where = "; ".join(describe_located(it) for it in (remaining or loc0["located"])[:3])
    if found:
        verdict = (" and ".join(f["statement"] for f in found) +
                   (f"; not distinguishable here from {', '.join(ambiguous)}" if ambiguous else ""))
    elif partial:
        verdict = (f"located, not named: the marker shadows differ from the line-integral model (chi^2/dof "
                   f"{before:.2f}); {' and '.join(p['effect'] for p in partial)} explains part of it "
                   f"(-> {after:.2f}) but leaves: {where or 'chi^2 above the noise'}; not claimed")
    elif loc0["located"] or before > ADEQUATE_RMS ** 2:
        verdict = (f"located, not named: the marker shadows differ from the line-integral model (chi^2/dof "
                   f"{before:.2f}): {where or 'no structure the tests name'}; no imaging effect of the library "
                   "explains it")
    else:
        verdict = "the marker shadows match the line-integral model to the noise"
    return {
        "verdict": verdict,
        "effects": found,
        "partial": partial,
        "status": "claimed" if found else "located" if (partial or loc0["located"] or before > ADEQUATE_RMS ** 2)
        else "clean",
        "located": loc0["located"],
        "remaining": remaining if chosen else [],
        "ambiguous_with": ambiguous if found else [],
        "candidates": rows,
        "stated_blur_px": im.stated_blur,
        "value_step": im.value_step,
        "stored_dtype": im.stored_dtype,
        "base_parameters": {"mu_per_mm": float(base["x"][0]), "shadow_size_change": float(base["x"][1]),
                            "blur_px": float(base["x"][2])},
        "chi2_per_dof_before": before,
        "chi2_per_dof_after": after,
        "heldout_gain_chi2": float(base["heldout"] - final["heldout"]) if chosen else 0.0,
        "noise_floor_attenuation": im.sigma_air,
        "n_patches": len(im.patches),
        "n_pixels": n,
        "skipped": im.skipped,
        "background_margin_px": im.margin_px,
        "radial_residual_before": _profile_at(im, base),
        "radial_residual_after": _profile_at(im, final),
    }


def _wide_margin(im: ImageModel) -> int:
    """px between the modelled shadows and the background ring that the
    base model's blur asks for: 3, or 2.5 blur sigmas beyond it when the
    blur is wider than 1 px (a focal spot's disc of radius R reads as a
    sigma of about R / 2)."""
    if im.stated_blur is not None:
        blur = im.stated_blur
    else:
        x0 = im.start()
        im.set_weights(x0)
        blur = float(ImageFitter(im, x0).fit([])[0][ImageModel.PARAMS.index("blur")])
    return 3 + int(np.ceil(2.5 * blur)) if blur > 1.0 else 3


def _family(label: str) -> str:
    return label.split(":")[0]


def _flexible(im, x, located) -> list:
    """The flexible members the located structure asks for: a focal spot where
    the edges differ (or follow magnification), a scatter field where the
    shadows' depth follows the detector position."""
    out = []
    edge = any(it["curve"] == "edge" or (it["curve"] == "residual" and it["variable"] == "radius") for it in located)
    field = any(it["curve"] in ("scatter", "gain") and "detector position" in (it["variable"], *it["also_follows"])
                for it in located if it["curve"] != "residual")
    if edge:
        out += spot_candidates(im, ImageCandidate)
    if any(it["curve"] == "ghost" for it in located):
        out.append(lag_candidate(ImageCandidate, FLOORS["detector_lag"]))
    if field:
        c = field_candidate(im, x, ImageCandidate)
        out += [c] if c is not None else []
    return out


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


def _unphysical(c: ImageCandidate, v) -> str | None:
    """Why a candidate's fitted values cannot be claimed: impossible physics,
    or pinned at the fit's bound (reported, never claimed)."""
    v = np.asarray(v, float)
    if c.impossible is not None:
        why = c.impossible(v)
        if why:
            return why
    for name, x in zip(c.free, v):
        lo, hi = BOUNDS[name]
        if x <= lo + 1e-6 * max(1.0, abs(lo)) or x >= hi - 1e-6 * max(1.0, abs(hi)):
            return f"{name} {x:.4g} is pinned at its bound"
    return None
