"""What the sweep's test files share: a small seed_bowl, the command line, and waiting for a worker."""

from __future__ import annotations

import sys
import time

from softsim_warp.commands import cli
from tests.subprocess_hooks import hooked_env

# 4^3 particles at 20 frames per second: the jelly reaches the hole's rim at t = 1.34 s.
SMALL = ["--set", "jelly.0.resolution=4", "--set", "simulation.fps=20"]
KS = "jelly.0.springs.*.ks"


def sweep(tmp_path, *argv, name="r.parquet"):
    out = tmp_path / name
    rc = cli.main(["sweep", "seed_bowl", *SMALL, *argv, "--out", str(out), "--quiet"])
    return rc, out


def env(test_dir=None, delay=0.0):
    """The sweep's environment; with ``test_dir``, each task marks its start and end there and waits
    ``delay`` seconds at its start (``tests/hooks/sitecustomize.py``)."""
    return hooked_env(marks=test_dir, delay=delay)


def wait_for(predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("timed out")


def sweep_command(*argv):
    return [sys.executable, "-m", "softsim_warp", "sweep", "seed_bowl", *SMALL, *argv, "--quiet"]
