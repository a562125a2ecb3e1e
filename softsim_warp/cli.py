"""Command line: ``softsim run``, ``softsim scenes``.

User errors (bad scene values, unknown names, unwritable outputs) print one line
``error: <file>: <key>: <what is wrong> (got <value>)`` and exit with 2; ``--debug`` shows the
traceback instead. An exploded run exits with 3, an interrupted one with 130 (SIGINT) or 143
(SIGTERM); files written up to that point stay valid.
"""

from __future__ import annotations

import argparse
import signal
import sys
import traceback

from .errors import SceneError, UserError

EXIT_EXPLODED = 3


def _add_common(p: argparse.ArgumentParser):
    p.add_argument("--device", default="cpu", help="Warp device: cpu or cuda:N (default cpu)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value by dotted key, e.g. jelly.0.springs.shear.ks=500 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show tracebacks for errors")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softsim", description="Mass-spring jelly simulator on NVIDIA Warp.")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="simulate a scene and write a USD animation")
    run.add_argument("scene", help="scene file (.toml) or built-in scene name (see `softsim scenes`)")
    run.add_argument("--integrator", help="euler, symplectic, midpoint, rk4 or implicit")
    run.add_argument("--dt", type=float, help="step size [s]")
    g = run.add_mutually_exclusive_group()
    g.add_argument("--duration", type=float, help="simulated seconds")
    g.add_argument("--frames", type=int, help="output frames after frame 0")
    run.add_argument("--fps", type=float, help="output frames per second")
    run.add_argument("--precision", choices=["float32", "float64"], help="scalar type of every kernel")
    run.add_argument("--out", default=None, help="USD output (.usdc or .usda; default <scene>.usdc)")
    run.add_argument("--metrics", help="write per-frame metrics as JSON")
    run.add_argument("--springs", action="store_true", help="also write springs as BasisCurves")
    run.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying a captured graph")
    _add_common(run)

    sub.add_parser("scenes", help="list the built-in scenes")
    for module in _plugin_modules():
        module.add_parser(sub, _add_common)
    return parser


# Further subcommands live in their own modules, each with ``add_parser(subparsers, add_common)``
# and ``run(args) -> int``; the subcommand's name is the module's ``COMMAND``.
PLUGINS = ("bench",)


def _plugin_modules():
    import importlib  # noqa: PLC0415

    return [importlib.import_module(f"softsim_warp.{name}") for name in PLUGINS]


def _flag_overrides(args) -> list:
    """Command-line flags become scene overrides, so they are validated like the file's values."""
    out = []
    for flag, key in (("integrator", "simulation.integrator"), ("dt", "simulation.dt"), ("fps", "simulation.fps"),
                      ("precision", "simulation.precision")):
        value = getattr(args, flag, None)
        if value is not None:
            out.append((key, value))
    if getattr(args, "duration", None) is not None:
        out.append(("simulation.duration", args.duration))
    if getattr(args, "frames", None) is not None:
        out.append(("simulation.frames", args.frames))
    return out


def load_for_cli(args):
    """Load the scene named on the command line with --set and flag overrides applied and validated."""
    from . import scene as scene_mod  # noqa: PLC0415

    path, read = scene_mod.resolve_scene_path(args.scene)
    source = str(path)
    try:
        text = read()
    except OSError as e:
        raise SceneError(source, None, f"cannot read: {e.strerror}") from None
    data = scene_mod.parse_toml(text, source)
    for item in args.overrides:
        key, value = scene_mod.parse_override(item)
        scene_mod.apply_override(data, key, value)
    for key, value in _flag_overrides(args):
        sim = data.setdefault("simulation", {})
        if not isinstance(sim, dict):
            raise SceneError(source, "simulation", "must be a table", sim)
        if key == "simulation.duration":
            sim.pop("frames", None)
        if key == "simulation.frames":
            sim.pop("duration", None)
        scene_mod.apply_override(data, key, value)
    validated = scene_mod.validate(data, source)
    sim = validated["simulation"]
    if sim["dt"] > 1.0 / sim["fps"]:
        raise SceneError(source, "simulation.dt", f"must not exceed the frame interval 1/fps = {1.0 / sim['fps']:g} s", sim["dt"])
    return scene_mod.Scene(validated, source=source, name=validated.get("name", path.stem))


def resolve_device(name: str):
    import warp as wp  # noqa: PLC0415

    wp.config.quiet = True
    try:
        return wp.get_device(name)
    except (RuntimeError, ValueError, TypeError):
        names = ", ".join(d.alias for d in wp.get_devices())
        raise UserError("--device", None, f"unknown or unavailable device; available: {names}", name, has_value=True) from None


class _Signals:
    """Turns SIGINT/SIGTERM into a request to stop after the current frame."""

    def __init__(self):
        self.received = None

    def __enter__(self):
        self._old = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.received is not None:  # a second signal: stop now
            raise KeyboardInterrupt
        self.received = signum

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        return False


def cmd_run(args) -> int:
    from pathlib import Path  # noqa: PLC0415

    from .outputs import check_writable, write_json_atomic  # noqa: PLC0415

    scene = load_for_cli(args)
    out = check_writable(args.out or f"{Path(scene.source).stem}.usdc", "--out", suffixes=(".usdc", ".usda", ".usd"))
    if args.metrics:
        check_writable(args.metrics, "--metrics")
    device = resolve_device(args.device)

    import warp as wp  # noqa: PLC0415

    wp.config.quiet = True
    from .integrators import make_integrator  # noqa: PLC0415
    from .model import build_model  # noqa: PLC0415
    from .runinfo import explosion_message, summary_dict, summary_line  # noqa: PLC0415
    from .simulate import Simulator  # noqa: PLC0415
    from .usd_io import UsdWriter  # noqa: PLC0415

    sim = scene.sim
    model = build_model(scene, device=device)
    integrator = make_integrator(sim["integrator"], model, scene.data.get("implicit"))
    frames = scene.frame_count()
    simulator = Simulator(model, integrator, sim["dt"], sim["fps"], frames, use_graph=None if not args.no_graph else False,
                          max_speed=sim.get("max_speed"))
    writer = UsdWriter(out, model, sim["fps"], springs=args.springs,
                       metadata={"softsim:scene": scene.name, "softsim:integrator": sim["integrator"], "softsim:dt": sim["dt"]})
    progress = None
    if not args.quiet:
        from tqdm import tqdm  # noqa: PLC0415

        progress = tqdm(total=frames + 1, unit="frame", desc=f"{scene.name} {sim['integrator']}", file=sys.stderr, leave=False)
    with _Signals() as signals:
        simulator.stop_requested = lambda: signals.received
        try:
            result = simulator.run([writer], progress=progress)
        except BaseException:
            writer.close(status="failed")
            raise
        finally:
            if progress is not None:
                progress.close()
        status = "exploded" if result.exploded else ("interrupted" if result.interrupted else "complete")
        summary = summary_dict(scene, model, integrator, simulator, result, device)
        writer.close(status=status, extra={"softsim:frames": result.frames_written})
        if args.metrics:
            write_json_atomic(args.metrics, {"summary": summary, "frames": [m.as_dict() for m in result.metrics]})
    print(summary_line(summary, out), file=sys.stderr)
    if result.exploded:
        print("error: " + explosion_message(scene, model, result), file=sys.stderr)
        return EXIT_EXPLODED
    if result.interrupted:
        return 128 + int(signals.received)
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
    parser = build_parser()
    args = parser.parse_args(argv)
    commands = dict(COMMANDS)
    commands.update({m.COMMAND: m.run for m in _plugin_modules()})
    try:
        return commands[args.command](args)
    except UserError as e:
        if getattr(args, "debug", False):
            traceback.print_exc()
        print(f"error: {e.line()}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        return 130
