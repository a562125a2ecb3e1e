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
def load_vec3_pointer(a: wp.array(dtype=wp.vec3), i: int) -> wp.vec3:
    """Contiguous ``a[i]`` addressed from the data pointer alone (Warp's ``a[i]`` also multiplies by a run-time stride)."""


@wp.func
def load_vec3(a: wp.array(dtype=wp.vec3), i: int):
    return a[i]


@wp.func
def load_vec4(a: wp.array(dtype=wp.vec4), i: int):
    t = a[i]
    return wp.vec3(t[0], t[1], t[2])


@wp.func
def load_soa(a: wp.array2d(dtype=float), i: int):
    return wp.vec3(a[0, i], a[1, i], a[2, i])


@wp.func
def load_packed_x(a: wp.array(dtype=wp.vec4), i: int):
    return load3(a, 2 * i)


@wp.func
def load_packed_v(a: wp.array(dtype=wp.vec4), i: int):
    return load3(a, 2 * i + 1)


# Per layout: the type of the position and velocity arrays, and how to read particle i of each
# (the packed layout passes its one interleaved array as both).
LAYOUTS = {
    "vec3": (wp.array(dtype=wp.vec3), load_vec3, load_vec3),
    "vec3 native": (wp.array(dtype=wp.vec3), load_vec3_pointer, load_vec3_pointer),
    "vec4": (wp.array(dtype=wp.vec4), load_vec4, load_vec4),
    "vec4 native": (wp.array(dtype=wp.vec4), load3, load3),
    "packed native": (wp.array(dtype=wp.vec4), load_packed_x, load_packed_v),
    "soa": (wp.array2d(dtype=float), load_soa, load_soa),
}


def make_kernel(layout, n, spacing, spring=spring):
    """The gather over ``layout``; ``spring`` is the per-spring force function (column_probe passes an rsqrtf one)."""
    rests = [spacing * float(np.sqrt(di * di + dj * dj + dk * dk)) for di, dj, dk in OFFSETS]
    offs = [(di * n + dj) * n + dk for di, dj, dk in OFFSETS]
    off_c = wp.constant(wp.types.vector(len(offs), wp.int32)(*offs))
    rest_c = wp.constant(wp.types.vector(len(rests), wp.float32)(*rests))
    count = len(offs)
    state_array, load_x, load_v = LAYOUTS[layout]

    @wp.kernel(module="unique")
    def k(x: state_array, v: state_array, f: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        a = i // (n * n)
        b = (i // n) % n
        c = i % n
        if a < 2 or b < 2 or c < 2 or a >= n - 2 or b >= n - 2 or c >= n - 2:
            return
        xi = load_x(x, i)
        vi = load_v(v, i)
        acc = wp.vec3()
        for s in range(count):
            p = i + off_c[s]
            acc += spring(xi - load_x(x, p), vi - load_v(v, p), rest_c[s])
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
    x3, v3 = wp.array(x, dtype=wp.vec3, device=dev), wp.array(v, dtype=wp.vec3, device=dev)
    packed = wp.array(np.hstack([pad(x), pad(v)]).reshape(-1, 4), dtype=wp.vec4, device=dev)
    inputs = {
        "vec3": (x3, v3),
        "vec3 native": (x3, v3),
        "vec4": (x4, v4),
        "vec4 native": (x4, v4),
        "packed native": (packed, packed),
        "soa": (wp.array(x.T.copy(), dtype=float, device=dev), wp.array(v.T.copy(), dtype=float, device=dev)),
    }
    variants = {}
    for layout, (xa, va) in inputs.items():
        f = wp.zeros(n**3, dtype=wp.vec3, device=dev)
        variants[layout] = (make_kernel(layout, n, spacing), n**3, [xa, va, f], f)
    run_cases(variants, dev, a.evals, a.repeats, n, a.out, key="layout")


if __name__ == "__main__":
    main()
