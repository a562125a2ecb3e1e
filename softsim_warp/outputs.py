"""Output files: checked before a run starts, written atomically (temporary sibling, then rename)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .errors import UserError


def check_writable(path, flag: str, suffixes=None):
    """Refuse an output path that cannot be written, before any simulation work is done."""
    p = Path(path)
    if suffixes and p.suffix not in suffixes:
        raise UserError(flag, None, f"unsupported file extension; use one of {', '.join(suffixes)}", str(p), has_value=True)
    if p.is_dir():
        raise UserError(flag, None, "is a directory, not a file", str(p), has_value=True)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UserError(flag, None, "directory does not exist", str(parent), has_value=True)
    if not os.access(parent, os.W_OK) or (p.exists() and not os.access(p, os.W_OK)):
        raise UserError(flag, None, "permission denied", str(p), has_value=True)
    return p


def write_json_atomic(path, data):
    """Write JSON to a temporary sibling and rename it over ``path``."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.partial-{os.getpid()}")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, allow_nan=True)
        f.write("\n")
    os.replace(tmp, p)
