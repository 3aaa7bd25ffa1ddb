"""A bundle solved again started from the solution before it, too (``calib/run.py``)."""

from __future__ import annotations

from .bundle import Observations, adjust


def from_before(fits: dict, before, frames: list, cam, obs: Observations, shape, radius) -> None:
    """``before``: (the last look's final bundle, its frames in slot order).
    When ``frames`` are the same, ``fits[name]`` of its family is replaced by
    that family fitted from it, if that ends at a lower chi-square. A frame's
    twist about its own centre has false minima (a weak twist about a far
    centre) the start from the search's poses can fall into on one look and
    not the one before (carm_images ball3d_ii: two of 12 frames' twists went
    from 9 and 15 to about 0, their centres 670 px out, and ten of one
    frame's 24 markers were set aside as off the prediction). The phantom
    as its file has it, as every fit here."""
    if before is None or [fr["frame"] for fr in frames] != before[1]:
        return
    b = before[0]
    name = b.family.name
    if name not in fits:
        return
    alt = adjust(b.family, cam, obs, shape.points, radius, None, None, start=b, max_nfev=30, points_sigma=0.0)
    if alt.fit.chi2 < fits[name].fit.chi2:
        fits[name] = alt
