"""Registry of physical effects shared by ``simulate`` and ``diagnose``."""

from . import imaging, motion, robot  # noqa: F401  (importing registers the effects)
from .base import REGISTRY, Effect, World, parse_effect
from .imaging import Imaging

__all__ = ["REGISTRY", "Effect", "Imaging", "World", "parse_effect"]
