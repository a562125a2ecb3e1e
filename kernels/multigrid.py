"""Geometric multigrid for the implicit system of a lattice jelly: transfer, Galerkin coarsening, smoothing.

Level 0 is the jelly's lattice (``nx x ny x nz`` particles, flat index ``(x ny + y) nz + z``), with
the implicit system of ``kernels/implicit.py``: A = M + sum_s B_s over the spring list, filtered
by the constraint projectors S_i. Level k + 1 coarsens each axis of level k with more than two
nodes: a coarse node sits on every even fine node, plus one on the last fine node when the count
is even (``coarse_size``), so odd and even sizes both keep the lattice's ends. Prolongation P is
1-D linear interpolation along each axis between those positions (trilinear in 3-D); restriction
is its transpose. It reproduces every field linear in the lattice coordinates exactly: the
translations and (for a nearly undeformed jelly) the rotations that make the stiff system
nearly singular.

Coarse operators are Galerkin products, stored dense: 27 3x3 blocks per node, one per neighbour
offset (slot ``(ox + 1) 9 + (oy + 1) 3 + (oz + 1)``, 13 the node itself), slot-major (``a[slot,
node]``: the threads of a warp, consecutive nodes, load one slot's blocks from consecutive
addresses, where node-major blocks would be strided). The fine operator used for the first
product is the projected system

    A^ = S A S + s (I - S)       (s: a diagonal scale of the row; S = I on free particles)

with each bending spring (offset 2 along an axis, the one 33rd-neighbour reach of the stencil)
split into two half-length springs with twice its block. That splitting has the same energy on
every linear field and never less on any field ((u_a - u_c)^T B (u_a - u_c) <= 2 (u_a - u_b)^T B
(u_a - u_b) + 2 (u_b - u_c)^T B (u_b - u_c)), and it keeps the fine operator within the 27-point
stencil, so every Galerkin product is 27-point again (a product with the 33-point operator would
be 125-point on the first coarse level). Fixed and contact-constrained directions keep their
Dirichlet meaning on the coarse levels: their part of a coarse function's elastic energy is
taken with the constrained components removed.

Products with a coarse operator are taken in difference form, A x = R x_I + sum_J A_IJ (x_J - x_I)
with R the level's row sums, which restrict exactly (P's rows sum to 1) and on the lattice are
formed without cancellation (m I on a free particle): in float32 the assembled diagonal of a stiff
level carries rounding noise the size of the mass, which made coarse levels indefinite along the
translations.

The smoother is damped block-Jacobi (order-free, one thread per node); a V-cycle with the same
number of pre- and post-smoothing sweeps, started from zero, is a symmetric positive definite
operator when every level's smoother converges (omega < 2 / lambda_max(D^-1 A)) and the coarsest
solve is SPD: it is a valid CG preconditioner. The jelly's own lattice joins either the same way
or additively (z = omega D^-1 r + P V(P^T r), no spring product; ``core/multigrid.py``). The
coarsest level (at most 2 x 2 x 2 nodes) is solved exactly by a dense Cholesky factorisation on
one thread, in float64.

Every kernel exists for float32 and float64 and runs on the CPU and CUDA. The host side is
``softsim_warp/core/multigrid.py``.
"""

import warp as wp

from .implicit import TILE
from .lattice import REST_SLOTS
from .precision import Float, both_precisions, mat33, vec3
from .springs import spring_jacobian

wp.set_module_options({"enable_backward": False})

STENCIL = 27  # blocks per node of a coarse operator
CENTER = 13  # slot of the node itself
HALF = 14  # slots CENTER..26: the node itself and the 13 offsets after it (the others are transposes)
COARSEST_NODES = 8  # the coarsest level: at most 2 nodes per axis
COARSEST_UNKNOWNS = 3 * COARSEST_NODES


def coarse_size(n: int) -> int:
    """Nodes of the coarsening of an axis of ``n`` nodes (``n`` itself at 2 nodes or fewer)."""
    if n <= 2:
        return n
    return (n + 1) // 2 if n % 2 else n // 2 + 1



# The jelly's lattice tables (one jelly) passed by value to the kernels whose neighbour loops are
# unrolled, so they read them from the launch's parameters rather than from memory (96 table loads
# per particle otherwise). mg_fine_setup_lattice's slot loop is not unrolled (27 > Warp's unroll
# limit), and a by-value table indexed at run time goes to local memory: it reads arrays.
rest_vec = wp.types.vector(REST_SLOTS, Float)


@wp.func
def axis_weight(i: int, c: int, n: int, nc: int, one: Float):
    """P's 1-D factor: weight of coarse node c in fine node i (axis of n fine, nc coarse nodes),
    in the precision of ``one``."""
    if i < 0 or i >= n or c < 0 or c >= nc:
        return type(one)(0.0)
    if nc == n:
        return wp.where(i == c, one, type(one)(0.0))
    if i % 2 == 0:
        return wp.where(c == i // 2, one, type(one)(0.0))
    if i == n - 1:
        # Even n: the last fine node is a coarse node of its own.
        return wp.where(c == nc - 1, one, type(one)(0.0))
    if c == i // 2 or c == i // 2 + 1:
        return type(one)(0.5)
    return type(one)(0.0)


@wp.func
def first_fine(c: int, n: int, nc: int):
    """The lowest fine index that coarse node c can weigh on (candidates: it and the next two)."""
    if nc == n:
        return c
    return wp.min(2 * c, n - 1) - 1


@wp.func
def first_coarse(i: int, n: int, nc: int):
    """The lowest coarse index fine node i can weigh on (candidates: it and the next)."""
    if nc == n:
        return i
    return i // 2


@wp.func
def node_index(x: int, y: int, z: int, shape: wp.vec3i):
    return (x * shape[1] + y) * shape[2] + z


@wp.func
def node_coord(i: int, shape: wp.vec3i):
    z = i % shape[2]
    y = (i // shape[2]) % shape[1]
    x = i // (shape[1] * shape[2])
    return wp.vec3i(x, y, z)


@wp.func
def inside(x: int, y: int, z: int, shape: wp.vec3i):
    return x >= 0 and y >= 0 and z >= 0 and x < shape[0] and y < shape[1] and z < shape[2]


@wp.func
def slot_offset(slot: int):
    return wp.vec3i(slot // 9 - 1, (slot // 3) % 3 - 1, slot % 3 - 1)


# -- the jelly's lattice, from positions --------------------------------------------------------
# One jelly's springs are implicit in the lattice (kernels/lattice.py: 26 neighbours in the
# 3x3x3 block, structural or shear, and 6 bending at +-2 along an axis), with one rest length
# per offset and one ks, kd per type. Each spring's block is springs.spring_jacobian's, which the
# kernels below recompute from the linearisation point wherever they need it, one thread per
# particle gathering over its neighbours: no spring list, no stored blocks, no atomics. A block
# is the same from either end of its spring (spring_jacobian of -d is that of d), so the gathered
# operator is exactly symmetric.


@wp.func
def smallest_normal(like: wp.float32):
    """The smallest normal float32."""
    return wp.float32(1.1754943508222875e-38)


@wp.func
def smallest_normal(like: wp.float64):  # noqa: F811 (the float64 overload of the same Warp function)
    """The smallest normal float64."""
    return wp.float64(2.2250738585072014e-308)


@wp.func
def pair_product(qi: vec3, qj: vec3, pi: vec3, pj: vec3, rest: Float, ks: Float, kd: Float, h: Float):
    """(B (p_i - p_j), (p_i - p_j).B (p_i - p_j)) for the spring (i, j), B its spring_jacobian block.

    The CG product's form of that block, the one place it is not called: B = alpha d^d^T + beta I
    with alpha = h kd + h^2 ks (1 - t), beta = h^2 ks t and t = max(0, 1 - r/|d|), applied to
    p_i - p_j without forming the matrix and without branches (one square root, one division;
    the matrix form costs several times the arithmetic in the kernel run most often).
    tests/test_kernels_multigrid.py checks it against spring_jacobian on random springs in both
    precisions. The smallest normal number added to |d|^2 keeps 1/|d| finite at q_i = q_j (the
    kernels' stand-in for an absent neighbour), where d^ = 0 and t = 0 (rest > 0): a zero block,
    as spring_jacobian gives there.
    """
    d = qi - qj
    inv = type(rest)(1.0) / wp.sqrt(wp.dot(d, d) + smallest_normal(rest))
    dhat = d * inv
    transverse = wp.max(type(rest)(1.0) - rest * inv, type(rest)(0.0))
    hks = h * h * ks
    alpha = h * kd + hks * (type(rest)(1.0) - transverse)
    dp = pi - pj
    t = alpha * wp.dot(dhat, dp) * dhat + (hks * transverse) * dp
    return t, wp.dot(dp, t)


@wp.func
def neighbour_type(di: int, dj: int, dk: int):
    """Spring type of a 3x3x3-block offset: 0 structural (one nonzero component), 1 shear."""
    return wp.min(wp.abs(di) + wp.abs(dj) + wp.abs(dk) - 1, 1)


@both_precisions
@wp.kernel(module="unique")
def mg_lattice_jacobians(
    h: Float,
    kv_scale: Float,
    shape: wp.vec3i,
    types: int,
    # Model (the jelly's rows of the lattice tables, kernels/lattice.py, by value):
    rest: rest_vec,
    ks: vec3,
    kd: vec3,
    # Linearisation point and velocity iterate:
    q: wp.array(dtype=vec3),
    qd_k: wp.array(dtype=vec3),
    # Out: sum of the particle's spring blocks, kv_scale df/dx v_k (as eval_spring_jacobians
    # accumulates them, every element written) and the linearisation point the products read
    diag_block_out: wp.array(dtype=mat33),
    rhs_out: wp.array(dtype=vec3),
    q_lin_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    c = node_coord(i, shape)
    qi = q[i]
    vi = qd_k[i]
    q_lin_out[i] = qi
    diag = wp.matrix(shape=(3, 3), dtype=type(h))
    kv = wp.vector(length=3, dtype=type(h))
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                if di != 0 or dj != 0 or dk != 0:
                    spring_type = neighbour_type(di, dj, dk)
                    if ((types >> spring_type) & 1) != 0 and inside(c[0] + di, c[1] + dj, c[2] + dk, shape):
                        j = node_index(c[0] + di, c[1] + dj, c[2] + dk, shape)
                        block, stiffness = spring_jacobian(
                            qi - q[j], rest[(di + 1) * 9 + (dj + 1) * 3 + dk + 1], ks[spring_type], kd[spring_type], h
                        )
                        diag = diag + block
                        if kv_scale != type(h)(0.0):
                            # df_i/dx v = -S (v_i - v_j), as eval_spring_jacobians adds it.
                            kv = kv + (-kv_scale * stiffness) * (vi - qd_k[j])
    if ((types >> 2) & 1) != 0:
        for axis in range(3):
            for side in range(2):
                o = wp.vec3i(0, 0, 0)
                o[axis] = 4 * side - 2
                if inside(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape):
                    j = node_index(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape)
                    block, stiffness = spring_jacobian(qi - q[j], rest[27 + axis], ks[2], kd[2], h)
                    diag = diag + block
                    if kv_scale != type(h)(0.0):
                        kv = kv + (-kv_scale * stiffness) * (vi - qd_k[j])
    diag_block_out[i] = diag
    rhs_out[i] = kv


# Fast math (approximate square root and reciprocal, 1 ulp or so) in the CG product only, the
# kernel run most often (docs/IMPLICIT.md). The operator stays exactly symmetric: a spring's block
# is the same from either end.
@both_precisions
@wp.kernel(module="unique", module_options={"fast_math": True})
def mg_lattice_mv(
    n: int,
    slot: int,
    h: Float,
    shape: wp.vec3i,
    types: int,
    rest: rest_vec,
    ks: vec3,
    kd: vec3,
    # System: the linearisation point (mg_lattice_jacobians) and the mass plus friction damper
    q: wp.array(dtype=vec3),
    mass_eff: wp.array(dtype=Float),
    p: wp.array(dtype=vec3),
    # Out: y = A p = M p + sum_j B_ij (p_i - p_j) (every element written); scalars[slot] += p.A p
    y_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    quad = type(h)(0.0)
    if i < n:
        c = node_coord(i, shape)
        qi = q[i]
        pi = p[i]
        mp = mass_eff[i] * pi
        acc = mp
        # p.A p = sum_i p_i.M p_i + sum over springs of (p_i - p_j).B (p_i - p_j): each spring
        # is met from both ends, so half of it here. Summing these non-negative terms keeps
        # float32 accurate, where sum_i p_i.(A p)_i would cancel for smooth p.
        spring_quad = type(h)(0.0)
        # An absent neighbour (outside the lattice, or of a spring type the jelly lacks) is the
        # particle itself, whose zero distance and zero p_i - p_j give exactly zero: every load is
        # unconditional.
        row = shape[1] * shape[2]
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    if di != 0 or dj != 0 or dk != 0:
                        spring_type = neighbour_type(di, dj, dk)
                        ok = ((types >> spring_type) & 1) != 0 and inside(c[0] + di, c[1] + dj, c[2] + dk, shape)
                        j = wp.where(ok, i + di * row + dj * shape[2] + dk, i)
                        t, e = pair_product(
                            qi, q[j], pi, p[j], rest[(di + 1) * 9 + (dj + 1) * 3 + dk + 1],
                            ks[spring_type], kd[spring_type], h,
                        )
                        acc = acc + t
                        spring_quad = spring_quad + e
        has_bending = ((types >> 2) & 1) != 0
        for axis in range(3):
            for side in range(2):
                o = wp.vec3i(0, 0, 0)
                o[axis] = 4 * side - 2
                ok = has_bending and inside(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape)
                j = wp.where(ok, i + o[0] * row + o[1] * shape[2] + o[2], i)
                t, e = pair_product(qi, q[j], pi, p[j], rest[27 + axis], ks[2], kd[2], h)
                acc = acc + t
                spring_quad = spring_quad + e
        y_out[i] = acc
        quad = wp.dot(pi, mp) + type(h)(0.5) * spring_quad
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(quad)), offset=slot)


@wp.func
def shifted(c: wp.vec3i, axis: int, delta: int):
    """c moved by delta along axis."""
    return wp.vec3i(
        c[0] + wp.where(axis == 0, delta, 0), c[1] + wp.where(axis == 1, delta, 0), c[2] + wp.where(axis == 2, delta, 0)
    )


@wp.func
def bending_block(
    a: wp.vec3i, axis: int, shape: wp.vec3i, rest: wp.array2d(dtype=Float), ks: Float, kd: Float, h: Float,
    q: wp.array(dtype=vec3),
):
    """Block of the bending spring (a, a + 2 e_axis), zero where it does not exist."""
    if a[axis] < 0 or a[axis] + 2 >= shape[axis]:
        return wp.matrix(shape=(3, 3), dtype=type(ks))
    b = shifted(a, axis, 2)
    qa = q[node_index(a[0], a[1], a[2], shape)]
    qb = q[node_index(b[0], b[1], b[2], shape)]
    block, _stiffness = spring_jacobian(qa - qb, rest[0, 27 + axis], ks, kd, h)
    return block


@both_precisions
@wp.kernel(module="unique")
def mg_fine_setup_lattice(
    h: Float,
    shape: wp.vec3i,
    types: int,
    rest: wp.array2d(dtype=Float),
    ks: wp.array2d(dtype=Float),
    kd: wp.array2d(dtype=Float),
    # System: linearisation point, mass plus friction damper, constraint filters
    q: wp.array(dtype=vec3),
    mass_eff: wp.array(dtype=Float),
    filters: wp.array(dtype=mat33),
    # Out: the split, projected operator as a 27-block stencil, its row sums, the smoother's block inverses
    a_out: wp.array2d(dtype=mat33),
    rowsum_out: wp.array(dtype=mat33),
    dinv_out: wp.array(dtype=mat33),
):
    i = wp.tid()
    c = node_coord(i, shape)
    identity = wp.identity(n=3, dtype=type(h))
    qi = q[i]
    filter_i = filters[i]
    has_bending = ((types >> 2) & 1) != 0
    ks_b = ks[0, 2]
    kd_b = kd[0, 2]
    # d: the sum of every spring block at i (its 32 neighbours) plus the mass; extra: the split
    # bending springs' excess on the diagonal, B on each end of a bending spring at i and 4 B
    # on the one centred on i.
    d = mass_eff[i] * identity
    extra = wp.matrix(shape=(3, 3), dtype=type(h))
    if has_bending:
        for axis in range(3):
            b_lo = bending_block(shifted(c, axis, -2), axis, shape, rest, ks_b, kd_b, h, q)
            b_hi = bending_block(c, axis, shape, rest, ks_b, kd_b, h, q)
            b_c = bending_block(shifted(c, axis, -1), axis, shape, rest, ks_b, kd_b, h, q)
            d = d + b_lo + b_hi
            extra = extra + b_lo + b_hi + type(h)(4.0) * b_c
    # Off-diagonal blocks and the row sum without its constrained part, formed without
    # cancellation: S M S + sum_j S B_ij (S_i - S_j) (+ s (I - S) below).
    rowsum = filter_i * (mass_eff[i] * identity) * filter_i
    for slot in range(STENCIL):
        if slot != CENTER:
            o = slot_offset(slot)
            block = wp.matrix(shape=(3, 3), dtype=type(h))
            if inside(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape):
                j = node_index(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape)
                neighbour_block = wp.matrix(shape=(3, 3), dtype=type(h))
                spring_type = neighbour_type(o[0], o[1], o[2])
                if ((types >> spring_type) & 1) != 0:
                    neighbour_block, _stiffness = spring_jacobian(
                        qi - q[j], rest[0, slot], ks[0, spring_type], kd[0, spring_type], h
                    )
                    d = d + neighbour_block
                if has_bending and spring_type == 0:
                    # An axis edge (i, i + o): twice each of the two bending springs through it,
                    # the one centred on i and the one beyond i + o or i.
                    axis = 0
                    if o[1] != 0:
                        axis = 1
                    if o[2] != 0:
                        axis = 2
                    far = c
                    if o[axis] < 0:
                        far = shifted(c, axis, -2)
                    neighbour_block = neighbour_block + type(h)(2.0) * (
                        bending_block(shifted(c, axis, -1), axis, shape, rest, ks_b, kd_b, h, q)
                        + bending_block(far, axis, shape, rest, ks_b, kd_b, h, q)
                    )
                filter_j = filters[j]
                block = -(filter_i * neighbour_block * filter_j)
                rowsum = rowsum + filter_i * neighbour_block * (filter_i - filter_j)
            a_out[slot, i] = block
    # Constrained directions: an identity row scaled like the rest of the row.
    s = (d[0, 0] + d[1, 1] + d[2, 2]) / type(h)(3.0)
    if s <= type(h)(0.0):
        s = type(h)(1.0)
    free = identity - filter_i
    dinv_out[i] = filter_i * wp.inverse(filter_i * d * filter_i + s * free) * filter_i
    a_out[CENTER, i] = filter_i * (d + extra) * filter_i + s * free
    rowsum_out[i] = rowsum + s * free


@both_precisions
@wp.kernel(module="unique")
def mg_galerkin(
    shape: wp.vec3i,
    coarse_shape: wp.vec3i,
    # The level above as a dense stencil [nodes, 27] and its row sums
    a_fine: wp.array2d(dtype=mat33),
    rowsum_fine: wp.array(dtype=mat33),
    # Out: the coarse stencil, its row sums and its diagonal blocks' inverses
    a_out: wp.array2d(dtype=mat33),
    rowsum_out: wp.array(dtype=mat33),
    dinv_out: wp.array(dtype=mat33),
):
    t, node = wp.tid()
    slot = CENTER + t
    o = slot_offset(slot)
    ci = node_coord(node, coarse_shape)
    cj = ci + o
    acc = a_fine.dtype(0.0)
    if not inside(cj[0], cj[1], cj[2], coarse_shape):
        a_out[slot, node] = acc
        return
    zero = acc[0, 0]
    one = type(zero)(1.0)
    # (R A P)_IJ = sum over fine pairs (i, j), |i - j| <= 1, of P_iI A_ij P_jJ; P factors by axis.
    fi = wp.vec3i(
        first_fine(ci[0], shape[0], coarse_shape[0]),
        first_fine(ci[1], shape[1], coarse_shape[1]),
        first_fine(ci[2], shape[2], coarse_shape[2]),
    )
    fj = wp.vec3i(
        first_fine(cj[0], shape[0], coarse_shape[0]),
        first_fine(cj[1], shape[1], coarse_shape[1]),
        first_fine(cj[2], shape[2], coarse_shape[2]),
    )
    # Loops over runtime ranges: Warp unrolls constant ones, 3^6 copies of the body here.
    for ix in range(fi[0], fi[0] + 3):
        wix = axis_weight(ix, ci[0], shape[0], coarse_shape[0], one)
        if wix == zero:
            continue
        for jx in range(fj[0], fj[0] + 3):
            if wp.abs(jx - ix) > 1:
                continue
            wx = wix * axis_weight(jx, cj[0], shape[0], coarse_shape[0], one)
            if wx == zero:
                continue
            for iy in range(fi[1], fi[1] + 3):
                wiy = axis_weight(iy, ci[1], shape[1], coarse_shape[1], one)
                if wiy == zero:
                    continue
                for jy in range(fj[1], fj[1] + 3):
                    if wp.abs(jy - iy) > 1:
                        continue
                    wxy = wx * wiy * axis_weight(jy, cj[1], shape[1], coarse_shape[1], one)
                    if wxy == zero:
                        continue
                    for iz in range(fi[2], fi[2] + 3):
                        wiz = axis_weight(iz, ci[2], shape[2], coarse_shape[2], one)
                        if wiz == zero:
                            continue
                        for jz in range(fj[2], fj[2] + 3):
                            if wp.abs(jz - iz) > 1:
                                continue
                            w = wxy * wiz * axis_weight(jz, cj[2], shape[2], coarse_shape[2], one)
                            if w == zero:
                                continue
                            i = node_index(ix, iy, iz, shape)
                            slot_ij = (jx - ix + 1) * 9 + (jy - iy + 1) * 3 + (jz - iz + 1)
                            acc = acc + w * a_fine[slot_ij, i]
    if slot == CENTER:
        sym = type(zero)(0.5) * (acc + wp.transpose(acc))
        a_out[slot, node] = sym
        dinv_out[node] = wp.inverse(sym)
        # Row sums restrict exactly (the rows of P sum to 1): sum_J (P^T A P)_IJ = sum_i P_iI rowsum_i.
        row_sum = rowsum_fine.dtype(0.0)
        for ix in range(fi[0], fi[0] + 3):
            wx = axis_weight(ix, ci[0], shape[0], coarse_shape[0], one)
            if wx == zero:
                continue
            for iy in range(fi[1], fi[1] + 3):
                wxy = wx * axis_weight(iy, ci[1], shape[1], coarse_shape[1], one)
                if wxy == zero:
                    continue
                for iz in range(fi[2], fi[2] + 3):
                    w = wxy * axis_weight(iz, ci[2], shape[2], coarse_shape[2], one)
                    if w == zero:
                        continue
                    row_sum = row_sum + w * rowsum_fine[node_index(ix, iy, iz, shape)]
        rowsum_out[node] = row_sum
    else:
        a_out[slot, node] = acc
        a_out[STENCIL - 1 - slot, node_index(cj[0], cj[1], cj[2], coarse_shape)] = wp.transpose(acc)


@wp.func
def stencil_result(
    mode: int, omega: Float, node: int, xi: vec3, r: vec3, dinv: wp.array(dtype=mat33), y_out: wp.array(dtype=vec3)
):
    """Write a stencil kernel's output for ``node`` from its residual r = b - A x: r itself
    (mode 0) or the damped Jacobi sweep x + omega D^-1 r (otherwise)."""
    if mode == 0:
        y_out[node] = r
    else:
        y_out[node] = xi + omega * (dinv[node] * r)


@both_precisions
@wp.kernel(module="unique")
def mg_stencil_op(
    mode: int,
    omega: Float,
    shape: wp.vec3i,
    a: wp.array2d(dtype=mat33),
    rowsum: wp.array(dtype=mat33),
    dinv: wp.array(dtype=mat33),
    b: wp.array(dtype=vec3),
    x: wp.array(dtype=vec3),
    # Out: mode 0 the residual b - A x; 1 a Jacobi sweep x + omega D^-1 (b - A x) (the sweep
    # from x = 0 is mg_restrict's)
    y_out: wp.array(dtype=vec3),
):
    node = wp.tid()
    c = node_coord(node, shape)
    # A x = R x_I + sum_J A_IJ (x_J - x_I), R the row sum: no cancellation of the large
    # stiffness terms on smooth x, and translations see exactly R (the mass) on every level.
    xi = x[node]
    r = b[node] - rowsum[node] * xi
    # Constant loops (unrolled) and branch-free: a neighbour outside the level stands as the node
    # itself, whose x_J - x_I = 0 adds exactly nothing, so every load is unconditional and the
    # compiler can issue them together (guarded loads in a slot loop are issued one at a time).
    row = shape[1] * shape[2]
    for ox in range(3):
        for oy in range(3):
            for oz in range(3):
                if ox != 1 or oy != 1 or oz != 1:
                    ok = inside(c[0] + ox - 1, c[1] + oy - 1, c[2] + oz - 1, shape)
                    j = wp.where(ok, node + (ox - 1) * row + (oy - 1) * shape[2] + oz - 1, node)
                    r = r - a[ox * 9 + oy * 3 + oz, node] * (x[j] - xi)
    stencil_result(mode, omega, node, xi, r, dinv, y_out)


@wp.func
def interpolate(c: wp.vec3i, shape: wp.vec3i, coarse_shape: wp.vec3i, e: wp.array(dtype=vec3)):
    """(P e) at fine node c: the 2 x 2 x 2 coarse candidates, unrolled and branch-free (weight 0, clamped address)."""
    f = wp.vec3i(
        first_coarse(c[0], shape[0], coarse_shape[0]),
        first_coarse(c[1], shape[1], coarse_shape[1]),
        first_coarse(c[2], shape[2], coarse_shape[2]),
    )
    acc = e.dtype(0.0)
    zero = acc[0]
    one = type(zero)(1.0)
    for ax in range(2):
        wx = axis_weight(c[0], f[0] + ax, shape[0], coarse_shape[0], one)
        jx = wp.min(f[0] + ax, coarse_shape[0] - 1)
        for ay in range(2):
            wxy = wx * axis_weight(c[1], f[1] + ay, shape[1], coarse_shape[1], one)
            jy = wp.min(f[1] + ay, coarse_shape[1] - 1)
            for az in range(2):
                w = wxy * axis_weight(c[2], f[2] + az, shape[2], coarse_shape[2], one)
                acc = acc + w * e[node_index(jx, jy, wp.min(f[2] + az, coarse_shape[2] - 1), coarse_shape)]
    return acc


@both_precisions
@wp.kernel(module="unique")
def mg_stencil_op_lanes(
    lanes: int,
    mode: int,
    omega: Float,
    shape: wp.vec3i,
    a: wp.array2d(dtype=mat33),
    rowsum: wp.array(dtype=mat33),
    dinv: wp.array(dtype=mat33),
    b: wp.array(dtype=vec3),
    x: wp.array(dtype=vec3),
    # Mode 2: the level below and its correction e, prolongated onto x first
    coarse_shape: wp.vec3i,
    e: wp.array(dtype=vec3),
    # Out: as mg_stencil_op's modes 0 and 1; mode 2 the sweep from x + P e (mg_prolong, then mode 1)
    y_out: wp.array(dtype=vec3),
):
    """mg_stencil_op with ``lanes`` threads per node (a block each), for the small levels.

    A one-thread node loads its 26 blocks in turn, each at the memory's latency, so a small
    level costs about the same whatever its size. Lane l takes the slots l, l + lanes, ... and
    the block sums them, so the loads overlap (docs/IMPLICIT.md). On the CPU, where a
    block is one thread, ``lanes`` is 1 and the one thread takes every slot. Mode 2 adds the
    prolongated correction to each x it reads (a launch less per level and cycle).
    """
    node, lane = wp.tid()
    c = node_coord(node, shape)
    xi = x[node]
    if mode == 2:
        xi = xi + interpolate(c, shape, coarse_shape, e)
    t = wp.vector(length=3, dtype=type(omega))
    slot = lane
    while slot < STENCIL:
        o = slot_offset(slot)
        cj = c + o
        if slot != CENTER and inside(cj[0], cj[1], cj[2], shape):
            xj = x[node_index(cj[0], cj[1], cj[2], shape)]
            if mode == 2:
                xj = xj + interpolate(cj, shape, coarse_shape, e)
            t = t + a[slot, node] * (xj - xi)
        slot += lanes
    total = wp.tile_sum(wp.tile(t, preserve_type=True))
    if lane == 0:
        stencil_result(mode, omega, node, xi, b[node] - rowsum[node] * xi - total[0], dinv, y_out)


@both_precisions
@wp.kernel(module="unique")
def mg_restrict(
    shape: wp.vec3i,
    coarse_shape: wp.vec3i,
    r: wp.array(dtype=vec3),
    omega: Float,
    dinv: wp.array(dtype=mat33),
    # Out: the coarse right-hand side R r, and the coarse level's first smoothing sweep from
    # zero, omega D^-1 R r (the cycle's next step, done here: one launch less per level)
    b_out: wp.array(dtype=vec3),
    x_out: wp.array(dtype=vec3),
):
    node = wp.tid()
    c = node_coord(node, coarse_shape)
    f = wp.vec3i(
        first_fine(c[0], shape[0], coarse_shape[0]),
        first_fine(c[1], shape[1], coarse_shape[1]),
        first_fine(c[2], shape[2], coarse_shape[2]),
    )
    one = type(omega)(1.0)
    # Constant loops (unrolled) over the 3 x 3 x 3 candidates, branch-free: a candidate outside
    # the level has weight 0 and loads a clamped address.
    wx = r.dtype(
        axis_weight(f[0], c[0], shape[0], coarse_shape[0], one),
        axis_weight(f[0] + 1, c[0], shape[0], coarse_shape[0], one),
        axis_weight(f[0] + 2, c[0], shape[0], coarse_shape[0], one),
    )
    wy = r.dtype(
        axis_weight(f[1], c[1], shape[1], coarse_shape[1], one),
        axis_weight(f[1] + 1, c[1], shape[1], coarse_shape[1], one),
        axis_weight(f[1] + 2, c[1], shape[1], coarse_shape[1], one),
    )
    wz = r.dtype(
        axis_weight(f[2], c[2], shape[2], coarse_shape[2], one),
        axis_weight(f[2] + 1, c[2], shape[2], coarse_shape[2], one),
        axis_weight(f[2] + 2, c[2], shape[2], coarse_shape[2], one),
    )
    acc = wp.vector(length=3, dtype=type(omega))
    for ax in range(3):
        ix = wp.clamp(f[0] + ax, 0, shape[0] - 1)
        for ay in range(3):
            iy = wp.clamp(f[1] + ay, 0, shape[1] - 1)
            wxy = wx[ax] * wy[ay]
            for az in range(3):
                i = node_index(ix, iy, wp.clamp(f[2] + az, 0, shape[2] - 1), shape)
                acc = acc + (wxy * wz[az]) * r[i]
    b_out[node] = acc
    x_out[node] = omega * (dinv[node] * acc)


@both_precisions
@wp.kernel(module="unique")
def mg_prolong(
    shape: wp.vec3i,
    coarse_shape: wp.vec3i,
    e: wp.array(dtype=vec3),
    # In/out: x += P e
    x: wp.array(dtype=vec3),
):
    i = wp.tid()
    x[i] = x[i] + interpolate(node_coord(i, shape), shape, coarse_shape, e)


@both_precisions
@wp.kernel(module="unique")
def mg_fine_pre(
    omega: Float,
    mass_eff: wp.array(dtype=Float),
    dinv: wp.array(dtype=mat33),
    r: wp.array(dtype=vec3),
    # Out: the pre-smoothing sweep from 0, x = omega D^-1 r, and y = M x (the springs add the rest of A x)
    x_out: wp.array(dtype=vec3),
    y_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    xi = omega * (dinv[i] * r[i])
    x_out[i] = xi
    y_out[i] = mass_eff[i] * xi


@both_precisions
@wp.kernel(module="unique")
def mg_fine_post(
    n: int,
    slot: int,
    omega: Float,
    filters: wp.array(dtype=mat33),
    dinv: wp.array(dtype=mat33),
    r: wp.array(dtype=vec3),
    x: wp.array(dtype=vec3),
    y: wp.array(dtype=vec3),
    # Out: the post-smoothing sweep z = x + omega D^-1 (r - S A x), and r.z into scalars[slot]
    z_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    rz = type(omega)(0.0)
    if i < n:
        ri = r[i]
        zi = x[i] + omega * (dinv[i] * (ri - filters[i] * y[i]))
        z_out[i] = zi
        rz = wp.dot(ri, zi)
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(rz)), offset=slot)


@both_precisions
@wp.kernel(module="unique")
def mg_fine_additive(
    n: int,
    slot: int,
    omega: Float,
    shape: wp.vec3i,
    coarse_shape: wp.vec3i,
    filters: wp.array(dtype=mat33),
    dinv: wp.array(dtype=mat33),
    r: wp.array(dtype=vec3),
    e: wp.array(dtype=vec3),
    # Out: the additive lattice level z = omega D^-1 r + S P e, and r.z into scalars[slot]
    z_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    rz = type(omega)(0.0)
    if i < n:
        acc = interpolate(node_coord(i, shape), shape, coarse_shape, e)
        ri = r[i]
        zi = omega * (dinv[i] * ri) + filters[i] * acc
        z_out[i] = zi
        rz = wp.dot(ri, zi)
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(rz)), offset=slot)


@wp.kernel(module="unique")
def mg_setup_due(
    every: int,
    constrained: int,
    # In/out: [solves since the last build, hierarchy stale]; out: whether this solve builds
    state: wp.array(dtype=wp.int32),
    flag_out: wp.array(dtype=wp.int32),
):
    # One thread. A solve with contact constraints builds (its filters are new), and leaves
    # the hierarchy stale for the next free solve; free solves build every `every`-th time.
    due = constrained != 0 or state[1] != 0 or state[0] >= every
    if due:
        state[0] = 1
    else:
        state[0] = state[0] + 1
    state[1] = constrained
    flag_out[0] = wp.where(due, 1, 0)


@both_precisions
@wp.kernel(module="unique")
def mg_coarse_factor(
    shape: wp.vec3i,
    a: wp.array2d(dtype=mat33),
    rowsum: wp.array(dtype=mat33),
    # Out: the Cholesky factor L (lower triangle) of the dense coarsest matrix, in float64
    chol_out: wp.array2d(dtype=wp.float64),
):
    nodes = shape[0] * shape[1] * shape[2]
    m = 3 * nodes
    for r in range(m):
        for col in range(m):
            chol_out[r, col] = wp.float64(0.0)
    # The diagonal blocks are the row sums minus the off-diagonal blocks, summed in float64: the
    # matrix's translations keep exactly the row sums' (mass) energy, however stiff the level.
    for node in range(nodes):
        c = node_coord(node, shape)
        row_sum = rowsum[node]
        for p in range(3):
            for q in range(3):
                chol_out[3 * node + p, 3 * node + q] = chol_out[3 * node + p, 3 * node + q] + wp.float64(row_sum[p, q])
        for slot in range(STENCIL):
            o = slot_offset(slot)
            if slot != CENTER and inside(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape):
                other = node_index(c[0] + o[0], c[1] + o[1], c[2] + o[2], shape)
                block = a[slot, node]
                for p in range(3):
                    for q in range(3):
                        v = wp.float64(block[p, q])
                        chol_out[3 * node + p, 3 * other + q] = v
                        chol_out[3 * node + p, 3 * node + q] = chol_out[3 * node + p, 3 * node + q] - v
    for k in range(m):
        pivot = chol_out[k, k]
        for s in range(k):
            pivot = pivot - chol_out[k, s] * chol_out[k, s]
        # The matrix is SPD; guard rounding on a nearly singular one.
        pivot = wp.sqrt(wp.max(pivot, wp.float64(1.0e-300)))
        chol_out[k, k] = pivot
        for r in range(k + 1, m):
            v = chol_out[r, k]
            for s in range(k):
                v = v - chol_out[r, s] * chol_out[k, s]
            chol_out[r, k] = v / pivot


@wp.kernel(module="unique")
def mg_coarse_inverse(
    chol: wp.array2d(dtype=wp.float64),
    # Out: the coarsest matrix's inverse, one column per thread (L L^T x = e_col), so that each
    # V-cycle's coarsest solve is one small matrix product over parallel threads instead of two
    # triangular solves on one
    inv_out: wp.array2d(dtype=wp.float64),
):
    col = wp.tid()
    m = chol.shape[0]
    for k in range(m):
        v = wp.where(k == col, wp.float64(1.0), wp.float64(0.0))
        for s in range(k):
            v = v - chol[k, s] * inv_out[s, col]
        inv_out[k, col] = v / chol[k, k]
    for kk in range(m):
        k = m - 1 - kk
        v = inv_out[k, col]
        for s in range(k + 1, m):
            v = v - chol[s, k] * inv_out[s, col]
        inv_out[k, col] = v / chol[k, k]


@both_precisions
@wp.kernel(module="unique")
def mg_coarse_solve(
    lanes: int,
    shape: wp.vec3i,
    inv: wp.array2d(dtype=wp.float64),
    b: wp.array(dtype=vec3),
    # Out: x = A^-1 b on the coarsest level, a block of ``lanes`` threads per node, lane l taking
    # the columns l, l + lanes, ... (one thread per node on the CPU)
    x_out: wp.array(dtype=vec3),
):
    node, lane = wp.tid()
    m = 3 * shape[0] * shape[1] * shape[2]
    x = wp.vec3d(wp.float64(0.0))
    s = lane
    while s < m:
        bs = wp.float64(b[s // 3][s % 3])
        x = x + bs * wp.vec3d(inv[3 * node, s], inv[3 * node + 1, s], inv[3 * node + 2, s])
        s += lanes
    total = wp.tile_sum(wp.tile(x, preserve_type=True))
    if lane == 0:
        x = total[0]
        zero = b.dtype(0.0)[0]
        x_out[node] = x_out.dtype(type(zero)(x[0]), type(zero)(x[1]), type(zero)(x[2]))
