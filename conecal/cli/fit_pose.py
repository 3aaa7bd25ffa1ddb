"""``conecal fit-pose``: per-frame 6-DoF pose of a robot-held marker holder."""

from __future__ import annotations

import click
import numpy as np

from .. import __version__
from ..binding import check_scan
from ..calib.rescue import rescue_frame
from ..documents.status import reason_lines
from ..errors import FitError
from ..fit.markers import read_markers
from ..fit.pose import PoseOptions, fit_helix, fit_poses, placement_errors
from ..fit.pose_parts import poses_totals
from ..fit.pose import refine_geometry as refine_geometry_fn
from ..geometry import ConeGeometry
from ..jsonio import read_json, rounded, write_json
from ..parts import frame_range as frame_range_of
from ..parts import selected_frames
from ..scan import load_scan
from .options import info, output_option, progress_bar

POSES_FORMAT = "conecal-poses/1"


@click.command("fit-pose")
@click.argument("scan", type=click.Path())
@click.option("--markers", "markers", required=True, type=click.Path(dir_okay=False), help="conecal-markers/1 from detect.")
@click.option("--geometry", "geometry", type=click.Path(dir_okay=False), default=None,
              help="conecal-geometry/1 (from fit-linear); default: the scan's nominal geometry.")
@output_option
@click.option("--max-rms", type=click.FloatRange(0, min_open=True), default=None,
              help="Reject a frame whose reprojection RMS exceeds this (px) [default: 0.5; 1.0 on a motion: free "
                   "scan, where a frame must also be within 2.5x the scan's median frame RMS].")
@click.option("--prior-mm", type=click.FloatRange(0, min_open=True), default=3.0, show_default=True,
              help="How far (mm) the true holder may be from the initial pose.")
@click.option("--prior-deg", type=click.FloatRange(0, min_open=True), default=2.0, show_default=True,
              help="How far (deg) the true holder may be turned from the initial pose.")
@click.option("--initial", type=click.Choice(["log", "previous"]), default="log", show_default=True,
              help="Start each frame from the joint log, or from the previous frame's placement error.")
@click.option("--use-flagged", is_flag=True, help="Also use truncated/overlapping/cluttered markers.")
@click.option("--distortion", default="auto", show_default=True,
              help="motion: free only: detector distortion family, 'auto' (chosen on held-out markers) or one of "
                   "none, radial, radial+S, radial+S+tangential, 'radial+S per frame', 'radial+S+tangential, S per "
                   "frame', polynomial3.")
@click.option("--phantom-sigma", type=click.FloatRange(min=0), default=None,
              help="motion: free only: how far (mm, 1 sigma) each sphere may sit from its phantom.csv position; "
                   "the phantom is refined with this prior and kept so only if held-out markers are predicted "
                   "better; 0: never refined.  [default: 0.1]")
@click.option("--frame-intrinsics", default=None, metavar="NAME[=SIGMA],...",
              help="motion: free only: free these intrinsics per frame, for a C-arm that sags between views "
                   "(sdd, c0, r0; SIGMA: the prior spread of a frame's value about the shared one, sdd mm "
                   "[5], c0 and r0 px [5]). Example: --frame-intrinsics sdd,c0,r0")
@click.option("--refine-geometry", is_flag=True,
              help="Refine the detector centre jointly with all poses (one bundle adjustment; the lab frame "
                   "stays that of --geometry).")
@click.option("--frames", "frame_range", default=None, metavar="START:STOP",
              help="Robot scans: only frames START <= k < STOP: writes a part for `conecal merge` (not with "
                   "--initial previous or --refine-geometry, which need every frame).")
@click.option("--part", "part", default=None, metavar="I/N",
              help="Robot scans: only the I-th of N nearly equal parts of the log, as with --frames.")
def command(scan, markers, geometry, output, max_rms, prior_mm, prior_deg, initial, use_flagged, distortion,
            phantom_sigma, frame_intrinsics, refine_geometry, frame_range, part):
    """Estimate the holder's pose (P_lab = R p_holder + t) in every frame of SCAN.

    A motion: free scan (a C-arm or radiography set-up imaging a known
    phantom at unlogged poses) is calibrated instead: identities from the
    phantom's pattern, one bundle adjustment of all poses with the shared
    sdd, principal point and detector distortion (family chosen on held-out
    markers); see docs/free_pose.md.

    Spheres are identified against phantom.csv by id (not by the nearest
    point of the helix), starting from the robot's joint log through its DH
    model; a frame that cannot be trusted is 'rejected: <reason>', never a
    wrong 'ok'. Also reports the helix that best fits the CAD coordinates
    and the robot's placement error per frame.

    \b
    Examples:
      conecal fit-pose demo/robot --markers demo/robot_markers.json -o demo/poses.json
      conecal fit-pose scans/holder --markers m.json --geometry g.json --initial previous -o poses.json
      conecal fit-pose demo/carm --markers demo/carm_markers.json -o demo/carm_poses.json
    """
    s = load_scan(scan)
    mdoc = read_markers(markers)
    check_scan(mdoc, markers, s.root, option=None, parts=("projections",))
    if s.config.motion == "free":
        from .fit_pose_free import run_free

        if refine_geometry or use_flagged or initial != "log":
            from ..errors import InputError
            raise InputError("--refine-geometry, --use-flagged, --initial: robot scans only (a free-pose fit always "
                             "refines the geometry and judges every marker by its own residual)")
        if frame_range or part:
            from ..errors import InputError
            raise InputError("--frames/--part: robot scans only (a free-pose calibration is one bundle adjustment "
                             "of every frame)")
        return run_free(s, scan, mdoc, markers, geometry, output, max_rms, distortion, frame_intrinsics,
                        phantom_sigma)
    subset = selected_frames(s, frame_range, part)
    if subset is not None and (initial == "previous" or refine_geometry):
        from ..errors import InputError
        raise InputError("--frames/--part: not with --initial previous or --refine-geometry, which need every frame")
    if max_rms is None:
        max_rms = 0.5
    if distortion != "auto" or frame_intrinsics or phantom_sigma is not None:
        from ..errors import InputError
        which = "distortion" if distortion != "auto" else "frame-intrinsics" if frame_intrinsics else "phantom-sigma"
        raise InputError(f"--{which}: only for motion: free scans")
    gdoc = read_json(geometry, "conecal-geometry") if geometry else None
    g = ConeGeometry.from_dict(gdoc) if gdoc else s.nominal_geometry()
    opt = PoseOptions(max_rms_px=max_rms, prior_mm=prior_mm, prior_deg=prior_deg)
    if s.phantom is None:
        from ..errors import InputError
        raise InputError(f"{s.root / 'scan.yaml'}: markers.phantom: fit-pose needs a holder phantom.csv")
    helix = fit_helix(s.phantom.positions[np.argsort(s.phantom.ids)])
    with progress_bar("fit-pose") as prog:
        poses, R_log, t_log = fit_poses(s, mdoc, g, opt, initial=initial, use_flagged=use_flagged, progress=prog,
                                        frames=None if subset is None else set(subset), rescue=rescue_frame)
    ok = [p for p in poses if p.status.ok]
    if not ok and subset is None:
        raise FitError(f"no frame could be fitted; first reason: {poses[0].status.sentence if poses else 'no frames'}")
    bundle = None
    if refine_geometry:
        from ..fit.markers import BIASING_FLAGS
        by_frame = {int(f["frame"]): [m for m in f["markers"] if use_flagged or not set(m.get("flags", [])) & set(BIASING_FLAGS)]
                    for f in mdoc["frames"]}
        g, bres, poses = refine_geometry_fn(g, poses, s.phantom.positions, s.phantom.ids, s.config.markers.diameter / 2,
                                            by_frame, opt.gate_px)
        ok = [p for p in poses if p.status.ok]
        bundle = {"parameters": {n: {"value": float(bres.value(n)), "sigma": float(bres.sigma[i]), "unit": "mm"}
                                 for i, n in enumerate(bres.names[:3])},
                  "held": ["source_x", "source_y", "source_z", "detector_rx", "detector_ry", "detector_rz"],
                  "chi2_reduced": bres.reduced_chi2, "undetermined": [n for n in bres.undetermined if not n.startswith("frame")]}
    place = placement_errors(poses, R_log, t_log)
    frames = []
    for p, pe in zip(poses, place["frames"]):
        fr = {"frame": p.frame, "R": p.R, "t": p.t, **p.status.fields()}
        if p.status.ok:
            fr.update({"sigma_rotation_deg": p.sigma_rotation_deg, "sigma_translation_mm": p.sigma_translation_mm,
                       "rms_px": p.rms_px, "n_spheres": p.n_spheres, "sphere_ids": p.ids, "placement_error": pe,
                       "found_by": p.found_by})
            if p.hidden:
                fr["hidden"] = p.hidden
        frames.append(fr)
    frames = rounded(frames)   # totals from the rounded frames: a merge of parts computes the same
    totals = rounded(poses_totals(frames))
    rms_all = totals["summary"]["rms_px"]
    doc = {"format": POSES_FORMAT, "software": f"conecal {__version__}", "scan": str(scan),
           "geometry_from": str(geometry) if geometry else "nominal", **g.to_dict(),
           "units": {"t": "mm", "R": "rotation matrix, P_lab = R p_holder + t", "rms_px": "px",
                     "sigma_rotation_deg": "deg (rotation vector components)", "sigma_translation_mm": "mm"},
           "options": {"max_rms_px": max_rms, "prior_mm": prior_mm, "prior_deg": prior_deg, "initial": initial},
           "helix": helix, "bundle_adjustment": bundle, **totals, "frames": frames}
    if subset is not None:
        doc["frame_range"] = frame_range_of(subset)
    write_json(output, rounded(doc))
    info(f"wrote {output}: {len(ok)}/{len(poses)} frames ok, reprojection RMS {rms_all:.4f} px; "
         f"helix radius {helix['radius_mm']:.3f} mm, pitch {helix['pitch_mm_per_turn']:.3f} mm/turn, "
         f"CAD residual {helix['rms_mm']:.4f} mm RMS")
    for line in reason_lines(totals["summary"]["reasons"]):
        info(line)
    if totals["placement"]:
        ps = totals["placement"]
        info(f"robot placement error: offset mean {np.round(ps['offset_mean_mm'], 3).tolist()} mm "
             f"(max {ps['offset_max_mm']:.3f} mm), rotation mean {ps['rotation_mean_deg']:.3f} deg "
             f"(max {ps['rotation_max_deg']:.3f} deg)")
