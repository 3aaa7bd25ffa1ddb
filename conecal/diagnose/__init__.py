"""``diagnose``: find the physics a fit left out, model it, and show the fit improve."""

from .image_select import diagnose_image
from .levels import merge_levels
from .model import ResultModel
from .candidates import candidates
from .select import diagnose
from .structure import structure_tests

__all__ = ["ResultModel", "candidates", "diagnose", "diagnose_image", "merge_levels", "structure_tests"]
