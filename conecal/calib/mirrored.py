"""Whether a free-pose scan's images are mirrored (columns reversed).

Many C-arm and radiography consoles write the image as the operator sees it,
left-right flipped against the detector's own column order, and nothing in
the file says so. No rigid pose explains the mirror image of a phantom that
is not planar (its mirror is another, mirror-handed phantom), so such a scan
fails to calibrate; a planar phantom's mirror image is the phantom seen from
behind with the principal point mirrored, and no test can tell (a planar
scan is not tested). When a free-pose fit fails, the same markers with their
columns reversed (``c -> cols - 1 - c``, the pixel-centre convention of the
scan contract) are calibrated once more: if that fit stands, the failure is
most likely the mirror, and the error says so. Units: px.
"""

from __future__ import annotations

import numpy as np

from ..errors import FitError

# a phantom whose positions' smallest principal extent is under this share of
# the largest is planar (a plate's beads, within their placement tolerance)
_PLANAR = 1e-3
# the mirrored fit must make at least this share of the frames ok
_MOST = 0.5


def planar(positions: np.ndarray) -> bool:
    """Whether phantom ``positions`` (n, 3) mm lie in one plane."""
    p = np.asarray(positions, float)
    s = np.linalg.svd(p - p.mean(0), compute_uv=False)
    return len(p) < 4 or s[-1] <= _PLANAR * s[0]


def mirrored_markers(markers: dict, cols: int) -> dict:
    """``markers`` (conecal-markers/1) with every centre's column reversed
    (``x -> cols - 1 - x``); σ and flags unchanged."""
    return {**markers, "frames": [{**f, "markers": [{**m, "x": cols - 1 - float(m["x"])} for m in f["markers"]]}
                                  for f in markers["frames"]]}


def mirror_hint(scan, markers: dict, geometry, opt, calibrate, say=lambda s: None) -> str | None:
    """After ``calibrate(scan, markers, geometry, opt)`` (the free-pose fit)
    failed: a sentence saying the images look mirrored, with the mirrored
    fit's numbers, when the same markers with columns reversed calibrate with
    most frames ok; else None (also for a planar phantom, where the mirror
    cannot be told, and which is not tried). ``say(line)``: feedback."""
    if scan.phantom is None or planar(scan.phantom.positions):
        return None
    say("trying the markers with the images' columns reversed (a mirrored display?)")
    try:
        res = calibrate(scan, mirrored_markers(markers, scan.config.detector.cols), geometry, opt)
    except FitError:
        return None
    ok = [f for f in res.frames if f["status"].ok]
    if len(ok) < _MOST * len(res.frames):
        return None
    rms = float(np.sqrt(np.mean(np.sum(res.bundle.residual_px ** 2, 1))))
    return (f"with every image's columns reversed, {len(ok)}/{len(res.frames)} frames calibrate at "
            f"{rms:.3f} px RMS: the projections look mirrored left-right (as many C-arm consoles write them); "
            f"reverse their columns and run detect again")
