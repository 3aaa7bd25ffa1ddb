"""diagnose, blind (issue 6): a confusion matrix over effects and seeds.

For each effect of the library that a rotation scan can show, and for
clean scans, simulate a swept rotation scan (varying speed, reversals) with
the effect switched on at 3-10x the noise in its signature, take the exact
shadow centroids plus Gaussian noise of 0.02 px as the measured markers
(detect's accuracy on these spheres; this isolates diagnose), fit-rotation
with the true source/detector, then diagnose without being told which
effect. Prints the confusion matrix, the rate of correct names, false
claims on clean scans, and RMS after modelling against the noise floor.

    python benchmarks/bench_diagnose.py            # 5 seeds per effect, ~4 min on 2 cores
    python benchmarks/bench_diagnose.py --seeds 2
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from conecal.cli.main import cli
from conecal.effects import parse_effect
from conecal.simulate import write_scan
from conecal.simulate.scenarios import rotation_scan

EFFECTS = {
    "clean": None,
    "rotary_wobble": "rotary_wobble:amplitude=0.05",
    "focal_spot_drift": "focal_spot_drift:velocity=0.0005/0/0",
    "detector_drift": "detector_drift:velocity=0.001/0.0005/0",
    "encoder_latency": "encoder_latency:latency=0.02",
    "backlash": "backlash:axis=theta,amount=0.2",
}
# drifts of source and detector have near-identical signatures in one
# rotation scan: naming either, with the other reported as ambiguous, counts
SAME = {"focal_spot_drift": {"focal_spot_drift", "detector_drift"},
        "detector_drift": {"focal_spot_drift", "detector_drift"}}


def make(root: Path, name: str, spec, seed: int, noise: float = 0.02) -> Path:
    sc = rotation_scan(seed, rows=256, cols=256, pitch=0.4, n_frames=72, schedule="sweep")
    sc.photons = 0
    if spec:
        sc.apply_effects([parse_effect(spec)])
    path = write_scan(sc, root / f"{name}_{seed}", seed=seed)
    truth = json.loads((path / "truth.json").read_text())
    rng = np.random.default_rng(seed + 99)
    frames = [{"frame": fr["frame"], "markers": [
        {"id": m["id"], "x": m["centroid"][0] + rng.normal(0, noise), "y": m["centroid"][1] + rng.normal(0, noise),
         "sigma": noise, "flags": []} for m in fr["markers"] if m["inside"]]} for fr in truth["frames"]]
    (path / "markers.json").write_text(json.dumps({"format": "conecal-markers/1",
                                                   "detector": {"shape": [256, 256]}, "frames": frames}))
    (path / "geometry.json").write_text(json.dumps(truth["geometry"]))
    return path


def run_one(path: Path) -> dict:
    r = CliRunner()
    out = r.invoke(cli, ["fit-rotation", str(path), "--markers", str(path / "markers.json"),
                         "--geometry", str(path / "geometry.json"), "-o", str(path / "rot.json")])
    if out.exit_code != 0:
        raise RuntimeError(out.output)
    out = r.invoke(cli, ["diagnose", str(path / "rot.json"), str(path), "-o", str(path / "diag.json")])
    if out.exit_code != 0:
        raise RuntimeError(out.output)
    return json.loads((path / "diag.json").read_text())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    args = ap.parse_args(argv)
    confusion = {e: Counter() for e in EFFECTS}
    ok, n, ratios = 0, 0, []
    clean_claims = 0
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec in EFFECTS.items():
            for seed in range(args.seeds):
                d = run_one(make(Path(tmp), name, spec, 200 + seed))
                named = [e["effect"].split(":")[0] for e in d["effects"]]
                top = named[0] if named else "none"
                label = top if len(named) <= 1 else "+".join(named)
                confusion[name][label] += 1
                n += 1
                if name == "clean":
                    clean_claims += bool(named)
                    ok += not named
                else:
                    good = SAME.get(name, {name})
                    ok += top in good and len(named) == 1
                    ratios.append(d["rms_px_after"] / d["noise_floor_px"])
                print(f"{name:18s} seed {200 + seed}: {d['verdict']}  (RMS {d['rms_px_before']:.4f} -> "
                      f"{d['rms_px_after']:.4f} px, floor {d['noise_floor_px']:.4f})", flush=True)
    labels = sorted({lab for c in confusion.values() for lab in c})
    print()
    print("confusion matrix (rows: simulated, columns: named by diagnose)")
    print(f"{'':18s}" + "".join(f"{lab[:16]:>17s}" for lab in labels))
    for name, c in confusion.items():
        print(f"{name:18s}" + "".join(f"{c.get(lab, 0):17d}" for lab in labels))
    n_eff = n - args.seeds
    correct = ok - (args.seeds - clean_claims)
    print()
    print(f"correct effect named: {correct}/{n_eff} ({100 * correct / n_eff:.0f} %; source vs detector drift "
          f"counted as one, they are reported as ambiguous with each other)")
    print(f"effect claimed on clean scans: {clean_claims}/{args.seeds} ({100 * clean_claims / args.seeds:.0f} %)")
    print(f"residual RMS after modelling / noise floor: median {np.median(ratios):.3f}, max {np.max(ratios):.3f}")
    return 0 if correct >= 0.9 * n_eff and clean_claims <= 0.05 * args.seeds and np.max(ratios) <= 1.15 else 1


if __name__ == "__main__":
    sys.exit(main())
