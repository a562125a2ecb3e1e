"""Does marching a thread along a lattice column cut the gather's cost on a GPU? A measurement.

    python benchmarks/column_probe.py --device cuda:0 --size 100 --out column_probe.json

The same 32-neighbour spring forces on the interior particles, computed several ways:

* ``gather``: one thread per particle loads its 32 neighbours (the lattice path's kernel shape);
* ``column K``: one thread per K consecutive particles along the slowest lattice axis keeps their
  positions, velocities and forces in registers and streams the K + 4 planes of neighbours past
  them: a neighbour shared by several of its particles is loaded once (about 12 + 20/K loads per
  particle instead of 32), and springs between two of its own particles are evaluated once. Its
  body is straight-line C generated per stencil (``wp.func_native``; Warp's unrolled Python loops
  over a K x 3 matrix took minutes to compile);
* ``column K runtime``: the lattice size read from memory instead of compiled in;
* ``... masks``: every neighbour load bounds-tested and masked, as a kernel for any column must;
* ``... tables``: rest lengths and coefficients read from arrays, as per-jelly tables are;
* ``gather runtime``: the per-particle gather with the lattice size read at run time;
* ``product gather``: softsim's own lattice force kernel (``eval_forces`` on a 100^3 jelly model,
  the gather kernel), over all particles, boundary included.

Prints ms per force evaluation (graph replay, median of repeats, variants timed in turn) and each
variant's ratio to ``gather``; the forces agree (checked before timing). Results and what became
of the idea: docs/PERFORMANCE.md, "Tried on the H200 and not kept".
"""

import numpy as np
import warp as wp
from layout_probe import make_kernel
from probe_common import OFFSETS, parser, perturbed_lattice, run_cases

wp.set_module_options({"enable_backward": False})


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
return rsqrtf(a);
#else
return 1.0f / wp::sqrt(a);
#endif
"""
)
def inv_sqrt(a: float) -> float: ...


@wp.func
def spring(d: wp.vec3, u: wp.vec3, rest: float):
    l2 = wp.dot(d, d)
    inv = inv_sqrt(l2)
    m = 1000.0 * (l2 * inv - rest) + 1.0 * wp.dot(u, d) * inv
    return (-m * inv) * d


def make_gather(n, spacing):
    """layout_probe's vec3 gather with this probe's spring (rsqrtf, as the product kernel)."""
    return make_kernel("vec3", n, spacing, spring=spring)


def make_gather_runtime(n, spacing):
    """The gather with the lattice size read at run time (neighbour offsets computed, not compiled in)."""
    rests = [spacing * float(np.sqrt(di * di + dj * dj + dk * dk)) for di, dj, dk in OFFSETS]
    off_i = wp.constant(wp.types.vector(len(OFFSETS), wp.int32)(*[o[0] for o in OFFSETS]))
    off_j = wp.constant(wp.types.vector(len(OFFSETS), wp.int32)(*[o[1] for o in OFFSETS]))
    off_k = wp.constant(wp.types.vector(len(OFFSETS), wp.int32)(*[o[2] for o in OFFSETS]))
    rest_c = wp.constant(wp.types.vector(len(rests), wp.float32)(*rests))
    count = len(OFFSETS)

    @wp.kernel(module="unique")
    def k(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        dims: wp.array(dtype=wp.int32),
        rest: wp.array(dtype=float),
        coef: wp.array(dtype=float),
    ):
        i = wp.tid()
        m = dims[0]
        a = i // (m * m)
        b = (i // m) % m
        c = i % m
        if a < 2 or b < 2 or c < 2 or a >= m - 2 or b >= m - 2 or c >= m - 2:
            return
        xi = x[i]
        vi = v[i]
        acc = wp.vec3()
        for s in range(count):
            p = i + (off_i[s] * m + off_j[s]) * m + off_k[s]
            acc += spring(xi - x[p], vi - v[p], rest_c[s])
        f[i] = acc

    return k


def make_product(n, spacing, dev):
    """softsim's lattice force kernel (gather) on an n^3 jelly with the probe's springs: (model, f)."""
    from softsim_warp.core.forces import eval_forces  # noqa: PLC0415
    from softsim_warp.core.model import ModelBuilder  # noqa: PLC0415

    b = ModelBuilder((0.0, 0.0, 0.0))
    springs = {t: {"ks": 1000.0, "kd": 1.0} for t in ("structural", "shear", "bending")}
    b.add_jelly((n, n, n), (n - 1) * spacing, 0.01, springs)
    model = b.finalize(dev, force_path="lattice")
    model.lattice.set_kernel("gather")
    return model, eval_forces


def column_snippet(n, K, spacing, runtime=False, masks=False, tables=False):
    """Straight-line C for one thread's K-particle column (the same text compiles for CPU and CUDA).

    ``runtime``: the lattice size is read from memory, so neighbour offsets are computed, not
    immediates; ``masks``: every neighbour load is bounds-tested, replaced by the first owned particle
    when outside and its springs masked to zero (as a kernel for any column must); ``tables``: rest
    lengths and coefficients are read from arrays, as per-jelly tables are.
    """
    plane = n * n
    r = {1: spacing, 2: spacing * float(np.sqrt(2.0)), 3: spacing * float(np.sqrt(3.0)), 4: 2.0 * spacing}
    slot = {1: 0, 2: 1, 3: 2, 4: 3}
    out = [
        "#if defined(__CUDA_ARCH__)",
        "#define INV_SQRT(a) rsqrtf(a)",
        "#else",
        "#define INV_SQRT(a) (1.0f / wp::sqrt(a))",
        "#endif",
        "#define SPR(T, QX, QY, QZ, UX, UY, UZ, R, OK) { const float dx = x##T##0 - (QX), dy = x##T##1 - (QY), dz = x##T##2 - (QZ); "
        "const float l2 = dx * dx + dy * dy + dz * dz; "
        + ("const float inv = l2 > 0.0f ? INV_SQRT(l2) : 0.0f; " if masks else "const float inv = INV_SQRT(l2); ")
        + "const float mm = -(KS * (l2 * inv - (R)) + KD * ((v##T##0 - (UX)) * dx + (v##T##1 - (UY)) * dy + (v##T##2 - (UZ)) * dz) * inv) * inv; "
        + ("const float m = (OK) ? mm : 0.0f; " if masks else "const float m = mm; ")
        + "f##T##0 += m * dx; f##T##1 += m * dy; f##T##2 += m * dz; }",
    ]
    if runtime:
        out.append("const int N = ((const int*)dims.data)[0], PL = N * N;")
    else:
        out.append(f"const int N = {n}, PL = {plane};")
    if tables:
        out.append("const float* RT = (const float*)rest.data; const float KS = ((const float*)coef.data)[0], KD = ((const float*)coef.data)[1];")
    else:
        out.append("const float KS = 1000.0f, KD = 1.0f;")
    out += [
        f"const int c = tid % N, b = (tid / N) % N, a0 = 2 + (tid / PL) * {K};",
        "if (b < 2 || c < 2 || b >= N - 2 || c >= N - 2) return;",
        "const int base = (a0 * N + b) * N + c;",
        "const float* X = (const float*)x.data; const float* V = (const float*)v.data; float* F = (float*)f.data;",
    ]
    for t in range(K):
        for d in range(3):
            out.append(f"const float x{t}{d} = X[3 * (base + {t} * PL) + {d}], v{t}{d} = V[3 * (base + {t} * PL) + {d}]; float f{t}{d} = 0.0f;")

    def rest(m):
        return f"RT[{slot[m]}]" if tables else f"{r[m]!r}f"

    for pp in range(K + 4):
        for dj in range(-2, 3):
            for dk in range(-2, 3):
                aj, ak = abs(dj), abs(dk)
                cross = (aj <= 1 and ak <= 1) or (aj + ak == 2 and 0 in (aj, ak))
                own = dj == 0 and dk == 0 and 2 <= pp < K + 2
                if not cross or own:
                    continue
                uses = []
                for t in range(K):
                    di = pp - 2 - t
                    ai = abs(di)
                    m = ai + aj + ak
                    if max(ai, aj, ak) <= 1 and m > 0:
                        uses.append((t, rest(m)))
                    elif m == 2 and 2 in (ai, aj, ak):
                        uses.append((t, rest(4)))
                if not uses:
                    continue
                if masks:
                    tests = [f"(unsigned)(a0 + {pp - 2}) < (unsigned)N"]
                    tests += [f"(unsigned)(b + {dj}) < (unsigned)N"] if dj else []
                    tests += [f"(unsigned)(c + {dk}) < (unsigned)N"] if dk else []
                    out.append("{ " + f"const bool okp = {' && '.join(tests)}; "
                               f"const int p = 3 * (okp ? base + {pp - 2} * PL + {dj} * N + {dk} : base);")
                else:
                    out.append("{ const bool okp = true; " + f"const int p = 3 * (base + {pp - 2} * PL + {dj} * N + {dk});")
                out.append("  const float qx = X[p], qy = X[p + 1], qz = X[p + 2], ux = V[p], uy = V[p + 1], uz = V[p + 2];")
                for t, rr in uses:
                    out.append(f"  SPR({t}, qx, qy, qz, ux, uy, uz, {rr}, okp)")
                out.append("}")
    for t in range(K):
        for s in range(t + 1, min(K, t + 3)):
            rr = rest(1) if s - t == 1 else rest(4)
            out.append(f"{{ const float h0 = f{t}0, h1 = f{t}1, h2 = f{t}2; "
                       f"SPR({t}, x{s}0, x{s}1, x{s}2, v{s}0, v{s}1, v{s}2, {rr}, true) "
                       f"f{s}0 -= f{t}0 - h0; f{s}1 -= f{t}1 - h1; f{s}2 -= f{t}2 - h2; }}")
    for t in range(K):
        out.append(f"F[3 * (base + {t} * PL)] = f{t}0; F[3 * (base + {t} * PL) + 1] = f{t}1; F[3 * (base + {t} * PL) + 2] = f{t}2;")
    out += ["#undef SPR", "#undef INV_SQRT", ""]
    return "\n".join(out)


def make_column(n, K, spacing, **flags):
    snippet = column_snippet(n, K, spacing, **flags)

    @wp.func_native(snippet)
    def column(
        tid: int,
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        dims: wp.array(dtype=wp.int32),
        rest: wp.array(dtype=float),
        coef: wp.array(dtype=float),
    ): ...

    @wp.kernel(module="unique")
    def k(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        f: wp.array(dtype=wp.vec3),
        dims: wp.array(dtype=wp.int32),
        rest: wp.array(dtype=float),
        coef: wp.array(dtype=float),
    ):
        column(wp.tid(), x, v, f, dims, rest, coef)

    return k, (n - 4) // K * n * n


def main():
    p = parser(__doc__)
    p.add_argument("--columns", default="2,4,8")
    p.add_argument("--no-product", action="store_true", help="leave out softsim's own gather kernel")
    a = p.parse_args()
    wp.config.quiet = True
    dev = wp.get_device(a.device)
    n, spacing = a.size, 0.05
    x, v = (wp.array(u, dtype=wp.vec3, device=dev) for u in perturbed_lattice(n, spacing))
    dims = wp.array([n], dtype=wp.int32, device=dev)
    rest = wp.array([spacing * float(np.sqrt(m)) for m in (1, 2, 3)] + [2.0 * spacing], dtype=float, device=dev)
    coef = wp.array([1000.0, 1.0], dtype=float, device=dev)

    def case(kernel, dim, extra):
        f = wp.zeros(n**3, dtype=wp.vec3, device=dev)
        return kernel, dim, [x, v, f, *extra], f

    variants = {"gather": case(make_gather(n, spacing), n**3, [])}
    variants["gather runtime"] = case(make_gather_runtime(n, spacing), n**3, [dims, rest, coef])
    flags = {"": {}, " runtime": {"runtime": True}, " runtime masks": {"runtime": True, "masks": True}}
    flags[" runtime masks tables"] = {"runtime": True, "masks": True, "tables": True}
    for K in (int(s) for s in a.columns.split(",")):
        assert (n - 4) % K == 0, f"--size minus 4 must be a multiple of {K}"
        for suffix, fl in flags.items():
            variants[f"column {K}{suffix}"] = case(*make_column(n, K, spacing, **fl), [dims, rest, coef])
    if not a.no_product:
        # The product kernel: forces of every particle, launched by eval_forces into f. Its rest lengths
        # come from the model's lattice, which is the probe's (positions differ only by the jitter).
        model, eval_forces = make_product(n, spacing, dev)
        f = wp.zeros(n**3, dtype=wp.vec3, device=dev)
        eval_forces(model, x, v, f)
        lat = model.lattice
        inputs = [model.particle_jelly, lat.jelly_start, lat.jelly_shape, lat.jelly_types, lat.jelly_rest]
        inputs += [lat.jelly_ks, lat.jelly_kd, x, v, f]
        variants["product gather (all particles)"] = (model.kernels.eval_lattice_springs, n**3, inputs, f)
    run_cases(variants, dev, a.evals, a.repeats, n, a.out)


if __name__ == "__main__":
    main()
