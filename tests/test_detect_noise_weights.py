"""The noise correlation factor of a centre's own weights: measured rho, then the variance it predicts."""

import cv2
import numpy as np

from conecal.detect.kernels import chord_patch
from conecal.detect.noise import noise_autocorrelation, noise_correlation, weights_kappa


def _blurred_noise(seed: int, s: float, n: int = 512) -> np.ndarray:
    w = np.random.default_rng(seed).normal(size=(n, n)).astype(np.float32)
    b = cv2.GaussianBlur(w, (0, 0), s)
    return b / b.std()


def test_white_noise_reads_one_and_the_frames_kappa_is_never_exceeded():
    a = np.random.default_rng(0).normal(size=(512, 512)).astype(np.float32)
    rho = noise_autocorrelation(a)
    c = len(rho) // 2
    assert abs(rho[c][c + 1]) < 0.03 and abs(rho[c + 1][c]) < 0.03 and rho[c][c] == 1.0
    for kind in ("model", "centroid"):
        assert weights_kappa(1.0, rho, kind, 3.0, 1.0) == 1.0
        assert weights_kappa(5.0, rho, kind, 3.0, 1.0) < 1.3
    # unmeasured: the frame's factor
    assert weights_kappa(7.0, (), "model", 3.0, 1.0) == 7.0


def test_the_factor_predicts_the_scatter_of_a_small_shadows_fit_weights_in_blurred_noise():
    # noise blurred over ~2 px (a scintillator, JPEG's smoothing): kappa ~ 4 pi s^2
    # for slowly varying weights, far less for a 2.5 px shadow's rim lobes
    s, R = 2.0, 2.5
    rho = noise_autocorrelation(_blurred_noise(1, s))
    kappa = noise_correlation(_blurred_noise(1, s))
    predicted = weights_kappa(kappa, rho, "model", R, 1.0)
    n = 41
    J = chord_patch(np.array([[20.3, 20.3, R, 1.0]]), n, n, 3, True)[..., 0].astype(np.float64)
    w = cv2.GaussianBlur(J, (0, 0), 1.0)
    sums = []
    for seed in range(2, 6):
        img = _blurred_noise(seed, s).astype(np.float64)
        # w . noise at every place of the frame
        sums.append(cv2.filter2D(img, -1, w, borderType=cv2.BORDER_CONSTANT)[n:-n, n:-n].ravel())
    measured = np.var(np.concatenate(sums)) / float((w * w).sum())
    assert 5 < kappa
    assert predicted < 0.6 * kappa
    assert abs(predicted / measured - 1) < 0.2, (predicted, measured, kappa)
