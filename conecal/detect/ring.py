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
