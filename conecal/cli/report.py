"""``conecal report``: what was estimated, how well."""

from __future__ import annotations

import click

from ..jsonio import read_json


def _fmt(v, unit):
    if v is None:
        return "-"
    return f"{v:.6g}" if unit != "mm" else f"{v:.4f}"


@click.command("report")
@click.argument("results", nargs=-1, required=True, type=click.Path(dir_okay=False))
def command(results):
    """Summarise fit RESULTS (conecal-geometry/1) on the terminal.

    One table per result: each parameter's initial and final value with its
    1-sigma uncertainty, the reprojection RMS, and warnings about
    parameters the data do not determine.

    \b
    Examples:
      conecal report demo/geometry.json
    """
    from rich.console import Console
    from rich.table import Table

    console = Console()
    for path in results:
        doc = read_json(path, "conecal-geometry")
        fit = doc.get("fit", {})
        table = Table(title=f"{path} — {doc.get('stage', '?')} on {doc.get('scan', '?')}", title_justify="left")
        for col in ("parameter", "unit", "initial", "final", "± 1σ", ""):
            table.add_column(col, justify="right" if col not in ("parameter", "unit", "") else "left")
        for name, p in fit.get("parameters", {}).items():
            if not p.get("free"):
                continue
            sig = p.get("sigma")
            note = "" if p.get("determined", True) else "[bold red]undetermined"
            table.add_row(name, p.get("unit", ""), _fmt(p.get("initial"), p.get("unit")), _fmt(p.get("value"), p.get("unit")),
                          "∞" if sig is None or sig == float("inf") else f"{sig:.2g}", note)
        console.print(table)
        rms = fit.get("rms_px")
        console.print(f"  reprojection RMS [bold]{rms:.4f} px[/] over {fit.get('n_observations')} markers, "
                      f"reduced χ² {fit.get('chi2_reduced', float('nan')):.2f}, outliers {fit.get('outliers', 0)}, "
                      f"start: {fit.get('start')}")
        src = doc["source"]
        det = doc["detector"]
        console.print(f"  source {[round(x, 4) for x in src]} mm; detector origin {[round(x, 4) for x in det['origin']]} mm")
        if fit.get("undetermined"):
            console.print(f"  [bold red]warning:[/] the data do not determine {', '.join(fit['undetermined'])}")
            for combo in fit.get("null_combinations", []):
                console.print(f"    free combination: {combo}")
