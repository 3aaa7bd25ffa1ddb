"""A scan directory: config, projections, log and (optionally) phantom, checked together."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import ConeGeometry, RigidTransform
from ..kinematics import Chain, DHRobot, LinearAxis, RotaryAxis
from .config import ScanConfig, load_config
from .stack import ProjectionStack
from .tables import Phantom, ScanLog, read_log, read_phantom


@dataclass(frozen=True, eq=False)
class Scan:
    """A loaded scan directory (``SCAN_FORMAT.md``)."""

    root: Path
    config: ScanConfig
    log: ScanLog
    stack: ProjectionStack
    phantom: Phantom | None

    @property
    def n_frames(self) -> int:
        return len(self.log)

    def nominal_geometry(self) -> ConeGeometry:
        d, n = self.config.detector, self.config.nominal
        return ConeGeometry.nominal(sod=n.sod, sdd=n.sdd, shape=(d.rows, d.cols), pixel_pitch=d.pixel_pitch,
                                    principal_point=n.principal_point)

    def nominal_chain(self) -> Chain:
        axes = []
        for a in self.config.axes:
            if a.type == "linear":
                axes.append(LinearAxis(a.name, a.direction))
            else:
                axes.append(RotaryAxis(a.name, a.direction, a.point if a.point is not None else (0, 0, 0)))
        return Chain(tuple(axes))

    def robot(self) -> DHRobot:
        r = self.config.robot
        return DHRobot(dh=np.asarray(r.dh), flange=RigidTransform.from_matrix(np.asarray(r.flange)),
                       base=RigidTransform.from_matrix(np.asarray(r.base)))

    def nominal_transforms(self) -> RigidTransform:
        """Sample-to-lab transforms per log row from the nominal kinematics."""
        if self.config.motion == "robot":
            return self.robot().transforms(self.log.readings)
        return self.nominal_chain().transforms(self.log.readings)


def load_scan(path: str | Path) -> Scan:
    """Load and cross-check a scan directory (or the path of its ``scan.yaml``).

    Raises :class:`InputError` naming the file and the key, row or frame.
    """
    path = Path(path)
    cfg_path = path / "scan.yaml" if path.is_dir() else path
    if not cfg_path.exists():
        raise InputError(f"{cfg_path}: file not found (a scan directory holds scan.yaml)")
    root = cfg_path.parent
    cfg = load_config(cfg_path)
    log = read_log(root / cfg.log, cfg.joint_names, cfg.optional_log_columns)

    def _file(key, name):
        if name is None:
            return None
        p = root / name
        if not p.exists():
            raise InputError(f"{cfg_path}: {key}: file not found ({p})")
        return p

    proj = _file("projections", cfg.projections)
    flat = _file("flat", cfg.flat)
    dark = _file("dark", cfg.dark)
    stack = ProjectionStack(proj, (cfg.detector.rows, cfg.detector.cols), cfg.values, flat, dark)
    # a log may list a subset of the pages (frames are page numbers): a scan
    # trimmed, or split by hand; every listed page must exist
    if np.any(log.frame >= len(stack)):
        bad = int(np.flatnonzero(log.frame >= len(stack))[0])
        raise InputError(f"{root / cfg.log}: line {bad + 2}, column 'frame': frame {log.frame[bad]} is past the last page "
                         f"of {proj} ({len(stack)} pages)")
    phantom = None
    if cfg.markers is not None and cfg.markers.phantom is not None:
        phantom = read_phantom(_file("markers.phantom", cfg.markers.phantom))
    return Scan(root=root, config=cfg, log=log, stack=stack, phantom=phantom)
