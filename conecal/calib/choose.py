"""Which detector distortion the data support: leave-markers-out.

Every identified centre is put in one of ``folds`` groups at random (a
fixed seed). Each family is fitted without one group at a time (poses,
intrinsics and distortion, started from the full fit) and predicts the
group it did not see; the score is the sum of whitened squared held-out
residuals. The family with the lowest score wins, except that the most
specific family (fewest parameters) whose paired held-out difference to
it is within max(3, two standard errors) is chosen instead: a flexible
field earns its place only by predicting markers it was not fitted on.
The standard error is taken over frames (each frame's summed difference),
not markers: a gain one or two frames make is no gain for the detector
(an independent generator's undistorted biplane: two wrongly named frames,
fitted by their own twists, made a per-frame twist win over the pinhole
at 0.088 against 0.207 px held-out, marker by marker; frame by frame it
does not, the pinhole is chosen and the two frames are rejected).
"""

from __future__ import annotations

import numpy as np

from ..errors import FitError
from ..stats import mostly_behind, not_worse, paired_behind
from .bundle import FAMILIES, Bundle, Family, Observations, adjust


def n_params(f: Family, n_frames: int) -> int:
    return f.k + f.k_frame * n_frames


def heldout_scores(family: Family, full: Bundle, obs: Observations, points, radius, folds: np.ndarray,
                   sigma_eff: np.ndarray) -> np.ndarray:
    """Per-observation held-out squared residual (whitened by ``sigma_eff``)."""
    r2 = np.full(len(obs), np.nan)
    F = len(full.R)
    for g in np.unique(folds):
        test = folds == g
        train = obs.subset(~test)
        if len(np.unique(train.slot)) < F:
            continue
        try:
            b = adjust(family, full.camera, train, points, radius, full.R, full.t, start=full, passes=1, max_nfev=30,
                       covariance=False)
        except FitError:
            # (more parameters than a fold leaves markers, as on a scan of a few
            # frames: the family is not tested, and so not chosen; a whole
            # calibration of 3 frames failed on a fold of its richest family)
            continue
        pred = b.predict(b.phantom(points)[obs.sph[test]], obs.slot[test], radius)
        r2[test] = np.sum((pred - obs.xy[test]) ** 2, 1) / sigma_eff[test] ** 2
    return r2


def _folds(n: int, n_folds: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, n_folds, n)


def _noise(fits, n: int) -> np.ndarray:
    """One noise scale (px per axis) for all candidates: the most flexible fit's residuals."""
    flexible = min(fits, key=lambda b: float(np.mean(np.sum(b.residual_px ** 2, 1))))
    return np.full(n, max(float(np.sqrt(np.mean(np.sum(flexible.residual_px ** 2, 1)) / 2)), 1e-3))


def paired_heldout(a: Bundle, b: Bundle, obs: Observations, points, radius, n_folds: int = 5,
                   seed: int = 0) -> dict:
    """Two fits of the same markers compared on held-out markers (the folds
    ``choose_family`` uses, one noise scale): ``gain`` is the held-out
    chi-square ``a`` loses to ``b`` (> 0: b predicts better), with its
    standard error, and each one's held-out RMS (px)."""
    folds = _folds(len(obs), n_folds, seed)
    sig = _noise((a, b), len(obs))
    sa = heldout_scores(a.family, a, obs, points, radius, folds, sig)
    sb = heldout_scores(b.family, b, obs, points, radius, folds, sig)
    ok = np.isfinite(sa) & np.isfinite(sb)
    gain, se = paired_behind(sa[ok], sb[ok])
    rms = lambda s: float(np.sqrt(np.nanmean(s) / 2) * sig[0])  # noqa: E731
    return {"gain": gain, "se": se, "rms_a": rms(sa), "rms_b": rms(sb), "chi2_b": float(sb[ok].sum()),
            "n": int(ok.sum())}


def beats(p: dict) -> bool:
    """``b`` beats ``a`` as a flexible family must: held-out markers can tell ``a`` is worse."""
    return p["n"] > 0 and not not_worse(p["gain"], p["se"])


def choose_refinement(plain: Bundle, refined: Bundle, obs: Observations, points, radius, n_folds: int = 5,
                      seed: int = 0) -> tuple[bool, dict]:
    """Whether the phantom refined (``refined``: each sphere's offset from its
    CAD position fitted) predicts held-out markers better than the CAD as given
    (``plain``). Returns the verdict and a row for the document."""
    p = paired_heldout(plain, refined, obs, points, radius, n_folds, seed)
    chosen = beats(p)
    return chosen, {"prior_sigma_mm": refined.points_sigma, "heldout_rms_px_cad": p["rms_a"],
                    "heldout_rms_px_refined": p["rms_b"], "gain_chi2": p["gain"], "gain_se": p["se"],
                    "chosen": chosen}


def choose_family(fits: dict, obs: Observations, points, radius, n_folds: int = 5, seed: int = 0,
                  families=FAMILIES, progress=None) -> tuple[Family, list[dict]]:
    """``fits``: family name -> its bundle on all of ``obs``. Returns the chosen
    family and one row per family (name, parameters, held-out score, chosen,
    why)."""
    folds = _folds(len(obs), n_folds, seed)
    n_frames = len(next(iter(fits.values())).R)
    sig = _noise(fits.values(), len(obs))
    scores = {}
    for i, f in enumerate(families):
        if f.name not in fits:
            continue
        scores[f.name] = heldout_scores(f, fits[f.name], obs, points, radius, folds, sig)
        if progress:
            progress(i + 1, len(families))
    ok = {n: s for n, s in scores.items() if np.isfinite(s).all()}
    fams = [f for f in families if f.name in ok]
    best = min(fams, key=lambda f: ok[f.name].sum())
    pick = best
    for f in sorted(fams, key=lambda f: (n_params(f, n_frames), ok[f.name].sum())):
        if n_params(f, n_frames) >= n_params(best, n_frames):
            break
        # (the clusters' error alone let a gain 17 of 18 frames shared, two of
        # them most, go: the third renderer's cage lost those two frames)
        if (not_worse(*paired_behind(ok[f.name], ok[best.name], obs.slot))
                and not mostly_behind(ok[f.name], ok[best.name], obs.slot)):
            pick = f
            break
    rows = []
    for f in families:
        if f.name not in scores:
            continue
        s = scores[f.name]
        row = {"family": f.name, "parameters": n_params(f, n_frames),
               "heldout_rms_px": float(np.sqrt(np.nanmean(s) / 2) * sig[0]) if np.isfinite(s).any() else None,
               "heldout_chi2": float(np.nansum(s)), "chosen": f is pick}
        if f is not pick and f.name in ok:
            row["behind_chosen_chi2"], row["behind_se"] = paired_behind(ok[f.name], ok[pick.name])
        elif f.name not in ok:
            row["why"] = ("a frame lost all its markers in a fold, or a fold left fewer markers than the family's "
                          "parameters: not scored")
        rows.append(row)
    return pick, rows
