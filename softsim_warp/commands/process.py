"""What the ``softsim`` process shares with its surroundings: the signals that stop it, its terminal
and its standard output.

Imported by ``__main__`` before the command line (and Warp) load, so it imports nothing heavy.

* ``STOP_SIGNALS``: SIGINT (Ctrl-C), SIGTERM (``kill``) and SIGHUP (the terminal was closed) all ask
  a command to stop the same way (exit 128 + signum: 130, 143, 129); SIGHUP not when the process
  started with it ignored (``nohup``). After SIGHUP the terminal may be gone, and writing to it
  fails (``EIO``), so :func:`on_stop_signal` points standard output and error at ``/dev/null``
  when they are that hung-up terminal: the run still closes and keeps its files (a ``kill -HUP``
  with the terminal still there leaves them as they are).
* :func:`guard_stdout`: standard output is written through a wrapper whose failures are
  :class:`StdoutError`, so ``cli.main`` can tell them from any other ``OSError``: a closed pipe
  (``softsim bench | head``) ends the command quietly with 141 (128 + SIGPIPE, what a Unix tool
  killed by SIGPIPE reports), another failure (``> /dev/full``, ``>&-``) is one line on stderr and
  exit 2. A standard output closed at start (``>&-``) is held open on ``/dev/null``, so no file the
  command opens can take descriptor 1 and receive its printed lines.
"""

from __future__ import annotations

import errno
import io
import os
import signal
import sys

# A process started with SIGHUP ignored (``nohup softsim run ...``) was asked to outlive its
# terminal: it keeps ignoring it. This module is imported before any handler is installed.
_HUP_IGNORED = signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM) + (() if _HUP_IGNORED else (signal.SIGHUP,))
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE
EXIT_STDOUT_FAILED = 2


def _is_hung_up(fd: int) -> bool:
    """Whether ``fd`` is a terminal that was hung up: the kernel answers its ioctls with ``EIO``
    (before it signals SIGHUP). A live terminal (``kill -HUP`` sent by hand) is not."""
    import termios  # noqa: PLC0415

    try:
        termios.tcgetattr(fd)
    except termios.error as e:
        return e.args[0] == errno.EIO
    except (OSError, ValueError):
        return False
    return False


def detach_terminal():
    """Point descriptors 1 and 2 at ``/dev/null`` where they are a hung-up terminal (on SIGHUP)."""
    for fd in (1, 2):
        if _is_hung_up(fd):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)


def on_stop_signal(signum):
    """What every stop-signal handler does first: after SIGHUP, stop writing to the lost terminal."""
    if signum == signal.SIGHUP:
        detach_terminal()


class StdoutError(OSError):
    """Writing to standard output failed (a closed pipe, a full device, a closed descriptor)."""


class _Stdout(io.RawIOBase):
    """Descriptor 1, whose write errors are :class:`StdoutError`; after :meth:`discard`, writes vanish."""

    def __init__(self, closed_at_start: bool):
        super().__init__()
        self.closed_at_start = closed_at_start
        self.discarding = False

    def writable(self):
        return True

    def fileno(self):
        return 1

    def isatty(self):
        return not self.closed_at_start and os.isatty(1)

    def write(self, data):
        if self.discarding:
            return len(data)
        if self.closed_at_start:
            raise StdoutError(errno.EBADF, "standard output is closed")
        try:
            return os.write(1, data)
        except OSError as e:
            raise StdoutError(e.errno, e.strerror) from None

    def discard(self):
        self.discarding = True


_RAW: _Stdout | None = None


def guard_stdout():
    """Write ``sys.stdout`` through :class:`_Stdout` (the process's entry point calls this once)."""
    global _RAW
    try:
        os.fstat(1)
        closed = False
    except OSError:
        closed = True
        null = os.open(os.devnull, os.O_WRONLY)
        if null != 1:
            os.dup2(null, 1)
            os.close(null)
    old = sys.stdout
    _RAW = _Stdout(closed)
    sys.stdout = io.TextIOWrapper(
        io.BufferedWriter(_RAW),
        encoding=getattr(old, "encoding", None) or "utf-8",
        errors=getattr(old, "errors", None) or "strict",
        line_buffering=bool(getattr(old, "line_buffering", False)),
    )


def _stdout_name() -> str | None:
    try:
        return os.readlink("/proc/self/fd/1")
    except OSError:
        return None


def stdout_failed(error: StdoutError) -> int:
    """Report a failed write to standard output (nothing for a closed pipe); returns the exit code.

    Later writes to it are dropped, so the flush at the process's end does not fail again."""
    if _RAW is not None:
        if _RAW.closed_at_start:
            where = None
        else:
            where = _stdout_name()
        _RAW.discard()
    else:
        where = None
    if error.errno == errno.EPIPE:
        return EXIT_BROKEN_PIPE
    from ..core.errors import COMMAND_LINE, UserError  # noqa: PLC0415

    if error.errno == errno.EBADF:
        what = "standard output is closed; redirect it to a file or /dev/null instead"
    else:
        what = f"cannot write to standard output: {error.strerror}"
    line = UserError(COMMAND_LINE, "stdout", what, where, has_value=where is not None).line()
    try:
        print(f"error: {line}", file=sys.stderr, flush=True)
    except (OSError, ValueError, AttributeError):
        pass
    return EXIT_STDOUT_FAILED
