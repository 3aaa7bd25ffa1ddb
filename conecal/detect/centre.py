"""A lone shadow's centre from a fitted sphere model, not its window's centroid.

The attenuation centroid over a window weighs each pixel's noise by its
distance from the centre, out to the window's rim: on an independent helix
(8-15 px shadows, Poisson noise, blur 0.6-1.0 px) lone spheres' centroids
were 0.058 px off where the Cramér-Rao bound of that image is 0.010-0.022 px.
A sphere's blurred chord profile on a quadratic background, fitted by least
squares, reached 0.020 px on the same shadows. The fitted circle's centre is
the attenuation centroid's point to 0.003 px on exact cone-beam shadows (a
2 mm ball at magnification 10, 15 degrees off axis included,
``tests/test_detect_centre.py``): the shadow's asymmetry that separates the
projected centre from the centroid (0.045 px there) moves both alike.

The centroid stays where the model cannot be trusted to replace it: a fit
that fails, a fitted size or contrast far from the window's, a centroid
whose σ holds more than noise, a centre the centroid disagrees with beyond
what their noise allows (something in the
patch the model does not hold: a holder's wall beside the shadow moved the
model 0.2-0.4 px where the centroid was 0.02-0.1 px off), or a fit no surer
than the centroid. Units: px, attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .frame import Blob, DetectOptions
from .overlap import fit_group, joint_sigma

# the fitted circle's centre and the cone-beam shadow's attenuation centroid:
# 0.0000-0.0033 px apart over six geometries (see the module's docstring)
MODEL_CENTROID_PX = 0.005
# the model's and the centroid's centres may differ by this many times their
# noise (in squared distance over the sum of their variances; chi-square of 2
# degrees of freedom: 13 % of honest markers keep their centroid). At 9 (3 σ
# per axis) the independent helix's lone beads beside its tube's wall kept 7
# model centres 0.2-0.4 px off at σ 0.03-0.06 (pull std 0.98 -> 1.21)
_AGREE = 4.0
# a centroid's σ over its model's is 2-3 (5-95 %: 1.5-3.8 on the independent
# helix, 2.0-3.1 on 8-bit JPEG); far above, the centroid's σ holds more than
# noise (a step beside the shadow: 3.0 px against the model's 0.04, where the
# model's centre was 0.17 px off and the centroid's 0.01), and it stays
_NOISE_LIKE = 4.0


def model_centre(a: np.ndarray, b: Blob, opt: DetectOptions, noise: float, invalid=None, others=()) -> Blob:
    """``b`` (measured alone by its centroid) with its centre and σ from a
    sphere model fitted on frame ``a`` (attenuation) about it, or ``b``
    unchanged where the model is not the better measurement. ``others``:
    (x, y, r) px of the shadows near it, left out of the fit; ``noise``: the
    frame's pixel noise.

    Only an unflagged marker: a flagged one's σ holds more than its noise (a
    neighbour's model, a hidden second sphere, a disturbed background), which
    a fit's σ would drop (tried on the helix's overlapping beads: pull std
    1.00 -> 3.87 with 12 of 153 beyond 5)."""
    if b.flags or not np.isfinite(b.sigma) or b.radius <= 1.0:
        return b
    start = np.array([[b.x, b.y, b.radius, max(b.mu_px, 1e-6)]])
    noise = max(noise, 1e-9)
    fit = fit_group(a, start, opt.blur_px, noise, mask_out=others, invalid=invalid, quadratic=True)
    if fit is None:
        return b
    sph = fit[1][0]
    if not (0.7 * b.radius <= sph[2] <= 1.4 * b.radius and 0.5 * b.mu_px <= sph[3] <= 2.0 * b.mu_px):
        return b
    s_fit = joint_sigma(fit[2][0], opt.noise_kappa)
    gap2 = (sph[0] - b.x) ** 2 + (sph[1] - b.y) ** 2
    if not np.isfinite(s_fit) or not s_fit < b.sigma <= _NOISE_LIKE * s_fit \
            or gap2 > _AGREE * (b.sigma**2 + s_fit**2):
        return b
    # (a gap beyond both noises, within the bar, is counted as the model's error)
    excess = max(gap2 / 2 - b.sigma**2 - s_fit**2, 0.0)
    return replace(b, x=float(sph[0]), y=float(sph[1]),
                   sigma=float(np.sqrt(s_fit**2 + MODEL_CENTROID_PX**2 + excess)))
