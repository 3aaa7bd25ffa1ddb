"""rp-grid, stage 0: the options and constants shared by every stage.

Lengths are in mm unless a name says px (pixels of the nominal detector);
angles in deg unless a name says otherwise. The five parameters are
``misalignment.NAMES`` (shift u and v in px, eta, theta, phi in deg).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ...errors import InputError
from .. import kernels

FAN_STEP_DEG = 0.5     # the planes of a pair's fan: one every half degree about the baseline

# Each parameter's sigma is multiplied by this factor: the RMS of error/sigma
# over 20 simulated scans (seeds 200-219, four kinds) that are not the
# benchmark's 100-119. The sigma from the sandwich, jackknife, batches and
# profiles sees the noise of the planes but not the errors common to all of
# them (the tables' smoothing, cosine weights, truncation edges), which
# dominate: uncalibrated, the errors were 1.1-3.7 sigma RMS (u 3.70, v 1.06,
# eta 3.51, theta 2.40, phi 3.24; rounded up; measured with B-spline
# look-ups, Newton refinements and the restarts along v).
# `python benchmarks/bench_rpgrid.py --no-fdk --no-sharpness-search --first-seed 200 --uncalibrated-sigma`
SIGMA_FACTORS = {"shift_u_px": 3.7, "shift_v_px": 1.1, "eta_deg": 3.6, "theta_deg": 2.4, "phi_deg": 3.3}

DEFAULT_RANGES = {"shift_u_px": 20.0, "shift_v_px": 20.0, "eta_deg": 3.0, "theta_deg": 3.0, "phi_deg": 3.0}


@dataclass(frozen=True)
class RPOptions:
    n_angles: int = 360                 # table angles over [0, pi)
    offset_step_px: float = 1.0         # table offsets every this many pixels (0.5: twice the tables' time and size)
    smooth_px: float = 3.0              # Gaussian sigma of the s-derivative (px): less noise bias
    kernel_order: int = 2               # 4: the s-derivative's kernel also differentiates cubics exactly
    pairs: int = 1500                   # random view pairs (pass 2: more where truncation drops most planes)
    # Pass 2 draws more pairs (up to max_pairs_factor x) when pass 1 used
    # under this fraction of its candidate planes, and draws them at the
    # separations where pass 1's planes survived: transaxial truncation keeps
    # ~16 % of the planes, almost all from nearly opposite views, and drawn
    # uniformly a few hundred such pairs carried v, which then moved by half
    # a pixel with the draw (benchmark 16/20 -> 17/20, README "Which planes")
    min_used_fraction: float = 0.5
    max_pairs_factor: float = 4.0
    planes_per_pair: int = 48           # at most, evenly over the fan; its full step is FAN_STEP_DEG
    # Gaussian sigma (deg of the planes' angle about the pair's baseline) of a
    # smoothing along each pair's fan (0: off). Each view's table is smoothed
    # along its own pencil of planes, and the two views of one plane have
    # different pencils: on noiseless data that alone biases theta (-0.67 deg
    # at 3 px). Along the fan, both views average the same planes with the
    # same weights: with 1 px tables and 0.5-0.75 deg, theta is off by
    # < 0.06 deg (benchmarks/rpgrid_fan_smoothing.py). Off by default: at
    # 1e5 photons the thinner tables' noise outweighs it (RESULTS.md).
    fan_sigma_deg: float = 0.0
    min_separation_deg: float = 20.0
    ranges: dict = field(default_factory=lambda: dict(DEFAULT_RANGES))   # grid half-widths
    grid_steps: dict = field(default_factory=lambda: {"shift_u_px": 1.0, "shift_v_px": 1.0, "eta_deg": 0.25,
                                                      "theta_deg": 0.5, "phi_deg": 0.5})
    truncation_level: float = 0.005     # fraction of a view's high percentile marking "object at the border"
    crop: tuple | None = None           # manual (col0, col1, row0, row1), inclusive, optional
    exclude_truncated: bool = True
    exclude_holder: bool = True
    loss: str = "cauchy"                # planes near an edge the tables interpolate badly are outliers
    holder_ratio: float = 2.5           # a holder is this many times denser than the object
    motion_margin_px: float = 3.0       # lines this close to a truncated stretch or holder are dropped too
    grid_motion_px: tuple = (15.0, 8.0)  # the same margin during the two grid passes
    # gradient evaluations allowed to each joint refinement (Newton steps on
    # a numerical Hessian, 11 evaluations each; see refine()); unconverged,
    # the CLI exits 1
    refine_max_nfev: int = 200
    # offsets (px) of v from which the final refinement starts again; the
    # lowest robust cost on one set of planes wins (see restart_along_v)
    v_restarts_px: tuple = (-0.5, -0.25, 0.25, 0.5)
    # the numerical Hessian's difference steps, in Gauss-Newton standard
    # deviations along the Gauss-Newton matrix's eigenvectors (core.solve)
    hessian_step: float = 2.0
    # table look-ups: cubic B-spline along s, prefiltered once (README
    # "Search"); or "cubic" (Catmull-Rom: its grids and whole-range scans
    # look up bilinearly, ~2x faster there, but its cost ripples along v),
    # "linear"
    interpolation: str = "spline"
    # divide each plane's disagreement by its noise sigma at the lines (see
    # RPProblem.noise_weighted); needs the second pass's noise tables
    noise_weights: bool = True
    sigma_factors: dict = field(default_factory=lambda: dict(SIGMA_FACTORS))   # see SIGMA_FACTORS
    undetermined_sigma: dict = field(default_factory=lambda: {"shift_u_px": 2.0, "shift_v_px": 2.0, "eta_deg": 0.5,
                                                              "theta_deg": 1.0, "phi_deg": 1.0})
    # Pass 2's tables (and noise tables) at most this large (GB): a longer
    # scan or a larger detector keeps every k-th of their smoothed offsets
    # (pipeline.pass2_keep_every); otherwise they grow as views x detector
    # width (1440 views of 1024^2: 3.4 GB). benchmarks/bench_rpgrid_scale.py
    max_table_gb: float = 2.0
    seed: int = 0


LOOKUPS = {"cubic": kernels.lookup_cubic, "spline": kernels.lookup_spline, "linear": kernels.lookup}


def _lookup(opt: RPOptions):
    """The refinements' table look-up of ``opt.interpolation``; InputError for an unknown one."""
    if opt.interpolation not in LOOKUPS:
        raise InputError(f"rp-grid: interpolation must be one of {sorted(LOOKUPS)}, not {opt.interpolation!r}")
    return LOOKUPS[opt.interpolation]
