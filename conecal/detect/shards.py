"""``detect --frames START:STOP`` on part of a scan, and ``merge`` of the parts.

A part holds every frame's raw measurements (before the scan-wide contrast
filter and the identities, which need every frame) at full precision, and
the options it used (the scan's pixel noise is measured on the same frame
of the whole log by every part). ``merge`` checks that the parts come from
one scan with one set of options and cover its log exactly once, then runs
the scan-wide steps: the merged document is the one a whole run writes,
byte for byte.
"""

from __future__ import annotations

from dataclasses import asdict, fields

from .. import __version__
from ..binding import bound_scans
from ..errors import InputError
from ..jsonio import read_json
from ..scan import Scan, load_scan
from .frame import Blob, DetectOptions
from .pipeline import MARKERS_FORMAT, assemble

PART_NOTE = "part of a scan (detect --frames): raw measurements; join the parts with conecal merge"
_BLOB_FIELDS = [f.name for f in fields(Blob)]
_FINGERPRINT = ("scan_yaml_sha256", "log_sha256", "projections_bytes", "projections_sha256_sampled")


def parse_frames(text: str, scan: Scan) -> tuple[int, int]:
    """``START:STOP`` (frame numbers, STOP excluded; either may be empty) -> (start, stop)."""
    frames = [int(f) for f in scan.log.frame]
    top = max(frames) + 1 if frames else 0
    start, sep, stop = text.partition(":")
    try:
        a = int(start) if start.strip() else 0
        b = int(stop) if stop.strip() else top
    except ValueError:
        a = b = -1
    if not sep or a < 0 or b <= a:
        raise InputError(f"--frames {text}: expected START:STOP with 0 <= START < STOP (frame numbers, STOP excluded)")
    return a, b


def parse_part(text: str, scan: Scan) -> list[int]:
    """``I/N``: the frames of the I-th (1-based) of N nearly equal parts of the
    log, in log order; a workflow need not know the number of frames."""
    i, sep, n = text.partition("/")
    try:
        i, n = int(i), int(n)
    except ValueError:
        i = n = 0
    if not sep or not 1 <= i <= n:
        raise InputError(f"--part {text}: expected I/N with 1 <= I <= N")
    frames = [int(f) for f in scan.log.frame]
    m = len(frames)
    return frames[(i - 1) * m // n:i * m // n]


def part_document(scan: Scan, opt: DetectOptions, frames_idx: list[int], results: list[list],
                  frame_range: tuple[int, int], lag: float) -> dict:
    rows, cols = scan.stack.shape
    return {"format": MARKERS_FORMAT, "software": f"conecal {__version__}", "frame_range": list(frame_range),
            "part": PART_NOTE, "detector": {"shape": [rows, cols]},
            "part_options": {**asdict(opt), "lag": lag},
            "frames": [{"frame": k, "markers": [], "blobs": [{n: getattr(b, n) for n in _BLOB_FIELDS} for b in res]}
                       for k, res in zip(frames_idx, results)]}


def _fingerprint(doc: dict) -> dict:
    b = doc.get("scan_binding") or {}
    return {k: b.get(k) for k in _FINGERPRINT}


def merge_parts(paths: list) -> dict:
    """The markers document of a whole scan from its parts (any order)."""
    parts = []
    for p in paths:
        doc = read_json(p, "conecal-markers")
        if not doc.get("frame_range") or "part_options" not in doc:
            raise InputError(f"{p}: not a part (detect --frames START:STOP writes parts)")
        if not doc.get("scan_binding"):
            raise InputError(f"{p}: scan_binding: a part must name its scan")
        parts.append((p, doc))
    p0, d0 = parts[0]
    for p, d in parts[1:]:
        if _fingerprint(d) != _fingerprint(d0) or d.get("scan") != d0.get("scan"):
            raise InputError(f"{p} and {p0} come from different scans")
        if d["part_options"] != d0["part_options"]:
            raise InputError(f"{p} and {p0} were detected with different options")
    scan = load_scan(bound_scans(d0, p0)[0])
    by_frame, owner = {}, {}
    for p, d in parts:
        for fr in d["frames"]:
            k = int(fr["frame"])
            if k in by_frame:
                raise InputError(f"{p}: frame {k} is also in {owner[k]}")
            try:
                by_frame[k] = [Blob(**{**b, "flags": list(b["flags"])}) for b in fr.get("blobs", [])]
            except (TypeError, KeyError) as exc:
                raise InputError(f"{p}: frames[frame {k}].blobs: {exc}") from None
            owner[k] = p
    frames_idx = [int(f) for f in scan.log.frame]
    missing = [k for k in frames_idx if k not in by_frame]
    if missing:
        raise InputError(f"the parts leave out frame(s) {missing[:5]}{' ...' if len(missing) > 5 else ''} of "
                         f"{scan.root}: give every part")
    extra = sorted(set(by_frame) - set(frames_idx))
    if extra:
        raise InputError(f"{owner[extra[0]]}: frame {extra[0]} is not in {scan.root}'s log")
    o = dict(d0["part_options"])
    o.pop("lag", None)
    o["diameter_px"] = tuple(o["diameter_px"])
    opt = DetectOptions(**o)
    doc = assemble(scan, opt, frames_idx, [by_frame[k] for k in frames_idx])
    return {**doc, "scan": d0["scan"]}
