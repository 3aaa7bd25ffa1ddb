"""One frame's markers, touching and merged shadows included.

:func:`detect_frame` measures every shadow alone (:mod:`.frame`), then
groups the shadows whose centroid windows meet and measures each again on
the frame with its neighbours' fitted models removed (:mod:`.overlap`), and
splits a blob rejected as elongated into the 2 or 3 spheres whose
attenuation it holds, when a joint fit says so. A shadow flagged clutter is
measured again with a straight background step (a plate's or holder's
edge) fitted beside it and removed. Units: px, attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .frame import Blob, DetectOptions, detect_blobs, refine
from .overlap import fit_group, fit_step, groups_of, render

# the cone-beam shadow's centroid and the model circle's centre differ by
# ~0.02 px; a larger disagreement is the neighbours' models' error
_CONE_OFFSET_PX = 0.03


def detect_frame(a: np.ndarray, opt: DetectOptions) -> list[Blob]:
    """All sphere-like shadows in attenuation frame ``a`` (not yet filtered by
    contrast). Raises :class:`conecal.detect.frame.NonFiniteFrame` on NaN/inf."""
    kept, merged, spoilt, noise, invalid, peaks = detect_blobs(a, opt)
    if not opt.joint_overlaps or not (kept or merged or spoilt):
        return kept
    # a misshapen blob holding two or more candidate peaks is merged shadows
    two = [b for b in spoilt if len(_peaks_in(b, peaks)) >= 2]
    merged = merged + two
    spoilt = [b for b in spoilt if b not in two]
    out = measure_crowded(a, kept, merged, opt, noise, invalid, peaks) if kept or merged else []
    # a misshapen clutter blob is kept only if removing a straight step beside
    # it leaves a clean sphere shadow, away from every marker already found
    for b in spoilt:
        b2 = _beside_step(a, b, opt, noise, invalid)
        if (b2 is not b and b2.anisotropy <= opt.max_anisotropy
                and all(np.hypot(b2.x - o.x, b2.y - o.y) > 0.8 * max(o.radius, b2.radius) for o in out)):
            out.append(b2)
    return out


def _typical(kept: list[Blob], opt: DetectOptions):
    """The frame's sphere radius (px) and contrast (attenuation per px of
    chord, None when no sphere stands alone): from its separate shadows, else
    the nominal size the options were made from."""
    ref = [b for b in kept if not b.flags] or kept
    if ref:
        return float(np.median([b.radius for b in ref])), float(np.median([b.mu_px for b in ref]))
    return float(np.sqrt(opt.diameter_px[0] * opt.diameter_px[1] / 0.96)) / 2, None


def _axis(a: np.ndarray, b: Blob):
    """Principal direction (unit, px) and variance along it of the
    background-subtracted blob around ``b``."""
    rows, cols = a.shape
    r = 2.5 * b.radius + 3
    c0, c1 = int(max(b.x - r, 0)), int(min(b.x + r + 1, cols))
    q0, q1 = int(max(b.y - r, 0)), int(min(b.y + r + 1, rows))
    roi = a[q0:q1, c0:c1].astype(np.float64)
    yy, xx = np.mgrid[q0:q1, c0:c1]
    ring = (xx - b.x) ** 2 + (yy - b.y) ** 2 > (r - 2) ** 2
    w = np.maximum(roi - (np.median(roi[ring]) if ring.any() else 0.0), 0)
    w[w < 0.15 * w.max()] = 0
    V = w.sum()
    if V <= 0:
        return np.array([1.0, 0.0]), 0.0
    mx, my = (w * xx).sum() / V, (w * yy).sum() / V
    C = np.array([[(w * (xx - mx) ** 2).sum(), (w * (xx - mx) * (yy - my)).sum()],
                  [0.0, (w * (yy - my) ** 2).sum()]]) / V
    C[1, 0] = C[0, 1]
    ev, evec = np.linalg.eigh(C)
    return evec[:, 1], float(ev[1])


def _peaks_in(m: Blob, peaks) -> list:
    """Candidate peaks (x, y) inside blob ``m``'s extent."""
    return [p for p in peaks if (p[0] - m.x) ** 2 + (p[1] - m.y) ** 2 < (1.5 * m.radius + 2) ** 2]


def _split(a, m: Blob, R1: float, mu1: float, opt: DetectOptions, noise: float, mask_out, invalid, peaks=()):
    """Spheres (k, 4) a merged blob holds, or None when one sphere (or none)
    explains it as well (BIC) or the parts are not of the frame's spheres.
    Tried: 1, 2 or 3 spheres along the blob's long axis. (Also trying one
    sphere at each candidate peak inside it found 12 % more of an independent
    helix's spheres but made 11 false ones on conecal's own: removed, see
    benchmarks/RESULTS.md.)"""
    # peaks of shadows already measured beside it are theirs, not this blob's
    inside = [p for p in _peaks_in(m, peaks)
              if all((p[0] - ox) ** 2 + (p[1] - oy) ** 2 > (0.8 * orad) ** 2 for ox, oy, orad in mask_out)]
    # not the attenuation of 2 or 3 of the frame's spheres -- unless the
    # top-hat saw as many peaks (spheres of two sizes)
    ratio = m.mu_px * m.radius**3 / (mu1 * R1**3) if mu1 is not None else 2.0
    if not 1.4 <= ratio <= (3.6 if len(inside) < 2 else 3.6 * len(inside)):
        return None
    mu0 = mu1 if mu1 is not None else m.mu_px
    e, var = _axis(a, m)
    spread = var - R1 * R1 / 5 - opt.blur_px**2
    if spread <= 0.25:
        return None
    starts = []
    for k in (1, 2, 3):
        if k == 1:
            pos = [0.0]
        elif k == 2:
            pos = [-np.sqrt(spread), np.sqrt(spread)]
        else:
            d = np.sqrt(1.5 * spread)
            pos = [-d, 0.0, d]
        starts.append(np.array([[m.x + p * e[0], m.y + p * e[1], R1 if k > 1 else m.radius, mu0] for p in pos]))
    best = None
    for s0 in starts:
        k = len(s0)
        fit = fit_group(a, s0, opt.blur_px, noise, mask_out, invalid)
        if fit is None:
            continue
        _, sph, _, _, chi2, n = fit
        bic = chi2 + (4 * k + 3) * np.log(n)
        if best is None or bic < best[0]:
            best = (bic, k, sph)
    if best is None or best[1] == 1:
        return None
    sph = best[2]
    if not (np.all((sph[:, 2] > 0.6 * R1) & (sph[:, 2] < 1.6 * R1))
            and (mu1 is None or np.all((sph[:, 3] > 0.5 * mu1) & (sph[:, 3] < 2.0 * mu1)))):
        return None
    return sph


def measure_crowded(a: np.ndarray, kept: list[Blob], merged: list[Blob], opt: DetectOptions, noise: float,
                    invalid=None, peaks=()) -> list[Blob]:
    """``kept`` with touching shadows re-measured together and merged blobs
    split; each re-measured blob carries the ``overlap`` flag."""
    R1, mu1 = _typical(kept, opt)
    blobs = list(kept)
    for m in merged:
        near = [(b.x, b.y, b.radius) for b in blobs if (b.x - m.x) ** 2 + (b.y - m.y) ** 2 < (6 * m.radius) ** 2]
        sph = _split(a, m, R1, mu1, opt, noise, near, invalid, peaks)
        if sph is None:
            continue
        for x, y, R, mu in sph:
            blobs.append(Blob(float(x), float(y), float(R), 0.0, float(mu), 0.0, 1.0, ["overlap"], 0.0))
    out: list = list(blobs)
    new = set(range(len(kept), len(blobs)))     # split parts: kept only once measured
    for g in groups_of(blobs, opt.blur_px):
        members = [blobs[i] for i in g]
        s0 = np.array([[b.x, b.y, b.radius, b.mu_px] for b in members])
        gx, gy = s0[:, 0].mean(), s0[:, 1].mean()
        reach = np.max(np.hypot(s0[:, 0] - gx, s0[:, 1] - gy) + s0[:, 2]) + 6 * opt.blur_px + 10
        others = [(b.x, b.y, b.radius) for j, b in enumerate(blobs)
                  if j not in g and (b.x - gx) ** 2 + (b.y - gy) ** 2 < (reach + 3 * b.radius) ** 2]
        fit = fit_group(a, s0, opt.blur_px, noise, others, invalid)
        if fit is None:
            continue
        (c0, q0, c1, q1), sph, sig, _, _, _ = fit
        local = sph.copy()
        local[:, 0] -= c0
        local[:, 1] -= q0
        models = [render((q1 - q0, c1 - c0), local[i:i + 1], opt.blur_px) for i in range(len(g))]
        total = np.sum(models, axis=0)
        work = a.copy()
        for n_i, i in enumerate(g):
            work[q0:q1, c0:c1] = a[q0:q1, c0:c1] - (total - models[n_i])
            b = refine(work, sph[n_i, 0], sph[n_i, 1], sph[n_i, 2], opt, others, noise, invalid)
            x_fit, y_fit = sph[n_i, :2]
            # the joint fit treats pixels as independent: correlated noise scales it
            s_fit = float(min(np.hypot(*sig[n_i, :2]) / np.sqrt(2) * np.sqrt(opt.noise_kappa), 1e6))   # px; an
            # undetermined joint fit's sigma can be 1e200, whose square overflows
            if b is None or np.hypot(b.x - x_fit, b.y - y_fit) > 0.5 * sph[n_i, 2]:
                # the centroid cannot be had: the joint model's centre stands
                if not np.isfinite(s_fit) or s_fit > 0.5:
                    out[i] = None if i in new else blobs[i]
                    continue
                b = replace(blobs[i], x=float(x_fit), y=float(y_fit), radius=float(sph[n_i, 2]),
                            mu_px=float(sph[n_i, 3]), sigma=float(np.hypot(s_fit, _CONE_OFFSET_PX)))
            else:
                gap2 = (b.x - x_fit) ** 2 + (b.y - y_fit) ** 2
                excess = max(gap2 / 2 - b.sigma**2 - s_fit**2 - _CONE_OFFSET_PX**2, 0.0)
                b.sigma = float(np.sqrt(b.sigma**2 + excess))
            b.flags = sorted(set(b.flags) | {"overlap"})
            out[i] = b
            new.discard(i)
    out = [b for i, b in enumerate(out) if b is not None and i not in new]
    return [_beside_step(a, b, opt, noise, invalid) if "clutter" in b.flags and "overlap" not in b.flags else b
            for b in out]


def _beside_step(a, b: Blob, opt: DetectOptions, noise: float, invalid) -> Blob:
    """A shadow flagged clutter measured again with a straight background
    step (a plate's edge) fitted and removed, when one is there and the
    centroid then passes the clutter tests; otherwise ``b`` as it was."""
    fit = fit_step(a, b.x, b.y, b.radius, b.mu_px, opt.blur_px, noise, invalid)
    if fit is None:
        return b
    (c0, q0, c1, q1), step, x_fit, y_fit = fit
    work = a.copy()
    work[q0:q1, c0:c1] -= step
    b2 = refine(work, b.x, b.y, b.radius, opt, (), noise, invalid)
    if b2 is None or "clutter" in b2.flags or np.hypot(b2.x - b.x, b2.y - b.y) > b.radius:
        return b
    gap2 = (b2.x - x_fit) ** 2 + (b2.y - y_fit) ** 2
    b2.sigma = float(np.sqrt(b2.sigma**2 + max(gap2 / 2 - b2.sigma**2 - _CONE_OFFSET_PX**2, 0.0)))
    return b2
