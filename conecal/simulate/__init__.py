"""Simulated scans: exact line integrals, detector physics, scan directories."""

from .render import Cylinder, Ellipsoid, Sphere, render_line_integrals
from .scenarios import BUILDERS, KINDS, Scenario, circular_scan, linear_raster, robot_helix, rotation_scan
from .carm import free_scan
from .writer import expose, write_scan

__all__ = ["Cylinder", "Ellipsoid", "Sphere", "render_line_integrals", "BUILDERS", "KINDS", "Scenario",
           "circular_scan", "free_scan", "linear_raster", "robot_helix", "rotation_scan", "expose", "write_scan"]
