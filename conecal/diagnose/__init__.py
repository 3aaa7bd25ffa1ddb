"""``diagnose``: find the physics a fit left out, model it, and show the fit improve."""

from .model import ResultModel
from .select import candidates, diagnose
from .structure import structure_tests

__all__ = ["ResultModel", "candidates", "diagnose", "structure_tests"]
