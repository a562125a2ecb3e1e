"""``softsim compare``: one scene under several integrators or parameter values, side by side.

Every variant becomes one world (a copy) of a single model, laid out in a grid in one USD stage
(:mod:`softsim_warp.studies.compare` runs them and says how). This module parses the flags and
``--vary`` values, checks the outputs, memory and stable steps, calls the study, and reports each
copy's end on stderr.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from ..core.errors import CommandLineError, SceneError
from ..core.methods import NAMES
from ..io import scene as scene_mod
from ..io import stable_step
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import JSON_SUFFIXES, USD_SUFFIXES, Outputs
from ..io.resources import check_fits
from ..io.scene import parse_override
from ..io.sweep import split_values
from ..studies.compare import DEFAULT_INTEGRATORS, Plan, expand_variants, run_comparison
from . import common

COMMAND = "compare"


def add_parser(subparsers, add_common):
    p = subparsers.add_parser(
        COMMAND,
        help="run copies of a scene with different integrators or parameters side by side in one USD stage",
        description="Run one copy of SCENE per variant (integrator and/or --vary values) in the same launches and "
        "write them side by side, laid out in a grid, to one USD stage.",
    )
    p.add_argument("scene", help="scene file (.toml) or built-in scene name")
    p.add_argument(
        "--integrators",
        help="comma-separated integrators, one copy each, in grid order "
        f"(default {','.join(DEFAULT_INTEGRATORS)}; with --vary: the scene's integrator)",
    )
    p.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="one copy per value of a dotted scene key, e.g. jelly.0.springs.structural.ks=1000,2000; "
                   "several --vary make a product")
    p.add_argument("--out", help="USD output (.usdc or .usda; default <scene>_compare.usdc)")
    p.add_argument("--metrics", help="write per-copy, per-frame metrics as JSON")
    p.add_argument("--plot", help="write a PNG of COM height, total energy and deformation over time, one line per copy")
    p.add_argument("--columns", type=int, help="copies per grid row (default ceil(sqrt(copies)))")
    p.add_argument("--gap", type=float, help="space between neighbouring copies [m] (default a quarter of a cell)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--duration", type=float, help="simulated seconds")
    g.add_argument("--frames", type=int, help="output frames after frame 0")
    p.add_argument("--dt", help="step size [s], or auto (the largest the stability prediction allows)")
    p.add_argument("--fps", type=float, help="output frames per second")
    p.add_argument("--precision", choices=["float32", "float64"], help="scalar type of every kernel")
    p.add_argument("--springs", action="store_true", help="also write springs as BasisCurves")
    p.add_argument("--allow-unstable", action="store_true",
                   help="run even when a copy's dt is above a jelly's predicted stable step (to watch it explode)")
    p.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying a captured graph")
    add_common(p)
    return p


def run(args) -> int:
    plan = plan_variants(args)
    outputs = Outputs()
    outputs.add_input("scene", plan.source)
    add_asset_inputs(outputs, *(v.data for v in plan.variants))
    out = outputs.add("--out", args.out if args.out is not None else f"{Path(plan.source).stem}_compare.usdc",
                      USD_SUFFIXES)
    outputs.add("--metrics", args.metrics, JSON_SUFFIXES, streams=True)
    outputs.add("--plot", args.plot, (".png",))
    if args.columns is not None and args.columns < 1:
        raise CommandLineError("--columns", "must be an integer >= 1", args.columns)
    if args.gap is not None and not (math.isfinite(args.gap) and args.gap >= 0):
        raise CommandLineError("--gap", "must be a finite number >= 0", args.gap)
    device = common.resolve_device(args.device)
    # Every copy runs at once: their memory together must fit, and the steps must be able to finish.
    copies = [scene_mod.Scene(v.data, source=plan.source) for v in plan.variants]
    check_fits(copies[0], device, frames=plan.frames, usd_springs=args.springs, copies=copies)
    stable_step.check_variants([v.data for v in plan.variants], plan.source, [v.name for v in plan.variants],
                               blame=lambda e: common.blame_flag(e, args), refuse=not args.allow_unstable)

    progress = common.progress_bar(plan.frames + 1, f"{plan.name} x{len(plan.variants)}", "frame", args.quiet)
    try:
        with common.Signals(regions=True) as signals, outputs:
            result = run_comparison(plan, device, out, metrics_path=args.metrics, plot_path=args.plot,
                                    columns=args.columns, gap=args.gap, springs=args.springs,
                                    use_graph=None if not args.no_graph else False, progress=progress,
                                    stop_requested=lambda: signals.received, stoppable=signals.stoppable,
                                    on_warm_up=common.warm_up_notice(args))
    finally:
        if progress is not None:
            progress.close()
    for v in result.variants:
        if v.exploded:
            state = f"exploded at t = {v.exploded['time']:.4g} s ({v.exploded['reason']})"
        else:
            state = "interrupted" if result.interrupted else "complete"
        print(f"{plan.name} [{v.name}]: {v.integrator}, {state}", file=sys.stderr)
    ended = "INTERRUPTED: " if result.interrupted else ""
    print(f"{ended}{plan.name}: {len(result.variants)} copies, {result.frames_written} frames, {result.steps} steps at "
          f"dt={plan.dt:g} s in {result.wall_seconds:.2f} s -> {result.written_path}", file=sys.stderr)
    if result.interrupted:
        return 128 + int(signals.received)
    exploded = [v.name for v in result.variants if v.exploded]
    if exploded:
        print(f"error: {plan.source}: copies exploded: {', '.join(exploded)}; the others ran to the end and every "
              "frame was kept (an exploded copy stays at its last finite frame)", file=sys.stderr)
        return common.EXIT_EXPLODED
    return 0


# ---------------------------------------------------------------------------------------------
# Variants


def _parse_vary(items) -> list[tuple[str, list]]:
    varies = []
    for item in items:
        if "=" not in item:
            raise SceneError("--vary", None, "expected KEY=V1,V2,...", item)
        key, raw = item.split("=", 1)
        key = key.strip()
        values = []
        for text in split_values(raw):
            if not text:
                raise SceneError("--vary", key, "empty value in the list", raw)
            values.append(parse_override(f"{key}={text}", source="--vary")[1])
        if any(k == key for k, _ in varies):
            raise SceneError("--vary", key, "given twice; list all its values in one --vary")
        if len(set(map(repr, values))) != len(values):
            raise SceneError("--vary", key, "repeats a value (each copy needs its own name)", raw)
        if key.split(".")[0] == "simulation" and key != "simulation.integrator":
            raise SceneError(
                "--vary", key,
                "every copy shares one clock and one model, so [simulation] values cannot vary; "
                "run them as separate `softsim run`s", raw,
            )
        varies.append((key, values))
    return varies


def plan_variants(args) -> Plan:
    """Load the scene (with --set and flags), expand --integrators x --vary and validate every copy.

    An error in a --vary item is an error of that flag: ``command line: --vary: <key>: ...``."""
    try:
        return _plan_variants(args)
    except SceneError as e:
        if e.source != "--vary":
            raise
        key = e.key.removeprefix("--set ") if e.key else None
        message = f"{key}: {e.message}" if key and key != "--set" else e.message
        raise (CommandLineError("--vary", message, e.value) if e.has_value else CommandLineError("--vary", message)) from None


def _plan_variants(args) -> Plan:
    path, source, base = scene_mod.read_scene_data(args.scene)
    common.init_warp_for_meshes(base, args)
    items = [scene_mod.parse_override(item) for item in args.overrides] + common.flag_overrides(args)
    scene_mod.apply_overrides(base, items)

    varies = _parse_vary(args.vary)
    if args.integrators is not None:
        integrators = [s.strip() for s in args.integrators.split(",")]
        for name in integrators:
            if name not in NAMES:
                raise CommandLineError("--integrators", f"unknown integrator; choose from {', '.join(NAMES)}",
                                       name)
        if len(set(integrators)) != len(integrators):
            raise CommandLineError("--integrators", "lists an integrator twice", args.integrators)
    elif varies:
        integrators = [None]  # the scene's own
    else:
        integrators = list(DEFAULT_INTEGRATORS)
    if any(k == "simulation.integrator" for k, _ in varies):
        if args.integrators is not None:
            raise SceneError("--vary", "simulation.integrator", "use --integrators or this --vary, not both")

    plan = expand_variants(base, path, source, integrators, varies, blame=lambda e: common.blame_flag(e, args))
    common.warn_overlaps(plan.variants[0].data, source)
    return plan
