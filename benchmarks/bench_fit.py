"""fit-linear and fit-rotation: honest sigmas, the paper's Table III, end to end, speed.

Run:  python benchmarks/bench_fit.py [--draws 200] [--quick]

1. Coverage and Cramer-Rao: exact shadow centroids plus Gaussian noise,
   many draws; per parameter the empirical std, the mean reported sigma,
   the coverage of the 1-sigma interval (target 68 +- 7 %) and std / CRB
   (the bound from the Jacobian at the truth; target <= 1.1).
2. The shape of Blumensath et al.'s Table III: error of source, detector,
   u and v against centre noise 0.1, 0.5, 1, 2 px, for their geometry
   (magnification 10, 2048^2 detector of 0.2 mm pixels, 3x3x2 raster).
3. End to end through simulated images and detect: reprojection RMS,
   rotary-axis direction and point errors.
4. Speed: the paper's randomised coordinate descent with bracketed line
   searches (35 iterations) against conecal's solver, same residuals and
   start; final cost and time of both.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from conecal.detect import detect_scan, options_for_scan
from conecal.fit.core import Parameter, solve
from conecal.fit.linear import LinearModel
from conecal.fit.markers import load_observations
from conecal.fit.rotation import AxisSpec, ChainModel
from conecal.fit.linear import fit_linear
from conecal.fit.rotation import fit_rotation
from conecal.geometry import ConeGeometry, rotvec_to_matrix
from conecal.jsonio import write_json
from conecal.scan import load_scan
from conecal.simulate import linear_raster, rotation_scan, write_scan

PAPER = dict(sod=100.0, sdd=1000.0, shape=(2048, 2048), pitch=0.2)


def paper_problem(rng, noise):
    """Blumensath et al.'s geometry: a 3x3x2 raster, M = 10; truth off nominal."""
    base = ConeGeometry.nominal(sod=PAPER["sod"], sdd=PAPER["sdd"], shape=PAPER["shape"],
                                pixel_pitch=(PAPER["pitch"],) * 2)
    grid = np.array([(x, y, z) for z in (-5.0, 5.0) for y in (-5.0, 0, 5.0) for x in (-5.0, 0, 5.0)])
    model = LinearModel(base, np.eye(3), ("x", "y", "z"), grid, 1.0)
    x_true = model.nominal_vector()
    x_true[:9] = [0.4, -0.3, 1.5, 2.0, -1.5, 4.0, 0.8, -0.6, 1.2]
    clean = model.predict(x_true)
    return model, x_true, clean


def fit_paper(model, xy, sigma):
    names = model.parameter_names()
    params = [Parameter(n, 0.0 if i < 9 else model.nominal_vector()[i], free=i < 9) for i, n in enumerate(names)]

    def r(x):
        return ((xy - model.predict(x)) / sigma).ravel()

    def j(x):
        return -(model.jacobian(x) / sigma).reshape(-1, len(names))

    return solve(params, r, j), r, j


def coverage_linear(draws, noise, rng):
    model, x_true, clean = paper_problem(rng, noise)
    est, sig = [], []
    for _ in range(draws):
        xy = clean + rng.normal(0, noise, clean.shape)
        res, _, _ = fit_paper(model, xy, noise)
        est.append(res.x[:9])
        sig.append(res.sigma[:9])
    J = -(model.jacobian(x_true) / noise).reshape(-1, len(x_true))[:, :9]
    crb = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    return model.parameter_names()[:9], np.array(est) - x_true[:9], np.array(sig), crb


def rotation_problem():
    g = ConeGeometry.nominal(sod=150, sdd=600, shape=(512, 512), pixel_pitch=(0.2, 0.2))
    d = rotvec_to_matrix(np.deg2rad([0.2, 0, -0.3])) @ np.array([0, 1.0, 0])
    true_axes = [AxisSpec("theta", "rotary", d, np.array([2.3, 0.0, 0.8]))]
    nominal_axes = [AxisSpec("theta", "rotary", np.array([0, 1.0, 0]), np.array([2.0, 0.0, 1.0]))]
    spheres = np.array([[0, 0, 0], [4.0, -4, 2], [-3, 2, 5], [5, 4, -3.0], [-5, 6, -2]])
    q = np.arange(0, 360, 5.0)[:, None]
    n = len(q)
    sph = np.tile(np.arange(5), n)
    rows = np.repeat(np.arange(n), 5)
    truth = ChainModel(g, true_axes, [0], q[rows], sph, 5, [0], np.full(5, 1.0))
    xt = np.zeros(truth.size())
    xt[4:] = spheres[1:].ravel()
    model = ChainModel(g, nominal_axes, [0], q[rows], sph, 5, [0], np.full(5, 1.0))
    # truth expressed in the fitted model's parameters (tilts and offsets from nominal)
    e1, e2 = model.frames[0]
    dp = true_axes[0].point - nominal_axes[0].point
    x_true = xt.copy()
    x_true[0] = np.degrees(np.arctan((d @ e1) / (d @ np.array([0, 1.0, 0]))))
    x_true[1] = np.degrees(np.arctan((d @ e2) / (d @ np.array([0, 1.0, 0]))))
    # the point: where the true axis line meets the plane through nominal point normal to nominal dir
    t = -(dp @ np.array([0, 1.0, 0])) / (d @ np.array([0, 1.0, 0]))
    pp = dp + t * d
    x_true[2], x_true[3] = pp @ e1, pp @ e2
    return model, x_true, truth.predict(xt)


def coverage_rotation(draws, noise, rng):
    model, x_true, clean = rotation_problem()
    names = model.names()
    est, sig = [], []
    for _ in range(draws):
        xy = clean + rng.normal(0, noise, clean.shape)

        def r(x):
            return ((xy - model.predict(x)) / noise).ravel()

        def j(x):
            return -(model.jacobian(x) / noise).reshape(-1, len(names))

        x0 = x_true.copy()
        x0[:4] = 0.0
        res = solve([Parameter(n, v, scale=0.01) for n, v in zip(names, x0)], r, j)
        est.append(res.x)
        sig.append(res.sigma)
    J = -(model.jacobian(x_true) / noise).reshape(-1, len(names))
    crb = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    return names, np.array(est) - x_true, np.array(sig), crb


def print_coverage(title, names, err, sig, crb, keep=None):
    print(f"\n{title}")
    print("| parameter | empirical std | mean reported sigma | coverage 1 sigma | std / CRB |")
    print("|---|---|---|---|---|")
    for i, n in enumerate(names):
        if keep and not keep(n):
            continue
        std = err[:, i].std(ddof=1)
        cov = np.mean(np.abs(err[:, i]) <= sig[:, i])
        print(f"| {n} | {std:.3g} | {sig[:, i].mean():.3g} | {100 * cov:.1f} % | {std / crb[i]:.3f} |")


def table3(rng, draws):
    print("\nTable III shape (paper geometry, 3x3x2 raster, mean |error| over draws)")
    print("| centre noise px | source mm | detector centre mm | u deg | v deg |")
    print("|---|---|---|---|---|")
    model, x_true, clean = paper_problem(rng, 0.0)
    gt = model.geometry(x_true)
    for noise in (0.1, 0.5, 1.0, 2.0):
        es, ed, eu, ev = [], [], [], []
        for _ in range(draws):
            res, _, _ = fit_paper(model, clean + rng.normal(0, noise, clean.shape), noise)
            g = model.geometry(res.x)
            es.append(np.linalg.norm(g.source - gt.source))
            ed.append(np.linalg.norm(g.detector_centre - gt.detector_centre))
            eu.append(np.degrees(np.arccos(np.clip(g.u @ gt.u, -1, 1))))
            ev.append(np.degrees(np.arccos(np.clip(g.v @ gt.v, -1, 1))))
        print(f"| {noise} | {np.mean(es):.4f} | {np.mean(ed):.4f} | {np.mean(eu):.5f} | {np.mean(ev):.5f} |")


def end_to_end(work: Path, seeds):
    print("\nEnd to end through simulated images and detect (fit-linear, then fit-rotation)")
    print("| seed | fit-linear RMS px | fit-rotation RMS px | axis direction error deg | axis point error mm |")
    print("|---|---|---|---|---|")
    for seed in seeds:
        lin = linear_raster(seed)
        rot = rotation_scan(seed, sod=100.0, sdd=500.0, true_geometry=lin.geometry)
        dl = write_scan(lin, work / f"lin{seed}", seed=seed, overwrite=True)
        dr = write_scan(rot, work / f"rot{seed}", seed=seed + 100, overwrite=True)
        sl, sr = load_scan(dl), load_scan(dr)
        write_json(work / "lm.json", detect_scan(sl, options_for_scan(sl)))
        write_json(work / "rm.json", detect_scan(sr, options_for_scan(sr)))
        fl = fit_linear(sl, load_observations(work / "lm.json", sl))
        fr = fit_rotation(sr, load_observations(work / "rm.json", sr), fl.geometry)
        truth = json.loads((dr / "truth.json").read_text())["rotary_axis"]
        ax = next(a for a in fr.axes if a.name == "theta")
        ang = np.degrees(np.arccos(abs(ax.direction @ truth["direction"])))
        dp = ax.point - truth["point"]
        dp -= (dp @ ax.direction) * ax.direction
        print(f"| {seed} | {np.sqrt(np.mean(fl.residual_px**2)):.4f} | {np.sqrt(np.mean(fr.residual_px**2)):.4f} | "
              f"{ang:.5f} | {np.linalg.norm(dp):.5f} |")


def coordinate_descent(cost, x0, scales, iterations, rng):
    """Blumensath et al.'s optimiser: per iteration a random order of the
    parameters, each minimised along its axis by a bracketed line search."""
    x = x0.copy()
    for _ in range(iterations):
        for i in rng.permutation(x.size):
            def f(t, i=i):
                y = x.copy()
                y[i] = t
                return cost(y)
            r = minimize_scalar(f, bracket=(x[i] - scales[i], x[i] + scales[i]), method="brent",
                                options={"xtol": 1e-8, "maxiter": 60})
            if r.fun < cost(x):
                x[i] = r.x
    return x


def speed(rng):
    print("\nSpeed (paper geometry, 0.5 px noise, same residuals and nominal start)")
    model, x_true, clean = paper_problem(rng, 0.5)
    xy = clean + rng.normal(0, 0.5, clean.shape)
    res, r, j = fit_paper(model, xy, 0.5)
    x0 = model.nominal_vector()

    def cost9(x9):
        x = x0.copy()
        x[:9] = x9
        return 0.5 * float(np.sum(r(x) ** 2))

    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        res, _, _ = fit_paper(model, xy, 0.5)
    t_ours = (time.perf_counter() - t0) / reps
    t0 = time.perf_counter()
    x_cd = coordinate_descent(cost9, np.zeros(9), np.ones(9), 35, rng)
    t_cd = time.perf_counter() - t0
    c_ours, c_cd = cost9(res.x[:9]), cost9(x_cd)
    print(f"conecal (trust-region LS, analytic Jacobian): cost {c_ours:.6g} in {1e3 * t_ours:.1f} ms")
    print(f"coordinate descent, 35 iterations:            cost {c_cd:.6g} in {1e3 * t_cd:.1f} ms")
    print(f"time ratio {t_cd / t_ours:.0f}x; conecal's cost is {'lower' if c_ours <= c_cd else 'HIGHER'}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args()
    rng = np.random.default_rng(2026)
    draws = 40 if args.quick else args.draws
    names, err, sig, crb = coverage_linear(draws, 0.5, rng)
    print_coverage(f"fit-linear, paper geometry, 0.5 px noise, {draws} draws", names, err, sig, crb)
    names, err, sig, crb = coverage_rotation(draws, 0.2, rng)
    print_coverage(f"fit-rotation, 5 spheres x 72 angles, 0.2 px noise, {draws} draws", names, err, sig, crb)
    table3(rng, 10 if args.quick else 50)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="conecal-bench-fit-"))
    end_to_end(work, [0] if args.quick else [0, 1, 2])
    speed(rng)


if __name__ == "__main__":
    main()
