"""Command line: ``softsim run``, ``softsim scenes``.

User errors (bad scene values, unknown names, unwritable outputs) print one line
``error: <file>: <key>: <what is wrong> (got <value>)`` and exit with 2; ``--debug`` shows the
traceback instead. An exploded run exits with 3, an interrupted one with 130 (SIGINT) or 143
(SIGTERM); files written up to that point stay valid.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import tempfile
import traceback

from .errors import CommandLineError, SceneError, UserError

EXIT_EXPLODED = 3


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


def _add_common(p: argparse.ArgumentParser):
    p.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:N (default cpu)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value by dotted key, e.g. jelly.0.springs.shear.ks=500 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show tracebacks for errors and Warp's start-up messages")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="softsim", description="Mass-spring jelly simulator on NVIDIA Warp.")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="simulate a scene and write a USD animation")
    run.add_argument("scene", help="scene file (.toml) or built-in scene name (see `softsim scenes`)")
    # Scene-valued flags are taken as text and validated by the scene schema, so `--dt -1` and
    # `--set simulation.dt=-1` get the same message.
    run.add_argument("--integrator", help="euler, symplectic, midpoint, rk4 or implicit")
    run.add_argument("--dt", help="step size [s]")
    g = run.add_mutually_exclusive_group()
    g.add_argument("--duration", help="simulated seconds")
    g.add_argument("--frames", help="output frames after frame 0")
    run.add_argument("--fps", help="output frames per second")
    run.add_argument("--precision", help="scalar type of every kernel: float32 or float64")
    run.add_argument("--deterministic", action="store_true",
                     help="atomic-free force and metric sums: bitwise-identical runs on CUDA too (CPU runs always are)")
    run.add_argument("--out", default=None, help="USD output (.usdc or .usda; default <scene>.usdc)")
    run.add_argument("--metrics", help="write per-frame metrics as JSON")
    run.add_argument("--springs", action="store_true", help="also write springs as BasisCurves")
    run.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying a captured graph")
    run.add_argument("--preview", metavar="GIF", help="also render the written USD to this animated GIF (softsim preview)")
    _add_common(run)

    sub.add_parser("scenes", help="list the built-in scenes")
    for module in _plugin_modules():
        module.add_parser(sub, _add_common)
    return parser


# Further subcommands live in their own modules, each with ``add_parser(subparsers, add_common)``
# and ``run(args) -> int``; the subcommand's name is the module's ``COMMAND``.
PLUGINS = ("compare", "preview_cmd", "bench", "accuracy", "stability")


def _plugin_modules():
    import importlib  # noqa: PLC0415

    return [importlib.import_module(f"softsim_warp.{name}") for name in PLUGINS]


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


def _flag_overrides(args) -> list:
    """Command-line flags become scene overrides, so they are validated like the file's values."""
    out = []
    for flag, key in (("integrator", "simulation.integrator"), ("dt", "simulation.dt"), ("fps", "simulation.fps"),
                      ("precision", "simulation.precision"), ("duration", "simulation.duration"),
                      ("frames", "simulation.frames")):
        value = getattr(args, flag, None)
        if value is not None:
            out.append((key, value if flag in ("integrator", "precision") else _number(value)))
    return out


def load_for_cli(args):
    """Load the scene named on the command line with --set and flag overrides applied and validated."""
    from . import scene as scene_mod  # noqa: PLC0415

    path, source, data = scene_mod.read_scene_data(args.scene)
    items = [scene_mod.parse_override(item) for item in args.overrides] + _flag_overrides(args)
    scene_mod.apply_overrides(data, items)
    validated = scene_mod.validate(data, source)
    sim = validated["simulation"]
    if sim["dt"] > 1.0 / sim["fps"]:
        raise SceneError(source, "simulation.dt", f"must not exceed the frame interval 1/fps = {1.0 / sim['fps']:g} s", sim["dt"])
    return scene_mod.Scene(validated, source=source, name=validated.get("name", path.stem))


def init_warp(debug=False):
    """Import and initialise Warp without its banner, module-load lines or missing-driver notice.

    A user error must read as one line; Warp prints a start-up banner and, on a machine without a
    CUDA driver, a notice from native code straight to file descriptor 2. Both are held back
    unless ``debug``.
    """
    import warp as wp  # noqa: PLC0415

    if debug:
        wp.init()
        return wp
    wp.config.log_level = wp.LOG_WARNING
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
    return wp


def resolve_device(name: str, debug=False):
    """The Warp device called ``name``; an unknown or absent one is a one-line user error."""
    wp = init_warp(debug)
    if not re.fullmatch(r"cpu|cuda(:\d+)?", name or ""):
        names = ", ".join(d.alias for d in wp.get_devices())
        raise CommandLineError("--device", f"unknown device name; use cpu or cuda:N (available here: {names})", name)
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
    if device.is_cuda and integrator == "implicit":
        raise CommandLineError(
            "--deterministic",
            "not available with the implicit integrator on CUDA (its solver sums with atomics); "
            "use an explicit integrator, or --device cpu",
            integrator,
        )


class _Signals:
    """Turns SIGINT/SIGTERM into a request to stop after the current frame.

    A second signal stops at once (KeyboardInterrupt) while frames are computed, but not while
    the output is being closed: a file half renamed is worse than waiting a moment.
    """

    def __init__(self):
        self.received = None
        self.closing = False
        self.busy = lambda: False  # True while a frame is being written: a stop-now waits for it

    def __enter__(self):
        self._old = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.received is not None and not self.closing and not self.busy():  # a second signal: stop now
            raise KeyboardInterrupt
        if self.received is None:
            self.received = signum

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        return False


_SIGNALS = None  # the run's signal state, for main's exit code after a stop-now


def cmd_run(args) -> int:
    # Signals are caught from the start: one that arrives before the first frame ends the run
    # with 128 + signum and leaves no output, one during the run stops it after that frame.
    global _SIGNALS
    with _Signals() as signals:
        _SIGNALS = signals
        return _run(args, signals)


def _run(args, signals) -> int:
    from pathlib import Path  # noqa: PLC0415

    from .outputs import check_outputs, check_writable, write_json_atomic  # noqa: PLC0415

    scene = load_for_cli(args)
    out, metrics_path = check_outputs(
        args.out or f"{Path(scene.source).stem}.usdc", args.metrics, scene_path=scene.source
    )
    if args.preview:
        check_writable(args.preview, "--preview", suffixes=(".gif",))
    device = resolve_device(args.device, args.debug)
    sim = scene.sim
    if args.deterministic:
        check_deterministic(sim["integrator"], device)
    frames = scene.frame_count()
    from .resources import check_fits  # noqa: PLC0415

    check_fits(scene, device, sim["integrator"], frames, usd_springs=args.springs, deterministic=args.deterministic)

    from .integrators import make_integrator  # noqa: PLC0415
    from .model import build_model  # noqa: PLC0415
    from .runinfo import explosion_message, summary_dict, summary_line  # noqa: PLC0415
    from .simulate import Simulator  # noqa: PLC0415
    from .usd_io import UsdWriter  # noqa: PLC0415

    model = build_model(scene, device=device, deterministic=args.deterministic)
    integrator = make_integrator(sim["integrator"], model, scene.data.get("implicit"))
    simulator = Simulator(model, integrator, sim["dt"], sim["fps"], frames, use_graph=None if not args.no_graph else False,
                          max_speed=sim.get("max_speed"))
    if signals.received is not None:
        return 128 + int(signals.received)
    writer = UsdWriter(out, model, sim["fps"], springs=args.springs,
                       metadata={"softsim:scene": scene.name, "softsim:integrator": sim["integrator"], "softsim:dt": sim["dt"],
                                 "softsim:deterministic": bool(args.deterministic)})
    progress = None
    if not args.quiet:
        from tqdm import tqdm  # noqa: PLC0415

        progress = tqdm(total=frames + 1, unit="frame", desc=f"{scene.name} {sim['integrator']}", file=sys.stderr, leave=False)
    simulator.stop_requested = lambda: signals.received
    signals.busy = lambda: simulator.writing
    try:
        result = simulator.run([writer], progress=progress)
    except BaseException as exc:
        signals.closing = True
        writer.close(status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
                     extra={"softsim:frames": writer.last_frame + 1})
        raise
    finally:
        if progress is not None:
            progress.close()
    signals.closing = True
    status = "exploded" if result.exploded else ("interrupted" if result.interrupted else "complete")
    summary = summary_dict(scene, model, integrator, simulator, result, device)
    summary["status"] = status
    summary["deterministic"] = bool(args.deterministic)
    if result.exploded:
        message = explosion_message(scene, model, result)
        summary["explosion"]["message"] = message
    writer.close(status=status, extra={"softsim:frames": result.frames_written})
    if metrics_path is not None:
        write_json_atomic(metrics_path, {"summary": summary, "frames": [m.as_dict() for m in result.metrics]})
    print(summary_line(summary, out), file=sys.stderr)
    if args.preview and result.frames_written:
        from .preview_cmd import render_gif_or_error  # noqa: PLC0415

        render_gif_or_error(out, args.preview)
    if result.exploded:
        print("error: " + message, file=sys.stderr)
        return EXIT_EXPLODED
    if result.interrupted:
        return 128 + int(signals.received or signal.SIGINT)
    return 0


def cmd_scenes(args) -> int:
    from .scene import builtin_scenes  # noqa: PLC0415

    scenes = builtin_scenes()
    width = max(len(n) for n in scenes)
    for name, desc in scenes.items():
        print(f"{name:<{width}}  {desc}")
    return 0


COMMANDS = {"run": cmd_run, "scenes": cmd_scenes}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        commands = dict(COMMANDS)
        commands.update({m.COMMAND: m.run for m in _plugin_modules()})
        return commands[args.command](args)
    except UserError as e:
        if getattr(args, "debug", False) or (args is None and "--debug" in argv):
            traceback.print_exc()
        print(f"error: {e.line()}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        return 128 + int(getattr(_SIGNALS, "received", None) or signal.SIGINT)
