"""rp-grid (issue 5): where does the smoothing of the Radon derivative put theta?

Each view's table is smoothed along s, i.e. over the planes of that view's
own pencil (planes through its source turning about an axis through it);
the two views of one plane have different pencils, and on noiseless data
that alone biases the weak tilt theta. Smoothing along each pair's fan of
planes instead (``RPOptions.fan_sigma_deg``: the planes through both
sources, turning about the baseline) averages the same planes in both
views, with the same weights.

On a noiseless plain scan (tables made at the true geometry, all five
parameters refined from the truth) this prints the errors for: the tables'
own smoothing of 3 px and of 1 px, and 0.7-1 px tables with a Gaussian
along each pair's fan (every plane of the fan, one per 0.5 deg; sigma in
degrees of the planes' angle about the baseline).

    python benchmarks/rpgrid_fan_smoothing.py            # seed 116, ~4 min on 2 cores
    python benchmarks/rpgrid_fan_smoothing.py --seed 108 --photons 1e5
    python benchmarks/rpgrid_fan_smoothing.py --kernel-orders   # 3-4 px tables, kernel order 2 and 4
    python benchmarks/rpgrid_fan_smoothing.py --kernel-orders --kind axial --seed 102
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from conecal.consistency import rpgrid
from conecal.geometry.misalignment import NAMES, misaligned
from conecal.scan import load_scan
from conecal.simulate import write_scan
from conecal.simulate.scenarios import circular_scan

# (table smoothing px, planes per pair, sigma along the fan in deg, derivative kernel order)
SETTINGS = [(3.0, 48, 0.0, 2), (1.0, 48, 0.0, 2), (1.0, 144, 0.5, 2), (1.0, 144, 0.75, 2), (0.7, 144, 0.6, 2)]
ORDER_SETTINGS = [(3.0, 48, 0.0, 2), (3.0, 48, 0.0, 4), (2.0, 48, 0.0, 4), (3.0, 144, 0.75, 4), (4.0, 48, 0.0, 4)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=116)
    ap.add_argument("--photons", type=float, default=0.0, help="0: noiseless")
    ap.add_argument("--kind", choices=["plain", "axial", "transaxial"], default="plain",
                    help="truncation of the simulated scan")
    ap.add_argument("--kernel-orders", action="store_true",
                    help="compare the derivative kernels of order 2 and 4 instead of the table widths")
    args = ap.parse_args(argv)
    sc = circular_scan(args.seed, random_misalignment=True, truncation=None if args.kind == "plain" else args.kind)
    sc.photons = args.photons
    truth = np.array([sc.truth_extra["misalignment"][n] for n in NAMES])
    with tempfile.TemporaryDirectory() as tmp:
        scan = load_scan(write_scan(sc, Path(tmp) / "plain", seed=args.seed))
        axis = rpgrid.check_scan(scan)
        nominal, transforms = scan.nominal_geometry(), scan.nominal_transforms()
        images = [scan.stack.read(int(k)) for k in scan.log.frame]
    print(f"{args.kind} scan {args.seed}, photons {args.photons:g}; truth " +
          "  ".join(f"{n}={v:+.3f}" for n, v in zip(NAMES, truth)))
    for smooth, per_pair, sigma, order in ORDER_SETTINGS if args.kernel_orders else SETTINGS:
        t = time.perf_counter()
        opt = rpgrid.RPOptions(smooth_px=smooth, kernel_order=order, planes_per_pair=per_pair, fan_sigma_deg=sigma,
                               noise_weights=False)
        tab = rpgrid.build_tables(iter(images), len(images), misaligned(nominal, truth), opt)
        prob = rpgrid.RPProblem(nominal, transforms, tab, axis, opt)
        prob.select(truth)
        fit = least_squares(prob.residuals, truth, jac=prob.jacobian, x_scale=np.array([1, 1, 0.1, 0.5, 0.5]),
                            max_nfev=40)
        err = fit.x - truth
        print(f"tables {smooth:.1f} px order {order}, {per_pair:3d} planes/pair, along the fan sigma {sigma:.2f} deg "
              f"({int(prob.keep.sum())} planes): error " + "  ".join(f"{n}={e:+.3f}" for n, e in zip(NAMES, err)) +
              f"   ({time.perf_counter() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
