"""A result bound to the scan it was computed from.

Every result that names its scan (``"scan"``) also records
``"scan_binding"``: the scan folder relative to the result file, and
fingerprints of its ``scan.yaml``, its log and its projection stack. A
consumer given a scan pairs it with a result only when the fingerprints
match, so that a geometry is never silently applied to a scan it was not
fitted on; relative paths resolve from the result file, not the cwd.

The stack's fingerprint is its size plus SHA-256 of 32 blocks of 64 KiB
spread over the file (start and end included): it tells scans apart and
costs milliseconds on a stack of gigabytes; it is not a tamper seal.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import yaml

from .errors import InputError

BLOCK = 1 << 16
BLOCKS = 32


def _sha256(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _sampled(path: Path) -> tuple[int | None, str | None]:
    try:
        size = path.stat().st_size
        h = hashlib.sha256(str(size).encode())
        with open(path, "rb") as fh:
            for k in range(BLOCKS):
                fh.seek(max(0, (size - BLOCK) * k // (BLOCKS - 1)))
                h.update(fh.read(BLOCK))
        return size, h.hexdigest()
    except OSError:
        return None, None


def fingerprint(scan_root: str | os.PathLike) -> dict | None:
    """Fingerprints of a scan folder's files (None when it holds no scan.yaml)."""
    root = Path(scan_root)
    cfg = root / "scan.yaml"
    yaml_hash = _sha256(cfg)
    if yaml_hash is None:
        return None
    try:
        spec = yaml.safe_load(cfg.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError):
        spec = {}
    spec = spec if isinstance(spec, dict) else {}
    out = {"scan_yaml_sha256": yaml_hash}
    if isinstance(spec.get("log"), str):
        out["log_sha256"] = _sha256(root / spec["log"])
    if isinstance(spec.get("projections"), str):
        out["projections_bytes"], out["projections_sha256_sampled"] = _sampled(root / spec["projections"])
    return {k: v for k, v in out.items() if v is not None}


def binding(scan_root: str | os.PathLike, result_path: str | os.PathLike) -> dict | None:
    """What a result written to ``result_path`` records about its scan."""
    fp = fingerprint(scan_root)
    if fp is None:
        return None
    root = Path(scan_root).resolve()
    if str(result_path) == "-":
        rel = str(root)
    else:
        rel = os.path.relpath(root, Path(result_path).resolve().parent)
    return {"path": Path(rel).as_posix(), **fp}


def bind(doc: dict, result_path) -> dict:
    """``doc`` with ``scan_binding`` added for the scan(s) its ``scan`` names."""
    scans = doc.get("scan")
    if "scan_binding" in doc or scans is None:
        return doc
    if isinstance(scans, (list, tuple)):
        b = [binding(s, result_path) for s in scans]
        b = b if all(x is not None for x in b) else None
    else:
        b = binding(scans, result_path)
    return {**doc, "scan_binding": b} if b is not None else doc


def _bindings(doc: dict) -> list[dict]:
    b = doc.get("scan_binding")
    return [] if b is None else (b if isinstance(b, list) else [b])


def bound_scans(doc: dict, result_path) -> list[Path]:
    """The scan folder(s) a result names, resolved from the result file's folder
    (documents without a binding: ``scan`` as stored)."""
    b = _bindings(doc)
    if b:
        base = Path(result_path).parent
        return [base / x["path"] if not Path(x["path"]).is_absolute() else Path(x["path"]) for x in b]
    scans = doc.get("scan")
    if scans is None:
        return []
    return [Path(s) for s in (scans if isinstance(scans, list) else [scans])]


ALL_PARTS = ("scan.yaml", "log", "projections")


def _differences(stored: dict, now: dict, parts=ALL_PARTS) -> list[str]:
    out = []
    if "scan.yaml" in parts and stored.get("scan_yaml_sha256") != now.get("scan_yaml_sha256"):
        out.append("scan.yaml differs")
    if "log" in parts and stored.get("log_sha256") != now.get("log_sha256"):
        out.append("the log differs")
    if "projections" not in parts:
        pass
    elif stored.get("projections_bytes") != now.get("projections_bytes"):
        out.append(f"the projections differ ({stored.get('projections_bytes')} vs {now.get('projections_bytes')} bytes)")
    elif stored.get("projections_sha256_sampled") != now.get("projections_sha256_sampled"):
        out.append("the projections differ")
    return out


def check_scan(doc: dict, result_path, scan_root, *, allow_other: bool = False, option: str | None = "--allow-other-scan",
               parts=ALL_PARTS) -> None:
    """Raise InputError unless ``scan_root`` is the (or a) scan ``doc`` was
    computed from, comparing ``parts`` (markers: the projections only, so that
    scan.yaml may be edited between detect and a fit). Results written before
    bindings existed are not checked."""
    b = _bindings(doc)
    if not b or allow_other:
        return
    now = fingerprint(scan_root) or {}
    diffs = [_differences(x, now, parts) for x in b]
    if any(not d for d in diffs):
        return
    stored = bound_scans(doc, result_path)[0]
    hint = f" (pass {option} to use it on this scan anyway)" if option else ""
    raise InputError(f"{result_path} was computed from scan {stored}, not {scan_root}: {'; '.join(diffs[0])}{hint}")
