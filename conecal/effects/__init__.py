"""Registry of physical effects shared by ``simulate`` and ``diagnose``."""

from . import motion  # noqa: F401  (importing registers the effects)
from .base import REGISTRY, Effect, World, parse_effect

__all__ = ["REGISTRY", "Effect", "World", "parse_effect"]
