"""Lattice kernel ablation on one device: gather vs shared-memory tile, per block size.

    python benchmarks/tile_sweep.py --device cuda:0 --size 100 --out tile_sweep.json

Times fused symplectic and RK4 steps (graph replay, median of repeats, interleaved) of the
``softsim bench`` jelly with the gather kernel and with the tile kernel at several thread-block
sizes, and prints ms per step and the ratio to gather measured in the same run.
"""

import argparse
import json

import numpy as np
import warp as wp

from softsim_warp import bench
from softsim_warp.kernels import lattice as lattice_kernels


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--threads", default="128,256,512")
    p.add_argument("--methods", default="symplectic,rk4")
    p.add_argument("--out")
    args = p.parse_args()
    wp.config.quiet = True
    device = wp.get_device(args.device)
    spec = bench.JellySpec()
    rows = []
    for method in args.methods.split(","):
        cases = []
        for kernel, threads in [("gather", None)] + [("tile", int(t)) for t in args.threads.split(",")]:
            model = bench.build_jelly_model(args.size, spec, device, force_path="lattice")
            model.lattice.set_kernel(kernel)
            if threads:
                lattice_kernels.TILE_THREADS = threads
            case = bench._OurCase(model, method, spec.dt, args.steps, True, {"fused": True})
            case.prepare()
            cases.append((kernel, threads, case))
        for _ in range(args.repeats):
            for kernel, threads, case in cases:
                if threads:
                    lattice_kernels.TILE_THREADS = threads  # graphs hold their launches; kept for clarity
                case.time_once()
        base = cases[0][2].ms_per_step()
        for kernel, threads, case in cases:
            ms = case.ms_per_step()
            rows.append(
                {"method": method, "kernel": kernel, "threads": threads, "ms_per_step": ms,
                 "speedup_vs_gather": base / ms, "finite": case.finite()}
            )
            print(f"{method:11s} {kernel:7s} {str(threads or '-'):>5s} {ms:9.4f} ms/step  x{base / ms:5.2f}  finite={case.finite()}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"device": str(device), "size": args.size, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
