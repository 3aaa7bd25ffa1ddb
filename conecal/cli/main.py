"""The ``conecal`` command: a group of thin subcommands.

Errors are translated to exit codes here and only here: bad usage or input
-> 2, a failed fit or other run-time failure -> 1, interrupted -> 130,
terminated (SIGTERM, SIGHUP) -> 128 + the signal's number.
"""

from __future__ import annotations

import importlib
import signal
import sys

import click

from .. import __version__
from ..errors import FitError, InputError, Terminated


def _raise_terminated(signum, _frame):
    raise Terminated(signum)


def _terminate_like_interrupt() -> None:
    """SIGTERM (``kill PID``, ``Popen.terminate()``, a batch scheduler) and
    SIGHUP (a closed terminal) end conecal the way Ctrl-C does."""
    for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, _raise_terminated)


_GLOBAL_FLAGS = ("-q", "--quiet", "-v", "--verbose")


def _global_flags_first(args: list[str]) -> list[str]:
    """Accept -q/-v after the subcommand (``conecal detect SCAN -q``), as a
    user expects of global flags: no subcommand has options of those names."""
    args = list(args)
    if "--" in args:
        cut = args.index("--")
        head, tail = args[:cut], args[cut:]
    else:
        head, tail = args, []
    moved = [a for a in head if a in _GLOBAL_FLAGS or (len(a) > 2 and a[0] == "-" and set(a[1:]) == {"v"})]
    if not moved:
        return args
    rest = [a for a in head if a not in moved]
    return moved + rest + tail


def _one_line(exc) -> str:
    """The message on one line: a file name or value holding a line break or
    another control character is shown escaped, as Python writes it."""
    return "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in str(exc))


# subcommand -> its module under conecal.cli, in the order ``--help`` lists them;
# a module is imported only when its command runs (or help lists them all):
# importing every stage took seconds before ``conecal --version`` answered
_COMMANDS = {"simulate": "simulate", "detect": "detect", "merge": "merge", "fit-linear": "fit_linear",
             "fit-rotation": "fit_rotation", "fit-pose": "fit_pose", "rp-grid": "rp_grid", "diagnose": "diagnose",
             "report": "report", "export": "export", "compare": "compare", "schema": "schema"}


class ConecalGroup(click.Group):
    def parse_args(self, ctx, args):
        return super().parse_args(ctx, _global_flags_first(args))

    def list_commands(self, ctx):
        return list(_COMMANDS)

    def get_command(self, ctx, name):
        if name not in _COMMANDS:
            return None
        return importlib.import_module(f"{__package__}.{_COMMANDS[name]}").command

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except InputError as exc:
            click.echo(f"Error: {_one_line(exc)}", err=True)
            sys.exit(2)
        except FitError as exc:
            click.echo(f"Fit failed: {_one_line(exc)}", err=True)
            sys.exit(1)
        except Terminated as exc:
            click.echo(f"Terminated by {signal.Signals(exc.signum).name}; no output was written.", err=True)
            sys.exit(128 + exc.signum)
        except KeyboardInterrupt:
            click.echo("Interrupted; no output was written.", err=True)
            sys.exit(130)
        except BrokenPipeError:
            # the reader went away (``conecal report X | head -1``): end quietly, as a
            # Unix tool killed by SIGPIPE would (128 + 13), without a traceback
            try:
                import os

                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            except OSError:
                pass
            sys.exit(141)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise  # click's own usage errors: it prints them and exits 2
        except Exception as exc:  # a bug, not the user's fault: one line unless -v
            if (ctx.obj or {}).get("verbosity", 0) > 0:
                raise
            click.echo(f"Error: internal error ({type(exc).__name__}: {_one_line(exc)}); no output was written. "
                       f"Run with -v for the traceback and please report it.", err=True)
            sys.exit(1)


@click.group(cls=ConecalGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="conecal")
@click.option("-v", "--verbose", count=True, help="More messages (repeatable).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors.")
@click.pass_context
def cli(ctx, verbose, quiet):
    """Geometry calibration of cone-beam X-ray CT systems.

    Units: mm and degrees in files and on the command line; pixel
    coordinates (column, row) with the centre of img[0, 0] at (0, 0).
    """
    ctx.ensure_object(dict)
    ctx.obj["verbosity"] = -1 if quiet else verbose
    _terminate_like_interrupt()
