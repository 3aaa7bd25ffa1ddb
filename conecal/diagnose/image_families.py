"""Image level: the members of the blur and scatter families beyond one
scan-wide number, offered where :mod:`.image_locate` says the residual
follows their variable.

- A focal spot: each sphere's shadow blurred by the spot's image, whose
  size grows with the sphere's magnification minus one (a detector's blur
  does not); as a uniform disc or a Gaussian.
- Lag that decays over frames: frame k back keeps ``lag decay^(k-1)``
  (k = 1..3); one frame's lag is the member with ``decay`` 0.
- Scatter that varies over the detector: a smooth field (a grid of broad
  Gaussian bumps) of the scatter fraction of the background, its grid
  chosen on held-out patches.

Units: spot sizes in px at the scan's mean magnification (and in mm in the
source plane), scatter as a fraction of the background intensity, detector
positions as fractions of its width (u) and height (v).
"""

from __future__ import annotations

import numpy as np

from .image_locate import field_degree, fit_field, patch_curves

# smallest sizes claimed: a disc radius and a Gaussian sigma in px, a field's largest scatter fraction
FLOORS = {"spot": 0.3, "spot_gauss": 0.15, "scatter_field": 0.005}

SPOT_PHYSICS = ("the focal spot is not a point: each sphere's shadow is blurred by the spot's image, which grows "
                "with the sphere's magnification minus one (a detector's blur does not)")
FIELD_PHYSICS = ("photons scattered in the object or in a structure beside the beam add intensity that varies "
                 "over the detector, so shadows read too thin where it is strong")


class Named:
    """An effect the image level names but the simulator's library has no class for: its physics, for the report."""

    def __init__(self, physics: str):
        self.physics = physics


def spot_candidates(im, Candidate) -> list:
    """Focal-spot members of the blur family (``Candidate``: the image level's candidate type)."""
    pitch = float(np.mean(im.g.pixel_pitch))
    m1 = im.mean_m1

    def mm(v):
        return v * pitch / m1 if m1 > 0 else float("nan")

    i_blur = im.PARAMS.index("blur")

    def begin(x, im, i_spot, factor):
        # the fitted detector blur is taken to be the spot's, mostly: a radius-R disc reads as sigma R / 2
        x = x.copy()
        x[i_spot] = max(factor * x[i_blur], 0.6)
        if im.stated_blur is None:
            x[i_blur] *= 0.3
        return x

    def member(label, name, kernel, size_words, factor):
        i_spot = im.PARAMS.index(name)
        return Candidate(
            label, (name,),
            lambda v, s: (f"shadows are blurred by {kernel} of {size_words} {v[0]:.3f} ± {s[0]:.3f} px at the mean "
                          f"magnification, growing with each sphere's magnification minus one: {kernel} focal spot "
                          f"of {size_words} {mm(v[0]):.4f} mm"),
            lambda v: Named(SPOT_PHYSICS), lambda v: v[0], FLOORS[name],
            begin=lambda x, im: begin(x, im, i_spot, factor))

    return [member("blur:focal_spot_disc", "spot", "a uniform disc", "radius", 2.0),
            member("blur:focal_spot_gauss", "spot_gauss", "a Gaussian", "sigma", 0.9)]


LAG_PHYSICS = ("the scintillator's afterglow decays over several frames: each frame keeps a share of the previous "
               "ones, smaller the further back")


def lag_candidate(Candidate, floor: float):
    """The lag member that decays over three frames."""
    def words(v, s):
        shares = ", ".join(f"{100 * v[0] * v[1] ** k:.2f} %" for k in range(3))
        return (f"each frame keeps {shares} of the frames 1, 2 and 3 back (lag {100 * v[0]:.2f} ± {100 * s[0]:.2f} % "
                f"decaying by {v[1]:.2f} ± {s[1]:.2f} per frame: ghosts of earlier marker positions; they pull "
                "detected centres back)")

    return Candidate("detector_lag:decaying", ("lag", "lag_decay"), words, lambda v: Named(LAG_PHYSICS),
                     lambda v: v[0], floor,
                     lambda v: "a detector cannot keep a negative fraction of a frame (lag < 0)" if v[0] < 0 else None)


def field_candidate(im, x, Candidate):
    """The scatter field member, at the degree held-out patches choose
    (None when a constant does as well: the scan-wide scatter candidate)."""
    degree, _ = field_degree(patch_curves(im, x, curves=("scatter",)))
    if degree == 0:
        return None
    state: dict = {}

    def prepare(model, x, train):
        vals = patch_curves(model, x, curves=("scatter",))
        f, coef = fit_field(vals, degree, train)
        # scattered intensity is not negative: where the estimates' level (which trades against the
        # attenuation coefficient mu, refitted next) puts part of the field below 0, it is raised
        lift = max(0.0, -float(f.min()))
        f = f + lift
        coef = coef.copy()
        coef[0] += lift
        for p, fi in zip(model.patches, f):
            p.extra_scatter = float(fi)
        lo, hi = int(np.argmin(f)), int(np.argmax(f))
        state.update(degree=degree, min=float(f[lo]), max=float(f[hi]),
                     min_at=[float(vals["u"][lo] + 0.5), float(vals["v"][lo] + 0.5)],
                     max_at=[float(vals["u"][hi] + 0.5), float(vals["v"][hi] + 0.5)], coefficients=coef.tolist())

    def words(v, s):
        return (f"an intensity of up to {100 * state['max']:.2f} % of the background is added under the shadows, "
                f"varying over the detector (a smooth field, {degree}x{degree} bumps: {100 * state['min']:.2f} % near "
                f"u={state['min_at'][0]:.2f}, v={state['min_at'][1]:.2f}, {100 * state['max']:.2f} % near "
                f"u={state['max_at'][0]:.2f}, v={state['max_at'][1]:.2f} of the detector's width and height)")

    def impossible(v):
        if state and state["min"] < -max(FLOORS["scatter_field"], 0.25 * state["max"]):
            return (f"the field reads {100 * state['min']:.2f} % scatter over part of the detector: scattered "
                    "intensity cannot be negative")
        return None

    n_terms = 1 + degree * degree
    return Candidate("scatter:field", (), words, lambda v: Named(FIELD_PHYSICS), lambda v: state.get("max", 0.0),
                     FLOORS["scatter_field"], impossible, n_extra=n_terms, prepare=prepare, state=state)
