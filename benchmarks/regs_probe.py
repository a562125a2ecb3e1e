"""Does capping the fused stage's registers (more resident warps) speed it up? A measurement.

    python benchmarks/regs_probe.py --device cuda:0 --size 100 --caps 0,80,72,64,56
    python benchmarks/regs_probe.py --device cuda:0 --size 100 --caps 0 \
        --kernels integrate_lattice_stage_stencil,integrate_lattice_stage

The fused stage kernels named by ``--kernels`` (``integrate_lattice_stage_padded``: the native
gather over padded arrays, what the model's states get; ``integrate_lattice_stage_padded_uniform``:
the same with the coefficients as a kernel argument, what large models of jellies that share them
get; ``integrate_lattice_stage_single``: that for one jelly of one mass; ``integrate_lattice_stage``:
the native gather with bounds-checked loads; ``integrate_lattice_stage_stencil``: the Warp-loop gather;
``gather:OPT+OPT``: the native gather built with those ``_gather_snippet`` options, plus ``indexed``
and ``single`` for the stage's own options; ``single_stage``: the one-jelly stage the model steps
with, compiled for its jelly), each compiled with
``cuda_max_registers`` at each cap (0: the compiler's choice), stepped through the benchmark jelly
with CUDA graphs, the stages sweeping in alternating directions or always forward (``--sweeps``),
at the given threads per block (``--block-dims``) and with a spacer allocated before each model
(``--shifts``, KiB: where its arrays land); the variants are timed in turn, round after round, in one process. The cap is
ignored on the CPU. Each variant's final positions are compared with the first variant's of the
same integrator (``max_rel_diff`` in the JSON; on the CPU the native and Warp-loop gathers give the
same bits). Results: docs/PERFORMANCE.md.
"""

import argparse
import json
import time
import types

import numpy as np
import warp as wp

from softsim_warp.commands.bench import JellySpec, build_jelly_model
from softsim_warp.core.integrators import ExplicitIntegrator


def stage_kernel(kernels, name, model=None):
    """A stage kernel by name: one in ``model.kernels``, or ``gather:OPT+OPT`` for the fused stage
    around ``gather_native`` built with those ``_gather_snippet`` options (e.g. ``gather:padded``; the
    option ``indexed`` builds the stage with Warp-indexed reads instead); ``single_stage``: what a
    one-jelly model steps with, ``model.kernels.single_stage`` for ``model``'s jelly."""
    if name == "single_stage":
        layout = model.lattice.layout
        return kernels.single_stage(layout.shape[0], layout.types[0])
    if not name.startswith("gather:"):
        return getattr(kernels, name)
    options = {opt: True for opt in name.split(":", 1)[1].split("+") if opt}
    # "indexed": the stage's own reads through Warp's indexing (make_integrate_lattice_stage(direct=False)).
    direct = not options.pop("indexed", False)
    # "single": the one-jelly stage (make_integrate_lattice_stage(single=True)).
    single = options.pop("single", False)
    return kernels.make_integrate_lattice_stage(kernels.make_gather_native(**options), direct=direct, single=single)


def install_stage_kernel(model, kernel):
    """Make the model's fused stages launch ``kernel``, whichever gather ``step_fused`` would pick
    (the padded one for the model's own states, the checked one for other arrays)."""
    model.kernels = types.SimpleNamespace(**vars(model.kernels))
    k = model.kernels
    k.integrate_lattice_stage = k.integrate_lattice_stage_padded = kernel
    k.integrate_lattice_stage_padded_uniform = k.integrate_lattice_stage_single = kernel
    k.single_stage = lambda shape, types: kernel


def variant_kernel(kernel, cap):
    if cap == 0:
        return kernel
    return wp.kernel(kernel.func, module="unique", cuda_max_registers=cap)


def _rel_diff(case, ref):
    """Largest position difference between two variants' final states, relative to the largest coordinate."""
    q = case["states"][0].particle_q.numpy().astype(np.float64)
    q_ref = ref["states"][0].particle_q.numpy().astype(np.float64)
    return float(np.abs(q - q_ref).max() / np.abs(q_ref).max())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--caps", default="0,80,72,64,56")
    parser.add_argument("--kernels", default="integrate_lattice_stage", help="stage kernels (names in model.kernels)")
    parser.add_argument("--integrators", default="symplectic,rk4")
    parser.add_argument("--block-dims", default="0", help="threads per block (0: the integrator's choice)")
    parser.add_argument(
        "--shifts", default="0", help="KiB allocated (and kept) before each model: where its arrays land in memory"
    )
    parser.add_argument(
        "--sweeps", default="alternate", help="alternate and/or forward: the stages' particle order (step_fused)"
    )
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    spec = JellySpec()
    caps = [int(c) for c in args.caps.split(",")]
    keep, cases, built = [], [], {}
    variants = [
        (name, cap, sweep, int(block), int(shift))
        for name in args.kernels.split(",")
        for cap in caps
        for sweep in args.sweeps.split(",")
        for block in args.block_dims.split(",")
        for shift in args.shifts.split(",")
    ]
    for method in args.integrators.split(","):
        for name, cap, sweep, block, shift in variants:
            # A spacer before the model moves where its arrays land (kept alive with the case).
            spacer = wp.empty(256 * int(shift), dtype=wp.float32, device=args.device)
            model = build_jelly_model(args.size, spec, args.device)
            model.lattice.set_kernel("gather")  # the per-particle stage kernels (the CPU default is "rows")
            if (name, cap) not in built:  # one build per variant, shared by the integrators
                built[name, cap] = variant_kernel(stage_kernel(model.kernels, name, model), cap)
            install_stage_kernel(model, built[name, cap])
            integrator = ExplicitIntegrator(model, method, alternate=sweep == "alternate", block_dim=block or None)
            states = [model.state(), model.state()]

            def step(count, integrator=integrator, states=states):
                for k in range(count):
                    integrator.step(states[k % 2], states[1 - k % 2], spec.dt)

            step(2)
            wp.synchronize_device(args.device)
            graph = None
            if wp.get_device(args.device).is_cuda:
                with wp.ScopedCapture(device=args.device, force_module_load=False) as capture:
                    step(args.steps)
                graph = capture.graph
            keep.append((spacer, model, integrator, states))
            cases.append(
                {
                    "integrator": method,
                    "kernel": name,
                    "cap": cap,
                    "sweep": sweep,
                    "block_dim": integrator.block_dim,
                    "shift_kib": int(shift),
                    "states": states,
                    "step": step,
                    "graph": graph,
                    "wall": [],
                }
            )
    for _ in range(args.repeats):
        for case in cases:
            wp.synchronize_device(args.device)
            t0 = time.perf_counter()
            if case["graph"] is not None:
                wp.capture_launch(case["graph"])
            else:
                case["step"](args.steps)
            wp.synchronize_device(args.device)
            case["wall"].append(time.perf_counter() - t0)
    rows = []
    print(
        f"{'integrator':<12}{'kernel':<40}{'cap':>6}{'sweep':>11}{'block':>7}{'shift':>7}{'ms/step':>12}{'vs first':>10}"
    )
    for case in cases:
        ms = 1e3 * float(np.median(case["wall"])) / args.steps
        base = next((c for c in rows if c["integrator"] == case["integrator"]), None)
        ratio = base["ms_per_step"] / ms if base else 1.0
        rows.append(
            {
                "integrator": case["integrator"],
                "kernel": case["kernel"],
                "cap": case["cap"],
                "sweep": case["sweep"],
                "block_dim": case["block_dim"],
                "shift_kib": case["shift_kib"],
                "state_address": case["states"][0].particle_q.ptr,
                "ms_per_step": ms,
                "speedup": ratio,
                "max_rel_diff": _rel_diff(case, next(c for c in cases if c["integrator"] == case["integrator"])),
            }
        )
        print(
            f"{case['integrator']:<12}{case['kernel']:<40}{case['cap']:>6}{case['sweep']:>11}{case['block_dim']:>7}{case['shift_kib']:>7}{ms:>12.4f}{ratio:>9.2f}x"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"device": str(wp.get_device(args.device)), "size": args.size, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
