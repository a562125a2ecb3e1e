"""Benchmark: the implicit solve with the multigrid preconditioner against block-Jacobi, by resolution.

The stiff jelly of ``bench_implicit.py`` (0.5 m cube of 1 kg, every spring type at ``--ks``, spinning
in free flight) takes ``--steps`` implicit steps of ``--dt`` at each size with each preconditioner.
Reported per case: ms per step (on CUDA the steps replay a captured graph), CG iterations per step
(mean/max), unconverged solves, and the time of each part of the solve, each timed alone over
repeated launches: the multigrid setup (one build of the Galerkin hierarchy, which a free-flight step
does on one in ``setup_every`` of its solves), one V-cycle,
and one CG iteration without its preconditioner (the spring product and the vector updates);
"per step" multiplies them by the step's solves and iterations. The device memory of the
hierarchy is in the JSON.

Usage::

    python benchmarks/bench_multigrid.py --device cpu --sizes 10 20 --out mg_cpu.json
    python benchmarks/bench_multigrid.py --device cuda:0 --sizes 10 20 40 100 --steps 20 --out mg_cuda.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_implicit import _time_steps, stiff_jelly  # noqa: E402

from softsim_warp.core.implicit import ImplicitIntegrator  # noqa: E402
from softsim_warp.core.multigrid import LatticeMultigrid  # noqa: E402
from softsim_warp.kernels import implicit as implicit_kernels  # noqa: E402


def _time_call(fn, device, repeats: int) -> float:
    """Seconds per call of ``fn`` (launches only), averaged over ``repeats`` after one warm-up call."""
    fn()
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / repeats


def _cg_iteration_parts(integ):
    """One CG iteration's launches without the preconditioner (as in ImplicitIntegrator._pcg_loop)."""
    model = integ.model
    device = model.device
    n = model.particle_count
    blocks = (n + implicit_kernels.TILE - 1) // implicit_kernels.TILE
    mg = integ.multigrid
    precond = integ.precond if mg is None else integ.no_precond
    lattice_product = mg is not None and mg.gather

    def run():
        wp.launch(
            implicit_kernels.cg_direction, dim=(blocks, implicit_kernels.TILE), block_dim=implicit_kernels.TILE,
            inputs=[n, int(not lattice_product), integ.mass_eff, integ.z], outputs=[integ.p, integ.ap, integ.scalars],
            device=device,
        )
        if lattice_product:
            mg.product(integ.p, integ.ap, integ.scalars, implicit_kernels.PAP)
        else:
            integ._spring_mv(integ.p)
        wp.launch(
            implicit_kernels.cg_update, dim=(blocks, implicit_kernels.TILE), block_dim=implicit_kernels.TILE,
            inputs=[n, int(mg is None), integ.filters, precond, integ.p, integ.ap],
            outputs=[integ.x, integ.r, integ.z, integ.scalars], device=device,
        )
        wp.launch(implicit_kernels.cg_end_iteration, dim=1, inputs=[integ.cg_max_iterations], outputs=[integ.scalars, integ.ints],
                  device=device)

    return run


def measure(size: int, preconditioner: str, device, steps: int, dt: float, ks: float, precision: str,
            repeats: int, options=None) -> dict:
    model = stiff_jelly(size, ks, device, precision)
    integ = ImplicitIntegrator(model, preconditioner=preconditioner)
    if options and integ.multigrid is not None:
        integ.multigrid = LatticeMultigrid(model, integ, **options)
    compile_s, seconds, finite = _time_steps(integ, model, dt, steps)
    stats = integ.stats()
    solves_per_step = stats["cg_solves"] / max(stats["cg_steps"], 1)
    its = stats["cg_iterations_mean"]
    parts = {"cg_iteration_ms": 1e3 * _time_call(_cg_iteration_parts(integ), device, repeats)}
    mg = integ.multigrid
    if mg is not None:
        # One build of the hierarchy; a step builds on solves_per_step / setup_every of its solves
        # (free flight: no contact constraints, which would rebuild every solve).
        parts["setup_ms"] = 1e3 * _time_call(mg.build, device, repeats)
        parts["vcycle_ms"] = 1e3 * _time_call(
            lambda: mg.apply(integ.r, integ.z, integ.scalars, implicit_kernels.RZ_NEW), device, repeats
        )
    else:
        parts["setup_ms"] = 0.0
        parts["vcycle_ms"] = 0.0
    per_step = {
        "setup_ms": parts["setup_ms"] * solves_per_step / (mg.setup_every if mg is not None else 1),
        "vcycle_ms": parts["vcycle_ms"] * (its + solves_per_step),
        "cg_iterations_ms": parts["cg_iteration_ms"] * its,
    }
    ms = 1e3 * seconds / steps
    return {
        "size": size,
        "particles": model.particle_count,
        "springs": model.spring_count,
        "preconditioner": integ.preconditioner,
        "setup_every": integ.multigrid.setup_every if integ.multigrid is not None else None,
        "precision": precision,
        "ks": ks,
        "dt": dt,
        "steps": steps,
        "ms_per_step": ms,
        "cg_iterations_mean": its,
        "cg_iterations_max": stats["cg_iterations_max"],
        "cg_solves_per_step": solves_per_step,
        "cg_unconverged_solves": stats["cg_unconverged_solves"],
        "parts_ms_each": parts,
        "parts_ms_per_step": per_step,
        "multigrid_levels": stats.get("multigrid_shapes"),
        "multigrid_bytes": mg.nbytes() if mg is not None else 0,
        "compile_seconds": compile_s,
        "finite": finite,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--sizes", type=int, nargs="+", default=[10, 20], help="particles per axis")
    p.add_argument(
        "--preconditioners", nargs="+", default=["jacobi", "multigrid"],
        help="jacobi, multigrid (its defaults); integer options of LatticeMultigrid after slashes, e.g. "
        "multigrid/setup_every=1/sweeps=2",
    )
    p.add_argument("--ks", type=float, default=1.0e5, help="spring stiffness of every type [N/m]")
    p.add_argument("--dt", type=float, default=0.01, help="implicit step [s]")
    p.add_argument("--steps", type=int, default=10, help="timed steps per case")
    p.add_argument("--repeats", type=int, default=10, help="repetitions of each timed part")
    p.add_argument("--precision", default="float32", choices=("float32", "float64"))
    p.add_argument("--out", default="bench_multigrid.json")
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    header = (
        f"{'n^3':>5} {'particles':>9} {'precond':>24} {'ms/step':>9} {'CG it mean/max':>15} {'unconv':>6} "
        f"{'setup ms':>9} {'V-cycles ms':>11} {'CG it ms':>9}  (per step)"
    )
    print(f"implicit, ks = {args.ks:.0e}, dt = {args.dt}, {args.precision}, {device} ({device.name})")
    print(header)
    print("-" * len(header))
    rows = []
    for size in args.sizes:
        for pc in args.preconditioners:
            name, *opts = pc.split("/")
            options = {key: int(value) for key, value in (o.split("=") for o in opts)}
            r = measure(size, name, device, args.steps, args.dt, args.ks, args.precision, args.repeats, options)
            r["preconditioner"] = pc if opts else r["preconditioner"]
            per = r["parts_ms_per_step"]
            print(
                f"{size:5d} {r['particles']:9d} {r['preconditioner']:>24} {r['ms_per_step']:9.2f} "
                f"{r['cg_iterations_mean']:8.1f}/{r['cg_iterations_max']:<6d} {r['cg_unconverged_solves']:6d} "
                f"{per['setup_ms']:9.2f} {per['vcycle_ms']:11.2f} {per['cg_iterations_ms']:9.2f}",
                flush=True,
            )
            rows.append(r)
    by = {(r["size"], r["preconditioner"]): r for r in rows}
    sizes = sorted({r["size"] for r in rows})
    for pc in args.preconditioners:
        its = [by[(s, pc)]["cg_iterations_mean"] for s in sizes if (s, pc) in by]
        if pc.startswith("multigrid") and len(its) > 1 and its[0] > 0:
            print(f"{pc} CG iterations, largest / smallest size: {its[-1] / its[0]:.2f} (largest / fewest: "
                  f"{max(its) / min(its):.2f})")
    result = {
        "device": str(device),
        "device_name": device.name,
        "warp_version": wp.config.version,
        "platform": platform.platform(),
        "cases": rows,
    }
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
