"""Steps per second of the spring-list path for jellies of n^3 particles, graph-captured.

Usage: python benchmarks/quick_steps.py --device cuda:0 --sizes 10,40,100 --integrators symplectic,rk4
Prints a table and writes JSON (--out). Times the median of repeated graph launches after a warm-up.
"""

import argparse
import json
import statistics
import time

import warp as wp

from softsim_warp import ModelBuilder, make_integrator
from softsim_warp.lattice import SPRING_TYPE_NAMES


def measure(n, method, device, steps, repeats):
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    # The reference jelly: particle mass 0.01, dt 1e-4, ground plane, all three spring types.
    b.add_jelly((n, n, n), 1.0, 0.01, {t: {"ks": 1000.0, "kd": 1.0} for t in SPRING_TYPE_NAMES}, center=(0, 0.6, 0))
    b.add_plane((0, 0, 0), (0, 1, 0), 0.5, 0.5)
    model = b.finalize(device)
    integ = make_integrator(method, model)
    s0, s1 = model.state(), model.state()
    t0 = time.perf_counter()
    integ.step(s0, s1, 1e-4)
    wp.synchronize_device(device)
    compile_s = time.perf_counter() - t0
    with wp.ScopedCapture(device=device) as cap:
        for _ in range(steps // 2):
            integ.step(s0, s1, 1e-4)
            integ.step(s1, s0, 1e-4)
    wp.capture_launch(cap.graph)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        wp.capture_launch(cap.graph)
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t) / steps)
    ms = 1e3 * statistics.median(times)
    return {"size": n, "particles": model.particle_count, "springs": model.spring_count, "integrator": method,
            "ms_per_step": ms, "steps_per_second": 1e3 / ms, "compile_seconds": compile_s}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--device", default="cpu")
    p.add_argument("--sizes", default="10,20")
    p.add_argument("--integrators", default="symplectic,rk4")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--out")
    a = p.parse_args()
    wp.config.quiet = True
    device = wp.get_device(a.device)
    rows = []
    print(f"{'size':>5} {'particles':>10} {'springs':>10} {'integrator':>11} {'ms/step':>9} {'steps/s':>9}")
    for n in [int(s) for s in a.sizes.split(",")]:
        for m in a.integrators.split(","):
            r = measure(n, m, device, a.steps, a.repeats)
            rows.append(r)
            print(f"{n:>5} {r['particles']:>10} {r['springs']:>10} {m:>11} {r['ms_per_step']:>9.4f} {r['steps_per_second']:>9.1f}")
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"device": str(device), "name": device.name, "warp": wp.config.version, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
