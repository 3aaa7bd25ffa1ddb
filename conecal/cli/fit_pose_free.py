"""``conecal fit-pose`` on a ``motion: free`` scan (thin: the work is in conecal.calib)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import __version__
from ..calib.bundle import FAMILIES
from ..calib.camera import INTRINSIC_UNITS
from ..calib.document import free_document
from ..calib.mirrored import mirror_hint
from ..calib.run import FreeOptions, calibrate_free
from ..documents.status import reason_lines
from ..errors import FitError, InputError
from ..geometry import ConeGeometry
from ..jsonio import read_json, rounded, write_json
from .options import info, progress_bar

POSES_FORMAT = "conecal-poses/1"


FRAME_PRIOR = {"sdd": 5.0, "c0": 5.0, "r0": 5.0}     # mm, px, px


def parse_frame_intrinsics(text: str | None) -> tuple:
    """``sdd,c0=3,r0=3`` -> (("sdd", 5.0), ("c0", 3.0), ("r0", 3.0)); InputError on a bad item."""
    if not text:
        return ()
    out = {}
    for item in text.split(","):
        name, _, sig = item.strip().partition("=")
        if name not in FRAME_PRIOR:
            raise InputError(f"--frame-intrinsics {text}: {name!r} is not one of sdd, c0, r0")
        try:
            value = float(sig) if sig else FRAME_PRIOR[name]
        except ValueError:
            raise InputError(f"--frame-intrinsics {text}: {sig!r} is not a number (the prior sigma of {name})") from None
        if not value > 0 or not np.isfinite(value):
            raise InputError(f"--frame-intrinsics {text}: the prior sigma of {name} must be positive")
        out[name] = value
    return tuple(out.items())


def run_free(s, scan, mdoc, markers, geometry, output, max_rms, distortion, frame_intrinsics=None,
             phantom_sigma=None) -> None:
    names = [f.name for f in FAMILIES]
    fi = parse_frame_intrinsics(frame_intrinsics)
    if distortion != "auto" and distortion not in names:
        raise InputError(f"--distortion {distortion}: expected auto or one of {', '.join(names)}")
    g = ConeGeometry.from_dict(read_json(geometry, "conecal-geometry")) if geometry else s.nominal_geometry()
    if geometry and (abs(g.u[0] - 1) > 1e-9 or abs(g.v[1] - 1) > 1e-9 or abs(g.source[0]) + abs(g.source[1]) > 1e-9):
        raise InputError(f"{geometry}: a free-pose calibration starts from a geometry in its own frame "
                         "(source on the z axis, u = +x, v = +y); give none to start from the nominal one")
    opt = FreeOptions(max_rms_px=max_rms if max_rms is not None else FreeOptions.max_rms_px, distortion=distortion,
                      frame_intrinsics=fi,
                      phantom_sigma_mm=phantom_sigma if phantom_sigma is not None else FreeOptions.phantom_sigma_mm)
    try:
        with progress_bar("fit-pose (pose search)") as prog:
            res = calibrate_free(s, mdoc, g, opt, progress=prog, say=info)
    except FitError as exc:
        hint = mirror_hint(s, mdoc, g, opt, calibrate_free, say=info)
        if hint is None:
            raise
        raise FitError(f"{exc}; {hint}") from None
    header = {"format": POSES_FORMAT, "software": f"conecal {__version__}", "scan": str(scan),
              "markers_from": str(markers), "geometry_from": str(geometry) if geometry else "nominal"}
    if output != "-":   # diagnose finds the markers from the result's folder, whatever the cwd
        header["markers_from_relative"] = Path(os.path.relpath(Path(markers).resolve(),
                                                               Path(output).resolve().parent)).as_posix()
    doc = free_document(res, opt, header)
    write_json(output, rounded(doc))
    sm = doc["summary"]
    it = doc["intrinsics"]
    info(f"wrote {output}: {sm['ok']}/{sm['frames']} frames ok, {sm['ambiguous']} ambiguous, {sm['rejected']} "
         f"rejected; reprojection RMS {sm['rms_px']:.4f} px")
    for line in reason_lines(sm["reasons"]):
        info(line)
    ref = doc["phantom_refinement"]
    if ref and ref["chosen"]:
        big = max(ref["spheres"], key=lambda r: float(np.linalg.norm(r["offset_mm"])))
        info(f"phantom refined: held-out {ref['heldout_rms_px_cad']:.3f} -> {ref['heldout_rms_px_refined']:.3f} px; "
             f"spheres off phantom.csv by up to {np.linalg.norm(big['offset_mm']):.3f} mm (id {big['id']})")
    if not sm["adequacy"].startswith("at the noise floor"):
        info(sm["adequacy"])
    d = doc["distortion"]
    info(f"sdd {it['sdd']['value']:.3f} +- {it['sdd']['sigma']:.3f} mm, principal point "
         f"({it['c0']['value']:.2f} +- {it['c0']['sigma']:.2f}, {it['r0']['value']:.2f} +- {it['r0']['sigma']:.2f}) px; "
         + (f"distortion {d['family']} (up to {d['max_displacement_px']:.2f} px)" if d else "no distortion claimed"))
    if fi:
        per = [f["intrinsics"] for f in doc["frames"] if "intrinsics" in f]
        spread = {n: (min(p[n]["value"] for p in per), max(p[n]["value"] for p in per)) for n, _ in fi}
        info("per frame: " + "; ".join(f"{n} {lo:.2f} to {hi:.2f} {INTRINSIC_UNITS[n]}"
                                       for n, (lo, hi) in spread.items()))
    if res.convention:
        info(f"phantom symmetry: {res.convention}")
