"""``conecal fit-linear``: source and detector from one sphere moved by linear axes."""

from __future__ import annotations

import click

from ..fit.linear import fit_linear
from ..fit.markers import load_observations
from ..fit.output import fit_summary, geometry_document
from ..scan import load_scan
from .options import centre_model_option, output_option, write_fit


@click.command("fit-linear")
@click.argument("scan", type=click.Path())
@click.option("--markers", "markers", required=True, type=click.Path(dir_okay=False), help="conecal-markers/1 from detect.")
@output_option
@click.option("--axis-scales", is_flag=True, help="Also estimate each axis' scale factor.")
@click.option("--axis-tilts", is_flag=True, help="Also estimate the axes' non-orthogonality (tilts, deg).")
@click.option("--loss", type=click.Choice(["linear", "soft_l1", "huber", "cauchy"]), default="linear", show_default=True,
              help="Robust loss; residuals beyond 3 sigma are reported as outliers.")
@click.option("--marker-id", type=int, default=None, help="Which tracked sphere to use (default: the longest track).")
@click.option("--use-flagged", is_flag=True, help="Also use truncated/overlapping/cluttered markers.")
@centre_model_option
def command(scan, markers, output, axis_scales, axis_tilts, loss, marker_id, use_flagged, centre_model):
    """Estimate source, detector position and orientation from SCAN's sphere track.

    The lab frame: origin at the sphere when every axis reads zero, axes
    along the manipulator's. Parameters the scan cannot determine are
    named in the output ('undetermined') instead of being returned as noise.

    \b
    Examples:
      conecal fit-linear demo/linear --markers demo/markers.json -o demo/geometry.json
      conecal fit-linear scans/raster --markers m.json --axis-scales --axis-tilts -o g.json
    """
    s = load_scan(scan)
    obs = load_observations(markers, s, use_flagged=use_flagged)
    fit = fit_linear(s, obs, axis_scales=axis_scales, axis_tilts=axis_tilts, loss=loss, marker_id=marker_id, centre_model=centre_model)
    res = fit.result
    summary = fit_summary(res, fit.residual_px, centre_model=centre_model, start=fit.start, loss=loss)
    axes = [{"name": n, "type": "linear", "direction": d, "scale": float(sc)}
            for n, d, sc in zip(fit.model.axis_names, fit.directions, fit.scales)]
    residuals = [{"frame": int(f), "id": int(i), "x": float(xy[0]), "y": float(xy[1]), "dx": float(d[0]),
                  "dy": float(d[1]), "sigma": float(sg)}
                 for f, i, xy, d, sg in zip(fit.obs.frame, fit.obs.ids, fit.obs.xy, fit.residual_px, fit.obs.sigma)]
    doc = geometry_document("fit-linear", fit.geometry, axes, summary, residuals, str(scan))
    write_fit(output, doc, res, summary, "")
