"""Model build time: a sweep's batch of worlds and a scene of many jellies, builder plus finalize.

Two cases, each timed from the validated scene dicts to a ready :class:`~softsim_warp.core.model.Model`
on ``--device`` (the builder's ``populate`` calls, then ``finalize``; the scene validation and the
sweep's planning are not counted):

* ``batch``: ``--worlds`` variants of the seed jelly (``seed_bowl``, 10^3 particles, 3 spring
  types) with every spring type's ks spread from 1000 to 8000 N/m, planned by the sweep's own
  ``plan_sweep`` and built as one model of that many worlds (``io/worlds.make_builder``), as a
  sweep's batch is;
* ``pile``: one world of ``--jellies`` jellies of 10^3 particles stacked as ``softsim bench --contact``
  stacks them (``pile_positions``), with contact between jellies (``build_model``, as ``softsim run``).

Each case is built ``--repeats`` times and the median reported (the first build also loads the
kernels' modules, so it is run once untimed), as wall time and as the process's CPU time (the
build runs on one thread; on a shared machine its CPU time is the wall time it would take alone).
Prints a table and writes JSON.

Usage::

    python benchmarks/bench_build.py --out bench_build.json
    python benchmarks/bench_build.py --worlds 1024 --jellies 512 --repeats 5
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

SCENE = "seed_bowl"
KS_LO, KS_HI = 1000, 8000


def batch_datas(worlds: int) -> list[dict]:
    """The validated scene dicts of ``worlds`` sweep variants of the seed jelly (ks varied)."""
    from softsim_warp.io import scene as scene_mod
    from softsim_warp.io.sweep import parse_axis, plan_sweep

    _, source, base = scene_mod.read_scene_data(SCENE)
    axes = [parse_axis(f"jelly.0.springs.*.ks={KS_LO}:{KS_HI}:{worlds}")]
    return [v.data for v in plan_sweep(base, source, axes)]


def pile_data(jellies: int) -> dict:
    """A validated scene of ``jellies`` 10^3 jellies in a block on the ground, contact between them."""
    from softsim_warp.studies.bench_contact import pile_positions
    from softsim_warp.io import scene as scene_mod

    _, source, base = scene_mod.read_scene_data("seed_plane")
    jelly = base["jelly"][0]
    spacing = jelly["size"] / (jelly["resolution"][0] - 1)
    data = copy.deepcopy(base)
    data["jelly"] = [dict(copy.deepcopy(jelly), center=list(c)) for c in pile_positions(jellies, 10, spacing)]
    data["plane"][0]["point"] = [0.0, 0.0, 0.0]
    return scene_mod.validate(data, source)


def time_batch(datas, device):
    from softsim_warp.io.worlds import make_builder

    t0, c0 = time.perf_counter(), time.process_time()
    builder = make_builder(datas)
    t1 = time.perf_counter()
    model = builder.finalize(device, datas[0]["simulation"]["precision"])
    t2, c2 = time.perf_counter(), time.process_time()
    return t1 - t0, t2 - t1, c2 - c0, model


def time_pile(data, device):
    from softsim_warp.core.model import ModelBuilder, populate

    t0, c0 = time.perf_counter(), time.process_time()
    builder = ModelBuilder(data["simulation"]["gravity"])
    builder.device = device
    populate(builder, data)
    t1 = time.perf_counter()
    model = builder.finalize(device, data["simulation"]["precision"])
    t2, c2 = time.perf_counter(), time.process_time()
    return t1 - t0, t2 - t1, c2 - c0, model


def measure(name, fn, arg, device, repeats):
    fn(arg, device)  # loads the kernels' modules
    builds, finals, cpu = [], [], []
    for _ in range(repeats):
        b, f, c, model = fn(arg, device)
        builds.append(b)
        finals.append(f)
        cpu.append(c)
    total = [b + f for b, f in zip(builds, finals)]
    return {
        "case": name,
        "worlds": model.world_count,
        "jellies": len(model.jellies),
        "particles": model.particle_count,
        "springs": model.spring_count,
        "path": "lattice" if model.lattice is not None else model.lattice_reason,
        "builder_seconds": statistics.median(builds),
        "finalize_seconds": statistics.median(finals),
        "total_seconds": statistics.median(total),
        "cpu_seconds": statistics.median(cpu),
        "repeats": repeats,
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--worlds", type=int, default=1024, help="worlds of the batch case (default 1024)")
    p.add_argument("--jellies", type=int, default=512, help="jellies of the pile case (default 512)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None, help="JSON file to write")
    args = p.parse_args(argv)

    import warp as wp

    wp.config.quiet = True
    wp.init()
    rows = [
        measure("batch", time_batch, batch_datas(args.worlds), args.device, args.repeats),
        measure("pile", time_pile, pile_data(args.jellies), args.device, args.repeats),
    ]
    head = f"{'case':<6} {'worlds':>6} {'jellies':>7} {'particles':>9} {'springs':>9} {'builder s':>9} {'finalize s':>10} {'total s':>8} {'cpu s':>6}  path"
    print(head)
    for r in rows:
        print(f"{r['case']:<6} {r['worlds']:>6} {r['jellies']:>7} {r['particles']:>9} {r['springs']:>9} "
              f"{r['builder_seconds']:>9.3f} {r['finalize_seconds']:>10.3f} {r['total_seconds']:>8.3f} {r['cpu_seconds']:>6.3f}  {r['path']}")
    if args.out:
        import softsim_warp

        try:  # the commit of the package measured (which need not be this file's)
            commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                    check=False, cwd=Path(softsim_warp.__file__).parent).stdout.strip()
        except OSError:
            commit = ""
        info = {"device": args.device, "load_average": os.getloadavg()[0], "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine(),
                "python": platform.python_version(), "commit": commit}
        Path(args.out).write_text(json.dumps({"info": info, "rows": rows}, indent=2) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
