"""What the GPU kernel probes in benchmarks/ share: the stencil, a perturbed lattice, and timing.

A probe builds variants of one force kernel, each a (kernel, launch dim, inputs) case writing
forces into its own array; :func:`run_cases` checks their forces against the first case and
times them as graph replays (median of repeats, the variants in turn).
"""

import argparse
import json
import time

import numpy as np
import warp as wp

# The 32 stencil offsets: the 3x3x3 block (structural and shear) and +-2 along each axis (bending).
OFFSETS = [(di, dj, dk) for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1) if (di, dj, dk) != (0, 0, 0)]
OFFSETS += [(2 * s, 0, 0) for s in (-1, 1)] + [(0, 2 * s, 0) for s in (-1, 1)] + [(0, 0, 2 * s) for s in (-1, 1)]


def parser(doc, size=100):
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--size", type=int, default=size)
    p.add_argument("--evals", type=int, default=200)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--out")
    return p


def perturbed_lattice(n, spacing, seed=0):
    """Positions of an n^3 lattice jittered by 4 % of the spacing, and random velocities (float32, [n^3, 3])."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3) * spacing
    x = (grid + rng.normal(0, 0.002, grid.shape)).astype(np.float32)
    v = rng.normal(0, 0.1, grid.shape).astype(np.float32)
    return x, v


def run_cases(variants, dev, evals, repeats, n, out=None, key="variant"):
    """Check and time ``variants`` {name: (kernel, dim, inputs, f)}; the first is the reference.

    Prints one line per variant (ms per evaluation, ratio to the first, largest relative force
    difference to the first, first-launch time) and writes the rows as JSON to ``out``.
    """
    cases = {}
    for name, (kernel, dim, inputs, f) in variants.items():
        t0 = time.perf_counter()
        wp.launch(kernel, dim=dim, inputs=inputs, device=dev)
        wp.synchronize_device(dev)
        compile_s = time.perf_counter() - t0
        with wp.ScopedCapture(device=dev) as cap:
            for _ in range(evals):
                wp.launch(kernel, dim=dim, inputs=inputs, device=dev)
        cases[name] = {"graph": cap.graph, "f": f, "times": [], "compile_s": compile_s}
    first = next(iter(cases))
    ref = cases[first]["f"].numpy()
    sel = np.any(ref != 0.0, axis=1)  # the particles the reference computes (a probe may skip the boundary)
    for c in cases.values():
        c["max_rel_diff"] = float(np.abs(c["f"].numpy()[sel] - ref[sel]).max() / np.abs(ref[sel]).max())
    for _ in range(repeats):
        for c in cases.values():
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            wp.capture_launch(c["graph"])
            wp.synchronize_device(dev)
            c["times"].append((time.perf_counter() - t0) / evals)
    base = float(np.median(cases[first]["times"]))
    rows = []
    print(f"{dev} ({dev.name}), {n}^3 particles, {evals} evaluations x {repeats} repeats")
    for name, c in cases.items():
        ms = 1e3 * float(np.median(c["times"]))
        rows.append(
            {
                key: name,
                "ms_per_eval": ms,
                f"speedup_vs_{first.split()[0]}": 1e3 * base / ms,
                "max_rel_diff": c["max_rel_diff"],
                "compile_s": c["compile_s"],
            }
        )
        print(
            f"{name:32s} {ms:8.4f} ms/eval  x{1e3 * base / ms:5.2f}  max rel diff {c['max_rel_diff']:.1e}"
            f"  first launch {c['compile_s']:.1f} s"
        )
    if out:
        with open(out, "w") as fh:
            json.dump({"device": dev.name, "size": n, "rows": rows}, fh, indent=1)
    return rows
