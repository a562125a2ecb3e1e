"""The ``softsim`` entry point: one subcommand per module of this package, errors as one line.

Each subcommand module has ``COMMAND`` (its name), ``add_parser(subparsers, add_common)`` and
``run(args) -> int``. A user error (bad scene value, unknown name, unwritable output) prints
``error: <file>: <key>: <what is wrong> (got <value>)`` and exits with 2; ``--debug`` shows the
traceback instead.

SIGINT, SIGTERM and SIGHUP end any command with 128 + signum (130, 143, 129) and no traceback
(``process.STOP_SIGNALS``): a command may catch them itself while it works (``softsim run`` stops
after the frame in progress, see ``common.Signals``); everywhere else in ``main`` the first one stops at once, as a
``KeyboardInterrupt`` whose cleanup (temporaries removed, locks released) later signals do not
interrupt. A signal before ``main`` runs, while Python imports the package (and Warp with it),
still gets Python's defaults.

Before the command runs, every path flag is checked not to be empty (``--out ''``, an unset shell
variable, is an error, not the default name) and Warp is initialised quietly with its kernel cache
checked (``io.warp_init.init_warp``), for every command that uses Warp. Standard output failing
(``process.StdoutError``) ends any command the same way: quietly with 141 for a closed pipe, else
one line and exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import signal
import sys
import threading
import traceback
import warnings

from ..core.errors import CommandLineError, UserError
from ..io.warp_init import init_warp
from . import accuracy, bench, common, compare, preview, process, run, scenes, stability, sweep

SUBCOMMANDS = (run, scenes, compare, preview, bench, accuracy, stability, sweep)
NO_WARP = ("scenes", "preview")  # commands that never start Warp
# Arguments that name a file (input or output), in any command: none may be the empty string.
PATH_ARGUMENTS = ("scene", "usd", "out", "metrics", "plot", "png", "gif", "preview")


class _Parser(argparse.ArgumentParser):
    """argparse with its errors turned into the one-line ``error: command line: <flag>: ...`` form.

    ``command`` is the subcommand the command line names (set by ``_main`` before parsing), so an
    unrecognized flag points to that subcommand's help."""

    command = None

    def error(self, message):
        raise _argparse_error(message, self.command)


def _argparse_error(message: str, command: str | None = None) -> CommandLineError:
    m = re.match(r"argument (\S+): (.*)$", message, re.S)
    key, text = (m.group(1), m.group(2)) if m else ("arguments", message)
    if key.startswith("-") and "/" in key:  # "-h/--help": name the long form
        key = key.split("/")[-1]
    m = re.match(r"^(.*): '(.*)'( \(choose from (.*)\))?$", text, re.S)
    if m:  # "invalid float value: 'abc'", "invalid choice: 'x' (choose from ...)"
        what = m.group(1) + (f"; choose from {m.group(4)}" if m.group(4) else "")
        return CommandLineError(key, what, m.group(2))
    m = re.match(r"^ignored explicit argument '(.*)'$", text, re.S)
    if m:  # "--deterministic=yes": a switch given a value
        return CommandLineError(key, "is a switch and takes no value", m.group(1))
    m = re.match(r"^unrecognized arguments: (.*)$", text, re.S)
    if m:
        see = f"softsim {command} --help" if command else "softsim --help"
        return CommandLineError("arguments", f"unrecognized arguments; see {see}", m.group(1))
    m = re.match(r"^the following arguments are required: (.*)$", text, re.S)
    if m:
        return CommandLineError(m.group(1), "is required")
    if text.startswith("not allowed with"):
        return CommandLineError(key, text, "both")
    return CommandLineError(key, text)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="softsim", description="Mass-spring jelly simulator on NVIDIA Warp.")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in SUBCOMMANDS:
        module.add_parser(sub, common.add_common)
    return parser


class _Stop:
    """main's own SIGINT/SIGTERM/SIGHUP handler: the first signal raises ``KeyboardInterrupt`` (while
    ``armed``), later ones are only recorded, so the cleanup the first one starts runs to the end."""

    def __init__(self):
        self.received = None
        self.armed = True

    def note_received(self, signum):
        """A signal a command's own handler (``common.Signals``) took while it stood in for this one:
        the first signal, whichever handler took it, gives the exit code."""
        if self.received is None:
            self.received = signum

    def __call__(self, signum, frame):
        self.note_received(signum)
        process.on_stop_signal(signum)
        if self.armed:
            self.armed = False
            raise KeyboardInterrupt


def _install(handler) -> dict:
    """Point SIGINT, SIGTERM and SIGHUP at ``handler``; returns the previous handlers ({} off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, handler) for sig in process.STOP_SIGNALS}




def main(argv=None) -> int:
    """Run the command in ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    Called without ``argv`` (the process's entry point), the stop signals are ignored after it
    returns, while the process exits, and standard output is flushed here (a failure to write it
    is reported like any other); called with ``argv`` (in-process, tests), the previous handlers
    are restored.
    """
    entry = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    stop = _Stop()
    previous = _install(stop)
    try:
        try:
            code = _main(argv)
            if entry:
                sys.stdout.flush()
        finally:
            stop.armed = False  # from here on a signal is only recorded
    except KeyboardInterrupt:
        code = 128 + int(stop.received or signal.SIGINT)
    except process.StdoutError as e:
        code = process.stdout_failed(e)
    finally:
        for sig, old in previous.items():
            # In-process, the caller's handlers come back. At the process's end signals are ignored:
            # Python resets its own handlers to the default while it shuts down, and a signal then
            # would kill the process (exit status -signum) after the command ended with its code.
            signal.signal(sig, signal.SIG_IGN if entry else old)
    return code


@contextlib.contextmanager
def _quiet_float_warnings(debug: bool):
    """No NumPy floating-point warning (overflow, invalid value) reaches stderr: an overflowing run
    is reported as an explosion by the run itself, in one line. ``--debug`` shows them."""
    if debug:
        yield
        return
    import numpy as np  # noqa: PLC0415

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=RuntimeWarning,
                                message=r".*(overflow|invalid value|divide by zero|underflow) encountered")
        yield


def _main(argv) -> int:
    args = None
    try:
        parser = build_parser()
        if not argv:  # bare `softsim`: what it can do, not an error line
            parser.print_usage(sys.stderr)
            print("run `softsim -h` for the commands, `softsim <command> -h` for one of them", file=sys.stderr)
            return 2
        commands = {m.COMMAND: m.run for m in SUBCOMMANDS}
        parser.command = next((a for a in argv if a in commands), None)
        args = parser.parse_args(argv)
        _check_paths(parser, args)
        if args.command not in NO_WARP:
            init_warp(getattr(args, "debug", False))
        with _quiet_float_warnings(getattr(args, "debug", False)):
            return commands[args.command](args)
    except UserError as e:
        if getattr(args, "debug", False) or (args is None and "--debug" in argv):
            traceback.print_exc()
        print(f"error: {e.line()}", file=sys.stderr)
        return e.exit_code


def _check_paths(parser, args):
    """Refuse an empty file name in any path argument (an unset shell variable: ``--out "$OUT"``)
    before anything else: taken as "not given", it would select the default name and replace that file."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[args.command]
    for action in sub._actions:
        if action.dest in PATH_ARGUMENTS and getattr(args, action.dest, None) == "":
            flag = action.option_strings[-1] if action.option_strings else action.dest
            what = "a scene file or built-in scene name" if action.dest == "scene" else "a file path"
            raise CommandLineError(flag, f"is empty; give {what}", "")
