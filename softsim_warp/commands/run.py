"""``softsim run``: simulate a scene and write its USD animation (and metrics, and a preview GIF).

User errors (bad scene values, unknown names, unwritable outputs) print one line and exit with 2;
an exploded run exits with 3, an interrupted one with 130 (SIGINT) or 143 (SIGTERM); the files
written up to that point stay valid.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

from ..core.methods import IMPLICIT
from ..core.model import build_model
from ..core.stepper import make_integrator
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import JSON_SUFFIXES, USD_SUFFIXES, Outputs, kept_partial_path, write_json_atomic
from ..io.penetration import PenetrationCheck
from ..io.penetration import summary_line as penetration_line
from ..io.resources import check_fits
from ..io.runinfo import explosion_message, profile_table, summary_dict, summary_line
from ..io.simulate import Simulator
from ..io.stable_step import check_stable_dt
from ..io.usd import UsdWriter
from . import common
from .common import EXIT_EXPLODED, Signals, check_deterministic, load_for_cli, resolve_device
from .preview import render_gif_or_error

COMMAND = "run"


def add_parser(subparsers, add_common):
    run = subparsers.add_parser("run", help="simulate a scene and write a USD animation")
    run.add_argument("scene", help="scene file (.toml) or built-in scene name (see `softsim scenes`)")
    # Scene-valued flags are taken as text and validated by the scene schema, so `--dt -1` and
    # `--set simulation.dt=-1` get the same message.
    run.add_argument("--integrator", help="euler, symplectic, midpoint, rk4 or implicit")
    run.add_argument("--dt", help="step size [s], or auto (the largest the stability prediction allows)")
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
    run.add_argument("--profile", action="store_true",
                     help="time each part of the step (kernels launched one by one, a device synchronise around "
                          "each part): a table on stdout, and time_* keys in --metrics")
    run.add_argument("--allow-unstable", action="store_true",
                     help="run even when dt is above a jelly's predicted stable step (to watch it explode)")
    run.add_argument("--preview", metavar="GIF", help="also render the written USD to this animated GIF (softsim preview)")
    run.add_argument("--check-penetration", action="store_true",
                     help="check every written frame for particles inside a collider, another jelly or their own "
                          "folded jelly, from the positions alone (io/penetration.py): a line on stdout, and a "
                          "penetration key in --metrics")
    add_common(run)



def run(args) -> int:
    # Signals are caught from the start (common.Signals with regions): the first one ends the run at
    # its next check -- before the first frame with no output, during the run after the frame in
    # progress, with every frame written -- and a second one stops at once, but only inside the
    # ``signals.stoppable()`` blocks below, whose KeyboardInterrupt this module cleans up after.
    with Signals(regions=True) as signals:
        return _run(args, signals)


def _run(args, signals) -> int:
    scene = load_for_cli(args)
    check_stable_dt(scene.data, scene.source, blame=lambda e: common.blame_flag(e, args), refuse=not args.allow_unstable)
    outputs = Outputs()
    outputs.add_input("scene", scene.source)
    add_asset_inputs(outputs, scene)
    default_out = f"{Path(scene.source).stem}.usdc"
    out = outputs.add("--out", args.out if args.out is not None else default_out, USD_SUFFIXES)
    metrics_path = outputs.add("--metrics", args.metrics, JSON_SUFFIXES, streams=True)
    preview_path = outputs.add("--preview", args.preview, (".gif",))
    if signals.received is not None:
        return signals.exit_code()
    with outputs:
        return _run_locked(args, signals, scene, out, metrics_path, preview_path)


def _run_locked(args, signals, scene, out, metrics_path, preview_path) -> int:
    device = resolve_device(args.device, args.debug)
    sim = scene.sim
    if args.deterministic:
        check_deterministic(sim["integrator"], device)
    frames = scene.frame_count()
    check_fits(scene, device, sim["integrator"], frames, usd_springs=args.springs, deterministic=args.deterministic)

    with signals.stoppable():  # a large model takes a while to build; nothing is written yet
        model = build_model(scene, device=device, deterministic=args.deterministic)
        integrator = make_integrator(sim["integrator"], model, scene.data.get(IMPLICIT.name))
        simulator = Simulator(model, integrator, sim["dt"], sim["fps"], frames,
                              use_graph=None if not args.no_graph else False, max_speed=sim.get("max_speed"),
                              profile=args.profile, end_time=scene.end_time(), on_warm_up=common.warm_up_notice(args))
    if signals.received is not None:
        return signals.exit_code()
    writer = UsdWriter(out, model, sim["fps"], springs=args.springs,
                       metadata={"softsim:scene": scene.name, "softsim:integrator": sim["integrator"], "softsim:dt": sim["dt"],
                                 "softsim:deterministic": bool(args.deterministic)})
    check = PenetrationCheck(model) if args.check_penetration else None
    progress = None
    try:
        if signals.received is not None:  # nothing simulated: no output
            writer.discard()
            return signals.exit_code()
        progress = common.progress_bar(frames + 1, f"{scene.name} {sim['integrator']}", "frame", args.quiet)
        simulator.stop_requested = lambda: signals.received
        signals.busy = lambda: simulator.writing
        # A signal during kernel compilation (the warm-up, first in Simulator.run) lets frame 0 be
        # written first; a second one stops it with no output.
        with signals.stoppable():
            result = simulator.run([writer] + ([check] if check is not None else []), progress=progress)
    except BaseException as exc:
        # A stop-now outside the steps, or an error: keep the frames written (a signal now is only recorded).
        if writer.last_frame < 0:
            writer.discard()
        else:
            writer.close(status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed",
                         extra={"softsim:frames": writer.last_frame + 1})
        raise
    finally:
        if progress is not None:
            progress.close()
    if result.interrupted and not result.frames_written:  # stopped during the warm-up: no output
        writer.discard()
        return signals.exit_code()
    # From here on the outputs are written whole: a signal is recorded, and reported by the exit code.
    status = "exploded" if result.exploded else ("interrupted" if result.interrupted else "complete")
    summary = summary_dict(scene, model, integrator, simulator, result, device)
    summary["status"] = status
    summary["deterministic"] = bool(args.deterministic)
    if check is not None:
        summary["penetration"] = check.summary()
    if result.exploded:
        message = explosion_message(scene, model, result)
        summary["explosion"]["message"] = message
    written = writer.close(status=status, extra={"softsim:frames": result.frames_written})
    # A run that may not replace its outputs (it did not complete, and they existed) keeps them all
    # as <stem>.partial<suffix>, so the USD and its metrics stay a pair.
    kept = written != out
    if metrics_path is not None:
        write_json_atomic(kept_partial_path(metrics_path) if kept else metrics_path,
                          {"summary": summary, "frames": [m.as_dict() for m in result.metrics]})
    print(summary_line(summary, written), file=sys.stderr)
    if args.profile:
        print(profile_table(summary))
    if check is not None:
        print(penetration_line(summary["penetration"]))
    if kept:
        print(f"note: {out} existed and the run did not complete: it is unchanged, the frames are in {written}",
              file=sys.stderr)
    if signals.received is not None and status == "complete":
        print(f"note: {signal.Signals(signals.received).name} came after the last frame: the outputs are complete"
              + ("; --preview was not rendered" if preview_path is not None else ""), file=sys.stderr)
    if preview_path is not None and result.frames_written and signals.received is None:
        # The outputs are in place; a signal now stops the rendering at once (nothing half-written:
        # the GIF goes to a temporary first).
        with signals.stoppable(immediate=True):
            render_gif_or_error(written, kept_partial_path(preview_path) if kept else preview_path)
    if result.exploded:
        print("error: " + message, file=sys.stderr)
    if signals.received is not None:
        return signals.exit_code()
    if result.exploded:
        return EXIT_EXPLODED
    if result.interrupted:
        return 128 + int(signal.SIGINT)
    return 0
