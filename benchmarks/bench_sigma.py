"""Is detect's sigma honest when the noise is not white? (issue 32 item 3)

Separated sphere shadows (radius 4-8 px) rendered by ``bench_crowded.draw``
(apart from conecal's model: 5x5 samples per pixel, exact chords, Gaussian
blur), then one of these noise models:

- ``white``: Gaussian noise added after the blur (what conecal simulates);
- ``blurred``: the noise passes through the scintillator's blur too
  (correlated over ~2 px), same per-pixel sigma;
- ``counts``: intensities I0 exp(-a) with Poisson-like noise, the log
  taken afterwards (noise grows with attenuation);
- ``jpeg8``: the white scan windowed to 8 bits and JPEG-compressed at
  quality 75, mapped back to attenuation with the known window;
- ``jpeg8_fine``: the same with noise of 0.4 grey levels, under the display's
  step: flat background holds JPEG's 8 px blocks, a shadow's slopes the
  steps and ringing;
- ``counts_blurred``: ``counts`` whose noise then passes through a
  scintillator's blur (sigma 1 px): the noise grown in a shadow is as
  correlated as the background's.

Each is measured with the nominal shadow size exact and wrong by -25 % and
+25 % (the ``diameter_px`` range a user derives from a nominal
magnification). Printed per noise model, size and flag class: markers,
RMS error, and the pull std (error/sigma over both coordinates; honest is
0.8-1.25).

    python benchmarks/bench_sigma.py [--trials 8]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_crowded import draw  # noqa: E402

from conecal.detect import DetectOptions, detect_frame  # noqa: E402
from conecal.detect.noise import noise_pixel  # noqa: E402

try:
    from conecal.detect.noise import noise_correlation  # noqa: E402
except ImportError:          # before the correlation factor existed
    noise_correlation = None
try:
    from conecal.detect.noise import noise_autocorrelation  # noqa: E402
except ImportError:          # before the autocorrelation was measured
    noise_autocorrelation = None

SHAPE = (384, 384)


def scene(rng):
    sph = []
    for cx in np.linspace(48, 336, 4):
        for cy in np.linspace(48, 336, 4):
            R = rng.uniform(4, 8)
            sph.append([cx + rng.uniform(-8, 8), cy + rng.uniform(-8, 8), R, rng.uniform(0.03, 0.08)])
    return sph


def noisy(kind, clean, rng, sd=0.004, blur=1.0):
    if kind == "white":
        return clean + rng.normal(0, sd, clean.shape)
    if kind == "blurred":
        n = cv2.GaussianBlur(rng.normal(0, 1, clean.shape).astype(np.float32), (0, 0), blur)
        return clean + sd * n / n.std()
    if kind in ("counts", "counts_blurred"):
        i0 = 1.0 / sd**2 * np.exp(-0.1)      # sd at the background's level
        cts = i0 * np.exp(-clean)
        n = rng.normal(0, 1, clean.shape) * np.sqrt(cts)
        if kind == "counts_blurred":
            g = cv2.GaussianBlur(rng.normal(0, 1, clean.shape).astype(np.float32), (0, 0), blur)
            n = cv2.GaussianBlur(n.astype(np.float32), (0, 0), blur) / g.std()   # the same per-pixel sd
        return -np.log(np.maximum(cts + n, 1.0) / i0)
    if kind in ("jpeg8", "jpeg8_fine"):
        lo, hi = 0.08, 0.1 + 0.08 * 16
        grey = 2.5 if kind == "jpeg8" else 0.4
        a = clean + rng.normal(0, grey * (hi - lo) / 255, clean.shape)   # noise of 2.5 (0.4) grey levels
        q = np.clip(np.rint((a - lo) / (hi - lo) * 255), 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", q, [cv2.IMWRITE_JPEG_QUALITY, 75])
        return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE).astype(np.float64) / 255 * (hi - lo) + lo
    raise ValueError(kind)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--kinds", nargs="+", default=["white", "blurred", "counts", "counts_blurred", "jpeg8",
                                                    "jpeg8_fine"])
    a = ap.parse_args()
    print("| noise | nominal size | class | markers | RMS px | pull std | kappa | s/frame |")
    print("|---|---|---|---|---|---|---|---|")
    for kind in a.kinds:
        for scale in (1.0, 0.75, 1.25):
            rng = np.random.default_rng(7)
            acc = {}
            t = 0.0
            kap = []
            for _ in range(a.trials):
                sph = scene(rng)
                clean = draw(SHAPE, sph, 1.0).astype(np.float64) + 0.1
                img = noisy(kind, clean, rng).astype(np.float32)
                extra = {}
                if noise_correlation is not None:
                    extra["noise_kappa"] = noise_correlation(img)
                    kap.append(extra["noise_kappa"])
                if noise_autocorrelation is not None:
                    extra["noise_rho"] = noise_autocorrelation(img)
                opt = DetectOptions(diameter_px=(8 * scale * 0.9, 16 * scale * 1.1), blur_px=1.0,
                                    pixel_noise=noise_pixel(img), **extra)
                t0 = time.perf_counter()
                blobs = detect_frame(img, opt)
                t += time.perf_counter() - t0
                for s in sph:
                    d = [np.hypot(b.x - s[0], b.y - s[1]) for b in blobs]
                    if d and min(d) < 0.5 * s[2]:
                        b = blobs[int(np.argmin(d))]
                        cls = ",".join(sorted(b.flags)) or "unflagged"
                        acc.setdefault(cls, []).append((b.x - s[0], b.y - s[1], b.sigma))
            for cls, rows in sorted(acc.items()):
                r = np.array(rows)
                rms = np.sqrt(np.mean(r[:, :2] ** 2))
                pull = np.std(np.concatenate([r[:, 0] / r[:, 2], r[:, 1] / r[:, 2]]))
                k = f"{np.median(kap):.2f}" if kap else "-"
                print(f"| {kind} | {scale:.2f} | {cls} | {len(r)}/{16 * a.trials} | {rms:.4f} | {pull:.2f} | {k} "
                      f"| {t / a.trials:.3f} |", flush=True)


if __name__ == "__main__":
    main()
