"""Reading ``conecal-markers/1`` into observation arrays for the fits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


def load_observations(path, scan, *, use_flagged: bool = False) -> Observations:
    doc = read_json(path, "conecal-markers")
    shape = doc.get("detector", {}).get("shape")
    expect = [scan.config.detector.rows, scan.config.detector.cols]
    if shape is not None and list(shape) != expect:
        raise InputError(f"{path}: detector shape {shape} does not match the scan's {expect} (rows, cols)")
    row_of = {int(f): i for i, f in enumerate(scan.log.frame)}
    rows, frames, ids, xy, sig = [], [], [], [], []
    for fi, fr in enumerate(doc.get("frames", [])):
        try:
            k = int(fr["frame"])
            markers = fr["markers"]
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{path}: frames[{fi}]: needs 'frame' and 'markers'") from None
        if k not in row_of:
            raise InputError(f"{path}: frames[{fi}]: frame {k} is not in the scan's log")
        for mi, m in enumerate(markers):
            try:
                x, y, s = float(m["x"]), float(m["y"]), float(m["sigma"])
            except (KeyError, TypeError, ValueError):
                raise InputError(f"{path}: frames[{fi}].markers[{mi}]: needs numbers x, y, sigma") from None
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(s) and s > 0):
                raise InputError(f"{path}: frames[{fi}].markers[{mi}]: x, y must be finite and sigma > 0")
            if not use_flagged and any(f in BIASING_FLAGS for f in m.get("flags", [])):
                continue
            rows.append(row_of[k])
            frames.append(k)
            ids.append(-1 if m.get("id") is None else int(m["id"]))
            xy.append((x, y))
            sig.append(s)
    return Observations(np.array(rows, int), np.array(frames, int), np.array(ids, int),
                        np.array(xy, float).reshape(-1, 2), np.array(sig, float))
