"""User-facing errors: one line, naming the file, the key, what is wrong and the value given."""

from __future__ import annotations


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
        parts = [self.source]
        if self.key:
            parts.append(self.key)
        text = ": ".join(parts) + ": " + self.message
        if self.has_value:
            text += f" (got {format_value(self.value)})"
        return text


class SceneError(UserError):
    """A scene file or override that is malformed, misspelt or out of range."""

    def __init__(self, source: str, key: str | None, message: str, *value):
        super().__init__(source, key, message, value[0] if value else None, has_value=bool(value))


class ExplosionError(Exception):
    """The simulation state became non-finite or implausibly fast."""

    exit_code = 3


def format_value(value) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {format_value(v)}" for k, v in value.items()) + "}"
    return str(value)
