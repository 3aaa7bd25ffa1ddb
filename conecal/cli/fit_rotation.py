"""``conecal fit-rotation``: rotary axes and sphere positions from a rotation scan."""

from __future__ import annotations

import click

from ..fit.markers import load_observations
from ..fit.output import fit_summary, geometry_document
from ..fit.rotation import fit_rotation
from ..geometry import ConeGeometry
from ..errors import InputError
from ..jsonio import read_json
from ..scan import load_scan
from .options import centre_model_option, output_option, write_fit


@click.command("fit-rotation")
@click.argument("scans", nargs=-1, required=True, type=click.Path())
@click.option("--markers", "markers", required=True, multiple=True, type=click.Path(dir_okay=False),
              help="conecal-markers/1 from detect, one per SCAN, in the same order.")
@click.option("--geometry", "geometry", type=click.Path(dir_okay=False), default=None,
              help="conecal-geometry/1 (from fit-linear); default: the scan's nominal geometry.")
@output_option
@click.option("--refine-geometry", is_flag=True, help="Also refine source and detector (bundle adjustment).")
@click.option("--loss", type=click.Choice(["linear", "soft_l1", "huber", "cauchy"]), default="linear", show_default=True)
@click.option("--use-flagged", is_flag=True, help="Also use truncated/overlapping/cluttered markers.")
@centre_model_option
def command(scans, markers, geometry, output, refine_geometry, loss, use_flagged, centre_model):
    """Estimate every moving rotary axis of SCANS (direction and a point on
    it, lab frame) and the spheres' positions on the sample.

    Several scans of one manipulator are fitted together (one bundle
    adjustment); each has its own spheres and reference sphere (the one at
    the lab origin at zero readings, found automatically). Spheres missing
    from some frames are fine. Axes that do not move, and linear axes, keep
    the values of --geometry. With --refine-geometry source and detector
    are estimated too; a linear raster among SCANS pins them down.

    \b
    Examples:
      conecal fit-rotation demo/rot --markers demo/rot_markers.json --geometry demo/geometry.json -o demo/rot_geometry.json
      conecal fit-rotation lin rot --markers lm.json --markers rm.json --geometry g.json --refine-geometry -o g2.json
    """
    if len(markers) != len(scans):
        raise click.BadParameter(f"{len(scans)} scans but {len(markers)} markers files", param_hint="--markers")
    loaded = [load_scan(sc) for sc in scans]
    s = loaded[0]
    gdoc = read_json(geometry, "conecal-geometry") if geometry else None
    g = ConeGeometry.from_dict(gdoc) if gdoc else s.nominal_geometry()
    if g.shape != (s.config.detector.rows, s.config.detector.cols):
        raise InputError(f"{geometry}: detector.shape {list(g.shape)} differs from {s.root / 'scan.yaml'}'s "
                         f"[{s.config.detector.rows}, {s.config.detector.cols}] (rows, cols)")
    obs = [load_observations(m, sc, use_flagged=use_flagged) for m, sc in zip(markers, loaded)]
    fit = fit_rotation(loaded, obs, g, geometry_doc=gdoc, refine_geometry=refine_geometry, loss=loss, centre_model=centre_model)
    res = fit.result
    summary = fit_summary(res, fit.residual_px, centre_model=centre_model, start="triangulation", loss=loss)
    axes = []
    for a in fit.axes:
        d = {"name": a.name, "type": a.type, "direction": a.direction}
        if a.type == "rotary":
            d["point"] = a.point
        else:
            d["scale"] = a.scale
        d["calibrated_here"] = a.name in [fit.model.axes[j].name for j in fit.model.free_axes]
        axes.append(d)
    sig = dict(zip(res.names, res.sigma))
    spheres = []
    for k, ((scan_k, sid), p) in enumerate(zip(fit.sphere_labels, fit.spheres)):
        ref = k in fit.model.references
        spheres.append({"scan": str(scans[scan_k]), "id": sid, "position": p, "reference": ref,
                        "diameter": float(2 * fit.model.radii[k]),
                        "sigma": [0.0, 0.0, 0.0] if ref else [sig[f"sphere{k}_{c}"] for c in "xyz"]})
    residuals = [{"scan": str(scans[k]), "frame": int(f), "id": int(i), "x": float(xy[0]), "y": float(xy[1]),
                  "dx": float(d[0]), "dy": float(d[1]), "sigma": float(sg)}
                 for k, f, i, xy, d, sg in zip(fit.scan_of_obs, fit.obs.frame, fit.obs.ids, fit.obs.xy, fit.residual_px,
                                               fit.obs.sigma)]
    doc = geometry_document("fit-rotation", fit.geometry, axes, summary, residuals,
                            str(scans[0]) if len(scans) == 1 else [str(x) for x in scans],
                            extra={"spheres": spheres, "geometry_from": str(geometry) if geometry else "nominal"})
    write_fit(output, doc, res, summary, f" of {len(spheres)} spheres")
