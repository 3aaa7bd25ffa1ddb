"""``conecal merge``: join the parts of a scan computed apart (``--frames``/``--part``)."""

from __future__ import annotations

import json

import click

from ..errors import InputError
from ..jsonio import write_json
from .options import info, output_option


def _format_of(path) -> str:
    try:
        with open(path, encoding="utf-8") as fh:
            fmt = json.load(fh).get("format", "")
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (OSError, ValueError, AttributeError) as exc:
        raise InputError(f"{path}: not a conecal JSON document ({exc})") from None
    return str(fmt).split("/")[0]


@click.command("merge")
@click.argument("parts", nargs=-1, required=True, type=click.Path(dir_okay=False))
@output_option
def command(parts, output):
    """Join PARTS written by `detect --frames/--part` (markers) or robot
    `fit-pose --frames/--part` (poses) into the document of the whole
    scan: the same document, byte for byte, that one run over every frame
    writes. For markers the contrast filter and the tracking run here, over
    every frame, so identities are linked across parts.

    The parts must come from one scan, with one set of options, and cover
    its log exactly once; anything else exits 2 naming the part.

    \b
    Examples:
      conecal detect demo/rot --part 1/2 -o p1.json
      conecal detect demo/rot --part 2/2 -o p2.json
      conecal merge p1.json p2.json -o demo/rot_markers.json
    """
    fmt = _format_of(parts[0])
    if fmt == "conecal-markers":
        from ..detect.shards import merge_marker_parts

        doc = merge_marker_parts(list(parts))
        write_json(output, doc)
        info(f"wrote {output}: {len(parts)} parts, {sum(len(f['markers']) for f in doc['frames'])} markers in "
             f"{len(doc['frames'])} frames, {doc['n_ids']} identities")
    elif fmt == "conecal-poses":
        from ..fit.pose_parts import merge_pose_parts

        doc = merge_pose_parts(list(parts))
        write_json(output, doc)
        sm = doc["summary"]
        info(f"wrote {output}: {len(parts)} parts, {sm['ok']}/{sm['frames']} frames ok, "
             f"reprojection RMS {sm['rms_px']:.4f} px")
    else:
        raise InputError(f"{parts[0]}: format {fmt or '(none)'}: merge joins conecal-markers or conecal-poses parts")
