"""Linear and rotary axes, chains, DH robots: readings -> rigid transforms."""

from .chain import Chain, DHRobot, LinearAxis, RotaryAxis, dh_modified

__all__ = ["Chain", "DHRobot", "LinearAxis", "RotaryAxis", "dh_modified"]
