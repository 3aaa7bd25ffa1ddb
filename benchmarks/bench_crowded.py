"""detect on touching/overlapping shadows and beside plate edges (issue 32).

Scenes rendered here, apart from conecal's model (5x5 samples per pixel,
exact chord lengths, Gaussian blur, noise added after the blur):

- pairs: equal spheres whose shadows are +0.5 .. -0.5 diameters apart
  (0 touching, -0.5 overlapping by half a diameter), random directions;
- plate: one sphere with a straight step (0.1-0.5 attenuation) 0-16 px
  beside its shadow.

Each frame is measured twice, with the crowded stage (default) and with
every shadow measured alone (``joint_overlaps=False``). Printed per class:
spheres found, RMS error against the true centre, pull (RMS error/sigma),
flags and time per frame.

    python benchmarks/bench_crowded.py [--trials 10]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from conecal.detect import DetectOptions, detect_frame  # noqa: E402
from conecal.detect.noise import noise_pixel  # noqa: E402

SS = 5


def draw(shape, spheres, blur):
    """Attenuation of spheres (x, y, R px, mu per px) sampled SS x SS per pixel, blurred."""
    h, w = shape
    img = np.zeros((h, w))
    o = (np.arange(SS) + 0.5) / SS - 0.5
    for x, y, R, mu in spheres:
        c0, c1 = int(max(x - R - 2, 0)), int(min(x + R + 3, w))
        q0, q1 = int(max(y - R - 2, 0)), int(min(y + R + 3, h))
        yy = np.arange(q0, q1)[:, None, None, None] + o[None, :, None, None]
        xx = np.arange(c0, c1)[None, None, :, None] + o[None, None, None, :]
        chord = 2 * mu * np.sqrt(np.maximum(R * R - (xx - x) ** 2 - (yy - y) ** 2, 0))
        img[q0:q1, c0:c1] += chord.mean(axis=(1, 3))
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur)


def measure(img, truth, opt):
    t0 = time.perf_counter()
    blobs = detect_frame(img, opt)
    dt = time.perf_counter() - t0
    rows = []
    for s in truth:
        d = [np.hypot(b.x - s[0], b.y - s[1]) for b in blobs]
        if d and min(d) < 0.5 * s[2]:
            b = blobs[int(np.argmin(d))]
            rows.append((b.x - s[0], b.y - s[1], b.sigma, bool(b.flags)))
    false = sum(1 for b in blobs if min(np.hypot(b.x - s[0], b.y - s[1]) for s in truth) > 0.5 * truth[0][2])
    return rows, false, dt


def summary(label, rows, n, false, t):
    r = np.array([x[:3] for x in rows]) if rows else np.zeros((0, 3))
    rms = np.sqrt(np.mean(r[:, :2] ** 2)) if len(r) else float("nan")
    pull = np.sqrt(np.mean((r[:, :2] / r[:, 2:3]) ** 2)) if len(r) else float("nan")
    flagged = sum(x[3] for x in rows)
    print(f"| {label} | {len(rows)}/{n} | {rms:.3f} | {pull:.2f} | {flagged} | {false} | {t:.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=10)
    a = ap.parse_args()
    rng = np.random.default_rng(2026)
    print("| scene | mode | found | RMS px | pull | flagged | false | s/frame |\n|---|---|---|---|---|---|---|---|")
    R, mu, blur, sd = 6.0, 0.05, 1.0, 0.004
    for gap in (0.5, 0.0, -0.25, -0.5):
        acc = {True: [[], 0, 0, 0.0], False: [[], 0, 0, 0.0]}
        for _ in range(a.trials):
            sph = []
            for cx in (60, 160, 260):
                for cy in (60, 160, 260):
                    d, ang = 2 * R * (1 + gap), rng.uniform(0, np.pi)
                    x0, y0 = cx + rng.uniform(-1, 1), cy + rng.uniform(-1, 1)
                    Ri = R * rng.uniform(0.9, 1.1)
                    sph += [[x0 - d / 2 * np.cos(ang), y0 - d / 2 * np.sin(ang), Ri, mu],
                            [x0 + d / 2 * np.cos(ang), y0 + d / 2 * np.sin(ang), Ri, mu]]
            img = (draw((320, 320), sph, blur) + 0.1 + rng.normal(0, sd, (320, 320))).astype(np.float32)
            for joint in (True, False):
                opt = DetectOptions(diameter_px=(7.2, 19.2), blur_px=blur, pixel_noise=noise_pixel(img),
                                    joint_overlaps=joint)
                rows, false, dt = measure(img, sph, opt)
                acc[joint][0] += rows
                acc[joint][1] += len(sph)
                acc[joint][2] += false
                acc[joint][3] += dt / a.trials
        for joint in (True, False):
            rows, n, false, t = acc[joint]
            summary(f"pairs gap {gap:+.2f} d | {'crowded' if joint else 'alone'}", rows, n, false, t)
    R = 8.0
    for dist in (0, 2, 4, 8, 16):
        acc = {True: [[], 0, 0, 0.0], False: [[], 0, 0, 0.0]}
        for _ in range(a.trials):
            for step in (0.1, 0.3, 0.5):
                x0, y0 = 100.3 + rng.uniform(-0.5, 0.5), 100.6 + rng.uniform(-0.5, 0.5)
                bg = np.full((200, 200), 0.1, np.float32)
                bg[:, int(x0 + R + dist):] += step
                img = cv2.GaussianBlur(bg, (0, 0), blur) + draw((200, 200), [[x0, y0, R, mu]], blur)
                img = (img + rng.normal(0, sd, img.shape)).astype(np.float32)
                for joint in (True, False):
                    opt = DetectOptions(diameter_px=(9.6, 25.6), blur_px=blur, pixel_noise=noise_pixel(img),
                                        joint_overlaps=joint)
                    rows, false, dt = measure(img, [[x0, y0, R, mu]], opt)
                    acc[joint][0] += rows
                    acc[joint][1] += 1
                    acc[joint][2] += false
                    acc[joint][3] += dt / a.trials / 3
        for joint in (True, False):
            rows, n, false, t = acc[joint]
            summary(f"plate edge {dist} px | {'crowded' if joint else 'alone'}", rows, n, false, t)


if __name__ == "__main__":
    main()
