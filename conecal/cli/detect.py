"""``conecal detect``: sub-pixel sphere markers in every frame."""

from __future__ import annotations

import click

from ..detect import detect_scan, options_for_scan
from ..detect.pipeline import scan_options
from ..jsonio import write_json
from ..parts import selected_frames
from ..scan import load_scan
from .options import info, output_option, progress_bar, workers_option


@click.command("detect")
@click.argument("scan", type=click.Path())
@output_option
@workers_option
@click.option("--threshold", type=click.FloatRange(2), default=10.0, show_default=True,
              help="Candidate height in noise sigmas (lower it for low-dose scans).")
@click.option("--blur-px", type=click.FloatRange(0), default=1.0, show_default=True,
              help="Expected system blur (Gaussian sigma, px); widens the windows.")
@click.option("--diameter-px", type=(float, float), default=None, metavar="MIN MAX",
              help="Shadow diameters to look for (px); default from markers.diameter and the nominal magnification.")
@click.option("--lag", type=click.FloatRange(0, 0.9), default=0.0, show_default=True,
              help="Detector lag to remove first: the fraction of the previous frame's intensity each frame "
                   "keeps (as `diagnose` reports it).")
@click.option("--frames", "frame_range", default=None, metavar="START:STOP",
              help="Only frames START <= k < STOP (frame numbers; either end may be left out): writes a part, "
                   "to be joined with the other parts by `conecal merge` (the same document a whole run writes).")
@click.option("--part", "part", default=None, metavar="I/N",
              help="Only the I-th of N nearly equal parts of the log (1 <= I <= N): a part, as with --frames.")
def command(scan, output, workers, threshold, blur_px, diameter_px, lag, frame_range, part):
    """Find calibration spheres in every projection of SCAN.

    Writes conecal-markers/1: per frame, each marker's centre (x = column,
    y = row, px; the attenuation centroid of its shadow), sigma (px, 1
    sigma), identity across frames and flags (truncated, overlap, clutter).

    \b
    Examples:
      conecal detect demo/linear -o demo/markers.json
      conecal detect scans/hexapod --diameter-px 30 60 -o markers.json
      conecal detect demo/rot --lag 0.046 -o markers.json   # after diagnose found lag
      conecal detect demo/rot --frames 0:36 -o part0.json     # then: conecal merge part*.json -o m.json
    """
    s = load_scan(scan)
    if s.stack.dead_pixels:
        n = s.stack.dead_pixels
        info(f"{s.config.flat}: {n} pixels ({n / (s.config.detector.rows * s.config.detector.cols):.0%}) are not "
             f"brighter than the dark image by a quarter of the open field's signal (an intensifier's dark "
             f"surround?): read as no transmission")
    if diameter_px is not None and not 0 < diameter_px[0] < diameter_px[1]:
        raise click.BadParameter("need 0 < MIN < MAX", param_hint="--diameter-px")
    opt = options_for_scan(s, threshold=threshold, blur_px=blur_px, diameter_px=diameter_px)
    idx = selected_frames(s, frame_range, part)
    if idx is not None:
        from ..detect.pipeline import measure_frames
        from ..detect.shards import part_document

        with progress_bar("detect") as prog:
            opt, results = measure_frames(s, opt, idx, workers=workers, lag=lag, progress=prog)
        write_json(output, {**part_document(s, opt, idx, results, lag), "scan": str(scan)})
        _say_size(opt, s)
        info(f"wrote {output}: a part, frames {idx[0]}..{idx[-1]} ({len(idx)} frames, {sum(map(len, results))} "
             f"blobs); join the parts with conecal merge")
        return
    # (the noise and the shadow size measured once, here, to be told below;
    # detect_scan takes the measured options as they are)
    opt = scan_options(s, opt)
    with progress_bar("detect") as prog:
        doc = detect_scan(s, opt, workers=workers, lag=lag, progress=prog)
    write_json(output, {**doc, "scan": str(scan)})
    _say_size(opt, s)
    n = sum(len(f["markers"]) for f in doc["frames"])
    flagged = sum(1 for f in doc["frames"] for m in f["markers"] if m["flags"])
    info(f"wrote {output}: {n} markers in {len(doc['frames'])} frames ({flagged} flagged), {doc['n_ids']} identities")


def _say_size(opt, scan) -> None:
    """Tell the user when the shadows were not the size the nominal
    magnification says (``opt.size_scale``: measured over nominal) or fell
    in more size classes than ``markers`` declares, and were looked for at
    the measured sizes (``opt.diameter_px``, px)."""
    from ..detect.size import rescaled

    lo, hi = opt.diameter_px
    m = scan.config.markers
    declared = len(set(m.diameters or (m.diameter,))) if m is not None else 0
    if declared and len(opt.shadow_px) > declared:
        info(f"the shadows fall in {len(opt.shadow_px)} size classes ("
             + ", ".join(f"{d:.1f}" for d in opt.shadow_px) + " px) where markers.diameter declares "
             f"{declared} (a phantom of two bead sizes?): looked for {lo:.1f}-{hi:.1f} px")
    elif rescaled(opt.size_scale):
        info(f"the shadows measure {opt.size_scale:.2f}x the size markers.diameter and the nominal magnification "
             f"give (sdd/sod off, or another sphere size?): looked for {lo:.1f}-{hi:.1f} px")
