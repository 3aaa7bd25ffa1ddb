"""Which left-out physics explains the residuals: refit with each candidate
effect, judge by held-out frames and an information criterion, refuse to
claim what does not beat noise, and say so when two effects explain the
data equally well.

Every candidate is refitted together with the fit's own parameters (see
``ResultModel._setup_base``), so that an effect is credited only with what
they cannot absorb. Held-out
error: two-fold, even frames against odd frames. A candidate is claimed
when it lowers the held-out chi^2 by more than ``max(10, 3k)`` (k its
parameter count) and BIC by more than 10. When the best claim leaves
significant structure, pairs with the other candidates are tried.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..effects.imaging import DetectorDistortion
from ..effects.motion import (AxisNonOrthogonality, AxisScale, Backlash, DetectorDrift, EncoderLatency, FocalSpotDrift,
                              RotaryRunout, RotaryWobble)
from ..kinematics import LinearAxis, RotaryAxis
from .model import CentroidPull, EllipseCentreBias
from .locate import describe, detector_field, frame_curves, locate
from .structure import structure_tests


@dataclass(frozen=True)
class Candidate:
    """An effect with its fitted parameters as a vector."""

    label: str
    names: tuple
    units: tuple
    scales: tuple
    build: object          # vector -> Effect
    describe: object       # vector, sigma -> plain words
    impossible: object = None   # vector -> reason the value cannot be physical, or None

    @property
    def k(self) -> int:
        return len(self.names)


def _moving(model):
    return [k for k, n in enumerate(model.chain.names) if np.ptp(model.readings[:, k]) > 0]


def candidates(model) -> list[Candidate]:
    """Every effect of the registry that this recording could show, parameterised."""
    if model.stage == "fit-pose":
        from .pose import candidates as pose_candidates

        return pose_candidates(model)
    out = []
    dur = max(float(np.ptp(model.times)), 1e-9)
    out.append(Candidate("focal_spot_drift", ("vx", "vy", "vz"), ("mm/s",) * 3, (1e-3 / dur,) * 3,
                         lambda x: FocalSpotDrift(tuple(x)),
                         lambda x, s: "the focal spot drifted (" + ", ".join(
                             f"{a} {1e3 * v:+.3f} ± {1e3 * e:.3f} µm/s" for a, v, e in zip("xyz", x, s)) + ")"))
    out.append(Candidate("detector_drift", ("vx", "vy", "vz"), ("mm/s",) * 3, (1e-3 / dur,) * 3,
                         lambda x: DetectorDrift(tuple(x)),
                         lambda x, s: "the detector drifted (" + ", ".join(
                             f"{a} {1e3 * v:+.3f} ± {1e3 * e:.3f} µm/s" for a, v, e in zip("xyz", x, s)) + ")"))
    out.append(Candidate("detector_distortion:radial", ("radial_px",), ("px",), (0.05,),
                         lambda x: DetectorDistortion(float(x[0]), 0.0),
                         lambda x, s: f"the detector image is warped radially by {x[0]:+.3f} ± {s[0]:.3f} px at its "
                                      "corner (pincushion > 0)"))
    out.append(Candidate("detector_distortion:s_shaped", ("s_px",), ("px",), (0.05,),
                         lambda x: DetectorDistortion(0.0, float(x[0])),
                         lambda x, s: f"the detector image is S-shaped: twisted by {x[0]:+.3f} ± {s[0]:.3f} px at its "
                                      "corner (counter-clockwise > 0), as an image intensifier in a magnetic field"))
    moving = _moving(model)
    axes = model.chain.axes
    for k in moving:
        a = axes[k]
        unit = "deg" if isinstance(a, RotaryAxis) else "mm"
        q = model.readings[:, k]
        v = np.gradient(q, model.times)
        if isinstance(a, LinearAxis):
            out.append(Candidate(f"axis_scale:{a.name}", ("scale",), ("",), (1e-4,),
                                 lambda x, n=a.name: AxisScale(n, float(x[0])),
                                 lambda x, s, n=a.name: f"axis {n} moves {x[0] * 1e6:+.0f} ± {s[0] * 1e6:.0f} ppm "
                                                        "more than its encoder says"))
            for b in moving:
                if b != k and isinstance(axes[b], LinearAxis):
                    out.append(Candidate(f"axis_nonorthogonality:{a.name}->{axes[b].name}", ("angle",), ("deg",), (0.01,),
                                         lambda x, n=a.name, m=axes[b].name: AxisNonOrthogonality(n, m, float(x[0])),
                                         lambda x, s, n=a.name, m=axes[b].name:
                                         f"axis {n} leans {x[0]:+.4f} ± {s[0]:.4f} deg towards {m}"))
        if isinstance(a, RotaryAxis):
            out.append(Candidate(f"rotary_wobble:{a.name}", ("a_cos", "a_sin"), ("deg", "deg"), (0.005, 0.005),
                                 lambda x, n=a.name: RotaryWobble(n, float(np.hypot(*x)), float(np.degrees(np.arctan2(x[1], x[0])))),
                                 lambda x, s, n=a.name: f"axis {n} wobbles by {np.hypot(*x):.4f} ± {np.hypot(*s) / np.sqrt(2):.4f} deg "
                                                        f"once per turn (phase {np.degrees(np.arctan2(x[1], x[0])):.0f} deg)"))
            out += _runout_candidates(model, a)
        if (v > 0).any() and (v < 0).any():
            out.append(Candidate(f"backlash:{a.name}", ("amount",), (unit,), (0.005,),
                                 lambda x, n=a.name: Backlash(n, float(x[0])),
                                 lambda x, s, n=a.name, u=unit: f"axis {n} has {x[0]:+.4f} ± {s[0]:.4f} {u} backlash "
                                                                "(error follows the direction of motion)"))
    if model.centre_model == "projection":
        d_mm = 2 * float(np.median(model.radii))
        out.append(Candidate("ellipse_centre_bias", ("fraction",), ("",), (0.05,),
                             lambda x: EllipseCentreBias(float(x[0])),
                             lambda x, s, d=d_mm: f"the measured centres are the shadows' attenuation centroids, not the "
                                                  f"projected sphere centres: {x[0]:.3f} ± {s[0]:.3f} of the ellipse-centre "
                                                  f"bias of {d:.2f} mm spheres (fit with --centre-model centroid)"))
    if moving:   # a lag ghost drags each centre back towards the previous frame's
        out.append(Candidate("detector_lag", ("pull",), ("",), (0.005,),
                             lambda x: CentroidPull(float(x[0])),
                             lambda x, s: f"each measured centre is pulled {100 * x[0]:+.2f} ± {100 * s[0]:.2f} % of "
                                          "the way back to the previous frame's (a lag ghost of the previous frame)",
                             lambda x: "a lag ghost cannot push a centre forwards (pull < 0)" if x[0] < 0 else None))
    if moving:   # one latency for every axis: the encoders are read together
        out.append(Candidate("encoder_latency", ("latency",), ("s",), (0.005,),
                             lambda x: EncoderLatency(float(x[0])),
                             lambda x, s: f"frames were exposed {1e3 * x[0]:+.1f} ± {1e3 * s[0]:.1f} ms after the "
                                          "encoders were read (error ∝ velocity)"))
    return out


RUNOUT_HARMONICS = (2, 3)
_TIMES = {2: "twice", 3: "three times"}


def _across_beam(model, a) -> float:
    """Angle (rad) in the axis' (e1, e2) plane of the direction across the
    beam: the runout the projections see (a fixed sensitive direction)."""
    from ..geometry.rotations import orthonormal_complement

    e1, e2 = orthonormal_complement(a.direction)
    t = np.cross(a.direction, model.geometry.source - a.point)
    return float(np.arctan2(t @ e2, t @ e1))


def _runout(axis: str, k: int, beta: float, x) -> RotaryRunout:
    """Runout ``x[0] cos(k q) + x[1] sin(k q)`` (mm) along the direction at
    ``beta``: a line traced k times per turn, i.e. equal forward and
    backward whirls."""
    A = float(np.hypot(*x))
    phi = float(np.arctan2(-x[1], x[0]))
    return RotaryRunout(axis, A / 2, float(np.degrees(phi + beta)), k, A / 2, float(np.degrees(phi - beta)))


def _runout_candidates(model, a) -> list[Candidate]:
    """Runout at 2 and 3 times per turn, across the beam. A circular scan
    sees the axis' sideways motion only across the beam (along it, only
    through a magnification change of ~1e-4); and once per turn it is a
    centring error, which the spheres' fitted positions absorb."""
    beta = _across_beam(model, a)
    return [Candidate(f"rotary_runout:{a.name}:{k}", ("across_cos", "across_sin"), ("mm", "mm"), (0.002, 0.002),
                      lambda x, n=a.name, k=k: _runout(n, k, beta, x),
                      lambda x, s, n=a.name, k=k:
                      f"axis {n} runs out {_TIMES[k]} per turn: its line moves across the beam by "
                      f"{1e3 * np.hypot(*x):.1f} ± {1e3 * float(np.sqrt(np.mean(np.square(s)))):.1f} µm "
                      f"(amplitude; first peak at {n} = {(np.degrees(np.arctan2(x[1], x[0])) / k) % (360 / k):.0f} deg, "
                      f"then every {360 / k:.0f} deg)")
            for k in RUNOUT_HARMONICS]


def _fit(model, cands, select=None, x0=None):
    """Least squares over the nine geometry parameters plus each candidate's."""
    ks = [c.k for c in cands]
    nb = model.n_base
    scales = np.concatenate([model.base_scales] + [c.scales for c in cands])

    def split(x):
        effs, i = [], nb
        for c, k in zip(cands, ks):
            effs.append(c.build(x[i:i + k]))
            i += k
        return x[:nb], effs

    def fun(x):
        x9, effs = split(x)
        return model.whitened(effs, x9, select)

    x0 = np.zeros(nb + sum(ks)) if x0 is None else x0
    res = least_squares(fun, x0, x_scale=scales, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=200 * len(x0))
    J = res.jac
    try:
        cov = np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((len(x0), len(x0)), np.nan)
    chi2 = float(res.fun @ res.fun)
    dof = max(len(res.fun) - len(x0), 1)
    cov *= max(chi2 / dof, 1.0)
    return res.x, np.sqrt(np.clip(np.diag(cov), 0, None)), chi2, split


def _heldout(model, cands) -> np.ndarray:
    """Two-fold held-out squared whitened residuals: fit on even frames,
    score odd ones, and back; (m,) per observation, in observation order."""
    even = model.obs.row % 2 == 0
    out = np.zeros(len(even))
    for train in (even, ~even):
        x, _, _, split = _fit(model, cands, train)
        x9, effs = split(x)
        r = model.whitened(effs, x9, ~train).reshape(-1, model.n_comp)
        out[~train] = np.sum(r * r, axis=1)
    return out


def evaluate(model, cands) -> dict:
    x, sig, chi2, split = _fit(model, cands)
    n = model.n_comp * len(model.obs.row)
    k = len(x)
    x9, effs = split(x)
    r2 = _heldout(model, cands)
    return {"cands": cands, "x": x, "sigma": sig, "chi2": chi2, "bic": chi2 + k * np.log(n),
            "heldout": float(r2.sum()), "heldout_r2": r2, "x9": x9, "effects": effs}


def score(base: dict, e: dict, k: int) -> dict:
    """How much a candidate with ``k`` more parameters beats ``base``; the claim rule.

    A candidate nests the base model, so on held-out data it can lose only
    what its ``k`` parameters fit to noise (χ² of order k). One that loses
    far more (``DEGENERATE_LOSS``) has an evaluation that broke (a fit that
    ran off, a parameter the held-out half cannot pin): it is marked
    ``degenerate`` and not scored."""
    gain = float(base["heldout"] - e["heldout"])
    bic = float(base["bic"] - e["bic"])
    out = {"heldout_gain_chi2": gain, "bic_gain": bic, "claimable": bool(gain > max(10.0, 3 * k) and bic > 10.0)}
    n = len(e.get("heldout_r2", ())) or 1
    if gain < -max(DEGENERATE_LOSS, 10 * k, 5 * np.sqrt(2 * n)):
        out.update(claimable=False, degenerate=True,
                   reason=f"held-out chi^2 worse by {-gain:.0f} than the base model it nests: a degenerate fit, "
                          "not scored")
    return out


# χ² a nested candidate may lose on held-out data before its evaluation is
# taken as broken rather than as a model that lost (see ``score``)
DEGENERATE_LOSS = 100.0
# A claim must bring the residual RMS within this factor of the noise floor
# and leave no significant structure (issue 28: adequacy before a claim).
ADEQUATE_RMS = 1.15


def rank(rows: list[dict], heldout_r2: dict) -> tuple[list[dict], list[str]]:
    """Sort candidate rows by held-out gain (in place); return the claimable
    ones, best first, and the labels of those the held-out data cannot tell
    from the best: a paired comparison of their held-out squared residuals
    (``heldout_r2``: label -> per-observation array) whose difference is
    within two standard errors (and at least 3). Each row gets
    ``behind_best_chi2`` and its standard error."""
    rows.sort(key=lambda r: -r["heldout_gain_chi2"])
    claimed = [r for r in rows if r["claimable"]]
    if not claimed:
        return [], []
    best = claimed[0]
    ambiguous = []
    for r in claimed[1:]:
        d = heldout_r2[r["effect"]] - heldout_r2[best["effect"]]
        se = float(np.sqrt(len(d) * d.var())) if len(d) > 1 else 0.0
        r["behind_best_chi2"], r["behind_best_stderr"] = float(d.sum()), se
        if d.sum() < max(3.0, 2 * se):
            ambiguous.append(r["effect"])
    return claimed, ambiguous


def _base_unit(name: str) -> tuple[str, float]:
    """Unit of one of the fit's own parameters and the factor to it."""
    if name.endswith(("_tilt1", "_tilt2")):
        return "deg", float(np.degrees(1.0))
    return ("deg", 1.0) if name in ("detector_rx", "detector_ry", "detector_rz") else ("mm", 1.0)


def point_model_cost(model, base: dict) -> dict | None:
    """What the papers' point model does to a fit, computed rather than estimated.

    A fit with ``--centre-model projection`` takes each marker for the
    projected sphere centre; ``detect`` measures the attenuation centroid,
    which lies outward by the ellipse-centre bias, known exactly from the
    sphere diameters and the geometry. Most of that bias looks like a
    radial rescale of each sphere's track and is absorbed by the fit's own
    parameters (sphere positions, axis, source and detector), so it hardly
    shows in the residuals and cannot be claimed from them. What can be
    said is how far it moved the fit: refit with the exact bias switched on
    and compare. None unless the fit used the point model."""
    if getattr(model, "centre_model", "centroid") != "projection":
        return None
    exact = [EllipseCentreBias(1.0)]
    zero = np.zeros(model.n_base)
    bias = model.predict(exact, zero) - model.predict(None, zero)
    sol = least_squares(lambda b: model.whitened(exact, b), base["x9"], x_scale=model.base_scales, method="lm")
    moved = sol.x - base["x9"]
    left = model.residual_px(exact, sol.x) - model.residual_px(None, base["x9"])
    shifts = {}
    for n, d in zip(model.base_names, moved):
        unit, f = _base_unit(n)
        shifts[n] = {"value": float(d * f), "unit": unit}
    big = max(shifts, key=lambda n: abs(shifts[n]["value"]) if shifts[n]["unit"] == "mm" else 0.0)
    rms_bias = float(np.sqrt(np.mean(bias ** 2)))
    rms_left = float(np.sqrt(np.mean(left ** 2)))
    d_mm = 2 * float(np.median(model.radii))
    return {"bias_rms_px": rms_bias, "bias_max_px": float(np.abs(bias).max()), "residual_change_rms_px": rms_left,
            "absorbed_fraction": float(1 - (rms_left / rms_bias) ** 2) if rms_bias > 0 else 1.0,
            "chi2_change": float(np.sum(model.whitened(exact, sol.x) ** 2) - np.sum(model.whitened(None, base["x9"]) ** 2)),
            "parameter_shifts": shifts,
            "statement": f"the fit took each marker for the projected sphere centre; the shadows' ellipse-centre bias "
                         f"({d_mm:.2f} mm spheres: RMS {rms_bias:.4f} px, up to {np.abs(bias).max():.4f} px) is known, "
                         f"and the fit's own parameters absorbed it: modelled, it changes the residuals by only "
                         f"{rms_left:.4f} px RMS but moves {big} by {1e3 * shifts[big]['value']:+.1f} µm; refit with "
                         f"--centre-model centroid"}


def diagnose(model, *, alpha: float = 0.01, progress=None, tie_breaker=None) -> dict:
    """The whole decision; returns a plain dict (JSON-ready) and the chosen evaluation.

    ``tie_breaker``: when the marker positions cannot tell the best effect
    from others, a callable ``{label: evaluation} -> {label: chi2}`` of
    other evidence per item (the image level: chi^2 of each marker patch
    rendered from each one's scene); the lowest total wins, and the others
    stay ambiguous unless it beats them by more than two standard errors of
    the paired difference (and 10).
    """
    base = evaluate(model, [])
    r0 = model.whitened(None, base["x9"])   # the fit's own parameters refitted: zero unless registration is free
    tests_before = structure_tests(model, r0, alpha)
    cands = candidates(model)
    rows = []
    evals = {}
    for i, c in enumerate(cands):
        e = evaluate(model, [c])
        evals[c.label] = e
        nb = model.n_base
        row = {"effect": c.label, "parameters": dict(zip(c.names, e["x"][nb:].tolist())),
               "sigma": dict(zip(c.names, e["sigma"][nb:].tolist())), **score(base, e, c.k)}
        why = c.impossible(e["x"][nb:]) if c.impossible is not None else None
        if why:
            row.update(claimable=False, impossible=why)
        rows.append(row)
        if progress:
            progress(i + 1, len(cands) + 1)
    claimed, ambiguous = rank(rows, {k: e["heldout_r2"] for k, e in evals.items()})
    chosen = []
    tie = None
    if claimed and ambiguous and tie_breaker is not None:
        labels = [claimed[0]["effect"]] + ambiguous[:5]
        per = tie_breaker({k: evals[k] for k in labels})
        tie = {k: float(np.sum(v)) for k, v in per.items()}
        winner = min(tie, key=tie.get)
        ambiguous = []
        for k in labels:
            d = per[k] - per[winner]
            if k != winner and d.sum() < max(10.0, 2 * np.sqrt(len(d) * d.var())):
                ambiguous.append(k)
        claimed = [r for r in claimed if r["effect"] == winner] + [r for r in claimed if r["effect"] != winner]
    if claimed:
        best = claimed[0]
        chosen = [best["effect"]]
        e_best = evals[best["effect"]]
        after = structure_tests(model, model.whitened(e_best["effects"], e_best["x9"]), alpha)
        if any(t["significant"] for t in after):
            # one effect does not explain it all: try pairs with the best
            best_pair, best_gain = None, 0.0
            by = {c.label: c for c in cands}
            for r in claimed[1:4]:
                e2 = evaluate(model, [by[best["effect"]], by[r["effect"]]])
                sc = score(e_best, e2, by[r["effect"]].k)
                if sc["claimable"] and sc["heldout_gain_chi2"] > best_gain:
                    best_pair, best_gain = (r["effect"], e2), sc["heldout_gain_chi2"]
            if best_pair is not None:
                chosen.append(best_pair[0])
                ambiguous = [a for a in ambiguous if a != best_pair[0]]
                evals["+".join(chosen)] = best_pair[1]
    final = evals["+".join(chosen)] if chosen else base
    r_after = model.whitened(final["effects"], final["x9"])
    tests_after = structure_tests(model, r_after, alpha)
    b0 = base["x9"]
    px_before = model.residual_px(None, b0)
    summary_before = model.summary(None, b0)   # physical units beyond px (fit-pose: mm, deg); {} otherwise
    px_after = model.residual_px(final["effects"], final["x9"])
    found = []
    if chosen:
        by = {c.label: c for c in cands}
        i = model.n_base
        for label in chosen:
            c = by[label]
            x, s = final["x"][i:i + c.k], final["sigma"][i:i + c.k]
            i += c.k
            found.append({"effect": label, "parameters": dict(zip(c.names, x.tolist())),
                          "sigma": dict(zip(c.names, s.tolist())), "units": dict(zip(c.names, c.units)),
                          "statement": c.describe(x, s), "physics": c.build(x).physics})
    located = located_mismatches(model, None, b0, alpha)
    floor = model.noise_floor_px()
    rms_after = model.rms_px(final["effects"], final["x9"])
    adequacy = None
    partial = []
    if chosen:
        remaining = located_mismatches(model, final["effects"], final["x9"], alpha)
        adequacy = {"rms_px_after": rms_after, "noise_floor_px": floor, "limit": ADEQUATE_RMS,
                    "rms_ok": bool(rms_after <= ADEQUATE_RMS * floor),
                    "structure_left": [t["variable"] for t in tests_after if t["significant"]],
                    "remaining": remaining}
        adequacy["adequate"] = bool(adequacy["rms_ok"] and not adequacy["structure_left"])
        if not adequacy["adequate"]:
            partial, found = found, []
    verdict = _verdict(found, partial, ambiguous, located, adequacy, model.rms_px(None, b0), floor)
    point = point_model_cost(model, base)
    if point is not None and not any(f["effect"] == "ellipse_centre_bias" for f in found):
        verdict += f"; {point['statement']}"
    return {
        "verdict": verdict,
        "point_model": point,
        "effects": found,
        "partial": partial,
        "located": located,
        "adequacy": adequacy,
        "ambiguous_with": ambiguous if found else [],
        "candidates": rows,
        "tests_before": tests_before,
        "tests_after": tests_after,
        "rms_px_before": model.rms_px(None, b0),
        "rms_px_after": model.rms_px(final["effects"], final["x9"]),
        "noise_floor_px": model.noise_floor_px(),
        **({"before": summary_before, "after": model.summary(final["effects"], final["x9"])}
           if summary_before else {}),
        "heldout_gain_chi2": float(base["heldout"] - final["heldout"]) if chosen else 0.0,
        "image_tie_break_chi2": tie,
        "n_observations": int(len(model.obs.row)),
        "base_parameters": dict(zip(model.base_names, final["x9"].tolist())),
        "observations": {"frame": model.obs.frame.tolist(), "id": model.obs.ids.tolist(),
                         "time": model.times[model.obs.row].tolist(),
                         "before": px_before.tolist(), "after": px_after.tolist()},
    }, final


def located_mismatches(model, effects, base, alpha: float) -> list[dict]:
    """Where the model and the recording differ, before any effect is named:
    the per-frame curves and the detector field of ``locate``."""
    out = locate(model, frame_curves(model, effects, base), alpha)
    field = detector_field(model, effects, base, alpha)
    if field is not None:
        out.append(field)
    return sorted(out, key=lambda d: -d["size_px"])


def _verdict(found, partial, ambiguous, located, adequacy, rms_before, floor) -> str:
    """The sentence, made from the decision's data."""
    where = "; ".join(describe(loc) for loc in located[:3])
    if found:
        return (" and ".join(f["statement"] for f in found)
                + (f"; not distinguishable here from {', '.join(ambiguous)}" if ambiguous else ""))
    if partial:
        left = adequacy["remaining"]
        what = "; ".join(describe(loc) for loc in left[:2]) or ", ".join(adequacy["structure_left"]) or "no structure"
        return (f"located, not named: {where or 'residual above the noise'}. "
                f"{' and '.join(f['effect'] for f in partial)} explains part of it (RMS {rms_before:.4f} -> "
                f"{adequacy['rms_px_after']:.4f} px against a noise floor of {floor:.4f} px) but leaves {what}; "
                "not claimed")
    if located:
        return (f"located, not named: {where}; no effect of the library explains it "
                f"(RMS {rms_before:.4f} px against a noise floor of {floor:.4f} px)")
    return "no left-out effect beats the noise"
