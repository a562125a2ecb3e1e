"""What every ``softsim`` subcommand shares: Warp start-up, the device, the scene with overrides,
signal handling, progress display and the parsing of list-valued flags.
"""

from __future__ import annotations

import contextlib
import functools
import math
import re
import signal
import sys
import threading

from ..core.errors import CommandLineError, SceneError, UserError
from ..core.methods import NAMES, method
from ..io import scene as scene_mod
from ..io.warp_init import init_warp
from . import process

EXIT_EXPLODED = 3


def add_common(p: argparse.ArgumentParser):
    p.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:N (default cpu)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value by dotted key, e.g. jelly.0.springs.shear.ks=500 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show tracebacks for errors and Warp's start-up messages")


def _number(text: str):
    """A flag's text as an int or float when it reads as one (nan and inf included), else the text."""
    if not isinstance(text, str):  # already parsed by argparse (type=float)
        return text
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


# Flags that set a scene value: validated as an override of the key, reported under the flag.
FLAG_KEYS = (("integrator", "simulation.integrator"), ("dt", "simulation.dt"), ("fps", "simulation.fps"),
             ("precision", "simulation.precision"), ("duration", "simulation.duration"),
             ("frames", "simulation.frames"))


def flag_overrides(args) -> list:
    """Command-line flags become scene overrides, so they are validated like the file's values."""
    out = []
    for flag, key in FLAG_KEYS:
        value = getattr(args, flag, None)
        if value is not None:
            out.append((key, value if flag in ("integrator", "precision") else _number(value)))
    return out


def blame_flag(error: SceneError, args) -> UserError:
    """A scene error about a value that a flag set, as an error of that flag (``--dt``, not the scene file)."""
    for flag, key in FLAG_KEYS:
        if error.key == key and getattr(args, flag, None) is not None:
            return CommandLineError("--" + flag, error.message, error.value) if error.has_value else CommandLineError(
                "--" + flag, error.message)
    return error


def load_for_cli(args):
    """Load the scene named on the command line with --set and flag overrides applied and validated."""
    path, source, data = scene_mod.read_scene_data(args.scene)
    init_warp_for_meshes(data, args)
    items = [scene_mod.parse_override(item) for item in args.overrides] + flag_overrides(args)
    try:
        scene_mod.apply_overrides(data, items)
        validated = scene_mod.validate(data, source)
        sim = validated["simulation"]
        if sim["dt"] > 1.0 / sim["fps"]:
            raise SceneError(source, "simulation.dt", f"must not exceed the frame interval 1/fps = {1.0 / sim['fps']:g} s",
                             sim["dt"])
    except SceneError as e:
        raise blame_flag(e, args) from None
    warn_overlaps(validated, source)
    return scene_mod.Scene(validated, source=source, name=validated.get("name", path.stem))


def warn_overlaps(data, source):
    """One line on stderr when jellies start overlapping (checks.overlap_warning): allowed, but
    usually two jellies placed at the same spot by mistake."""
    from ..io.checks import overlap_warning  # noqa: PLC0415

    line = overlap_warning(data, source)
    if line is not None:
        print(line, file=sys.stderr)


def init_warp_for_meshes(data, args):
    """Initialise Warp (quietly, see :func:`~softsim_warp.io.warp_init.init_warp`) before validating
    a scene with mesh jellies: validation voxelises them with Warp (io/mesh_scene.py)."""
    jellies = data.get("jelly") if isinstance(data.get("jelly"), list) else [data.get("jelly")]
    if any(isinstance(j, dict) and "mesh" in j for j in jellies):
        init_warp(getattr(args, "debug", False))


COMPILE_NOTICE_AFTER = 1.0  # seconds; loading cached kernels takes milliseconds


@contextlib.contextmanager
def compile_notice(quiet=False, after=COMPILE_NOTICE_AFTER):
    """Say once, on stderr, that Warp is compiling kernels, when the block (a warm-up: the
    ``on_warm_up`` of a Stepper or Simulator, see :func:`warm_up_notice`) takes longer than
    ``after`` seconds: only the first run compiles (minutes on the CPU), later runs load the cached
    kernels in milliseconds."""
    if quiet or getattr(compile_notice, "shown", False):
        yield
        return
    import warp as wp  # noqa: PLC0415

    def notice():
        compile_notice.shown = True
        print(f"compiling kernels (first run only; cached in {wp.config.kernel_cache_dir}) ...", file=sys.stderr,
              flush=True)

    timer = threading.Timer(after, notice)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def warm_up_notice(args):
    """The ``on_warm_up`` a command gives its simulators: :func:`compile_notice`, silent with --quiet."""
    return functools.partial(compile_notice, getattr(args, "quiet", False))


def progress_bar(total, desc, unit="run", quiet=False):
    """A tqdm bar on stderr that disappears when done; None with ``quiet``, and drawn only on a
    terminal (a log file or a pipe gets the command's lines, not the bar's redraws)."""
    if quiet:
        return None
    from tqdm import tqdm  # noqa: PLC0415

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, dynamic_ncols=True, disable=None)


class ProgressLog:
    """A command's progress: ``progress(total)`` opens a bar (what the measuring functions take as
    ``progress``), ``log(line)`` prints a line above it; both silent with ``quiet``."""

    def __init__(self, desc, unit="run", quiet=False):
        self.desc, self.unit, self.quiet = desc, unit, quiet
        self.bar = None

    def progress(self, total):
        self.bar = progress_bar(total, self.desc, self.unit, self.quiet)
        return self.bar

    def log(self, line):
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)


def resolve_device(name: str, debug=False):
    """The Warp device called ``name``; an unknown or absent one is a one-line user error."""
    wp = init_warp(debug)
    if not re.fullmatch(r"cpu|cuda(:\d+)?", name or ""):
        names = ", ".join(d.alias for d in wp.get_devices())
        raise CommandLineError("--device", f"unknown device name; use cpu or cuda:N (available here: {names})", name)
    if name.startswith("cuda") and wp.get_cuda_device_count() == 0:
        # Without a GPU, Warp's lookup of "cuda" (the current context) prints driver errors first.
        raise CommandLineError("--device", "device not available here; available: cpu", name)
    try:
        return wp.get_device(name)
    except (RuntimeError, ValueError, TypeError):
        names = ", ".join(d.alias for d in wp.get_devices())
        raise CommandLineError("--device", f"device not available here; available: {names}", name) from None


def check_deterministic(integrator: str, device):
    """--deterministic covers force and metric sums; the implicit solver's own sums use atomics.

    On the CPU every run is deterministic anyway; on CUDA the combination is refused rather than
    promised and not kept.
    """
    if device.is_cuda and not method(integrator).explicit:
        raise CommandLineError(
            "--deterministic",
            "not available with the implicit integrator on CUDA (its solver sums with atomics); "
            "use an explicit integrator, or --device cpu",
            integrator,
        )


class Signals:
    """Turns SIGINT/SIGTERM/SIGHUP (``process.STOP_SIGNALS``) into a request to stop after the current frame.

    The first signal is recorded (``received``) and the command stops at its next check; a second
    one stops at once (``KeyboardInterrupt``). At most one ``KeyboardInterrupt`` is ever raised:
    after it, signals are only recorded, so the cleanup it starts (temporaries removed, files
    closed, locks released) is never cut short by another one.

    Where a second signal may stop at once: by default (``softsim compare``) anywhere except while
    ``closing`` or ``busy()``; with ``regions=True`` (``softsim run``) only inside
    ``with signals.stoppable():`` blocks, the parts whose ``KeyboardInterrupt`` the command
    handles, and not while ``busy()`` (a frame is being written: a file half written is worse than
    waiting a moment). ``stoppable(immediate=True)`` lets the first signal stop at once too (after
    the run, while ``--preview`` renders).
    """

    def __init__(self, regions=False):
        self.received = None  # the first signal
        self.count = 0  # signals received
        self.stopped = False  # the KeyboardInterrupt was raised
        self.closing = False
        self.busy = lambda: False  # True while a frame is being written: a stop-now waits for it
        self._regions = regions
        self._stoppable = 0
        self._immediate = 0

    def __enter__(self):
        self._old = {}
        for sig in process.STOP_SIGNALS:
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    @contextlib.contextmanager
    def stoppable(self, immediate=False):
        """A block a signal may stop at once with a ``KeyboardInterrupt`` (see the class)."""
        self._stoppable += 1
        self._immediate += bool(immediate)
        try:
            yield self
        finally:
            self._stoppable -= 1
            self._immediate -= bool(immediate)

    def _handle(self, signum, frame):
        self.count += 1
        first = self.received is None
        if first:
            self.received = signum
        process.on_stop_signal(signum)
        if self.stopped or self.closing or self.busy():
            return
        if self._regions and not self._stoppable:
            return
        if first and not self._immediate:
            return
        self.stopped = True
        raise KeyboardInterrupt

    def exit_code(self) -> int:
        """128 + the first signal (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP)."""
        return 128 + int(self.received or signal.SIGINT)

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
            # The handler put back learns of the first signal (``cli.main``'s: a stop-now leaving
            # this block, or a signal after it, ends the command with that first signal's code).
            note = getattr(old, "note_received", None)
            if self.received is not None and note is not None:
                note(self.received)
        return False


def float_list(text):
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(text) from None
    return values


def parse_methods(text, flag="--integrators"):
    names = [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        if n not in NAMES:
            raise CommandLineError(flag, f"unknown integrator; choose from {', '.join(NAMES)}", n)
    if not names:
        raise CommandLineError(flag, "needs at least one integrator", text)
    return names


def parse_positive_list(text, flag):
    try:
        values = float_list(text)
    except ValueError:
        raise CommandLineError(flag, "must be a comma-separated list of numbers", text) from None
    if not values or any(not math.isfinite(v) or v <= 0 for v in values):
        raise CommandLineError(flag, "values must be finite and > 0", text)
    return values


def check_positive(value, flag):
    if value is not None and (not math.isfinite(value) or value <= 0):
        raise CommandLineError(flag, "must be finite and > 0", value)
