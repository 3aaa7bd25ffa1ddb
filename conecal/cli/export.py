"""``conecal export``: per-view geometry in the sample frame for a reconstructor."""

from __future__ import annotations

import click
import numpy as np

from .. import __version__
from ..export import astra_vectors, per_view, projection_matrices, views, write_array
from ..scan import load_scan
from .options import check_output, info


@click.command("export")
@click.argument("result", type=click.Path(dir_okay=False))
@click.option("--scan", "scan", type=click.Path(), default=None,
              help="The scan whose log gives each view's readings (for a geometry file).")
@click.option("--format", "fmt", type=click.Choice(["astra", "matrices", "rtk", "distortion"]), required=True,
              help="astra: cone_vec rows (source, detector centre, u*pu, v*pv); "
                   "matrices: 3x4 projection matrices to (column, row, 1); "
                   "rtk: RTK geometry XML (needs itk-rtk; projection images with spacing (pu, pv) and origin "
                   "(-(cols-1)/2*pu, -(rows-1)/2*pv)); "
                   "distortion: float32 TIFF, pages dc, dr (px) at every ideal pixel centre (per frame if the "
                   "distortion is per frame): cv2.remap(img, c + dc, r + dr, ...) removes it.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), callback=check_output,
              help="Output file: .npy for a numpy array, anything else for text (one view per row).")
@click.option("--other-scan", "other_scan", is_flag=True,
              help="--scan is not the scan RESULT was fitted on but another scan of the same system (e.g. the "
                   "object's scan after a phantom calibration): use its log. Every axis it moves must be in RESULT.")
def command(result, scan, fmt, output, other_scan):
    """Write the per-view geometry of RESULT (conecal-geometry/1 with --scan,
    or conecal-poses/1) in the sample frame.

    --scan must be the scan RESULT was fitted on (its fingerprints are in
    RESULT), or, with --other-scan, another scan of the same system whose
    moving axes RESULT calibrated; anything else exits 2.

    Each view is the lab geometry seen from the sample at rest (the frame's
    sample-to-lab transform inverted). mm; pixel coordinates have the
    centre of img[0, 0] at (0, 0), and the ASTRA detector centre is the
    point of pixel coordinates ((cols-1)/2, (rows-1)/2).

    \b
    Examples:
      conecal export demo/rot_geometry.json --scan demo/rot --format astra -o demo/views.txt
      conecal export demo/poses.json --format matrices -o demo/matrices.npy
      conecal export demo/carm_poses.json --format distortion -o demo/carm_distortion.tif
    """
    if fmt == "distortion":
        from ..export.distortion import distortion_pages, write_distortion_tiff

        pages, names = distortion_pages(result)
        write_distortion_tiff(output, pages, names, f"conecal {__version__} export from {result}; measured = ideal + "
                                                    "(dc, dr) at ideal pixel centres")
        peak = max(float(np.hypot(pages[i], pages[i + 1]).max()) for i in range(0, len(pages), 2))
        info(f"wrote {output}: {len(pages)} pages ({', '.join(names[:4])}{', ...' if len(names) > 4 else ''}), "
             f"largest displacement {peak:.3f} px")
        return
    s = load_scan(scan) if scan else None
    g, frames, T, warnings = views(result, s, other_scan=other_scan)
    geoms = per_view(g, T)
    rows, cols = geoms[0].shape
    if fmt == "rtk":
        from ..export.rtk import detector_origin_spacing, write_rtk_xml

        write_rtk_xml(output, geoms)
        (ox, oy), (pu, pv) = detector_origin_spacing(geoms[0])
        info(f"wrote {output}: {len(geoms)} views (RTK XML); give RTK's projections spacing ({pu:g}, {pv:g}) and "
             f"origin ({ox:g}, {oy:g})" + "".join(f"; {w}" for w in warnings))
        return
    if fmt == "astra":
        arr = astra_vectors(geoms)
        header = (f"conecal {__version__} export from {result}: ASTRA cone_vec, one view per row "
                  f"(srcX srcY srcZ dX dY dZ uX uY uZ vX vY vZ), mm, detector {rows} rows x {cols} cols; "
                  f"frames {frames[0]}..{frames[-1]}")
    else:
        arr = projection_matrices(geoms)
        header = (f"conecal {__version__} export from {result}: 3x4 projection matrices, row-major, one view per "
                  f"row, sample frame (mm) -> (column, row, 1); frames {frames[0]}..{frames[-1]}")
    write_array(output, arr, header)
    info(f"wrote {output}: {len(geoms)} views ({fmt})" + "".join(f"; {w}" for w in warnings))
