"""``softsim sweep``: a parameter study, one row per variant, on Dask (local worker processes or a cluster).

The engine (plan, batches, tasks, rows, cluster) is :mod:`softsim_warp.io.sweep`; this module is
its command line, the ``--find-stable-dt`` task (the bisection of ``softsim stability``) and the
summary. docs/SWEEP.md documents the options and the results' columns.
"""

from __future__ import annotations

import copy
import shutil
import sys
import time

from ..core.errors import CommandLineError, SceneError
from ..io import scene as scene_mod
from ..io import stable_step
from ..io import sweep as engine
from ..io.mesh_scene import add_asset_inputs
from ..io.outputs import Outputs, is_stream, kept_partial_path, target_of
from ..io.resources import check_fits, check_steps
from ..io.warp_init import init_warp
from . import common

COMMAND = "sweep"


def add_parser(subparsers, add_common):
    p = subparsers.add_parser(
        COMMAND,
        help="parameter study: many variants of a scene as batched worlds on Dask workers, one row each",
        description="Run every variant of SCENE (the product of the --vary values, or --samples Latin-hypercube "
        "points, times --integrators and --dts) as worlds batched into Dask tasks, and write one row per variant "
        "to a Parquet or CSV table. Rows are kept as tasks finish; --resume runs only the missing ones.",
    )
    p.add_argument("scene", help="scene file (.toml) or built-in scene name")
    p.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2,...|KEY=LO:HI:N[:log]",
                   help="values of a dotted scene key (as --set; '*' stands for every entry, e.g. "
                   "jelly.0.springs.*.ks): a list, or N values from LO to HI, linear or log; several make a product")
    p.add_argument("--integrators",
                   help="comma-separated integrators, each variant run with each (default: the scene's)")
    p.add_argument("--dts", metavar="DT1,DT2,...|LO:HI:N[:log]", help="step sizes [s], each variant run with each")
    p.add_argument("--samples", type=int,
                   help="draw N Latin-hypercube points of the --vary axes instead of their product")
    p.add_argument("--seed", type=int, default=0, help="seed of --samples (default 0)")
    p.add_argument("--duration", help="simulated seconds of every variant")
    p.add_argument("--out", help="results table: .parquet or .csv (default <scene>_sweep.parquet)")
    p.add_argument("--plot",
                   help="write the study's figure (.png/.pdf/.svg): lines for one varied key, heat maps for two")
    p.add_argument("--metric", default=None,
                   help="the heat map's column (default energy_change_relative; stable_dt with --find-stable-dt)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, help="local worker processes (default: one per CPU core; on cuda:N one)")
    g.add_argument("--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster (tcp://host:8786)")
    p.add_argument("--batch", type=int,
                   help="worlds per task (default: what fits in memory, spread over the workers)")
    resume = "keep the rows already in --out (or its .partial file) and its parts; run the rest"
    p.add_argument("--resume", action="store_true", help=resume)
    p.add_argument("--reference", action="store_true",
                   help="also run each variant in float64 with rk4 and report the error against it")
    p.add_argument("--find-stable-dt", action="store_true",
                   help="per variant and integrator, the largest stable dt by bisection (as softsim stability)")
    p.add_argument("--rtol", type=float, default=0.02, help="--find-stable-dt: relative width of the final bracket")
    p.add_argument("--allow-unstable", action="store_true",
                   help="run the variants whose dt is above a jelly's predicted stable step too (as --dts does)")
    p.add_argument("--no-graph", action="store_true", help="launch kernels one by one instead of replaying graphs")
    add_common(p)
    return p


def _check_args(args):
    if args.samples is not None and not 1 <= args.samples <= engine.MAX_VARIANTS:
        raise CommandLineError("--samples", f"must be an integer from 1 to {engine.MAX_VARIANTS}", args.samples)
    if args.samples is not None and not args.vary:
        raise CommandLineError("--samples", "draws points of the --vary axes; give at least one --vary", args.samples)
    if args.seed < 0:
        raise CommandLineError("--seed", "must be an integer >= 0", args.seed)
    if args.workers is not None and args.workers < 1:
        raise CommandLineError("--workers", "must be an integer >= 1", args.workers)
    if args.batch is not None and args.batch < 1:
        raise CommandLineError("--batch", "must be an integer >= 1", args.batch)
    if args.find_stable_dt and args.dts:
        raise CommandLineError("--dts", "--find-stable-dt finds the step itself; drop --dts", args.dts)
    if args.find_stable_dt and args.reference:
        raise CommandLineError("--reference", "not with --find-stable-dt", "--reference")
    if not 0 < args.rtol < 1:
        raise CommandLineError("--rtol", "must be > 0 and < 1", args.rtol)
    if args.scheduler is not None:
        args.scheduler = engine.check_scheduler_address(args.scheduler)
    if not (args.device in ("cpu", "cuda") or args.device.startswith("cuda:")):
        raise CommandLineError("--device", "use cpu, cuda:N, or cuda (every GPU, one worker each)", args.device)


def plan(args):
    """Axes and variants of the command line, every variant validated; (axes, variants, source, mode)."""
    _check_args(args)
    path, source, base = scene_mod.read_scene_data(args.scene)
    items = [scene_mod.parse_override(item) for item in args.overrides] + common.flag_overrides(args)
    try:
        scene_mod.apply_overrides(base, items)
        scene_mod.validate(copy.deepcopy(base), source)
    except scene_mod.SceneError as e:
        raise common.blame_flag(e, args) from None
    axes = [engine.parse_axis(item) for item in args.vary]
    if args.dts:
        dts = engine.parse_axis(args.dts, flag="--dts", key="simulation.dt")
        axes.append(dts)
    integrators = common.parse_methods(args.integrators) if args.integrators else None
    if integrators and len(set(integrators)) != len(integrators):
        raise CommandLineError("--integrators", "lists an integrator twice", args.integrators)
    mode = "stable_dt" if args.find_stable_dt else ("reference" if args.reference else "run")
    variants = engine.plan_sweep(base, source, axes, integrators, args.samples, args.seed, mode,
                                 blame=lambda e: common.blame_flag(e, args))
    explore = bool(args.dts) or args.allow_unstable
    above = stable_step.check_sweep(variants, source, mode, explore, blame=lambda e: common.blame_flag(e, args))
    if above:
        print(f"warning: {source}: {above} of {len(variants)} variants have a dt above their predicted stable step; "
              "they run, and their rows say how they ended", file=sys.stderr)
    if args.plot:
        keys = plotted_keys(axes, variants)
        if len(keys) > 2 and args.samples is None:
            raise CommandLineError("--plot", f"draws one or two varied keys; this sweep varies {len(keys)}: "
                                   f"{', '.join(keys)}", args.plot)
    return axes, variants, source, mode, path


def plotted_keys(axes, variants):
    """The varied columns with more than one value (dt included)."""
    keys = []
    for a in axes:
        col = "dt" if a.key == "simulation.dt" else a.key
        if len({engine._canonical(v.values[col]) for v in variants}) > 1:
            keys.append(col)
    return keys


# ---------------------------------------------------------------------------------------------
# --find-stable-dt: one task per variant and integrator


def stable_dt_task(spec: dict) -> list[dict]:
    """A Dask task: a row per variant of ``studies.stability.variant_stable_dt`` (a variant's failure
    is its row), with the wall time and the worker."""
    from ..studies import stability  # noqa: PLC0415

    wp = init_warp()
    device = wp.get_device(spec["device"])
    rows = []
    for v in spec["variants"]:
        t0 = time.perf_counter()
        row = {"variant_id": v["id"], "device": str(device)}
        try:
            scene = scene_mod.Scene(v["data"], source=spec.get("source", "<sweep>"))
            row.update(stability.variant_stable_dt(scene, device, rtol=spec["rtol"], use_graph=spec["use_graph"]))
        except Exception as e:  # noqa: BLE001 - a variant's failure is its row
            row.update(status="failed", error=f"{type(e).__name__}: {e}")
        row["wall_seconds"] = time.perf_counter() - t0
        row["worker"] = f"{_node()}:{_pid()}"
        rows.append(row)
    return rows


def _node():
    import os  # noqa: PLC0415

    return os.uname().nodename


def _pid():
    import os  # noqa: PLC0415

    return os.getpid()


# ---------------------------------------------------------------------------------------------
# Run


class _DeviceKind:
    """A device named only by kind (a remote scheduler's workers): enough for the step-time floor."""

    def __init__(self, name):
        self.is_cuda = str(name).startswith("cuda")

    def __str__(self):
        return "cuda" if self.is_cuda else "cpu"


def check_variant_steps(variants, source, mode, device):
    """Refuse, before a cluster starts, a sweep of which any variant's steps could not finish in
    ``resources.MAX_RUN_DAYS`` days (each variant's own dt and duration, as ``softsim run`` checks)."""
    if mode == "stable_dt":
        return  # probes choose their own dt, at most stability.MAX_PROBE_STEPS steps each
    where = device if hasattr(device, "is_cuda") else _DeviceKind(device)
    for v in variants:
        scene = scene_mod.Scene(v.data, source=source)
        check_steps(scene, where, scene.frame_count())


def run(args) -> int:
    axes, variants, source, mode, path = plan(args)
    name = variants[0].data.get("name", path.stem)
    for module in ("pyarrow", "distributed"):
        engine.require(module)
    outputs = Outputs()
    outputs.add_input("scene", source)
    add_asset_inputs(outputs, *(v.data for v in variants))
    default_out = f"{path.stem}_sweep.parquet"
    out = outputs.add("--out", args.out if args.out is not None else default_out, engine.RESULT_SUFFIXES)
    plot_path = outputs.add("--plot", args.plot, (".png", ".pdf", ".svg"))
    device = args.device
    gpus = 0
    if args.scheduler is None:
        if device == "cuda":
            wp = init_warp(args.debug)
            gpus = wp.get_cuda_device_count()
            if gpus == 0:
                raise CommandLineError("--device", "no CUDA device here", device)
            local = wp.get_device("cuda:0")
        else:
            local = common.resolve_device(device, args.debug)
    try:
        if args.scheduler is None:
            # Every group's largest variant must fit and finish (as softsim run checks a run).
            seen = set()
            for v in variants:
                key = engine.group_key(v)
                if key not in seen:
                    seen.add(key)
                    scene = scene_mod.Scene(v.data, source=source)
                    if mode == "stable_dt":
                        check_fits(scene, local, frames=0)
                    else:
                        check_fits(scene, local, frames=scene.frame_count())
        check_variant_steps(variants, source, mode, local if args.scheduler is None else args.device)
    except SceneError as e:
        if args.dts and e.key == "simulation.dt":  # the dt that --dts gave: name the flag the user typed
            raise CommandLineError("--dts", e.message.replace("raise simulation.dt", "raise --dts"), e.value) from None
        raise
    meta = {"scene": name, "source": source, "mode": mode, "keys": [a.key for a in axes]}
    schema = engine.make_schema(axes, variants, mode, meta)
    if args.metric is not None:
        numeric = [f.name for f in schema if str(f.type) in ("double", "int64") and f.name != "index"]
        if args.metric not in numeric:
            raise CommandLineError("--metric", f"not a numeric column of this sweep; choose from {', '.join(numeric)}",
                                   args.metric)
    by_id = {v.id: v for v in variants}
    # A figure that existed is replaced only by the complete sweep's (as the results file).
    plot_existed = plot_path is not None and target_of(plot_path).exists() and not is_stream(plot_path)

    with common.Signals() as signals, outputs:
        store = engine.RowStore(out, schema, resume=args.resume)
        done = store.done_ids()
        stale = done - set(by_id)
        if stale:
            why = f"'{store.results}' holds {len(stale)} rows that are not variants of this sweep"
            raise CommandLineError("--resume", f"{why} (another scene, --set or --vary); use another --out", str(out))
        todo = [v for v in variants if v.id not in done]
        say = (lambda line: None) if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
        if done:
            rest = f"running the other {len(todo)}"
            say(f"{name}: {len(done)} of {len(variants)} rows already in {store.results}; {rest}")
        outcome = engine.Outcome()
        t0 = time.perf_counter()
        cluster = None
        if todo:
            cluster = engine.start_cluster(device, args.workers, args.scheduler, gpus)
            t0, startup = time.perf_counter(), time.perf_counter() - t0
            try:
                say(f"{name}: {len(todo)} variants on {cluster.workers} worker{'s' if cluster.workers != 1 else ''} "
                    f"(started in {startup:.1f} s; scheduler {cluster.address}); dashboard: "
                    + (cluster.dashboard or "not served (install bokeh>=3.1 for it)"))
                if mode == "stable_dt":
                    batches = [[v] for v in todo]
                    fn = stable_dt_task
                else:
                    budget = engine.memory_budget(device, cluster.workers) if args.scheduler is None else None
                    batches = engine.make_batches(todo, cluster.workers, device.startswith("cuda"), budget, args.batch)
                    fn = engine.run_batch
                specs = []
                for i, b in enumerate(batches):
                    spec = engine.task_spec(b, cluster.device, i, use_graph=not args.no_graph)
                    spec.update(source=source, rtol=args.rtol)
                    specs.append(spec)
                say(f"{name}: {len(specs)} tasks of up to {max(len(b) for b in batches)} worlds")

                writing = [False]
                signals.busy = lambda: writing[0]  # a second Ctrl-C waits for the rows being written

                def on_rows(rows):
                    for r in rows:
                        v = by_id[r["variant_id"]]
                        r.update(v.values)
                        r["index"] = v.index
                        r["precision"] = v.data["simulation"]["precision"]
                    writing[0] = True
                    try:
                        store.add(rows)
                        if store.due():
                            store.consolidate()
                    except OSError as e:  # a full disk; run_tasks would read an OSError as a lost scheduler
                        if not store.rows:  # nothing kept: no parts folder to --resume from
                            shutil.rmtree(store.parts, ignore_errors=True)
                        raise CommandLineError("--out", f"cannot write the rows of '{target_of(out)}': "
                                               f"{e.strerror or e}", str(out)) from None
                    finally:
                        writing[0] = False

                progress = common.progress_bar(len(todo), name, "variant", args.quiet)
                try:
                    outcome = engine.run_tasks(cluster, fn, specs, on_rows, stop_requested=lambda: signals.received,
                                               progress=progress)
                finally:
                    if progress is not None:
                        progress.close()
            except KeyboardInterrupt:
                outcome.interrupted = True
            finally:
                signals.closing = True  # the rows are written whole from here on
                complete = len(store.rows) == len(variants)
                if store.rows or complete:
                    store.consolidate(final=complete)
                cluster.close()
        elif store.parts.exists():
            store.consolidate(final=True)
        wall = time.perf_counter() - t0
        rows = sorted(store.rows.values(), key=lambda r: r["index"])
        complete = len(rows) == len(variants)
        _summary(say, name, rows, len(variants), len(todo), wall, out if complete else store.results, mode)
        if plot_path is not None and rows:
            from ..io.sweep_plot import plot_sweep  # noqa: PLC0415

            if not complete and (store.keep_out or plot_existed) and not is_stream(plot_path):
                plot_path = kept_partial_path(plot_path)
            keys = plotted_keys(axes, variants)
            plot_sweep(rows, keys, plot_path, mode=mode, metric=args.metric, title=f"{name}: {len(rows)} variants",
                       sampled=args.samples is not None)
    kept = _kept(store, out, len(variants))
    if outcome.interrupted or signals.received is not None:
        if complete:
            print(f"{name}: interrupted after the last row; {kept}", file=sys.stderr)
        else:
            print(f"{name}: interrupted; {kept}; run again with --resume for the rest", file=sys.stderr)
        return signals.exit_code()
    if outcome.scheduler_lost or outcome.lost:
        if outcome.scheduler_lost:
            why = f"the scheduler was lost ({outcome.scheduler_lost})"
        else:
            why = (f"the tasks of {len(outcome.lost)} variants gave no rows (first: {outcome.errors[0]}; a task is "
                   "given up after its worker died 3 times)")
        print(f"error: {out}: {why}; {kept}; run again with --resume for the rest", file=sys.stderr)
        return 1
    return 0


def _kept(store, out, total) -> str:
    """Where the rows of a sweep that stopped are, for its last message."""
    if len(store.rows) == total:
        return f"all {total} rows are in {out}"
    if not store.rows:
        where = "no row finished"
    else:
        where = f"{len(store.rows)} of {total} rows kept in {store.results}"
    if store.keep_out and target_of(out).exists():
        where += f"; {out}, which predates this sweep, is unchanged"
    return where


def _summary(say, name, rows, total, ran, wall, out, mode):
    counts = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    states = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    rate = f", {ran / wall:.3g} variants/s" if ran and wall > 0 else ""
    say(f"{name}: {len(rows)} of {total} rows ({states}); {ran} run in {wall:.1f} s{rate} -> {out}")
    failed = [r for r in rows if r["status"] == "failed"]
    for r in failed[:3]:
        say(f"  failed: variant {r['index']} ({r['integrator']}, dt={r['dt']:g}): {r.get('error')}")
    if len(failed) > 3:
        say(f"  ... and {len(failed) - 3} more failed (see the error column)")
