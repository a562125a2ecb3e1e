"""Benchmark: the multigrid's coarse stencil product with one thread per node against a block per node.

``core/multigrid.py`` takes the coarse levels of at most ``LANES_MAX_NODES`` nodes with
``mg_stencil_op_lanes`` (a block of ``LANES`` threads per node, a slot per thread) on CUDA, and the
larger ones with ``mg_stencil_op`` (one thread per node, its 26 blocks in turn). This times both
kernels (a Jacobi sweep, mode 1) on random stencils of cubic levels of the sizes a 100^3 jelly's
hierarchy has, each as the median over ``--repeats`` replays of a graph of ``--launches``
launches, side by side in one run, and the spring product of the jelly's lattice
(``mg_lattice_mv``) at ``--fine``^3 particles for scale. Times are per launch.

Usage::

    python benchmarks/bench_multigrid_kernels.py --device cuda:0 --out bench_multigrid_kernels.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from softsim_warp.studies.timing import TimedSteps  # noqa: E402
from softsim_warp.core import multigrid  # noqa: E402
from softsim_warp.kernels import implicit as implicit_kernels  # noqa: E402
from softsim_warp.kernels import multigrid as multigrid_kernels  # noqa: E402


def _per_launch_us(launch, device, launches: int, repeats: int) -> float:
    """Median microseconds per launch over ``repeats`` runs of ``launches`` launches (a replayed graph
    on CUDA; softsim bench's timing)."""
    timed = TimedSteps(device, lambda count: [launch() for _ in range(count)], launches, device.is_cuda)
    timed.prepare()
    for _ in range(repeats):
        timed.time_once()
    return 1e3 * timed.ms_per_step()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--sizes", type=int, nargs="+", default=[51, 26, 14, 8, 5, 3], help="nodes per axis of the levels")
    p.add_argument("--fine", type=int, default=100, help="particles per axis of the spring product's lattice")
    p.add_argument("--launches", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", help="write the results as JSON")
    args = p.parse_args(argv)
    wp.init()
    device = wp.get_device(args.device)
    mat33 = wp.types.matrix((3, 3), wp.float32)
    vec3 = wp.types.vector(3, wp.float32)
    rng = np.random.default_rng(0)
    lanes = multigrid.LANES if device.is_cuda else 1
    rows = []
    print(f"coarse stencil sweep on {device.name}: us per launch (median of {args.repeats} x {args.launches})")
    print(f"{'level':>7} {'nodes':>8} {'one thread/node':>16} {'block/node':>11} {'ratio':>6}")
    for n in args.sizes:
        count = n**3
        shape = wp.vec3i(n, n, n)

        def arr(*dims, dtype, scale=1.0):
            return wp.array(scale * rng.standard_normal(dims).astype(np.float32), dtype=dtype, device=device)

        a, rowsum, dinv = arr(27, count, 3, 3, dtype=mat33), arr(count, 3, 3, dtype=mat33), arr(count, 3, 3, dtype=mat33)
        b, x = arr(count, 3, dtype=vec3), arr(count, 3, dtype=vec3)
        y_one = wp.zeros(count, dtype=vec3, device=device)
        y_lanes = wp.zeros(count, dtype=vec3, device=device)
        args_op = [1, wp.float32(0.5), shape, a, rowsum, dinv, b, x]
        one = _per_launch_us(
            lambda: wp.launch(multigrid_kernels.mg_stencil_op, dim=count, inputs=args_op, outputs=[y_one], device=device),
            device, args.launches, args.repeats,
        )
        block = _per_launch_us(
            lambda: wp.launch(
                multigrid_kernels.mg_stencil_op_lanes, dim=(count, lanes), block_dim=lanes, inputs=[lanes, *args_op, shape, x],
                outputs=[y_lanes], device=device,
            ),
            device, args.launches, args.repeats,
        )
        err = float(np.abs(y_one.numpy() - y_lanes.numpy()).max() / np.abs(y_one.numpy()).max())
        rows.append({"level": n, "nodes": count, "one_thread_us": one, "lanes_us": block, "relative_difference": err})
        print(f"{n:>5}^3 {count:>8} {one:>16.2f} {block:>11.2f} {one / block:>6.2f}")
    nf = args.fine**3
    spacing = 0.5 / (args.fine - 1)
    grid = np.stack(np.meshgrid(*[np.arange(args.fine)] * 3, indexing="ij"), -1).reshape(-1, 3) * spacing
    q = wp.array((grid + 0.01 * spacing * rng.standard_normal(grid.shape)).astype(np.float32), dtype=vec3, device=device)
    pv = wp.array(rng.standard_normal((nf, 3)).astype(np.float32), dtype=vec3, device=device)
    rest = np.zeros(multigrid_kernels.REST_SLOTS, dtype=np.float32)
    for slot in range(27):
        rest[slot] = spacing * np.linalg.norm([slot // 9 - 1, (slot // 3) % 3 - 1, slot % 3 - 1])
    rest[27:30] = 2.0 * spacing
    tables = [wp.types.vector(multigrid_kernels.REST_SLOTS, wp.float32)(*rest.tolist()), vec3(1e5, 1e5, 1e5), vec3(0.5, 0.5, 0.25)]
    mass = wp.full(nf, 1.0 / nf, dtype=wp.float32, device=device)
    y = wp.zeros(nf, dtype=vec3, device=device)
    scalars = wp.zeros(8, dtype=wp.float32, device=device)  # the product adds p.Ap into slot 0
    product = _per_launch_us(
        lambda: wp.launch(
            multigrid_kernels.mg_lattice_mv, dim=(implicit_kernels.tile_blocks(nf), implicit_kernels.TILE), block_dim=implicit_kernels.TILE,
            inputs=[nf, 0, wp.float32(0.01), wp.vec3i(args.fine, args.fine, args.fine), 7, *tables, q, mass, pv],
            outputs=[y, scalars], device=device,
        ),
        device, args.launches, args.repeats,
    )
    print(f"spring product (mg_lattice_mv) at {args.fine}^3: {product:.1f} us per launch")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(
                {
                    "device": str(device),
                    "device_name": device.name,
                    "warp_version": wp.__version__,
                    "lanes": lanes,
                    "lanes_max_nodes": multigrid.LANES_MAX_NODES,
                    "stencil_sweep": rows,
                    "spring_product": {"size": args.fine, "us_per_launch": product},
                },
                f,
                indent=1,
            )
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
