"""``softsim stability SCENE``: the largest stable step of each integrator, measured and predicted.

The measurement (the stability criterion, the probe runs, the bisection, the table and plots) is
:mod:`softsim_warp.studies.stability`; this module parses the flags, refuses runs that cannot
finish, calls it, prints the table and saves the report.
"""

from __future__ import annotations

import math

from ..core.errors import CommandLineError
from ..core.methods import NAMES
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import JSON_SUFFIXES, Outputs, save_report
from ..io.resources import check_fits
from ..studies.stability import (
    DEFAULT_KS,
    DEFAULT_RTOL,
    DEFAULT_STEPS,
    MAX_PROBE_STEPS,
    analyse,
    format_table,
    plot_report,
)
from .common import (
    ProgressLog,
    check_positive,
    load_for_cli,
    parse_methods,
    parse_positive_list,
    resolve_device,
    warm_up_notice,
)

COMMAND = "stability"


def add_parser(subparsers, add_common):
    p = subparsers.add_parser("stability", help="largest stable dt per integrator: measured by bisection and predicted")
    p.add_argument("scene", help="scene file (.toml) or built-in scene name")
    p.add_argument("--integrators", default=",".join(NAMES),
                   help="comma-separated methods (default: all; implicit is skipped if unavailable)")
    p.add_argument("--ks", help=f"comma-separated stiffnesses of the map [N/m] (default {','.join(f'{k:g}' for k in DEFAULT_KS)}; "
                                "'none' for no map)")
    p.add_argument("--steps", type=int, default=DEFAULT_STEPS, help=f"free-jelly run length [steps] (default {DEFAULT_STEPS})")
    p.add_argument("--duration", type=float, help="scene run length [s] (default min(scene duration, 1 s))")
    p.add_argument("--lattice", type=int,
                   help="particles per axis of the free jelly, at most, at the jelly's spacing (default: the jelly's own)")
    p.add_argument("--jelly", type=int, default=0, help="which jelly of the scene is measured (default 0)")
    p.add_argument("--no-scene", action="store_true", help="measure on the free jelly only (skip the full-scene runs)")
    p.add_argument("--rtol", type=float, default=DEFAULT_RTOL, help=f"relative width of the final bracket (default {DEFAULT_RTOL})")
    p.add_argument("--precision", choices=["float32", "float64"], help="precision of the runs")
    p.add_argument("--out", help="write the report as JSON")
    p.add_argument("--plot", help="write the plots (.png/.pdf/.svg)")
    p.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying graphs")
    add_common(p)


def check_run_lengths(args):
    """Refuse a --steps beyond what one probe may run (:data:`MAX_PROBE_STEPS`)."""
    if args.steps > MAX_PROBE_STEPS:
        raise CommandLineError("--steps", f"must be at most {MAX_PROBE_STEPS:,} (the longest probe run)", args.steps)


def check_scene_runs(args, scene, device):
    """Refuse a scene run that no dt up to the frame interval can finish within
    :data:`MAX_PROBE_STEPS` steps, and a scene too large for memory, before any work."""
    fps = scene.sim["fps"]
    duration = args.duration or min(scene.run_seconds(), 1.0)
    if not args.no_scene and math.ceil(duration * fps) > MAX_PROBE_STEPS:
        raise CommandLineError("--duration", f"a scene run of {duration:g} s takes more than {MAX_PROBE_STEPS:,} steps "
                               f"even at the largest dt tried (1/fps = {1.0 / fps:g} s); shorten it", args.duration)
    check_fits(scene, device, frames=0)


def run(args) -> int:
    methods = parse_methods(args.integrators)
    ks = () if args.ks and args.ks.strip().lower() == "none" else (
        parse_positive_list(args.ks, "--ks") if args.ks else DEFAULT_KS)
    if args.steps < 10:
        raise CommandLineError("--steps", "must be an integer >= 10", args.steps)
    check_positive(args.duration, "--duration")
    check_run_lengths(args)
    if args.lattice is not None and args.lattice < 2:
        raise CommandLineError("--lattice", "must be an integer >= 2", args.lattice)
    if not (0 < args.rtol < 1):
        raise CommandLineError("--rtol", "must be > 0 and < 1", args.rtol)
    scene = load_for_cli(args)
    outputs = Outputs()
    outputs.add_input("scene", args.scene)
    add_asset_inputs(outputs, scene)
    # --plot first: `--out r.png --plot r.png` is two outputs in one file before it is a bad extension.
    outputs.add("--plot", args.plot, (".png", ".pdf", ".svg"))
    outputs.add("--out", args.out, JSON_SUFFIXES, streams=True)
    if not 0 <= args.jelly < len(scene.jellies):
        raise CommandLineError("--jelly", f"this scene has jellies 0 to {len(scene.jellies) - 1}", args.jelly)
    device = resolve_device(args.device)
    check_scene_runs(args, scene, device)
    shown = ProgressLog(f"{scene.name} stability", unit="limit", quiet=args.quiet)
    with outputs:
        report = analyse(scene, methods, ks_values=ks, device=device, precision=args.precision, steps=args.steps,
                         duration=args.duration, rtol=args.rtol, scene_runs=not args.no_scene,
                         use_graph=not args.no_graph, lattice_max=args.lattice, jelly_index=args.jelly, log=shown.log,
                         progress=shown.progress, on_warm_up=warm_up_notice(args))
        print(format_table(report))
        save_report(report, args.out, args.plot, plot_report)
    return 0
