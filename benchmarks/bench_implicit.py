"""Benchmark: the implicit integrator's cost against the explicit ones at their stable steps.

For each lattice size (particles per axis), a stiff jelly (the jelly_drop jelly: 0.5 m cube, 1 kg,
every spring type at ``--ks``) spins in free flight. Reported per size, all in the same run:

* ``implicit`` at ``--dt`` (default 0.01) with each linear solver: ms per step, CG iterations per
  step (mean/max), and ms per simulated second;
* ``rk4`` and ``symplectic`` at their largest stable step (the linear analysis of a 5x5x5 lattice
  with the same spacing, masses and springs, times 0.85; see ``STABLE_FRACTION``), ms per step
  and per simulated second.

Compile time is measured apart (the first two steps) and not in the step timings; on CUDA the
steps replay a captured graph, as the simulator's frames do. ``--euler-limit``
also bisects the largest step at which ``euler`` survives ``--euler-steps`` steps of the
jelly_drop scene (ground contact) at each ``--ks``, next to the predicted limit.

Usage::

    python benchmarks/bench_implicit.py --device cpu --sizes 5 10 20 --out bench_implicit.json
    python benchmarks/bench_implicit.py --euler-limit --ks 1e5 1e6 --sizes

The measuring functions (:func:`measure_implicit`, :func:`measure_explicit`) are reusable by
``softsim bench``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import platform

import numpy as np
import warp as wp

from softsim_warp.core.implicit import ImplicitIntegrator
from softsim_warp.core.integrators import ExplicitIntegrator
from softsim_warp.core.model import ModelBuilder, build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.io.metrics import speed_bound
from softsim_warp.core.stability_analysis import predict_lattice_dt
from softsim_warp.studies.timing import TimedSteps

SPRING_TYPES = ("structural", "shear", "bending")
# jelly_drop's dampers; the stiffness is the benchmark's parameter.
DAMPING = {"structural": 0.1, "shear": 0.1, "bending": 0.05}
EDGE = 0.5  # m
TOTAL_MASS = 1.0  # kg


def stiff_jelly(size: int, ks: float, device, precision="float32"):
    """The jelly_drop jelly at ``size`` particles per axis, in free flight, spinning about a tilted axis."""
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    springs = {t: {"ks": ks, "kd": DAMPING[t]} for t in SPRING_TYPES}
    b.add_jelly(
        (size,) * 3,
        EDGE,
        TOTAL_MASS / size**3,
        springs,
        center=(0.0, 1.0, 0.0),
        axis=(1.0, 0.0, 1.0),
        degrees=20.0,
        angular_velocity=(2.0, 4.0, 1.0),
    )
    return b.finalize(device, precision)


# Safety factor on the predicted limit. The limit of a finite lattice falls towards the infinite
# lattice's as interior particles with the full 32-spring stencil appear: at the 40^3 jelly's
# spacing and ks = 1e5, symplectic Euler's limit is 5.68e-6 s on a 4^3 analysis lattice (no
# particle has all 32 neighbours), 5.46e-6 on 5^3 and 5.32e-6 on 6^3, converging to about 5.1e-6.
# 0.9 x the 4^3 value ran unstable at 40^3 and 80^3 on the GPU; 0.85 x the 5^3 value leaves 8 %.
STABLE_FRACTION = 0.85
ANALYSIS_N = 5


@functools.lru_cache(maxsize=None)
def _predicted_limits(size: int, ks: float) -> dict:
    n = min(size, ANALYSIS_N)
    spacing = EDGE / (size - 1)
    return predict_lattice_dt(
        (n,) * 3, spacing * (n - 1), TOTAL_MASS / size**3, ks, DAMPING, methods=("symplectic", "rk4", "midpoint", "euler")
    )


def stable_dt(size: int, ks: float, method: str) -> float:
    """STABLE_FRACTION times the largest stable step of ``method`` for the benchmark jelly (linear analysis, 5^3 lattice)."""
    return STABLE_FRACTION * _predicted_limits(size, ks)[method]


def _time_steps(integ, model, dt, steps):
    """(compile seconds, seconds for ``steps`` steps, finite at the end).

    On CUDA the steps are captured once as a graph and replayed, as the simulator does for a
    frame; on the CPU they are launched one by one (:class:`~softsim_warp.studies.timing.TimedSteps`).
    The integrator's statistics count the timed steps only.
    """
    states = [model.state(), model.state()]

    def step(count):
        for k in range(count):
            integ.step(states[k % 2], states[1 - k % 2], dt)

    timed = TimedSteps(model.device, step, steps, model.device.is_cuda)
    compile_s = timed.prepare()
    if hasattr(integ, "reset_stats"):
        integ.reset_stats()
    timed.time_once()
    seconds = timed.wall[-1] * steps / timed.steps
    finite = bool(np.isfinite(states[0].particle_q.numpy()).all())
    return compile_s, seconds, finite


def measure_implicit(size: int, dt: float = 0.01, device="cpu", steps: int = 10, ks: float = 1.0e5, **options) -> dict:
    """ms per step and CG iterations of ``implicit`` on the stiff jelly; ``options`` go to ImplicitIntegrator."""
    model = stiff_jelly(size, ks, device)
    integ = ImplicitIntegrator(model, **options)
    compile_s, seconds, finite = _time_steps(integ, model, dt, steps)
    stats = integ.stats()
    ms = 1e3 * seconds / steps
    return {
        "integrator": "implicit",
        "solver": integ.solver,
        "preconditioner": integ.preconditioner,
        "size": size,
        "particles": model.particle_count,
        "springs": model.spring_count,
        "dt": dt,
        "steps": steps,
        "ms_per_step": ms,
        "ms_per_sim_second": ms / dt,
        "cg_iterations_mean": stats["cg_iterations_mean"],
        "cg_iterations_max": stats["cg_iterations_max"],
        "cg_unconverged_solves": stats["cg_unconverged_solves"],
        "warm_start": integ.warm_start,
        "compile_seconds": compile_s,
        "finite": finite,
    }


def measure_explicit(
    size: int, method: str, device="cpu", steps: int = 200, ks: float = 1.0e5, dt: float | None = None
) -> dict:
    """ms per step of an explicit method on the stiff jelly at ``dt`` (default: 0.9 x its stable step)."""
    dt = stable_dt(size, ks, method) if dt is None else dt
    model = stiff_jelly(size, ks, device)
    integ = ExplicitIntegrator(model, method)
    compile_s, seconds, finite = _time_steps(integ, model, dt, steps)
    ms = 1e3 * seconds / steps
    return {
        "integrator": method,
        "size": size,
        "particles": model.particle_count,
        "springs": model.spring_count,
        "dt": dt,
        "steps": steps,
        "ms_per_step": ms,
        "ms_per_sim_second": ms / dt,
        "compile_seconds": compile_s,
        "finite": finite,
    }


def euler_survives(ks: float, dt: float, steps: int, device="cpu", scene_name="jelly_drop") -> bool:
    """Whether ``steps`` steps of euler on the stiff scene stay finite and below the explosion speed."""
    scene = load_scene(scene_name, [f"jelly.0.springs.{t}.ks={ks}" for t in SPRING_TYPES])
    model = build_model(scene, device)
    integ = ExplicitIntegrator(model, "euler")
    s0, s1 = model.state(), model.state()
    for _ in range(steps):
        integ.step(s0, s1, dt)
        s0, s1 = s1, s0
    v = s0.particle_qd.numpy()
    return bool(np.isfinite(v).all() and np.linalg.norm(v, axis=1).max() <= speed_bound(model))


def euler_limit(ks: float, steps: int, device="cpu", iterations: int = 8, scene_name="jelly_drop") -> dict:
    """Bisect (in log dt) the largest step at which euler survives ``steps`` steps of the stiff scene."""
    scene = load_scene(scene_name, [f"jelly.0.springs.{t}.ks={ks}" for t in SPRING_TYPES])
    j = scene.jellies[0]
    spacing = j["size"][0] / (j["resolution"][0] - 1)
    kd = {t: j["springs"][t]["kd"] for t in SPRING_TYPES}
    pred = predict_lattice_dt((4, 4, 4), 3 * spacing, j["particle_mass"], ks, kd, methods=("euler",))["euler"]
    lo, hi = pred / 4.0, pred * 16.0
    assert euler_survives(ks, lo, steps, device, scene_name), "euler fails even at a quarter of the predicted limit"
    if euler_survives(ks, hi, steps, device, scene_name):
        return {
            "scene": scene_name,
            "ks": ks,
            "predicted_dt": pred,
            "survives_up_to_dt": hi,
            "steps": steps,
            "note": "survived the upper end",
        }
    for _ in range(iterations):
        mid = math.sqrt(lo * hi)
        if euler_survives(ks, mid, steps, device, scene_name):
            lo = mid
        else:
            hi = mid
    return {
        "scene": scene_name,
        "ks": ks,
        "predicted_dt": pred,
        "survives_up_to_dt": lo,
        "fails_at_dt": hi,
        "steps": steps,
        "simulated_seconds": lo * steps,
        "implicit_dt_ratio": 0.01 / lo,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--sizes", type=int, nargs="*", default=[5, 10, 20], help="particles per axis")
    p.add_argument("--ks", type=float, nargs="+", default=[1.0e5], help="spring stiffness of every type [N/m]")
    p.add_argument("--dt", type=float, default=0.01, help="implicit step [s]")
    p.add_argument("--steps", type=int, default=10, help="timed implicit steps per case")
    p.add_argument("--explicit-steps", type=int, default=200, help="timed explicit steps per case")
    p.add_argument("--solvers", nargs="+", default=["matrix_free", "bsr", "warp_cg"])
    p.add_argument("--no-warm-start", action="store_true", help="start every CG solve from 0 (for comparison)")
    p.add_argument("--no-explicit", action="store_true", help="skip the explicit integrators")
    p.add_argument("--euler-limit", action="store_true", help="also bisect euler's survival step on jelly_drop")
    p.add_argument("--euler-steps", type=int, default=20000)
    p.add_argument("--euler-scene", default="jelly_drop", help="scene for --euler-limit (e.g. seed_bowl)")
    p.add_argument("--out", default="bench_implicit.json")
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    rows, limits = [], []
    header = (
        f"{'ks':>8} {'n^3':>5} {'particles':>9} {'integrator':>22} {'dt [s]':>9} {'ms/step':>9} {'ms/sim s':>10} "
        f"{'CG it mean/max':>15}"
    )
    print(header)
    print("-" * len(header))
    for ks in args.ks:
        for size in args.sizes:
            cases = [
                measure_implicit(size, args.dt, device, args.steps, ks, solver=s, warm_start=not args.no_warm_start)
                for s in args.solvers
            ]
            if not args.no_explicit:
                cases += [measure_explicit(size, m, device, args.explicit_steps, ks) for m in ("rk4", "symplectic")]
            for r in cases:
                r["ks"] = ks
                name = r["integrator"] + (f"/{r['solver']}" if "solver" in r else "")
                cg = f"{r['cg_iterations_mean']:.1f}/{r['cg_iterations_max']}" if "solver" in r else "-"
                print(
                    f"{ks:8.0e} {size:5d} {r['particles']:9d} {name:>22} {r['dt']:9.2e} {r['ms_per_step']:9.2f} "
                    f"{r['ms_per_sim_second']:10.1f} {cg:>15}",
                    flush=True,
                )
                rows.append(r)
        if args.euler_limit:
            lim = euler_limit(ks, args.euler_steps, device, scene_name=args.euler_scene)
            limits.append(lim)
            print(
                f"euler on {args.euler_scene}, ks={ks:.0e}: predicted limit {lim['predicted_dt']:.3e} s, survives "
                f"{lim['steps']} steps up to dt = {lim['survives_up_to_dt']:.3e} s",
                flush=True,
            )
    result = {
        "device": str(device),
        "device_name": device.name,
        "warp_version": wp.config.version,
        "platform": platform.platform(),
        "cases": rows,
        "euler_limits": limits,
    }
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
