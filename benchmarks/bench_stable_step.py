"""The stable-step prediction that ``softsim run`` checks before stepping: its cost and its accuracy.

Run::

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_stable_step.py --timing 10 20 30 35 40 --json bench_stable_step_timing.json
    python benchmarks/bench_stable_step.py --accuracy --json bench_stable_step_accuracy.json

``--timing R...``: the prediction (io/stable_step.py's pre-flight settings) of ``mesh_drop``'s
mesh jelly voxelised at R cells across, for the scene's integrator and for all of them: particles,
springs, Lanczos iterations, passes over the spring list, and wall and process CPU seconds (best
of ``--repeats``; on a shared machine the CPU time is the cost, the wall time includes waiting for
a core; run with ``OPENBLAS_NUM_THREADS=1`` for one core's). Nothing compiles: the prediction is
NumPy.

``--accuracy``: the predicted limit against the limit measured by stepping, as ``softsim stability``
measures it (bisection to ``--rtol`` on 1000 steps of the jelly, free, at rest plus a small random
displacement, float64; the measured value is the middle of the final bracket), for a box jelly, a
mesh jelly, stiff springs, and springs whose kd/ks differs by type, each with every explicit
integrator; and, for the two scenes as given (gravity, terrain, contact; ``--scene-seconds``
simulated), their own integrator. The ratio measured / predicted is what
``io/stable_step.REFUSE_FACTOR`` must stay above. Nothing here is asserted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

from softsim_warp.studies import stability
from softsim_warp.core import stability_model as sm
from softsim_warp.core.methods import EXPLICIT_NAMES as EXPLICIT
from softsim_warp.io import stable_step
from softsim_warp.io.scene import load_scene

CASES = [
    ("box jelly_drop 10^3", "jelly_drop", []),
    ("mesh blob (mesh_drop)", "mesh_drop", []),
    ("stiff ks=1e5, 6^3", "hard_stiff_1e5", ["jelly.0.resolution=6"]),
    ("kd/ks by type, 6x5x4", "jelly_drop", ["jelly.0.resolution=[6,5,4]", "jelly.0.springs.structural.ks=500",
                                             "jelly.0.springs.structural.kd=5", "jelly.0.springs.shear.ks=200",
                                             "jelly.0.springs.shear.kd=0.2", "jelly.0.springs.bending.ks=100",
                                             "jelly.0.springs.bending.kd=3"]),
]
SCENES = [("jelly_drop", []), ("mesh_drop", [])]


def timing(resolutions, repeats):
    rows = []
    for res in resolutions:
        scene = load_scene("mesh_drop", [f"jelly.0.resolution={res}"])
        jelly = scene.jellies[0]
        for methods in ((scene.sim["integrator"],), EXPLICIT):
            best, cpu, pred, op = math.inf, math.inf, None, None
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                op = sm.jelly_operator(jelly)
                pred = sm.predict_operator_dt(op, methods, **stable_step.PREFLIGHT)
                best = min(best, time.perf_counter() - t0)
                cpu = min(cpu, time.process_time() - c0)
            rows.append({"resolution": res, "methods": list(methods), "particles": op.n, "springs": int(op.a.size),
                         "iterations": pred.iterations, "spring_passes": op.products, "seconds": best,
                         "cpu_seconds": cpu,
                         "dt": {m: pred.dt[m] for m in methods}})
            print(f"R={res:>3} {op.n:>7} particles {op.a.size:>8} springs  {','.join(methods):<30} "
                  f"{pred.iterations:>4} iterations {op.products:>4} passes {best:>7.3f} s wall "
                  f"{cpu:>7.3f} s CPU", flush=True)
    return rows


def measured(model, method, guess, rtol, **kw):
    lim = stability.measure_limit(model, method, guess=guess, max_dt=0.1, rtol=rtol, **kw)
    if lim["bound"]:
        return math.nan, lim
    return math.sqrt(lim["dt"] * lim["unstable_dt"]), lim


def accuracy(rtol, scene_seconds):
    rows = []
    print(f"{'case':<24} {'method':<11} {'predicted':>11} {'measured':>11} {'meas/pred':>9}", flush=True)
    for name, scene_name, sets in CASES:
        scene = load_scene(scene_name, sets)
        jelly = scene.jellies[0]
        pred = sm.predict_jelly_dt(jelly, EXPLICIT, **stable_step.PREFLIGHT).dt
        model = sm.jelly_builder(jelly).finalize("cpu", "float64")
        for method in EXPLICIT:
            if not (math.isfinite(pred[method]) and pred[method] > 0):
                rows.append({"case": name, "method": method, "predicted": pred[method], "measured": None})
                print(f"{name:<24} {method:<11} {pred[method]:>11.4g} {'-':>11}", flush=True)
                continue
            m, lim = measured(model, method, pred[method], rtol, steps=stability.DEFAULT_STEPS)
            rows.append({"case": name, "method": method, "predicted": pred[method], "measured": m,
                         "stable_dt": lim["dt"], "unstable_dt": lim["unstable_dt"], "ratio": m / pred[method]})
            print(f"{name:<24} {method:<11} {pred[method]:>11.4g} {m:>11.4g} {m / pred[method]:>9.3f}", flush=True)
    for scene_name, sets in SCENES:
        scene = load_scene(scene_name, sets)
        method = scene.sim["integrator"]
        pred = min(stable_step.jelly_limit(scene.data, i, method) for i in range(len(scene.jellies)))
        model = stability.scene_model(scene, "cpu", "float64")
        m, lim = measured(model, method, pred, rtol, duration=scene_seconds)
        name = f"scene {scene_name}"
        rows.append({"case": name, "method": method, "predicted": pred, "measured": m, "stable_dt": lim["dt"],
                     "unstable_dt": lim["unstable_dt"], "ratio": m / pred, "duration": scene_seconds})
        print(f"{name:<24} {method:<11} {pred:>11.4g} {m:>11.4g} {m / pred:>9.3f}", flush=True)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--timing", type=int, nargs="*", help="mesh_drop resolutions to time the prediction at")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--accuracy", action="store_true", help="predicted against measured limits")
    p.add_argument("--rtol", type=float, default=0.02, help="--accuracy: relative width of the final bracket")
    p.add_argument("--scene-seconds", type=float, default=0.5, help="--accuracy: simulated seconds of a scene probe")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args(argv)
    out = {"refuse_factor": stable_step.REFUSE_FACTOR, "auto_fraction": stable_step.AUTO_FRACTION}
    if args.timing:
        out["timing"] = timing(args.timing, args.repeats)
    if args.accuracy:
        out["accuracy"] = accuracy(args.rtol, args.scene_seconds)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
