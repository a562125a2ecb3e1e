"""Test-only hooks for the ``softsim`` processes the tests start (never imported by the package).

A test that puts this folder first on ``PYTHONPATH`` (``tests/subprocess_hooks.py``) has Python
import this module at start-up, in the command's process and in every process it starts (a sweep's
Dask workers; a ``sitecustomize`` it shadows still runs). It patches the package's functions as
their modules load, so a test can reach a phase of a real process without any test code in the
package:

``SOFTSIM_TEST_PAUSE="phase[:n],..."``: the process stops at each named phase, writes
``softsim-test: paused at <phase>`` to stderr and waits there until ``n`` signals (default 1) have
come (60 s at most), so a test can signal a process that sits in that phase. Phases: ``import``
(``python -m softsim_warp`` before it imports the command line), ``start`` (``cli.main`` before the
command) and, in ``softsim run``: ``scene``, ``build``, ``writer`` (its USD writer made, nothing
written), ``compile`` (before the warm-up), ``run`` (after frame 2), ``save``, ``cleanup`` (a run
ended by an exception) and ``preview``. Each phase pauses once.

``SOFTSIM_SWEEP_TEST_DIR``: each sweep task marks its start and end there
(``<task>.<pid>.running`` / ``.done``) and, at start, waits ``SOFTSIM_SWEEP_TEST_DELAY`` seconds,
so a test can kill a worker while it holds a task.
"""

from __future__ import annotations

import functools
import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
import time
from pathlib import Path


class _OnImport(importlib.abc.MetaPathFinder):
    """Runs ``before()`` and ``after(module)`` around the first execution of the named modules."""

    def __init__(self):
        self.hooks = {}

    def add(self, name, before=None, after=None):
        self.hooks[name] = (before, after)

    def find_spec(self, name, path=None, target=None):
        if name not in self.hooks:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        before, after = self.hooks.pop(name)
        exec_module = spec.loader.exec_module

        def run(module):
            if before is not None:
                before()
            exec_module(module)
            if after is not None:
                after(module)

        spec.loader.exec_module = run
        return spec


# --- SOFTSIM_TEST_PAUSE ------------------------------------------------------------------------


def _parse_pauses(text: str) -> dict:
    out = {}
    for item in text.split(","):
        name, _, count = item.strip().partition(":")
        if name:
            out[name] = int(count or 1)
    return out


PAUSES = _parse_pauses(os.environ.get("SOFTSIM_TEST_PAUSE", ""))


def pause(phase: str, signals=None):
    """Wait at ``phase`` when SOFTSIM_TEST_PAUSE names it: for its count of signals on ``signals``
    (a ``commands.common.Signals``), or, without one, until a signal's handler raises (60 s at most)."""
    wanted = PAUSES.pop(phase, None)
    if wanted is None:
        return
    # The count before the marker: a signal sent as soon as the test reads the marker may come
    # before the next line runs, and counted after it, the wait would miss it.
    start = signals.count if signals is not None else 0
    print(f"softsim-test: paused at {phase}", file=sys.stderr, flush=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (signals is None or signals.count - start < wanted):
        time.sleep(0.01)


def _patch_cli(cli):
    main = cli._main

    @functools.wraps(main)
    def _main(argv):
        pause("start")  # the first signal raises KeyboardInterrupt here (cli.main's handler)
        return main(argv)

    cli._main = _main


def _patch_run(run):
    """``softsim run``'s phases, each at the call that begins it. Its ``Signals`` is the one
    ``run._run`` receives."""
    held = {}
    run_scene, run_locked = run._run, run._run_locked

    @functools.wraps(run_scene)
    def _run(args, signals):
        held["signals"] = signals
        pause("scene", signals)
        return run_scene(args, signals)

    @functools.wraps(run_locked)
    def _run_locked(args, signals, *rest):
        pause("build", signals)
        return run_locked(args, signals, *rest)

    class UsdWriter(run.UsdWriter):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            pause("writer", held["signals"])

        def close(self, *args, **kwargs):
            if sys.exc_info()[1] is not None:  # closed by the handler of an exception: the cleanup
                pause("cleanup", held["signals"])
            return super().close(*args, **kwargs)

        def discard(self, *args, **kwargs):
            if sys.exc_info()[1] is not None:
                pause("cleanup", held["signals"])
            return super().discard(*args, **kwargs)

    class Simulator(run.Simulator):
        def run(self, writers=(), *args, **kwargs):
            signals = held["signals"]
            pause("compile", signals)
            requested, usd = self.stop_requested, writers[0]

            def stop_requested():
                if usd.last_frame == 2:
                    pause("run", signals)
                return requested()

            self.stop_requested = stop_requested
            return super().run(writers, *args, **kwargs)

    def pausing(phase, fn):
        @functools.wraps(fn)
        def call(*args, **kwargs):
            pause(phase, held["signals"])
            return fn(*args, **kwargs)

        return call

    run._run, run._run_locked = _run, _run_locked
    run.UsdWriter, run.Simulator = UsdWriter, Simulator
    run.summary_dict = pausing("save", run.summary_dict)
    run.render_gif_or_error = pausing("preview", run.render_gif_or_error)


# --- SOFTSIM_SWEEP_TEST_DIR --------------------------------------------------------------------


def _mark(spec, phase):
    name = Path(os.environ["SOFTSIM_SWEEP_TEST_DIR"]) / f"{spec['task']}.{os.getpid()}"
    if phase == "start":
        name.with_suffix(name.suffix + ".running").write_text("")
        time.sleep(float(os.environ.get("SOFTSIM_SWEEP_TEST_DELAY", "0")))
    else:
        name.with_suffix(name.suffix + ".done").write_text("")


def _marking(module, name):
    """Replace the task function ``module.name`` by one that marks its start and end; it keeps the
    name, so Dask still sends it to the workers by reference, where this hook has replaced it too."""
    task = getattr(module, name)

    @functools.wraps(task)
    def marked(spec):
        _mark(spec, "start")
        rows = task(spec)
        _mark(spec, "end")
        return rows

    setattr(module, name, marked)


def _load_shadowed():
    """Run the ``sitecustomize`` this one shadows, if another folder on ``sys.path`` has one."""
    here = Path(__file__).resolve().parent
    rest = [e for e in sys.path if Path(e or os.curdir).resolve() != here]
    spec = importlib.machinery.PathFinder.find_spec("sitecustomize", rest)
    if spec is not None and spec.loader is not None:
        spec.loader.exec_module(importlib.util.module_from_spec(spec))


_load_shadowed()
_hooks = _OnImport()
if PAUSES:
    _hooks.add("softsim_warp.commands.cli", before=lambda: pause("import"), after=_patch_cli)
    _hooks.add("softsim_warp.commands.run", after=_patch_run)
if os.environ.get("SOFTSIM_SWEEP_TEST_DIR"):
    _hooks.add("softsim_warp.io.sweep.batch", after=lambda m: _marking(m, "run_batch"))
    _hooks.add("softsim_warp.commands.sweep", after=lambda m: _marking(m, "stable_dt_task"))
if _hooks.hooks:
    sys.meta_path.insert(0, _hooks)
