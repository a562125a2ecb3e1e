"""Lattice kernel ablation on one device: gather vs shared-memory tile, per block size.

    python benchmarks/tile_sweep.py --device cuda:0 --size 100 --out tile_sweep.json

Times fused symplectic and RK4 steps (graph replay, median of repeats, interleaved) of the
``softsim bench`` jelly with the gather kernel in index order and in brick orders
(``LatticeData.set_brick``), and with the tile kernel at several thread-block sizes, and prints ms per step and the ratio to gather measured in the same run.
"""

import argparse
import json

import warp as wp

from softsim_warp import bench
from softsim_warp.kernels import lattice as lattice_kernels


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--threads", default="128,256", help="thread-block sizes of the tile kernel (empty: none)")
    p.add_argument("--bricks", default="2x4x32,4x4x16,4x8x8,8x8x4", help="thread orders of the gather kernel")
    p.add_argument("--methods", default="symplectic,rk4")
    p.add_argument("--out")
    args = p.parse_args()
    wp.config.quiet = True
    device = wp.get_device(args.device)
    spec = bench.JellySpec()
    rows = []
    for method in args.methods.split(","):
        cases = []
        variants = [("gather", None)]
        variants += [("gather", tuple(int(n) for n in b.split("x"))) for b in args.bricks.split(",") if b]
        variants += [("tile", int(t)) for t in args.threads.split(",") if t]
        for kernel, threads in variants:
            model = bench.build_jelly_model(args.size, spec, device, force_path="lattice")
            model.lattice.set_kernel(kernel)
            if kernel == "gather" and threads:
                model.lattice.set_brick(threads)
            elif threads:
                lattice_kernels.TILE_THREADS = threads
            case = bench._OurCase(model, method, spec.dt, args.steps, True, {"fused": True})
            case.prepare()
            cases.append((kernel, threads, case))
        for _ in range(args.repeats):
            for kernel, threads, case in cases:
                case.time_once()
        base = cases[0][2].ms_per_step()
        for kernel, threads, case in cases:
            ms = case.ms_per_step()
            rows.append(
                {"method": method, "kernel": kernel, "threads_or_brick": threads, "ms_per_step": ms,
                 "speedup_vs_gather": base / ms, "finite": case.finite()}
            )
            print(f"{method:11s} {kernel:7s} {str(threads or '-'):>12s} {ms:9.4f} ms/step  x{base / ms:5.2f}  finite={case.finite()}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"device": str(device), "size": args.size, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
