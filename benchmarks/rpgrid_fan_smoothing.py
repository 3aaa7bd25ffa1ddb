"""rp-grid (issue 5): where does the smoothing of the Radon derivative put theta?

An experiment, not yet a change of ``conecal rp-grid``. Each view's table
is smoothed along s, i.e. over the planes of that view's own pencil (planes
through its source turning about an axis through it); the two views of one
plane have different pencils, and on noiseless data that alone biases the
weak tilt theta. Smoothing along each pair's fan of planes instead (the
planes through both sources, turning about the baseline) averages the same
planes in both views, with the same weights.

On a noiseless plain scan (tables made at the true geometry, all five
parameters refined from the truth, unweighted residuals) this prints the
errors for: the tables' own smoothing of 3 px (rp-grid's default) and of
1 px, and 0.7-1 px tables with a Gaussian along a denser fan (144 planes per
pair, sigma in planes of the fan).

    python benchmarks/rpgrid_fan_smoothing.py            # seed 116, ~4 min on 2 cores
    python benchmarks/rpgrid_fan_smoothing.py --seed 108 --photons 1e5
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from conecal.consistency import rpgrid
from conecal.consistency.misalignment import NAMES, misaligned
from conecal.scan import load_scan
from conecal.simulate import write_scan
from conecal.simulate.scenarios import circular_scan

SETTINGS = [(3.0, 48, 0.0), (1.0, 48, 0.0), (1.0, 144, 1.0), (1.0, 144, 1.5), (0.7, 144, 1.2)]


def fan_matrix(prob: rpgrid.RPProblem, sigma_planes: float):
    """Kept planes and a sparse Gaussian along each pair's fan (the
    candidates are contiguous per pair and in order of their angle about
    the baseline; dropped planes leave gaps that the weights skip)."""
    idx = np.flatnonzero(prob.keep)
    pair = prob.vi[idx].astype(np.int64) * 100000 + prob.vj[idx]
    cuts = np.flatnonzero(np.diff(pair)) + 1
    rows, cols, vals = [], [], []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(idx)]):
        pos = idx[lo:hi]
        for a in range(lo, hi):
            d = (pos - idx[a]).astype(float)
            w = np.exp(-0.5 * (d / sigma_planes) ** 2) if sigma_planes > 0 else (d == 0).astype(float)
            ok = np.abs(d) <= 3 * max(sigma_planes, 0.1)
            rows += [a] * int(ok.sum())
            cols += list(np.arange(lo, hi)[ok])
            vals += list(w[ok] / w[ok].sum())
    return idx, sparse.csr_matrix((vals, (rows, cols)), shape=(len(idx), len(idx)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=116)
    ap.add_argument("--photons", type=float, default=0.0, help="0: noiseless")
    args = ap.parse_args(argv)
    sc = circular_scan(args.seed, random_misalignment=True)
    sc.photons = args.photons
    truth = np.array([sc.truth_extra["misalignment"][n] for n in NAMES])
    with tempfile.TemporaryDirectory() as tmp:
        scan = load_scan(write_scan(sc, Path(tmp) / "plain", seed=args.seed))
        axis = rpgrid.check_scan(scan)
        nominal, transforms = scan.nominal_geometry(), scan.nominal_transforms()
        images = [scan.stack.read(int(k)) for k in scan.log.frame]
    print(f"plain scan {args.seed}, photons {args.photons:g}; truth " +
          "  ".join(f"{n}={v:+.3f}" for n, v in zip(NAMES, truth)))
    for smooth, per_pair, sigma in SETTINGS:
        t = time.perf_counter()
        opt = rpgrid.RPOptions(smooth_px=smooth, planes_per_pair=per_pair, noise_weights=False)
        tab = rpgrid.build_tables(iter(images), len(images), misaligned(nominal, truth), opt)
        prob = rpgrid.RPProblem(nominal, transforms, tab, axis, opt)
        prob.select(truth)
        idx, W = fan_matrix(prob, sigma)
        f_true = rpgrid._frame(misaligned(nominal, truth), tab.ref)
        Fi, Fj = prob._grangeat(f_true, prob.mi[idx]), prob._grangeat(f_true, prob.mj[idx])

        def residuals(p):
            f = rpgrid._frame(misaligned(nominal, p), tab.ref)
            return W @ (prob._values(f, prob.vi[idx], prob.mi[idx], F=Fi) - prob._values(f, prob.vj[idx], prob.mj[idx], F=Fj))

        fit = least_squares(residuals, truth, x_scale=np.array([1, 1, 0.1, 0.5, 0.5]), diff_step=1e-4, max_nfev=40)
        err = fit.x - truth
        print(f"tables {smooth:.1f} px, {per_pair:3d} planes/pair, along the fan sigma {sigma:.1f} planes "
              f"({len(idx)} planes): error " + "  ".join(f"{n}={e:+.3f}" for n, e in zip(NAMES, err)) +
              f"   ({time.perf_counter() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
