"""rp-grid, stage 6: a circular scan in, a ``conecal-geometry/1`` document out.

``run`` reads the stack twice: pass 1 on every other view (at most ~180)
with the nominal cosine weights (tables, grids, a first refinement); pass 2
on every view with pass 1's cosine weights and, where truncation left
few usable planes, more view pairs drawn where planes survive
(``sparse_selection``, ``pass2_pairs``); then the final refinement,
restarts along v and sigma. ``document`` writes the result (lengths in mm,
angles in deg, shifts in px of the nominal detector).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ...errors import FitError, InputError
from ...geometry.misalignment import NAMES, UNITS, misaligned
from .cost import RPProblem
from .options import RPOptions
from .search import grid_search, refine, restart_along_v
from .sigma import RPResult, finish
from .tables import NOISE_ANGLE_STEP, NOISE_S_STEP, build_tables


def check_scan(scan) -> np.ndarray:
    """The rotary axis direction of a circular scan; InputError otherwise."""
    cfg = scan.config
    if cfg.motion != "circular":
        raise InputError(f"{scan.root / 'scan.yaml'}: motion: rp-grid needs a circular scan, not {cfg.motion!r}")
    rotary = [a for a in cfg.axes if a.type == "rotary"]
    if len(rotary) != 1 or len(cfg.axes) != 1:
        raise InputError(f"{scan.root / 'scan.yaml'}: axes: a circular scan has exactly one rotary axis")
    if scan.n_frames < 36:
        raise InputError(f"{scan.root / cfg.log}: {scan.n_frames} frames; rp-grid needs at least 36 views")
    return np.asarray(rotary[0].direction, float)


def sparse_selection(opt: RPOptions, selection: dict) -> bool:
    """Whether a pass used under ``min_used_fraction`` of its candidate planes."""
    return selection["used"] < opt.min_used_fraction * selection["candidates"]


def pass2_pairs(opt: RPOptions, selection: dict, pair_yield=None) -> int:
    """View pairs of pass 2: ``opt.pairs``, or more (at most
    ``max_pairs_factor`` times) so that the used planes reach
    ``min_used_fraction`` of pass 1's candidates. With ``pair_yield``
    (:meth:`RPProblem.separation_yield`), the pairs are drawn in proportion
    to their yield, and each brings sum(n y^2) / sum(n y) planes."""
    if not sparse_selection(opt, selection):
        return opt.pairs
    used, want = selection["used"], opt.min_used_fraction * selection["candidates"]
    if pair_yield is None:
        per_pair = used / opt.pairs
    else:
        _, y, n = pair_yield
        per_pair = float(np.sum(n * y * y) / max(np.sum(n * y), 1e-12))
    return int(min(np.ceil(want / max(per_pair, 1e-12)), opt.max_pairs_factor * opt.pairs))


def pass2_keep_every(n: int, view_bytes: float, opt: RPOptions, noise: bool) -> int:
    """Every how many offsets pass 2 keeps of tables of ``n`` views,
    ``view_bytes`` each in full: the least k that holds them, and their
    noise tables (made coarser, and not thinned), within ``opt.max_table_gb``."""
    budget, extra = opt.max_table_gb * 1e9, (1.0 / (NOISE_ANGLE_STEP * NOISE_S_STEP) if noise else 0.0)
    for k in range(1, 9):
        if n * view_bytes * (1.0 / k + extra) <= budget:
            return k
    raise InputError(f"rp-grid: {n} views' tables need {n * view_bytes * (0.125 + extra) / 1e9:.1f} GB even with "
                     f"every 8th offset kept; raise --max-table-gb (now {opt.max_table_gb:g})")


def run(scan, opt: RPOptions, progress=None) -> tuple[RPResult, RPProblem]:
    """rp-grid on a loaded circular scan, in two passes over the stack.

    Pass 1: tables of every other view (at most ~180) with the nominal
    cosine weights; grids and a first refinement. Pass 2: tables of every
    view (every k-th offset kept where they would exceed
    ``opt.max_table_gb``: ``pass2_keep_every``) with the cosine weights of
    pass 1's geometry (a 2 deg tilt moves the principal point by ~20 mm,
    and the weights' error would mimic a tilt) and more view pairs where pass 1 used few of its planes
    (``pass2_pairs``), then the final refinement and sigma. Frames are read one at a
    time in each pass.
    """
    axis = check_scan(scan)
    nominal = scan.nominal_geometry()
    frames = [int(k) for k in scan.log.frame]
    n = len(frames)
    T_all = scan.nominal_transforms()
    step = max(1, n // 180)
    first = np.arange(0, n, step)
    total = len(first) + n + 20

    def images(idx):
        for k in idx:
            yield scan.stack.read(frames[k])

    def prog(offset, span):
        def cb(done, of):
            if progress:
                progress(offset + round(done * span / max(of, 1)), total)
        return cb

    # the cheap test first: a few views tell whether any plane is usable at all
    # (an object filling the field of view), before the tables of the whole scan
    probe = np.unique(np.linspace(0, n - 1, min(n, 16)).round().astype(int))
    try:
        RPProblem(nominal, T_all[probe], build_tables(images(probe), len(probe), nominal, opt), axis,
                  opt).select(np.zeros(5), min_planes=1)
    except FitError as exc:
        raise FitError(f"{exc} (seen on {len(probe)} views, before the tables of all {n})") from None
    t0 = time.perf_counter()
    tab1 = build_tables(images(first), len(first), nominal, opt, progress=prog(0, len(first)))
    prob1 = RPProblem(nominal, T_all[first], tab1, axis, opt)
    t1 = time.perf_counter()
    p_grid, evals = grid_search(prob1, opt, progress=lambda d, o: progress and progress(len(first) + round(10 * d / o), total))
    fit1, _ = refine(prob1, opt, p_grid)
    pair_yield = prob1.separation_yield() if sparse_selection(opt, prob1.last_selection) else None
    opt2 = replace(opt, pairs=pass2_pairs(opt, prob1.last_selection, pair_yield))
    keep = pass2_keep_every(n, tab1.tables[0].nbytes, opt, opt.noise_weights)
    del prob1, tab1
    t2 = time.perf_counter()
    tab2 = build_tables(images(range(n)), n, misaligned(nominal, fit1.x), opt, progress=prog(len(first) + 10, n),
                        noise=opt.noise_weights, keep_every=keep)
    prob = RPProblem(nominal, T_all, tab2, axis, opt2, pair_yield)
    t3 = time.perf_counter()
    fit, scale = refine(prob, opt2, fit1.x)
    before = fit
    fit, scale, restarts = restart_along_v(prob, opt2, fit, scale)
    t4 = time.perf_counter()
    res = finish(prob, opt2, fit, scale, p_grid, evals + fit1.nfev + restarts,
                 {"tables_pass1": t1 - t0, "search_pass1": t2 - t1, "tables_pass2": t3 - t2, "refine_pass2": t4 - t3})
    res.seconds["sigma"] = time.perf_counter() - t4
    res.seconds["total"] = time.perf_counter() - t0
    res.pass1 = fit1.x
    res.restarted_from = None if fit is before else np.array(before.x)
    if progress:
        progress(total, total)
    return res, prob


def document(res: RPResult, prob: RPProblem, scan, opt: RPOptions) -> dict:
    """The ``conecal-geometry/1`` document of an rp-grid run."""
    from ...fit.output import GEOMETRY_FORMAT
    from ... import __version__
    from ...jsonio import rounded

    g = misaligned(prob.nominal, res.x)
    undetermined = [n for n, s in zip(NAMES, res.sigma) if not np.isfinite(s) or s > opt.undetermined_sigma[n]]
    params = {}
    for k, (n, u) in enumerate(zip(NAMES, UNITS)):
        params[n] = {"index": k, "initial": 0.0, "free": True, "value": float(res.x[k]),
                     "sigma": float(res.sigma[k]) if np.isfinite(res.sigma[k]) else None, "unit": u,
                     "sigma_curvature": float(res.sigma_curvature[k]), "sigma_jackknife": float(res.sigma_jackknife[k]),
                     "sigma_batches": float(res.sigma_batches[k]), "sigma_slices": float(res.sigma_slices[k]),
                     "sigma_uncalibrated": float(res.sigma_uncalibrated[k]),
                     "sigma_factor": float(opt.sigma_factors[n]),
                     "grid": float(res.grid_best[k]), "determined": n not in undetermined}
    axes = [{"name": a.name, "type": a.type, "direction": list(a.direction),
             "point": list(a.point) if a.point is not None else [0.0, 0.0, 0.0]} for a in scan.config.axes]
    free = list(NAMES)
    corr = res.fit.correlation
    doc = {
        "format": GEOMETRY_FORMAT, "software": f"conecal {__version__}", "stage": "rp-grid", "scan": str(scan.root),
        **g.to_dict(), "axes": axes,
        "misalignment": params,
        "fit": {
            "method": "redundant plane integrals (Grangeat), grids then Newton",
            "parameters": params,
            "correlation": {"names": free, "matrix": np.where(np.isfinite(corr), corr, 0.0)},
            "undetermined": undetermined,
            "at_search_bound": list(res.at_bound),
            "cost_nominal": res.cost_nominal, "cost_final": res.cost_final,
            "cost_reduction": res.cost_nominal / res.cost_final if res.cost_final > 0 else None,
            "chi2_reduced": res.fit.reduced_chi2,
            "planes": {**res.planes, "pairs": prob.n_pairs, "planes_per_pair": opt.planes_per_pair,
                       "pairs_drawn": "by separation yield" if prob.pairs_by_yield else "uniformly",
                       "min_separation_deg": opt.min_separation_deg},
            "tables": {"views": int(prob.tab.tables.shape[0]), "max_gb": opt.max_table_gb,
                       "offset_step_px": prob.tab.ds / min(prob.nominal.pixel_pitch), "angles": opt.n_angles,
                       "offsets": int(prob.tab.tables.shape[2]), "ds_mm": prob.tab.ds, "smooth_px": opt.smooth_px,
                       "kernel_order": opt.kernel_order, "fan_sigma_deg": opt.fan_sigma_deg,
                       "interpolation": opt.interpolation,
                       "region": list(prob.tab.rect), "megabytes": prob.tab.nbytes / 1e6},
            "ranges": dict(opt.ranges), "grid_steps": dict(opt.grid_steps),
            "evaluations": res.evaluations,
            "seconds": res.seconds,
            "converged": bool(res.fit.success),
            "grangeat_factors": "following",
            # a lower minimum found by a restart means the cost has several
            # along v (README "Restarts along v")
            "restarts_along_v": {"offsets_px": list(opt.v_restarts_px),
                                 "moved_from": None if res.restarted_from is None
                                 else dict(zip(NAMES, map(float, res.restarted_from)))},
        },
        "cost_slices": res.slices,
        "units": {"length": "mm", "angle": "deg", "shift": "px of the nominal detector"},
    }
    return rounded(doc)
