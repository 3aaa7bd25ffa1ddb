"""Second fits of the chosen distortion family that the markers may not tell
from the chosen fit: listed in the distortion choice, and where held-out
markers cannot tell them apart their spread is part of the intrinsics' and
poses' model sigma (``document._tied``), as a tied family's is. Units: px, mm.
"""

from __future__ import annotations

from dataclasses import replace

from ..stats import not_worse
from .bundle import Bundle, Observations, adjust
from .choose import n_params, paired_heldout

CENTRED = "the chosen, principal point held at the detector centre"
RESTARTED = "the chosen, started afresh from the pinhole fit"
# tied also when behind by less than this share of the held-out chi-square:
# a difference that small is a matter of the folds, not of the recording
MARGIN = 0.02


def _row(name: str, alt: Bundle, final: Bundle, obs: Observations, points, radius, folds: int,
         why_measured: str) -> dict:
    p = paired_heldout(alt, final, obs, points, radius, folds)
    row = {"family": name, "parameters": n_params(final.family, len(final.R)), "heldout_rms_px": p["rms_a"],
           "chosen": False, "behind_chosen_chi2": p["gain"], "behind_se": p["se"]}
    # Held-out markers hardly see the principal point (the poses absorb it); the
    # fit's own chi-square does, where the markers are at their noise. There an
    # alternative it rejects (chi-square(2) beyond 6) is none; where structure
    # remains (reduced chi-square above 2) that test is not to be trusted, and
    # held-out markers decide alone.
    delta = (alt.fit.chi2 - final.fit.chi2) / final.covariance_scale
    row["in_sample_delta_chi2"] = float(delta)
    if final.fit.reduced_chi2 <= 2.0 and delta > 6.0:
        row["why"] = why_measured
    else:
        row["tied"] = bool(not_worse(p["gain"], p["se"]) or p["gain"] < MARGIN * p["chi2_b"])
    return row


def _afresh(final: Bundle, fits: dict) -> Bundle | None:
    """The pinhole fit of the same frames (with the chosen fit's refined
    phantom, if any) to start a second fit from; None if there is none."""
    start = fits.get("none")
    if start is None or len(start.R) != len(final.R):
        return None
    if final.point_offsets is not None:
        start = replace(start, point_offsets=final.point_offsets, points_sigma=final.points_sigma)
    return start


def centred_alternative(final: Bundle, fits: dict, choice: list, obs: Observations, points, radius, cam,
                        folds: int) -> None:
    """A planar phantom seen from few directions, with a distortion about a free
    centre, may not tell the principal point from the detector centre: the
    chosen model refitted with it held there (sigma 0.5 px). A family whose
    twist turns about a centre per frame starts it from the pinhole fit
    (``_afresh``): pulled from the chosen fit's minimum, its twists' centres
    stuck (the real recording: held-out 0.66 px against 0.16)."""
    start = _afresh(final, fits) if final.family.twist_centre else final
    centred = adjust(final.family, cam, obs, points, radius, None, None, start=start or final, centre_sigma=0.5,
                     max_nfev=100)
    fits[CENTRED] = centred
    choice.append(_row(CENTRED, centred, final, obs, points, radius, folds,
                       "rejected by the fit's own chi-square: at the noise floor the principal point is measured"))


def restarted_alternative(final: Bundle, fits: dict, choice: list, obs: Observations, points, radius, cam,
                          folds: int) -> None:
    """A family whose twist turns about a centre of its own per frame has more
    than one minimum: the twists' centres, the shared decentring and the
    principal point trade. The chosen fit started from seeded twists
    (``twist.seed_twists``); this one is the same family refitted from the
    pinhole fit, every twist at zero about the shared centre. On the real
    intensifier recording the two land 800 px apart in the principal point,
    each with a stated sigma of 30 px, and predict held-out markers alike
    (0.162 against 0.168 px): the point is not determined there, and the
    spread says so. Nothing for other families."""
    start = _afresh(final, fits)
    if not final.family.twist_centre or start is None:
        return
    alt = adjust(final.family, cam, obs, points, radius, None, None, start=start, max_nfev=100)
    fits[RESTARTED] = alt
    choice.append(_row(RESTARTED, alt, final, obs, points, radius, folds,
                       "rejected by the fit's own chi-square: the chosen fit's minimum is the deeper one"))


__all__ = ["CENTRED", "RESTARTED", "centred_alternative", "restarted_alternative"]
