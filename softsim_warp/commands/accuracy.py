"""``softsim accuracy SCENE``: speed against error for each integrator and step size.

The measurement (reference runs, errors, fitted orders, table and plots) is
:mod:`softsim_warp.studies.accuracy`; this module parses the flags, refuses what cannot run,
calls it, prints the table and saves the report.
"""

from __future__ import annotations

from ..core.errors import CommandLineError
from ..core.methods import NAMES
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import JSON_SUFFIXES, Outputs, save_report
from ..io.resources import MAX_RUN_DAYS, check_fits, scene_counts, step_seconds_floor
from ..studies.accuracy import REFERENCE_DIVISOR, ReferenceExploded, format_table, measure, plot_report
from .common import (
    ProgressLog,
    check_positive,
    load_for_cli,
    parse_methods,
    parse_positive_list,
    resolve_device,
    warm_up_notice,
)

COMMAND = "accuracy"


def add_parser(subparsers, add_common):
    p = subparsers.add_parser("accuracy", help="error against a float64 rk4 reference and wall time, per integrator and dt")
    p.add_argument("scene", help="scene file (.toml) or built-in scene name")
    p.add_argument("--integrators", default=",".join(NAMES),
                   help="comma-separated methods (default: all; implicit is skipped if unavailable)")
    p.add_argument("--dts", help="comma-separated steps [s] (default: the scene's dt x 2, 1, 1/2, 1/4, 1/8)")
    p.add_argument("--duration", type=float, help="simulated seconds (default: the scene's)")
    p.add_argument("--reference-dt", type=float, help="reference rk4 step [s] (default: smallest dt / 8)")
    p.add_argument("--fps", type=float, help="frames per second compared (default: the scene's)")
    p.add_argument("--precision", choices=["float32", "float64"], help="precision of the runs (reference: float64)")
    p.add_argument("--out", help="write the report as JSON")
    p.add_argument("--plot", help="write the work-precision and convergence plots (.png/.pdf/.svg)")
    p.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying graphs")
    add_common(p)


def run(args) -> int:
    methods = parse_methods(args.integrators)
    dts = parse_positive_list(args.dts, "--dts") if args.dts else None
    for flag in ("duration", "reference_dt", "fps"):
        check_positive(getattr(args, flag), "--" + flag.replace("_", "-"))
    scene = load_for_cli(args)
    outputs = Outputs()
    outputs.add_input("scene", args.scene)
    add_asset_inputs(outputs, scene)
    # --plot first: `--out r.png --plot r.png` is two outputs in one file before it is a bad extension.
    outputs.add("--plot", args.plot, (".png", ".pdf", ".svg"))
    outputs.add("--out", args.out, JSON_SUFFIXES, streams=True)
    fps = args.fps or scene.sim["fps"]
    for d in dts or ():
        if d > 1.0 / fps:
            raise CommandLineError("--dts", f"steps must not exceed the frame interval 1/fps = {1.0 / fps:g} s", d)
    device = resolve_device(args.device)
    check_fits(scene, device, frames=0)  # one run at a time, no USD frames kept
    # The reference run takes the most steps: refuse it up front when it could not finish.
    duration = args.duration or scene.run_seconds()
    reference = args.reference_dt or min(dts or [scene.sim["dt"] * 0.125]) / REFERENCE_DIVISOR
    floor = step_seconds_floor(scene_counts(scene.data).particles, device.is_cuda)
    if duration / reference * floor > MAX_RUN_DAYS * 86400.0:
        flag, value = ("--reference-dt", args.reference_dt) if args.reference_dt else ("--dts", args.dts or scene.sim["dt"])
        raise CommandLineError(flag, f"the reference run of {duration / reference:.3g} steps would take at least "
                               f"{duration / reference * floor / 86400.0:.3g} days on {device} "
                               f"(at most {MAX_RUN_DAYS} days allowed)", value)
    shown = ProgressLog(f"{scene.name} accuracy", unit="run", quiet=args.quiet)
    with outputs:
        try:
            return _measure_and_save(args, scene, methods, dts, device, shown)
        finally:
            if shown.bar is not None:
                shown.bar.close()


def _measure_and_save(args, scene, methods, dts, device, shown) -> int:
    try:
        report = measure(scene, methods, dts, device=device, precision=args.precision, duration=args.duration,
                         reference_dt=args.reference_dt, fps=args.fps, use_graph=not args.no_graph, log=shown.log,
                         progress=shown.progress, on_warm_up=warm_up_notice(args))
    except ReferenceExploded as e:
        given = (args.reference_dt,) if args.reference_dt else ()
        raise CommandLineError("--reference-dt", str(e), *given) from None
    print(format_table(report))
    save_report(report, args.out, args.plot, plot_report)
    return 0
