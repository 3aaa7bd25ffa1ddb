"""detect's time per frame against an earlier commit, side by side in one run
(issue 32's target: no more than 1.5x the time of the code the issue was
filed on, f5b6b02, on the raster and helix benchmarks).

Frames: the independent helix phantom (``helix_indep.py``: 50 spheres of
8.9-13.8 px, a plastic tube, 1024^2), drawn once. Each tree (this checkout,
and ``--reference`` extracted by ``git archive`` into a temporary folder)
runs in its own process, one BLAS thread, over the same frames with the
options both understand (shadow diameters, the frame's pixel noise and
noise correlation measured once by this checkout); the first frame is
detected once untimed (compilation). The trees run alternately,
``--repeats`` times each; the best run per tree counts.

    python benchmarks/bench_detect_speed.py [--reference f5b6b02] [--frames 8] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

_CHILD = r"""
import json, sys, time
import numpy as np
from dataclasses import replace
from conecal.detect import DetectOptions, detect_frame
try:
    from threadpoolctl import threadpool_limits
    threadpool_limits(1, "blas")
except ImportError:
    pass
d = np.load(sys.argv[1])
typed = DetectOptions(diameter_px=(float(d["nominal"][0]) * 0.9, float(d["nominal"][1]) * 1.1))
frames = [np.ascontiguousarray(f, np.float32) for f in d["frames"]]
opts = [replace(typed, pixel_noise=float(p), noise_kappa=float(k)) for p, k in zip(d["pixel_noise"], d["kappa"])]
detect_frame(frames[0], opts[0])
t, n = 0.0, 0
for f, o in zip(frames, opts):
    t0 = time.perf_counter()
    n += len(detect_frame(f, o))
    t += time.perf_counter() - t0
print(json.dumps({"s_per_frame": t / len(frames), "markers": n}))
"""


def _frames(path: Path, seed: int, n: int) -> None:
    sys.path.insert(0, str(HERE))
    import helix_indep as gen
    from conecal.detect.noise import noise_correlation, noise_pixel

    frames, truth = gen.make_frames(seed, n)
    r = [t["r_px"] for fr in truth for t in fr]
    np.savez(path, frames=np.array(frames, np.float32), nominal=(2 * min(r), 2 * max(r)),
             pixel_noise=[noise_pixel(f) for f in frames], kappa=[noise_correlation(f) for f in frames])


def _run(tree: Path, data: Path) -> dict:
    import json

    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD, str(data)], env=env, check=True,
                         capture_output=True, text=True, cwd=tempfile.gettempdir())
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default="f5b6b02", help="the commit to compare with")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ref = tmp / "reference"
        ref.mkdir()
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", a.reference], check=True, capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(ref)], input=arch.stdout, check=True)
        data = tmp / "frames.npz"
        _frames(data, a.seed, a.frames)
        runs: dict[str, list] = {"reference": [], "this": []}
        for _ in range(a.repeats):
            for name, tree in (("reference", ref), ("this", ROOT)):
                runs[name].append(_run(tree, data))
        print(f"helix seed {a.seed}, {a.frames} frames 1024^2, one process, one BLAS thread; best of {a.repeats}")
        print("| code | s/frame (each run) | markers |")
        print("|---|---|---|")
        best = {}
        for name, rs in runs.items():
            best[name] = min(r["s_per_frame"] for r in rs)
            label = a.reference if name == "reference" else "this checkout"
            each = " ".join(f"{r['s_per_frame']:.2f}" for r in rs)
            print(f"| {label} | {best[name]:.2f} ({each}) | {rs[0]['markers']} |")
        print(f"\nratio this / {a.reference}: {best['this'] / best['reference']:.2f} (target <= 1.5)")


if __name__ == "__main__":
    main()
