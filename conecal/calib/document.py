"""The ``conecal-poses/1`` document of a free-pose calibration.

Stated sigmas combine the bundle's statistical sigma (scaled by the
reduced chi-square when that exceeds 1) with the model's: how far the
estimate moves to the distortion families the held-out markers cannot tell
from the chosen one (a decentring term and the principal point, for one,
trade off on a planar grid), beyond what noise alone would move it. For a
more flexible family f nesting the chosen c, noise alone gives
``E[(v_f - v_c)^2] = s_f^2 - s_c^2`` (Hausman); a shift beyond twice that
difference's sigma counts in full, a smaller one not at all, and the mean
over the tied families is the model variance. ``sigma = hypot(statistical,
model)``.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..geometry import matrix_to_rotvec
from ..geometry.sphere import hidden_behind
from ..stats import not_worse
from .bundle import Bundle
from .camera import INTRINSIC_UNITS, INTRINSICS
from .run import FreeOptions, FreeResult

GAUGE = ("lab frame = the imaging system's: source at (0, 0, -sod) with the nominal sod, detector plane "
         "perpendicular to +z with u = +x, v = +y (no stage defines another frame); aspect and skew fixed by the "
         "stated pixel pitch; distortion without an affine part (a shift, scale or rotation of the image belongs "
         "to the principal point, sdd and poses); a refined phantom (phantom_refinement) keeps its CAD "
         "frame through the offsets' prior: a rigid motion or scaling of the whole phantom is the poses'")

# added where the chosen family turns each frame's twist about its own centre
TWIST_GAUGE = ("; a frame's twist centre and the shared q1, q2 trade at first order (twist centre offset "
               "delta_k + c / s_k with q + c leaves the field unchanged): their split is held by the twist "
               "centres' prior (sigma half the normalising radius about the distortion centre), and the field "
               "a frame's distortion entry gives is what is measured, not its parts")


def _tied(res: FreeResult) -> list[Bundle]:
    out = []
    for row in res.choice:
        if row.get("chosen") or "behind_chosen_chi2" not in row or row.get("why"):
            continue
        if row.get("tied", not_worse(row["behind_chosen_chi2"], row["behind_se"])):
            out.append(res.fits[row["family"]])
    return out


def _combine(stat: float, spreads: list, sigmas: list | None = None) -> tuple[float, float]:
    """``spreads``: v_f - v_c per tied family; ``sigmas``: their own statistical s_f."""
    if not spreads:
        return float(stat), 0.0
    sigmas = sigmas if sigmas is not None else [stat] * len(spreads)
    # a shift counts only when noise alone would rarely make it (beyond 2 sigma of
    # the difference): max(0, d^2 - E d^2) on its own inflates sigma on average.
    # Nested fits differ by noise of variance |s_f^2 - s_c^2|, whichever is the
    # more flexible (a tied family, or the principal point held at the centre)
    excess = [d * d if d * d > 4 * max(abs(sf * sf - stat * stat), 1e-12 * stat * stat) else 0.0
              for d, sf in zip(spreads, sigmas)]
    model = float(np.sqrt(np.mean(excess)))
    return float(np.hypot(stat, model)), model


def free_document(res: FreeResult, opt: FreeOptions, header: dict) -> dict:
    b = res.bundle
    tied = _tied(res)
    intr = {}
    for name, unit, get in (("sdd", "mm", lambda x: x.camera.sdd), ("c0", "px", lambda x: x.camera.c0),
                            ("r0", "px", lambda x: x.camera.r0)):
        total, model = _combine(b.sigma(name), [get(t) - get(b) for t in tied], [t.sigma(name) for t in tied])
        intr[name] = {"value": get(b), "sigma": total, "sigma_statistical": b.sigma(name), "sigma_model": model,
                      "unit": unit}
    dist = None
    if b.distortion is not None:
        names = [f"distortion_{n}" for n in b.distortion.names]
        sig = [b.sigma(n) if n in b.fit.names else 0.0 for n in names]
        dist = b.distortion.to_dict(sig)
        dist["family"] = b.family.name
        if b.family.free_centre:
            dist["centre_sigma"] = [b.sigma("distortion_c0"), b.sigma("distortion_r0")]
        if b.family.per_frame:
            dist["per_frame"] = list(b.family.per_frame)
        c, r = np.mgrid[0:b.camera.shape[0]:16, 0:b.camera.shape[1]:16]
        d = b.distortion.displacement(np.stack([r, c], -1).astype(float))
        dist["max_displacement_px"] = float(np.hypot(d[..., 0], d[..., 1]).max())
    none = res.pinhole or res.fits.get("none")
    frames = []
    for fr in res.frames:
        s = fr.get("slot")
        st = fr["status"]
        out = {"frame": fr["frame"], **st.fields()}
        best = fr["search"].best
        R, t = (b.R[s], b.t[s]) if s is not None and st.state != "rejected" and s < len(b.R) else \
            ((best.R, best.t) if best is not None else (np.eye(3), np.zeros(3)))
        out["R"], out["t"] = R, t
        if s is not None and s < len(b.R):
            rot_stat = np.degrees([b.sigma(f"frame{s}_{n}") for n in ("rx", "ry", "rz")])
            tr_stat = np.array([b.sigma(f"frame{s}_{n}") for n in ("tx", "ty", "tz")])
            rot_sp = [np.degrees(matrix_to_rotvec(x.R[s] @ b.R[s].T)) for x in tied]
            tr_sp = [x.t[s] - b.t[s] for x in tied]
            rot_sf = [np.degrees([x.sigma(f"frame{s}_{n}") for n in ("rx", "ry", "rz")]) for x in tied]
            tr_sf = [[x.sigma(f"frame{s}_{n}") for n in ("tx", "ty", "tz")] for x in tied]
            out["sigma_rotation_deg"] = [_combine(rot_stat[i], [v[i] for v in rot_sp], [v[i] for v in rot_sf])[0]
                                         for i in range(3)]
            if "mirror_spread_rad" in fr:
                spread = np.degrees(np.abs(fr["mirror_spread_rad"]))
                out["sigma_rotation_deg"] = [float(np.hypot(a, b_)) for a, b_ in zip(out["sigma_rotation_deg"], spread)]
            out["sigma_translation_mm"] = [_combine(tr_stat[i], [v[i] for v in tr_sp], [v[i] for v in tr_sf])[0]
                                           for i in range(3)]
            d, p = fr["pairs"]
            out["rms_px"] = fr.get("rms_px")
            if none is not None and s < len(none.R):
                sel = np.flatnonzero(_slot_mask(none, s))
                out["rms_px_pinhole"] = float(np.sqrt(np.mean(np.sum(none.residual_px[sel] ** 2, 1))))
            out["n_spheres"] = int(len(p))
            out["sphere_ids"] = [int(res.shape.ids[j]) for j in p]
            out["matched"] = [[int(i), int(res.shape.ids[j])] for i, j in zip(d, p)]
            if fr.get("set_aside"):
                out["set_aside"] = fr["set_aside"]
            seen = np.zeros(len(res.shape.points), bool)
            seen[np.asarray(p, int)] = True
            hidden = hidden_behind(b.frame_camera(s).geometry(), b.phantom(res.shape.points) @ R.T + t,
                                   res.shape.radius, seen, res.shape.ids)
            if hidden:
                out["hidden"] = hidden
            if b.family.per_frame and b.distortion is not None:
                out["distortion"] = b.frame_distortion(s).to_dict()
            if b.frame_intrinsics:
                out["intrinsics"] = {}
                for n in INTRINSICS:
                    v, sg = b.frame_intrinsic(s, n)
                    out["intrinsics"][n] = {"value": v, "sigma": sg, "unit": INTRINSIC_UNITS[n]}
                out.update(b.frame_camera(s).geometry().to_dict())
        if fr["search"].convention:
            out["convention"] = fr["search"].convention
        if fr.get("identified_by") and st.ok:
            out["identified_by"] = fr["identified_by"]
        if "mirror_delta_chi2" in fr:
            out["mirror_delta_chi2"] = fr["mirror_delta_chi2"]
        frames.append(out)
    reasons = Counter(f["status"].state for f in res.frames)
    ok_res = [np.sum(b.residual_px[_slot_mask(b, f.get("slot"))] ** 2, 1) for f in res.frames
              if f["status"].ok and f.get("slot") is not None]
    rms = float(np.sqrt(np.mean(np.concatenate(ok_res)))) if ok_res else float("nan")
    geo = b.camera.geometry().to_dict()
    doc = {**header, "motion": "free", **geo, "axes": [], "intrinsics": intr, "distortion": dist,
           "gauge": GAUGE + (TWIST_GAUGE if b.family.twist_centre else ""), "distortion_choice": res.choice, "phantom_refinement": _refinement(res),
           "marker_sigma_scale": res.sigma_scales,
           "phantom": {"planar": bool(res.shape.planar), "lattice": res.shape.lattice is not None,
                       "symmetries": len(res.shape.perms)},
           "units": {"t": "mm", "R": "rotation matrix, P_lab = R p_phantom + t", "rms_px": "px",
                     "sigma_rotation_deg": "deg (rotation vector components, lab axes)",
                     "sigma_translation_mm": "mm", "intrinsics": "sdd mm; c0, r0 px (principal point)"},
           "options": {"max_rms_px": opt.max_rms_px, "floor_factor": opt.floor_factor,
                       "outlier_factor": opt.outlier_factor, "distortion": opt.distortion, "folds": opt.folds,
                       "phantom_sigma_mm": opt.phantom_sigma_mm,
                       "frame_intrinsics_sigma": dict(opt.frame_intrinsics)},
           "summary": {"frames": len(frames), "ok": reasons.get("ok", 0), "ambiguous": reasons.get("ambiguous", 0),
                       "rejected": reasons.get("rejected", 0),
                       "reasons": dict(sorted(Counter(f["reason"] for f in frames if "reason" in f).items())),
                       "rms_px": rms, "chi2_reduced": b.fit.reduced_chi2,
                       "adequacy": _adequacy(rms, b.fit.reduced_chi2)},
           "frames": frames}
    return doc


def _slot_mask(b: Bundle, s) -> np.ndarray:
    return b.slot == s


def _adequacy(rms: float, chi2_red: float) -> str:
    """Whether the chosen model reaches the centres' stated noise, in words."""
    if not np.isfinite(chi2_red) or chi2_red <= 2.0:
        return f"at the noise floor (reduced chi-square {chi2_red:.2f})"
    k = float(np.sqrt(chi2_red))
    return (f"not at the noise floor: the model leaves {rms:.3f} px RMS, {k:.1f}x the centres' stated sigma; "
            f"structure no distortion family holds remains (conecal diagnose locates it); sigma are scaled by "
            f"{k:.1f} but do not hold the bias that structure puts in the intrinsics")


def _refinement(res) -> dict | None:
    """The held-out test of refining the phantom and, when kept, each sphere's
    offset (mm, phantom frame) from its CAD position with sigma."""
    if res.refinement is None:
        return None
    out = dict(res.refinement)
    b = res.bundle
    if b.point_offsets is not None:
        out["spheres"] = [{"id": int(i), "offset_mm": [float(v) for v in off],
                           "sigma_mm": [b.sigma(f"point{j}_{a}") for a in "xyz"]}
                          for j, (i, off) in enumerate(zip(res.shape.ids, b.point_offsets))]
    return out
