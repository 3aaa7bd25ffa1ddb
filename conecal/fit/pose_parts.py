"""A robot fit-pose document's totals, computed from its frames alone, so that
``fit-pose --frames``/``--part`` parts merge into the bytes of one run."""

from __future__ import annotations

from collections import Counter

import numpy as np

from ..parts import cover, read_parts
from .pose import placement_summary

# what must agree between parts of one fit (everything but the frames and totals)
SAME = ("format", "software", "geometry_from", "source", "detector", "axes", "units", "options", "helix",
        "bundle_adjustment")


def poses_totals(frames: list[dict]) -> dict:
    """``summary`` and ``placement`` of a poses document from its (rounded) frames."""
    ok = [f for f in frames if f["status"] == "ok"]
    n = np.array([2 * f["n_spheres"] for f in ok], float)
    ms = np.array([f["rms_px"] ** 2 for f in ok], float)
    rms = float(np.sqrt(np.sum(n * ms) / np.sum(n))) if ok else float("nan")
    return {"placement": placement_summary([f.get("placement_error") if f["status"] == "ok" else None
                                            for f in frames]),
            "summary": {"frames": len(frames), "ok": len(ok), "rejected": len(frames) - len(ok),
                        "rejection_rate": (len(frames) - len(ok)) / len(frames) if frames else float("nan"),
                        "reasons": dict(sorted(Counter(f["reason"] for f in frames if "reason" in f).items())),
                        "rms_px": rms}}


def merge_pose_parts(paths: list) -> dict:
    """The poses document of a whole robot scan from its parts (any order)."""
    from ..jsonio import rounded

    parts, scan = read_parts(paths, "conecal-poses", SAME)
    by_frame = cover(parts, scan)
    frames = [by_frame[int(k)][1] for k in scan.log.frame]
    doc = {k: v for k, v in parts[0][1].items() if k not in ("frame_range", "scan_binding", "frames")}
    return {**doc, **rounded(poses_totals(frames)), "frames": frames}
