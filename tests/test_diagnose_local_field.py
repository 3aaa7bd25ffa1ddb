"""diagnose's local places on the detector (``diagnose.local_field``) and the
set-aside detections it pairs again (``diagnose.free._set_aside``)."""

import numpy as np
import pytest

from conecal.diagnose.free import _set_aside
from conecal.diagnose.local_field import local_displacements

SHAPE = (512, 512)


def _markers(seed: int, frames: int = 20, per: int = 60, sigma: float = 0.05):
    """Centres scattered over the detector in ``frames`` frames, residuals of
    white noise ``sigma`` px."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(20, 492, (frames * per, 2))
    frame = np.repeat(np.arange(frames), per)
    return rng, xy, rng.normal(0, sigma, xy.shape), np.full(len(xy), sigma), frame


def test_a_bump_is_found_where_it_is():
    rng, xy, r, s, fr = _markers(1)
    c = np.array([300.0, 200.0])
    r = r + 0.3 * np.exp(-((xy - c) ** 2).sum(1) / (2 * 12.0 ** 2))[:, None] * np.array([0.6, -0.8])
    found, inside, tested = local_displacements(xy, r, s, fr, SHAPE)
    assert len(found) == 1, [f["shape"] for f in found]
    f = found[0]
    assert np.hypot(*(np.array(f["centre_px"]) - c)) < 15
    d = np.array(f["displacement_px"])
    assert d @ np.array([0.6, -0.8]) > 0.7 * np.hypot(*d)
    assert inside[np.hypot(*(xy - c).T) < 10].all() and tested > 100


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_noise_and_a_smooth_field_make_no_place(seed):
    rng, xy, r, s, fr = _markers(seed)
    z = (xy - 256) / 256
    # a cubic field of 1.5 px at the corners: the polynomial field's, not a place
    r = r + 0.5 * np.stack([z[:, 0] ** 2 + z[:, 1] ** 2 + 0.5 * z[:, 0] ** 3, z[:, 0] * z[:, 1] + 0.5 * z[:, 1] ** 3], 1)
    found, _, _ = local_displacements(xy, r, s, fr, SHAPE)
    assert not found, [f["shape"] for f in found]


def test_one_frame_or_understated_sigma_make_no_place():
    rng, xy, r, s, fr = _markers(5)
    # one frame's markers near a point all 1 px off (a wrong sphere, motion): that frame's, not the detector's
    near = np.flatnonzero(fr == 3)[:20]
    xy[near] = [250.0, 250.0] + rng.normal(0, 8, (20, 2))
    r[near] += [1.0, 0.0]
    found, _, _ = local_displacements(xy, r, s, fr, SHAPE)
    assert not found, [f["shape"] for f in found]
    # residuals three times the stated sigma, with a few gross ones: the scatter, not sigma, judges
    rng, xy, r, s, fr = _markers(6, sigma=0.15)
    r[rng.choice(len(r), 10, replace=False)] += rng.normal(0, 2.0, (10, 2))
    found, _, _ = local_displacements(xy, r, s / 3, fr, SHAPE)
    assert not found, [f["shape"] for f in found]


def test_set_aside_detections_pair_only_where_unambiguous():
    ids = [10, 11, 12, 13]
    pred = np.array([[100.0, 100.0], [130.0, 100.0], [100.0, 130.0], [300.0, 300.0]])
    ms = [{"x": 100.2, "y": 100.1, "flags": []},          # 0: used by the fit
          {"x": 131.0, "y": 100.5, "flags": []},          # 1: sphere 11, 1.1 px off: paired
          {"x": 115.0, "y": 100.0, "flags": []},          # 2: between 10 and 11: not paired
          {"x": 100.5, "y": 131.0, "flags": ["truncated"]},  # 3: truncated: not paired
          {"x": 299.0, "y": 300.0, "flags": []},          # 4, 5: two claim sphere 13: neither
          {"x": 301.0, "y": 300.5, "flags": []},
          {"x": 101.0, "y": 99.0, "flags": []}]           # 6: beside sphere 10, which the fit used
    assert _set_aside(ms, {0}, {10}, pred, ids) == [(1, 11)]


def test_the_report_draws_a_place():
    from conecal.report.located import located_figure, located_table

    place = {"component": "local displacement on the detector", "unit": "px", "variable": "detector position",
             "shape": "a place", "size": 1.1, "size_px": 1.1, "centre_px": [432.0, 432.0], "radius_px": 48.0,
             "displacement_px": [-1.1, 0.02]}
    png = located_figure({"located": [place]})
    assert png is not None and png[:4] == b"\x89PNG"
    assert "local displacement on the detector" in located_table({"located": [place]})
    assert located_figure({"located": []}) is None
