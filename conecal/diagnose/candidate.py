"""One candidate effect as diagnose fits it: a vector of parameters (with
units and scales) that builds an :class:`~conecal.effects.Effect`, the
words that state it, and its family. Its own module so that the geometric
(``candidates``) and the robot (``pose``) registries both use it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Candidate:
    """An effect with its fitted parameters as a vector."""

    label: str
    names: tuple
    units: tuple
    scales: tuple
    build: object          # vector -> Effect
    describe: object       # vector, sigma -> plain words
    impossible: object = None   # vector -> reason the value cannot be physical, or None
    family: str = ""            # members of one family compete on held-out data first (default: the label)
    x0: tuple = None            # start (default: zeros)
    local: bool = False         # a form local in time (spline, warm-up): not asked to extrapolate across time blocks
    flexible: bool = False      # fitted only when the residuals were located on a variable in ``follows``
    follows: tuple = ()         # (or a simpler member of the family helped)

    @property
    def k(self) -> int:
        return len(self.names)

    @property
    def family_key(self) -> str:
        return self.family or self.label
