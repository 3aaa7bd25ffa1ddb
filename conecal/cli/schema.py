"""``conecal schema``: the JSON Schema of each document conecal reads or writes."""

from __future__ import annotations

import click

from ..documents import SCHEMA_NAMES, model_for, schema_text


@click.command("schema")
@click.argument("name", required=False, type=click.Choice(SCHEMA_NAMES))
def command(name):
    """Print the JSON Schema (draft 2020-12) of document NAME.

    Without NAME, list the documents. ``scan`` is scan.yaml (its parsed
    YAML); the others are the JSON results. Every document conecal reads is
    checked against its model, and every one it writes too; keys a schema
    does not list are allowed (a document may say more than its readers use).

    \b
    Examples:
      conecal schema
      conecal schema geometry > geometry.schema.json
      python -m jsonschema -i out/geometry.json geometry.schema.json
    """
    if name is None:
        for n in SCHEMA_NAMES:
            doc = (model_for(n).__doc__ or "").strip().splitlines() if n != "scan" else []
            click.echo(f"{n:10s} {doc[0] if doc else '``scan.yaml`` (conecal-scan/1): what was recorded and how'}")
        return
    click.echo(schema_text(name), nl=False)
