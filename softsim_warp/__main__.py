"""``python -m softsim_warp``: the ``softsim`` command line (``commands.cli.main``)."""

import signal
import sys

from .commands import process


def _stop(signum, frame):
    """SIGINT, SIGTERM or SIGHUP while the command line's modules load: end with 128 + signum, no
    traceback (nothing is written yet). ``cli.main`` installs its own handlers when it starts."""
    for sig in process.STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    process.on_stop_signal(signum)
    sys.exit(128 + signum)


def entry() -> int:
    """Catch SIGINT, SIGTERM and SIGHUP first, guard standard output (``commands/process.py``), then
    import the command line (Warp with it) and run it.

    The package's own ``__init__`` runs before this (it imports Warp too): a signal during that
    import still gets Python's defaults.
    """
    for sig in process.STOP_SIGNALS:
        signal.signal(sig, _stop)
    process.guard_stdout()
    from .commands.cli import main  # noqa: PLC0415

    return main()


if __name__ == "__main__":
    sys.exit(entry())
