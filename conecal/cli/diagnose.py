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
def command(result, scan, output, alpha):
    """Find the physical effect that RESULT (fit-rotation or fit-linear on
    SCAN) left out, model it, and show the fit improve.

    The residuals are tested against time, frame order, each axis reading,
    velocity and direction, position on the detector, marker id and rotation
    harmonics (Holm-adjusted). Then every effect of the registry that this
    recording could show (focal-spot and detector drift, axis scale and
    non-orthogonality, rotary wobble, encoder latency, backlash) is fitted
    together with the source/detector; an effect is claimed only if it
    lowers the held-out error (even vs odd frames) and BIC clearly, and
    reported as ambiguous when another explains the data as well.

    \b
    Examples:
      conecal diagnose demo/rot_geometry.json demo/rot -o demo/diagnosis.json
    """
    from .. import __version__
    from ..diagnose import ResultModel, diagnose
    from ..jsonio import read_json, rounded, write_json
    from ..scan import load_scan

    doc = read_json(result, "conecal-geometry")
    s = load_scan(scan)
    model = ResultModel(doc, s, result)
    with progress_bar("diagnose") as prog:
        out, final = diagnose(model, alpha=alpha, progress=prog)
    g = model.geometry_after(final["x9"])
    out = {"format": "conecal-diagnosis/1", "software": f"conecal {__version__}", "result": str(result),
           "scan": str(scan), "stage": doc.get("stage"), **out,
           "refitted_geometry": {"format": "conecal-geometry/1", **g.to_dict(), "axes": doc.get("axes", [])},
           "units": {"residual": "px", "chi2": "sum of squared whitened residuals (by detect's sigma)"}}
    write_json(output, rounded(out))
    info(f"wrote {output}: {out['verdict']}; RMS {out['rms_px_before']:.4f} -> {out['rms_px_after']:.4f} px "
         f"(noise floor {out['noise_floor_px']:.4f} px)")
