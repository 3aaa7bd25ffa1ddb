"""Options and helpers shared by the subcommands (who uses what is noted)."""

from __future__ import annotations

import contextlib
import sys

import click

def check_output(ctx, param, value):
    """Fail before any work (exit 2) if ``-o`` cannot be written: its folder is a
    file, or exists and is not writable; ``-`` is standard output."""
    import os
    from pathlib import Path

    if value is None or value == "-":
        return value
    p = Path(value)
    if p.is_dir():
        raise click.BadParameter(f"{value}: is a directory", ctx=ctx, param=param)
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise click.BadParameter(f"{value}: {parent} is not a directory", ctx=ctx, param=param)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise click.BadParameter(f"{value}: cannot write in {parent} (permission denied)", ctx=ctx, param=param)
    return value


# detect, fit-*, report: where the result goes
output_option = click.option("-o", "--output", "output", required=True, type=click.Path(dir_okay=False),
                             callback=check_output,
                             help="Output JSON file (written atomically; '-' for standard output).")
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
    if verbosity() < 0:
        yield None
        return
    if not sys.stderr.isatty():
        # under make or a batch scheduler: a plain line about every 10 s
        import time

        last = [time.monotonic()]

        def line(done, total):
            now = time.monotonic()
            if now - last[0] >= 10 or (total and done == total and now - last[0] >= 1):
                last[0] = now
                click.echo(f"{description}: {done}/{total if total else '?'}", err=True)

        yield line
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
