"""``diagnose`` on a free-pose calibration: where does the chosen model still miss?

fit-pose on a ``motion: free`` scan already chose the detector distortion
on held-out markers; what is left is located here, on the ok frames'
markers against the result's own prediction (camera, distortion, poses):

- a displacement field over the detector (2-D polynomials, degree chosen on
  held-out markers: ``locate.detector_field``): a distortion the families
  do not hold, or one that changes from frame to frame;
- one sphere whose mean residual, seen in the phantom's frame, is not zero:
  the phantom is not where its CAD file says (a sphere off by a fraction
  of a mm);
- frames whose residual exceeds the others' (a sagging C-arm, a frame with
  a wrong sphere, motion during the exposure);
- a place on the detector whose markers are displaced from those around it
  (``local_field``: a dent in an intensifier's screen). fit-pose sets such
  markers aside as outliers, so the detections it left out of an ok frame
  are paired again here with the sphere predicted nearest, where that is
  unambiguous, and judged with the others. A place found is reported first;
  its markers then stay out of the other tests (a dent's markers otherwise
  read as a sphere off its CAD position or as frames above the others).

Residuals are whitened by detect's sigma scaled up to the fit's own
scatter when detect's sigma is too small (as on real images). Nothing is
named: the verdict is "no structure beyond the noise floor" or "located,
not named: ...".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..calib.camera import Camera
from ..geometry.distortion import Distortion
from ..geometry.sphere import shadow_bias
from .local_field import local_displacements
from .locate import describe, detector_field


@dataclass
class _Obs:
    xy: np.ndarray
    sigma: np.ndarray


class _FreeView:
    """What ``detector_field`` reads: observations, residuals, detector shape."""

    stage = "fit-pose (free)"

    def __init__(self, xy, sigma, residual, geometry):
        self.obs = _Obs(xy, sigma)
        self._r = residual
        self.geometry = geometry

    def residual_px(self, effects=None, base=None):
        return self._r


def _prediction(doc, frame, P, radius):
    # a frame with its own intrinsics (--frame-intrinsics) is projected with them
    it = frame.get("intrinsics") or doc["intrinsics"]
    det = doc["detector"]
    cam = Camera(it["sdd"]["value"], it["c0"]["value"], it["r0"]["value"], float(-doc["source"][2]),
                 tuple(det["pixel_pitch"]), tuple(det["shape"]))
    X = P @ np.asarray(frame["R"]).T + np.asarray(frame["t"])
    q = cam.project(X) + shadow_bias(cam.geometry(), X, radius, coarse=True)
    dd = frame.get("distortion") or doc.get("distortion")
    return (Distortion.from_dict(dd).distort(q) if dd else q), cam


# a detection left out of an ok frame is paired with the sphere predicted
# nearest when the next prediction is this many times as far: within a sixth
# of the spheres' spacing (3.3 px of a 20 px pitch), far beyond the noise
# and well short of a neighbour
_UNAMBIGUOUS = 5.0


def _set_aside(ms: list, used: set, used_ids: set, pred: np.ndarray, ids: list) -> list:
    """The detections ``ms`` an ok frame left out (not in ``used``, not
    truncated), each as (detection index, sphere id) with the sphere (not
    in ``used_ids``) whose prediction ``pred`` (S, 2) px is nearest,
    where the second nearest is ``_UNAMBIGUOUS`` times as far; a sphere
    two detections claim is left out."""
    pairs = {}
    if len(ids) < 2:
        return []
    for i, m in enumerate(ms):
        if i in used or "truncated" in (m.get("flags") or []):
            continue
        d = np.hypot(pred[:, 0] - m["x"], pred[:, 1] - m["y"])
        j, k = np.argsort(d)[:2]
        if ids[j] in used_ids or d[k] < _UNAMBIGUOUS * d[j]:
            continue
        pairs.setdefault(ids[j], []).append(i)
    return [(v[0], s) for s, v in pairs.items() if len(v) == 1]


def diagnose_free(doc: dict, scan, markers: dict, alpha: float = 0.01) -> dict:
    pos = dict(zip(scan.phantom.ids.tolist(), scan.phantom.positions))
    # a result that refined the phantom is judged with the spheres where it put them
    for sph in (doc.get("phantom_refinement") or {}).get("spheres", []):
        pos[sph["id"]] = pos[sph["id"]] + np.asarray(sph["offset_mm"])
    radius = scan.config.markers.diameter / 2
    by_frame = {int(f["frame"]): f["markers"] for f in markers["frames"]}
    xy, sig, res, fid, sid, aside = [], [], [], [], [], []
    cam = None
    ids_all = scan.phantom.ids.tolist()
    for f in doc["frames"]:
        if f["status"] != "ok" or not f.get("matched"):
            continue
        ms = by_frame.get(int(f["frame"]), [])
        pred_all, cam = _prediction(doc, f, np.array([pos[s] for s in ids_all]), radius)
        at = dict(zip(ids_all, pred_all))
        pairs = list(f["matched"])
        extra = _set_aside(ms, {i for i, _ in pairs}, {s for _, s in pairs}, pred_all, ids_all)
        for i, s in pairs + extra:
            xy.append([ms[i]["x"], ms[i]["y"]])
            sig.append(ms[i].get("sigma") or 0.05)
            res.append(np.array(xy[-1]) - at[s])
            fid.append(int(f["frame"]))
            sid.append(s)
        aside += [False] * len(pairs) + [True] * len(extra)
    if not xy:
        return {"verdict": "nothing to diagnose: no frame is ok", "located": [], "claims": []}
    xy, res = np.array(xy, float), np.array(res, float)
    sig = np.array(sig, float)
    fid, sid, aside = np.array(fid), np.array(sid), np.array(aside)
    used = ~aside
    n_par = 3 + 6 * len(np.unique(fid))
    chi2_red = float(np.sum((res[used] / sig[used, None]) ** 2) / max(1, 2 * used.sum() - n_par))
    scale = float(np.sqrt(max(1.0, chi2_red)))
    s_eff = sig * scale
    rms = float(np.sqrt(np.mean(np.sum(res[used] ** 2, 1))))
    n_markers, n_frames = int(used.sum()), int(len(np.unique(fid[used])))
    located, tests = [], []
    places, inside, n_places = local_displacements(xy, res, s_eff, fid, tuple(doc["detector"]["shape"]), alpha)
    located += places
    tests.append({"variable": "detector position (local)", "tested": n_places, "significant": len(places),
                  "set_aside_paired": int(aside.sum())})
    # the remaining tests on the markers the fit used, outside any place found
    keep = used & ~inside
    xy, res, sig, s_eff, fid, sid = (v[keep] for v in (xy, res, sig, s_eff, fid, sid))
    field = detector_field(_FreeView(xy, s_eff, res, cam.geometry()), None, None, alpha)
    if field:
        located.append(field)
    # per sphere: the mean residual turned into the phantom frame (pose-independent CAD error)
    sph_p = []
    for s in np.unique(sid):
        sel = sid == s
        if sel.sum() < 3:
            continue
        z = res[sel] / s_eff[sel, None]
        c2 = float(np.sum(z.mean(0) ** 2) * sel.sum())
        sph_p.append((s, float(chi2_dist.sf(c2, 2)), float(np.hypot(*res[sel].mean(0)))))
    m = max(1, len(sph_p))
    bad_s = [(s, min(1.0, m * p), size) for s, p, size in sph_p if m * p < alpha]
    tests.append({"variable": "sphere id", "tested": len(sph_p), "significant": len(bad_s)})
    if bad_s:
        worst = max(bad_s, key=lambda t: t[2])
        located.append({"component": "one sphere's mean residual", "unit": "px", "variable": "sphere id",
                        "shape": f"{len(bad_s)} sphere(s) off their CAD position (largest: id {worst[0]})",
                        "size": worst[2], "size_px": worst[2], "p_adjusted": worst[1], "also_follows": [],
                        "spheres": [int(s) for s, _, _ in bad_s]})
    # per frame: residual chi-square against the pooled scatter
    fr_p = []
    for k in np.unique(fid):
        sel = fid == k
        c2 = float(np.sum((res[sel] / s_eff[sel, None]) ** 2))
        dof = max(1, 2 * int(sel.sum()) - 6)
        fr_p.append((int(k), float(chi2_dist.sf(c2, dof)), float(np.sqrt(np.mean(np.sum(res[sel] ** 2, 1))))))
    m = max(1, len(fr_p))
    bad_f = [(k, min(1.0, m * p), rms) for k, p, rms in fr_p if m * p < alpha]
    tests.append({"variable": "frame", "tested": len(fr_p), "significant": len(bad_f)})
    if bad_f:
        worst = max(bad_f, key=lambda t: t[2])
        located.append({"component": "frame residual", "unit": "px", "variable": "frame",
                        "shape": f"{len(bad_f)} frame(s) above the others (worst: frame {worst[0]})",
                        "size": worst[2], "size_px": worst[2], "p_adjusted": worst[1], "also_follows": [],
                        "frames": [k for k, _, _ in bad_f]})
    verdict = ("no structure beyond the noise floor" if not located else
               "located, not named: " + "; ".join(describe(loc) for loc in located))
    located = [dict(loc, level="geometry", description=describe(loc)) for loc in located]
    return {"verdict": verdict, "located": located, "tests": tests, "claims": [],
            "rms_px": rms, "chi2_reduced": chi2_red, "sigma_scale": scale,
            "n_markers": n_markers, "n_frames": n_frames,
            "note": ("free-pose result: fit-pose already chose the detector distortion on held-out markers "
                     f"({(doc.get('distortion') or {}).get('family', 'none')}); diagnose locates what the chosen "
                     "model still misses; the image level is not run on free-pose results yet")}
