"""Scan directories: scan.yaml models, TIFF stacks, logs, phantoms."""

from .config import SCAN_FORMAT, ScanConfig, load_config
from .scan import Scan, load_scan
from .stack import ProjectionStack
from .tables import Phantom, ScanLog, read_log, read_phantom

__all__ = ["SCAN_FORMAT", "ScanConfig", "load_config", "Scan", "load_scan", "ProjectionStack",
           "Phantom", "ScanLog", "read_log", "read_phantom"]
