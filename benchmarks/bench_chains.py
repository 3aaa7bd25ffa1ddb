"""detect on rows of overlapping spheres seen edge-on, no sphere alone (issue 32).

A frame holds three rows of seven spheres (R 7.5 px, ±3 %), each row at
5-20° with its spheres 10-11.5 px apart (a third to a quarter of a diameter
overlapping), drawn with :func:`benchmarks.bench_two_sizes.frame`'s own
forms (not conecal's model), white noise 0.003 (SNR ≈ 100). The scene of
``tests/test_detect_chains.py``, over more seeds. Printed per seed: spheres
with a marker within 3.75 px (of 21), those off by more than max(0.3 px,
3 σ), the frame's time; then the totals.

    python benchmarks/bench_chains.py [--seeds 0 1 2 3 4 5 6 7 8 9]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_two_sizes import frame  # noqa: E402
from conecal.detect import DetectOptions, detect_frame  # noqa: E402
from conecal.detect.noise import noise_pixel  # noqa: E402


def scene(seed: int):
    """(frame, centres (21, 2) px) of three rows of seven, as described above."""
    rng = np.random.default_rng(seed)
    sph = []
    for y0 in (50.0, 130.0, 210.0):
        ang, step = np.radians(rng.uniform(5, 20)), rng.uniform(10.0, 11.5)
        for i in range(7):
            c = np.array([60.0, y0]) + i * step * np.array([np.cos(ang), np.sin(ang)]) + rng.normal(0, 0.2, 2)
            sph.append([*c, 7.5 * rng.uniform(0.97, 1.03), 0.02])
    return frame(sph, rng, shape=(260, 200), noise=0.003), np.array(sph)[:, :2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    args = ap.parse_args()
    total = [0, 0, 0.0]
    for seed in args.seeds:
        a, truth = scene(seed)
        t0 = time.perf_counter()
        blobs = detect_frame(a, DetectOptions(diameter_px=(9, 24), pixel_noise=noise_pixel(a), shadow_px=(15.0,)))
        dt = time.perf_counter() - t0
        found = off = 0
        for p in truth:
            b = min(blobs, key=lambda b: np.hypot(b.x - p[0], b.y - p[1]), default=None)
            e = np.inf if b is None else np.hypot(b.x - p[0], b.y - p[1])
            found += e < 3.75
            off += 0.3 < e < 3.75 and e > 3 * b.sigma
        total = [total[0] + found, total[1] + off, total[2] + dt]
        print(f"seed {seed}: found {found}/21, off > max(0.3 px, 3 sigma) {off}, {dt:.1f} s", flush=True)
    print(f"total: found {total[0]}/{21 * len(args.seeds)}, off {total[1]}, {total[2]:.1f} s")


if __name__ == "__main__":
    main()
