"""Lattice fast path: spring forces of regular jellies without spring index arrays or atomics.

In a jelly built by ``ModelBuilder.add_jelly`` the springs are implicit in the lattice index: the
particle at lattice coordinate (a, b, c) is joined to the particles at the 32 offsets of the
standard stencil (structural: +-1 along an axis, 6; shear: face and body diagonals of the
3x3x3 block, 12 + 8; bending: +-2 along an axis, 6), when they exist. Each jelly carries one rest
length per offset (table ``jelly_rest[j, slot]``, see :func:`rest_slot`) and one ks/kd per spring
type, so a step reads no per-spring data at all.

Three kernels evaluate the same forces:

* ``eval_lattice_springs`` (``eval_forces`` on CUDA: the implicit integrator, unfused stepping):
  one thread per particle gathers its up-to-32 neighbours (``gather_lattice_force``, Warp loops)
  and writes its own force once. Each spring is evaluated twice (once from each end), there are
  no atomics, and the sum order per particle is fixed, so the result is deterministic. It stays
  in Warp loops because the implicit solve at ks = 1e6 on CUDA needs forces without the fused
  multiply-adds the compiler puts into the native gather (docs/PERFORMANCE.md).
* ``integrate_lattice_stage`` (the explicit methods on CUDA) fuses the gather with an integrator
  stage and, on the last stage, plane contact: one kernel per stage. Its gather
  (``make_gather_native``) is straight-line C++ generated per stencil (:func:`_gather_snippet`,
  the same text on CPU and CUDA), faster on CUDA than the same sums as Warp loops and the same bits
  on the CPU. ``make_single_stage`` builds the same kernel compiled for one jelly's shape, with its
  coefficients as a kernel argument and unconditional loads from padded state arrays
  (``Model.particle_array``): the stage of a one-jelly model from 2^18 particles on.
* ``eval_lattice_rows`` (the CPU path): Warp's CPU backend runs a kernel's threads as one scalar
  call each, so a thread-per-particle kernel cannot use the CPU's vector units. This kernel runs
  one thread per jelly and does the work in a native C++ loop (``wp.func_native``) over the 16
  half-stencil offsets; the inner loops are plain array loops that the C++ compiler vectorises,
  and each spring is evaluated once.
  ``integrate_lattice_rows_stage`` appends the stage update to the same loop. It is race-free on
  CUDA too (each thread owns one jelly's particles) but slow there, so the model uses it on the
  CPU only.

The spring force of every one of them is ``springs.spring_force``: ``eval_masked_springs`` calls it,
and the others (``stencil_spring_force``, the ``SOFTSIM_SPRING`` macro, the row loops) are it
rewritten for speed and checked against it on random springs, as the native stage updates are
against ``integration.stage_values`` (tests/test_kernels_lattice.py). They agree with
``eval_springs`` over the spring list to float32 rounding (tests/test_perf_paths.py).
Measurements and the reasons for each choice: docs/PERFORMANCE.md.
"""

import functools
import itertools

import numpy as np
import warp as wp

from . import contact, integration, springs
from .precision import Float, both_precisions, concrete, is_generic, vec3

# Spring types and their stencils: the lattice geometry that the gather kernels compile in.
STRUCTURAL, SHEAR, BENDING = 0, 1, 2
SPRING_TYPE_NAMES = ("structural", "shear", "bending")


def _half_stencil(offsets):
    """Keep one offset of each +/- pair (the lexicographically positive one), so each pair is listed once."""
    return [o for o in offsets if o > (0, 0, 0)]


# Structural: axis neighbours at offset 1. Shear: face and body diagonals of the 3x3x3 block.
# Bending: axis neighbours at offset 2. Each stencil holds one offset per +/- pair.
_AXES = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
STENCILS = {
    STRUCTURAL: _AXES,
    SHEAR: _half_stencil(
        [o for o in itertools.product((-1, 0, 1), repeat=3) if sum(abs(c) for c in o) >= 2]
    ),
    BENDING: [(2 * a, 2 * b, 2 * c) for a, b, c in _AXES],
}

wp.set_module_options({"enable_backward": False})

# Half-stencil offsets (one per +/- pair) and their spring types, in lattice.STENCILS order.
HALF_OFFSETS = [(off, t) for t, stencil in STENCILS.items() for off in stencil]
REST_SLOTS = 32
# Length of the uniform gather's coefficient vector (``common_coefficients``).
COEF_LENGTH = 22


def rest_slot(di, dj, dk):
    """Column of ``jelly_rest`` for a stencil offset; symmetric offsets share a value.

    Offsets inside the 3x3x3 block use (di+1)*9 + (dj+1)*3 + (dk+1) (0..26); bending offsets
    (+-2 along an axis) use 27 + axis.
    """
    if max(abs(di), abs(dj), abs(dk)) == 2:
        return 27 + [abs(di), abs(dj), abs(dk)].index(2)
    return (di + 1) * 9 + (dj + 1) * 3 + (dk + 1)


def pair_slot(off):
    """The rest slot an offset and its opposite share: that of the larger of the two (as tuples)."""
    return rest_slot(*max(off, tuple(-x for x in off)))


# Spring type of each +/- offset pair's slot (one per half-stencil offset), and those slots in the
# order of ``common_coefficients``.
PAIR_SLOT_TYPE = {pair_slot(off): t for off, t in HALF_OFFSETS}
UNIFORM_SLOTS = sorted(PAIR_SLOT_TYPE)


def common_coefficients(rest, ks, kd, types, dtype):
    """The uniform gather's coefficients when every jelly that has a spring type has the same ones.

    ``rest`` [J, REST_SLOTS], ``ks`` and ``kd`` [J, 3] and ``types`` [J] are ``LatticeLayout``'s
    tables. Returns ks r for each slot of UNIFORM_SLOTS, then -ks and kd per type (zeros for a type
    no jelly has), as an array of ``dtype``; or None when two jellies that both have a type differ
    in its ks, kd or a rest length. Rounded as the table gather computes them: rest and ks first to
    ``dtype``, then their product in ``dtype``.
    """
    rest, ks, kd = (np.asarray(t, dtype=np.float64).astype(dtype) for t in (rest, ks, kd))
    types = np.asarray(types)
    coef = np.zeros(COEF_LENGTH, dtype=dtype)
    for t in range(3):
        having = np.flatnonzero((types >> t) & 1)
        if having.size == 0:
            continue
        index = [n for n, s in enumerate(UNIFORM_SLOTS) if PAIR_SLOT_TYPE[s] == t]
        slots = [UNIFORM_SLOTS[n] for n in index]
        table = np.concatenate([rest[having][:, slots], ks[having, t : t + 1], kd[having, t : t + 1]], axis=1)
        if not np.all(table == table[0]):
            return None
        first = having[0]
        coef[index] = rest[first, slots] * ks[first, t]
        coef[16 + t] = -ks[first, t]
        coef[19 + t] = kd[first, t]
    return coef


# The smallest normal number of each precision, as C++ literals: the guard of the stencil spring
# force (``stencil_spring_force``, ``SOFTSIM_SPRING``).
_SMALLEST_NORMAL = {"float": "1.17549435e-38f", "double": "2.2250738585072014e-308"}


def _spring_macros(ctype):
    """The SOFTSIM_RSQRT and SOFTSIM_SPRING macros of the native gathers (see ``_gather_snippet``).

    ``SOFTSIM_SPRING`` is ``stencil_spring_force`` in C++ (the same operations in the same order),
    checked against it and against ``springs.spring_force`` by tests/test_kernels_lattice.py.
    """
    tiny = _SMALLEST_NORMAL[ctype]
    rsqrt = (
        "#if defined(__CUDA_ARCH__)\n"
        '#define SOFTSIM_RSQRT(a, r) asm("rsqrt.approx.ftz.f32 %0, %1;" : "=f"(r) : "f"(a))\n'
        "#else\n"
        "#define SOFTSIM_RSQRT(a, r) r = T(1) / wp::sqrt(a)\n"
        "#endif\n"
        if ctype == "float"
        else "#define SOFTSIM_RSQRT(a, r) r = T(1) / wp::sqrt(a)\n"
    )
    spring = (
        "#define SOFTSIM_SPRING(kr_, nks_, kd_, ok_) { \\\n"
        "  const T dx = x0 - bx, dy = x1 - by, dz = x2 - bz; \\\n"
        f"  const T l2 = dx * dx + (dy * dy + (dz * dz + T({tiny}))); \\\n"
        "  T inv; SOFTSIM_RSQRT(l2, inv); \\\n"
        "  const T dot = (v0 - ux) * dx + (v1 - uy) * dy + (v2 - uz) * dz; \\\n"
        "  const T s = (kr_ - kd_ * (dot * inv)) * inv + nks_; \\\n"
        "  if (ok_) { f0 += s * dx; f1 += s * dy; f2 += s * dz; } }\n"
    )
    # The macros are textual: undefining them after the return statement is fine.
    return rsqrt + spring


def _stencil_neighbours():
    """The 32 stencil offsets and their spring types, in the native gathers' order."""
    # The 32 offsets and spring types in gather_lattice_force's order (the 3x3x3 block in
    # (di, dj, dk) order, then bending axis by axis, -2 before +2), so the sums round alike.
    neighbours = []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                m = abs(di) + abs(dj) + abs(dk)
                if m:
                    neighbours.append(((di, dj, dk), min(m - 1, 1)))
    for axis in range(3):
        for side in (-2, 2):
            o = [0, 0, 0]
            o[axis] = side
            neighbours.append((tuple(o), 2))
    return neighbours


def _coefficient_lines(uniform):
    """C++ lines defining the native gathers' coefficients: ks r per offset pair, -ks and kd per type."""
    lines = []
    # Coefficients per +/- offset pair (the rest table is symmetric): ks r, -ks and kd.
    if uniform:
        # Coefficients from the kernel argument (the constant bank): UNIFORM_SLOTS order, then -ks, kd.
        for n, s in enumerate(UNIFORM_SLOTS):
            lines.append(f"const T r{s}k = coef.c[{n}];")
        lines.append("const T n0 = coef.c[16], n1 = coef.c[17], n2 = coef.c[18];")
        lines.append("const T c0 = coef.c[19], c1 = coef.c[20], c2 = coef.c[21];")
    else:
        for s in UNIFORM_SLOTS:
            lines.append(f"const T r{s}k = rest[{s}] * k{PAIR_SLOT_TYPE[s]};")
        lines.append("const T n0 = -k0, n1 = -k1, n2 = -k2;")
    return lines


def _gather_snippet(ctype, padded=False, uniform=False, shape=None, types=None, start=None):
    """C++ body of ``gather_native``: the 32-neighbour force on particle i, straight-line.

    Generated per stencil so that every neighbour is addressed from one of 21 row pointers (one
    per (di, dj)) plus a constant, which the compiler folds into the load instruction; a
    neighbour's validity is the AND of three per-axis flags computed once per thread. An invalid
    neighbour (outside the lattice, or of an absent spring type) is not loaded: the particle's
    own position and velocity stand in for it, whose zero distance gives exactly zero force, so
    no address outside the arrays is read (the loads are predicated, not branched around). Same
    sums in the same order as the stencil loops.

    A spring's force on i is s d with d = x_i - x_b, 1/l = rsqrt(dx^2 + (dy^2 + (dz^2 + tiny))) and
    s = (ks r - kd ((v_i - v_b) . d) / l) / l - ks, the same as -(ks (l - r) + kd (dv . d^)) d^:
    ks r is one coefficient per offset, so the factor takes three instructions after the
    reciprocal square root, and the squared length three fused multiply-adds. Adding the smallest
    normal number ``tiny`` (which changes no squared length above 2^-100 or so) instead of testing
    for zero keeps coincident particles (and a stand-in) at exactly zero force: d = 0 and s stays
    finite (for ks r below 3.7e19 in float32). Two instructions a spring fewer than
    max(|d|^2, tiny) and kr / l - ks - kd (dv . d) / l^2.

    Why it is faster than the Warp loops: their select-then-index addressing and short-circuit
    bounds tests cost integer instructions per spring that the row pointers and per-axis flags here
    do not (the counts are in docs/PERFORMANCE.md). On CUDA the reciprocal square root is
    ``rsqrt.approx.ftz`` (the instruction rsqrtf uses for normal numbers, without its denormal
    fix-up).

    ``padded``: for state arrays that sit inside an allocation reaching ``LatticeData.pad``
    elements past both ends (``Model.particle_array``), so that every stencil address of every
    particle is readable. Then all 64 neighbour loads are unconditional and a spring's force is
    added only when the spring exists: the add is predicated, so whatever an invalid neighbour's
    address holds (a particle of another jelly or world, even a non-finite one, or the zeroed pad)
    never reaches the sum. No stand-in moves, same sums in the same order.

    ``uniform``: for models whose jellies all have the same rest lengths, ks and kd
    (``LatticeData.uniform``). The coefficients (``common_coefficients``) come as the kernel
    argument ``coef`` instead of per-jelly tables; on CUDA a kernel argument lives in the constant
    bank, which an instruction reads as an operand, so a spring needs no load and no multiply for
    its coefficients. Same bits as the tables
    (``common_coefficients`` rounds ks r as the table gather does).

    ``shape``, ``types``, ``start``: the jelly's lattice shape (nx, ny, nz), spring-type mask and first
    particle compiled in as constants, for a model of one jelly (``single_stage``). Then every
    neighbour's address is the thread's own plus a constant, which the load instruction carries: the
    gather needs two base pointers instead of one per lattice row (42), the lattice coordinate
    divisions become multiplications, and the springs of absent types are not compiled at all,
    which takes registers and instructions off the build (docs/PERFORMANCE.md). Same arithmetic,
    same bits.
    """
    flag = {-2: "m2", -1: "m1", 1: "p1", 2: "p2"}
    lines = [
        f"typedef {ctype} T;",
        "const int start = " + ("((const int*)jelly_start.data)[j];" if start is None else f"{int(start)};"),
    ]
    if shape is None:
        lines += [
            "const int* shape = (const int*)jelly_shape.data + 3 * j;",
            "const int nx = shape[0], ny = shape[1], nz = shape[2], row = ny * nz;",
        ]
    else:
        nx, ny, nz = (int(n) for n in shape)
        lines.append(f"const int nx = {nx}, ny = {ny}, nz = {nz}, row = {ny * nz};")
    lines += [
        "const int local = i - start;",
        "const unsigned ul = (unsigned)local, unz = (unsigned)nz, uny = (unsigned)ny, uab = ul / unz;",
        "const int c = (int)(ul - uab * unz), a = (int)(uab / uny), b = (int)(uab - (unsigned)a * uny);",
        "const int types = " + ("((const int*)jelly_types.data)[j];" if types is None else f"{int(types)};"),
        "const bool s0 = (types & 1) != 0, s1 = (types & 2) != 0, s2 = (types & 4) != 0;",
    ]
    for v, n in (("a", "nx"), ("b", "ny"), ("c", "nz")):
        lines.append(f"const bool {v}m2 = {v} >= 2, {v}m1 = {v} >= 1, {v}p1 = {v} + 1 < {n}, {v}p2 = {v} + 2 < {n};")
    if not uniform:
        lines += [
            f"const T* rest = (const T*)jelly_rest.data + {REST_SLOTS} * j;",
            "const T* ks = (const T*)jelly_ks.data + 3 * j;",
            "const T* kd = (const T*)jelly_kd.data + 3 * j;",
            "const T k0 = ks[0], k1 = ks[1], k2 = ks[2], c0 = kd[0], c1 = kd[1], c2 = kd[2];",
        ]
    lines += [
        "const T* X = (const T*)q.data + 3 * i;",
        "const T* V = (const T*)qd.data + 3 * i;",
        "const T x0 = X[0], x1 = X[1], x2 = X[2], v0 = V[0], v1 = V[1], v2 = V[2];",
        "T f0 = T(0), f1 = T(0), f2 = T(0);",
    ]

    neighbours = _stencil_neighbours()
    lines += _coefficient_lines(uniform)
    rows = sorted({(o[0], o[1]) for o, _ in neighbours})
    for di, dj in rows:
        name = f"{di + 2}{dj + 2}"
        lines.append(f"const T* xr{name} = X + 3 * ({di} * row + {dj} * nz);")
        lines.append(f"const T* vr{name} = V + 3 * ({di} * row + {dj} * nz);")

    for (di, dj, dk), ty in neighbours:
        name = f"{di + 2}{dj + 2}"
        conds = [f"s{ty}"] + [f"{v}{flag[d]}" for v, d in zip("abc", (di, dj, dk)) if d]
        s = pair_slot((di, dj, dk))
        head = (
            f"{{ const bool ok = {' && '.join(conds)};"
            f" const T* xp = xr{name} + {3 * dk}; const T* vp = vr{name} + {3 * dk};"
        )
        if padded:
            lines.append(
                head + " const T bx = xp[0], by = xp[1], bz = xp[2], ux = vp[0], uy = vp[1], uz = vp[2];"
                f" SOFTSIM_SPRING(r{s}k, n{ty}, c{ty}, ok); }}"
            )
        else:
            lines.append(
                head + " T bx = x0, by = x1, bz = x2, ux = v0, uy = v1, uz = v2;"
                " if (ok) { bx = xp[0]; by = xp[1]; bz = xp[2]; ux = vp[0]; uy = vp[1]; uz = vp[2]; }"
                f" SOFTSIM_SPRING(r{s}k, n{ty}, c{ty}, true); }}"
            )
    lines.append("return wp::vec_t<3, T>(f0, f1, f2);")
    return _spring_macros(ctype) + "\n".join(lines) + "\n#undef SOFTSIM_SPRING\n#undef SOFTSIM_RSQRT\n"


# Margin of absent points around a masked jelly's box in its index grid: the stencil reaches 2 points.
MASK_MARGIN = 2


def _masked_gather_snippet(ctype):
    """C++ body of ``masked_gather``: the stencil force on particle i of a masked lattice (mesh jelly).

    A masked jelly is a box lattice with points missing. Its ``index`` table (passed as the
    gathers' first table argument, ``jelly_start``) holds first each particle's position in the
    index grid, then the jellies' index grids: per jelly its box with a margin of ``MASK_MARGIN``
    absent points on every side, each entry a particle index or -1 (``core/masked_lattice.py``).
    ``jelly_shape`` holds each jelly's grid dimensions (box + 2 margins). A neighbour at stencil
    offset (di, dj, dk) is the grid entry at a constant offset from the particle's own (one of 21
    row pointers plus a constant, as in ``_gather_snippet``); the margin makes every offset of every
    present point land inside the jelly's grid, so there are no bounds tests at all. An absent
    neighbour (-1) or one of an absent spring type is replaced by the particle itself (exactly zero
    force, see ``_gather_snippet``), so every load is unconditional and valid. Same spring
    arithmetic and order as ``gather_native``; over a whole box it gives the same sums.

    A spring costs what the box gather's does plus one 4-byte grid load (shared by the 32 threads of
    a warp along a lattice row, so cached) and the select and two address computations of the
    neighbour's index. Coefficients, grid dimensions and spring types come from the per-jelly tables:
    compiling one jelly's in gained too little to keep (docs/PERFORMANCE.md).
    """
    lines = [
        f"typedef {ctype} T;",
        "const int* index = (const int*)jelly_start.data;",
        "const int* dims = (const int*)jelly_shape.data + 3 * j;",
        "const int nz = dims[2], row = dims[1] * dims[2];",
        "const int* G = index + index[i];",
        "const int types = ((const int*)jelly_types.data)[j];",
        "const bool s0 = (types & 1) != 0, s1 = (types & 2) != 0, s2 = (types & 4) != 0;",
        f"const T* rest = (const T*)jelly_rest.data + {REST_SLOTS} * j;",
        "const T* ks = (const T*)jelly_ks.data + 3 * j;",
        "const T* kd = (const T*)jelly_kd.data + 3 * j;",
        "const T k0 = ks[0], k1 = ks[1], k2 = ks[2], c0 = kd[0], c1 = kd[1], c2 = kd[2];",
    ]
    lines += [
        "const T* X0 = (const T*)q.data;",
        "const T* V0 = (const T*)qd.data;",
        "const T* X = X0 + 3 * i;",
        "const T* V = V0 + 3 * i;",
        "const T x0 = X[0], x1 = X[1], x2 = X[2], v0 = V[0], v1 = V[1], v2 = V[2];",
        "T f0 = T(0), f1 = T(0), f2 = T(0);",
    ]
    neighbours = _stencil_neighbours()
    lines += _coefficient_lines(False)
    for di, dj in sorted({(o[0], o[1]) for o, _ in neighbours}):
        lines.append(f"const int* g{di + 2}{dj + 2} = G + ({di} * row + {dj} * nz);")
    for (di, dj, dk), ty in neighbours:
        s = pair_slot((di, dj, dk))
        lines.append(
            f"{{ const int gp = g{di + 2}{dj + 2}[{dk}]; const int p = (s{ty} && gp >= 0) ? gp : i;"
            " const T* xp = X0 + 3 * p; const T* vp = V0 + 3 * p;"
            " const T bx = xp[0], by = xp[1], bz = xp[2], ux = vp[0], uy = vp[1], uz = vp[2];"
            f" SOFTSIM_SPRING(r{s}k, n{ty}, c{ty}, true); }}"
        )
    lines.append("return wp::vec_t<3, T>(f0, f1, f2);")
    return _spring_macros(ctype) + "\n".join(lines) + "\n#undef SOFTSIM_SPRING\n#undef SOFTSIM_RSQRT\n"


def _rows_snippet(ctype, with_stage=False):
    """C++ body of the CPU row kernel for scalar type ``ctype`` ("float" or "double").

    With ``with_stage`` the forces go to a scratch buffer and an integrator stage follows (the
    same arithmetic as ``stage_values`` in kernels/integration.py, for the jelly's world).
    """
    table = ", ".join(f"{{{di}, {dj}, {dk}, {t}, {rest_slot(di, dj, dk)}}}" for (di, dj, dk), t in HALF_OFFSETS)
    head = f"""
    typedef {ctype} T;
    static const int OFFSETS[{len(HALF_OFFSETS)}][5] = {{{table}}};"""
    if with_stage:
        head += """
    const int w = ((const int*)jelly_world.data)[j];
    const int count = ((const int*)world_stage_count.data)[w];
    if (stage >= count) return;"""
    return (
        head
        + _ROWS_FORCES.format(T=ctype, REST_SLOTS=REST_SLOTS, NOFF=len(HALF_OFFSETS))
        + (_ROWS_STAGE if with_stage else "")
    )


_ROWS_STAGE = """
    // Stage update of the jelly's particles (stage_values, vectorised): a = f/m + g.
    const T* __restrict__ inv_mass = (const T*)particle_inv_mass.data + start;
    const T* __restrict__ x_n = (const T*)q_n.data + 3 * start;
    const T* __restrict__ v_n = (const T*)qd_n.data + 3 * start;
    T* __restrict__ x_out = (T*)q_out.data + 3 * start;
    T* __restrict__ v_out = (T*)qd_out.data + 3 * start;
    const T g[3] = {gravity[0], gravity[1], gravity[2]};
    if (((const int*)world_symplectic.data)[w]) {
        // Semi-implicit Euler: velocity first, then position with the new velocity.
        for (int p = 0; p < n; ++p) {
            const T inv_mass_p = inv_mass[p];
            for (int d = 0; d < 3; ++d) {
                const T a = inv_mass_p == T(0) ? T(0) : force[3 * p + d] * inv_mass_p + g[d];
                const T vnew = v_n[3 * p + d] + h * a;
                v_out[3 * p + d] = vnew;
                x_out[3 * p + d] = x_n[3 * p + d] + h * vnew;
            }
        }
        return;
    }
    const int cols = world_stage_b.shape[1];
    const T b = ((const T*)world_stage_b.data)[w * cols + stage];
    const T b0 = ((const T*)world_stage_b.data)[w * cols];
    T* __restrict__ acc_x_out = (T*)acc_q_out.data + 3 * start;
    T* __restrict__ acc_v_out = (T*)acc_qd_out.data + 3 * start;
    const bool first = stage == 0, last = stage == count - 1;
    const T h_c_next = last ? T(0) : h * ((const T*)world_stage_c.data)[w * cols + stage + 1];
    T* __restrict__ x_next = (T*)q_next_out.data + 3 * start;
    T* __restrict__ v_next = (T*)qd_next_out.data + 3 * start;
    for (int p = 0; p < n; ++p) {
        const T inv_mass_p = inv_mass[p];
        for (int d = 0; d < 3; ++d) {
            const int e = 3 * p + d;
            const T a = inv_mass_p == T(0) ? T(0) : force[e] * inv_mass_p + g[d];
            const T vs = v[e];
            T acc_x = b * vs, acc_v = b * a;
            // Stage 0's position term b_0 v_n is recomputed at stage 1, not stored (stage_values).
            if (stage == 1) { acc_x = acc_x + b0 * v_n[e]; acc_v = acc_v + acc_v_out[e]; }
            else if (!first) { acc_x = acc_x + acc_x_out[e]; acc_v = acc_v + acc_v_out[e]; }
            if (last) {
                x_out[e] = x_n[e] + h * acc_x;
                v_out[e] = v_n[e] + h * acc_v;
            } else {
                if (!first) acc_x_out[e] = acc_x;
                acc_v_out[e] = acc_v;
                x_next[e] = x_n[e] + h_c_next * vs;
                v_next[e] = v_n[e] + h_c_next * a;
            }
        }
    }
"""

_ROWS_FORCES = """
    const int start = ((const int*)jelly_start.data)[j];
    const int* shape = (const int*)jelly_shape.data + 3 * j;
    const int nx = shape[0], ny = shape[1], nz = shape[2];
    const int n = nx * ny * nz;
    const T* rest = (const T*)jelly_rest.data + {REST_SLOTS} * j;
    const T* ks = (const T*)jelly_ks.data + 3 * j;
    const T* kd = (const T*)jelly_kd.data + 3 * j;
    const int types = ((const int*)jelly_types.data)[j];
    const T* __restrict__ x = (const T*)q.data + 3 * start;
    const T* __restrict__ v = (const T*)qd.data + 3 * start;
    const int* __restrict__ coord_k_of = (const int*)coord_k.data + start;
    T* __restrict__ force = (T*)f_out.data + 3 * start;
    T* __restrict__ first_end_force = (T*)scratch.data + 3 * start;
    for (int e = 0; e < 3 * n; ++e) force[e] = T(0);
    for (int o = 0; o < {NOFF}; ++o) {{
        const int di = OFFSETS[o][0], dj = OFFSETS[o][1], dk = OFFSETS[o][2], ty = OFFSETS[o][3];
        if (!((types >> ty) & 1)) continue;
        const T r = rest[OFFSETS[o][4]], k = ks[ty], c = kd[ty];
        // Spring (p, p + L). Loop bounds keep a + di and b + dj inside the lattice; within a slab
        // of fixed a the valid b form one contiguous range of p, and only k + dk needs a test.
        const int L = (di * ny + dj) * nz + dk;
        const int a0 = di < 0 ? -di : 0, a1 = di > 0 ? nx - di : nx;
        const int b0 = dj < 0 ? -dj : 0, b1 = dj > 0 ? ny - dj : ny;
        for (int a = a0; a < a1; ++a) {{
            int p0 = (a * ny + b0) * nz, p1 = (a * ny + b1) * nz;
            // Partners past either end of the jelly are out-of-lattice k + dk anyway: skip them.
            if (p0 < -L) p0 = -L;
            if (p1 > n - L) p1 = n - L;
            // Pass 1: force on the first end, kept for pass 2. No iteration reads another's
            // output, so the compiler vectorises it; an out-of-lattice partner gives zero.
            for (int p = p0; p < p1; ++p) {{
                const int s = 3 * p, e = 3 * (p + L);
                const bool ok = (unsigned)(coord_k_of[p] + dk) < (unsigned)nz;
                const T dx = x[s] - x[e], dy = x[s + 1] - x[e + 1], dz = x[s + 2] - x[e + 2];
                const T ux = v[s] - v[e], uy = v[s + 1] - v[e + 1], uz = v[s + 2] - v[e + 2];
                const T l2 = dx * dx + dy * dy + dz * dz;
                // Coincident particles have no direction: zero force, as in spring_force.
                const T inv = l2 > T(0) ? T(1) / wp::sqrt(l2) : T(0);
                const T m_all = -(k * (l2 * inv - r) + c * (ux * dx + uy * dy + uz * dz) * inv) * inv;
                // Select after computing: folding the test into the expression makes the compiler
                // predicate the divide and square root, which is much slower.
                const T m = ok ? m_all : T(0);
                const T fx = m * dx, fy = m * dy, fz = m * dz;
                force[s] += fx; force[s + 1] += fy; force[s + 2] += fz;
                first_end_force[s] = fx; first_end_force[s + 1] = fy; first_end_force[s + 2] = fz;
            }}
            // Pass 2: the opposite force on the second end (apart from pass 1: p + L may be p + 1).
            for (int p = p0; p < p1; ++p) {{
                const int s = 3 * p, e = 3 * (p + L);
                force[e] -= first_end_force[s];
                force[e + 1] -= first_end_force[s + 1];
                force[e + 2] -= first_end_force[s + 2];
            }}
        }}
    }}
"""


# -- Module-level kernels and funcs (generic over float32 and float64, kernels/precision.py) ----------

_CTYPES = {wp.float32: "float", wp.float64: "double"}

# The uniform gather's coefficients (common_coefficients), passed by value.
CoefVec = wp.types.vector(COEF_LENGTH, Float)


def _for_precision(kernel, scalar):
    """Declare ``kernel``'s overload for ``scalar`` only: a kernel around a native snippet or a
    shape is built per precision by its factory (``both_precisions`` declares both)."""
    wp.overload(kernel, {name: concrete(t, scalar) for name, t in kernel.adj.arg_types.items() if is_generic(t)})
    return kernel


# Native helpers: a snippet's return type cannot be generic, so each is declared for float32 and for
# float64 under one name, and Warp picks the overload from the argument types.
for _scalar, _ctype in _CTYPES.items():

    @wp.func_native(
        "#if defined(__CUDA_ARCH__)\nreturn rsqrtf(x);\n#else\nreturn 1.0f / wp::sqrt(x);\n#endif\n"
        if _ctype == "float"
        else "return 1.0 / wp::sqrt(x);"
    )
    def inv_sqrt(x: _scalar) -> _scalar:
        """1/sqrt(x): on CUDA in float32 the hardware rsqrtf (within 2 ulp), elsewhere exact."""

    @wp.func_native(f"return {_SMALLEST_NORMAL[_ctype]};")
    def smallest_normal(like: _scalar) -> _scalar:
        """The smallest normal number of ``like``'s type (the guard of ``stencil_spring_force``)."""

    @wp.func_native(_rows_snippet(_ctype))
    def lattice_rows_native(
        j: int,
        jelly_start: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=_scalar),
        jelly_ks: wp.array2d(dtype=_scalar),
        jelly_kd: wp.array2d(dtype=_scalar),
        coord_k: wp.array(dtype=wp.int32),
        q: wp.array(dtype=wp.types.vector(3, _scalar)),
        qd: wp.array(dtype=wp.types.vector(3, _scalar)),
        scratch: wp.array(dtype=wp.types.vector(3, _scalar)),
        f_out: wp.array(dtype=wp.types.vector(3, _scalar)),
    ):
        """Spring forces of lattice jelly j by row loops (``_ROWS_FORCES``)."""

    @wp.func_native(_rows_snippet(_ctype, with_stage=True))
    def lattice_rows_stage_native(
        j: int,
        stage: int,
        h: _scalar,
        jelly_start: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=_scalar),
        jelly_ks: wp.array2d(dtype=_scalar),
        jelly_kd: wp.array2d(dtype=_scalar),
        jelly_world: wp.array(dtype=wp.int32),
        coord_k: wp.array(dtype=wp.int32),
        particle_inv_mass: wp.array(dtype=_scalar),
        gravity: wp.types.vector(3, _scalar),
        world_stage_count: wp.array(dtype=wp.int32),
        world_symplectic: wp.array(dtype=wp.int32),
        world_stage_c: wp.array2d(dtype=_scalar),
        world_stage_b: wp.array2d(dtype=_scalar),
        q_n: wp.array(dtype=wp.types.vector(3, _scalar)),
        qd_n: wp.array(dtype=wp.types.vector(3, _scalar)),
        q: wp.array(dtype=wp.types.vector(3, _scalar)),
        qd: wp.array(dtype=wp.types.vector(3, _scalar)),
        scratch: wp.array(dtype=wp.types.vector(3, _scalar)),
        f_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        acc_q_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        acc_qd_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        q_next_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        qd_next_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        q_out: wp.array(dtype=wp.types.vector(3, _scalar)),
        qd_out: wp.array(dtype=wp.types.vector(3, _scalar)),
    ):
        """Spring forces of lattice jelly j by row loops, then its particles' stage update (``_ROWS_STAGE``)."""


del _scalar, _ctype


@wp.func
def stencil_spring_force(x: vec3, xb: vec3, v: vec3, vb: vec3, kr: Float, nks: Float, kd: Float):
    """``springs.spring_force`` as s d with one reciprocal square root (see ``_gather_snippet``).

    Algebraically ``spring_force(x, xb, v, vb, rest, ks, kd)`` with ``kr`` = ks times the rest length
    and ``nks`` = -ks: -(ks (l - r) + kd (dv . d) / l) d / l = ((ks r - kd (dv . d) / l) / l - ks) d.
    The form exists because the IEEE square root and the three divisions of d / |d| dominate the
    gather on CUDA, and the product ks r is one coefficient per stencil slot; rsqrtf's 2 ulp are of
    the order of the float32 rounding the sum already has. Coincident particles give zero force, as
    in ``spring_force``: the squared length has the smallest normal number added, so s stays finite
    while d = 0. Same operations in the same order as the native gathers' ``SOFTSIM_SPRING``
    (bitwise on the CPU); tests/test_kernels_lattice.py checks both against ``spring_force``.
    """
    d = x - xb
    inv = inv_sqrt(d[0] * d[0] + (d[1] * d[1] + (d[2] * d[2] + smallest_normal(kr))))
    s = (kr - kd * (wp.dot(v - vb, d) * inv)) * inv + nks
    return s * d


@wp.func
def lattice_coord(local: int, shape: wp.vec3i):
    """Lattice coordinate (a, b, c) of a jelly-local particle index (i*ny + j)*nz + k."""
    c = local % shape[2]
    t = local // shape[2]
    return wp.vec3i(t // shape[1], t % shape[1], c)


@wp.func
def inside(a: int, b: int, c: int, shape: wp.vec3i):
    return a >= 0 and a < shape[0] and b >= 0 and b < shape[1] and c >= 0 and c < shape[2]


@wp.func
def gather_lattice_force(
    i: int,
    j: int,
    jelly_start: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    jelly_kd: wp.array2d(dtype=Float),
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
):
    """Spring force on particle i of lattice jelly j: the sum over its stencil neighbours, in Warp loops."""
    shape = jelly_shape[j]
    lc = lattice_coord(i - jelly_start[j], shape)
    a = lc[0]
    b = lc[1]
    c = lc[2]
    types = jelly_types[j]
    # Per-type coefficients read once (the unrolled loop would otherwise load them per neighbour).
    ks_structural = jelly_ks[j, 0]
    ks_shear = jelly_ks[j, 1]
    kd_structural = jelly_kd[j, 0]
    kd_shear = jelly_kd[j, 1]
    x = integration.load_contiguous(q, i)
    v = integration.load_contiguous(qd, i)
    f = type(x)(type(ks_structural)(0.0))
    # Structural and shear: the 26 neighbours in the 3x3x3 block. These loops have constant
    # bounds, so Warp unrolls them and every offset below is a compile-time constant.
    # Branch-free: a neighbour outside the lattice (or of an absent spring type) is replaced by
    # the particle itself, whose zero distance gives exactly zero force (stencil_spring_force).
    # Every load is then unconditional, so the compiler can issue the 64 neighbour loads
    # together instead of one guarded load after another; same sums in the same order
    # (x + 0 = x), so the same bits.
    row = shape[1] * shape[2]
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                m = wp.abs(di) + wp.abs(dj) + wp.abs(dk)
                if m > 0:
                    ty = wp.min(m - 1, 1)  # one nonzero component: structural, else shear
                    ok = ((types >> ty) & 1) != 0 and inside(a + di, b + dj, c + dk, shape)
                    p = wp.where(ok, i + di * row + dj * shape[2] + dk, i)
                    rest = integration.entry_contiguous(jelly_rest, j, (di + 1) * 9 + (dj + 1) * 3 + dk + 1)
                    ks = wp.where(ty == 0, ks_structural, ks_shear)
                    kd = wp.where(ty == 0, kd_structural, kd_shear)
                    f += stencil_spring_force(
                        x, integration.load_contiguous(q, p), v, integration.load_contiguous(qd, p), rest * ks, -ks, kd
                    )
    # Bending: +-2 along each axis.
    has_bending = ((types >> 2) & 1) != 0
    ks_bending = jelly_ks[j, 2]
    kd_bending = jelly_kd[j, 2]
    for axis in range(3):
        for side in range(2):
            o = wp.vec3i(0, 0, 0)
            o[axis] = 4 * side - 2
            ok = has_bending and inside(a + o[0], b + o[1], c + o[2], shape)
            p = wp.where(ok, i + o[0] * row + o[1] * shape[2] + o[2], i)
            kr = integration.entry_contiguous(jelly_rest, j, 27 + axis) * ks_bending
            f += stencil_spring_force(
                x, integration.load_contiguous(q, p), v, integration.load_contiguous(qd, p), kr, -ks_bending, kd_bending
            )
    return f


@both_precisions
@wp.kernel
def eval_lattice_springs(
    # Model:
    particle_jelly: wp.array(dtype=wp.int32),
    jelly_start: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    jelly_kd: wp.array2d(dtype=Float),
    # State in:
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
    # Out (every element written; no zeroing needed):
    f_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    j = particle_jelly[i]
    f_out[i] = gather_lattice_force(i, j, jelly_start, jelly_shape, jelly_types, jelly_rest, jelly_ks, jelly_kd, q, qd)


@functools.cache
def make_gather_native(scalar, padded=False, uniform=False, shape=None, types=None, start=None):
    """``gather_native`` for ``scalar`` with the given ``_gather_snippet`` options (``shape`` a tuple).

    Its arguments are ``gather_lattice_force``'s and the uniform coefficients ``coef``, which a
    uniform gather reads instead of the rest, ks and kd tables (the others ignore it).
    """
    vec = wp.types.vector(3, scalar)

    @wp.func_native(
        _gather_snippet(_CTYPES[scalar], padded=padded, uniform=uniform, shape=shape, types=types, start=start)
    )
    def gather_native(
        i: int,
        j: int,
        jelly_start: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=scalar),
        jelly_ks: wp.array2d(dtype=scalar),
        jelly_kd: wp.array2d(dtype=scalar),
        q: wp.array(dtype=vec),
        qd: wp.array(dtype=vec),
        coef: wp.types.vector(COEF_LENGTH, scalar),
    ) -> vec: ...

    return gather_native


@functools.cache
def make_masked_gather(scalar):
    """``masked_gather`` for ``scalar``: the native gather of a masked lattice (``_masked_gather_snippet``),
    with the arguments of ``make_gather_native``'s gathers."""
    vec = wp.types.vector(3, scalar)

    @wp.func_native(_masked_gather_snippet(_CTYPES[scalar]))
    def masked_gather(
        i: int,
        j: int,
        jelly_start: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=scalar),
        jelly_ks: wp.array2d(dtype=scalar),
        jelly_kd: wp.array2d(dtype=scalar),
        q: wp.array(dtype=vec),
        qd: wp.array(dtype=vec),
        coef: wp.types.vector(COEF_LENGTH, scalar),
    ) -> vec: ...

    return masked_gather


@functools.cache
def make_integrate_lattice_stage(scalar, gather, single=False):
    """The fused stage kernel for ``scalar`` around a per-particle native gather (``make_gather_native``,
    ``make_masked_gather``).

    The kernel passes the gather both the per-jelly tables and ``stencil_coef``, the jellies'
    common coefficients (a kernel argument); a uniform gather reads the latter. The stage update is
    ``integration.stage_values_direct``, the one stage update of kernels/integration.py.

    The particle's jelly, world and inverse mass, the per-world tableau and the plane range, point
    and normal are read from the arrays' data pointers, one address computation each, instead of
    through Warp's indexing (the wrap of a negative index and a 64-bit multiply by the run-time
    stride). These are the model's and the integrator's own arrays, contiguous by construction.

    ``single``: for a model that is one jelly of particles of one mass (``LatticeData.single``):
    the jelly is 0 and the world and inverse mass are particle 0's, so the kernel reads no
    per-particle jelly, world or mass.
    """

    @wp.kernel(module="unique")
    def integrate_lattice_stage(
        stage: int,
        h: Float,
        with_contact: int,
        # Model:
        particle_inv_mass: wp.array(dtype=Float),
        particle_world: wp.array(dtype=wp.int32),
        particle_jelly: wp.array(dtype=wp.int32),
        gravity: vec3,
        jelly_start: wp.array(dtype=wp.int32),
        jelly_shape: wp.array(dtype=wp.vec3i),
        jelly_types: wp.array(dtype=wp.int32),
        jelly_rest: wp.array2d(dtype=Float),
        jelly_ks: wp.array2d(dtype=Float),
        jelly_kd: wp.array2d(dtype=Float),
        world_stage_count: wp.array(dtype=wp.int32),
        world_symplectic: wp.array(dtype=wp.int32),
        world_stage_c: wp.array2d(dtype=Float),
        world_stage_b: wp.array2d(dtype=Float),
        # Model, planes (read when with_contact != 0):
        plane_first: wp.array(dtype=wp.int32),
        plane_point: wp.array(dtype=vec3),
        plane_normal: wp.array(dtype=vec3),
        plane_hole_center: wp.array(dtype=vec3),
        plane_hole_radius: wp.array(dtype=Float),
        plane_restitution: wp.array(dtype=Float),
        plane_friction: wp.array(dtype=Float),
        eps: Float,
        eps_v: Float,
        rest_steps: Float,
        world_contact_beta: wp.array(dtype=Float),
        # The jellies' common stencil coefficients (read by uniform gathers only):
        stencil_coef: CoefVec,
        # State in (y_n) and stage state (y_s):
        q_n: wp.array(dtype=vec3),
        qd_n: wp.array(dtype=vec3),
        q_s: wp.array(dtype=vec3),
        qd_s: wp.array(dtype=vec3),
        # Out: accumulators, next stage state, and the step's result
        acc_q_out: wp.array(dtype=vec3),
        acc_qd_out: wp.array(dtype=vec3),
        q_next_out: wp.array(dtype=vec3),
        qd_next_out: wp.array(dtype=vec3),
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        # Forces, gravity and the stage update in one pass. A thread reads neighbours only from
        # the stage state y_s and writes only its own particle into other buffers, so no thread
        # depends on another's output within the launch.
        i = wp.tid()
        # The particle whose jelly, world and mass are read: itself, or 0 for all in a single jelly.
        p = i
        j = int(0)
        if wp.static(single):
            p = 0
        else:
            j = integration.int_contiguous(particle_jelly, i)
        f = gather(i, j, jelly_start, jelly_shape, jelly_types, jelly_rest, jelly_ks, jelly_kd, q_s, qd_s, stencil_coef)
        w = integration.int_contiguous(particle_world, p)
        inv_mass = integration.scalar_contiguous(particle_inv_mass, p)
        kind, x, v = integration.stage_values_direct(
            i,
            stage,
            h,
            f,
            inv_mass,
            w,
            gravity,
            world_stage_count,
            world_symplectic,
            world_stage_c,
            world_stage_b,
            q_n,
            qd_n,
            qd_s,
            acc_q_out,
            acc_qd_out,
        )
        if kind == 0:
            return
        # Contact acts on the stage's values before they are stored, so each particle is
        # written once (storing first and reading back for contact would cost a store and a load).
        if with_contact != 0 and inv_mass != type(h)(0.0):
            if kind == 1:
                # Plane contact on the step's result, as collide_planes does after the step.
                x, v = contact.contact_planes_direct(
                    x,
                    v,
                    qd_n,
                    i,
                    w,
                    plane_first,
                    plane_point,
                    plane_normal,
                    plane_hole_center,
                    plane_hole_radius,
                    plane_restitution,
                    plane_friction,
                    eps,
                    eps_v,
                    rest_steps,
                    h * integration.scalar_contiguous(world_contact_beta, w),
                    0,
                )
            else:
                # The next stage state's resting contacts, as integrators.filter_stage_contacts
                # does between stages (velocities only; h = 0: no position gain). Two calls rather
                # than one on selected inputs, which is slower on CUDA (docs/PERFORMANCE.md).
                x, v = contact.contact_planes_direct(
                    x,
                    v,
                    qd_n,
                    i,
                    w,
                    plane_first,
                    plane_point,
                    plane_normal,
                    plane_hole_center,
                    plane_hole_radius,
                    plane_restitution,
                    plane_friction,
                    eps,
                    eps_v,
                    rest_steps,
                    type(h)(0.0),
                    1,
                )
        if kind == 1:
            integration.store_contiguous(q_out, i, x)
            integration.store_contiguous(qd_out, i, v)
        else:
            integration.store_contiguous(q_next_out, i, x)
            integration.store_contiguous(qd_next_out, i, v)

    return _for_precision(integrate_lattice_stage, scalar)


def make_single_stage(scalar, shape, types):
    """The fused stage for a model of one jelly of one particle mass with padded states
    (``LatticeData.single``, ``Model.particle_array``): the jelly's lattice shape, spring-type mask,
    first particle (0) and coefficients compiled in or passed as a kernel argument, unconditional
    neighbour loads, no per-particle jelly, world or mass read (docs/PERFORMANCE.md). Built once
    per (scalar, shape, types) and compiled on first launch (Warp caches the build on disk)."""
    shape = tuple(int(n) for n in shape)
    gather = make_gather_native(scalar, padded=True, uniform=True, shape=shape, types=int(types), start=0)
    return make_integrate_lattice_stage(scalar, gather, single=True)


def make_masked_stage(scalar):
    """The fused stage of masked lattices (mesh jellies, core/masked_lattice.py): the stage kernel
    around the masked gather, built once per precision."""
    return make_integrate_lattice_stage(scalar, make_masked_gather(scalar))


@both_precisions
@wp.kernel
def eval_lattice_rows(
    # Model:
    jelly_start: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    jelly_kd: wp.array2d(dtype=Float),
    particle_coord_k: wp.array(dtype=wp.int32),
    # State in:
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
    # Scratch (one vec3 per particle) and out (every element written):
    scratch: wp.array(dtype=vec3),
    f_out: wp.array(dtype=vec3),
):
    # One thread per jelly; jellies own disjoint particle ranges, so threads never collide.
    j = wp.tid()
    lattice_rows_native(
        j, jelly_start, jelly_shape, jelly_types, jelly_rest, jelly_ks, jelly_kd, particle_coord_k, q, qd, scratch,
        f_out,
    )


@both_precisions
@wp.kernel
def integrate_lattice_rows_stage(
    stage: int,
    h: Float,
    # Model:
    jelly_start: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    jelly_kd: wp.array2d(dtype=Float),
    jelly_world: wp.array(dtype=wp.int32),
    particle_coord_k: wp.array(dtype=wp.int32),
    particle_inv_mass: wp.array(dtype=Float),
    gravity: vec3,
    world_stage_count: wp.array(dtype=wp.int32),
    world_symplectic: wp.array(dtype=wp.int32),
    world_stage_c: wp.array2d(dtype=Float),
    world_stage_b: wp.array2d(dtype=Float),
    # State in (y_n) and stage state (y_s):
    q_n: wp.array(dtype=vec3),
    qd_n: wp.array(dtype=vec3),
    q_s: wp.array(dtype=vec3),
    qd_s: wp.array(dtype=vec3),
    # Scratch (two vec3 per particle):
    scratch: wp.array(dtype=vec3),
    f_scratch: wp.array(dtype=vec3),
    # Out: accumulators, next stage state, and the step's result
    acc_q_out: wp.array(dtype=vec3),
    acc_qd_out: wp.array(dtype=vec3),
    q_next_out: wp.array(dtype=vec3),
    qd_next_out: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    # The CPU fused stage: one thread per jelly computes its forces (row loops) and then
    # its particles' stage update, both vectorised. Jellies own disjoint particle ranges.
    j = wp.tid()
    lattice_rows_stage_native(
        j,
        stage,
        h,
        jelly_start,
        jelly_shape,
        jelly_types,
        jelly_rest,
        jelly_ks,
        jelly_kd,
        jelly_world,
        particle_coord_k,
        particle_inv_mass,
        gravity,
        world_stage_count,
        world_symplectic,
        world_stage_c,
        world_stage_b,
        q_n,
        qd_n,
        q_s,
        qd_s,
        scratch,
        f_scratch,
        acc_q_out,
        acc_qd_out,
        q_next_out,
        qd_next_out,
        q_out,
        qd_out,
    )


@both_precisions
@wp.kernel
def reduce_lattice_springs(
    # Model:
    particle_jelly: wp.array(dtype=wp.int32),
    jelly_start: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    # State in:
    q: wp.array(dtype=vec3),
    # Out, per jelly (zeroed by the caller):
    spring_energy_out: wp.array(dtype=Float),
):
    # Each particle sums 1/2 ks (l - r)^2 over its forward (half-stencil) neighbours, so each
    # spring is counted once, from its lexicographically smaller end.
    i = wp.tid()
    j = particle_jelly[i]
    shape = jelly_shape[j]
    lc = lattice_coord(i - jelly_start[j], shape)
    types = jelly_types[j]
    x = q[i]
    e = type(spring_energy_out).dtype(0.0)
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                forward = di > 0 or (di == 0 and (dj > 0 or (dj == 0 and dk > 0)))
                if forward:
                    ty = wp.min(wp.abs(di) + wp.abs(dj) + wp.abs(dk) - 1, 1)
                    if ((types >> ty) & 1) != 0 and inside(lc[0] + di, lc[1] + dj, lc[2] + dk, shape):
                        p = i + (di * shape[1] + dj) * shape[2] + dk
                        stretch = wp.length(x - q[p]) - jelly_rest[j, (di + 1) * 9 + (dj + 1) * 3 + dk + 1]
                        e += jelly_ks[j, ty] * stretch * stretch
    if ((types >> 2) & 1) != 0:
        for axis in range(3):
            o = wp.vec3i(0, 0, 0)
            o[axis] = 2
            if inside(lc[0] + o[0], lc[1] + o[1], lc[2] + o[2], shape):
                p = i + (o[0] * shape[1] + o[1]) * shape[2] + o[2]
                stretch = wp.length(x - q[p]) - jelly_rest[j, 27 + axis]
                e += jelly_ks[j, 2] * stretch * stretch
    e = type(e)(0.5) * e
    if wp.isfinite(e):
        wp.atomic_add(spring_energy_out, j, e)


# -- Masked lattices (mesh jellies): the lattice stencil over the points that exist -------------------


@wp.func
def masked_neighbour(i: int, ok: bool, cell: int, offset: int, grid_start: int, grid: wp.array(dtype=wp.int32)):
    """The particle at lattice index cell + offset, or i itself (zero force) when the offset is
    off the lattice (``ok`` false) or the point is not in the jelly (grid entry -1)."""
    p = grid[grid_start + wp.where(ok, cell + offset, cell)]
    return wp.where(p < 0, i, p)


@both_precisions
@wp.kernel
def eval_masked_springs(
    # Model:
    particle_jelly: wp.array(dtype=wp.int32),
    particle_cell: wp.array(dtype=wp.int32),
    jelly_shape: wp.array(dtype=wp.vec3i),
    jelly_grid_start: wp.array(dtype=wp.int32),
    grid: wp.array(dtype=wp.int32),
    jelly_types: wp.array(dtype=wp.int32),
    jelly_rest: wp.array2d(dtype=Float),
    jelly_ks: wp.array2d(dtype=Float),
    jelly_kd: wp.array2d(dtype=Float),
    # State in:
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
    # Out (every element written):
    f_out: wp.array(dtype=vec3),
):
    # One thread per particle gathers the stencil springs to its present neighbours (as the
    # lattice path's gather_lattice_force, with the neighbour looked up in the jelly's grid of
    # particle indices), each with springs.spring_force: no atomics, a fixed order, so deterministic.
    i = wp.tid()
    j = particle_jelly[i]
    shape = jelly_shape[j]
    cell = particle_cell[i]
    gs = jelly_grid_start[j]
    c = cell % shape[2]
    t = cell // shape[2]
    b = t % shape[1]
    a = t // shape[1]
    row = shape[1] * shape[2]
    types = jelly_types[j]
    x = q[i]
    v = qd[i]
    f = type(x)(type(jelly_rest).dtype(0.0))
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                m = wp.abs(di) + wp.abs(dj) + wp.abs(dk)
                if m > 0:
                    ty = wp.min(m - 1, 1)  # one nonzero component: structural, else shear
                    ok = ((types >> ty) & 1) != 0
                    ok = ok and a + di >= 0 and a + di < shape[0] and b + dj >= 0 and b + dj < shape[1]
                    ok = ok and c + dk >= 0 and c + dk < shape[2]
                    p = masked_neighbour(i, ok, cell, di * row + dj * shape[2] + dk, gs, grid)
                    rest = jelly_rest[j, (di + 1) * 9 + (dj + 1) * 3 + dk + 1]
                    f += springs.spring_force(x, q[p], v, qd[p], rest, jelly_ks[j, ty], jelly_kd[j, ty])
    if ((types >> 2) & 1) != 0:
        for axis in range(3):
            for side in range(2):
                o = wp.vec3i(0, 0, 0)
                o[axis] = 4 * side - 2
                ok = a + o[0] >= 0 and a + o[0] < shape[0] and b + o[1] >= 0 and b + o[1] < shape[1]
                ok = ok and c + o[2] >= 0 and c + o[2] < shape[2]
                p = masked_neighbour(i, ok, cell, o[0] * row + o[1] * shape[2] + o[2], gs, grid)
                rest = jelly_rest[j, 27 + axis]
                f += springs.spring_force(x, q[p], v, qd[p], rest, jelly_ks[j, 2], jelly_kd[j, 2])
    f_out[i] = f
