"""Plain descriptions of a located mismatch, for forms no effect of the
library has: the reading of a rotary axis off by a constant from one moment
on (a slip, a knock), or by a harmonic of its own angle (an eccentric or
badly scaled encoder disc). Fitted like effects, never claimed as physics:
a named effect must explain the recording better than such a description
(``select.JUMP_MARGIN_BIC``) before it is claimed; a tie is reported as
ambiguous."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .candidates import Candidate


@dataclass(frozen=True, eq=False)
class ReadingJump:
    """A description, not an effect of the library: from ``t0`` (s) on, the
    axis stood ``amount`` (its unit) beyond its logged reading, as after an
    encoder slip or a knock. ``diagnose`` fits it where the residuals jump
    in time, so that a smooth named effect is not claimed for a jump."""

    axis: int
    t0: float
    amount: float
    name = "reading_jump"
    physics = "the axis' reading and its true position differ by a constant from one moment on (a slip or a knock)"

    def apply(self, world):
        q = np.array(world.true_readings, float)
        q[np.asarray(world.times) >= self.t0, self.axis] += self.amount
        return world.replace(true_readings=q)


@dataclass(frozen=True, eq=False)
class ReadingHarmonic:
    """A description, not an effect of the library: the axis stood
    ``a cos(h q) + b sin(h q)`` (its unit) beyond its reading q, the same at
    every turn -- an encoder disc mounted off-centre (h = 1) or out of round."""

    axis: int
    harmonic: int
    a: float
    b: float
    name = "reading_harmonic"
    physics = "the axis' reading is off by an amount that repeats every turn (an eccentric or out-of-round encoder)"

    def apply(self, world):
        q = np.array(world.true_readings, float)
        ang = np.deg2rad(np.asarray(world.readings, float)[:, self.axis]) * self.harmonic
        q[:, self.axis] += self.a * np.cos(ang) + self.b * np.sin(ang)
        return world.replace(true_readings=q)


def plain_descriptions(model, located) -> list[Candidate]:
    """One description per located mismatch of the rotation about a moving
    rotary axis: a jump in time (one parameter), or a harmonic of that
    axis' angle (two)."""
    chain = getattr(model, "chain", None)
    if chain is None or getattr(model, "stage", None) == "fit-pose":
        return []
    out = []
    for loc in located:
        for k, name in enumerate(chain.names):
            if not (model.rotary[k] and np.ptp(model.readings[:, k]) > 0
                    and loc["component"] == f"rotation about axis {name}"):
                continue
            if "at_time" in loc:
                t0 = float(loc["at_time"])
                out.append(Candidate(f"reading_jump:{name}@{t0:g}s", ("amount",), ("deg",), (0.005,),
                                     lambda x, k=k, t0=t0: ReadingJump(k, t0, float(x[0])),
                                     lambda x, s, n=name, t0=t0: f"the {n} reading off by {x[0]:+.4f} ± {s[0]:.4f} deg "
                                                                 f"from t = {t0:g} s on (a jump: a slip or a knock)"))
            elif loc["variable"] == name and loc["shape"].startswith("harmonic "):
                h = int(loc["shape"].split()[1])
                out.append(Candidate(f"reading_harmonic:{name}:{h}", ("a_cos", "a_sin"), ("deg", "deg"), (0.005, 0.005),
                                     lambda x, k=k, h=h: ReadingHarmonic(k, h, float(x[0]), float(x[1])),
                                     lambda x, s, n=name, h=h: (
                                         f"the {n} reading off by {np.hypot(x[0], x[1]):.4f} ± {max(s[0], s[1]):.4f} deg "
                                         f"{h}x per turn (an eccentric or out-of-round encoder disc)")))
    return out
