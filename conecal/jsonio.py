"""Atomic, versioned, deterministic JSON output and checked JSON input."""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .binding import bind
from .documents import check, check_output
from .errors import FormatVersionError, InputError


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None  # JSON has no NaN; null says "not determined"
    return obj


def umask() -> int:
    """The process's umask (read without changing it for longer than a call)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def new_file_mode() -> int:
    """``0666 & ~umask``: the mode a plain ``open()`` would give a new file."""
    return 0o666 & ~umask()


def atomic_write(path: str | os.PathLike, write) -> None:
    """Call ``write(binary_file)`` on a temporary file in ``path``'s folder, then
    rename it to ``path``, so that readers (and ``make -j``) never see a
    partial file; the file gets mode ``0666 & ~umask`` like any new file."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise InputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise InputError(f"{path}: cannot write ({exc.strerror or exc})") from None
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_write`)."""
    atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def dumps(doc: dict) -> str:
    """Serialise with sorted keys; numpy values become plain JSON."""
    if "format" not in doc:
        raise ValueError("every conecal output states its format version")
    plain = _plain(doc)
    check_output(plain)
    return json.dumps(plain, sort_keys=True, indent=1) + "\n"


def write_json(path: str | os.PathLike, doc: dict) -> None:
    """Write ``doc`` atomically (``-``: to standard output), bound to the scan
    its ``scan`` key names (see :mod:`conecal.binding`)."""
    doc = bind(doc, path)
    if str(path) == "-":
        sys.stdout.write(dumps(doc))
        sys.stdout.flush()
        return
    atomic_write_text(path, dumps(doc))


def read_json(path: str | os.PathLike, expected: str | tuple[str, ...], *, parts_ok: bool = False) -> dict:
    """Read a conecal JSON file and check its ``format`` key.

    ``expected`` is a format name without version (``conecal-markers``) or a
    tuple of them. Version 1 is the only one this conecal reads; a newer one
    asks the user to upgrade.
    """
    path = Path(path)
    expected = (expected,) if isinstance(expected, str) else expected
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    fmt = doc.get("format") if isinstance(doc, dict) else None
    if not isinstance(fmt, str) or "/" not in fmt:
        raise InputError(f"{path}: key 'format' missing; expected one of {', '.join(e + '/1' for e in expected)}")
    name, _, version = fmt.partition("/")
    if name not in expected:
        raise InputError(f"{path}: format is {fmt!r}, expected one of {', '.join(e + '/1' for e in expected)}")
    if version != "1":
        raise FormatVersionError(f"{path}: format {fmt!r} is newer than this conecal reads ({name}/1); upgrade conecal")
    check(doc, path)
    if doc.get("frame_range") and not parts_ok:
        raise InputError(f"{path}: frame_range: a part of a scan (--frames/--part); join the parts with conecal merge")
    return doc


def rounded(obj: Any, digits: int = 12) -> Any:
    """Round every float to ``digits`` significant digits, so that outputs do
    not change with the last bits of a BLAS call."""
    if isinstance(obj, dict):
        return {k: rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [rounded(v, digits) for v in obj]
    if isinstance(obj, np.ndarray):
        return rounded(obj.tolist(), digits)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if not np.isfinite(v) or v == 0.0:
            return v
        return float(f"{v:.{digits}g}")
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
