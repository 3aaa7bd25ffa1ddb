"""rp-grid (issue 5): how much of an estimate's error is bias and how much
noise, and does the reported sigma say so?

One simulated circular scan (fixed misalignment) is written again with
several noise seeds (1e5 photons). For each draw and each setting the
tables are made at the true geometry (with their noise tables), the five
parameters refined from the truth (``rpgrid.refine``) and sigma taken as
rp-grid reports it (``rpgrid.finish``). Prints each draw's errors and
sigmas, then per setting the mean and spread of the errors against the
mean reported sigma.

    python benchmarks/rpgrid_noise_draws.py                       # axial scan 102, 5 draws, ~8 min
    python benchmarks/rpgrid_noise_draws.py --draws 4 --fourth-order-fan
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from conecal.consistency import rpgrid
from conecal.geometry.misalignment import NAMES, misaligned
from conecal.scan import load_scan
from conecal.simulate import write_scan
from conecal.simulate.scenarios import circular_scan

# name: RPOptions
SETTINGS = {
    "default (3 px, order 2, 48 planes/pair)": {},
    "3 px order 4, fan 0.75 deg, 144 planes/pair": {"kernel_order": 4, "fan_sigma_deg": 0.75, "planes_per_pair": 144},
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", choices=["plain", "holder", "axial", "transaxial"], default="axial")
    ap.add_argument("--seed", type=int, default=102, help="the scan's seed (misalignment; its own noise is draw 0)")
    ap.add_argument("--draws", type=int, default=5)
    ap.add_argument("--fourth-order-fan", action="store_true", help="only the fourth-order kernel with the fan")
    args = ap.parse_args(argv)
    sc = circular_scan(args.seed, random_misalignment=True, dense_holder=args.kind == "holder",
                       truncation=args.kind if args.kind in ("axial", "transaxial") else None)
    truth = np.array([sc.truth_extra["misalignment"][n] for n in NAMES])
    settings = {k: v for k, v in SETTINGS.items() if not args.fourth_order_fan or v}
    errors = {k: [] for k in settings}
    sigmas = {k: [] for k in settings}
    # the benchmark's own draw first (write_scan's seed is the noise seed)
    for noise_seed in [args.seed] + list(range(1, args.draws)):
        with tempfile.TemporaryDirectory() as tmp:
            scan = load_scan(write_scan(sc, Path(tmp) / "scan", seed=noise_seed))
            axis = rpgrid.check_scan(scan)
            nominal, transforms = scan.nominal_geometry(), scan.nominal_transforms()
            images = [scan.stack.read(int(k)) for k in scan.log.frame]
        for name, kw in settings.items():
            t = time.perf_counter()
            opt = rpgrid.RPOptions(**kw)
            tab = rpgrid.build_tables(iter(images), len(images), misaligned(nominal, truth), opt, noise=True)
            prob = rpgrid.RPProblem(nominal, transforms, tab, axis, opt)
            fit, scale = rpgrid.refine(prob, opt, truth)
            res = rpgrid.finish(prob, opt, fit, scale, truth, 0, {})
            err = fit.x - truth
            errors[name].append(err)
            sigmas[name].append(res.sigma)
            print(f"{name:45s} noise {noise_seed:3d}: err " + " ".join(f"{e:+.3f}" for e in err) +
                  "  sigma " + " ".join(f"{e:.3f}" for e in res.sigma) + f"  ({time.perf_counter() - t:.0f} s)",
                  flush=True)
    print(f"\n{args.kind} scan {args.seed}, {args.draws} noise draws, refined from the truth")
    for name in settings:
        e, s = np.array(errors[name]), np.array(sigmas[name])
        print(f"{name:45s} " + "  ".join(f"{n}={m:+.3f}±{d:.3f} (σ {q:.3f})" for n, m, d, q in
                                         zip(NAMES, e.mean(0), e.std(0, ddof=min(1, len(e) - 1)), s.mean(0))))


if __name__ == "__main__":
    main()
