"""detect: accuracy against the simulator's exact centres, and speed against a bare read.

Run:  python benchmarks/bench_detect.py [--quick] [--workdir DIR]

Accuracy: per scene and seed, the error of every unflagged marker against
the exact attenuation centroid of its sphere shadow (truth.json), the pull
(RMS error / RMS reported sigma; 1 means honest uncertainties), fully
visible markers found, false detections (nothing within a quarter diameter
of a true marker). Speed: wall time of `detect` on a 1024x1024 stack of
>= 200 frames next to a bare page-by-page tifffile read of the same file,
both from the page cache, on this machine's cores.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from conecal.detect import detect_scan, options_for_scan
from conecal.detect.evaluate import Score, score_markers
from conecal.scan import load_scan
from conecal.simulate import linear_raster, robot_helix, rotation_scan, write_scan
from conecal.simulate.clutter import add_clutter


def score(scan_dir: Path, fov_radius: float | None = None):
    """Detect on a simulated scan and score it against its truth.json."""
    s = load_scan(scan_dir)
    doc = detect_scan(s, options_for_scan(s), workers=os.cpu_count() or 2)
    truth = json.loads((scan_dir / "truth.json").read_text())
    diam = [m["diameter_px"] for f in truth["frames"] for m in f["markers"]]
    return score_markers(doc, truth, fov_radius=fov_radius, shape=s.stack.shape), (min(diam), max(diam))

def scenes(quick: bool):
    seeds = [0, 1] if quick else [0, 1, 2]
    for seed in seeds:
        # 2 mm spheres at 40-100 px on a sloped background, 3e4 photons
        yield "sphere 2 mm, M=5 (50 px)", None, linear_raster(seed, rows=768, cols=768, sod=100, sdd=500)
        yield "sphere 2 mm, M=9 (90 px)", None, linear_raster(seed, rows=1024, cols=1024, sod=100, sdd=900,
                                                            steps=(4.0, 4.0, 6.0))
        yield "helix holder 0.8 mm (12 px)", None, robot_helix(seed, n_frames=24 if quick else 40)
        sc = rotation_scan(seed, rows=384, cols=384, n_frames=12, diameters=(2.0, 1.2))
        add_clutter(sc, np.random.default_rng(seed))
        yield "clutter: rod, plate, bone, faint, lag, FOV, JPEG", sc.fov_radius, sc


def accuracy(work: Path, quick: bool) -> dict:
    """Per scene, all seeds pooled: (Score, diameter range px, seeds)."""
    pooled: dict = {}
    for k, (name, fov, sc) in enumerate(scenes(quick)):
        d = write_scan(sc, work / f"acc{k}", seed=k, overwrite=True)
        sc_, diam = score(d, fov)
        if name not in pooled:
            pooled[name] = [sc_, list(diam), 1]
        else:
            p = pooled[name]
            p[0] = Score(np.concatenate([p[0].errors, sc_.errors]), np.concatenate([p[0].sigmas, sc_.sigmas]),
                         p[0].found + sc_.found, p[0].visible + sc_.visible, p[0].false + sc_.false,
                         p[0].flagged + sc_.flagged)
            p[1] = [min(p[1][0], diam[0]), max(p[1][1], diam[1])]
            p[2] += 1
    return pooled

def speed(work: Path, quick: bool) -> dict:
    n = (4, 4, 4) if quick else (6, 6, 6)       # 64 or 216 frames
    sc = linear_raster(7, rows=1024, cols=1024, sod=100, sdd=500, counts=n, steps=(2.0, 2.0, 3.0))
    d = write_scan(sc, work / "speed", seed=7, overwrite=True)
    path = d / "projections.tif"
    s = load_scan(d)
    opt = options_for_scan(s)

    def bare():
        with tifffile.TiffFile(path) as tf:
            for page in tf.pages:
                page.asarray()

    bare()  # warm the page cache for both
    t_bare, t_det = [], []
    for _ in range(5):
        t0 = time.perf_counter()
        bare()
        t_bare.append(time.perf_counter() - t0)
        s = load_scan(d)
        t0 = time.perf_counter()
        detect_scan(s, opt, workers=os.cpu_count() or 2)
        t_det.append(time.perf_counter() - t0)
    return {"frames": int(np.prod(n)), "shape": "1024x1024", "bare_read_s": min(t_bare), "detect_s": min(t_det),
            "ratio": min(t_det) / min(t_bare), "cores": os.cpu_count()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer seeds and frames")
    ap.add_argument("--workdir", default=None, help="where to write the simulated scans (default: a temp dir)")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="conecal-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    if not args.skip_accuracy:
        print("| scene | seeds | diameters px | markers | RMS px | max px | pull | found/visible | false | flagged |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for name, (r, diam, seeds) in accuracy(work, args.quick).items():
            print(f"| {name} | {seeds} | {diam[0]:.0f}-{diam[1]:.0f} | {r.errors.size} | {r.rms:.4f} | "
                  f"{r.errors.max():.3f} | {r.pull:.2f} | {r.found}/{r.visible} | {r.false} | {r.flagged} |")
    if not args.skip_speed:
        r = speed(work, args.quick)
        print(f"\nspeed ({r['frames']} frames {r['shape']}, {r['cores']} cores): bare tifffile read {r['bare_read_s']:.2f} s, "
              f"detect {r['detect_s']:.2f} s, ratio {r['ratio']:.2f}x (target <= 3x)")


if __name__ == "__main__":
    main()
