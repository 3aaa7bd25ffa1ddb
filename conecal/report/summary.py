"""What an engineer reads first about a geometry: distances, magnification,
principal point, detector tilts, calibrated axes, the reference sphere, and
(for a simulated scan) the errors against the truth. One home for the
terminal report and the HTML page.

Lab frame, mm and degrees; pixel coordinates (column, row).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..binding import bound_scans
from ..errors import InputError
from ..geometry import ConeGeometry
from ..jsonio import read_json


def _centre_of_rotation(doc: dict) -> tuple[np.ndarray, str]:
    """The point the set-up is measured to: a calibrated rotary axis' foot
    from the source, else the lab origin."""
    g = ConeGeometry.from_dict(doc)
    for a in doc.get("axes", []):
        if a.get("type") == "rotary" and (a.get("calibrated_here") or doc.get("stage") == "rp-grid"):
            d, p = np.asarray(a["direction"], float), np.asarray(a.get("point", [0, 0, 0]), float)
            foot = p + ((g.source - p) @ d) * d
            return foot, f"rotation axis {a['name']}"
    return np.zeros(3), "lab origin"


def geometry_rows(doc: dict) -> list[tuple[str, str, str]]:
    """(quantity, value, unit) rows of a geometry or poses document."""
    g = ConeGeometry.from_dict(doc)
    centre, what = _centre_of_rotation(doc)
    ray = centre - g.source
    sod = float(np.linalg.norm(ray))
    sdd = float(g.sdd)
    c = ray / sod
    n = g.normal if g.normal @ c > 0 else -g.normal
    # out-of-plane tilts: the central ray seen in the detector's (u, n) and (v, n) planes
    tilt_u = np.degrees(np.arctan2(c @ g.v, c @ n))
    tilt_v = np.degrees(np.arctan2(c @ g.u, c @ n))
    inplane = np.degrees(np.arctan2(g.u[1], g.u[0]))
    pp = g.principal_point
    hit = g.pixel_of_plane_point(g.source + c * (((g.detector_origin - g.source) @ n) / max(c @ n, 1e-12)))
    mag = float(g.magnification(centre[None])[0])
    rows = [(f"SOD (source to {what})", f"{sod:.4f}", "mm"),
            ("SDD (source to detector plane)", f"{sdd:.4f}", "mm"),
            (f"magnification at the {what}", f"{mag:.5f}", ""),
            ("principal point (foot of the source's perpendicular)", f"({pp[0]:.2f}, {pp[1]:.2f})", "px (c, r)"),
            (f"central ray (source to {what}) meets the detector at", f"({hit[0]:.2f}, {hit[1]:.2f})", "px (c, r)"),
            ("detector tilt about u (central ray in the v-n plane)", f"{tilt_u:+.4f}", "deg"),
            ("detector tilt about v (central ray in the u-n plane)", f"{tilt_v:+.4f}", "deg"),
            ("detector in-plane rotation (u against lab x)", f"{inplane:+.4f}", "deg"),
            ("pixel pitch", f"{g.pixel_pitch[0]:g} x {g.pixel_pitch[1]:g}", "mm"),
            ("detector", f"{g.shape[0]} rows x {g.shape[1]} cols", "")]
    for a in doc.get("axes", []):
        if a.get("type") == "rotary" and (a.get("calibrated_here") or doc.get("stage") == "rp-grid"):
            d = np.round(np.asarray(a["direction"], float), 6).tolist()
            p = np.round(np.asarray(a.get("point", [0, 0, 0]), float), 4).tolist()
            rows.append((f"rotation axis {a['name']}: direction", str(d), "unit vector, lab"))
            rows.append((f"rotation axis {a['name']}: point", str(p), "mm, lab"))
    refs = [s for s in doc.get("spheres", []) if s.get("reference")]
    if doc.get("spheres") is not None:
        rows.append(("reference sphere (at the lab origin at zero readings)",
                     ", ".join(f"id {s['id']}" for s in refs) if refs else "none: every sphere fitted", ""))
    return rows


def truth_lines(doc: dict, path) -> list[str]:
    """For a simulated scan (truth.json beside its scan.yaml): the result's errors."""
    scans = bound_scans(doc, path)
    truth_path = scans[0] / "truth.json" if len(scans) == 1 else None
    if truth_path is None or not Path(truth_path).is_file():
        return []
    try:
        truth = read_json(truth_path, "conecal-truth")
    except InputError:
        return []
    out = []
    if truth.get("misalignment") and doc.get("misalignment"):
        out.append("vs truth: " + ", ".join(
            f"{n} {doc['misalignment'][n]['value'] - v:+.4f}" for n, v in truth["misalignment"].items()
            if n in doc["misalignment"]))
    if not truth.get("geometry"):
        return out
    g, t = ConeGeometry.from_dict(doc), ConeGeometry.from_dict(truth["geometry"])
    ang = np.degrees(np.arccos(np.clip(np.dot(g.normal, t.normal), -1, 1)))
    axis = truth.get("rotary_axis")
    fitted = next((a for a in doc.get("axes", []) if a.get("calibrated_here") and a.get("type") == "rotary"), None)
    if axis and fitted:
        d = np.asarray(fitted["direction"])
        dp = np.asarray(fitted["point"]) - axis["point"]
        dp -= (dp @ d) * d
        out.append(f"vs truth: rotary axis {fitted['name']} direction "
                   f"{np.degrees(np.arccos(min(1.0, abs(d @ axis['direction'])))):.5f} deg, "
                   f"point {np.linalg.norm(dp):.5f} mm")
    out.append(f"vs truth ({truth_path}): source {np.linalg.norm(g.source - t.source):.4f} mm, "
               f"detector centre {np.linalg.norm(g.detector_centre - t.detector_centre):.4f} mm, "
               f"detector normal {ang:.4f} deg, u {np.degrees(np.arccos(np.clip(g.u @ t.u, -1, 1))):.4f} deg")
    return out
