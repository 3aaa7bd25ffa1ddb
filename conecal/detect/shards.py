"""``detect --frames``/``--part`` on part of a scan, and the merge of the parts.

A part holds every frame's raw measurements (before the scan-wide contrast
filter and the identities, which need every frame) at full precision, and
the options it used (the scan's pixel noise is measured on the same frame
of the whole log by every part). The merge (after the checks of
:mod:`conecal.parts`) runs the scan-wide steps: the merged document is the
one a whole run writes, byte for byte.
"""

from __future__ import annotations

from dataclasses import asdict, fields

from .. import __version__
from ..errors import InputError
from ..parts import cover, frame_range, read_parts
from ..scan import Scan
from .options import Blob, DetectOptions
from .pipeline import MARKERS_FORMAT, assemble

PART_NOTE = "part of a scan (detect --frames/--part): raw measurements; join the parts with conecal merge"
_BLOB_FIELDS = [f.name for f in fields(Blob)]


def part_document(scan: Scan, opt: DetectOptions, frames_idx: list[int], results: list[list], lag: float) -> dict:
    rows, cols = scan.stack.shape
    return {"format": MARKERS_FORMAT, "software": f"conecal {__version__}", "frame_range": frame_range(frames_idx),
            "part": PART_NOTE, "detector": {"shape": [rows, cols]},
            "part_options": {**asdict(opt), "lag": lag},
            "frames": [{"frame": k, "markers": [], "blobs": [{n: getattr(b, n) for n in _BLOB_FIELDS} for b in res]}
                       for k, res in zip(frames_idx, results)]}


def merge_marker_parts(paths: list) -> dict:
    """The markers document of a whole scan from its parts (any order)."""
    parts, scan = read_parts(paths, "conecal-markers", ("part_options",))
    by_frame = cover(parts, scan)
    frames_idx = [int(f) for f in scan.log.frame]
    results = []
    for k in frames_idx:
        p, fr = by_frame[k]
        try:
            results.append([Blob(**{**b, "flags": list(b["flags"])}) for b in fr.get("blobs", [])])
        except (TypeError, KeyError) as exc:
            raise InputError(f"{p}: frames[frame {k}].blobs: {exc}") from None
    o = dict(parts[0][1]["part_options"])
    o.pop("lag", None)
    o["diameter_px"] = tuple(o["diameter_px"])
    o["shadow_px"] = tuple(o.get("shadow_px", ()))
    doc = assemble(scan, DetectOptions(**o), frames_idx, results)
    return {**doc, "scan": parts[0][1]["scan"]}
