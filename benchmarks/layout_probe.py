"""Does the state's memory layout bound the lattice gather on a GPU? A measurement, not product code.

    python benchmarks/layout_probe.py --device cuda:0 --size 100 --out layout_probe.json

The same 32-neighbour spring gather (structural, shear and bending stencil; interior particles
only, so no bounds tests) over positions and velocities stored three ways:

* ``vec3``: 12-byte elements, as ``State`` stores them: each component is its own 4-byte load, and
  a warp's load of one component spans three 128-byte lines;
* ``vec4``: 16-byte padded elements: one 16-byte load per neighbour and array;
* ``soa``: three float arrays: each component load of a warp is one 128-byte line.

It prints ms per force evaluation (graph replay, median of repeats, layouts timed in turn) and
each layout's ratio to ``vec3``. The forces of the three agree (checked before timing).
"""

import argparse
import json
import time

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

OFFSETS = [(di, dj, dk) for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1) if (di, dj, dk) != (0, 0, 0)]
OFFSETS += [(2 * s, 0, 0) for s in (-1, 1)] + [(0, 2 * s, 0) for s in (-1, 1)] + [(0, 0, 2 * s) for s in (-1, 1)]


@wp.func
def spring(d: wp.vec3, u: wp.vec3, rest: float):
    l2 = wp.dot(d, d)
    inv = 1.0 / wp.sqrt(l2)
    m = 1000.0 * (l2 * inv - rest) + 1.0 * wp.dot(u, d) * inv
    return (-m * inv) * d


def make_kernel(layout, n, spacing):
    rests = [spacing * float(np.sqrt(di * di + dj * dj + dk * dk)) for di, dj, dk in OFFSETS]
    offs = [(di * n + dj) * n + dk for di, dj, dk in OFFSETS]
    off_c = wp.constant(wp.types.vector(len(offs), wp.int32)(*offs))
    rest_c = wp.constant(wp.types.vector(len(rests), wp.float32)(*rests))
    count = len(offs)

    if layout == "vec3":

        @wp.kernel(module="unique")
        def k(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            xi = x[i]
            vi = v[i]
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                acc += spring(xi - x[p], vi - v[p], rest_c[s])
            f[i] = acc

    elif layout == "vec4":

        @wp.kernel(module="unique")
        def k(x: wp.array(dtype=wp.vec4), v: wp.array(dtype=wp.vec4), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            x4 = x[i]
            v4 = v[i]
            xi = wp.vec3(x4[0], x4[1], x4[2])
            vi = wp.vec3(v4[0], v4[1], v4[2])
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                xp = x[p]
                vp = v[p]
                acc += spring(xi - wp.vec3(xp[0], xp[1], xp[2]), vi - wp.vec3(vp[0], vp[1], vp[2]), rest_c[s])
            f[i] = acc

    else:

        @wp.kernel(module="unique")
        def k(x: wp.array2d(dtype=float), v: wp.array2d(dtype=float), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            xi = wp.vec3(x[0, i], x[1, i], x[2, i])
            vi = wp.vec3(v[0, i], v[1, i], v[2, i])
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                acc += spring(xi - wp.vec3(x[0, p], x[1, p], x[2, p]), vi - wp.vec3(v[0, p], v[1, p], v[2, p]), rest_c[s])
            f[i] = acc

    return k


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--size", type=int, default=100)
    p.add_argument("--evals", type=int, default=200)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--out")
    a = p.parse_args()
    wp.config.quiet = True
    dev = wp.get_device(a.device)
    n, spacing = a.size, 0.05
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3) * spacing
    x = (grid + rng.normal(0, 0.002, grid.shape)).astype(np.float32)
    v = rng.normal(0, 0.1, grid.shape).astype(np.float32)
    pad = lambda u: np.concatenate([u, np.zeros((len(u), 1), np.float32)], 1)  # noqa: E731
    inputs = {
        "vec3": (wp.array(x, dtype=wp.vec3, device=dev), wp.array(v, dtype=wp.vec3, device=dev)),
        "vec4": (wp.array(pad(x), dtype=wp.vec4, device=dev), wp.array(pad(v), dtype=wp.vec4, device=dev)),
        "soa": (wp.array(x.T.copy(), dtype=float, device=dev), wp.array(v.T.copy(), dtype=float, device=dev)),
    }
    cases = {}
    for layout, (xa, va) in inputs.items():
        f = wp.zeros(n**3, dtype=wp.vec3, device=dev)
        kernel = make_kernel(layout, n, spacing)
        wp.launch(kernel, dim=n**3, inputs=[xa, va], outputs=[f], device=dev)
        with wp.ScopedCapture(device=dev) as cap:
            for _ in range(a.evals):
                wp.launch(kernel, dim=n**3, inputs=[xa, va], outputs=[f], device=dev)
        cases[layout] = {"graph": cap.graph, "f": f, "times": []}
    ref = cases["vec3"]["f"].numpy()
    for layout, c in cases.items():
        err = float(np.abs(c["f"].numpy() - ref).max() / np.abs(ref).max())
        c["max_rel_diff"] = err
    for _ in range(a.repeats):
        for c in cases.values():
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            wp.capture_launch(c["graph"])
            wp.synchronize_device(dev)
            c["times"].append((time.perf_counter() - t0) / a.evals)
    base = float(np.median(cases["vec3"]["times"]))
    rows = []
    print(f"{dev} ({dev.name}), {n}^3 particles, {a.evals} evaluations x {a.repeats} repeats")
    for layout, c in cases.items():
        ms = 1e3 * float(np.median(c["times"]))
        rows.append({"layout": layout, "ms_per_eval": ms, "speedup_vs_vec3": 1e3 * base / ms, "max_rel_diff": c["max_rel_diff"]})
        print(f"{layout:5s} {ms:8.4f} ms/eval  x{1e3 * base / ms:5.2f}  max rel diff to vec3 {c['max_rel_diff']:.1e}")
    if a.out:
        with open(a.out, "w") as fh:
            json.dump({"device": dev.name, "size": n, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
