"""Candidate peaks that a neighbour's shadow spoilt: seeds for the joint
fits of :mod:`.crowded`. Units: px."""

from __future__ import annotations

from .frame import window_reach
from .options import DetectOptions, Blob
from .overlap import components


def crowd_seeds(peaks, kept: list[Blob], R1: float, opt: DetectOptions, strong=None) -> list:
    """Candidate peaks (x, y) that no shadow measured alone accounts for and
    that lie within touching reach of another shadow or such peak: shadows
    spoilt by a neighbour, to be measured with it (one per 0.8 R1). A chain
    of such peaks counts only when it reaches a shadow or holds a peak among
    ``strong`` (default all: as strong as a sphere's); weak peaks touching
    only each other are noise on a broad blot."""
    free: list = []
    for px, py in peaks:
        if any((px - b.x) ** 2 + (py - b.y) ** 2 < (0.8 * b.radius) ** 2 for b in kept):
            continue
        if any((px - q[0]) ** 2 + (py - q[1]) ** 2 < (0.8 * R1) ** 2 for q in free):
            continue
        free.append((px, py))
    reach = window_reach(R1, R1, opt.blur_px)
    pts = free + [(b.x, b.y) for b in kept]
    real = [strong is None or p in strong for p in free] + [True] * (len(pts) - len(free))
    touching, links = set(), []
    for i in range(len(free)):
        for j in range(i + 1, len(pts)):
            if (pts[i][0] - pts[j][0]) ** 2 + (pts[i][1] - pts[j][1]) ** 2 < reach**2:
                touching |= {i, j}
                # (two weak peaks do not carry a chain: over a spine's edges one
                # weak peak touches the next across the whole frame)
                if real[i] or real[j]:
                    links.append((i, j))
    comp = components(len(pts), links)
    anchored = {comp[i] for i in range(len(pts)) if real[i]}
    return [p for i, p in enumerate(free) if i in touching and comp[i] in anchored]
