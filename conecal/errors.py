"""Package error tree.

Each class also inherits the matching built-in so that library users can
catch either. The CLI alone translates them to exit codes: ``InputError`` ->
2 (bad usage or input), ``FitError`` -> 1 (a run-time failure).
"""


class ConecalError(Exception):
    """Base of every error conecal raises on purpose."""


class InputError(ConecalError, ValueError):
    """Bad input: a file, a key, a row or a frame that breaks the contract.

    The message is one line and names the file and the place in it.
    """


class FormatVersionError(InputError):
    """A file written by a newer conecal (or another format entirely)."""


class FitError(ConecalError, RuntimeError):
    """A fit that could not produce a trustworthy result."""


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread so that the same clean-up
    as for Ctrl-C runs (temporary files removed, workers ended); the CLI
    exits 128 + ``signum``."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum
