"""Scoring ``detect`` against a simulator's truth (for tests and benchmarks)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Score:
    """Errors (px) and sigmas of unflagged, fully visible markers; counts."""

    errors: np.ndarray
    sigmas: np.ndarray
    found: int
    visible: int
    false: int
    flagged: int

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.errors**2))) if self.errors.size else float("nan")

    @property
    def pull(self) -> float:
        """RMS per-axis error over RMS reported sigma: 1 for honest uncertainties
        (errors are 2-D distances, sigma is per axis, hence the factor 2)."""
        return float(np.sqrt(np.mean(self.errors**2) / (2 * np.mean(self.sigmas**2)))) if self.errors.size else float("nan")


def score_markers(doc: dict, truth: dict, *, fov_radius: float | None = None, shape=None,
                  isolated: bool = True) -> Score:
    """Match detections to true shadow centroids frame by frame.

    A detection farther than a quarter diameter from every true marker is
    false. A true marker is fully visible when inside the detector, (with
    ``fov_radius``) inside the circular field of view with room for its
    window, and (with ``isolated``) no other shadow within reach.
    """
    errs, sig, found, visible, false, flagged = [], [], 0, 0, 0, 0
    for fr, tf in zip(doc["frames"], truth["frames"]):
        if not tf["markers"]:
            false += len(fr["markers"])
            continue
        P = np.array([m["centroid"] for m in tf["markers"]])
        D = np.array([m["diameter_px"] for m in tf["markers"]])
        vis = np.array([m["inside"] for m in tf["markers"]])
        if isolated:
            dd = np.hypot(P[:, None, 0] - P[None, :, 0], P[:, None, 1] - P[None, :, 1]) + np.eye(len(P)) * 1e9
            vis &= np.all(dd > (D[:, None] + D[None, :]) / 2 * 1.15 + 6, axis=1)
        if fov_radius is not None:
            c = (np.asarray(shape[::-1], float) - 1) / 2
            vis &= np.hypot(P[:, 0] - c[0], P[:, 1] - c[1]) + D / 2 + 8 < fov_radius
        hit = set()
        for m in fr["markers"]:
            d = np.hypot(P[:, 0] - m["x"], P[:, 1] - m["y"])
            j = int(d.argmin())
            if d[j] > D[j] / 4:
                false += 1
                continue
            hit.add(j)
            if m["flags"]:
                flagged += 1
            elif vis[j]:
                errs.append(d[j])
                sig.append(m["sigma"])
        visible += int(vis.sum())
        found += sum(1 for j in np.flatnonzero(vis) if j in hit)
    return Score(np.array(errs), np.array(sig), found, visible, false, flagged)
