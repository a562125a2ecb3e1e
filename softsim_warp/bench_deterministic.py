"""Cost of ``--deterministic``: step time of the atomic-free force path against the atomic one.

Run::

    python -m softsim_warp.bench_deterministic --device cpu --json bench_det_cpu.json
    python -m softsim_warp.bench_deterministic --device cuda:0 --res 10 40 100 --json bench_det_cuda.json

For each lattice resolution and integrator it builds the jelly_drop scene twice (atomic and
deterministic), compiles and warms up, then times ``--steps`` steps ``--repeats`` times (on CUDA
as one captured graph, on the CPU launch by launch) and reports the median time per step and the
ratio. Compile time is reported apart. Nothing here is asserted: the numbers are for the docs.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time


def time_steps(device, res, integrator, deterministic, steps, repeats, dt=1e-4):
    import warp as wp  # noqa: PLC0415

    from .integrators import make_integrator  # noqa: PLC0415
    from .model import build_model  # noqa: PLC0415
    from .scene import load_scene  # noqa: PLC0415

    scene = load_scene("jelly_drop", [f"jelly.0.resolution=[{res},{res},{res}]"])
    model = build_model(scene, device=device, deterministic=deterministic)
    integ = make_integrator(integrator, model)
    states = [model.state(), model.state()]

    def run(n):
        for i in range(n):
            integ.step(states[i % 2], states[(i + 1) % 2], dt)

    t0 = time.perf_counter()
    run(2)
    wp.synchronize_device(device)
    compile_s = time.perf_counter() - t0
    graph = None
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            run(steps)
        graph = cap.graph
    samples = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        if graph is not None:
            wp.capture_launch(graph)
        else:
            run(steps)
        wp.synchronize_device(device)
        samples.append((time.perf_counter() - t0) / steps)
    return {
        "particles": model.particle_count,
        "springs": model.spring_count,
        "compile_seconds": compile_s,
        "step_seconds": statistics.median(samples),
        "step_seconds_min": min(samples),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m softsim_warp.bench_deterministic", description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--res", type=int, nargs="+", default=[10, 20, 30], help="particles per axis")
    p.add_argument("--integrators", nargs="+", default=["symplectic", "rk4"])
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", help="write the rows as JSON")
    a = p.parse_args(argv)

    import warp as wp  # noqa: PLC0415

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(a.device)
    rows = []
    header = (f"{'res':>5} {'particles':>10} {'springs':>10} {'integrator':>10} {'atomic ms/step':>15} "
              f"{'determ. ms/step':>16} {'ratio':>6}")
    print(f"device {device} ({device.name}), warp {wp.config.version}, {a.steps} steps x {a.repeats}")
    print(header)
    for res in a.res:
        for integrator in a.integrators:
            atomic = time_steps(device, res, integrator, False, a.steps, a.repeats)
            det = time_steps(device, res, integrator, True, a.steps, a.repeats)
            ratio = det["step_seconds"] / atomic["step_seconds"]
            rows.append({"device": str(device), "device_name": device.name, "res": res, "integrator": integrator,
                         "atomic": atomic, "deterministic": det, "ratio": ratio})
            print(f"{res:>5} {atomic['particles']:>10} {atomic['springs']:>10} {integrator:>10} "
                  f"{1e3 * atomic['step_seconds']:>15.4f} {1e3 * det['step_seconds']:>16.4f} {ratio:>6.2f}")
            sys.stdout.flush()
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"warp_version": wp.config.version, "steps": a.steps, "repeats": a.repeats, "rows": rows}, f,
                      indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
