"""diagnose, blind (issue 6): a confusion matrix over effects and seeds.

For every effect of the library, and for clean scans, simulate a scan with
the effect switched on at 3-10x the noise in its signature: a swept
rotation scan (varying speed, reversals; 72 frames, 5 spheres, 256², 3e4
photons per pixel) for the rotation, drift, timing, detector and image
effects, a 5x5x3 linear raster for axis scale and non-orthogonality. Take
the exact shadow centroids plus Gaussian noise of 0.02 px as the measured
markers (detect's accuracy on these spheres; this isolates diagnose;
``--detect`` runs ``conecal detect`` instead), fit (fit-rotation with the
true source/detector, or fit-linear), then diagnose, both levels, without
being told which effect. Prints the confusion matrix, the sizes found, the
rate of correct names (exactly the right effect and nothing else), false
claims on clean scans, and residual RMS after modelling against the noise
floor (marker centres and image pixels). Robot effects: a 7-joint arm
sweeping its elbow while it turns the helix holder in place, true poses
plus fit-pose's noise (``--detect``: the frames through detect and
fit-pose), diagnosed on the poses.

    python benchmarks/bench_diagnose.py            # every kind, 5 seeds each (rotation kinds ~40 s a scan,
                                                   # arm-frame kinds ~2.5 min: detect and fit-pose at 640²)
    python benchmarks/bench_diagnose.py --seeds 1 --only clean blur detector_lag
    python benchmarks/bench_diagnose.py --only clean_arm joint_offset robot_deflection arm_encoder_latency joint_backlash
    python benchmarks/bench_diagnose.py --only clean_arm_frames arm_blur arm_beam_hardening arm_detector_lag arm_scatter
    python benchmarks/bench_diagnose.py --lag-demo  # lag through detect, detect --lag, refit (~1 min)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from conecal.cli.main import cli

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diagnose_cases import EFFECTS, make, named, run_one  # noqa: E402


def lag_demo(seed: int = 210) -> int:
    """Detector lag through detect: the ghost pulls detect's centres back, the
    image level measures the lag, detect --lag removes it, the fit improves."""
    with tempfile.TemporaryDirectory() as tmp:
        kind, spec, _ = EFFECTS["detector_lag"]
        path = make(Path(tmp), "detector_lag", spec, seed, kind=kind, noise=None)
        d = run_one(path, kind)
        lag = d["image_level"]["effects"][0]["parameters"]["lag"] if d["image_level"]["effects"] else 0.0
        print(f"simulated lag 5 %; markers from conecal detect\n1. {d['verdict']}\n   fit RMS {d['rms_px_before']:.4f} px "
              f"(noise floor {d['noise_floor_px']:.4f} px)")
        out = CliRunner().invoke(cli, ["detect", str(path), "--lag", f"{lag:.4f}", "-o", str(path / "markers.json")])
        if out.exit_code != 0:
            raise RuntimeError(out.output)
        d2 = run_one(path, kind)
        print(f"2. after conecal detect --lag {lag:.4f}: {d2['verdict']}\n   fit RMS {d2['rms_px_before']:.4f} px "
              f"-> {d2['rms_px_after']:.4f} px after diagnose (noise floor {d2['noise_floor_px']:.4f} px)")
        print(f"fit RMS improved {d['rms_px_before'] / d2['rms_px_before']:.1f}x")
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--lag-demo", action="store_true", help="only the detector-lag round trip through detect --lag")
    ap.add_argument("--only", nargs="*", help="effects to run (default: all)")
    ap.add_argument("--detect", action="store_true",
                    help="markers from conecal detect on the frames (default: exact centroids + 0.02 px noise)")
    args = ap.parse_args(argv)
    if args.lag_demo:
        return lag_demo()
    which = {k: v for k, v in EFFECTS.items() if not args.only or k in args.only}
    confusion = {e: Counter() for e in which}
    n_eff = ok_eff = ok_or_ambiguous = n_clean = clean_claims = 0
    ratios, image_ratios, sizes = [], [], {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for name, (kind, spec, good) in which.items():
            for seed in range(args.seeds):
                d = run_one(make(Path(tmp), name, spec, 200 + seed, kind=kind,
                                 noise=None if args.detect else 0.02), kind)
                got = named(d)
                confusion[name]["+".join(got) if got else "none"] += 1
                if not good:
                    n_clean += 1
                    clean_claims += bool(got)
                else:
                    n_eff += 1
                    ok_eff += len(got) == 1 and got[0] in good
                    # the right effect among those diagnose said it cannot tell apart
                    said = set(d.get("ambiguous_with") or []) | set((d.get("image_level") or {}).get("ambiguous_with")
                                                                    or [])
                    ok_or_ambiguous += len(got) == 1 and (got[0] in good or bool(said & good))
                    if got:
                        e = d["effects"][0]
                        sizes.setdefault(name, []).append(
                            ", ".join(f"{k} {v:.4g} ± {e['sigma'][k]:.2g}" for k, v in e["parameters"].items()))
                ratios.append(d["rms_px_after"] / d["noise_floor_px"])
                if d.get("image_level") and "chi2_per_dof_after" in d["image_level"]:
                    image_ratios.append(np.sqrt(d["image_level"]["chi2_per_dof_after"]))
                print(f"{name:22s} seed {200 + seed}: {d['verdict']}  (RMS {d['rms_px_before']:.4f} -> "
                      f"{d['rms_px_after']:.4f} px, floor {d['noise_floor_px']:.4f})", flush=True)
    elapsed = time.perf_counter() - t0
    labels = sorted({lab for c in confusion.values() for lab in c})
    short = {lab: lab.replace("detector_distortion:", "distortion:")[:20] for lab in labels}
    print()
    print("confusion matrix (rows: simulated, columns: named by diagnose)")
    print(f"{'':22s}" + "".join(f"{short[lab]:>21s}" for lab in labels))
    for name, c in confusion.items():
        print(f"{name:22s}" + "".join(f"{c.get(lab, 0):21d}" for lab in labels))
    print()
    for name, v in sizes.items():
        print(f"sizes found, {name}: " + "; ".join(v))
    print()
    if n_eff:
        print(f"correct effect named (and nothing else claimed): {ok_eff}/{n_eff} ({100 * ok_eff / n_eff:.0f} %; "
              "source vs detector drift counted as one, they are reported as ambiguous with each other)")
        print(f"named, or reported not distinguishable from the one named: {ok_or_ambiguous}/{n_eff} "
              f"({100 * ok_or_ambiguous / n_eff:.0f} %)")
    if n_clean:
        print(f"effect claimed on clean scans: {clean_claims}/{n_clean} ({100 * clean_claims / n_clean:.0f} %)")
    print(f"marker residual RMS after modelling / noise floor: median {np.median(ratios):.3f}, max {np.max(ratios):.3f}")
    if image_ratios:
        print(f"image residual RMS after modelling / noise floor (sqrt chi2/dof): median {np.median(image_ratios):.3f}, "
              f"max {np.max(image_ratios):.3f}")
    print(f"{len(ratios)} scans in {elapsed:.0f} s ({elapsed / len(ratios):.1f} s per scan: simulate, fit, diagnose)")
    good = ((not n_eff or ok_eff >= 0.9 * n_eff) and clean_claims <= 0.05 * max(n_clean, 1)
            and np.max(ratios) <= 1.15 and (not image_ratios or np.max(image_ratios) <= 1.15))
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
