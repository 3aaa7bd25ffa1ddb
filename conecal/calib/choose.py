"""Which detector distortion the data support: leave-markers-out.

Every identified centre is put in one of ``folds`` groups at random (a
fixed seed). Each family is fitted without one group at a time (poses,
intrinsics and distortion, started from the full fit) and predicts the
group it did not see; the score is the sum of whitened squared held-out
residuals. The family with the lowest score wins, except that the most
specific family (fewest parameters) whose paired held-out difference to
it is within max(3, two standard errors) is chosen instead: a flexible
field earns its place only by predicting markers it was not fitted on.
"""

from __future__ import annotations

import numpy as np

from .bundle import FAMILIES, Bundle, Family, Observations, adjust


def _n_params(f: Family, n_frames: int) -> int:
    return f.k + len(f.per_frame) * n_frames


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
        b = adjust(family, full.camera, train, points, radius, full.R, full.t, start=full, passes=1, max_nfev=30,
                   covariance=False)
        pred = b.predict(points[obs.sph[test]], obs.slot[test], radius)
        r2[test] = np.sum((pred - obs.xy[test]) ** 2, 1) / sigma_eff[test] ** 2
    return r2


def choose_family(fits: dict, obs: Observations, points, radius, n_folds: int = 5, seed: int = 0,
                  families=FAMILIES, progress=None) -> tuple[Family, list[dict]]:
    """``fits``: family name -> its bundle on all of ``obs``. Returns the chosen
    family and one row per family (name, parameters, held-out score, chosen,
    why)."""
    rng = np.random.default_rng(seed)
    folds = rng.integers(0, n_folds, len(obs))
    n_frames = len(next(iter(fits.values())).R)
    # one noise scale for all families: the most flexible fit's residuals
    flexible = min(fits.values(), key=lambda b: float(np.mean(np.sum(b.residual_px ** 2, 1))))
    sig = np.full(len(obs), max(float(np.sqrt(np.mean(np.sum(flexible.residual_px ** 2, 1)) / 2)), 1e-3))
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
    for f in sorted(fams, key=lambda f: (_n_params(f, n_frames), ok[f.name].sum())):
        if _n_params(f, n_frames) >= _n_params(best, n_frames):
            break
        d = ok[f.name] - ok[best.name]
        behind, se = float(d.sum()), float(np.sqrt(len(d)) * d.std())
        if behind < max(3.0, 2 * se):
            pick = f
            break
    rows = []
    for f in families:
        if f.name not in scores:
            continue
        s = scores[f.name]
        row = {"family": f.name, "parameters": _n_params(f, n_frames),
               "heldout_rms_px": float(np.sqrt(np.nanmean(s) / 2) * sig[0]) if np.isfinite(s).any() else None,
               "heldout_chi2": float(np.nansum(s)), "chosen": f is pick}
        if f is not pick and f.name in ok:
            d = ok[f.name] - ok[pick.name]
            row["behind_chosen_chi2"] = float(d.sum())
            row["behind_se"] = float(np.sqrt(len(d)) * d.std())
        elif f.name not in ok:
            row["why"] = "a frame lost all its markers in a fold: not scored"
        rows.append(row)
    return pick, rows
