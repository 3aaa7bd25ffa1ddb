"""The noise detect measures: over what is a measurement, as it grows with
the background's level, and what the tests built on it then say."""

import numpy as np

from conecal.detect import DetectOptions
from conecal.detect.noise import noise_at, noise_pixel, noise_slope, noise_small
from conecal.detect.overlap import render


def _ramp(rng, n=384, top=2.0, photons=4000.0, sph=None, power=1):
    """Attenuation of a linear detector's frame over a background rising
    0 -> ``top`` across its columns (as their ``power``), with quantum noise
    (sigma grows as exp(a / 2)); ``sph`` (k, 4) spheres rendered on it."""
    yy, xx = np.mgrid[0:n, 0:n]
    a = top * (xx / (n - 1)) ** power + 0.0 * yy
    if sph is not None:
        a = a + render((n, n), sph, 0.8)
    return (-np.log(np.maximum(rng.poisson(photons * np.exp(-a)), 0.5) / photons)).astype(np.float32)


def test_quantum_noise_grows_as_exp_half_the_attenuation():
    rng = np.random.default_rng(1)
    beta, level = noise_slope([_ramp(rng), _ramp(rng)])
    assert abs(beta - 0.5) < 0.1 and 0.8 < level < 1.2
    # a uniform noise has no slope; a frame of one level none to measure
    flat = rng.normal(0.0, 0.01, (384, 384)).astype(np.float32) + np.linspace(0, 2, 384)[None, :].astype(np.float32)
    assert abs(noise_slope([flat])[0]) < 0.1
    assert noise_slope([rng.normal(0.0, 0.01, (384, 384)).astype(np.float32)])[0] == 0.0
    opt = DetectOptions(diameter_px=(8.0, 12.0), noise_slope=0.5, noise_level=1.0)
    assert np.isclose(noise_at(0.02, 2.0, opt), 0.02 * np.exp(0.5))


def test_what_lies_outside_an_intensifiers_field_is_no_noise():
    """An intensifier's circular field leaves a fifth to a third of the frame
    at one value beyond ``max_attenuation``; counted, it read as noiseless
    pixels and the frame's noise came out at 0.4-0.8 of its shadows' rings."""
    rng = np.random.default_rng(2)
    n = 400
    a = rng.normal(0.3, 0.02, (n, n)).astype(np.float32)
    yy, xx = np.mgrid[0:n, 0:n]
    a[(xx - n / 2) ** 2 + (yy - n / 2) ** 2 > (0.45 * n) ** 2] = 13.8
    assert noise_pixel(a) < 0.85 * 0.02 and noise_small(a) < 0.85 * 0.02
    assert abs(noise_pixel(a, limit=4.0) / 0.02 - 1) < 0.08
    assert abs(noise_small(a, limit=4.0) / 0.02 - 1) < 0.08


def test_a_shadow_behind_thick_material_is_not_clutter_for_its_noise():
    """A sphere over a thick part of the phantom sits in more noise than the
    frame's median: its ring read as structure and every such marker was
    flagged clutter. With the measured slope it is flagged only as its
    level's noise says."""
    from dataclasses import replace

    from conecal.detect.crowded import detect_frame

    rng = np.random.default_rng(3)
    n = 384
    sph = np.array([[x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), 5.0, 0.12]
                    for x in (60, 150, 240, 330) for y in (60, 150, 240, 330)])
    frames = [_ramp(rng, n, 3.5, 20000.0, sph, power=2) for _ in range(2)]
    beta, level = noise_slope(frames)
    opt = DetectOptions(diameter_px=(7.0, 14.0), blur_px=0.8, pixel_noise=noise_pixel(frames[0]),
                        noise_slope=beta, noise_level=level)
    blobs = detect_frame(frames[1], opt)
    assert len(blobs) == len(sph)
    dark = [b for b in blobs if b.x > 280]            # behind 2.6 of attenuation, the median 0.9
    assert sum("clutter" in b.flags for b in dark) <= 1
    old = detect_frame(frames[1], replace(opt, noise_slope=0.0))
    assert sum("clutter" in b.flags for b in old if b.x > 280) >= 3


def test_a_small_shadow_in_heavy_noise_keeps_its_half_maximum_size():
    """A 6 px shadow at ten times the noise (a 1.6 mm bead over a thick
    cylinder): its window's second moment, which weighs each pixel's noise
    by rho^2 out to 2.7 radii, came out negative and the shadow was lost
    (an independent renderer's coded helix lost half its small beads)."""
    from conecal.detect.crowded import detect_frame

    rng = np.random.default_rng(4)
    n = 360
    sph = np.array([[x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), 3.0, 0.085]
                    for x in range(40, n - 20, 56) for y in range(40, n - 20, 56)])
    # (a sharper image than the blur typed: 9 of 36 were found)
    img = (1.5 + render((n, n), sph, 0.7) + rng.normal(0.0, 0.045, (n, n))).astype(np.float32)
    opt = DetectOptions(diameter_px=(3.7, 9.8), blur_px=1.0, pixel_noise=noise_pixel(img))
    blobs = detect_frame(img, opt)
    found = sum(min(np.hypot(b.x - sph[:, 0], b.y - sph[:, 1])) < 1.5 for b in blobs)
    assert found >= 0.95 * len(sph) and len(blobs) <= found + 1
