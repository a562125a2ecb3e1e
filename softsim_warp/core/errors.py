"""User-facing errors: one line, naming the file, the key, what is wrong and the value given.

Every user error prints as ``<file>: <key>: <what is wrong> (got <value>)``. Errors in command-line
flags name ``command line`` as the file and the flag as the key; a value that was not given at all
reads ``(got nothing)``, so every line has the same four parts and can be parsed.
"""

from __future__ import annotations

COMMAND_LINE = "command line"


class UserError(Exception):
    """An error in what the user asked for; the CLI prints it as one line and exits with ``exit_code``."""

    exit_code = 2

    def __init__(self, source: str, key: str | None, message: str, value=None, has_value: bool = False):
        self.source = str(source)
        self.key = key
        self.message = message
        self.value = value
        self.has_value = has_value
        super().__init__(self.line())

    def line(self) -> str:
        # A message is one line whatever the value holds (a TOML string may contain newlines).
        key = self.key if self.key else "(scene)"
        got = format_value(self.value) if self.has_value else "nothing"
        return _one_line(f"{self.source}: {key}: {self.message} (got {got})")


class SceneError(UserError):
    """A scene file or override that is malformed, misspelt or out of range."""

    def __init__(self, source: str, key: str | None, message: str, *value):
        super().__init__(source, key, message, value[0] if value else None, has_value=bool(value))


class CommandLineError(UserError):
    """A command-line flag that is malformed or names something that does not exist."""

    def __init__(self, flag: str, message: str, *value):
        super().__init__(COMMAND_LINE, flag, message, value[0] if value else None, has_value=bool(value))


class ExplosionError(Exception):
    """The simulation state became non-finite or implausibly fast."""

    exit_code = 3


_MAX_VALUE_CHARS = 200


def _one_line(text: str) -> str:
    return text.replace("\r", "\\r").replace("\n", "\\n")


def format_value(value) -> str:
    """A value as the user would write it in TOML, cut to a readable length."""
    text = _format(value)
    if len(text) > _MAX_VALUE_CHARS:
        text = text[: _MAX_VALUE_CHARS - 3] + "..."
    return text


def _format(value) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_format(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_format(v)}" for k, v in value.items()) + "}"
    return str(value)


_WARNED: set = set()


def warn(source: str, key: str | None, message: str, *value) -> None:
    """Print a one-line warning about a scene value on stderr, in the error line's four parts
    (``warning: <file>: <key>: <what> (got <value>)``), once per process for the same line."""
    import sys  # noqa: PLC0415

    line = "warning: " + UserError(source, key, message, value[0] if value else None, has_value=bool(value)).line()
    if line not in _WARNED:
        _WARNED.add(line)
        print(line, file=sys.stderr, flush=True)
