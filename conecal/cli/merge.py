"""``conecal merge``: join the parts of a scan detected apart (``detect --frames``)."""

from __future__ import annotations

import click

from ..jsonio import write_json
from .options import info, output_option


@click.command("merge")
@click.argument("parts", nargs=-1, required=True, type=click.Path(dir_okay=False))
@output_option
def command(parts, output):
    """Join PARTS written by `detect --frames START:STOP` into the markers
    document of the whole scan: the same document, byte for byte, that one
    `detect` over every frame writes (identities are linked across parts:
    the contrast filter and tracking run here, over every frame).

    The parts must come from one scan, with one set of options, and cover
    its log exactly once; anything else exits 2 naming the part.

    \b
    Examples:
      conecal detect demo/rot --frames 0:36 -o p0.json
      conecal detect demo/rot --frames 36: -o p1.json
      conecal merge p0.json p1.json -o demo/rot_markers.json
    """
    from ..detect.shards import merge_parts

    doc = merge_parts(list(parts))
    write_json(output, doc)
    info(f"wrote {output}: {len(parts)} parts, {sum(len(f['markers']) for f in doc['frames'])} markers in "
         f"{len(doc['frames'])} frames, {doc['n_ids']} identities")
