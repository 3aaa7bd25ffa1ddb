"""Parts of a scan computed apart (``--frames START:STOP`` / ``--part I/N``)
and the checks every ``merge`` makes: the parts come from one scan (the
same fingerprints), were made with one set of options, and cover the scan's
log exactly once.
"""

from __future__ import annotations

from .binding import bound_scans
from .errors import InputError
from .jsonio import read_json
from .scan import Scan, load_scan

_FINGERPRINT = ("scan_yaml_sha256", "log_sha256", "projections_bytes", "projections_sha256_sampled")


def parse_frames(text: str, scan: Scan) -> list[int]:
    """``START:STOP`` (frame numbers, STOP excluded; either end may be left out):
    the log's frames in that range, in log order."""
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
    out = [k for k in frames if a <= k < b]
    if not out:
        raise InputError(f"--frames {text}: no frame of {scan.root}'s log is in this range")
    return out


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
    out = frames[(i - 1) * len(frames) // n:i * len(frames) // n]
    if not out:
        raise InputError(f"--part {text}: {scan.root}'s log has only {len(frames)} frames")
    return out


def selected_frames(scan: Scan, frames: str | None, part: str | None) -> list[int] | None:
    """The frames a ``--frames``/``--part`` option selects (None: the whole scan)."""
    if frames is not None and part is not None:
        raise InputError("give --frames or --part, not both")
    if frames is not None:
        return parse_frames(frames, scan)
    if part is not None:
        return parse_part(part, scan)
    return None


def frame_range(frames: list[int]) -> list[int]:
    return [min(frames), max(frames) + 1]


def _fingerprint(doc: dict) -> dict:
    b = doc.get("scan_binding") or {}
    return {k: b.get(k) for k in _FINGERPRINT}


def read_parts(paths: list, fmt: str, same: tuple[str, ...]) -> tuple[list[tuple[str, dict]], Scan]:
    """Read parts of one format; check they share their scan and the keys
    ``same`` (options, geometry, ...). Returns the parts and the scan."""
    parts = []
    for p in paths:
        doc = read_json(p, fmt, parts_ok=True)
        if not doc.get("frame_range"):
            raise InputError(f"{p}: not a part (--frames START:STOP or --part I/N writes parts)")
        if not doc.get("scan_binding"):
            raise InputError(f"{p}: scan_binding: a part must name its scan")
        parts.append((str(p), doc))
    p0, d0 = parts[0]
    for p, d in parts[1:]:
        if _fingerprint(d) != _fingerprint(d0) or d.get("scan") != d0.get("scan"):
            raise InputError(f"{p} and {p0} come from different scans")
        for key in same:
            if d.get(key) != d0.get(key):
                raise InputError(f"{p} and {p0} differ in {key!r}: they were not made with the same options")
    return parts, load_scan(bound_scans(d0, p0)[0])


def cover(parts: list[tuple[str, dict]], scan: Scan) -> dict[int, tuple[str, dict]]:
    """Frame number -> (part, frame entry); every log frame exactly once."""
    by_frame = {}
    for p, d in parts:
        for fr in d["frames"]:
            k = int(fr["frame"])
            if k in by_frame:
                raise InputError(f"{p}: frame {k} is also in {by_frame[k][0]}")
            by_frame[k] = (p, fr)
    frames_idx = [int(f) for f in scan.log.frame]
    missing = [k for k in frames_idx if k not in by_frame]
    if missing:
        raise InputError(f"the parts leave out frame(s) {missing[:5]}{' ...' if len(missing) > 5 else ''} of "
                         f"{scan.root}: give every part")
    extra = sorted(set(by_frame) - set(frames_idx))
    if extra:
        raise InputError(f"{by_frame[extra[0]][0]}: frame {extra[0]} is not in {scan.root}'s log")
    return by_frame
