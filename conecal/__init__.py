"""conecal: geometry calibration of cone-beam X-ray CT systems.

Units: mm and degrees at the edges (YAML, logs, JSON), radians inside the
code. Frames and conventions follow ``SCAN_FORMAT.md`` (format 1).
"""

__version__ = "0.1.0"
