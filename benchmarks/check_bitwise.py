"""CPU results bit for bit before and after a change: ``python benchmarks/check_bitwise.py save base.npz`` on
the old tree, then ``python benchmarks/check_bitwise.py check base.npz`` on the new one.

Steps a set of built-in scenes with every integrator on the CPU (float32, and float64 for some)
and stores the final positions and velocities; ``check`` lists every array that differs in any bit.
"""

import sys

import numpy as np
import warp as wp

import softsim_warp as ss

wp.config.quiet = True

CASES = [  # (scene, integrators, precisions, steps)
    ("jelly_drop", ("euler", "symplectic", "midpoint", "rk4", "implicit"), ("float32", "float64"), 60),
    ("seed_bowl", ("symplectic", "rk4", "implicit"), ("float32",), 60),
    ("seed_sphere", ("symplectic", "midpoint"), ("float32",), 40),
    ("pile", ("symplectic", "rk4", "implicit"), ("float32",), 40),
    ("mesh_drop", ("symplectic", "implicit"), ("float32",), 40),
    ("platform", ("symplectic", "rk4", "implicit"), ("float32",), 40),
    ("turntable", ("symplectic",), ("float32",), 40),
    ("twist", ("symplectic",), ("float32",), 30),
    ("hang", ("rk4", "implicit"), ("float64",), 40),
    ("stack", ("symplectic",), ("float32",), 40),
]

def run():
    out = {}
    for name, methods, precs, steps in CASES:
        for prec in precs:
            for m in methods:
                scene = ss.load_scene(name)
                try:
                    model = ss.build_model(scene, device="cpu", precision=prec)
                    integ = ss.make_integrator(m, model)
                except Exception as e:  # e.g. implicit refusing moving terrain
                    out[f"{name}/{prec}/{m}/error"] = np.frombuffer(type(e).__name__.encode(), np.uint8)
                    continue
                st = ss.Stepper(model, integ, scene.sim["dt"])
                st.advance(steps)
                out[f"{name}/{prec}/{m}/q"] = st.state.particle_q.numpy()
                out[f"{name}/{prec}/{m}/qd"] = st.state.particle_qd.numpy()
                print(name, prec, m, "done", flush=True)
    return out

if __name__ == "__main__":
    mode, path = sys.argv[1], sys.argv[2]
    res = run()
    if mode == "save":
        np.savez(path, **res); print("saved", len(res))
    else:
        base = dict(np.load(path))
        bad = [k for k in sorted(set(base) | set(res)) if k not in base or k not in res or base[k].shape != res[k].shape
               or not np.array_equal(base[k].view(np.uint8), res[k].view(np.uint8))]
        for k in bad:
            print("DIFFERS:", k, (np.max(np.abs(base[k] - res[k])) if k in base and k in res and base[k].shape == res[k].shape else "missing/shape"))
        print("bitwise identical" if not bad else f"{len(bad)} differ")
        sys.exit(1 if bad else 0)
