"""fit-pose judges detect's sigma by its own residuals, one factor per flag class."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from conecal.calib.bundle import Observations
from conecal.calib.run import _class_scales, _detections, _rescaled


def _scan(rng, overlap_noise: float):
    """One frame: 150 unflagged markers scattered as their sigma (0.05 px)
    says, 80 flagged overlap at ``overlap_noise`` times it, 5 flagged
    truncated (too few to judge)."""
    flags = [[]] * 150 + [["overlap"]] * 80 + [["truncated"]] * 5
    frame = {"markers": [{"x": 10.0 * i, "y": 5.0, "sigma": 0.05, "flags": f} for i, f in enumerate(flags)]}
    xy, sig, cls = _detections(frame)
    noise = np.where(cls == "overlap", overlap_noise, 1.0) * sig
    resid = rng.normal(0, 1, (len(xy), 2)) * noise[:, None]
    d = np.arange(len(xy))
    obs = Observations(np.zeros(len(xy), int), d, xy, sig)
    usable = [{"frame": 0, "slot": 0, "pairs": (d, d)}]
    return SimpleNamespace(residual_px=resid), obs, usable, {0: (xy, sig, cls)}


def test_a_flag_class_whose_residuals_are_wider_gets_a_wider_sigma():
    b, obs, usable, dets = _scan(np.random.default_rng(3), 4.0)
    scales = _class_scales(b, obs, usable, dets)
    assert set(scales) == {"unflagged", "overlap"}          # 5 truncated: too few to judge
    ratio = scales["overlap"]["factor"] / scales["unflagged"]["factor"]
    assert 3.2 < ratio < 4.8, ratio
    assert _rescaled(dets, scales)
    xy, sig, cls = dets[0]
    assert np.allclose(sig[cls == "overlap"], 0.05 * scales["overlap"]["factor"])
    assert np.allclose(sig[cls == "truncated"], 0.05)


def test_classes_that_scatter_alike_are_left_alone():
    b, obs, usable, dets = _scan(np.random.default_rng(4), 1.0)
    scales = _class_scales(b, obs, usable, dets)
    assert all(0.8 < v["factor"] < 1.25 for v in scales.values()), scales
    assert not _rescaled(dets, scales) and np.all(dets[0][1] == 0.05)
    # rows not the bundle's (another order): nothing is judged
    shuffled = Observations(obs.slot, obs.sph, obs.xy, obs.sigma[::-1] * np.linspace(1, 2, len(obs)))
    assert _class_scales(b, shuffled, usable, dets) == {}
