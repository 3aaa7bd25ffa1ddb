"""Every document conecal reads or writes, as a pydantic model.

``check(doc, path)`` validates a document by its ``format`` key; it runs on
every JSON file conecal reads (bad content -> :class:`InputError` naming the
file and the key) and on every one it writes (a document that breaks its
own schema is a bug and is not written). ``conecal schema NAME`` prints the
JSON Schema of each.
"""

from __future__ import annotations

import json

from pydantic import BaseModel, ValidationError

from ..errors import InputError
from .common import validation_message
from .results import DiagnosisDocument, GeometryDocument, MarkersDocument, PosesDocument, TruthDocument

MODELS: dict[str, type[BaseModel]] = {
    "conecal-markers": MarkersDocument,
    "conecal-geometry": GeometryDocument,
    "conecal-poses": PosesDocument,
    "conecal-diagnosis": DiagnosisDocument,
    "conecal-truth": TruthDocument,
}


def _scan_model():
    from ..scan.config import ScanConfig   # the scan format lives with the scan reader
    return ScanConfig


SCHEMA_NAMES = ("scan", "markers", "geometry", "poses", "diagnosis", "truth")


def model_for(name: str) -> type[BaseModel]:
    """``name``: ``scan``, ``markers``, ... or a format name ``conecal-markers``."""
    short = name.removeprefix("conecal-").split("/")[0]
    if short == "scan":
        return _scan_model()
    try:
        return MODELS[f"conecal-{short}"]
    except KeyError:
        raise InputError(f"no document named {name!r}; one of: {', '.join(SCHEMA_NAMES)}") from None


def schema(name: str) -> dict:
    """JSON Schema (draft 2020-12) of a document."""
    model = model_for(name)
    out = model.model_json_schema()
    short = name.removeprefix("conecal-").split("/")[0]
    out["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    out["$id"] = f"conecal-{short}/1"
    if short == "scan":
        out["description"] = ("scan.yaml (YAML; this schema applies to its parsed content). " +
                              (out.get("description") or ""))
        out["x-log-csv"] = LOG_CSV
    return out


# log.csv has no JSON form; its columns, as docs/scan-format.md states them
LOG_CSV = {
    "description": "log.csv: a header row, then one row per frame (a subset of the pages is allowed)",
    "columns": {
        "frame": "integer >= 0, unique: the page of the projection stack",
        "time": "seconds since the start of the scan, not decreasing",
        "<axis name>": "one column per axis of scan.yaml (mm or degrees), or q1..qn for a robot (degrees)",
        "rx, ry, rz, tx, ty, tz": "motion: free only, optional: a rough pose guess (rotation vector in degrees, mm)",
    },
}


def schema_text(name: str) -> str:
    return json.dumps(schema(name), indent=1, sort_keys=True) + "\n"


def check(doc: dict, path) -> dict:
    """Validate ``doc`` (a parsed conecal JSON document) against the model of its
    ``format``; return it unchanged. InputError names ``path`` and the key."""
    name = str(doc.get("format", "")).split("/")[0]
    model = MODELS.get(name)
    if model is None:
        return doc
    try:
        model.model_validate(doc)
    except ValidationError as exc:
        raise InputError(f"{path}: {validation_message(exc)}") from None
    return doc


class InvalidOutput(RuntimeError):
    """conecal built a document that breaks its own schema (a bug, never the user's input)."""


def check_output(doc: dict) -> None:
    try:
        check(doc, "output")
    except InputError as exc:
        raise InvalidOutput(f"conecal built an invalid {doc.get('format')} document ({exc}); please report it") \
            from None
