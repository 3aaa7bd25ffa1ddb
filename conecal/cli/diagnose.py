"""``conecal diagnose``: which physics did the fit leave out?"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from .options import info, output_option, progress_bar


@click.command("diagnose")
@click.argument("result", type=click.Path(dir_okay=False))
@click.argument("scan", type=click.Path())
@output_option
@click.option("--alpha", type=click.FloatRange(1e-6, 0.2), default=0.01, show_default=True,
              help="Family-wise false-alarm level of the residual tests (Holm-adjusted).")
@click.option("--image/--no-image", "image_level", default=True, show_default=True,
              help="Also compare every marker's recorded shadow with the one the fitted scene renders "
                   "(blur, beam hardening, detector lag, scatter).")
@click.option("--image-frames", type=click.IntRange(4, 100000), default=None,
              help="Frames (evenly spread) whose marker patches the image level uses [default: 48; 12 on a "
                   "fit-pose result, whose frames hold ~50 spheres each].")
@click.option("--markers", "markers", type=click.Path(dir_okay=False), default=None,
              help="Free-pose results: the markers file fit-pose read [default: the result's markers_from].")
@click.option("--allow-other-scan", is_flag=True,
              help="Diagnose RESULT on SCAN although SCAN is not the scan RESULT was fitted on (e.g. a scan.yaml "
                   "edited on purpose); without it a mismatch exits 2.")
def command(result, scan, output, alpha, image_level, image_frames, markers, allow_other_scan):
    """Find the physical effect that RESULT (fit-rotation, fit-linear or
    fit-pose on SCAN) left out, model it, and show the fit improve.

    The residuals are tested against time, frame order, each axis reading,
    velocity and direction, position on the detector, marker id and rotation
    harmonics (Holm-adjusted). Then every effect of the registry that this
    recording could show (focal-spot and detector drift, axis scale and
    non-orthogonality, rotary wobble, rotary runout 2 and 3 times per turn
    (across the beam), encoder latency, backlash, radial and
    S-shaped detector distortion) is fitted together with the fit's own
    parameters. At the image level each marker's shadow is rendered from
    the fitted scene and compared pixel by pixel with the recording (blur
    wider than stated, beam hardening, detector lag, scatter). An effect is
    claimed only if it lowers the held-out error (even vs odd frames) and
    BIC clearly, and reported as ambiguous when the held-out data cannot
    tell it from another (paired, within two standard errors).

    On a free-pose result (fit-pose on a motion: free scan, which already
    chose the detector distortion on held-out markers) what the chosen model
    still misses is located: a place on the detector whose markers are
    displaced from those around it (a dent in an intensifier's screen; the
    markers fit-pose set aside are judged too), a field over the detector, a
    sphere off its CAD position, frames above the others.

    On a fit-pose result the observations are the holder's poses against
    the arm's model (joint log through the DH table, registration refitted):
    joint zero offsets, the arm yielding under the holder's weight, encoder
    latency and joint backlash; at the image level every frame's holder is
    rendered from its fitted pose.

    \b
    Examples:
      conecal diagnose demo/rot_geometry.json demo/rot -o demo/diagnosis.json
      conecal diagnose demo/poses.json demo/arm -o demo/arm_diagnosis.json
      conecal diagnose demo/carm_poses.json demo/carm -o demo/carm_diagnosis.json
    """
    from .. import __version__
    from ..diagnose import ResultModel, diagnose, diagnose_image, merge_levels
    from ..binding import check_scan
    from ..diagnose.image_select import scene_chi2
    from ..jsonio import read_json, rounded, write_json
    from ..scan import load_scan

    doc = read_json(result, ("conecal-geometry", "conecal-poses"))
    check_scan(doc, result, scan, allow_other=allow_other_scan)
    s = load_scan(scan)
    if doc.get("stage") in ("fit-rotation", "fit-linear") and \
            list(doc["detector"]["shape"]) != [s.config.detector.rows, s.config.detector.cols]:
        from ..errors import InputError
        raise InputError(f"{result}: detector.shape {list(doc['detector']['shape'])} differs from "
                         f"{s.root / 'scan.yaml'}'s [{s.config.detector.rows}, {s.config.detector.cols}] (rows, cols)")
    if doc.get("motion") == "free":
        from ..diagnose.free import diagnose_free
        from ..fit.markers import read_markers

        src = markers or doc.get("markers_from")
        if not src:
            from ..errors import InputError
            raise InputError(f"{result}: markers_from: a free-pose result must name its markers file")
        if not markers and not Path(src).is_absolute() and not Path(src).exists():
            src = Path(result).parent / doc["markers_from_relative"] if doc.get("markers_from_relative") else src
        mdoc = read_markers(src)
        check_scan(mdoc, src, scan, option=None, parts=("projections",))
        out = diagnose_free(doc, s, mdoc, alpha)
        out = {"format": "conecal-diagnosis/1", "software": f"conecal {__version__}", "result": str(result),
               "scan": str(scan), "stage": "fit-pose (free)", **out, "image_level": None,
               "units": {"residual": "px (measured - predicted)", "size": "px"}}
        write_json(output, rounded(out))
        info(f"wrote {output}: {out['verdict']}")
        return
    pose = doc["format"].startswith("conecal-poses")
    if pose:
        from ..diagnose.pose import PoseModel, PoseScene

        model = PoseModel(doc, s, result)
        # the image level re-renders every frame's holder from its fitted pose
        scene = PoseScene(doc, s, result) if image_level else None
    else:
        model = scene = ResultModel(doc, s, result)
    if image_frames is None:   # a holder frame has ~50 spheres, a rotation frame a handful
        image_frames = 12 if pose else 48
    tie = (lambda evals: scene_chi2(model, s, evals)) if image_level and not pose else None
    with progress_bar("diagnose: geometry") as prog:
        out, final = diagnose(model, alpha=alpha, progress=prog, tie_breaker=tie)
    image = None
    if image_level:
        with progress_bar("diagnose: image") as prog:
            # robot effects move the poses, which fit-pose measured per frame: nothing to re-render
            # the fit's own scene unless the geometric level changed it: its base refit alone can drift
            # along directions the centres hardly see (0.4 mm along the beam on a clean scan), which
            # the shadows' sizes do see
            claimed = () if pose else tuple(final.get("effects") or ())
            image = diagnose_image(scene, s, geometric_effects=claimed,
                                   geometric_base=final["x9"] if claimed else None, max_frames=image_frames,
                                   progress=prog)
        out = merge_levels(out, image)
    units = ({"residual": "px: the holder's mean sphere shadow, fitted pose minus the arm's model",
              "observation": "one frame's pose: rotation vector (rad, lab) and translation (mm, lab), fitted minus "
                             "modelled",
              "chi2": "sum of squared whitened residuals (by fit-pose's sigma and the arm's repeatability)"}
             if pose else {"residual": "px", "chi2": "sum of squared whitened residuals (by detect's sigma)"})
    out = {"format": "conecal-diagnosis/1", "software": f"conecal {__version__}", "result": str(result),
           "scan": str(scan), "stage": model.stage if pose else doc.get("stage"), **out, "image_level": image,
           **model.refitted(final["x9"]), "units": units}
    write_json(output, rounded(out))
    info(f"wrote {output}: {out['verdict']}; RMS {out['rms_px_before']:.4f} -> {out['rms_px_after']:.4f} px "
         f"(noise floor {out['noise_floor_px']:.4f} px)")
    if pose:
        b, a = out["before"], out["after"]
        info(f"holder pose RMS {b['rms_translation_mm']:.4f} -> {a['rms_translation_mm']:.4f} mm, "
             f"{b['rms_rotation_deg']:.4f} -> {a['rms_rotation_deg']:.4f} deg (arm repeatability "
             f"{np.round(a['repeatability']['translation_mm'], 4).tolist()} mm)")
