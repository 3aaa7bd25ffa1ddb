"""Options and helpers shared by the subcommands (who uses what is noted)."""

from __future__ import annotations

import contextlib
import sys

import click

# detect, fit-*, report: where the result goes
output_option = click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False),
                             help="Output JSON file (written atomically).")
# fit-linear, fit-rotation: what a marker's measured centre is predicted as
centre_model_option = click.option(
    "--centre-model", type=click.Choice(["centroid", "projection"]), default="centroid", show_default=True,
    help="centroid: the attenuation centroid of the sphere's shadow (what detect measures); projection: the "
         "projected sphere centre, as the papers model it (leaves out the ellipse-centre bias; for comparison).")
# detect, simulate: threads for frames
workers_option = click.option("--workers", type=click.IntRange(1, 64), default=2, show_default=True,
                              help="Frames processed in parallel.")


def verbosity() -> int:
    ctx = click.get_current_context(silent=True)
    while ctx is not None and ctx.parent is not None:
        ctx = ctx.parent
    return (ctx.obj or {}).get("verbosity", 0) if ctx is not None else 0


def info(msg: str) -> None:
    """Print a line to stderr unless -q."""
    if verbosity() >= 0:
        click.echo(msg, err=True)


@contextlib.contextmanager
def progress_bar(description: str):
    """Yield a ``progress(done, total)`` callback drawing a rich bar on a
    terminal (stderr); silent when -q or when stderr is not a terminal."""
    if verbosity() < 0 or not sys.stderr.isatty():
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
    from rich.console import Console

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=Console(stderr=True), transient=False) as prog:
        task = prog.add_task(description, total=None)

        def update(done, total):
            prog.update(task, completed=done, total=total)

        yield update


def write_fit(output, doc: dict, res, summary: dict, what: str = "") -> None:
    """Refuse an unconverged fit (exit 1), else write ``doc`` atomically and
    say how well it fits and what the data leave undetermined."""
    from ..errors import FitError
    from ..jsonio import write_json

    if not res.success:
        raise FitError(f"least squares stopped without converging: {res.message}")
    write_json(output, doc)
    info(f"wrote {output}: reprojection RMS {summary['rms_px']:.4f} px over {summary['n_observations']} markers"
         f"{what}, reduced chi2 {res.reduced_chi2:.2f}")
    if res.undetermined:
        info(f"warning: the scan does not determine {', '.join(res.undetermined)}")
