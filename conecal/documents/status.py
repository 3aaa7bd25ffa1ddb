"""A frame's pose status as structured fields, and the contract's sentence made from them.

The scan contract's ``status`` is a sentence: ``ok``, ``ambiguous: <reason>``
or ``rejected: <reason>``. conecal writes it from three parts a program can
read without parsing it: ``state`` (ok | ambiguous | rejected), ``reason``
(one of the short keys below, the same for every frame that failed the same
way) and ``detail`` (the numbers, for a person). A poses document holds
``status`` (the sentence) and ``reason`` (the key; absent for ``ok``).
"""

from __future__ import annotations

from dataclasses import dataclass

# reason keys: what a frame's pose failed on
REASONS = {
    "few_markers": "fewer usable markers than a pose needs",
    "no_pose": "no pose explains enough markers",
    "beyond_prior": "only poses farther from the initial pose than the prior allows fit",
    "few_identified": "too few of the spheres on the detector identified",
    "ambiguous_identity": "several identifications or poses fit about equally",
    "screw_shift": "the helix fits better shifted along its own screw",
    "mirror_pose": "a planar phantom's mirror pose fits about as well",
    "off_prediction": "too few markers near the bundle's prediction",
    "residual": "reprojection residual above the limit",
}


@dataclass(frozen=True)
class Status:
    """One frame's status. ``state``: ok | ambiguous | rejected; ``reason``:
    a key of :data:`REASONS` (empty for ok); ``detail``: the numbers."""

    state: str = "ok"
    reason: str = ""
    detail: str = ""

    def __post_init__(self):
        if self.state not in ("ok", "ambiguous", "rejected"):
            raise ValueError(f"status state must be ok, ambiguous or rejected, not {self.state!r}")
        if (self.state == "ok") != (self.reason == ""):
            raise ValueError("a reason is given exactly when the state is not ok")
        if self.reason and self.reason not in REASONS:
            raise ValueError(f"unknown status reason {self.reason!r}")

    @property
    def ok(self) -> bool:
        return self.state == "ok"

    @property
    def sentence(self) -> str:
        """The contract's ``status``: ``ok`` or ``<state>: <detail>``."""
        return "ok" if self.ok else f"{self.state}: {self.detail or REASONS[self.reason]}"

    def fields(self) -> dict:
        """The document's fields: ``status`` and, when not ok, ``reason``."""
        return {"status": self.sentence} if self.ok else {"status": self.sentence, "reason": self.reason}

    def __str__(self) -> str:
        return self.sentence


OK = Status()


def rejected(reason: str, detail: str) -> Status:
    return Status("rejected", reason, detail)


def ambiguous(reason: str, detail: str) -> Status:
    return Status("ambiguous", reason, detail)


def reason_lines(counts: dict) -> list[str]:
    """A summary's ``reasons`` (key -> frames) as terminal lines, most frequent first."""
    return [f"  {n} frame(s): {REASONS.get(k, k)} ({k})" for k, n in sorted(counts.items(), key=lambda kv: -kv[1])]


def state_of(frame: dict) -> str:
    """A poses document frame's state: ok, ambiguous or rejected."""
    return str(frame.get("status", "")).partition(":")[0]


def reason_of(frame: dict) -> str:
    """A poses document frame's reason key; for files written before the
    ``reason`` field, the sentence after the state (a person's words, not a key)."""
    if frame.get("reason"):
        return frame["reason"]
    state, _, rest = str(frame.get("status", "")).partition(":")
    return rest.strip().split(" (")[0] if rest else state
