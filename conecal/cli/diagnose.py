"""``conecal diagnose``: which physics did the fit leave out?"""

from __future__ import annotations

import click

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
@click.option("--image-frames", type=click.IntRange(4, 100000), default=48, show_default=True,
              help="Frames (evenly spread) whose marker patches the image level uses.")
def command(result, scan, output, alpha, image_level, image_frames):
    """Find the physical effect that RESULT (fit-rotation or fit-linear on
    SCAN) left out, model it, and show the fit improve.

    The residuals are tested against time, frame order, each axis reading,
    velocity and direction, position on the detector, marker id and rotation
    harmonics (Holm-adjusted). Then every effect of the registry that this
    recording could show (focal-spot and detector drift, axis scale and
    non-orthogonality, rotary wobble, encoder latency, backlash, radial and
    S-shaped detector distortion) is fitted together with the fit's own
    parameters. At the image level each marker's shadow is rendered from
    the fitted scene and compared pixel by pixel with the recording (blur
    wider than stated, beam hardening, detector lag, scatter). An effect is
    claimed only if it lowers the held-out error (even vs odd frames) and
    BIC clearly, and reported as ambiguous when the held-out data cannot
    tell it from another (paired, within two standard errors).

    \b
    Examples:
      conecal diagnose demo/rot_geometry.json demo/rot -o demo/diagnosis.json
    """
    from .. import __version__
    from ..diagnose import ResultModel, diagnose, diagnose_image, merge_levels
    from ..diagnose.image import scene_chi2
    from ..jsonio import read_json, rounded, write_json
    from ..scan import load_scan

    doc = read_json(result, "conecal-geometry")
    s = load_scan(scan)
    model = ResultModel(doc, s, result)
    tie = (lambda evals: scene_chi2(model, s, evals)) if image_level else None
    with progress_bar("diagnose: geometry") as prog:
        out, final = diagnose(model, alpha=alpha, progress=prog, tie_breaker=tie)
    image = None
    if image_level:
        with progress_bar("diagnose: image") as prog:
            image = diagnose_image(model, s, geometric_effects=final.get("effects") or (), geometric_base=final["x9"],
                                   max_frames=image_frames, progress=prog)
        out = merge_levels(out, image)
    g = model.geometry_after(final["x9"])
    out = {"format": "conecal-diagnosis/1", "software": f"conecal {__version__}", "result": str(result),
           "scan": str(scan), "stage": doc.get("stage"), **out, "image_level": image,
           "refitted_geometry": {"format": "conecal-geometry/1", **g.to_dict(), "axes": doc.get("axes", [])},
           "units": {"residual": "px", "chi2": "sum of squared whitened residuals (by detect's sigma)"}}
    write_json(output, rounded(out))
    info(f"wrote {output}: {out['verdict']}; RMS {out['rms_px_before']:.4f} -> {out['rms_px_after']:.4f} px "
         f"(noise floor {out['noise_floor_px']:.4f} px)")
