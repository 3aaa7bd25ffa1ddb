"""The candidate effects diagnose fits: families of forms, each member a
vector of parameters that builds an :class:`~conecal.effects.Effect`.

An effect is a *family* (issue 28): the axis direction as a Fourier series
of the angle (a precession, a nod in any plane, two harmonics), the axis
line running out 1-4 times per turn, drifts of the focal spot or the
detector as a line, a warm-up exponential, a quadratic or a cubic spline in
time, detector distortion as one radial or S-shaped number, radial +
tangential + S about a free centre, or a polynomial field, lag of one or
two frames. ``select`` fits every member and names, per family, the most
specific member that predicts held-out frames as well as the best one.
"""

from __future__ import annotations

import numpy as np

from ..effects.imaging import DetectorDistortion, DetectorWarp
from ..effects.motion import (AxisNonOrthogonality, AxisScale, Backlash, DetectorDrift, DriftPath, EncoderLatency,
                              FocalSpotDrift, RotaryRunout, RotaryTiltSeries, RotaryWobble)
from ..geometry.distortion import Distortion
from ..kinematics import LinearAxis, RotaryAxis
from .candidate import Candidate
from .model import CentroidPull, EllipseCentreBias

def _moving(model):
    return [k for k, n in enumerate(model.chain.names) if np.ptp(model.readings[:, k]) > 0]


def candidates(model) -> list[Candidate]:
    """Every effect of the registry that this recording could show, parameterised."""
    if model.stage == "fit-pose":
        from .pose import candidates as pose_candidates

        return pose_candidates(model)
    out = []
    dur = max(float(np.ptp(model.times)), 1e-9)
    out.append(Candidate("focal_spot_drift", ("vx", "vy", "vz"), ("mm/s",) * 3, (1e-3 / dur,) * 3,
                         lambda x: FocalSpotDrift(tuple(x)),
                         lambda x, s: "the focal spot drifted (" + ", ".join(
                             f"{a} {1e3 * v:+.3f} ± {1e3 * e:.3f} µm/s" for a, v, e in zip("xyz", x, s)) + ")",
                         family="focal_spot_drift"))
    out.append(Candidate("detector_drift", ("vx", "vy", "vz"), ("mm/s",) * 3, (1e-3 / dur,) * 3,
                         lambda x: DetectorDrift(tuple(x)),
                         lambda x, s: "the detector drifted (" + ", ".join(
                             f"{a} {1e3 * v:+.3f} ± {1e3 * e:.3f} µm/s" for a, v, e in zip("xyz", x, s)) + ")",
                         family="detector_drift"))
    out += _drift_family(model, dur)
    out.append(Candidate("detector_distortion:radial", ("radial_px",), ("px",), (0.05,),
                         lambda x: DetectorDistortion(float(x[0]), 0.0),
                         lambda x, s: f"the detector image is warped radially by {x[0]:+.3f} ± {s[0]:.3f} px at its "
                                      "corner (pincushion > 0)", family="detector_distortion"))
    out.append(Candidate("detector_distortion:s_shaped", ("s_px",), ("px",), (0.05,),
                         lambda x: DetectorDistortion(0.0, float(x[0])),
                         lambda x, s: f"the detector image is S-shaped: twisted by {x[0]:+.3f} ± {s[0]:.3f} px at its "
                                      "corner (counter-clockwise > 0), as an image intensifier in a magnetic field",
                         family="detector_distortion"))
    out += _distortion_family(model)
    moving = _moving(model)
    axes = model.chain.axes
    for k in moving:
        a = axes[k]
        unit = "deg" if isinstance(a, RotaryAxis) else "mm"
        q = model.readings[:, k]
        v = np.gradient(q, model.times)
        if isinstance(a, LinearAxis):
            out.append(Candidate(f"axis_scale:{a.name}", ("scale",), ("",), (1e-4,),
                                 lambda x, n=a.name: AxisScale(n, float(x[0])),
                                 lambda x, s, n=a.name: f"axis {n} moves {x[0] * 1e6:+.0f} ± {s[0] * 1e6:.0f} ppm "
                                                        "more than its encoder says"))
            for b in moving:
                if b != k and isinstance(axes[b], LinearAxis):
                    out.append(Candidate(f"axis_nonorthogonality:{a.name}->{axes[b].name}", ("angle",), ("deg",), (0.01,),
                                         lambda x, n=a.name, m=axes[b].name: AxisNonOrthogonality(n, m, float(x[0])),
                                         lambda x, s, n=a.name, m=axes[b].name:
                                         f"axis {n} leans {x[0]:+.4f} ± {s[0]:.4f} deg towards {m}"))
        if isinstance(a, RotaryAxis):
            out.append(Candidate(f"rotary_wobble:{a.name}", ("a_cos", "a_sin"), ("deg", "deg"), (0.005, 0.005),
                                 lambda x, n=a.name: RotaryWobble(n, float(np.hypot(*x)), float(np.degrees(np.arctan2(x[1], x[0])))),
                                 lambda x, s, n=a.name: f"axis {n} wobbles by {np.hypot(*x):.4f} ± {np.hypot(*s) / np.sqrt(2):.4f} deg "
                                                        f"once per turn (phase {np.degrees(np.arctan2(x[1], x[0])):.0f} deg)",
                                 family=f"rotary_wobble:{a.name}"))
            out += _wobble_family(a)
            out += _runout_candidates(model, a)
        if (v > 0).any() and (v < 0).any():
            out.append(Candidate(f"backlash:{a.name}", ("amount",), (unit,), (0.005,),
                                 lambda x, n=a.name: Backlash(n, float(x[0])),
                                 lambda x, s, n=a.name, u=unit: f"axis {n} has {x[0]:+.4f} ± {s[0]:.4f} {u} backlash "
                                                                "(error follows the direction of motion)"))
    if model.centre_model == "projection":
        d_mm = 2 * float(np.median(model.radii))
        out.append(Candidate("ellipse_centre_bias", ("fraction",), ("",), (0.05,),
                             lambda x: EllipseCentreBias(float(x[0])),
                             lambda x, s, d=d_mm: f"the measured centres are the shadows' attenuation centroids, not the "
                                                  f"projected sphere centres: {x[0]:.3f} ± {s[0]:.3f} of the ellipse-centre "
                                                  f"bias of {d:.2f} mm spheres (fit with --centre-model centroid)"))
    if moving:   # a lag ghost drags each centre back towards the previous frame's
        out.append(Candidate("detector_lag", ("pull",), ("",), (0.005,),
                             lambda x: CentroidPull(float(x[0])),
                             lambda x, s: f"each measured centre is pulled {100 * x[0]:+.2f} ± {100 * s[0]:.2f} % of "
                                          "the way back to the previous frame's (a lag ghost of the previous frame)",
                             lambda x: "a lag ghost cannot push a centre forwards (pull < 0)" if x[0] < 0 else None,
                             family="detector_lag"))
        out.append(Candidate("detector_lag:two_frames", ("pull1", "pull2"), ("", ""), (0.005, 0.005),
                             lambda x: CentroidPull(float(x[0]), float(x[1])),
                             lambda x, s: f"each measured centre is pulled {100 * x[0]:+.2f} ± {100 * s[0]:.2f} % of "
                                          f"the way back to the previous frame's and {100 * x[1]:+.2f} ± "
                                          f"{100 * s[1]:.2f} % to the one before (a lag ghost decaying over frames)",
                             lambda x: "a lag ghost cannot push a centre forwards (pull < 0)" if min(x) < 0 else None,
                             family="detector_lag", flexible=True))
    if moving:   # one latency for every axis: the encoders are read together
        out.append(Candidate("encoder_latency", ("latency",), ("s",), (0.005,),
                             lambda x: EncoderLatency(float(x[0])),
                             lambda x, s: f"frames were exposed {1e3 * x[0]:+.1f} ± {1e3 * s[0]:.1f} ms after the "
                                          "encoders were read (error ∝ velocity)"))
    return out


RUNOUT_HARMONICS = (1, 2, 3, 4)
_TIMES = {1: "once", 2: "twice", 3: "three times", 4: "four times"}


def _across_beam(model, a) -> float:
    """Angle (rad) in the axis' (e1, e2) plane of the direction across the
    beam: the runout the projections see (a fixed sensitive direction)."""
    from ..geometry.rotations import orthonormal_complement

    e1, e2 = orthonormal_complement(a.direction)
    t = np.cross(a.direction, model.geometry.source - a.point)
    return float(np.arctan2(t @ e2, t @ e1))


def _runout(axis: str, k: int, beta: float, x) -> RotaryRunout:
    """Runout ``x[0] cos(k q) + x[1] sin(k q)`` (mm) along the direction at
    ``beta``: a line traced k times per turn, i.e. equal forward and
    backward whirls."""
    A = float(np.hypot(*x))
    phi = float(np.arctan2(-x[1], x[0]))
    return RotaryRunout(axis, A / 2, float(np.degrees(phi + beta)), k, A / 2, float(np.degrees(phi - beta)))


def _runout_ellipse(axis: str, k: int, beta: float, x) -> RotaryRunout:
    """Runout ``(x0 cos kq + x1 sin kq) across + (x2 cos kq + x3 sin kq) along``
    the beam (mm): any ellipse traced k times per turn, as a forward whirl
    ``(u - i w) / 2`` and a backward one ``(u + i w) / 2`` of the complex
    displacements ``u``, ``w`` in the axis' (e1, e2) plane."""
    t = np.exp(1j * beta)
    u, w = (x[0] + 1j * x[2]) * t, (x[1] + 1j * x[3]) * t
    f, b = (u - 1j * w) / 2, (u + 1j * w) / 2
    return RotaryRunout(axis, float(abs(f)), float(np.degrees(np.angle(f))), k, float(abs(b)),
                        float(-np.degrees(np.angle(b))))


def _runout_candidates(model, a) -> list[Candidate]:
    """Runout at 1-4 times per turn, across the beam; and, where that helps,
    as an ellipse with a part along the beam too. A circular scan sees the
    axis' motion along the beam only through a magnification change (~2e-4
    for 20 µm at 100 mm), which precise markers far from the axis do show;
    once per turn a forward whirl is a centring error, which the spheres'
    fitted positions absorb."""
    beta = _across_beam(model, a)
    ellipses = [Candidate(f"rotary_runout:{a.name}:{k}:ellipse", ("across_cos", "across_sin", "along_cos", "along_sin"),
                          ("mm",) * 4, (0.002,) * 4,
                          lambda x, n=a.name, k=k: _runout_ellipse(n, k, beta, x),
                          lambda x, s, n=a.name, k=k:
                          f"axis {n} runs out {_TIMES[k]} per turn: its line moves across the beam by "
                          f"{1e3 * np.hypot(x[0], x[1]):.1f} µm and along it by {1e3 * np.hypot(x[2], x[3]):.1f} µm "
                          f"(amplitudes, ± {1e3 * float(np.sqrt(np.mean(np.square(s)))):.1f} µm)",
                          family=f"rotary_runout:{a.name}", flexible=True, follows=(a.name,))
                for k in RUNOUT_HARMONICS if k > 1]
    return ellipses + [Candidate(f"rotary_runout:{a.name}:{k}", ("across_cos", "across_sin"), ("mm", "mm"), (0.002, 0.002),
                      lambda x, n=a.name, k=k: _runout(n, k, beta, x),
                      lambda x, s, n=a.name, k=k:
                      f"axis {n} runs out {_TIMES[k]} per turn: its line moves across the beam by "
                      f"{1e3 * np.hypot(*x):.1f} ± {1e3 * float(np.sqrt(np.mean(np.square(s)))):.1f} µm "
                      f"(amplitude; first peak at {n} = {(np.degrees(np.arctan2(x[1], x[0])) / k) % (360 / k):.0f} deg, "
                      f"then every {360 / k:.0f} deg)", family=f"rotary_runout:{a.name}")
            for k in RUNOUT_HARMONICS]




def _xyz_words(x, s, scale=1e3, unit="µm") -> str:
    return ", ".join(f"{a} {scale * v:+.1f} ± {scale * e:.1f} {unit}" for a, v, e in zip("xyz", x, s))


DRIFT_PARTS = {"focal_spot_drift": ("source", "the focal spot"), "detector_drift": ("detector", "the detector")}
SPLINE_ORDER = 5     # cubic B-splines: 2 interior knots; enough for a warm-up plus a creep


def _drift_family(model, dur) -> list[Candidate]:
    """Drifts in time beyond a line: a warm-up exponential (its time
    constant fitted, as log(tau / duration)), a quadratic and a cubic spline."""
    out = []
    for fam, (part, who) in DRIFT_PARTS.items():
        def warm(x, part=part):
            return DriftPath(part, "warmup", 1, float(dur * np.exp(x[3])), tuple(x[:3]))

        out.append(Candidate(f"{fam}:warmup", ("ax", "ay", "az", "log_tau"), ("mm",) * 3 + ("",),
                             (1e-3,) * 3 + (0.3,),
                             warm,
                             lambda x, s, who=who: f"{who} moved as a warm-up settling (" + _xyz_words(x[:3], s[:3])
                                                   + f" in all, time constant {dur * np.exp(x[3]):.0f} s)",
                             lambda x: ("a warm-up time constant beyond 10 scan durations is a line, not a settling"
                                        if x[3] > np.log(10) else None),
                             family=fam, x0=(0.0, 0.0, 0.0, np.log(0.3)), local=True, flexible=True,
                             follows=("time",)))
        out.append(Candidate(f"{fam}:quadratic", tuple(f"{c}{k}" for k in (1, 2) for c in "xyz"), ("mm",) * 6,
                             (1e-3,) * 6,
                             lambda x, part=part: DriftPath(part, "poly", 2, 0.0, tuple(x)),
                             lambda x, s, who=who: f"{who} drifted along a curve (by the end: "
                                                   + _xyz_words(x[:3] + x[3:], np.hypot(s[:3], s[3:])) + ")",
                             family=fam, flexible=True, follows=("time",)))
        names = tuple(f"{c}{k}" for k in range(1, SPLINE_ORDER + 1) for c in "xyz")
        out.append(Candidate(f"{fam}:spline", names, ("mm",) * len(names), (1e-3,) * len(names),
                             lambda x, part=part: DriftPath(part, "spline", SPLINE_ORDER, 0.0, tuple(x)),
                             lambda x, s, who=who: f"{who} drifted along a smooth path in time (cubic spline; "
                                                   f"largest excursion {_spline_peak(model, x):.1f} µm)",
                             family=fam, local=True, flexible=True, follows=("time",)))
    return out


def _spline_peak(model, x) -> float:
    d = DriftPath("source", "spline", SPLINE_ORDER, 0.0, tuple(x)).offsets(model.times)
    return float(1e3 * np.linalg.norm(d, axis=1).max())


def _wobble_family(a) -> list[Candidate]:
    """The axis direction as a Fourier series of the angle: order 1 (a
    precession of either sense, a nod in any plane) and order 2."""
    out = []
    for order in (1, 2):
        names = tuple(f"{c}{k}" for k in range(1, order + 1) for c in ("e1_cos", "e1_sin", "e2_cos", "e2_sin"))

        def words(x, s, n=a.name, order=order):
            C = np.asarray(x).reshape(-1, 4)
            amp = [float(np.sqrt(np.sum(c ** 2) / 2)) for c in C]
            shape = ("a nod in one plane" if order == 1 and _is_nod(C[0]) else "a precession" if order == 1
                     else "a tilt path of two harmonics")
            return (f"axis {n} wobbles as it turns: {shape}, " + ", ".join(
                f"{amp[k]:.4f} deg RMS at {k + 1}x per turn" for k in range(order))
                + f" (± {float(np.sqrt(np.mean(np.square(s)))):.4f} deg per term)")

        out.append(Candidate(f"rotary_wobble:{a.name}:order{order}", names, ("deg",) * len(names),
                             (0.005,) * len(names),
                             lambda x, n=a.name: RotaryTiltSeries(n, tuple(x)), words,
                             family=f"rotary_wobble:{a.name}", flexible=True, follows=(a.name,)))
    return out


def _is_nod(c) -> bool:
    """Whether the order-1 tilt (a, b, c, d) traces a line (a nod) rather
    than a circle: the 2x2 matrix [[a, b], [c, d]] is near rank 1."""
    sv = np.linalg.svd(np.asarray(c).reshape(2, 2), compute_uv=False)
    return bool(sv[1] < 0.3 * sv[0])


def _distortion_family(model) -> list[Candidate]:
    """Detector distortion beyond one number: radial k1, k2 + tangential p1,
    p2 + S about a free centre (offset from the detector centre, px), and a
    polynomial field of degree 3 (no affine part: that is the geometry's)."""
    shape = tuple(model.geometry.shape)
    base = Distortion.radial(shape)
    c0 = np.asarray(base.centre)
    out = []

    def free(x):
        return DetectorWarp(Distortion.radial(shape, centre=tuple(c0 + x[:2]), radius=base.radius, k1=x[2], k2=x[3],
                                              p1=x[4], p2=x[5], s=x[6]))

    out.append(Candidate("detector_distortion:radial_tangential",
                         ("dc0", "dr0", "k1", "k2", "p1", "p2", "s"), ("px",) * 7, (5.0, 5.0) + (0.05,) * 5,
                         free,
                         lambda x, s: f"the detector image is warped about ({c0[0] + x[0]:.0f}, {c0[1] + x[1]:.0f}) px: "
                                      f"radial {x[2]:+.3f} ± {s[2]:.3f} and {x[3]:+.3f} ± {s[3]:.3f} px, tangential "
                                      f"{np.hypot(x[4], x[5]):.3f} px, S-shaped {x[6]:+.3f} ± {s[6]:.3f} px at the "
                                      "corner (as an image intensifier)",
                         family="detector_distortion", flexible=True, follows=("detector position",),
                         impossible=lambda x: _far_centre(x[:2], shape)))
    poly = Distortion.polynomial(shape, 3)
    out.append(Candidate("detector_distortion:polynomial3", poly.names, ("px",) * len(poly.names),
                         (0.05,) * len(poly.names),
                         lambda x: DetectorWarp(poly.with_coefficients(tuple(x))),
                         lambda x, s: "the detector image is warped by a smooth field (polynomial of degree 3, up to "
                                      f"{_field_peak(poly.with_coefficients(tuple(x)), model):.3f} px where the "
                                      "markers are)",
                         family="detector_distortion", flexible=True, follows=("detector position",)))
    return out


def _far_centre(offset, shape) -> str | None:
    """A warp centred further from the detector's centre than the detector's own size (rows, cols) is a
    fitted curvature, not a detector's distortion."""
    dc, dr = (float(v) for v in offset)
    if abs(dc) > shape[1] or abs(dr) > shape[0]:
        return (f"the warp's centre is ({dc:+.0f}, {dr:+.0f}) px from the detector's centre, more than the "
                "detector's own size: not a distortion of this detector")
    return None


def _field_peak(dist, model) -> float:
    return float(np.linalg.norm(dist.displacement(model.obs.xy), axis=-1).max())
