"""Markerless detector misalignment of a circular scan from redundant plane integrals.

Every plane through two source positions of the trajectory is seen by both
views. By Grangeat's relation, the derivative of the object's plane
integral along the plane normal is, in each view,

    dRf/drho (m, m.S) = (D^2 + s_pp^2) / D^2 * d/ds R[g_w](alpha, s),

where ``g_w = g D / sqrt(D^2 + u^2 + v^2)`` is the cosine-weighted
projection, ``R`` its 2D Radon transform on the detector line where the
plane meets the detector, ``D`` the source-detector distance (along the
detector normal), ``s_pp`` the line's distance from the principal point and
``m`` the plane's unit normal (oriented towards the line's side). The two
views must agree; with a wrong detector geometry they map the plane to the
wrong lines and disagree. The cost ``c_RP`` is the sum of squared
disagreements over a fixed sample of planes.

How the work is split:

- each view's table ``d/ds R[g_w](alpha, s)`` is computed once (pixel-driven
  Radon transform, derivative of a Gaussian along s) with the nominal
  cosine weights and kept in float32; frames are read one at a time, so
  memory is the tables, never the stack, and the tables of pass 2 keep
  every k-th of their smoothed offsets where they would exceed
  ``max_table_gb`` (2 GB);
- planes: random view pairs (at least ``min_separation_deg`` apart), and
  for each pair a fan of planes through both sources (rotating about the
  baseline), kept where they pass within the object's bounding sphere;
  planes whose line leaves either view's detector through a truncated edge
  (object present at the border: a long object, a wide object or a holder
  reaching out of the field of view) are dropped, automatically; where
  that leaves under half of them, pass 2 draws more pairs, and draws them
  at the separations where pass 1's planes survived (``separation_yield``);
- the five parameters are found by 2D grids over (shift u, eta),
  (shift v, theta), (theta, phi) and (shift v, theta) again, joint local
  refinements from a 3x3 pattern of tilts (the tilts barely change the
  cost and trade against the others), the 2D grids again, narrower, then a
  joint Newton refinement on the analytic gradient of the cost and its
  numerical Hessian (``refine``: Gauss-Newton's J^T J counts the noise's
  own slope and crept); sigma is the largest of the M-estimator's sandwich
  from that Hessian, a leave-views-out jackknife, the spread of disjoint
  batches of planes and of their minima along each range, times a factor
  per parameter calibrated on simulated scans (``SIGMA_FACTORS``).

The stages, one module each (imports run one way, top to bottom):

- ``options``: :class:`RPOptions` and the shared constants (``SIGMA_FACTORS``,
  ``DEFAULT_RANGES``, ``FAN_STEP_DEG``, the table look-ups ``LOOKUPS``);
- ``tables``: each view's table, its noise variance, truncated border
  stretches and holder hull (:func:`build_tables`, :class:`ViewTables`);
- ``planes``: the plane sample and its selection, the look-up arrays
  (``_PlaneSample``, the base class of :class:`RPProblem`);
- ``cost``: :class:`RPProblem`, the cost, residuals and Jacobian;
- ``search``: grids, the Newton refinement and restarts along v;
- ``sigma``: :func:`finish`, sigma and :class:`RPResult`;
- ``pipeline``: a scan in (:func:`check_scan`, :func:`run`, pass 2's pairs),
  a document out (:func:`document`).

Every name of the former single module ``rpgrid.py`` is still an attribute
of this package, and setting one here (``monkeypatch.setattr(rpgrid, ...)``)
sets it in the stage modules too, as it did when they were one module.
"""

from __future__ import annotations

from ...geometry.misalignment import NAMES, UNITS
from ..radon import KERNEL_REACH
from . import cost, options, pipeline, planes, search, sigma, tables  # noqa: F401  (rpgrid.sigma etc.)
from .cost import RPProblem
from .options import DEFAULT_RANGES, FAN_STEP_DEG, LOOKUPS, SIGMA_FACTORS, RPOptions, _lookup
from .pipeline import check_scan, document, pass2_pairs, run, sparse_selection
from .planes import _Frame, _frame, _Planes, _PlaneSample
from .search import (F_SCALE, STAGES, _bilinear, _grid, _grid_passes, _multistart, _parameters, _solve, grid_search,
                     refine, restart_along_v)
from .sigma import (RPResult, _pair_batches, _plane_gradients, batch_sigma, cost_slices, finish, jackknife_sigma,
                    slice_sigma)
from .tables import (HULL_VERTICES, NOISE_ANGLE_STEP, NOISE_S_STEP, ViewTables, _edge_flags, _holder_hull,
                     _view_table, _view_variance, build_tables)

__all__ = [
    "NAMES", "UNITS", "KERNEL_REACH",
    # options
    "DEFAULT_RANGES", "FAN_STEP_DEG", "LOOKUPS", "SIGMA_FACTORS", "RPOptions", "_lookup",
    # tables
    "HULL_VERTICES", "NOISE_ANGLE_STEP", "NOISE_S_STEP", "ViewTables", "_edge_flags", "_holder_hull",
    "_view_table", "_view_variance", "build_tables",
    # planes, cost
    "_Frame", "_frame", "_Planes", "_PlaneSample", "RPProblem",
    # search
    "F_SCALE", "STAGES", "_bilinear", "_grid", "_grid_passes", "_multistart", "_parameters", "_solve",
    "grid_search", "refine", "restart_along_v",
    # sigma
    "RPResult", "_pair_batches", "_plane_gradients", "batch_sigma", "cost_slices", "finish", "jackknife_sigma",
    "slice_sigma",
    # pipeline
    "check_scan", "document", "pass2_pairs", "run", "sparse_selection",
]
