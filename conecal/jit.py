"""numba's ``njit``, with its compiled-function cache kept out of the installed package.

numba's ``cache=True`` writes ``*.nbi``/``*.nbc`` files beside the sources (``__pycache__``) when that
directory is writable. In an installed ``site-packages/conecal`` those files are not pip's, so
``pip uninstall`` leaves them, and the ``conecal/`` directory they keep becomes a namespace package
that shadows a later editable install ("cannot import name '__version__' from 'conecal'"). Unless
the user has chosen a place (``NUMBA_CACHE_DIR``), the cache goes to the user's cache directory
(``$XDG_CACHE_HOME/conecal/numba``, else ``~/.cache/conecal/numba``); where that cannot be written,
numba falls back to its own choices.
"""

from __future__ import annotations

import os
from pathlib import Path

from numba import config, njit, prange

__all__ = ["cache_dir", "njit", "prange"]


def cache_dir() -> Path:
    """Directory conecal asks numba to cache compiled functions in (the user's cache)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "conecal" / "numba"


if not os.environ.get("NUMBA_CACHE_DIR"):
    # numba reads config.CACHE_DIR when each cached function is created, so this must run before
    # conecal's kernels are decorated (every kernel module imports njit from here)
    config.CACHE_DIR = str(cache_dir())
