"""Per-view geometry in the sample frame, for reconstructors.

A calibration gives the source and detector in the lab frame and, per
frame, the sample-to-lab transform ``T_k`` (from calibrated axes and the
scan's log, or from fitted poses). A reconstructor wants the sample at
rest: view ``k`` is the lab geometry mapped by ``T_k^-1``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..binding import check_scan
from ..errors import InputError
from ..geometry import ConeGeometry, RigidTransform
from ..jsonio import atomic_write, read_json
from ..kinematics import Chain


def chain_from_doc(doc: dict, path) -> Chain:
    """The axes of a geometry document as a chain; InputError when it has none."""
    if not doc.get("axes"):
        raise InputError(f"{path}: axes: a geometry without axes has no per-view motion; export needs them")
    try:
        return Chain.from_list(doc["axes"])
    except ValueError as exc:
        raise InputError(f"{path}: axes: {exc}") from None


def views(result_path, scan=None, *, other_scan: bool = False) -> tuple[ConeGeometry | list, list[int], RigidTransform,
                                                                        list[str]]:
    """The lab geometry (a list, one per view, when a poses file frees the
    source and detector per frame), frame numbers, sample-to-lab transforms per view and
    warnings, from a ``conecal-poses/1`` file or a ``conecal-geometry/1``
    file plus its scan (whose log gives the readings): the scan RESULT was
    fitted on or, with ``other_scan``, another scan of the same system."""
    doc = read_json(result_path, ("conecal-geometry", "conecal-poses"))
    if scan is not None:
        check_scan(doc, result_path, scan.root, allow_other=other_scan, option="--other-scan")
        if list(doc["detector"]["shape"]) != [scan.config.detector.rows, scan.config.detector.cols]:
            raise InputError(f"{result_path}: detector.shape {list(doc['detector']['shape'])} differs from "
                             f"{scan.root / 'scan.yaml'}'s detector ({scan.config.detector.rows} rows, "
                             f"{scan.config.detector.cols} cols)")
    g = ConeGeometry.from_dict(doc)
    warnings = []
    if doc["format"].startswith("conecal-poses"):
        ok = [f for f in doc["frames"] if f["status"] == "ok"]
        skipped = len(doc["frames"]) - len(ok)
        if skipped:
            warnings.append(f"{skipped} rejected frame(s) left out")
        if not ok:
            raise InputError(f"{result_path}: no frame has status ok")
        T = RigidTransform(np.array([f["R"] for f in ok]), np.array([f["t"] for f in ok]))
        if any("detector" in f for f in ok):
            # source and detector freed per frame (a sagging C-arm): each view its own
            g = [ConeGeometry.from_dict(f) if "detector" in f else g for f in ok]
        return g, [int(f["frame"]) for f in ok], T, warnings
    if scan is None:
        raise InputError(f"{result_path}: a geometry file needs --scan (its log gives each view's axis readings)")
    chain = chain_from_doc(doc, result_path)
    names = list(scan.log.names)
    missing = [a for a in chain.names if a not in names]
    if missing:
        raise InputError(f"{scan.root / 'log.csv'}: has no column for axis {missing[0]!r} of {result_path}")
    for name in names:
        if name in chain.names or name in ("frame", "time"):
            continue
        col = np.asarray(scan.log.column(name), float)
        if col.size and np.ptp(col) > 0:
            raise InputError(f"{scan.root / scan.config.log}: column {name!r} moves ({col.min():g} to {col.max():g}) "
                             f"but {result_path} has no axis {name!r}: its views would ignore that motion")
    q = np.column_stack([scan.log.column(a) for a in chain.names])
    return g, [int(f) for f in scan.log.frame], chain.transforms(q), warnings


def per_view(g: ConeGeometry | list, T: RigidTransform) -> list[ConeGeometry]:
    """Geometry of each view in the sample frame; ``g``: the lab geometry, or one per view."""
    inv = T.inverse()
    gs = g if isinstance(g, list) else [g] * len(T)
    return [gk.transformed(inv[k]) for k, gk in enumerate(gs)]


def astra_vectors(geoms: list[ConeGeometry]) -> np.ndarray:
    """ASTRA ``cone_vec`` rows (n, 12): source, detector centre, u*pu, v*pv."""
    return np.array([gk.to_astra_vec() for gk in geoms])


def projection_matrices(geoms: list[ConeGeometry]) -> np.ndarray:
    """3x4 matrices (n, 3, 4) mapping homogeneous sample points to (c, r, 1)."""
    return np.array([gk.projection_matrix() for gk in geoms])


def write_array(path, array: np.ndarray, header: str) -> None:
    """``.npy`` as numpy stores it; anything else as text, one view per row,
    with a commented header; written atomically."""
    import io

    def write(fh):
        if Path(path).suffix == ".npy":
            np.save(fh, array)
        else:
            buf = io.StringIO()
            np.savetxt(buf, array.reshape(len(array), -1), fmt="%.10g", header=header)
            fh.write(buf.getvalue().encode())

    atomic_write(path, write)
