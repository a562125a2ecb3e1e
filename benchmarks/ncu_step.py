"""Steps the benchmark jelly without graphs, for a hardware-counter profile of one fused stage.

    ncu --clock-control none --set full -k regex:integrate_lattice_stage --launch-skip 10 \
        --launch-count 1 python benchmarks/ncu_step.py --size 100 --integrator symplectic

Graph replay hides kernels from a simple ``ncu`` filter, so this runs plain launches; the kernel
is the same one the graph replays. Results: docs/PERFORMANCE.md.
"""

import argparse
import os
import sys

import warp as wp

from softsim_warp.commands.bench import JellySpec, build_jelly_model
from softsim_warp.core.integrators import ExplicitIntegrator

sys.path.insert(0, os.path.dirname(__file__))
from regs_probe import install_stage_kernel, stage_kernel  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--integrator", default="symplectic")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--block-dim", type=int, default=None)
    parser.add_argument(
        "--kernel", default=None, help="stage kernel, as regs_probe --kernels (default: the model's own choice)"
    )
    args = parser.parse_args()
    spec = JellySpec()
    model = build_jelly_model(args.size, spec, args.device)
    if args.kernel is not None:
        install_stage_kernel(model, stage_kernel(model.kernels, args.kernel, model))
    integrator = ExplicitIntegrator(model, args.integrator, block_dim=args.block_dim)
    states = [model.state(), model.state()]
    for k in range(args.steps):
        integrator.step(states[k % 2], states[1 - k % 2], spec.dt)
    wp.synchronize_device(args.device)


if __name__ == "__main__":
    main()
