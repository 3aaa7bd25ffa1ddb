"""Marker identities across frames by predicted nearest-neighbour assignment.

Each track predicts its next position from its last two (constant velocity
in the image); detections are assigned to predictions by the Hungarian
method within a gate, unassigned detections start new tracks. Ids are
renumbered in order of first appearance (frame, then column, then row),
so the result is deterministic.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def track(frames: list[list], max_gap: int = 3, predictor=None,
          kinematic_first: bool = False) -> tuple[list[list[int]], dict[int, tuple[int, int]]]:
    """Assign ids to per-frame blob lists (objects with x, y, radius).

    ``predictor(k1, xy, k2) -> xy`` predicts where a marker seen at ``xy`` in
    frame ``k1`` appears in frame ``k2`` from the logged motion; it is used
    for a track's first link, and always when ``kinematic_first`` (motion
    that is not smooth in the image, such as a raster).
    Returns ids per frame (same nesting as ``frames``) and each id's
    (first, last) frame.
    """
    tracks: list[dict] = []
    ids_out: list[list[int]] = []
    for k, blobs in enumerate(frames):
        live = [t for t in tracks if k - t["last"] <= max_gap]
        ids = [-1] * len(blobs)
        if blobs and live:
            P = np.array([[b.x, b.y] for b in blobs])
            R = np.array([b.radius for b in blobs])
            nn = np.full(len(blobs), np.inf)
            if len(blobs) > 1:
                d = np.hypot(P[:, None, 0] - P[None, :, 0], P[:, None, 1] - P[None, :, 1])
                np.fill_diagonal(d, np.inf)
                nn = d.min(axis=1)
            pred, gate = [], []
            for t in live:
                gap = k - t["last"]
                if predictor is not None and (kinematic_first or t["v"] is None):
                    pred.append(predictor(t["last"], t["p"], k))
                    gate.append(3.0 * t["r"] + 5.0)
                elif t["v"] is not None:
                    pred.append(t["p"] + gap * t["v"])
                    gate.append(max(0.6 * t["r"], 3.0) * gap)
                else:
                    pred.append(t["p"])
                    gate.append(4.0 * t["r"] + 5.0)
            pred, gate = np.array(pred), np.array(gate)
            cost = np.hypot(pred[:, None, 0] - P[None, :, 0], pred[:, None, 1] - P[None, :, 1])
            # a first link must also be unambiguous: closer than half the nearest neighbour
            first_link = np.array([t["v"] is None or kinematic_first for t in live])
            allowed = cost <= np.minimum(gate[:, None], np.where(first_link, 0.5, np.inf)[:, None] * nn[None, :])
            allowed &= np.abs(np.array([t["r"] for t in live])[:, None] - R[None, :]) < 0.35 * R[None, :] + 1.0
            big = 1e9
            rows, cols = linear_sum_assignment(np.where(allowed, cost, big))
            for i, j in zip(rows, cols):
                if allowed[i, j]:
                    t = live[i]
                    newp = P[j]
                    t["v"] = (newp - t["p"]) / (k - t["last"])
                    t["p"], t["r"], t["last"] = newp, R[j], k
                    ids[j] = t["id"]
        for j, b in enumerate(blobs):
            if ids[j] < 0:
                t = {"id": len(tracks), "p": np.array([b.x, b.y]), "v": None, "r": b.radius, "first": k, "last": k}
                tracks.append(t)
                ids[j] = t["id"]
        ids_out.append(ids)
    # deterministic renumbering by first appearance
    first = {}
    for k, (ids, blobs) in enumerate(zip(ids_out, frames)):
        for i, b in zip(ids, blobs):
            if i not in first:
                first[i] = (k, round(b.x, 3), round(b.y, 3))
    order = sorted(first, key=lambda i: first[i])
    remap = {old: new for new, old in enumerate(order)}
    ids_out = [[remap[i] for i in ids] for ids in ids_out]
    spans: dict[int, list[int]] = {}
    for k, ids in enumerate(ids_out):
        for i in ids:
            spans.setdefault(i, [k, k])[1] = k
    return ids_out, {i: (s[0], s[1]) for i, s in spans.items()}
