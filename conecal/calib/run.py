"""``fit-pose`` on a ``motion: free`` scan: search, bundle, distortion choice, status.

1. Every frame's spheres are identified from the pattern (``search.py``),
   with the log's rough pose guess when it has one.
2. The identified frames are bundle-adjusted together (``bundle.py``) for
   every distortion family; spheres the search missed are picked up at
   the bundle's prediction, and markers whose residual is far beyond the
   scan's noise floor are set aside (fit-pose judges markers by its own
   residuals, not by detect's flags alone).
3. The family is chosen on held-out markers (``choose.py``); the chosen
   bundle is refitted.
4. A frame is ``ok`` only with a unique identity and a residual at the
   noise floor (RMS within ``floor_factor`` of the scan's pooled RMS and
   below ``max_rms_px``); a planar phantom's mirror pose that fits as well
   makes it ``ambiguous``. Rejected frames leave the bundle, which is
   solved again without them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..documents.status import rejected
from ..errors import FitError
from ..geometry import rotvec_to_matrix
from .bundle import FAMILIES, Bundle, Family, Observations, adjust, family_named
from .twist import seed_twists
from .alternatives import centred_alternative, restarted_alternative
from .camera import Camera, Field
from .choose import choose_family, choose_refinement
from .partial import partial_maps
from .judge import judge, mirrors
from .neighbours import in_sequence
from .phantom import describe_phantom
from .restart import from_before
from .candidate import assign
from .search import SearchOptions, held_back, search_frame
from .second_look import second_look


@dataclass(frozen=True)
class FreeOptions:
    """max_rms_px: a frame above this RMS is rejected; floor_factor: a frame's
    RMS may exceed the scan's pooled RMS by this factor; outlier_factor: a
    marker beyond this many pooled RMS is set aside; distortion: 'auto'
    (chosen on held-out markers) or a family name; folds: held-out groups;
    mirror_chi2: a mirror pose within this chi-square of the fit ties;
    frame_intrinsics: (name, prior sigma) pairs of intrinsics freed per
    frame (sdd mm; c0, r0 px), for a C-arm that sags between views;
    phantom_sigma_mm: prior sigma of each sphere's offset from its CAD
    position when the phantom is refined (kept only if held-out markers
    say so), 0: never refined."""

    max_rms_px: float = 1.0
    floor_factor: float = 2.5
    outlier_factor: float = 5.0
    distortion: str = "auto"
    folds: int = 5
    mirror_chi2: float = 25.0
    search: SearchOptions = SearchOptions()
    frame_intrinsics: tuple = ()
    phantom_sigma_mm: float = 0.1


@dataclass
class FreeResult:
    camera: Camera
    bundle: Bundle | None
    frames: list          # per frame dict (frame, status, R, t, ...)
    choice: list          # rows of the distortion choice
    shape: object
    convention: str
    fits: dict            # family name -> bundle on the final frames
    refinement: dict | None = None   # the held-out test of refining the phantom
    pinhole: Bundle | None = None    # no distortion, the phantom as its file says (rms_px_pinhole)
    # flag class -> {"factor": detect's sigma scaled by, "markers": n} (empty: not rescaled)
    sigma_scales: dict = field(default_factory=dict)


def _detections(frame: dict):
    """(centres (n, 2) px, detect's sigma (n,) px, flag class (n,): the
    marker's flags joined, 'unflagged' for none)."""
    ms = frame["markers"]
    xy = np.array([[m["x"], m["y"]] for m in ms], float).reshape(-1, 2)
    sig = np.array([m.get("sigma") or 0.05 for m in ms], float)
    cls = np.array([",".join(sorted(m.get("flags") or [])) or "unflagged" for m in ms], dtype=object)
    return xy, np.maximum(sig, 1e-3), cls


# a flag class's sigma is rescaled only from this many of its markers, and
# only when its residuals' scale differs from the scan's by more than this
# factor (the median of n chi-square(2) values scatters by ~1.7 / sqrt(n))
_CLASS_MIN = 20
_CLASS_DIFFERS = 1.25


def _class_scales(b: Bundle, obs: Observations, usable: list, dets: dict) -> dict:
    """Each flag class's sigma factor, from the bundle's own residuals: the
    median of (|r| / sigma)^2 over the class's markers against the median
    over all (a robust variance component per class: detect's sigma may be
    right for separated shadows and several times too small for overlapping
    ones). Classes with fewer than _CLASS_MIN markers keep 1."""
    cls = _row_classes(usable, dets, obs)
    if cls is None:
        return {}
    z2 = np.sum(b.residual_px ** 2, 1) / obs.sigma ** 2
    whole = float(np.median(z2))
    out = {}
    for c in np.unique(cls):
        m = cls == c
        if m.sum() >= _CLASS_MIN and whole > 0:
            out[str(c)] = {"factor": float(np.sqrt(np.median(z2[m]) / whole)), "markers": int(m.sum())}
    return out


def _rescaled(dets: dict, scales: dict) -> bool:
    """Each detection's sigma times its flag class's factor, when some class
    differs from the scan by more than _CLASS_DIFFERS; returns whether."""
    f = {c: v["factor"] for c, v in scales.items()}
    if len(f) < 2 or all(1 / _CLASS_DIFFERS <= v <= _CLASS_DIFFERS for v in f.values()):
        return False
    for k, (xy, sig, cls) in dets.items():
        dets[k] = (xy, sig * np.array([f.get(str(c), 1.0) for c in cls]), cls)
    return True


def shadow_depth(markers: dict, diameter_mm: float, cam: Camera) -> float | None:
    """The phantom's distance from the source (mm) its markers' shadows say:
    the nominal sdd over the median magnification 2 r pitch / diameter of
    the markers with a radius (px), not flagged overlap or truncated (whose
    radius is no one sphere's); None for fewer than 20. (A shadow's moment
    radius reads 0.92-0.98 of its own: the depth a few % long, well inside
    the search's 0.85-1.17.)"""
    r = [m["radius"] for f in markers["frames"] for m in f["markers"]
         if not {"overlap", "truncated"} & set(m.get("flags", ())) and m.get("radius") is not None
         and np.isfinite(m["radius"]) and m["radius"] > 0]
    if len(r) < 20:
        return None
    m = 2 * float(np.median(r)) * float(np.sqrt(np.prod(cam.pitch))) / diameter_mm
    return float(cam.sdd / m)


def _guesses(scan):
    extra = scan.log.extra
    if not extra:
        return None
    W = np.deg2rad(np.column_stack([extra["rx"], extra["ry"], extra["rz"]]))
    T = np.column_stack([extra["tx"], extra["ty"], extra["tz"]])
    return [(rotvec_to_matrix(w), t) for w, t in zip(W, T)]


# the nominal sod is searched about unless the shadows put the phantom farther
# off than this factor (the search's depths span 0.85-1.17 of it)
_DEPTH_KEPT = 1.1


def calibrate_free(scan, markers: dict, geometry, opt: FreeOptions = FreeOptions(), progress=None,
                   say=lambda s: None) -> FreeResult:
    """Calibrate ``scan`` (motion: free) from ``markers`` (conecal-markers/1);
    ``geometry``: the starting (nominal) ConeGeometry in the free-pose lab
    frame. ``progress(done, total)``, ``say(line)``: feedback."""
    cam = Camera.nominal(geometry, scan.config.nominal.sod)
    cam = replace(cam, field=Field.from_mask(getattr(scan.stack, "field_mask", None)))
    radius = scan.config.markers.diameter / 2
    shape = describe_phantom(scan.phantom.positions, scan.phantom.ids, radius=radius)
    guesses = _guesses(scan)
    by_frame = {int(f["frame"]): f for f in markers["frames"]}
    depth = shadow_depth(markers, scan.config.markers.diameter, cam)
    if depth is not None and abs(np.log(depth / cam.sod)) > np.log(_DEPTH_KEPT):
        say(f"the markers' shadows put the phantom {depth:.0f} mm from the source, not the nominal sod "
            f"{cam.sod:g} mm: the pose search looks there")
        opt = replace(opt, search=replace(opt.search, depth_mm=depth))
    frames = []
    dets = {}
    order = [int(k) for k in scan.log.frame]
    for n, k in enumerate(order):
        f = by_frame.get(k, {"markers": []})
        xy, sig, cls = _detections(f)
        dets[k] = (xy, sig, cls)
        res = search_frame(cam, shape, xy, guesses[n] if guesses else None, opt.search)
        frames.append({"frame": k, "search": res, "status": res.status})
        if progress:
            progress(n + 1, len(order))
    weak = held_back([fr["search"] for fr in frames], [len(dets[fr["frame"]][0]) for fr in frames])
    for fr, why in zip(frames, weak):
        fr["status"] = why or fr["status"]
    usable = [fr for fr in frames if fr["status"].ok]
    say(f"identified {len(usable)}/{len(frames)} frames from the pattern"
        + (f" ({sum(w is not None for w in weak)} more weakly, left to the second look)" if any(weak) else ""))
    if len(usable) < 2:
        reasons = sorted({fr["status"].sentence for fr in frames})
        raise FitError(f"{len(usable)} of {len(frames)} frames identified; a calibration needs 2 or more "
                       f"(first reason: {reasons[0] if reasons else 'no frames'})")
    fams = FAMILIES if opt.distortion == "auto" else (family_named("none"), family_named(opt.distortion))
    scales, rescaled = {}, False
    before = None
    for look in range(2):
        in_sequence(cam, shape, usable)
        final, fits, choice, refinement, pinhole, usable, obs = _solve(fams, cam, usable, dets, shape, radius, opt,
                                                                        before)
        if look:
            break
        before = (final, [fr["frame"] for fr in usable])
        # fit-pose judges detect's sigma by its own residuals, per flag class
        scales = _class_scales(final, obs, usable, dets)
        rescaled = _rescaled(dets, scales)
        if rescaled:
            say("marker sigma per flag class, from the residuals: " + ", ".join(
                f"{c} x{v['factor']:.2f} ({v['markers']})" for c, v in scales.items()))
        # frames the search left ambiguous or got wrong, and frames that leave
        # markers unexplained, searched again with the calibrated camera; the
        # bundle is solved again when an identification changed
        won, lost = second_look(final, [fr for fr in frames if fr not in usable], usable, dets, shape,
                                final.phantom(shape.points), opt)
        if not won and not lost and not rescaled:
            break
        if won or lost:
            say(f"second look with the calibrated camera: {len(won)} frame(s) identified anew, "
                f"{len(lost)} no longer unique")
        usable = sorted({id(fr): fr for fr in usable + won if fr not in lost}.values(),
                        key=lambda fr: order.index(fr["frame"]))
    mirrors(final, usable, obs, shape, radius, opt)
    if opt.distortion == "auto":
        centred_alternative(final, fits, choice, obs, shape.points, radius, cam, opt.folds)
        restarted_alternative(final, fits, choice, obs, shape.points, radius, cam, opt.folds)
    # (the conventions the ok frames were labelled by: a frame left ambiguous
    # keeps the search's, which in_sequence replaced on the others)
    conv = sorted({fr["search"].convention for fr in frames if fr["status"].ok and fr["search"].convention})
    return FreeResult(final.camera, final, frames, choice, shape, "; ".join(conv), fits, refinement, pinhole,
                      scales if rescaled else {})


def _solve(fams, cam, usable, dets, shape, radius, opt: FreeOptions, before=None):
    """Bundle, distortion choice and frame judgement until no frame is
    rejected; returns (final, fits, choice, refinement, pinhole, usable, obs).
    ``before``: see ``restart.from_before``."""
    bar = 0.0
    for attempt in range(6):
        obs, fits, usable = _fit_families(fams, cam, usable, dets, shape, radius, opt, before)
        if opt.distortion == "auto":
            chosen, choice = choose_family(fits, obs, shape.points, radius, opt.folds)
        else:
            chosen, choice = family_named(opt.distortion), [{"family": opt.distortion, "chosen": True,
                                                             "why": "named by --distortion"}]
        pinhole = fits["none"]
        chosen, choice, fits, start, refinement = _refine_phantom(chosen, choice, fits, fams, cam, obs, shape,
                                                                  radius, opt)
        final = fits[chosen.name] = adjust(chosen, cam, obs, shape.points, radius, None, None,
                                           start=start, max_nfev=100)
        cls = _row_classes(usable, dets, obs)
        dropped, bar = judge(final, usable, obs, opt, bar,
                              None if cls is None else np.array(["overlap" in c for c in cls]),
                              anew=shape.lattice is None and bool(partial_maps(shape.points)))
        if not dropped:
            return final, fits, choice, refinement, pinhole, usable, obs
        usable = [fr for fr in usable if fr["status"].ok]
        if len(usable) < 2:
            raise FitError("fewer than 2 frames left at the noise floor")
    raise FitError("frames kept being rejected after 6 bundle adjustments; the model does not fit this scan")


def _refine_phantom(chosen, choice, fits, fams, cam, obs: Observations, shape, radius, opt: FreeOptions):
    """The spheres may not sit where the CAD file says (a drilled plate: a tenth
    of a mm): the chosen family refitted with every sphere's offset free, kept
    only if held-out markers are predicted better. A phantom off its file leaks
    into the distortion, so when kept the families are chosen again with the
    spheres where the refit put them. Returns (chosen, choice, fits, the bundle
    to start the final fit from, the test's row or None)."""
    start = fits[chosen.name]
    if opt.phantom_sigma_mm <= 0:
        return chosen, choice, fits, start, None
    refined = adjust(chosen, cam, obs, shape.points, radius, None, None, start=start,
                     points_sigma=opt.phantom_sigma_mm)
    use, refinement = choose_refinement(start, refined, obs, shape.points, radius, opt.folds)
    if not use:
        return chosen, choice, fits, start, refinement
    if opt.distortion == "auto":
        moved = refined.phantom(shape.points)
        fits = {f.name: adjust(f, cam, obs, moved, radius, None, None, start=fits[f.name], max_nfev=30) for f in fams}
        chosen, choice = choose_family(fits, obs, moved, radius, opt.folds)
        refined = replace(fits[chosen.name], point_offsets=refined.point_offsets, points_sigma=refined.points_sigma)
    return chosen, choice, fits, refined, refinement


def _fit_families(fams, cam, usable, dets, shape, radius, opt, before=None):
    """Bundle every family on ``usable`` frames: from the search's poses, then
    again after re-gathering markers at the most flexible fit's prediction
    (and from ``before``: ``restart.from_before``)."""
    obs, slots = _observations(usable, dets)
    R0 = np.array([fr["search"].best.R for fr in usable])
    t0 = np.array([fr["search"].best.t for fr in usable])
    fi = dict(opt.frame_intrinsics)
    base = adjust(family_named("none"), cam, obs, shape.points, radius, R0, t0, frame_intrinsics=fi)
    fits = {"none": base}
    for fam in fams[1:]:
        fits[fam.name] = adjust(fam, cam, obs, shape.points, radius, R0, t0, start=_nested(fam, fits, obs, shape))
    from_before(fits, before, usable, cam, obs, shape, radius)
    flexible = min(fits.values(), key=lambda b: float(np.mean(np.sum(b.residual_px ** 2, 1))))
    obs, kept = _regather(flexible, obs, usable, dets, shape, radius, opt)
    idx = [slots[fr["frame"]] for fr in kept]
    R0, t0 = flexible.R[idx], flexible.t[idx]
    fits = {"none": adjust(family_named("none"), cam, obs, shape.points, radius, R0, t0, frame_intrinsics=fi)}
    for fam in fams[1:]:
        # a family the data hardly constrain (a per-frame twist on an undistorted
        # detector) creeps; 30 evaluations are enough to score it
        fits[fam.name] = adjust(fam, cam, obs, shape.points, radius, R0, t0, start=_nested(fam, fits, obs, shape),
                                max_nfev=30)
    from_before(fits, before, kept, cam, obs, shape, radius)
    for s, fr in enumerate(kept):
        fr["slot"] = s
    return obs, fits, kept


def _nested(fam: Family, fits: dict, obs: Observations, shape) -> Bundle:
    """The fit to start ``fam`` from: the richest one already made of a family
    nested in it (same model, no term it does not free), else the pinhole's;
    for a family whose twist turns about a centre per frame, with each
    frame's twist and centre seeded (``twist.seed_twists``)."""
    def inside(f: Family) -> bool:
        return (f.model == fam.model and set(f.shared) <= set(fam.shared) and set(f.per_frame) <= set(fam.per_frame)
                and f.free_centre <= fam.free_centre and f.twist_centre <= fam.twist_centre)
    nested = [b for b in fits.values() if b.family.model is not None and inside(b.family)]
    if not nested:
        return fits["none"]
    start = max(nested, key=lambda b: (b.family.k_frame, b.family.k))
    if fam.twist_centre and start.twist is None:
        start = seed_twists(start, fam, obs, shape.points)
    return start


def _pairs(fr: dict):
    """A frame's (detections, spheres) as the bundle takes them."""
    return fr.get("pairs") or (fr["search"].best.det, fr["search"].best.sph)


def _gather(usable, dets, j: int) -> np.ndarray:
    """Item ``j`` of ``dets`` (0 centres, 1 sigma, 2 flag class) of every
    bundled detection, in the bundle's row order."""
    return np.concatenate([dets[fr["frame"]][j][np.asarray(_pairs(fr)[0], int)] for fr in usable])


def _row_classes(usable, dets, obs: Observations) -> np.ndarray | None:
    """detect's flag class of each of the bundle's rows ``obs``, or None when
    the frames' pairs are not those rows in their order."""
    cls = _gather(usable, dets, 2)
    if len(cls) != len(obs) or not np.array_equal(_gather(usable, dets, 1), obs.sigma):
        return None
    return cls


def _observations(usable, dets):
    slots = {fr["frame"]: s for s, fr in enumerate(usable)}
    slot = np.concatenate([np.full(len(_pairs(fr)[0]), s) for s, fr in enumerate(usable)])
    sph = np.concatenate([np.asarray(_pairs(fr)[1], int) for fr in usable])
    return Observations(slot, sph, _gather(usable, dets, 0), _gather(usable, dets, 1)), slots


def _regather(b: Bundle, obs: Observations, usable, dets, shape, radius, opt: FreeOptions):
    """Re-assign every frame's detections at the bundle's prediction, within
    ``outlier_factor`` pooled RMS (at least 0.5 px): picks up spheres the
    search missed, sets aside markers the model cannot explain. A marker is
    also set aside when its residual exceeds ``outlier_factor`` robust scales
    of the fit's residuals in units of its own sigma (a blob merged with
    clutter keeps its neighbours' sigma: 0.5 px off at sigma 0.05 is well
    inside the px gate, yet pulls the whole bundle)."""
    pooled = float(np.sqrt(np.mean(np.sum(b.residual_px ** 2, 1))))
    gate = max(0.5, opt.outlier_factor * pooled)
    # (|r| / sigma of a 2-D Gaussian has median 1.1774 sigma's scale)
    scale = float(np.median(np.linalg.norm(b.residual_px, axis=1) / obs.sigma)) / 1.1774
    pts = b.phantom(shape.points)
    found, far = [], np.zeros(len(pts))
    seen = np.zeros(len(pts))
    for s, fr in enumerate(usable):
        X, S = dets[fr["frame"]][:2]
        pred = b.predict(pts, np.full(len(pts), s), radius)
        p, d = assign(pred, X, gate)
        out = np.linalg.norm(pred[p] - X[d], axis=1) > opt.outlier_factor * scale * S[d]
        found.append((p, d, out))
        np.add.at(seen, p, 1)
        np.add.at(far, p[out], 1)
    # a sphere off in most of its frames is the phantom's or the model's error
    # (a sphere off its CAD position), for the refinement and diagnose, not gross
    systematic = far > 0.3 * np.maximum(seen, 1)
    for fr, (p, d, out) in zip(usable, found):
        good = ~out | systematic[p]
        p, d = p[good], d[good]
        fr["pairs"] = (d, p)
        fr["set_aside"] = int(len(fr["search"].best.det) - len(np.intersect1d(d, fr["search"].best.det)))
    keep = [fr for fr in usable if len(fr["pairs"][0]) >= opt.search.min_spheres]
    for fr in usable:
        if fr not in keep:
            fr["slot"] = None
            fr["status"] = rejected("off_prediction",
                                    f"{len(fr['pairs'][0])} markers within {gate:.2f} px of the bundle's prediction")
    obs, _ = _observations(keep, dets)
    return obs, keep
