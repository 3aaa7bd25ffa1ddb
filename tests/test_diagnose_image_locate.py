"""Image level, locate before naming (conecal/diagnose/image_locate.py) and
the focal-spot kernel: laws checked on per-patch values drawn here, not by
conecal's simulator."""

import numpy as np
import pytest

from conecal.diagnose.image import disc_kernel
from conecal.diagnose.image_locate import CURVES, FLOORS, curve_tests, field_degree
from conecal.stats import holm


def _patches(n=300, seed=0):
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n)
    frame = np.sort(rng.integers(0, 90, n)).astype(float)
    return {"u": u, "v": v, "time": frame / 90 - 0.5, "m1": 4 + 0.4 * u, "parity": (frame % 2).astype(int),
            "est": {c: np.full(n, np.nan) for c in CURVES}, "sigma": {c: np.full(n, np.nan) for c in CURVES}}, rng


def _significant(tests, curve, alpha=0.01):
    p = holm([t["p"] for t in tests])
    return [t for t, a in zip(tests, p) if t["curve"] == curve and a < alpha and t["size"] >= FLOORS[curve]]


def test_noise_alone_locates_nothing():
    hits = 0
    for seed in range(20):
        vals, rng = _patches(seed=seed)
        for c in CURVES:
            vals["sigma"][c][:] = 0.002
            vals["est"][c] = rng.normal(0, 0.002, len(vals["u"]))
        hits += any(_significant(curve_tests(vals), c) for c in CURVES)
    assert hits <= 1      # 20 scans at alpha 0.01


def test_noise_larger_than_its_sigma_is_not_a_structure():
    """Per-patch σ 3x too small (correlated noise on a real detector): the F test on the curve's own scatter."""
    vals, rng = _patches(seed=3)
    vals["sigma"]["scatter"][:] = 0.001
    vals["est"]["scatter"] = rng.normal(0, 0.003, len(vals["u"]))
    assert not [t for t in _significant(curve_tests(vals), "scatter") if t["variable"] != "none"]


def test_a_field_over_the_detector_is_located_there():
    vals, rng = _patches(seed=1)
    u, v = vals["u"], vals["v"]
    bump = 0.04 * np.exp(-((u - 0.1) ** 2 + (v + 0.15) ** 2) / (2 * 0.12 ** 2))
    vals["sigma"]["scatter"][:] = 0.002
    vals["est"]["scatter"] = bump + rng.normal(0, 0.002, len(u))
    sig = _significant(curve_tests(vals), "scatter")
    best = max(sig, key=lambda t: t["chi2"] / t["scale"] - 2 * t["dof"])
    assert best["variable"] == "detector position"
    hi = np.array(best["range_at"][1]) - 0.5       # where the fitted field is highest
    assert np.hypot(*(hi - [0.1, -0.15])) < 0.1
    assert field_degree(vals)[0] >= 2
    vals["est"]["scatter"] = 0.01 + rng.normal(0, 0.002, len(u))
    assert field_degree(vals)[0] == 0


def test_a_blur_that_grows_with_magnification_follows_it():
    vals, rng = _patches(seed=2)
    m1 = vals["m1"] = 4 + rng.uniform(-0.4, 0.4, len(vals["u"]))
    vals["sigma"]["edge"][:] = 0.02
    vals["est"]["edge"] = 0.5 * (m1 - 4) + rng.normal(0, 0.02, len(m1))
    sig = _significant(curve_tests(vals), "edge")
    assert max(sig, key=lambda t: t["chi2"] / t["scale"] - 2 * t["dof"])["variable"] == "m1"


@pytest.mark.parametrize("radius", [0.7, 2.5, 6.0])
def test_disc_kernel_is_a_disc_that_moves_smoothly_with_its_radius(radius):
    k = disc_kernel(radius)
    assert k.sum() == pytest.approx(1.0)
    h = k.shape[0] // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    # a uniform disc's variance per axis is R^2 / 4 (plus a pixel's 1/12); the rim ramp is coarse below 1 px
    assert (k * xx ** 2).sum() == pytest.approx(radius ** 2 / 4 + 1 / 12, rel=0.1 if radius < 1 else 0.03)
    d = (disc_kernel(radius + 1e-4)[1:-1, 1:-1] if disc_kernel(radius + 1e-4).shape != k.shape
         else disc_kernel(radius + 1e-4)) - k
    assert 0 < np.abs(d).sum() < 1e-3      # a step of 1e-4 px changes it, a little


def test_a_lag_decaying_over_frames_adds_each_earlier_frame_with_its_share():
    """The image model's ghost term: frame k back keeps lag * decay^(k-1) of its recorded
    transmission, and the background keeps its level (the recorded one has the lag in it)."""
    from conecal.diagnose.image import ImageModel, Patch

    yy, xx = np.mgrid[0:31, 0:31]
    chord = 2 * np.sqrt(np.clip(64 - (xx - 15.0) ** 2 - (yy - 15.0) ** 2, 0, None))
    prev, T2, T3 = (np.exp(-0.5 * np.roll(chord, s, axis=1)) for s in (3, 6, 9))
    bg = np.full(chord.shape, 0.2)
    p = Patch(0, 0, 0, (0, 31, 0, 31), np.zeros_like(chord), bg, chord, prev, np.ones_like(chord), 8.0,
              np.array([15.0, 15.0]), 0.01, earlier=[(T2, np.ones_like(chord)), (T3, np.ones_like(chord))])
    p.dchord = np.zeros_like(chord)
    x = np.zeros(len(ImageModel.PARAMS))
    x[ImageModel.PARAMS.index("mu")] = 0.5
    lag, decay = 0.04, 0.5
    x[ImageModel.PARAMS.index("lag")] = lag
    one = ImageModel.predict_patch(None, p, x)
    T = np.exp(-0.5 * chord)
    assert one == pytest.approx(bg - np.log((1 - lag) * T + lag * prev), abs=1e-12)
    x[ImageModel.PARAMS.index("lag_decay")] = decay
    c = [lag, lag * decay, lag * decay ** 2]
    expect = bg - np.log((1 - sum(c)) * T + c[0] * prev + c[1] * T2 + c[2] * T3)
    assert ImageModel.predict_patch(None, p, x) == pytest.approx(expect, abs=1e-12)
    assert not np.allclose(expect, one)

