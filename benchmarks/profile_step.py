"""Profile: the time of each kernel in a step, from CUDA's activity records (a GPU tool).

Two cases, each stepped uncaptured (kernel by kernel) after warm-up steps, then ``--steps`` steps
recorded with ``wp.timing_begin`` / ``wp.timing_end``; the table sums each kernel's time over the
recorded steps and divides by them (ms per step), largest first. Kernels launched inside a graph
are not recorded by name, so nothing here is captured: the launch gaps of uncaptured steps are not
in the table (it sums kernel time only), but the total is not the captured step's time either.

With ``--captured R``, each launch of one step is instead timed on its own, as R launches captured
in a graph and replayed (median of 7 replays), in the step's order: the cost a launch has inside
the captured step, without the launch gaps that uncaptured steps add.

With ``--passes K,K,...`` (``contact`` only), whole steps are timed as ``softsim bench --contact``
times them (``--steps`` steps captured in a graph, the median of 7 replays, the cases in turn): the
step without contact, and the step with contact with K velocity passes for each K (at least 1: the
last pass writes the step's result back): what a pass costs inside the step. Each case steps its
own states from the pile's start; the table gives each case's list builds, so that cases whose piles moved differently
show it.

* ``implicit``: the stiff spinning jelly of ``bench_implicit.py`` at ``--size``^3, implicit Euler
  (``--preconditioner``), ``--dt``.
* ``contact``: the pile of ``softsim bench --contact`` (``--jellies`` jellies of 10^3), symplectic.

Usage::

    python benchmarks/profile_step.py implicit --device cuda:0 --size 100 --out prof_mg.json
    python benchmarks/profile_step.py contact --device cuda:0 --jellies 1000 --out prof_contact.json
    python benchmarks/profile_step.py contact --device cuda:0 --jellies 1000 --warmup 200 --captured 50
    python benchmarks/profile_step.py contact --device cuda:0 --jellies 1000 --steps 100 --passes 0,1,2,4
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys

import warp as wp

from softsim_warp.studies.timing import TimedSteps

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def _implicit_case(args, device):
    from bench_implicit import stiff_jelly  # noqa: PLC0415

    from softsim_warp.core.implicit import ImplicitIntegrator  # noqa: PLC0415

    model = stiff_jelly(args.size, args.ks, device, args.precision)
    integ = ImplicitIntegrator(model, preconditioner=args.preconditioner)
    integ._graph_ok = False  # the CG loop launch by launch (a captured loop's kernels go unnamed)
    states = [model.state(), model.state()]

    def step(k):
        integ.step(states[k % 2], states[1 - k % 2], args.dt)

    return step, integ


def _contact_case(args, device):
    from softsim_warp.studies.bench import JellySpec  # noqa: PLC0415
    from softsim_warp.studies.bench_contact import build_pile  # noqa: PLC0415
    from softsim_warp.core.stepper import make_integrator  # noqa: PLC0415

    spec = JellySpec()
    model = build_pile(args.jellies, 10, spec, device, args.precision, contact=True)
    integ = make_integrator("symplectic", model)
    states = [model.state(), model.state()]

    def step(k):
        integ.step(states[k % 2], states[1 - k % 2], spec.dt)

    return step, integ


def _captured(args, device, step) -> int:
    """Each launch of one step, timed as ``args.captured`` launches of it in a replayed graph
    (softsim bench's timing: the median of 7 replays)."""
    launches = []
    launch = wp.launch

    def record(kernel, dim, inputs=(), outputs=(), device=None, **kwargs):
        launches.append((kernel, dim, list(inputs), list(outputs), kwargs))
        return launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, **kwargs)

    wp.launch = record
    try:
        step(args.warmup)
    finally:
        wp.launch = launch
    wp.synchronize_device(device)
    rows = []
    for kernel, dim, inputs, outputs, kwargs in launches:

        def repeat(count, kernel=kernel, dim=dim, inputs=inputs, outputs=outputs, kwargs=kwargs):
            for _ in range(count):
                launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device, **kwargs)

        timed = TimedSteps(device, repeat, args.captured, use_graph=True)
        timed.prepare()
        for _ in range(7):
            timed.time_once()
        rows.append((kernel.key, dim, timed.ms_per_step()))
    total = sum(t for _, _, t in rows)
    print(f"{args.case} on {device.name}: {len(rows)} launches a step, each timed as {args.captured} captured launches")
    print(f"{'kernel':<60} {'dim':>10} {'ms':>9}")
    for key, dim, t in rows:
        print(f"{key[-60:]:<60} {dim!s:>10} {t:9.4f}")
    print(f"{'sum':<60} {'':>10} {total:9.4f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"case": args.case, "args": vars(args), "device_name": device.name, "launch_ms": rows}, f, indent=1)
    return 0


def _pass_counts(args) -> list[int]:
    """``--passes`` as counts of velocity passes (a one-line exit for anything else)."""
    if args.case != "contact":
        raise SystemExit("--passes applies to the contact case only")
    try:
        counts = [int(t) for t in args.passes.split(",") if t.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise SystemExit(f"--passes: expected comma-separated counts >= 1, got {args.passes!r}")
    return counts


def _passes(args, device, model, counts, repeats=7) -> int:
    """The whole step with each count of velocity passes, against the step without contact."""
    from softsim_warp.studies.bench import JellySpec  # noqa: PLC0415
    from softsim_warp.studies.bench_contact import PileCase  # noqa: PLC0415

    dt = JellySpec().dt

    def case(contact, passes=0):
        # Each case steps its own states from the pile's start, as softsim bench --contact's do,
        # with its own integrator and so its own contact lists (its run state).
        timed = PileCase(model, "symplectic", dt, args.steps, True, contact)
        hook = timed.integrator.run.particle_contact
        hook.pass_records = [wp.zeros_like(hook.warm_records) for _ in range(2)]  # the passes' buffers for any count
        hook.iterations = passes
        timed.contact = hook
        builds = hook.builds_done()
        timed.prepare()
        timed.builds = hook.builds_done() - builds
        return timed

    cases = {"no contact": case(False)}
    for k in counts:
        cases[f"contact, {k} velocity passes"] = case(True, k)
    for _ in range(repeats):
        for timed in cases.values():
            builds = timed.contact.builds_done()
            timed.time_once()
            timed.builds += timed.contact.builds_done() - builds
    base = cases["no contact"].ms_per_step()
    rows = [(name, t.ms_per_step(), t.ms_per_step() / base, t.builds) for name, t in cases.items()]
    # Steps each case ran: two first steps, the graph's replay in prepare, then the timed replays.
    steps = 2 + (1 + repeats) * cases["no contact"].steps
    print(f"{args.case} on {device.name}: {args.jellies} jellies, {args.steps} steps captured, median of {repeats}")
    print(f"{'case':<32} {'ms/step':>9} {'x no contact':>13} {f'list builds in {steps} steps':>28}")
    for name, ms, ratio, builds in rows:
        print(f"{name:<32} {ms:9.4f} {ratio:13.2f} {builds if name != 'no contact' else '':>28}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(
                {"case": args.case, "args": vars(args), "device_name": device.name, "steps_ms": rows}, f, indent=1
            )
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case", choices=["implicit", "contact"])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--ks", type=float, default=1.0e5)
    p.add_argument("--dt", type=float, default=0.01)
    p.add_argument("--preconditioner", default="multigrid")
    p.add_argument("--jellies", type=int, default=1000)
    p.add_argument("--precision", default="float32")
    p.add_argument("--warmup", type=int, default=6)
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--out", default=None)
    p.add_argument("--sequence", type=int, default=0, help="also print the first N launches of the last step in order")
    p.add_argument("--captured", type=int, default=0, help="time each launch of a step as N captured launches")
    p.add_argument("--passes", default=None, help="contact: time whole steps with these counts of velocity passes")
    args = p.parse_args(argv)
    counts = _pass_counts(args) if args.passes else None
    wp.init()
    device = wp.get_device(args.device)
    step, integ = (_implicit_case if args.case == "implicit" else _contact_case)(args, device)
    for k in range(args.warmup):
        step(k)
    wp.synchronize_device(device)
    if args.captured:
        return _captured(args, device, step)
    if args.passes:
        return _passes(args, device, integ.model, counts)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    for k in range(args.steps):
        step(args.warmup + k)
    results = wp.timing_end()
    ms = collections.defaultdict(float)
    launches = collections.Counter()
    for r in results:
        name = r.name.split("forward_kernel_")[0].removeprefix("forward kernel ").split("_cuda_kernel")[0]
        ms[name] += r.elapsed / args.steps
        launches[name] += 1
    if args.sequence:
        per_step = len(results) // args.steps
        for r in results[-per_step:][: args.sequence]:
            print(f"  {r.name.split('_cuda_kernel')[0][-40:]:<40} {1e3 * r.elapsed:8.1f} us")
    total = sum(ms.values())
    rows = sorted(ms.items(), key=lambda kv: -kv[1])
    print(f"{args.case} on {device.name}: kernel time per step {total:.3f} ms over {args.steps} uncaptured steps")
    print(f"{'kernel':<48} {'ms/step':>9} {'share':>6} {'launches/step':>14}")
    for name, t in rows:
        print(f"{name[:48]:<48} {t:9.4f} {100 * t / total:5.1f}% {launches[name] / args.steps:14.1f}")
    stats = integ.stats() if hasattr(integ, "stats") else {}
    if stats:
        print("stats:", {k: v for k, v in stats.items() if isinstance(v, (int, float))})
    if args.out:
        with open(args.out, "w") as f:
            json.dump(
                {
                    "case": args.case,
                    "args": vars(args),
                    "device_name": device.name,
                    "kernel_ms_per_step": dict(rows),
                    "launches_per_step": {k: launches[k] / args.steps for k in ms},
                    "stats": {k: v for k, v in stats.items() if isinstance(v, (int, float, str))},
                },
                f,
                indent=1,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
