"""A sphere shadow beside an edge (a plate's step, a holder's wall): the
background across the edge fitted and removed (:mod:`.background`), then
the shadow's centroid measured again, or, where that stays disturbed, the
centre of a sphere model fitted on the cleaned patch. Units: px,
attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .background import fit_profile, structured
from .frame import refine
from .options import Blob, DetectOptions
from .overlap import disc_misfit, fit_group, joint_sigma

# how far a centroid and a model's centre may differ before the gap counts as
# the neighbours' models' (or the edge's) error. Not the cone-beam shadow's own
# centroid-to-circle gap, which is 0.003 px at most (centre.MODEL_CENTROID_PX);
# kept at the value the overlap and edge classes' pulls were measured with
CONE_OFFSET_PX = 0.03
# a sphere model on a patch whose edge was removed must fit its disc to this chi^2
# per pixel (in the pixel noise's variance), or as well as the background around it
# (on a tube's wall: spheres 0.8-4.8 against 2.5-70 around; a diffuse blob 34 against 17)
_EDGE_MODEL_CHI2 = 4.0
# ... or by this much more than the background around it, up to 3x that bar (the
# profile under the shadow is what the pixels beside it pin least: the independent
# helix's steel spheres where two walls cross read 3.7-7.8 on the disc against 2.4-5.6
# around, centres 0.1 px from the truth, and one on a wall's edge 4.09 against 2.67,
# 0.05 px off; a diffuse "bone" blob 54-62 against 35-46)
_EDGE_UNDER_SHADOW = 1.6
# the model's centre stands because the centroid on the cleaned patch was still
# disturbed: their gap is mostly the centroid's error, and half of it (a quarter of
# its square) is counted in the model's sigma. All of it left the typical marker's
# sigma 2-3x too large (robust pull 0.34-0.53 on the independent helix); half brings
# the class's pull std into 0.88-1.20 there and 0.69-1.02 on an independent renderer
_EDGE_GAP_SHARE = 0.5


def beside_edge(a, b: Blob, opt: DetectOptions, noise: float, invalid, others=()) -> Blob:
    """A shadow flagged clutter measured again with the background across an
    edge beside it (a plate's step, a tube's wall) fitted and removed, when
    one is there and the centroid then passes the clutter tests; otherwise
    ``b`` as it was. ``others``: (x, y, r) of the shadows around it."""
    if "clutter" not in b.flags and not structured(a, b.x, b.y, b.radius, opt.blur_px, noise, invalid, others):
        return b
    fit = fit_profile(a, np.array([[b.x, b.y, b.radius, b.mu_px]]), opt.blur_px, noise, invalid, others)
    if fit is None:
        return b
    (c0, q0, c1, q1), bg, sph = fit
    x_fit, y_fit = sph[0, :2]
    work = a.copy()
    work[q0:q1, c0:c1] -= bg
    b2 = refine(work, b.x, b.y, b.radius, opt, others, noise, invalid)
    # (a centroid the removed edge leaves elongated is still disturbed: what the
    # profile missed under the shadow, weighed by rho^2)
    if (b2 is None or "clutter" in b2.flags or b2.anisotropy > opt.max_anisotropy
            or np.hypot(b2.x - b.x, b2.y - b.y) > b.radius):
        return _edge_model(work, b, b2, sph, opt, noise, invalid, others)
    gap2 = (b2.x - x_fit) ** 2 + (b2.y - y_fit) ** 2
    b2.sigma = float(np.sqrt(b2.sigma**2 + max(gap2 / 2 - b2.sigma**2 - CONE_OFFSET_PX**2, 0.0)))
    return b2


def _edge_model(work, b: Blob, b2: Blob | None, sph: np.ndarray, opt: DetectOptions, noise: float, invalid,
                others) -> Blob:
    """The shadow's model centre on the frame with an edge's background
    removed, when its centroid ``b2`` there is still disturbed or elongated
    (the edge's profile under the shadow is what the profile fit knows
    least, and a centroid weighs it by distance): a sphere fitted with a
    plane on the cleaned patch, kept when it fits its disc to 2x the noise,
    or as well as the background model fits the patch around it (or 1.5x
    as well, up to 12x the noise variance), and it is of a sphere's size
    near the profile fit's sphere ``sph``; σ from the fit (scaled by its
    residual and the noise correlation), widened by ``_EDGE_GAP_SHARE`` of
    its gap to the centroid ``b2``.
    Else ``b`` as it was. Flags: clutter (the background was disturbed)."""
    fit = fit_group(work, sph, opt.blur_px, noise, others, invalid)
    if fit is None:
        return b
    _, s2, sig, _, chi2, n_pix = fit
    x, y, R, mu = s2[0]
    s_fit = joint_sigma(sig[0], opt.kappa_for("model", R))
    on, off = disc_misfit(work, fit, opt.blur_px, noise, others, invalid)
    bar = max(_EDGE_MODEL_CHI2, off, min(_EDGE_UNDER_SHADOW * off, 3 * _EDGE_MODEL_CHI2))
    if (on > bar or not 0.25 * opt.diameter_px[0] <= R <= 0.55 * opt.diameter_px[1]
            or np.hypot(x - sph[0, 0], y - sph[0, 1]) > 0.5 * R or not np.isfinite(s_fit) or s_fit > 0.5):
        return b
    gap2 = (b2.x - x) ** 2 + (b2.y - y) ** 2 if b2 is not None else 0.0
    return replace(b, x=float(x), y=float(y), radius=float(R), mu_px=float(mu), anisotropy=1.0,
                   sigma=float(np.sqrt(s_fit**2 + CONE_OFFSET_PX**2 + _EDGE_GAP_SHARE**2 * gap2 / 2)),
                   flags=sorted(set(b.flags) | {"clutter"}))
