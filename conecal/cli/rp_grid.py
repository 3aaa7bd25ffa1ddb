"""``conecal rp-grid``: markerless detector misalignment of a circular scan."""

from __future__ import annotations

import click

from ..geometry.misalignment import NAMES
from ..consistency.rpgrid import DEFAULT_RANGES, RPOptions, document, run
from ..errors import FitError, InputError
from ..scan import load_scan
from .options import info, output_option, progress_bar


def _ranges(items) -> dict:
    out = dict(DEFAULT_RANGES)
    for item in items:
        name, _, val = item.partition("=")
        if name not in out:
            raise InputError(f"--range {item}: unknown parameter {name!r} (known: {', '.join(NAMES)})")
        try:
            out[name] = float(val)
        except ValueError:
            raise InputError(f"--range {item}: {val!r} is not a number") from None
        if not out[name] > 0:
            raise InputError(f"--range {item}: the half-width must be positive")
    return out


def _crop(text):
    if text is None:
        return None
    try:
        box = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise InputError(f"--crop {text}: expected COL0,COL1,ROW0,ROW1 (integers)") from None
    if len(box) != 4:
        raise InputError(f"--crop {text}: expected four numbers COL0,COL1,ROW0,ROW1")
    return box


@click.command("rp-grid")
@click.argument("scan", type=click.Path())
@output_option
@click.option("--range", "ranges", multiple=True, metavar="NAME=HALFWIDTH",
              help=f"Grid half-width of a parameter (px or deg; repeatable). Defaults: "
                   f"{', '.join(f'{k}={v:g}' for k, v in DEFAULT_RANGES.items())}.")
@click.option("--pairs", type=click.IntRange(10, 100000), default=1500, show_default=True,
              help="View pairs sampled (where truncation drops most of their planes, pass 2 draws up to 4x more, "
                   "at the separations whose planes survived).")
@click.option("--planes-per-pair", type=click.IntRange(4, 1000), default=48, show_default=True)
@click.option("--angles", type=click.IntRange(36, 4000), default=360, show_default=True,
              help="Angles of each view's Radon table over 180 deg.")
@click.option("--crop", default=None, metavar="COL0,COL1,ROW0,ROW1",
              help="Use only this detector region (inclusive pixel indices). Not needed for holders or truncation.")
@click.option("--keep-truncated", is_flag=True, help="Do not drop planes whose lines leave the detector where the object is.")
@click.option("--smooth-px", type=click.FloatRange(0.5, 20.0), default=3.0, show_default=True,
              help="Gaussian sigma (px) of each table's derivative along s.")
@click.option("--kernel-order", type=click.Choice(["2", "4"]), default="2", show_default=True,
              help="4: a derivative kernel that is also exact on cubics (less smoothing bias, 1.85x the noise).")
@click.option("--fan-sigma-deg", type=click.FloatRange(0.0, 10.0), default=0.0, show_default=True,
              help="Smoothing along each pair's fan of planes (deg; 0: off). Use with --planes-per-pair 144.")
@click.option("--interpolation", type=click.Choice(["spline", "cubic", "linear"]), default="spline", show_default=True,
              help="Table look-ups: cubic B-spline along the offset (spline) or Catmull-Rom (cubic).")
@click.option("--max-table-gb", type=click.FloatRange(0.05, 1000.0), default=RPOptions.max_table_gb, show_default=True,
              help="Memory for the second pass's tables (GB); a larger scan keeps every k-th of their smoothed offsets to fit.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the plane sample.")
def command(scan, output, ranges, pairs, planes_per_pair, angles, crop, keep_truncated, smooth_px, kernel_order,
            fan_sigma_deg, interpolation, max_table_gb, seed):
    """Find the detector misalignment of circular SCAN from redundant plane integrals.

    No markers: every plane through two source positions is measured by
    both views (Grangeat). The five parameters, relative to the nominal
    geometry and about the detector centre: shift_u_px, shift_v_px (px),
    eta_deg (in-plane rotation), theta_deg (tilt about u), phi_deg (tilt
    about v). Writes the corrected geometry (conecal-geometry/1), the
    estimates with sigma and the cost slices through the optimum.

    \b
    Examples:
      conecal rp-grid demo/circular -o demo/rp.json
      conecal rp-grid scans/ct --range shift_u_px=40 --range eta_deg=5 -o rp.json
    """
    # options that lost their benchmarks (benchmarks/RESULTS.md): still honoured
    # during a deprecation period, then removed
    retired = []
    if kernel_order != "2":
        retired.append("--kernel-order 4 (benchmarks/RESULTS.md, 'a fourth-order derivative kernel': 1.85x the noise, "
                       "mixed on the benchmark)")
    if fan_sigma_deg:
        retired.append("--fan-sigma-deg (benchmarks/RESULTS.md, 'the fan smoothing inside rp-grid': less bias "
                       "without noise, the wrong basin with it)")
    if interpolation != "spline":
        retired.append(f"--interpolation {interpolation} (benchmarks/RESULTS.md, 'B-spline look-ups by default')")
    for r in retired:
        info(f"deprecated: {r}; it will be removed in a later release")
    opt = RPOptions(ranges=_ranges(ranges), pairs=pairs, planes_per_pair=planes_per_pair, n_angles=angles,
                    crop=_crop(crop), exclude_truncated=not keep_truncated, smooth_px=smooth_px,
                    kernel_order=int(kernel_order), fan_sigma_deg=fan_sigma_deg,
                    interpolation=interpolation, max_table_gb=max_table_gb, seed=seed)
    s = load_scan(scan)
    with progress_bar("rp-grid") as prog:
        res, prob = run(s, opt, progress=prog)
    if not res.fit.success:
        raise FitError(f"rp-grid: the refinement did not converge: {res.fit.message}")
    doc = document(res, prob, s, opt)
    from ..jsonio import write_json

    write_json(output, doc)
    tab = doc["fit"]["tables"]
    if tab["offset_step_px"] != opt.offset_step_px:
        info(f"tables with offsets every {tab['offset_step_px']:g} px ({tab['megabytes']:.0f} MB, --max-table-gb "
             f"{opt.max_table_gb:g})")
    est = ", ".join(f"{n} {x:+.3f}±{sg:.3f}" for n, x, sg in zip(NAMES, res.x, res.sigma))
    info(f"wrote {output}: {est}; cost {res.cost_nominal:.4g} -> {res.cost_final:.4g} "
         f"over {res.planes['used']} planes")
    if doc["fit"]["undetermined"]:
        info(f"warning: the scan does not determine {', '.join(doc['fit']['undetermined'])} "
             f"(sigma beyond {', '.join(f'{opt.undetermined_sigma[n]:g}' for n in doc['fit']['undetermined'])})")
