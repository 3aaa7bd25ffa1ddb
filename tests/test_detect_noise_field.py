"""detect where the noise is not one number for the frame: the noise field (issue 32)."""

import numpy as np

from conecal.detect import DetectOptions, detect_frame
from conecal.detect.noise import noise_field, noise_pixel
from conecal.detect.overlap import render

SHAPE = (256, 320)


def _scene(rng):
    """Spheres (x, y, R px, mu per px) on a 5 x 4 lattice, jittered."""
    return np.array([[x + rng.uniform(-2, 2), y + rng.uniform(-2, 2), 6.0, 0.06]
                     for x in np.arange(5) * 60 + 40 for y in np.arange(4) * 60 + 38])


def _body(shape):
    """A phantom body's attenuation: 0.2 on the left, rising smoothly to 1.6 on the right."""
    x = np.arange(shape[1]) / (shape[1] - 1)
    return np.tile(0.2 + 1.4 * x * x, (shape[0], 1))


def test_a_shadow_on_a_thick_body_is_not_clutter_for_its_quanta():
    """Quanta make the noise grow with attenuation (3.3x here from left to
    right): with one noise for the frame every shadow on the thick side
    read as clutter; the field follows it and the flags go."""
    rng = np.random.default_rng(5)
    body = _body(SHAPE)
    sph = _scene(rng)
    a = body + render(SHAPE, sph, 1.0)
    noisy = (a + rng.normal(0, 1, SHAPE) * 0.005 * np.exp(a / 2 * 1.7)).astype(np.float32)
    f = noise_field(noisy, noise_pixel(noisy))
    assert 2.0 < f.white[4, -1] / f.white[4, 0] < 4.5 and f.at(300, 128) > 1.5 * f.level
    opt = DetectOptions(diameter_px=(8, 16), pixel_noise=noise_pixel(noisy))
    blobs = detect_frame(noisy, opt)
    assert len(blobs) == len(sph)
    assert sum("clutter" in b.flags for b in blobs) <= 1
