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
from conecal.scan import load_scan
from conecal.simulate import linear_raster, robot_helix, rotation_scan, write_scan
from conecal.simulate.clutter import add_clutter


def score(scan_dir: Path, fov_radius: float | None = None) -> dict:
    s = load_scan(scan_dir)
    doc = detect_scan(s, options_for_scan(s), workers=os.cpu_count() or 2)
    truth = json.loads((scan_dir / "truth.json").read_text())
    rows, cols = s.stack.shape
    errs, sig, visible, found, false, flagged = [], [], 0, 0, 0, 0
    for fr, tf in zip(doc["frames"], truth["frames"]):
        P = np.array([m["centroid"] for m in tf["markers"]])
        D = np.array([m["diameter_px"] for m in tf["markers"]])
        inside = np.array([m["inside"] for m in tf["markers"]])
        # fully visible: inside the detector (and field of view), no other shadow within reach
        dd = np.hypot(P[:, None, 0] - P[None, :, 0], P[:, None, 1] - P[None, :, 1]) + np.eye(len(P)) * 1e9
        alone = np.all(dd > (D[:, None] + D[None, :]) / 2 * 1.15 + 6, axis=1)
        vis = inside & alone
        if fov_radius is not None:
            vis &= np.hypot(P[:, 0] - (cols - 1) / 2, P[:, 1] - (rows - 1) / 2) + D / 2 + 8 < fov_radius
        hit = set()
        for m in fr["markers"]:
            d = np.hypot(P[:, 0] - m["x"], P[:, 1] - m["y"])
            j = int(d.argmin())
            if d[j] > D[j] / 4:
                false += 1
                continue
            hit.add(j)
            if m["flags"]:
                flagged += 1
            elif vis[j]:
                errs.append(d[j])
                sig.append(m["sigma"])
        visible += int(vis.sum())
        found += sum(1 for j in np.flatnonzero(vis) if j in hit)
    errs, sig = np.array(errs), np.array(sig)
    return {"n": len(errs), "rms_px": float(np.sqrt(np.mean(errs**2))), "max_px": float(errs.max()),
            "pull": float(np.sqrt(np.mean(errs**2) / np.mean(sig**2))), "visible": visible, "found": found,
            "false": false, "flagged": flagged,
            "diam_px": (float(np.min([m["diameter_px"] for f in truth["frames"] for m in f["markers"]])),
                        float(np.max([m["diameter_px"] for f in truth["frames"] for m in f["markers"]])))}


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


def accuracy(work: Path, quick: bool) -> list[tuple[str, dict]]:
    rows = []
    for k, (name, fov, sc) in enumerate(scenes(quick)):
        d = write_scan(sc, work / f"acc{k}", seed=k, overwrite=True)
        rows.append((name, score(d, fov)))
    return rows


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
        print("| scene | diameters px | markers | RMS px | max px | pull | found/visible | false | flagged |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, r in accuracy(work, args.quick):
            print(f"| {name} | {r['diam_px'][0]:.0f}-{r['diam_px'][1]:.0f} | {r['n']} | {r['rms_px']:.4f} | "
                  f"{r['max_px']:.3f} | {r['pull']:.2f} | {r['found']}/{r['visible']} | {r['false']} | {r['flagged']} |")
    if not args.skip_speed:
        r = speed(work, args.quick)
        print(f"\nspeed ({r['frames']} frames {r['shape']}, {r['cores']} cores): bare tifffile read {r['bare_read_s']:.2f} s, "
              f"detect {r['detect_s']:.2f} s, ratio {r['ratio']:.2f}x (target <= 3x)")


if __name__ == "__main__":
    main()
