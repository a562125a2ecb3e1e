"""The environment that loads ``tests/hooks/sitecustomize.py`` into the processes a test starts:
pauses at the phases of ``softsim run`` and marks of a sweep's tasks, with no hook in the package."""

from __future__ import annotations

import os
from pathlib import Path

HOOKS = Path(__file__).resolve().parent / "hooks"
VARIABLES = ("SOFTSIM_TEST_PAUSE", "SOFTSIM_SWEEP_TEST_DIR", "SOFTSIM_SWEEP_TEST_DELAY")


def hooked_env(base=None, *, pauses="", marks=None, delay=0.0) -> dict:
    """``base`` (default ``os.environ``) with the hooks on ``PYTHONPATH`` and set as asked: ``pauses``
    for ``SOFTSIM_TEST_PAUSE``, ``marks`` (a folder) and ``delay`` for a sweep's task marks; the
    hooks' variables that are not asked for are removed."""
    env = dict(os.environ if base is None else base)
    for name in VARIABLES:
        env.pop(name, None)
    if pauses:
        env["SOFTSIM_TEST_PAUSE"] = pauses
    if marks is not None:
        env["SOFTSIM_SWEEP_TEST_DIR"] = str(marks)
        env["SOFTSIM_SWEEP_TEST_DELAY"] = str(delay)
    if pauses or marks is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(HOOKS)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env
