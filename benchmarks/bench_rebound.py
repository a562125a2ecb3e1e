"""Measure: how high the jelly_drop jelly bounces, per integrator and step (restitution with ``implicit``).

For each case (integrator and dt) the jelly_drop scene runs for ``--duration`` seconds; the centre of
mass height is sampled every 2 ms (every step when dt is larger). Reported: the lowest height of the
first impact, the apex of the first rebound after it, and the rebound (apex minus lowest). The
jelly's resting height is 0.25 m (half its 0.5 m edge).

Usage::

    python benchmarks/bench_rebound.py --cases implicit:0.01 implicit:0.005 symplectic:4e-4
    python benchmarks/bench_rebound.py --ks 1e5 --cases implicit:0.01 symplectic:3e-5
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import warp as wp

from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.model import build_model
from softsim_warp.io.scene import load_scene

SPRING_TYPES = ("structural", "shear", "bending")


def rebound(integrator: str, dt: float, ks: float | None = None, duration: float = 1.6, device="cpu") -> dict:
    """First impact's lowest centre-of-mass height, the next apex, and the rebound [m] of jelly_drop."""
    overrides = [f"jelly.0.springs.{t}.ks={ks}" for t in SPRING_TYPES] if ks else []
    scene = load_scene("jelly_drop", overrides)
    model = build_model(scene, device)
    integ = make_integrator(integrator, model, scene.data.get("implicit") if integrator == "implicit" else None)
    mass = model.particle_mass_host
    s0, s1 = model.state(), model.state()
    every = max(1, round(0.002 / dt))
    times, heights = [], []
    for k in range(round(duration / dt)):
        integ.step(s0, s1, dt)
        s0, s1 = s1, s0
        if k % every == 0:
            times.append((k + 1) * dt)
            heights.append(float((s0.particle_q.numpy()[:, 1] * mass).sum() / mass.sum()))
    y = np.array(heights)
    low = int(np.argmax(np.diff(y) > 0.0))  # the first minimum: the end of the first impact
    top = low
    while top + 1 < len(y) and y[top + 1] >= y[top]:
        top += 1
    return {
        "integrator": integrator,
        "dt": dt,
        "ks": ks,
        "lowest": y[low],
        "lowest_t": times[low],
        "apex": y[top],
        "apex_t": times[top],
        "rebound": y[top] - y[low],
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=["implicit:0.01", "implicit:0.005", "symplectic:4e-4"])
    p.add_argument("--ks", type=float, default=None, help="every spring type's ks (default: the scene's)")
    p.add_argument("--duration", type=float, default=1.6)
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=None, help="JSON file for the rows")
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    rows = []
    print(f"{'integrator':>11} {'dt [s]':>8} {'ks':>8} {'lowest [m]':>10} {'apex [m]':>9} {'rebound [m]':>11}")
    for case in args.cases:
        name, dt = case.split(":")
        r = rebound(name, float(dt), args.ks, args.duration, args.device)
        rows.append(r)
        ks = f"{args.ks:.0e}" if args.ks else "scene"
        print(
            f"{name:>11} {float(dt):8.1e} {ks:>8} {r['lowest']:10.3f} {r['apex']:9.3f} {r['rebound']:11.3f}", flush=True
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
