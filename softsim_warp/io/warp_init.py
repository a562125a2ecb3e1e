"""Warp's start-up for the command line and the sweep's workers: quiet, with its kernel cache checked."""

from __future__ import annotations

import os
import tempfile

from ..core.errors import UserError
from ..core.native_output import held_stderr


_READY = False  # Warp started and its cache checked in this process: later calls only return it


def init_warp(debug=False):
    """Import and initialise Warp without its banner, module-load lines or missing-driver notice,
    and check that its kernel cache can be written; returns the ``warp`` module.

    A user error must read as one line; Warp prints a start-up banner (on stdout) and, on a machine
    without a CUDA driver, a notice from native code straight to file descriptor 2. Both are held
    back unless ``debug`` (in a sweep's workers they would also repeat once per worker).
    ``cli.main`` calls this before every command that uses Warp, a sweep worker before its tasks.

    A kernel cache that cannot be created or written (``HOME=/proc``, ``WARP_CACHE_PATH`` read-only
    or naming a file) is a one-line error naming the directory, raised before any work. Warp reads
    its cache's place once, when it starts, so the check is made once per process.
    """
    global _READY
    import warp as wp  # noqa: PLC0415

    if _READY:
        return wp
    try:
        if debug:
            wp.init()
        else:
            wp.config.quiet = True
            wp.config.log_level = wp.LOG_WARNING
            with held_stderr():
                wp.init()
    except OSError as e:
        raise _kernel_cache_error(wp, e) from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".softsim-probe-", dir=wp.config.kernel_cache_dir)
    except OSError as e:
        raise _kernel_cache_error(wp, e) from None
    os.close(fd)
    os.unlink(probe)
    _READY = True
    return wp


def _kernel_cache_error(wp, error: OSError) -> UserError:
    """The one line for a Warp kernel cache that cannot be made or written (``wp.init`` sets
    ``kernel_cache_dir`` before it creates the directory)."""
    cache = wp.config.kernel_cache_dir
    given = os.environ.get("WARP_CACHE_PATH")
    name = os.fspath(error.filename) if error.filename else cache
    where = "" if name == cache or name.startswith(cache + os.sep) else f" ('{name}')"
    return UserError(
        "environment", "WARP_CACHE_PATH",
        f"cannot use '{cache}' as Warp's kernel cache: {error.strerror or error}{where}; "
        "set WARP_CACHE_PATH to a writable directory",
        given, has_value=given is not None,
    )
