"""Reading ``conecal-markers/1`` into observation arrays for the fits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..binding import check_scan
from ..errors import InputError
from ..jsonio import read_json

# flags that bias a centroid: such markers are left out unless asked for
BIASING_FLAGS = ("truncated", "overlap", "clutter")


@dataclass(frozen=True, eq=False)
class Observations:
    """Marker centres per (frame row, id): ``row`` indexes the scan log."""

    row: np.ndarray      # (m,) int, index into the scan's log rows
    frame: np.ndarray    # (m,) int, frame number as in the log
    ids: np.ndarray      # (m,) int (-1 when unknown)
    xy: np.ndarray       # (m, 2) px
    sigma: np.ndarray    # (m,) px
    radius: np.ndarray | None = None   # (m,) shadow radius px, where detect gave it


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def read_markers(path) -> dict:
    """Read and check a ``conecal-markers/1`` file: every frame a number and a
    list of markers; every marker finite x, y, a positive sigma, an integer
    or null id and a list of flag strings. InputError names the place."""
    doc = read_json(path, "conecal-markers")
    shape = (doc.get("detector") or {}).get("shape")
    if not (isinstance(shape, list) and len(shape) == 2 and all(isinstance(v, int) and v > 0 for v in shape)):
        shape = None
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise InputError(f"{path}: 'frames' must be a list")
    for fi, fr in enumerate(frames):
        if not isinstance(fr, dict) or not isinstance(fr.get("frame"), int) or isinstance(fr.get("frame"), bool) \
                or not isinstance(fr.get("markers"), list):
            raise InputError(f"{path}: frames[{fi}]: needs an integer 'frame' and a list 'markers'")
        for mi, m in enumerate(fr["markers"]):
            where = f"{path}: frames[{fi}].markers[{mi}]"
            if not isinstance(m, dict):
                raise InputError(f"{where}: must be an object")
            for key in ("x", "y", "sigma"):
                if not _number(m.get(key)):
                    raise InputError(f"{where}: {key!r} must be a finite number, got {m.get(key)!r}")
            if m["sigma"] <= 0:
                raise InputError(f"{where}: 'sigma' must be > 0, got {m['sigma']!r}")
            if shape is not None and not (-shape[1] <= m["x"] <= 2 * shape[1] and -shape[0] <= m["y"] <= 2 * shape[0]):
                raise InputError(f"{where}: ({m['x']!r}, {m['y']!r}) px lies far outside the {shape[1]}x{shape[0]} detector")
            if m.get("id") is not None and (not isinstance(m["id"], int) or isinstance(m["id"], bool)):
                raise InputError(f"{where}: 'id' must be an integer or null, got {m['id']!r}")
            flags = m.get("flags", [])
            if not isinstance(flags, list) or not all(isinstance(f, str) for f in flags):
                raise InputError(f"{where}: 'flags' must be a list of strings, got {flags!r}")
    return doc


def load_observations(path, scan, *, use_flagged: bool = False) -> Observations:
    doc = read_markers(path)
    check_scan(doc, path, scan.root, option=None, parts=("projections",))
    shape = doc.get("detector", {}).get("shape")
    expect = [scan.config.detector.rows, scan.config.detector.cols]
    if shape is not None and list(shape) != expect:
        raise InputError(f"{path}: detector shape {shape} does not match the scan's {expect} (rows, cols)")
    row_of = {int(f): i for i, f in enumerate(scan.log.frame)}
    rows, frames, ids, xy, sig, rad = [], [], [], [], [], []
    for fi, fr in enumerate(doc.get("frames", [])):
        k, markers = fr["frame"], fr["markers"]
        if k not in row_of:
            raise InputError(f"{path}: frames[{fi}]: frame {k} is not in the scan's log")
        for m in markers:
            x, y, s = float(m["x"]), float(m["y"]), float(m["sigma"])
            if not use_flagged and any(f in BIASING_FLAGS for f in m.get("flags", [])):
                continue
            rows.append(row_of[k])
            frames.append(k)
            ids.append(-1 if m.get("id") is None else int(m["id"]))
            xy.append((x, y))
            sig.append(s)
            r = m.get("radius")
            rad.append(float(r) if isinstance(r, (int, float)) and not isinstance(r, bool) and np.isfinite(r) else np.nan)
    return Observations(np.array(rows, int), np.array(frames, int), np.array(ids, int),
                        np.array(xy, float).reshape(-1, 2), np.array(sig, float), np.array(rad, float))
