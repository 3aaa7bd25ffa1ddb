"""Locate a mismatch before naming it.

The fit's model is freed per frame: every frame gets a small rigid motion
of its markers (a rotation about and a shift along three lab directions),
fitted to that frame's residuals with its σ. The resulting per-frame
curves say *where* the model and the recording differ, whatever physics
is behind it: an angle error that follows the rotation angle (a harmonic),
the time (a drift), the direction of motion (backlash), the velocity
(latency) or one frame onwards (a slip). A displacement field over the
detector, shared by all frames, stands for the detector itself.

Each curve is tested against each recorded variable with a small family of
shapes (Fourier harmonics 1-4 of a rotary reading, polynomials of degree
1-3 in time or a linear reading, a step with the direction of motion, a
line in velocity, a single jump at some frame): the χ² the shape explains
beyond a constant, χ²-distributed under pure noise, with p-values adjusted
by Holm's method over every (curve, variable, shape) tried. A significant
curve is reported with the variable and shape that predict it best on
held-out frames (interleaved folds), its size in its own unit and in
pixels, and the other variables that predict it as well (ambiguous).

Units: rotations in degrees, shifts in mm, sizes on the detector in px.
Frames: rotations about, and shifts along, the lab directions named in
each curve (``axis``: the moving rotary axis; ``beam``: the detector
normal; ``across``: their cross product), about the frame's markers'
centroid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from ..stats import holm

# a located curve must also be at least this many px on the detector: the
# noise floor of detect is ~0.01-0.02 px, and no geometry cares below this
MIN_SIZE_PX = 0.005
HARMONICS = (1, 2, 3, 4)
POLY_DEGREES = (1, 2, 3)


@dataclass(frozen=True)
class FrameCurves:
    """Per-frame values (n, k) of k named components with σ (n, k), NaN where
    a frame does not determine a component; ``px_per_unit`` (k,) is the RMS
    detector displacement of a unit of each component."""

    rows: np.ndarray
    names: tuple
    units: tuple
    values: np.ndarray
    sigma: np.ndarray
    px_per_unit: np.ndarray
    frames: np.ndarray | None = None   # (n,) the frame number of each row


def _directions(model, g):
    """Orthonormal lab directions (3, 3) and their names for the curves."""
    beam = g.normal / np.linalg.norm(g.normal)
    axis, axis_name = None, None
    chain = getattr(model, "chain", None)
    if chain is not None:
        for k, a in enumerate(chain.axes):
            if model.rotary[k] and np.ptp(model.readings[:, k]) > 0:
                axis, axis_name = np.asarray(a.direction, float), a.name
                break
    if axis is None:   # no rotary axis: the detector's own directions
        u = g.u - (g.u @ beam) * beam
        u /= np.linalg.norm(u)
        return np.array([u, np.cross(beam, u), beam]), ("detector u", "detector v", "beam")
    axis = axis - (axis @ beam) * beam
    axis /= np.linalg.norm(axis)
    across = np.cross(axis, beam)
    return np.array([axis, across, beam]), (f"axis {axis_name}", "across", "beam")


def frame_curves(model, effects, base) -> FrameCurves:
    """The fit's model freed per frame (see the module docstring)."""
    if getattr(model, "stage", None) == "fit-pose":
        r = model._residual(effects, base)
        s = model.sigma
        conv = np.array([np.degrees(1.0)] * 3 + [1.0] * 3)
        J = model._px_jacobian
        ppu = np.sqrt(np.mean(np.sum(J ** 2, axis=1), axis=0)) / conv
        return FrameCurves(model.obs.row, tuple(f"pose {c}" for c in model.component_names),
                           ("deg",) * 3 + ("mm",) * 3, r * conv, s * conv, ppu, np.asarray(model.obs.frame))
    o = model.obs
    idx = np.arange(len(o.row))
    X, pred = model.lab_centres(list(effects or ()), base, idx)
    r = o.xy - pred
    g = model.geometry_after(base)
    _, JX = g.project_jacobian(X)                                  # (m, 2, 3) px/mm
    E, dnames = _directions(model, g)
    names = tuple([f"rotation about {d}" for d in dnames] + [f"shift along {d}" for d in dnames])
    units = ("deg",) * 3 + ("mm",) * 3
    rows = np.unique(o.row)
    n, k = len(rows), 6
    vals, sig = np.full((n, k), np.nan), np.full((n, k), np.nan)
    A_all = np.zeros((len(idx), 2, k))
    for i in range(len(rows)):
        sel = np.flatnonzero(o.row == rows[i])
        Xc = X[sel].mean(axis=0)
        for j in range(3):
            # rotation by a small angle about E[j] through the centroid: dX = E[j] x (X - Xc)
            A_all[sel, :, j] = np.einsum("mij,mj->mi", JX[sel], np.cross(E[j], X[sel] - Xc))
            A_all[sel, :, 3 + j] = JX[sel] @ E[j]
    for i, row in enumerate(rows):
        sel = np.flatnonzero(o.row == row)
        w = 1.0 / o.sigma[sel]
        A = (A_all[sel] * w[:, None, None]).reshape(-1, k)
        y = (r[sel] * w[:, None]).ravel()
        # rotations need 3 markers, shifts 1; along the beam only a
        # magnification change shows, which needs a spread of markers too
        free = [4, 3] if len(sel) < 3 else list(range(k))
        Af = A[:, free]
        U, s, Vt = np.linalg.svd(Af, full_matrices=False)
        good = s > 1e-6 * s[0] if s.size else np.zeros(0, bool)
        if not good.all():   # a degenerate frame: keep only the two in-plane shifts
            free = [4, 3]
            Af = A[:, free]
            U, s, Vt = np.linalg.svd(Af, full_matrices=False)
        coef = Vt.T @ ((U.T @ y) / s)
        cov = (Vt.T / s ** 2) @ Vt
        vals[i, free] = coef
        sig[i, free] = np.sqrt(np.diag(cov))
    conv = np.array([np.degrees(1.0)] * 3 + [1.0] * 3)
    ppu = np.sqrt(np.mean(np.sum(A_all ** 2, axis=1), axis=0)) / conv
    first = np.array([np.flatnonzero(o.row == row)[0] for row in rows], int)
    return FrameCurves(rows, names, units, vals * conv, sig * conv, ppu, np.asarray(o.frame)[first])


def _row_variables(model, rows) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(variable, shape, basis (n, p), the variable's values (n,)) for every
    shape of every recorded variable at ``rows``; a direction of motion is
    given by its velocity."""
    t = np.asarray(model.times, float)[rows]
    out = []

    def poly(x, name):
        span = np.ptp(x)
        if span <= 0:
            return
        z = 2 * (x - x.min()) / span - 1
        for d in POLY_DEGREES:
            out.append((name, "linear" if d == 1 else f"polynomial of degree {d}",
                        np.column_stack([z ** p for p in range(1, d + 1)]), x))

    poly(t, "time")
    for k, name in enumerate(model.axis_names):
        q_all = np.asarray(model.readings[:, k], float)
        if np.ptp(q_all) <= 0:
            continue
        q = q_all[rows]
        if model.rotary[k]:
            a = np.deg2rad(q)
            if np.ptp(q) > 90:
                for h in HARMONICS:
                    out.append((name, f"harmonic {h} (×{h} per turn)", np.column_stack([np.cos(h * a), np.sin(h * a)]),
                                q))
            else:
                poly(q, name)
        else:
            poly(q, name)
        v_all = np.gradient(q_all, model.times) if len(q_all) > 1 else np.zeros_like(q_all)
        v = v_all[rows]
        if (v > 0).any() and (v < 0).any():
            out.append((f"direction of {name}", "step with the direction of motion", np.sign(v)[:, None], v))
        if np.ptp(v) > 1e-9 * max(1.0, np.abs(v).max()):
            out.append((f"velocity of {name}", "proportional to velocity", v[:, None], v))
    return out


def _wls_drop(y, w, B):
    """χ² explained by basis B beyond a constant (weights w = 1/σ²), and the fitted curve."""
    A = np.column_stack([np.ones(len(y)), B])
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
    c0 = np.sum(w * y) / np.sum(w)
    r0 = y - c0
    fit = A @ coef
    r1 = y - fit
    return float(np.sum(w * r0 ** 2) - np.sum(w * r1 ** 2)), fit - c0, coef


def _cv_error(y, w, B, folds: int = 5) -> float:
    """Held-out weighted squared error of a constant plus B, interleaved folds."""
    n = len(y)
    A = np.column_stack([np.ones(n), B])
    sw = np.sqrt(w)
    err = 0.0
    for f in range(folds):
        test = np.arange(n) % folds == f
        if test.all() or (~test).sum() <= A.shape[1]:
            continue
        coef, *_ = np.linalg.lstsq(A[~test] * sw[~test, None], y[~test] * sw[~test], rcond=None)
        err += float(np.sum(w[test] * (y[test] - A[test] @ coef) ** 2))
    return err


def _jump_scan(y, w, order):
    """Best single jump in frame order: (χ² explained, position, curve)."""
    n = len(y)
    best = (0.0, None, None)
    for cut in range(3, n - 3):
        step = np.zeros(n)
        step[order[cut:]] = 1.0
        d, curve, _ = _wls_drop(y, w, step[:, None])
        if d > best[0]:
            best = (d, cut, curve)
    return best


def locate(model, curves: FrameCurves, alpha: float = 0.01) -> list[dict]:
    """Significant per-frame curves, each with the variable and shape that
    predict it best; see the module docstring. JSON-ready dicts, largest first."""
    rows = curves.rows
    variables = _row_variables(model, rows)
    times = np.asarray(model.times, float)[rows]
    trials = []   # (component, rows used, variable, shape, basis, drop, dof, curve, the variable's values)
    jump_at = {}  # trial -> time (s) of the first frame after its jump
    for k, name in enumerate(curves.names):
        y, s = curves.values[:, k], curves.sigma[:, k]
        ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
        if ok.sum() < 8:
            continue
        yk, wk = y[ok], 1.0 / s[ok] ** 2
        for var, shape, B, x in variables:
            d, curve, _ = _wls_drop(yk, wk, B[ok])
            trials.append((k, ok, var, shape, B[ok], d, B.shape[1], curve, x[ok]))
        # a jump at one frame onwards: a scan over positions, Bonferroni over them
        order = np.argsort(times[ok], kind="stable")
        d, cut, curve = _jump_scan(yk, wk, order)
        if cut is not None:
            jump_at[len(trials)] = float(times[ok][order[cut]])
            trials.append((k, ok, "time", f"jump after the {cut}th frame in time", None, d, ("jump", ok.sum()), curve,
                           times[ok]))
    if not trials:
        return []
    pvals = []
    for t in trials:
        d, dof = t[5], t[6]
        if isinstance(dof, tuple):     # jump: one parameter, scanned over n positions
            p = min(1.0, chi2.sf(d, 1) * dof[1])
        else:
            p = float(chi2.sf(d, dof))
        pvals.append(p)
    adj = holm(pvals)
    out = []
    for k, name in enumerate(curves.names):
        mine = [i for i, t in enumerate(trials) if t[0] == k and adj[i] < alpha]
        if not mine:
            continue
        y, s = curves.values[:, k], curves.sigma[:, k]
        ok = trials[mine[0]][1]
        yk, wk = y[ok], 1.0 / s[ok] ** 2
        # held-out error of each significant shape; the best, and those within noise of it
        cv = {}
        for i in mine:
            t = trials[i]
            if t[4] is None:
                step = (t[7] > t[7].min() + 0.5 * np.ptp(t[7])).astype(float)[:, None]
                cv[i] = _cv_error(yk, wk, step)
            else:
                cv[i] = _cv_error(yk, wk, t[4])
        best = min(cv, key=cv.get)
        tb = trials[best]
        size = float(np.sqrt(np.mean(tb[7] ** 2)))
        size_px = size * float(curves.px_per_unit[k])
        if size_px < MIN_SIZE_PX:
            continue
        # other variables that predict the curve as well: within 5 % of what
        # the best explains on held-out frames (or 4 units of χ²)
        cv_const = _cv_error(yk, wk, np.zeros((len(yk), 0)))
        margin = max(4.0, 0.05 * (cv_const - cv[best]))
        also = sorted({trials[i][2] for i in cv if i != best and trials[i][2] != tb[2] and cv[i] - cv[best] < margin})
        out.append({"component": name, "unit": curves.units[k], "variable": tb[2], "shape": tb[3],
                    "size": size, "size_px": size_px, "p_adjusted": float(adj[best]),
                    "chi2_explained": float(tb[5]), "chi2_total": float(np.sum(wk * (yk - np.sum(wk * yk) / np.sum(wk)) ** 2)),
                    "frames": int(ok.sum()), "also_follows": also,
                    **({"at_time": jump_at[best]} if best in jump_at else {}),
                    "series": _series(tb, yk, wk, curves.frames[ok] if curves.frames is not None else None)})
    out.sort(key=lambda d: -d["size_px"])
    return out


def _series(trial, y, w, frames) -> dict:
    """The located curve as plotted: each frame's value with σ against the
    variable it follows, and the shape fitted to it (its weighted mean added)."""
    x = trial[8]
    order = np.argsort(x, kind="stable")
    out = {"x_variable": ("velocity of " + trial[2][len("direction of "):]) if trial[2].startswith("direction of ")
           else trial[2],
           "x": x[order].tolist(), "value": y[order].tolist(), "sigma": (1.0 / np.sqrt(w[order])).tolist(),
           "model": (trial[7] + np.sum(w * y) / np.sum(w))[order].tolist()}
    if frames is not None:
        out["frame"] = np.asarray(frames)[order].astype(int).tolist()
    return out


def detector_field(model, effects, base, alpha: float = 0.01, max_degree: int = 3) -> dict | None:
    """A displacement field over the detector shared by every frame: the
    residuals regressed on 2-D polynomials of the detector position (degree
    2..``max_degree``; lower degrees are a per-frame shift or the geometry's
    own). The degree is chosen on held-out markers (interleaved folds).
    Returns the significant field's size and degree, or None."""
    if getattr(model, "stage", None) == "fit-pose" or not hasattr(model.obs, "xy"):
        return None
    o = model.obs
    r = model.residual_px(effects, base)
    rows_, cols_ = model.geometry.shape
    half = np.array([(cols_ - 1) / 2, (rows_ - 1) / 2])
    z = (o.xy - half) / half
    w = 1.0 / o.sigma ** 2
    tests = []

    def basis(z, deg):
        return np.column_stack([z[:, 0] ** i * z[:, 1] ** j for i in range(deg + 1) for j in range(deg + 1 - i)
                                if 0 < i + j])

    gu, gv = np.linspace(0, cols_ - 1, 9), np.linspace(0, rows_ - 1, 9)
    grid = np.stack(np.meshgrid(gu, gv), axis=-1).reshape(-1, 2)
    zg = (grid - half) / half
    for deg in range(2, max_degree + 1):
        B = basis(z, deg)
        d = 0.0
        cv = 0.0
        fitted = np.zeros_like(r)
        on_grid = np.zeros((len(grid), 2))
        for c in range(2):
            dc, curve, coef = _wls_drop(r[:, c], w, B)
            d += dc
            fitted[:, c] = curve
            # the field without its weighted mean, as the curve is given
            on_grid[:, c] = basis(zg, deg) @ coef[1:] + coef[0] - np.sum(w * r[:, c]) / np.sum(w)
            cv += _cv_error(r[:, c], w, B)
        dof = 2 * B.shape[1]
        tests.append({"degree": deg, "chi2_explained": d, "dof": dof, "p": float(chi2.sf(d, dof)), "cv": cv,
                      "rms_px": float(np.sqrt(np.mean(np.sum(fitted ** 2, axis=1)))),
                      "max_px": float(np.max(np.hypot(*fitted.T))),
                      "grid": {"u_px": gu.tolist(), "v_px": gv.tolist(),
                               "du": on_grid[:, 0].reshape(9, 9).tolist(), "dv": on_grid[:, 1].reshape(9, 9).tolist()}})
    m = len(tests)
    sig = [t for t in tests if min(1.0, m * t["p"]) < alpha]
    if not sig:
        return None
    best = min(sig, key=lambda t: t["cv"])
    if best["rms_px"] < MIN_SIZE_PX:
        return None
    return {"component": "displacement field over the detector", "unit": "px", "variable": "detector position",
            "shape": f"polynomial field of degree {best['degree']}", "size": best["rms_px"], "size_px": best["rms_px"],
            "max_px": best["max_px"], "p_adjusted": min(1.0, m * best["p"]), "chi2_explained": best["chi2_explained"],
            "also_follows": [], "field": best["grid"]}


def describe(loc: dict) -> str:
    """One located mismatch in plain words."""
    unit = loc["unit"]
    size = (f"{loc['size']:.4f} {unit}" if unit == "deg" else f"{1e3 * loc['size']:.1f} µm" if unit == "mm"
            else f"{loc['size']:.3f} {unit}")
    words = f"{loc['component']} follows {loc['variable']} ({loc['shape']}; RMS {size}, {loc['size_px']:.3f} px)"
    if loc.get("also_follows"):
        words += f", or equally {', '.join(loc['also_follows'])}"
    return words
