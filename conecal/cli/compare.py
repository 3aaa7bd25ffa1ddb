"""``conecal compare``: do two results agree, in physical terms?"""

from __future__ import annotations

import sys

import click

from ..export.compare import compare_files


@click.command("compare")
@click.argument("a", type=click.Path(dir_okay=False))
@click.argument("b", type=click.Path(dir_okay=False))
@click.option("--tol-px", type=click.FloatRange(0), default=0.05, show_default=True,
              help="Largest allowed reprojection difference of points in the field of view (px).")
@click.option("--tol-sigma", type=click.FloatRange(0), default=3.0, show_default=True,
              help="Largest allowed parameter difference in combined sigmas.")
def command(a, b, tol_px, tol_sigma):
    """Compare results A and B (conecal-geometry/1 or conecal-poses/1).

    Exit 0 when they agree within the tolerances (float noise never
    fails), 1 with a readable difference when they do not, 2 on bad input.

    \b
    Examples:
      conecal compare golden/geometry.json out/geometry.json
      conecal compare golden/poses.json out/poses.json --tol-px 0.02
    """
    c = compare_files(a, b, tol_px, tol_sigma)
    for line in c.lines:
        click.echo(line)
    click.echo("agree" if c.agree else "DIFFER")
    sys.exit(0 if c.agree else 1)
