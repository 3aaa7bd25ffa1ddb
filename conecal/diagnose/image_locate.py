"""Image level, locate before naming: where the recorded marker shadows
differ from the line-integral model of :mod:`.image`, before any imaging
effect is named, and what is left after one is.

Each patch (one marker shadow in one frame) is given, one at a time, local
freedoms the scan-wide model does not have, each estimated by weighted
least squares on that patch's residual alone, with its σ:

- ``gain``: the shadow reads deeper (+) or shallower (-) than modelled, as a
  fraction of its modelled attenuation;
- ``scatter``: an intensity added under the shadow, as a fraction of the
  background intensity around it;
- ``edge``: edges wider (+) or sharper (-) than modelled, as the Gaussian
  variance added (px², signed);
- ``ghost``: a fraction of the previous frame's recorded transmission
  (detector lag), where there is a previous frame.

Each per-patch curve is tested against its scan-wide mean (what a
one-parameter effect fits) and against the variables a patch carries: its
position on the detector (polynomials of degree 1-3 in u and v), the time
(frame order, degree 1-3) and the sphere's magnification (degree 1: a focal
spot's blur grows with M - 1, a detector's does not). Two profiles of the
residual itself say what shape is left: its mean against the distance from
the shadow centre (in shadow radii: the edge's shape) and against the
modelled attenuation (the value transfer). The profiles' standard errors
come from the spread between patches and the curves' tests are F tests on
their own scatter when it exceeds their σ, so noise correlated within a
patch (a blurred scintillator, JPEG) does not by itself make a structure.
p-values are Holm-adjusted over every test; a located item must also be
larger than ``FLOORS`` (what clean scans from other simulators show).

Units: gain and scatter as fractions, edge in px², ghost as a fraction of
the previous frame; positions in detector px (u along columns, v along
rows); profile sizes in attenuation (-ln I/I0).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2 as chi2_dist
from scipy.stats import f as f_dist

from ..stats import holm, not_worse, paired_behind

CURVES = ("gain", "scatter", "edge", "ghost")
UNITS = {"gain": "fraction of the modelled attenuation", "scatter": "fraction of the background intensity",
         "edge": "px^2 (Gaussian variance added)", "ghost": "fraction of the previous frame"}
WORDS = {"gain": "the shadows read {sense} than modelled", "scatter": "an intensity is added under the shadows",
         "edge": "the shadows' edges are {sense} than modelled", "ghost": "a ghost of the previous frame"}
# what each curve (and each residual profile, by its variable) measures, as a located item's component
COMPONENTS = {"gain": "each shadow's depth (local gain)", "scatter": "an intensity added under the shadows",
              "edge": "each shadow's edge width", "ghost": "a ghost at the previous frame's position",
              "radius": "the shadows' mean edge profile",
              "attenuation": "recorded against modelled attenuation (the value transfer)"}
# Smallest located sizes, about twice what clean scans (conecal's and an independent simulator's) show
# and what a named effect leaves behind when it is the right one. Profiles: in units of the pixel noise
# (0.1 of it carries 1 % of the noise variance; clean scans of an independent simulator read 0.02 and 0.10,
# a claimed blur leaves 0.06). Edge: 0.1 px^2 is 0.04 px of sigma at a 1.25 px blur. The curves' chi^2
# does not size them: a patch's estimate also takes up what else its shadow misses, and their scatter
# exceeds their sigma several-fold.
FLOORS = {"gain": 0.003, "scatter": 0.003, "edge": 0.1, "ghost": 0.003, "radius": 0.1, "attenuation": 0.2}
EDGE_STEP = 0.25     # px^2: the variance step of the edge column
DEGREES = (1, 2, 3)


def _column(im, p, x, name, A):
    """d(modelled attenuation)/d(curve) on patch ``p`` at parameters ``x`` (``A``: the model there), by a finite step."""
    if name == "gain":
        return A - p.background
    y = np.array(x, float)
    if name == "scatter":
        keep = p.extra_scatter
        p.extra_scatter = keep + 0.01
        try:
            return (im.predict_patch(p, y) - A) / 0.01
        finally:
            p.extra_scatter = keep
    if name == "edge":
        i = im.PARAMS.index("blur")
        y[i] = np.sqrt(y[i] ** 2 + EDGE_STEP)
        return (im.predict_patch(p, y) - A) / EDGE_STEP
    i = im.PARAMS.index("lag")
    y[i] += 0.01
    return (im.predict_patch(p, y) - A) / 0.01


def patch_curves(im, x, curves=CURVES) -> dict:
    """Per-patch local estimates of each curve with σ (NaN where a patch
    cannot tell), and the patches' variables."""
    n = len(im.patches)
    est = {c: np.full(n, np.nan) for c in CURVES}
    sig = {c: np.full(n, np.nan) for c in CURVES}
    for i, p in enumerate(im.patches):
        w2 = p.weight ** 2
        A = im.predict_patch(p, x)
        r = p.recorded - A
        for c in curves:
            if c == "ghost" and p.previous is None:
                continue
            col = _column(im, p, x, c, A)
            h = float((w2 * col * col).sum())
            if h <= 0:
                continue
            q = float((w2 * r * col).sum()) / h
            dof = max(r.size - 1, 1)
            # the patch's own excess over its noise (real data: correlated, mis-stated) widens its σ
            red = float((w2 * (r - q * col) ** 2).sum()) / dof
            est[c][i], sig[c][i] = q, np.sqrt(max(red, 1.0) / h)
    g = im.g
    return {"est": est, "sigma": sig,
            "u": np.array([p.centre[0] for p in im.patches]) / g.shape[1] - 0.5,
            "v": np.array([p.centre[1] for p in im.patches]) / g.shape[0] - 0.5,
            "time": _order(np.array([p.frame for p in im.patches], float)),
            "m1": np.array([p.m1 for p in im.patches]), "parity": np.array([p.parity for p in im.patches])}


def _order(t):
    span = np.ptp(t)
    return (t - t.min()) / span - 0.5 if span > 0 else np.zeros_like(t)


def position_basis(u, v, degree: int) -> np.ndarray:
    """Polynomial terms of total degree <= ``degree`` in the normalised detector position."""
    return np.column_stack([u ** i * v ** (d - i) for d in range(degree + 1) for i in range(d + 1)])


def _basis(vals, variable, degree):
    if variable == "detector position":
        return position_basis(vals["u"], vals["v"], degree)
    t = vals[variable] - np.mean(vals[variable]) if variable == "m1" else vals[variable]
    if variable == "m1":
        t = t / (np.ptp(t) or 1.0)
    return np.column_stack([t ** d for d in range(degree + 1)])


def _wls(y, w, B):
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(B * sw[:, None], y * sw, rcond=None)
    r = y - B @ coef
    return coef, float((w * r * r).sum())


def curve_tests(vals: dict) -> list[dict]:
    """Every (curve, variable, shape) test: chi^2 explained, dof, p, and the
    fitted structure's size (RMS over patches, the curve's unit)."""
    tests = []
    for c in CURVES:
        y, s = vals["est"][c], vals["sigma"][c]
        ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
        if ok.sum() < 12:
            continue
        y, w = y[ok], 1.0 / s[ok] ** 2
        sub = {k: vals[k][ok] for k in ("u", "v", "time", "m1")}
        chi0 = float((w * y * y).sum())
        mean = float((w * y).sum() / w.sum())
        chi_c = float((w * (y - mean) ** 2).sum())
        fits = {}
        for var, degs in (("detector position", DEGREES), ("time", DEGREES), ("m1", (1,))):
            if var == "m1" and np.ptp(sub["m1"]) < 1e-6:
                continue
            for d in degs:
                B = _basis(sub, var, d)
                coef, chi = _wls(y, w, B)
                fits[(var, d)] = (B, coef, chi)
        # the residual scale beyond the patches' σ: from the fullest description tried
        full = min((chi for _, _, chi in fits.values()), default=chi_c)
        k_full = max((B.shape[1] for B, _, _ in fits.values()), default=1)
        dof_full = max(len(y) - k_full, 1)
        scale = max(full / dof_full, 1.0)
        tests.append(_test(c, "none", "scan-wide mean", chi0 - chi_c, 1, scale, dof_full, abs(mean), mean))
        for (var, d), (B, coef, chi) in fits.items():
            var_fit = B @ coef - mean
            size = float(np.sqrt(np.mean(var_fit ** 2)))
            t = _test(c, var, f"degree {d}" if var != "detector position" else f"degree {d} in (u, v)",
                      chi_c - chi, B.shape[1] - 1, scale, dof_full, size, mean)
            fitted = B @ coef
            lo, hi = int(np.argmin(fitted)), int(np.argmax(fitted))
            t["range"] = [float(fitted[lo]), float(fitted[hi])]
            if var == "detector position":
                # where on the detector (fractions of its width and height) the curve is lowest and highest
                t["range_at"] = [[float(sub["u"][j] + 0.5), float(sub["v"][j] + 0.5)] for j in (lo, hi)]
            tests.append(t)
    return tests


def _test(curve, variable, shape, dchi, k, scale, dof_full, size, mean):
    dchi = max(float(dchi), 0.0)
    p = (float(f_dist.sf(dchi / k / scale, k, dof_full)) if scale > 1.0
         else float(chi2_dist.sf(dchi, k)))
    return {"curve": curve, "variable": variable, "shape": shape, "chi2": dchi, "dof": int(k), "p": p,
            "scale": float(scale),
            "size": float(size), "mean": float(mean), "unit": UNITS[curve]}


def profile(im, x, variable: str, bins: int = 16) -> dict:
    """Mean residual (recorded - modelled attenuation) per bin of ``variable``
    (``radius``: distance from the shadow centre in shadow radii, 0-2;
    ``attenuation``: the modelled attenuation above the background), each
    patch counted once per bin; standard errors from the spread between patches."""
    per = []
    preds = [im.predict_patch(p, x) for p in im.patches]
    if variable == "radius":
        edges = np.linspace(0, 2, bins + 1)
    else:
        top = np.percentile(np.concatenate([(A - p.background).ravel() for p, A in zip(im.patches, preds)]), 99.9)
        edges = np.linspace(0.02 * top, top, bins + 1)
    for p, A in zip(im.patches, preds):
        r = (p.recorded - A).ravel()
        if variable == "radius":
            yy, xx = np.mgrid[p.box[0]:p.box[1], p.box[2]:p.box[3]]
            key = (np.hypot(xx - p.centre[0], yy - p.centre[1]) / p.radius_px).ravel()
        else:
            key = (A - p.background).ravel()
        k = np.digitize(key, edges) - 1
        ok = (k >= 0) & (k < bins)
        s = np.bincount(k[ok], r[ok], bins)
        n = np.bincount(k[ok], None, bins)
        per.append(np.where(n > 0, s / np.maximum(n, 1), np.nan))
    P = np.array(per)
    cnt = np.sum(np.isfinite(P), axis=0)
    mean = np.nansum(P, axis=0) / np.maximum(cnt, 1)
    se = np.sqrt(np.nansum((P - mean) ** 2, axis=0) / np.maximum(cnt - 1, 1) / np.maximum(cnt, 1))
    ok = (cnt >= 8) & (se > 0)
    chi = float(np.sum((mean[ok] / se[ok]) ** 2))
    return {"variable": variable, "centres": (0.5 * (edges[1:] + edges[:-1])).tolist(), "mean": mean.tolist(),
            "stderr": se.tolist(), "chi2": chi, "dof": int(ok.sum()),
            "p": float(chi2_dist.sf(chi, max(int(ok.sum()), 1))),
            "size": float(np.sqrt(np.mean(mean[ok] ** 2))) if ok.any() else 0.0}


def locate_image(im, x, alpha: float = 0.01) -> dict:
    """Located mismatches of the image model at parameters ``x``: the
    per-patch curves' significant structures (Holm over every test, above
    ``FLOORS``), best first, and the two residual profiles. JSON-ready."""
    vals = patch_curves(im, x)
    tests = curve_tests(vals)
    profs = [profile(im, x, "radius"), profile(im, x, "attenuation")]
    allp = [t["p"] for t in tests] + [pr["p"] for pr in profs]
    adj = holm(allp)
    for t, a in zip(tests + profs, adj):
        t["p_adjusted"] = float(a)
    noise = float(im.sigma_air)
    located = []
    for c in CURVES:
        sig = [t for t in tests if t["curve"] == c and t["p_adjusted"] < alpha and t["size"] >= FLOORS[c]]
        if not sig:
            continue
        # the mean first (a one-parameter effect), then the description with the best AIC
        sig.sort(key=lambda t: (t["variable"] != "none", -(t["chi2"] / t["scale"] - 2 * t["dof"])))
        best = sig[0]
        item = dict(best, level="image", also_follows=sorted({t["variable"] for t in sig[1:]} - {best["variable"]}))
        located.append(item)
    for pr in profs:
        if pr["p_adjusted"] < alpha and pr["size"] >= FLOORS[pr["variable"]] * noise:
            located.append({"level": "image", "curve": "residual", "variable": pr["variable"],
                            "shape": "profile", "size": pr["size"], "unit": "attenuation", "p": pr["p"],
                            "p_adjusted": pr["p_adjusted"], "size_in_noise": pr["size"] / noise})
    located.sort(key=lambda t: -t["chi2"] if "chi2" in t else 0.0)
    return {"located": located, "tests": tests, "profiles": profs, "curves": vals}


def describe(item: dict) -> str:
    """One located image item in plain words."""
    if item["curve"] == "residual":
        what = ("the shadows' edge profile" if item["variable"] == "radius"
                else "the recorded attenuation against the modelled one (the value transfer)")
        return f"{what} differs from the model by {item['size']:.4f} RMS ({item['size_in_noise']:.2f}x the pixel noise)"
    c = item["curve"]
    sense = ""
    if c == "gain":
        sense = "deeper" if item["mean"] > 0 else "shallower"
    if c == "edge":
        sense = "wider" if item["mean"] > 0 else "sharper"
    head = WORDS[c].format(sense=sense)
    if item["variable"] == "none":
        return f"{head}: {item['mean']:+.4f} ({item['unit']}) over the scan"
    lo, hi = item.get("range", (np.nan, np.nan))
    where = f", from {lo:+.4f} to {hi:+.4f}"
    if "range_at" in item:
        (ul, vl), (uh, vh) = item["range_at"]
        where += (f" (lowest near u={ul:.2f}, v={vl:.2f}, highest near u={uh:.2f}, v={vh:.2f} of the detector's "
                  "width and height)")
    var = {"m1": "the sphere's magnification", "time": "time"}.get(item["variable"], item["variable"])
    return f"{head}, following {var} ({item['shape']}): {item['size']:.4f} RMS ({item['unit']}){where}"


FIELD_ORDERS = (0, 2, 3, 4, 5, 6)   # 0: a constant; g: a g x g grid of Gaussian bumps over the patches


def field_basis(u, v, order: int) -> np.ndarray:
    """A smooth field over the detector: a constant plus, for ``order`` g >= 2,
    g x g Gaussian bumps on a grid spanning the patches (as wide as the grid
    spacing). Scatter is broad but not a polynomial: a bump a third of the
    detector wide needs degree 7 as a polynomial."""
    cols = [np.ones_like(u)]
    if order >= 2:
        gu, gv = np.linspace(u.min(), u.max(), order), np.linspace(v.min(), v.max(), order)
        w2 = 2 * max(gu[1] - gu[0], gv[1] - gv[0], 1e-3) ** 2
        cols += [np.exp(-((u - a) ** 2 + (v - b) ** 2) / w2) for a in gu for b in gv]
    return np.column_stack(cols)


def fit_field(vals: dict, order: int, train=None):
    """The per-patch scatter estimates as a smooth field over the detector
    (:func:`field_basis` of ``order``), fitted on ``train`` patches with a
    small ridge on the bumps (a bump no training patch sees stays near 0);
    returns the field at every patch and its coefficients."""
    y, s = vals["est"]["scatter"], vals["sigma"]["scatter"]
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    if train is not None:
        ok &= train
    B = field_basis(vals["u"], vals["v"], order)
    w = 1.0 / s[ok] ** 2
    Bw = B[ok] * w[:, None]
    H = B[ok].T @ Bw
    ridge = 1e-6 * np.trace(H) / max(len(H), 1) * np.eye(len(H))
    ridge[0, 0] = 0.0
    coef = np.linalg.solve(H + ridge, Bw.T @ y[ok])
    return B @ coef, coef


def field_degree(vals: dict) -> tuple[int, dict]:
    """The field's order chosen on held-out patches (fit on even frames,
    predict odd, and back): the lowest within 2 standard errors of the best."""
    y, s = vals["est"]["scatter"], vals["sigma"]["scatter"]
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    per = {}
    for d in FIELD_ORDERS:
        r2 = np.zeros(len(y))
        for train in (vals["parity"] == 0, vals["parity"] == 1):
            f, _ = fit_field(vals, d, train)
            test = ok & ~train
            r2[test] = ((y[test] - f[test]) / s[test]) ** 2
        per[d] = r2[ok]
    best = min(per, key=lambda d: per[d].sum())
    for d in sorted(per):
        if not_worse(*paired_behind(per[d], per[best])):
            return d, {k: float(v.sum()) for k, v in per.items()}
    return best, {k: float(v.sum()) for k, v in per.items()}
