"""The ``softsim`` entry point: one subcommand per module of this package, errors as one line.

Each subcommand module has ``COMMAND`` (its name), ``add_parser(subparsers, add_common)`` and
``run(args) -> int``. A user error (bad scene value, unknown name, unwritable output) prints
``error: <file>: <key>: <what is wrong> (got <value>)`` and exits with 2; ``--debug`` shows the
traceback instead.
"""

from __future__ import annotations

import argparse
import re
import sys
import traceback

from ..core.errors import CommandLineError, UserError
from . import accuracy, bench, common, compare, preview, run, scenes, stability

SUBCOMMANDS = (run, scenes, compare, preview, bench, accuracy, stability)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors turned into the one-line ``error: command line: <flag>: ...`` form."""

    def error(self, message):
        raise _argparse_error(message)


def _argparse_error(message: str) -> CommandLineError:
    m = re.match(r"argument (\S+): (.*)$", message, re.S)
    key, text = (m.group(1), m.group(2)) if m else ("arguments", message)
    if key.startswith("-") and "/" in key:  # "-h/--help": name the long form
        key = key.split("/")[-1]
    m = re.match(r"^(.*): '(.*)'( \(choose from (.*)\))?$", text, re.S)
    if m:  # "invalid float value: 'abc'", "invalid choice: 'x' (choose from ...)"
        what = m.group(1) + (f"; choose from {m.group(4)}" if m.group(4) else "")
        return CommandLineError(key, what, m.group(2))
    m = re.match(r"^unrecognized arguments: (.*)$", text, re.S)
    if m:
        return CommandLineError("arguments", "unrecognized arguments; see softsim run --help", m.group(1))
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


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        commands = {m.COMMAND: m.run for m in SUBCOMMANDS}
        return commands[args.command](args)
    except UserError as e:
        if getattr(args, "debug", False) or (args is None and "--debug" in argv):
            traceback.print_exc()
        print(f"error: {e.line()}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        return 128 + common.received_signal()
