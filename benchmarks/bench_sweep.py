"""Variants per second of ``softsim sweep``: one batch against ``softsim bench``, and against separate runs.

The study is the seed jelly (``seed_bowl``, 10^3 particles) for ``--duration`` simulated seconds
(default 1 s) at the scene's integrator and step, with every spring type's ks spread over
``--variants`` values from 1000 to 8000 N/m.

By default (docs/SWEEP.md's "Speed" table) the sweep's own task code runs in this process on
``--device``: the variants as one batch (or batches of ``--batch`` worlds), as a worker runs them.
It reports the batch's build time, its kernel loading (start-up, not counted in the rates), the
frames' time (stepping, the per-world reductions on the device and judging all worlds on the host,
each part timed too), variants/s (build and frames counted) and particle-steps/s (frames), and
``softsim bench`` stepping the same worlds (the batch's model, its integrator, ``--bench-steps`` steps as one captured graph,
median of ``--repeats``): the sweep's particle-steps/s over bench's is its share of the device.

``--processes`` instead compares whole processes, three ways:

* ``sweep``: one ``softsim sweep`` process (its worker start-up, kernel loading and results file
  included), ``--workers`` local worker processes (on CUDA: one per GPU, or as given);
* ``run, serial``: ``softsim run`` processes one after another (each writes its USD file: what a
  user running them by hand gets);
* ``run, parallel``: the same, ``--workers`` processes at a time.

The separate runs are timed on the first ``--runs`` variants (default all) and reported per
variant, so a large sweep need not be run twice. Each line also gives the sweep's own rate after
start-up (the ``N run in T s`` of its summary line). Prints a table and writes JSON.

``--scaling 1,2,4`` instead times the sweep alone at each worker count and reports the efficiency
``rate(n) / (n rate(first))`` after start-up; with ``--device cuda`` each worker is one GPU
(dask-cuda).

Usage::

    python benchmarks/bench_sweep.py --device cpu --variants 64
    python benchmarks/bench_sweep.py --device cuda:0 --variants 1024
    python benchmarks/bench_sweep.py --processes --device cpu --variants 16 --workers 2
    python benchmarks/bench_sweep.py --processes --device cuda:0 --variants 4000 --runs 32 --workers 1
    python benchmarks/bench_sweep.py --device cuda --variants 4000 --scaling 1,2,4 --out bench_sweep_scaling.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

SCENE = "seed_bowl"
KS_LO, KS_HI = 1000, 8000


def _softsim(*argv):
    return [sys.executable, "-m", "softsim_warp", *argv]


def ks_values(n: int) -> list[float]:
    return [KS_LO + (KS_HI - KS_LO) * i / max(n - 1, 1) for i in range(n)]


def time_sweep(args, folder: Path, workers=None) -> dict:
    out = folder / f"sweep{workers or ''}.parquet"
    cmd = _softsim("sweep", SCENE, "--duration", str(args.duration), "--vary",
                   f"jelly.0.springs.*.ks={KS_LO}:{KS_HI}:{args.variants}", "--device", args.device, "--out", str(out))
    workers = workers or args.workers
    if workers:
        cmd += ["--workers", str(workers)]
    if args.batch:
        cmd += ["--batch", str(args.batch)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"sweep failed ({done.returncode}):\n{done.stderr}")
    m = re.search(r"(\d+) run in ([0-9.]+) s", done.stderr)
    tasks = re.search(r"(\d+) tasks of up to (\d+) worlds", done.stderr)
    ran, inner = (int(m.group(1)), float(m.group(2))) if m else (args.variants, wall)
    return {
        "method": "sweep" if workers is None else f"sweep, {workers} workers",
        "workers": workers,
        "variants": args.variants,
        "wall_seconds": wall,
        "variants_per_second": args.variants / wall,
        "after_startup_seconds": inner,
        "variants_per_second_after_startup": ran / inner if inner > 0 else None,
        "tasks": int(tasks.group(1)) if tasks else None,
        "batch": int(tasks.group(2)) if tasks else None,
    }


def time_runs(args, folder: Path, parallel: int) -> dict:
    ks = ks_values(args.variants)[: args.runs or args.variants]

    def one(i):
        k = ks[i]
        cmd = _softsim("run", SCENE, "--duration", str(args.duration), "--device", args.device, "--quiet",
                       "--out", str(folder / f"run{i}.usdc"))
        for t in ("structural", "shear", "bending"):
            cmd += ["--set", f"jelly.0.springs.{t}.ks={k}"]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode not in (0, 3):  # 3: exploded, still a result
            raise SystemExit(f"softsim run failed ({done.returncode}):\n{done.stderr}")

    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=parallel) as pool:
        list(pool.map(one, range(len(ks))))
    wall = time.perf_counter() - t0
    return {
        "method": "run, serial" if parallel == 1 else f"run, {parallel} parallel",
        "variants": len(ks),
        "wall_seconds": wall,
        "variants_per_second": len(ks) / wall,
    }


def plan(args) -> list[dict]:
    """The variants as the sweep's tasks receive them (validated scene dicts)."""
    from softsim_warp.io import scene as scene_mod  # noqa: PLC0415
    from softsim_warp.io.sweep import parse_axis, plan_sweep  # noqa: PLC0415

    _, source, base = scene_mod.read_scene_data(SCENE)
    base["simulation"]["duration"] = args.duration
    variants = plan_sweep(base, source, [parse_axis(f"jelly.0.springs.*.ks={KS_LO}:{KS_HI}:{args.variants}")])
    return [{"id": v.id, "data": v.data, "reference": v.reference} for v in variants]


def time_batch(args) -> dict:
    """The sweep's task code on ``args.device`` in this process, and ``softsim bench`` on its model."""
    import numpy as np  # noqa: PLC0415

    from softsim_warp.studies.bench import IntegratorCase  # noqa: PLC0415
    from softsim_warp.io.sweep import batch as batch_mod  # noqa: PLC0415
    from softsim_warp.io.warp_init import init_warp  # noqa: PLC0415

    wp = init_warp()
    device = wp.get_device(args.device)
    specs = plan(args)
    size = args.batch or len(specs)
    # Start-up, not timed: a first model builds the kernel objects and loads the modules a build uses.
    t0 = time.perf_counter()
    batch_mod._Batch([specs[0]["data"]], device, True)
    startup = time.perf_counter() - t0
    build = compile_s = frames = 0.0
    phases = {"launch_seconds": 0.0, "read_seconds": 0.0, "judge_seconds": 0.0}
    rows, model, integrator = [], None, None
    for i in range(0, len(specs), size):
        t = {}
        rows += batch_mod._simulate(specs[i: i + size], device, timings=t)
        build += t["build_seconds"]
        compile_s += t["compile_seconds"]
        frames += t["step_seconds"]
        for key in phases:
            phases[key] += t[key]
        model, integrator = t["model"], t["integrator"]
    work = sum(r["particles"] * r["steps"] for r in rows)
    data = specs[0]["data"]["simulation"]
    case = IntegratorCase(model, data["integrator"], data["dt"], args.bench_steps, use_graph=True)
    case.integrator = integrator  # the batch's own (one method per world), as its steps used it
    case.prepare()
    for _ in range(args.repeats):
        case.time_once()
    bench_rate = model.particle_count / (case.ms_per_step() * 1e-3)
    sweep_rate = work / frames
    statuses = {s: sum(r["status"] == s for r in rows) for s in {r["status"] for r in rows}}
    return {
        "device": str(device),
        "variants": len(specs),
        "batch": size,
        "particles_per_variant": rows[0]["particles"],
        "steps_per_variant": int(np.max([r["steps"] for r in rows])),
        "statuses": statuses,
        "build_seconds": build,
        "startup_seconds": startup,
        "compile_seconds": compile_s,
        "frames_seconds": frames,
        **{f"frames_{key}": value for key, value in phases.items()},
        "judge_us_per_world_frame": phases["judge_seconds"] / max(sum(r["frames"] for r in rows), 1) * 1e6,
        "variants_per_second": len(specs) / (build + frames),
        "variants_per_second_frames": len(specs) / frames,
        "particle_steps_per_second": sweep_rate,
        "bench_particles": model.particle_count,
        "bench_steps": case.steps,
        "bench_ms_per_step": case.ms_per_step(),
        "bench_particle_steps_per_second": bench_rate,
        "share_of_bench": sweep_rate / bench_rate,
    }


def run_batch_table(args):
    r = time_batch(args)
    print(f"{SCENE} (10^3 particles), {args.duration:g} s simulated, ks {KS_LO}..{KS_HI} over {r['variants']} "
          f"variants in batches of {r['batch']}, device {r['device']} ({r['statuses']})")
    print(f"{'build [s]':>10}{'load [s]':>10}{'frames [s]':>11}{'variants/s':>12}{'particle-steps/s':>18}"
          f"{'bench p-steps/s':>17}{'sweep/bench':>13}")
    print(f"{r['build_seconds']:>10.3f}{r['compile_seconds']:>10.2f}{r['frames_seconds']:>11.3f}"
          f"{r['variants_per_second']:>12.4g}{r['particle_steps_per_second']:>18.4g}"
          f"{r['bench_particle_steps_per_second']:>17.4g}{r['share_of_bench']:>12.0%}")
    print(f"(variants/s counts the build and the frames, not the start-up ({r['startup_seconds']:.2f} s) or the "
          f"kernels' loading; frames alone: "
          f"{r['variants_per_second_frames']:.4g} variants/s; bench: {r['bench_particles']} particles, "
          f"{r['bench_ms_per_step']:.3f} ms/step over {r['bench_steps']} steps)")
    print(f"frames: launching the steps {r['frames_launch_seconds']:.3f} s (on the CPU: taking them), the reductions "
          f"and reading them {r['frames_read_seconds']:.3f} s (on CUDA: mostly waiting for the steps), judging the "
          f"worlds on the host {r['frames_judge_seconds']:.4f} s ({r['judge_us_per_world_frame']:.2f} us per world "
          f"a frame)")
    report = {"scene": SCENE, "duration": args.duration, "host": platform.node(),
              "cpus": len(os.sched_getaffinity(0)), "batch": r}
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"-> {args.out}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--variants", type=int, default=16)
    p.add_argument("--processes", action="store_true",
                   help="compare whole processes: softsim sweep against separate softsim run processes")
    p.add_argument("--bench-steps", type=int, default=100, help="steps of the softsim bench replay (default 100)")
    p.add_argument("--repeats", type=int, default=5, help="softsim bench replays timed (median; default 5)")
    p.add_argument("--runs", type=int, help="separate runs timed (default: every variant)")
    p.add_argument("--workers", type=int, help="sweep workers and parallel runs (default: sweep's default; runs: CPUs)")
    p.add_argument("--batch", type=int, help="the sweep's --batch")
    p.add_argument("--duration", type=float, default=1.0)
    p.add_argument("--no-serial", action="store_true", help="skip the serial runs")
    p.add_argument("--scaling", help="comma-separated worker counts: the sweep alone at each, with the efficiency "
                   "rate(n) / (n rate(first)); with --device cuda one worker per GPU (dask-cuda)")
    p.add_argument("--out", default="bench_sweep.json")
    args = p.parse_args(argv)

    if args.scaling:
        run_scaling(args)
        return
    if not args.processes:
        run_batch_table(args)
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rows.append(time_sweep(args, folder))
        if not args.no_serial:
            rows.append(time_runs(args, folder, 1))
        parallel = args.workers or len(os.sched_getaffinity(0))
        if parallel > 1:
            rows.append(time_runs(args, folder, parallel))
    base = next((r for r in rows if r["method"] == "run, serial"), rows[-1])
    print(f"{SCENE} (10^3 particles), {args.duration:g} s simulated, ks {KS_LO}..{KS_HI} over {args.variants} "
          f"variants, device {args.device}")
    print(f"{'method':<18}{'variants':>9}{'wall [s]':>10}{'variants/s':>12}{'vs serial':>10}{'after start-up':>16}")
    for r in rows:
        after = r.get("variants_per_second_after_startup")
        print(f"{r['method']:<18}{r['variants']:>9}{r['wall_seconds']:>10.2f}{r['variants_per_second']:>12.3g}"
              f"{r['variants_per_second'] / base['variants_per_second']:>9.2f}x"
              f"{(f'{after:.3g}/s' if after else ''):>16}")
    report = {
        "scene": SCENE,
        "duration": args.duration,
        "device": args.device,
        "workers": args.workers,
        "host": platform.node(),
        "cpus": len(os.sched_getaffinity(0)),
        "rows": rows,
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"-> {args.out}")


def run_scaling(args):
    counts = [int(n) for n in args.scaling.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            rows.append(time_sweep(args, Path(tmp), workers=n))
    first = rows[0]
    print(f"{SCENE} (10^3 particles), {args.duration:g} s simulated, {args.variants} variants, device {args.device}")
    print(f"{'workers':>8}{'tasks':>7}{'batch':>7}{'wall [s]':>10}{'variants/s':>12}{'after start-up':>16}"
          f"{'efficiency':>12}")
    for r in rows:
        rate = r["variants_per_second_after_startup"] or r["variants_per_second"]
        base = first["variants_per_second_after_startup"] or first["variants_per_second"]
        r["efficiency"] = rate / (base * r["workers"] / first["workers"])
        print(f"{r['workers']:>8}{r['tasks'] or 0:>7}{r['batch'] or 0:>7}{r['wall_seconds']:>10.2f}"
              f"{r['variants_per_second']:>12.3g}{rate:>14.3g}/s{r['efficiency']:>11.0%}")
    report = {"scene": SCENE, "duration": args.duration, "device": args.device, "host": platform.node(),
              "scaling": rows}
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
