"""The ring of background about a shadow, and the other shadows it leaves
out: pixel sets in a box of the frame (box coordinates: column, row; px)."""

from __future__ import annotations

import numpy as np


def keep_out(others, c0: int, q0: int, blur: float) -> list:
    """(x, y, radius) in a box at column c0, row q0 of the discs that the
    shadows ``others`` ((x, y, r) in the frame, px) cover, ``blur`` (px) and
    a margin included: what a background ring leaves out."""
    return [(ox - c0, oy - q0, 1.15 * r + 3 * blur + 2) for ox, oy, r in others]


def ring_mask(shape: tuple[int, int], x: float, y: float, r0: float, r1: float, discs=(),
              invalid: np.ndarray | None = None) -> np.ndarray:
    """The pixels of a box of ``shape`` (rows, cols) between r0 and r1 px of
    (x, y) (box coordinates: column, row), without the ``discs`` ((x, y,
    radius) each: other shadows, as :func:`keep_out` gives them) and
    ``invalid`` pixels."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    d2 = (xx - x) ** 2 + (yy - y) ** 2
    ring = (d2 >= r0 * r0) & (d2 <= r1 * r1)
    for ox, oy, orad in discs:
        if abs(ox - x) < r1 + orad and abs(oy - y) < r1 + orad:
            ring &= (xx - ox) ** 2 + (yy - oy) ** 2 > orad * orad
    if invalid is not None and invalid.shape == ring.shape:
        ring &= ~invalid
    return ring


def ring_level(a: np.ndarray, b, blobs: list, blur: float) -> float:
    """The background's level (attenuation) about blob ``b``: the median of a
    3 px ring just outside its shadow, other shadows left out; nan when
    fewer than 8 pixels remain."""
    r0 = b.radius + 2 * blur + 1
    r1 = r0 + 3
    rows, cols = a.shape
    c0, c1 = max(int(b.x - r1), 0), min(int(b.x + r1) + 2, cols)
    q0, q1 = max(int(b.y - r1), 0), min(int(b.y + r1) + 2, rows)
    if c1 <= c0 or q1 <= q0:
        return float("nan")
    ring = ring_mask((q1 - q0, c1 - c0), b.x - c0, b.y - q0, r0, r1,
                     [(o.x - c0, o.y - q0, o.radius + 2 * blur + 1) for o in blobs if o is not b])
    v = a[q0:q1, c0:c1][ring]
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size >= 8 else float("nan")
