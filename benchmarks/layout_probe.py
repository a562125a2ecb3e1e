"""Does the state's memory layout bound the lattice gather on a GPU? A measurement, not product code.

    python benchmarks/layout_probe.py --device cuda:0 --size 100 --out layout_probe.json

The same 32-neighbour spring gather (structural, shear and bending stencil; interior particles
only, so no bounds tests) over positions and velocities stored several ways:

* ``vec3``: 12-byte elements, as ``State`` stores them: each component is its own 4-byte load, and
  a warp's load of one component spans three 128-byte lines;
* ``vec3 native``: the same arrays, each element addressed from the data pointer by a native
  helper: Warp's ``a[i]`` also multiplies by the array's run-time stride, this isolates that cost;
* ``vec4``: 16-byte padded elements, indexed as Warp arrays. Warp's ``vec4`` is a struct of four
  floats with 4-byte alignment, so NVRTC loads an element one 4-byte component at a time (three
  ``ld.global.f32`` in the PTX, the pad never read), not as one 16-byte load: this variant does not
  test vector loads;
* ``vec4 native``: the same arrays, each element read by ``load3``, a native helper that on CUDA
  casts the element's address to ``float4`` and reads it with one 16-byte ``__ldg`` (read-only
  path): the padded layout with genuine 128-bit loads;
* ``packed native``: position and velocity interleaved in one array of 32-byte records
  (x y z 0 vx vy vz 0), each neighbour read by two 16-byte ``load3`` from adjacent addresses;
* ``soa``: three float arrays: each component load of a warp is one 128-byte line.

It prints ms per force evaluation (graph replay, median of repeats, layouts timed in turn) and
each layout's ratio to ``vec3``. The forces of all layouts agree (checked before timing).
"""

import numpy as np
import warp as wp
from probe_common import OFFSETS, parser, perturbed_lattice, run_cases

wp.set_module_options({"enable_backward": False})


@wp.func
def spring(d: wp.vec3, u: wp.vec3, rest: float):
    l2 = wp.dot(d, d)
    inv = 1.0 / wp.sqrt(l2)
    m = 1000.0 * (l2 * inv - rest) + 1.0 * wp.dot(u, d) * inv
    return (-m * inv) * d


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
const float4 t = __ldg((const float4*)a.data + i);
return wp::vec3(t.x, t.y, t.z);
#else
const float* t = (const float*)a.data + 4 * i;
return wp::vec3(t[0], t[1], t[2]);
#endif
"""
)
def load3(a: wp.array(dtype=wp.vec4), i: int) -> wp.vec3:
    """The first three floats of contiguous ``a[i]``, on CUDA read as one 16-byte load."""


@wp.func_native(
    """
const float* t = (const float*)a.data + 3 * i;
return wp::vec3(t[0], t[1], t[2]);
"""
)
def load3_packed(a: wp.array(dtype=wp.vec3), i: int) -> wp.vec3:
    """Contiguous ``a[i]`` addressed from the data pointer alone (Warp's ``a[i]`` also multiplies by a run-time stride)."""


def make_kernel(layout, n, spacing, spring=spring):
    """The gather over ``layout``; ``spring`` is the per-spring force function (column_probe passes an rsqrtf one)."""
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

    elif layout == "vec3 native":

        @wp.kernel(module="unique")
        def k(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            xi = load3_packed(x, i)
            vi = load3_packed(v, i)
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                acc += spring(xi - load3_packed(x, p), vi - load3_packed(v, p), rest_c[s])
            f[i] = acc

    elif layout == "vec4 native":

        @wp.kernel(module="unique")
        def k(x: wp.array(dtype=wp.vec4), v: wp.array(dtype=wp.vec4), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            xi = load3(x, i)
            vi = load3(v, i)
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                acc += spring(xi - load3(x, p), vi - load3(v, p), rest_c[s])
            f[i] = acc

    elif layout == "packed native":

        @wp.kernel(module="unique")
        def k(xv: wp.array(dtype=wp.vec4), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            a = i // (n * n)
            b = (i // n) % n
            c = i % n
            if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
                return
            xi = load3(xv, 2 * i)
            vi = load3(xv, 2 * i + 1)
            acc = wp.vec3()
            for s in range(count):
                p = i + off_c[s]
                acc += spring(xi - load3(xv, 2 * p), vi - load3(xv, 2 * p + 1), rest_c[s])
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
                acc += spring(
                    xi - wp.vec3(x[0, p], x[1, p], x[2, p]), vi - wp.vec3(v[0, p], v[1, p], v[2, p]), rest_c[s]
                )
            f[i] = acc

    return k


def main():
    a = parser(__doc__).parse_args()
    wp.config.quiet = True
    dev = wp.get_device(a.device)
    n, spacing = a.size, 0.05
    x, v = perturbed_lattice(n, spacing)
    pad = lambda u: np.concatenate([u, np.zeros((len(u), 1), np.float32)], 1)  # noqa: E731
    x4, v4 = wp.array(pad(x), dtype=wp.vec4, device=dev), wp.array(pad(v), dtype=wp.vec4, device=dev)
    inputs = {
        "vec3": [wp.array(x, dtype=wp.vec3, device=dev), wp.array(v, dtype=wp.vec3, device=dev)],
        "vec3 native": [wp.array(x, dtype=wp.vec3, device=dev), wp.array(v, dtype=wp.vec3, device=dev)],
        "vec4": [x4, v4],
        "vec4 native": [x4, v4],
        "packed native": [wp.array(np.hstack([pad(x), pad(v)]).reshape(-1, 4), dtype=wp.vec4, device=dev)],
        "soa": [wp.array(x.T.copy(), dtype=float, device=dev), wp.array(v.T.copy(), dtype=float, device=dev)],
    }
    variants = {}
    for layout, arrays in inputs.items():
        f = wp.zeros(n**3, dtype=wp.vec3, device=dev)
        variants[layout] = (make_kernel(layout, n, spacing), n**3, [*arrays, f], f)
    run_cases(variants, dev, a.evals, a.repeats, n, a.out, key="layout")


if __name__ == "__main__":
    main()
