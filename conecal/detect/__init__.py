"""Sphere markers: candidates, sub-pixel centroids, identities across frames."""

from .crowded import detect_frame
from .options import Blob, DetectOptions
from .pipeline import MARKERS_FORMAT, detect_scan, options_for_scan
from .track import track

__all__ = ["Blob", "DetectOptions", "detect_frame", "MARKERS_FORMAT", "detect_scan", "options_for_scan", "track"]
