"""Sphere markers: candidates, sub-pixel centroids, identities across frames."""

from .frame import Blob, DetectOptions, detect_frame
from .pipeline import MARKERS_FORMAT, detect_scan, options_for_scan
from .track import track

__all__ = ["Blob", "DetectOptions", "detect_frame", "MARKERS_FORMAT", "detect_scan", "options_for_scan", "track"]
