"""``log.csv`` and ``phantom.csv`` readers with row-precise errors."""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    if not rows:
        raise InputError(f"{path}: empty file, expected a header row")
    header = [h.strip() for h in rows[0]]
    return header, rows[1:]


def _numbers(path: Path, header: list[str], rows: list[list[str]]) -> np.ndarray:
    out = np.empty((len(rows), len(header)))
    for i, row in enumerate(rows):
        line = i + 2  # header is line 1
        if len(row) != len(header):
            raise InputError(f"{path}: line {line}: {len(row)} values, header has {len(header)}")
        for j, cell in enumerate(row):
            try:
                val = float(cell)
            except ValueError:
                raise InputError(f"{path}: line {line}, column {header[j]!r}: not a number ({cell.strip()!r})") from None
            if not np.isfinite(val):
                raise InputError(f"{path}: line {line}, column {header[j]!r}: not finite ({cell.strip()!r})")
            out[i, j] = val
    return out


@dataclass(frozen=True, eq=False)
class ScanLog:
    """One row per frame: ``frame`` (page index), ``time`` (s), ``readings``
    (n_frames, n_axes) in mm or degrees, columns in the order of ``names``."""

    frame: np.ndarray
    time: np.ndarray
    readings: np.ndarray
    names: tuple[str, ...]
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame)

    def column(self, name: str) -> np.ndarray:
        return self.readings[:, self.names.index(name)]


def read_log(path: str | Path, names: list[str], optional: list[str] = ()) -> ScanLog:
    """Read ``log.csv`` whose reading columns must be exactly ``names``;
    ``optional`` columns may be present (all or none of them), and are
    returned in ``extra``."""
    path = Path(path)
    header, rows = _read_csv(path)
    for required in ("frame", "time"):
        if required not in header:
            raise InputError(f"{path}: header: column {required!r} is missing")
    unknown = [h for h in header if h not in ("frame", "time") and h not in names and h not in optional]
    if unknown:
        allowed = ", ".join(list(names) + list(optional)) or "none"
        raise InputError(f"{path}: header: column {unknown[0]!r} is not an axis in scan.yaml (allowed: {allowed})")
    missing = [n for n in names if n not in header]
    if missing:
        raise InputError(f"{path}: header: column {missing[0]!r} for axis {missing[0]!r} is missing")
    present = [h for h in optional if h in header]
    if present and len(present) != len(optional):
        gone = [h for h in optional if h not in header]
        raise InputError(f"{path}: header: column {gone[0]!r} is missing (give all of {', '.join(optional)} or none)")
    if len(set(header)) != len(header):
        raise InputError(f"{path}: header: repeated column names")
    if not rows:
        raise InputError(f"{path}: no data rows")
    data = _numbers(path, header, rows)
    frame = data[:, header.index("frame")]
    if np.any(frame != np.round(frame)) or np.any(frame < 0):
        bad = int(np.flatnonzero((frame != np.round(frame)) | (frame < 0))[0])
        raise InputError(f"{path}: line {bad + 2}, column 'frame': must be a page index (integer >= 0)")
    frame = frame.astype(int)
    if len(np.unique(frame)) != len(frame):
        dup = int(np.flatnonzero(np.bincount(frame) > 1)[0])
        raise InputError(f"{path}: column 'frame': frame {dup} appears twice")
    time = data[:, header.index("time")]
    back = np.flatnonzero(np.diff(time) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(f"{path}: line {i + 2}, column 'time': time goes backwards ({time[i]} after {time[i - 1]})")
    readings = np.column_stack([data[:, header.index(n)] for n in names]) if names else np.zeros((len(rows), 0))
    extra = {h: data[:, header.index(h)] for h in present}
    return ScanLog(frame=frame, time=time, readings=readings, names=tuple(names), extra=extra)


@dataclass(frozen=True, eq=False)
class Phantom:
    """Marker holder: sphere ``ids`` and their ``positions`` (n, 3) mm in the holder frame."""

    ids: np.ndarray
    positions: np.ndarray


def read_phantom(path: str | Path) -> Phantom:
    path = Path(path)
    header, rows = _read_csv(path)
    need = ["id", "x", "y", "z"]
    missing = [h for h in need if h not in header]
    if missing:
        raise InputError(f"{path}: header: column {missing[0]!r} is missing (need id,x,y,z)")
    if not rows:
        raise InputError(f"{path}: no spheres listed")
    data = _numbers(path, header, rows)
    ids = data[:, header.index("id")]
    if np.any(ids != np.round(ids)):
        raise InputError(f"{path}: column 'id': ids must be integers")
    ids = ids.astype(int)
    if len(np.unique(ids)) != len(ids):
        raise InputError(f"{path}: column 'id': repeated sphere id")
    pos = np.column_stack([data[:, header.index(c)] for c in "xyz"])
    return Phantom(ids=ids, positions=pos)
