"""A shadow whose contrast depends on the background under it (a display
image stored as transmission): the scan's gain eta, and sigmas that cover
the centroid shift a background slope then causes."""

from dataclasses import replace

import numpy as np

from conecal.detect.crowded import detect_frame
from conecal.detect.options import Blob, DetectOptions
from conecal.detect.ring import ring_mask
from conecal.detect.gain import linearised, measure_gain, response_lambda, with_background, with_gain_sigma
from conecal.detect.noise import noise_correlation, noise_pixel


def test_a_ring_leaves_out_the_other_shadows_and_invalid_pixels():
    ring = ring_mask((41, 41), 20.0, 20.0, 10.0, 15.0)
    r = np.hypot(*(np.mgrid[0:41, 0:41] - 20.0))
    assert np.array_equal(ring, (r >= 10) & (r <= 15))
    bad = np.zeros((41, 41), bool)
    bad[:, :8] = True
    away = ring_mask((41, 41), 20.0, 20.0, 10.0, 15.0, [(32.0, 20.0, 4.0)], bad)
    assert away.sum() < ring.sum() and not away[20, 32] and not away[20, 6] and away[20, 9]


def _blobs(rng, eta, n_frames=3, n=20, magnified=False):
    out = []
    for _ in range(n_frames):
        res = []
        for _ in range(n):
            bg = rng.uniform(0.0, 0.6)
            # a tilted grid: the spheres farther from the source are smaller and,
            # per px of chord, denser (mu_px ~ 1/M): no gain of the background's
            r = 6.0 * (1 + 0.3 * bg) if magnified else rng.uniform(5.0, 7.0)
            chord = 0.5 * np.exp(eta * bg) * (1 + 0.03 * rng.standard_normal())
            res.append(Blob(100.0, 100.0, r, 0.03, chord / r, chord, 1.0, [], 50.0, bg=bg, bg_gx=0.0, bg_gy=0.0))
        out.append(res)
    return out


def test_gain_is_the_slope_of_log_contrast_on_the_background_level():
    rng = np.random.default_rng(0)
    g = measure_gain(_blobs(rng, 2.0))
    assert g.significant and abs(g.eta - 2.0) < 3 * g.se and g.se < 0.15
    g0 = measure_gain(_blobs(rng, 0.0))
    assert abs(g0.eta) < 3 * g0.se + 0.05
    # magnification that varies with the background is not a gain
    gm = measure_gain(_blobs(rng, 0.0, magnified=True))
    assert abs(gm.eta) < 0.15, gm
    # too few markers: nothing is claimed
    assert measure_gain(_blobs(rng, 2.0, n_frames=1, n=10)).n < 30


def _display_frame(rng, n=420, pitch=52, R=8.0, mu=0.03, k=2.0):
    """A log-windowed display image (stored as transmission, as an
    intensifier's export is) of spheres on a sloped background; and the
    sphere centres (px)."""
    yy, xx = np.mgrid[0:n, 0:n]
    # true attenuation of the background: a holder's ribs (slopes to 0.005 k per px)
    A = 0.6 + 0.08 * k * np.sin(2 * np.pi * (xx + 0.6 * yy) / 100)
    centres = [(x + rng.uniform(-3, 3), y + rng.uniform(-3, 3))
               for x in range(40, n - 30, pitch) for y in range(40, n - 30, pitch)]
    s = 4   # sub-pixel rays per axis
    for cx, cy in centres:
        w = int(R) + 3
        x0, y0 = int(cx) - w, int(cy) - w
        sub = (np.mgrid[0:(2 * w + 1) * s, 0:(2 * w + 1) * s] + 0.5) / s
        d2 = (sub[1] + x0 - 0.5 - cx) ** 2 + (sub[0] + y0 - 0.5 - cy) ** 2
        chord = 2 * mu * np.sqrt(np.maximum(R * R - d2, 0)) * 6
        A[y0:y0 + 2 * w + 1, x0:x0 + 2 * w + 1] += chord.reshape(2 * w + 1, s, 2 * w + 1, s).mean(axis=(1, 3))
    import cv2
    I = cv2.GaussianBlur(np.exp(-A), (0, 0), 0.8)
    I = rng.poisson(I * 2000) / 2000
    L = np.log(np.maximum(I, 1e-5))
    lo, hi = np.percentile(L, [0.1, 99.9])
    g = np.round(8 + 242 * np.clip((L - lo) / (hi - lo), 0, 1))
    return -np.log(g / 255), centres


def test_sigma_covers_the_shift_a_display_image_gives_a_shadow_on_a_slope():
    rng = np.random.default_rng(5)
    frames, truth = [], []
    for _ in range(2):
        a, c = _display_frame(rng)
        frames.append(a)
        truth.append(c)
    a = frames[0]
    opt = DetectOptions(diameter_px=(12.0, 20.0), blur_px=0.8, pixel_noise=noise_pixel(a),
                        noise_kappa=noise_correlation(a))
    found = [with_background(f, detect_frame(f, opt), opt) for f in frames]
    covered, gain = with_gain_sigma(found, opt)
    assert gain.significant and gain.eta > 0.5

    def pulls(res):
        p = []
        for blobs, cs in zip(res, truth):
            for b in blobs:
                d = [np.hypot(b.x - x, b.y - y) for x, y in cs]
                j = int(np.argmin(d))
                if d[j] < 3 and not b.flags:
                    p += [(b.x - cs[j][0]) / b.sigma, (b.y - cs[j][1]) / b.sigma]
        return np.array(p)

    before, after = pulls(found), pulls(covered)
    assert len(after) >= 2 * 40
    # the noise alone says too little (pull std 1.9); with the gain's term
    # sigma covers the shift (0.7: eta from the contrast is the deep core's,
    # up to twice the gain the centroid sees; an upper bound)
    assert np.std(before) > 1.4
    assert 0.6 < np.std(after) < 1.3, (np.std(before), np.std(after))


def test_a_display_images_response_is_measured_and_its_shadows_then_read_true():
    """On a log display stored as transmission (T linear in the line
    integral) lambda = 1 makes the shadows add; measured from the shadows'
    central chords against their background, and a frame measured through
    it has its centroids where the spheres are (in attenuation, each is
    pulled up the background's slope)."""
    rng = np.random.default_rng(5)
    frames, truth = zip(*[_display_frame(rng) for _ in range(2)])
    opt = DetectOptions(diameter_px=(12.0, 20.0), blur_px=0.8, pixel_noise=noise_pixel(frames[0]),
                        noise_kappa=noise_correlation(frames[0]))
    found = [with_background(f, detect_frame(f, opt), opt) for f in frames]
    lam = response_lambda(found)
    assert 0.8 < lam < 1.2, lam

    def errors(res):
        e = []
        for blobs, cs in zip(res, truth):
            for b in blobs:
                d = [np.hypot(b.x - x, b.y - y) for x, y in cs]
                if min(d) < 3:
                    e.append(min(d))
        return np.array(e)

    lin = [linearised(f, lam) for f in frames]
    opt_l = replace(opt, pixel_noise=noise_pixel(lin[0]), noise_kappa=noise_correlation(lin[0]))
    before, after = errors(found), errors([detect_frame(f, opt_l) for f in lin])
    assert len(after) >= len(before) >= 2 * 40
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    assert rms(after) < 0.5 * rms(before), (rms(before), rms(after))   # 0.082 -> 0.027 px
    # in attenuation the same shadows read no gain: nothing to linearise
    again = [with_background(f, detect_frame(f, opt_l), opt_l) for f in lin]
    assert response_lambda(again) == 0.0


def test_no_response_is_claimed_where_the_shadows_add_or_the_beam_hardens():
    rng = np.random.default_rng(1)
    assert response_lambda(_blobs(rng, 0.0)) == 0.0
    assert response_lambda(_blobs(rng, -1.0)) == 0.0      # hardened behind thicker material
    assert response_lambda(_blobs(rng, 2.0, n_frames=1, n=10)) == 0.0   # too few to tell
    # a gain no lambda within reach takes away is no display's curve either
    # (a steep slope over a background that hardly varies)
    flat = [[replace(b, bg=b.bg / 20, mu_px=b.mu_px * np.exp(19 * b.bg / 20)) for b in res] for res in _blobs(rng, 0.0)]
    assert measure_gain(flat).significant and response_lambda(flat) == 0.0
