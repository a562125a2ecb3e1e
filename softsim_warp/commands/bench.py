"""``softsim bench``: particle-steps per second per jelly size and integrator, optionally against Newton.

The measurement (the benchmark jelly, timed cases, step bytes, copy bandwidth, GPU clocks, table
and plot) is :mod:`softsim_warp.studies.bench`, and ``--contact``'s piles of jellies are
:mod:`softsim_warp.studies.bench_contact`. This module parses the flags, refuses the ones the
chosen benchmark would ignore and sizes that would not fit, calls the study, prints its table and
saves the report.
"""

from __future__ import annotations

import datetime
import math
from dataclasses import asdict

from ..core.methods import EXPLICIT_NAMES, IMPLICIT, NAMES, SYMPLECTIC
from ..core.errors import CommandLineError
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import Outputs, save_report
from ..io.resources import check_bench_size, check_counts, heaviest, lattice_spring_count
from ..io.scene import load_scene
from ..studies import bench_contact
from ..studies.bench import (
    DEFAULT_INTEGRATORS,
    CaseRefused,
    JellySpec,
    device_name,
    format_gpu_clocks,
    format_implicit_peer,
    format_table,
    measure,
    measure_copy_bandwidth,
    plot,
    scene_group,
    size_groups,
    versions,
)
from ..studies.bench_newton import implicit_peer, newton_version
from .common import ProgressLog, resolve_device

COMMAND = "bench"
DEFAULT_JELLIES = "8,64,216,512,1000"
# Flags (flag -> argparse dest) of one benchmark only, refused where they would be ignored: those
# that only ``--contact`` uses, and those of the implicit integrator's run against Newton's VBD
# (only with --peer newton and implicit among --integrators, without --scene or --contact).
CONTACT_FLAGS = {"--jellies": "jellies", "--contact-size": "contact_size"}
IMPLICIT_PEER_FLAGS = {"--implicit-peer-ks": "implicit_peer_ks", "--implicit-peer-dt": "implicit_peer_dt"}
# The parameter of a case the study refuses -> the flag that named it.
CASE_FLAGS = {"integrator": "--integrators", "path": "--paths"}


def _parse_list(text, flag, allowed=None, convert=str):
    items = [t.strip() for t in str(text).split(",") if t.strip()]
    if not items:
        raise CommandLineError(flag, "needs at least one value", text)
    out = []
    for item in items:
        try:
            value = convert(item)
        except ValueError:
            raise CommandLineError(flag, "not a comma-separated list of integers", text) from None
        if allowed is not None and value not in allowed:
            raise CommandLineError(flag, f"unknown value {item!r}; choose from {', '.join(allowed)}", text)
        out.append(value)
    return out


def add_parser(subparsers, add_common):
    p = subparsers.add_parser("bench", help="particle-steps per second per jelly size and integrator (and vs Newton)")
    p.add_argument(
        "--sizes", default="10,20,40", help="jelly sizes n (n^3 particles), comma-separated (default 10,20,40)"
    )
    p.add_argument(
        "--integrators", default=",".join(DEFAULT_INTEGRATORS), help="comma-separated (default: all explicit)"
    )
    p.add_argument(
        "--paths", default="auto", help="force paths: auto (what the model picks), lattice, springs; comma-separated"
    )
    p.add_argument("--steps", type=int, default=200, help="steps per timed repeat (default 200)")
    p.add_argument("--repeats", type=int, default=7, help="timed repeats; the median is reported (default 7)")
    p.add_argument("--copies", type=int, default=1, help="copies of the jelly, one per world, in one model (batching)")
    p.add_argument("--precision", choices=["float32", "float64"], default="float32")
    p.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying a graph")
    p.add_argument("--scene", help="benchmark this scene (name or .toml, with its dt) instead of the size sweep")
    p.add_argument("--peer", choices=["newton"], help="also step the same jelly with Newton's SolverSemiImplicit")
    p.add_argument(
        "--implicit-peer-ks", type=float, default=1.0e5,
        help="with --peer and implicit: ks of the stiff jelly stepped by implicit and Newton's VBD (1e5)",
    )
    p.add_argument("--implicit-peer-dt", type=float, default=0.01, help="its step [s] (0.01)")
    p.add_argument(
        "--variants",
        action="store_true",
        help="measure the fast paths one by one (graph, lattice, fusion, batching) instead of --paths",
    )
    p.add_argument("--out", help="write the results as JSON")
    p.add_argument("--plot", help="write a log-log plot of particle-steps/s over particle count (PNG)")
    _add_contact_arguments(p)
    # The flags of one benchmark default to None, so that _check_flags can tell whether they were
    # given; their own defaults travel in the namespace (flag_defaults) for the benchmark that runs.
    dests = (*CONTACT_FLAGS.values(), *IMPLICIT_PEER_FLAGS.values())
    p.set_defaults(flag_defaults={d: p.get_default(d) for d in dests}, **dict.fromkeys(dests))
    add_common(p)
    return p


def _check_flags(args):
    """Refuse values no benchmark can use and flags that the chosen benchmark would ignore.

    ``--set`` changes a scene, so it needs ``--scene`` (the size sweep builds :class:`JellySpec`'s
    jelly, ``--contact`` its piles); ``--jellies`` and ``--contact-size`` need ``--contact``. Then the
    flags of the benchmark that runs get their defaults where they were not given.
    """
    for flag, dest in IMPLICIT_PEER_FLAGS.items():
        value = getattr(args, dest)
        if value is None:
            continue
        if not (math.isfinite(value) and value > 0):
            raise CommandLineError(flag, "must be a finite number > 0", value)
        methods = [m.strip() for m in str(args.integrators).split(",")]
        if args.peer != "newton" or IMPLICIT.name not in methods or args.scene is not None or args.contact:
            why = "sets the implicit integrator's run against Newton's VBD: give --peer newton and implicit in --integrators"
            raise CommandLineError(flag, why + " (and neither --scene nor --contact)", value)
    if args.contact:
        own = "not with --contact, which times its own piles of jellies"
        if args.scene is not None:
            raise CommandLineError("--scene", own, args.scene)
        if args.variants:
            raise CommandLineError("--variants", own, "--variants")
        if args.paths != "auto":
            raise CommandLineError("--paths", own, args.paths)
        if args.copies != 1:
            raise CommandLineError("--copies", own, args.copies)
        if args.plot is not None:
            raise CommandLineError("--plot", "not with --contact, which draws no plot (only --out)", args.plot)
    else:
        for flag, dest in CONTACT_FLAGS.items():
            if getattr(args, dest) is not None:
                raise CommandLineError(flag, "applies only with --contact", getattr(args, dest))
    if args.overrides and not args.scene:
        value = args.overrides[0] if len(args.overrides) == 1 else args.overrides
        why = "changes a scene, so it applies only with --scene (the size sweep and --contact build their own jellies)"
        raise CommandLineError("--set", why, value)
    # The defaults of what will run: the contact flags stay None without --contact.
    for dest in (*IMPLICIT_PEER_FLAGS.values(), *(CONTACT_FLAGS.values() if args.contact else ())):
        if getattr(args, dest) is None:
            setattr(args, dest, args.flag_defaults[dest])


def _add_contact_arguments(p):
    """The flags of ``bench --contact``."""
    p.add_argument(
        "--contact",
        action="store_true",
        help="benchmark contact between jellies: piles of --jellies jellies, with and without contact",
    )
    p.add_argument(
        "--jellies",
        default=DEFAULT_JELLIES,
        help=f"with --contact: jelly counts of the piles, comma-separated (default {DEFAULT_JELLIES})",
    )
    p.add_argument(
        "--contact-size", type=int, default=10, help="with --contact: particles per jelly edge (default 10)"
    )


def run(args) -> int:
    sizes = _parse_list(args.sizes, "--sizes", convert=int)
    if any(n < 2 for n in sizes):
        raise CommandLineError("--sizes", "each size must be at least 2", args.sizes)
    methods = _parse_list(args.integrators, "--integrators", allowed=NAMES)
    paths = _parse_list(args.paths, "--paths", allowed=("auto", "lattice", "springs"))
    for flag, value, low in (("--steps", args.steps, 1), ("--repeats", args.repeats, 1), ("--copies", args.copies, 1)):
        if value < low:
            raise CommandLineError(flag, f"must be at least {low}", value)
    if args.peer and args.scene:
        raise CommandLineError("--peer", "compares the size sweep only; leave out --scene", args.peer)
    _check_flags(args)
    # Warp is initialised (quietly) by cli.main before any command that uses it.
    # The scene and its --set values are validated before any output is checked or anything measured.
    scene = load_scene(args.scene, args.overrides) if args.scene else None
    outputs = Outputs()
    outputs.add_input("--scene", args.scene)
    if scene is not None:
        add_asset_inputs(outputs, scene)
    outputs.add("--out", args.out, (".json",))
    outputs.add("--plot", args.plot, (".png",))
    device = resolve_device(args.device)
    if args.peer:
        try:
            newton_version()
        except RuntimeError as exc:
            raise CommandLineError("--peer", str(exc), args.peer) from None

    spec = JellySpec()
    bandwidth = measure_copy_bandwidth(device)
    use_graph = not args.no_graph
    if args.contact:
        return _run_contact(args, device, spec, versions(args.peer), device_name(device))

    if scene is not None:
        groups = [scene_group(scene, device, args.precision)]
    else:
        # Each size must fit before anything is built (the largest method's buffers, all copies).
        for n in sizes:
            count = max(args.copies, 8 if args.variants else 1)
            check_bench_size(n, count, device, heaviest(methods), *(("--copies", args.copies) if args.copies >= count
                                                           else ("--variants", "8 copies")))
        groups = size_groups(sizes, spec, device, args.precision, args.copies)

    shown = ProgressLog("bench", unit="size", quiet=args.quiet)
    try:
        results, peers, gpu_clocks = measure(
            groups, methods, paths, spec, device, bandwidth, steps=args.steps, repeats=args.repeats,
            copies=args.copies, variants=args.variants, batch=scene is None, peer=bool(args.peer),
            use_graph=use_graph, progress=shown.progress,
        )
    except CaseRefused as exc:
        raise CommandLineError(CASE_FLAGS[exc.what], exc.message, exc.value) from None

    implicit_rows = []
    if args.peer and IMPLICIT.name in methods and not args.scene:
        # Newton's implicit solver (VBD) against ours on a stiff spinning jelly in free flight, with
        # the error against a float64 reference (bench_newton.implicit_peer).
        for n in sizes:
            implicit_rows += implicit_peer(n, args.implicit_peer_ks, 0.1, args.implicit_peer_dt, device)
    print(format_table(results, bandwidth, device))
    if implicit_rows:
        print(format_implicit_peer(implicit_rows, args.implicit_peer_ks, args.implicit_peer_dt))
    for line in format_gpu_clocks(gpu_clocks):
        print(line)
    data = {
        "arguments": {k: v for k, v in vars(args).items() if isinstance(v, (str, int, float, bool, list, type(None)))},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "device": str(device),
        "device_name": device_name(device),
        "versions": versions(args.peer),
        "bandwidth_gbs": bandwidth / 1e9,
        "settings": {
            "steps": args.steps + (args.steps % 2),
            "repeats": args.repeats,
            "graph": use_graph,
            "precision": args.precision,
            "copies": args.copies,
            "jelly": asdict(spec) if not args.scene else None,
            "scene": args.scene,
        },
        "results": results,
        "peer": peers,
        "implicit_peer": implicit_rows,
        # nvidia-smi's samples while each size's cases were timed (ClockMonitor; empty without it).
        "gpu_clocks": gpu_clocks,
    }
    with outputs:
        save_report(data, args.out, args.plot, plot)
    return 0


def _run_contact(args, device, spec, versions, device_name) -> int:
    """The ``--contact`` benchmark (:mod:`softsim_warp.studies.bench_contact`), with ``run``'s device."""
    counts = [t.strip() for t in str(args.jellies).split(",") if t.strip()]
    try:
        counts = [int(c) for c in counts]
    except ValueError:
        raise CommandLineError("--jellies", "expected comma-separated jelly counts", args.jellies) from None
    if not counts or min(counts) < 2:
        raise CommandLineError("--jellies", "each count must be at least 2 (contact is between jellies)", args.jellies)
    if args.contact_size < 2:
        raise CommandLineError("--contact-size", "must be at least 2", args.contact_size)
    methods = [t.strip() for t in str(args.integrators).split(",") if t.strip()]
    if args.integrators == ",".join(EXPLICIT_NAMES):  # bench's default: one method is enough here
        methods = [SYMPLECTIC.name]
    outputs = Outputs()
    outputs.add("--out", args.out, (".json",))
    if args.peer:
        try:
            newton_version()
        except RuntimeError as exc:
            raise CommandLineError("--peer", str(exc), args.peer) from None
    use_graph = not args.no_graph
    size = args.contact_size
    _check_pile_sizes(counts, size, methods, device, args.jellies)
    rows = bench_contact.measure(counts, size, methods, spec, device, precision=args.precision, steps=args.steps,
                                 repeats=args.repeats, use_graph=use_graph, peer=bool(args.peer))
    print(bench_contact.format_table(rows, device_name, spec, size, args.steps, args.repeats))
    report = {
        "command": "bench --contact",
        "device": device_name,
        "versions": versions,
        "settings": {
            "jelly_size": size,
            "spacing": spec.spacing,
            "particle_mass": spec.particle_mass,
            "ks": spec.ks,
            "kd": spec.kd,
            "dt": spec.dt,
            "steps": args.steps,
            "repeats": args.repeats,
            "precision": args.precision,
            "jelly_gap_spacings": bench_contact.JELLY_GAP,
            "newton_particle_radius_spacings": bench_contact.NEWTON_RADIUS,
        },
        "results": rows,
    }
    save_report(report, args.out)
    return 0


def _check_pile_sizes(counts, size, methods, device, value):
    """Refuse a pile that would not fit, before any is built: every particle of a pile takes part
    in contact (--jellies names it; a single jelly too large names --contact-size)."""
    springs = lattice_spring_count((size, size, size))
    check_counts(size**3, springs, device, heaviest(methods), "--contact-size", size, contact_particles=size**3)
    for count in counts:
        check_counts(count * size**3, count * springs, device, heaviest(methods), "--jellies", value,
                     contact_particles=count * size**3)
