"""Cost of ``--deterministic``: step time of the atomic-free force paths against the atomic one.

Run::

    python benchmarks/bench_deterministic.py --device cpu --json bench_det_cpu.json
    python benchmarks/bench_deterministic.py --device cuda:0 --res 10 40 100 --json bench_det_cuda.json

For each lattice resolution and integrator it builds the jelly_drop scene three times: the spring
list with atomic adds (``atomic``), the spring list with the fixed-order CSR gather
(``deterministic``: what ``--deterministic`` does for arbitrary spring sets), and the lattice path
(``lattice``: the default for lattice jellies, atomic-free by construction, so ``--deterministic``
keeps it at no cost). It compiles and warms up each, then times ``--steps`` steps ``--repeats`` times, the two
variants alternately (on CUDA one captured graph, wall time; on the CPU launch by launch, the
calling thread's CPU time, since Warp runs CPU kernels on that thread and other processes on the
machine then do not skew the numbers). It reports the median time per step and the median ratio
deterministic / atomic. Compile time is recorded apart. Nothing here is asserted.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

from softsim_warp.core.model import build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.studies.bench import IntegratorCase


class Case(IntegratorCase):
    """jelly_drop at ``res``^3 on one force path, warmed up; its steps a captured graph on CUDA, launches on the CPU."""

    def __init__(self, device, res, integrator, deterministic, steps, dt=1e-4, force_path="springs"):
        scene = load_scene("jelly_drop", [f"jelly.0.resolution=[{res},{res},{res}]"])
        model = build_model(scene, device=device, deterministic=deterministic, force_path=force_path)
        super().__init__(model, integrator, dt, steps, use_graph=model.device.is_cuda)
        self.compile_seconds = self.prepare()

    def time(self) -> tuple[float, float]:
        """(wall seconds, this thread's CPU seconds) per step."""
        self.time_once()
        return self.wall[-1] / self.steps, self.thread[-1] / self.steps


def compare(device, res, integrator, steps, repeats) -> dict:
    """Atomic spring list against the deterministic one and the lattice path, timed in turn so a busy machine slows all alike."""
    cases = {
        "atomic": Case(device, res, integrator, False, steps),
        "deterministic": Case(device, res, integrator, True, steps),
        "lattice": Case(device, res, integrator, True, steps, force_path="auto"),
    }
    samples = {name: [] for name in cases}
    for _ in range(repeats):
        for name, case in cases.items():
            samples[name].append(case.time())
    out = {
        "res": res,
        "integrator": integrator,
        "particles": cases["atomic"].model.particle_count,
        "springs": cases["atomic"].model.spring_count,
    }
    # On the CPU, Warp runs kernels on the calling thread: its CPU time is the cost, unaffected by
    # other processes taking turns on the cores. On CUDA the wall time of the graph is.
    use_cpu_time = not cases["atomic"].model.device.is_cuda
    for name, case in cases.items():
        out[name] = {
            "compile_seconds": case.compile_seconds,
            "wall_seconds_per_step": statistics.median(w for w, _ in samples[name]),
            "cpu_seconds_per_step": statistics.median(c for _, c in samples[name]),
        }
    key = "cpu_seconds_per_step" if use_cpu_time else "wall_seconds_per_step"
    col = 1 if use_cpu_time else 0
    out["timed"] = key
    for name in ("deterministic", "lattice"):
        ratios = [d[col] / a[col] for a, d in zip(samples["atomic"], samples[name])]
        out["ratio" if name == "deterministic" else "lattice_ratio"] = statistics.median(ratios)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/bench_deterministic.py", description=__doc__.splitlines()[0])
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
    timed = "CPU-thread" if not device.is_cuda else "wall (graph)"
    print(f"device {device} ({device.name}), warp {wp.config.version}, {a.steps} steps x {a.repeats}, {timed} time")
    print(
        f"{'res':>5} {'particles':>10} {'springs':>10} {'integrator':>10} {'atomic ms/step':>15} "
        f"{'determ. ms/step':>16} {'ratio':>6} {'lattice ms/step':>16} {'ratio':>6}"
    )
    for res in a.res:
        for integrator in a.integrators:
            row = compare(device, res, integrator, a.steps, a.repeats)
            row["device"], row["device_name"] = str(device), device.name
            rows.append(row)
            k = row["timed"]
            print(
                f"{res:>5} {row['particles']:>10} {row['springs']:>10} {integrator:>10} "
                f"{1e3 * row['atomic'][k]:>15.4f} {1e3 * row['deterministic'][k]:>16.4f} {row['ratio']:>6.2f} "
                f"{1e3 * row['lattice'][k]:>16.4f} {row['lattice_ratio']:>6.2f}"
            )
            sys.stdout.flush()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(
                {"warp_version": wp.config.version, "steps": a.steps, "repeats": a.repeats, "rows": rows}, f, indent=1
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
