"""A shadow's centre from its fitted sphere model, not its window's centroid.

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
whose σ holds more than noise, or a fit no surer than the centroid. A
centre the centroid disagrees with beyond what their noise allows says the
patch holds something the model does not (a holder's wall beside the shadow
moved the model 0.2-0.4 px where the centroid was 0.02-0.1 px off; a display's
curve over glare moved centroids 0.1-0.25 px where the models were right):
where the model's background holds the patch around the shadow, the marker
is then measured as a flagged one is, σ covering the gap, and flagged
``clutter`` beyond 3 σ. A flagged shadow that stands apart from the others is
measured by its model too, on the background an edge's profile or a
quadratic gives, with σ for how much the centre depends on that choice
(:func:`_apart_centre`). Units: px, attenuation.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .background import fit_profile, smooth_under, structured
from .frame import window_radius
from .options import Blob, DetectOptions
from .overlap import disc_misfit, fit_group, group_box, joint_sigma, odd_misfit

# the fitted circle's centre and the cone-beam shadow's attenuation centroid:
# 0.0000-0.0033 px apart over six geometries (see the module's docstring)
MODEL_CENTROID_PX = 0.005
# the model's and the centroid's centres may differ by this many times their
# noise (in squared distance over the sum of their variances; chi-square of 2
# degrees of freedom: 13 % of honest markers keep their centroid). At 9 (3 σ
# per axis) the independent helix's lone beads beside its tube's wall kept 7
# model centres 0.2-0.4 px off at σ 0.03-0.06 (pull std 0.98 -> 1.21)
_AGREE = 4.0
# an unflagged marker whose model and centroid differ by more than this (in
# squared distance over the sum of their variances; chi-square of 2 degrees of
# freedom: 1 % of honest markers; 3 σ per axis) is flagged clutter
_DISAGREE = 9.0
# ... counted only where the model's background fits the patch around the
# shadow to this mean squared residual (in the pixel noise's variance; 1.1-1.2
# on the first renderer's intensifier grids)
_AROUND_HOLDS = 2.0
# a centroid's σ over its model's is 2-3 (5-95 %: 1.5-3.8 on the independent
# helix, 2.0-3.1 on 8-bit JPEG); far above, the centroid's σ holds more than
# noise (a step beside the shadow: 3.0 px against the model's 0.04, where the
# model's centre was 0.17 px off and the centroid's 0.01), and it stays
_NOISE_LIKE = 4.0
# a flagged marker's centre and its model's may differ by this many times
# their σ (squared distance over the sum of variances)
_APART_AGREE = 9.0
# a one-sphere model's misfit on its disc over that around it, beyond which
# the shadow may hold two
_DISC_MISFIT = 2.0
# a one-sphere model's contrast over the frame's, beyond which a marker said
# to be two shadows nearly on top is left so
_ONE_CONTRAST = 1.3
# the smoothed-in background's Gaussian, in shadow radii
_SMOOTH_RADII = 2.0


def model_centre(a: np.ndarray, b: Blob, opt: DetectOptions, noise: float, invalid=None, others=(),
                 typical=(0.0, None)) -> Blob:
    """``b`` (measured alone by its centroid) with its centre and σ from a
    sphere model fitted on frame ``a`` (attenuation) about it, or ``b``
    unchanged where the model is not the better measurement. ``others``:
    (x, y, r) px of the shadows near it, left out of the fit; ``noise``: the
    frame's pixel noise; ``typical``: the frame's sphere radius (px) and
    contrast (None when unknown).

    A flagged marker's σ holds more than its noise (a neighbour's model, a
    disturbed background), which a fit's σ alone would drop (tried on the
    helix's overlapping beads: pull std 1.00 -> 3.87 with 12 of 153 beyond
    5): only one whose shadow stands apart is measured so, with σ for the
    background hidden under it (:func:`_apart_centre`). One whose σ covers a
    second sphere nearly on top (``b.pair``) only a model holding one
    sphere's contrast narrows."""
    if not np.isfinite(b.sigma) or b.radius <= 1.0 or "truncated" in b.flags:
        return b
    if b.flags:
        return _apart_centre(a, b, opt, noise, invalid, others, typical)
    start, noise, fit = _own_fit(a, b, opt, noise, invalid, others)
    if fit is None:
        return b
    sph = fit[1][0]
    if not _like(sph, b):
        return b
    s_fit = joint_sigma(fit[2][0], opt.kappa_for("model", fit[1][0][2]))
    gap2 = (sph[0] - b.x) ** 2 + (sph[1] - b.y) ** 2
    if np.isfinite(s_fit) and gap2 > _AGREE * (b.sigma**2 + s_fit**2) and gap2 > 2 * MODEL_CENTROID_PX**2 \
            and disc_misfit(a, fit, opt.blur_px, noise, others, invalid)[1] <= _AROUND_HOLDS:
        # Two measurements of one shadow that disagree beyond their noise:
        # something in the patch holds more than a sphere on a quadratic (a
        # display's curve over a glare gradient moved centroids 0.15-0.25 px
        # radially where the model was 0.02-0.08 px off; a wall beside a bead
        # moved the model instead). Measured as a disturbed marker is (on two
        # backgrounds, ``_apart_centre``), with σ covering the gap; flagged
        # clutter beyond _DISAGREE. (Only where the model's quadratic holds the
        # patch around the shadow: beside a plate's step that a centroid was
        # measured without, the model is what the step moved.)
        wide = float(np.sqrt(b.sigma**2 + gap2 / 2))
        flag = gap2 > _DISAGREE * (b.sigma**2 + s_fit**2)
        m = _apart_centre(a, replace(b, flags=sorted(set(b.flags) | {"clutter"}), sigma=wide), opt, noise, invalid,
                          others, typical, odd=True, own=(start, noise, fit))
        return replace(m, flags=m.flags if flag else b.flags)
    # (the bar is on the estimators' white-noise ratio: noise correlated over
    # more than the shadow's radius widens the centroid's σ more than the model's)
    like = _NOISE_LIKE * np.sqrt(opt.kappa_for("centroid", window_radius(b.radius, opt.blur_px))
                                 / opt.kappa_for("model", sph[2]))
    if not np.isfinite(s_fit) or not s_fit < b.sigma <= like * s_fit \
            or gap2 > _AGREE * (b.sigma**2 + s_fit**2):
        return b
    # (a gap beyond both noises, within the bar, is counted as the model's error)
    excess = max(gap2 / 2 - b.sigma**2 - s_fit**2, 0.0)
    return replace(b, x=float(sph[0]), y=float(sph[1]),
                   sigma=float(np.sqrt(s_fit**2 + MODEL_CENTROID_PX**2 + excess)))


def _apart_centre(a: np.ndarray, b: Blob, opt: DetectOptions, noise: float, invalid, others, typical,
                  odd: bool = False, own=None) -> Blob:
    """A flagged marker (``overlap``: measured with its neighbours' models
    removed; ``clutter``: a disturbed background) whose shadow stands apart
    from every other (no disc overlaps its own), measured by its own sphere
    model with the others left out, where that is surer than what it has.

    The background under the shadow is the unknown: where the patch holds
    more than a quadratic follows (:func:`.background.structured`: a tube's
    wall, a plate's edge), it is the edge's profile along its level lines
    (:func:`.background.fit_profile`), and the sphere is fitted on the frame
    less it; elsewhere a quadratic fitted with the sphere. σ says how much
    the centre depends on that choice: half the squared gap to the centre
    fitted on a second background (the quadratic beside a profile; beside a
    quadratic, the frame less a background smoothed in from around the
    shadows, :func:`.background.smooth_under`) is added to the fit's
    variance per axis. ``typical``: the frame's sphere radius (px) and
    contrast (None when unknown), for a marker whose window misread them.
    A marker said to be two shadows nearly on top (``b.pair``) is kept unless
    the model holds one sphere's contrast per px of chord (two read more)."""
    if any(np.hypot(x - b.x, y - b.y) < r + b.radius for x, y, r in others):
        return b
    # (``own``: :func:`_own_fit`'s result when the caller has it already)
    start, noise, fit = own if own is not None else _own_fit(a, b, opt, noise, invalid, others)
    if fit is None:
        return b
    # (a second sphere in the shadow, which its elongation may have shown:
    # one sphere leaves on its disc 3.7x the misfit around it, where lone
    # beads on the helix's tube read 0.5-1.7x)
    on, around = disc_misfit(a, fit, opt.blur_px, noise, others, invalid)
    if odd:
        # (only the odd part: a shadow the model shapes a little wrong,
        # glare or a display's curve about it, left 3.5-7x around on its
        # disc for lone spheres of the first renderer's intensifier grid)
        on = odd_misfit(a, fit, opt.blur_px, noise, others, invalid)
    if on > _DISC_MISFIT * around:
        return b
    # (a pair nearly on top doubles the chord: fitted as one sphere it read
    # 1.5-3.1x the frame's contrast on the helix, where its larger beads, which
    # the pair tests took for pairs, read 0.8-1.0x)
    if b.pair and (typical[1] is None or fit[1][0][3] > _ONE_CONTRAST * typical[1]):
        return b
    # (sphere (x, y, R, mu), centre σ) on the quadratic background
    quad = fit[1][0], joint_sigma(fit[2][0], opt.kappa_for("model", fit[1][0][2]))
    # (a patch whose scatter reads as structure but where no edge's profile
    # beats a plane is measured as one without: on the first renderer's log
    # display the profile found none for beads whose centroids were 0.1 px off
    # at σ 0.02 and whose quadratic models were 0.01-0.03 px off)
    prof = fit_profile(a, start, opt.blur_px, noise, invalid, others) \
        if structured(a, b.x, b.y, b.radius, opt.blur_px, noise, invalid, others) else None
    if prof is not None:
        best, second = _fit_less(a, prof[0], prof[1], start, opt, noise, invalid, others), quad
    else:
        discs = [*others, (b.x, b.y, b.radius)]
        box = group_box(a.shape, start, opt.blur_px)
        bg = smooth_under(a, box, discs, opt.blur_px, _SMOOTH_RADII * b.radius, invalid)
        best, second = quad, None if bg is None else _fit_less(a, box, bg, start, opt, noise, invalid, others)
    if best is None or second is None or not (_plausible(best[0], b, typical) and _plausible(second[0], b, typical)):
        return b
    (x, y), (x2, y2) = best[0][:2], second[0][:2]
    s2 = best[1] ** 2 + MODEL_CENTROID_PX**2 + ((x - x2) ** 2 + (y - y2) ** 2) / 2
    gap2 = (x - b.x) ** 2 + (y - b.y) ** 2
    if not (np.isfinite(s2) and s2 < b.sigma**2) or gap2 > _APART_AGREE * (b.sigma**2 + s2):
        return b
    excess = max(gap2 / 2 - b.sigma**2 - s2, 0.0)
    return replace(b, x=float(x), y=float(y), sigma=float(np.sqrt(s2 + excess)))


def _own_fit(a: np.ndarray, b: Blob, opt: DetectOptions, noise: float, invalid, others):
    """``b``'s sphere model on a quadratic background, the shadows ``others``
    left out: (start (1, 4), the noise used, :func:`.overlap.fit_group`'s
    result or None)."""
    start = np.array([[b.x, b.y, b.radius, max(b.mu_px, 1e-6)]])
    noise = max(noise, 1e-9)
    return start, noise, fit_group(a, start, opt.blur_px, noise, mask_out=others, invalid=invalid, quadratic=True)


def _fit_less(a: np.ndarray, box, bg: np.ndarray, start: np.ndarray, opt: DetectOptions, noise: float, invalid,
              others):
    """One sphere fitted, with a plane, on the frame's patch ``box`` less
    the background image ``bg`` over it: (x, y, R, mu frame px, centre σ
    px) or None."""
    c0, q0, c1, q1 = box
    off = np.array([c0, q0, 0.0, 0.0])
    fit = fit_group((a[q0:q1, c0:c1] - bg).astype(np.float32), start - off, opt.blur_px, noise,
                    mask_out=[(x - c0, y - q0, r) for x, y, r in others],
                    invalid=None if invalid is None else invalid[q0:q1, c0:c1], box=(0, 0, c1 - c0, q1 - q0))
    return None if fit is None else (fit[1][0] + off, joint_sigma(fit[2][0], opt.kappa_for("model", fit[1][0][2])))


def _plausible(sph: np.ndarray, b: Blob, typical) -> bool:
    """A fitted sphere of ``b``'s size and contrast, or of the frame's
    (``typical`` radius and contrast, bounds as a crowd's member must keep:
    a disturbed window misreads both)."""
    R1, mu1 = typical
    return _like(sph, b) or (mu1 is not None and 0.6 * R1 < sph[2] < 1.6 * R1 and 0.5 * mu1 < sph[3] < 2.0 * mu1)


def _like(sph: np.ndarray, b: Blob) -> bool:
    """Whether a fitted sphere (x, y, R, mu) is of ``b``'s size and contrast."""
    return bool(0.7 * b.radius <= sph[2] <= 1.4 * b.radius and 0.5 * b.mu_px <= sph[3] <= 2.0 * b.mu_px)
