"""Linearised backward Euler (Baraff and Witkin 1998): spring Jacobians and a filtered PCG.

One step solves ``A dv = b`` with

    A = M - h df/dv - h^2 df/dx,   b = M (v_n - v_k) + h (f(X, V) + M g) + c_kv df/dx v_k

where (X, V) is the point the forces are linearised about and v_k the current velocity iterate
(see ``softsim_warp/core/implicit.py``). Every spring (a, b) contributes the symmetric 3x3 block
(``spring_jacobian`` of kernels/springs.py, its one definition, which the multigrid's kernels
call too)

    B_s = h kd d^d^T + h^2 S,   S = ks [d^d^T + max(0, 1 - r/|d|) (I - d^d^T)],

with d = x_a - x_b, to A's diagonal blocks (a, a) and (b, b) and -B_s to (a, b) and (b, a), since
f_a depends on x_a - x_b only and f_b = -f_a. ``df_a/dv_a = -kd d^d^T`` is the projected damper;
``df_a/dx_a = -S`` is the spring's stiffness: stretching along d^ plus the rotation of a spring
under tension. The damper also depends on x through d^ (a term proportional to the relative
velocity over |d|); it is left out, as Baraff and Witkin do, because it is not symmetric and CG
needs a symmetric matrix. Leaving out part of the Jacobian changes only the Newton direction:
extra Newton iterations still converge to the backward Euler solution.

Definiteness fix: under compression (|d| < r) the transverse factor 1 - r/|d| is negative, so S is
indefinite there and A can lose positive definiteness; the factor is clamped to >= 0, which keeps
every B_s positive semi-definite and A = M + sum_s B_s positive definite.

The matrix is never assembled for the matrix-free solver: A p = M p + sum_s (+-) B_s (p_a - p_b)
is one pass over the particles and one over the spring list with atomic adds. Taking the
difference p_a - p_b first matters in float32: with stiff springs B_s is ~1e4 times the particle
mass, and the assembled form D_a p_a - B_s p_b cancels those large terms for smooth p (rigid
motion, gravity), losing about four digits of the residual. The diagonal blocks
D_i = m_i I + sum B_s are accumulated only for the preconditioner (and the assembled solver).

Constraints (Baraff and Witkin's modified PCG): each particle has a filter S_i, a symmetric
projector onto the directions in which its dv is free: I for a free particle, 0 for a fixed one
(inverse mass 0), I - n n^T for a touching one whose velocity along the contact normal n is
prescribed. Contact friction enters as a tangential damper c (I - n n^T) on such a particle: c is
added to its mass in the product (``mass_eff``; in its free directions the filter leaves, the
damper acts as c I) and -c v_k to b. The initial guess holds the prescribed part,
(I - S_i) dv_i; residuals, preconditioned residuals and search directions are filtered, so CG
solves for the free part only, and the prescribed part enters the free rows through the springs.
The preconditioner is stored already filtered, S_i P_i S_i.

CG reductions (dot products) are tile sums over blocks of ``TILE`` threads with one atomic add per
block; the kernels that reduce are launched with ``dim=(blocks, TILE)`` and ``block_dim=TILE``.
The scalars of the iteration live in a small device array (slots below), so the loop runs without
reading anything back to the host and can be captured with ``wp.capture_while``.

Every kernel and func is written once for float32 and float64 (kernels/precision.py); the host
side is ``softsim_warp/core/implicit.py``.
"""

import warp as wp

from .contact import bowl_distance, bowl_holds, plane_distance, sphere_distance
from .mesh import mesh_distance
from .precision import Float, both_precisions, mat33, vec3
from .springs import spring_jacobian

wp.set_module_options({"enable_backward": False})

# Threads per reduction block; the launcher in softsim_warp/core/implicit.py uses the same value.
TILE = 256


def tile_blocks(count: int) -> int:
    """Blocks of TILE threads that cover ``count`` items (a tiled kernel's launch is (blocks, TILE))."""
    return (count + TILE - 1) // TILE

# Slots of the CG scalar array.
BB = 0  # b.b (filtered)
RZ = 1  # r.z of the current iterate
RR = 2  # r.r of the current iterate
PAP = 3  # p.Ap accumulator
RZ_NEW = 4  # r.z accumulator
RR_NEW = 5  # r.r accumulator
BETA = 6  # beta for the next direction update
TOL2 = 7  # (tol |b|)^2
SCALAR_SLOTS = 8

# Slots of the CG integer array: iteration count and loop condition (capture_while reads slot 1).
ITER = 0
COND = 1

# Slots of the statistics array (whole run, updated on the device).
STEP_ITERS = 0  # CG iterations of the step in progress (summed over its solves)
TOTAL_ITERS = 1
MAX_ITERS = 2  # largest per-step total
STEPS = 3
SOLVES = 4
UNCONVERGED = 5  # solves that stopped at the iteration cap or broke down above the tolerance
STAT_SLOTS = 6

# Columns of the per-body restitution array (one row per jelly, or per loose particle). Positions
# r are taken relative to a reference particle of the body (its first), which keeps float32 sums of
# m r r^T accurate far from the origin.
BODY_BUDGET = 0  # energy the contact solve removed from the free result [J]
BODY_KINETIC = 1  # kinetic energy of the free result [J]
BODY_MOMENTUM = 2  # 2..4: sum m v after the contact solve
BODY_MOMENT = 5  # 5..7: sum m r
BODY_SECOND = 8  # 8..13: sum m r r^T (xx, yy, zz, xy, xz, yz)
BODY_ANGULAR = 14  # 14..16: sum m r x v
BODY_IMPULSE = 17  # 17..19: sum of e_i (J_i.n_i) n_i, the restitution impulses of the colliding particles
BODY_TORQUE = 20  # 20..22: sum of r_i x (that)
BODY_KINETIC_AFTER = 23  # kinetic energy after the contact solve [J]
BODY_MOMENTUM_FREE = 24  # 24..26: sum m v of the free result
BODY_ANGULAR_FREE = 27  # 27..29: sum m r x v of the free result (r after the contact solve)
BODY_SLOTS = 30


@wp.func
def add_spring_product(block: mat33, p: wp.array(dtype=vec3), a: int, b: int, y: wp.array(dtype=vec3)):
    """y_a += block (p_a - p_b), y_b -= the same: one spring's share of a block product.

    Shared by the matrix-vector product (block B_s) and the df/dx v term of the right-hand side
    (block -c S). Taking p_a - p_b first keeps float32 accurate (module docstring). Returns
    (p_a - p_b).block (p_a - p_b), the spring's share of p.A p.
    """
    delta = p[a] - p[b]
    t = block * delta
    wp.atomic_add(y, a, t)
    wp.atomic_sub(y, b, t)
    return wp.dot(delta, t)


@both_precisions
@wp.kernel(module="unique")
def eval_spring_jacobians(
    h: Float,
    kv_scale: Float,
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    spring_damping: wp.array(dtype=Float),
    # Linearisation point and velocity iterate:
    particle_q: wp.array(dtype=vec3),
    particle_qd_k: wp.array(dtype=vec3),
    # Out (diag and rhs zeroed by the caller, accumulated):
    spring_block_out: wp.array(dtype=mat33),
    diag_block_out: wp.array(dtype=mat33),
    rhs_out: wp.array(dtype=vec3),
):
    tid = wp.tid()
    pair = spring_indices[tid]
    a = pair[0]
    b = pair[1]
    block, stiffness = spring_jacobian(
        particle_q[a] - particle_q[b],
        spring_rest_length[tid],
        spring_stiffness[tid],
        spring_damping[tid],
        h,
    )
    spring_block_out[tid] = block
    wp.atomic_add(diag_block_out, a, block)
    wp.atomic_add(diag_block_out, b, block)
    if kv_scale != type(h)(0.0):
        # kv_scale df/dx v: df_a/dx v = -S (v_a - v_b), and b gets the opposite.
        add_spring_product(-kv_scale * stiffness, particle_qd_k, a, b, rhs_out)


@wp.func
def diagonal_inverse(m: mat33):
    """Jacobi: the inverse of m's diagonal, as a matrix."""
    out = type(m)()
    for k in range(3):
        diagonal = m[k, k]
        if diagonal != type(diagonal)(0.0):
            out[k, k] = type(diagonal)(1.0) / diagonal
    return out


@wp.func
def invert_block(d: mat33, block_jacobi: int):
    """The preconditioner block: d^-1 (block-Jacobi) or the inverse of d's diagonal (Jacobi)."""
    if block_jacobi != 0:
        return wp.inverse(d)
    return diagonal_inverse(d)


@both_precisions
@wp.kernel(module="unique")
def build_system(
    n: int,
    h: Float,
    warm_scale: Float,
    block_jacobi: int,
    reset_filters: int,
    # Model:
    particle_mass: wp.array(dtype=Float),
    gravity: vec3,
    fixed: wp.array(dtype=wp.int32),
    # Mass plus contact friction's tangential damper (= particle_mass without contact)
    mass_eff: wp.array(dtype=Float),
    # State: v_n, the iterate v_k and the spring forces at the linearisation point
    qd_n: wp.array(dtype=vec3),
    qd_k: wp.array(dtype=vec3),
    f: wp.array(dtype=vec3),
    dv_warm: wp.array(dtype=vec3),
    # In: spring sums of the diagonal blocks and of the df/dx v term; out: D and b (filtered)
    diag_block: wp.array(dtype=mat33),
    rhs: wp.array(dtype=vec3),
    # In/out: filters (reset to free/fixed, or kept from the contact constraints)
    filters: wp.array(dtype=mat33),
    # Out: preconditioner, initial guess x0 and M x0, b.b
    precond_out: wp.array(dtype=mat33),
    x_out: wp.array(dtype=vec3),
    ax_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    bb = type(h)(0.0)
    if i < n:
        identity = wp.identity(n=3, dtype=type(h))
        constraint_filter = filters[i]
        if reset_filters != 0:
            # Fixed particles have dv = 0: nothing of them is solved for.
            constraint_filter = wp.where(fixed[i] != 0, wp.matrix(shape=(3, 3), dtype=type(h)), identity)
            filters[i] = constraint_filter
        m = particle_mass[i]
        mass_damped = mass_eff[i]
        d = m * identity + diag_block[i]
        diag_block[i] = d
        # A friction damper c (I - n n^T) (contact solve only) adds c to the diagonal and
        # -c v_k to b; in the free directions (I - n n^T) the filter keeps, it acts as c I.
        b = constraint_filter * (
            m * (qd_n[i] - qd_k[i]) + h * (f[i] + m * gravity) + rhs[i] - (mass_damped - m) * qd_k[i]
        )
        rhs[i] = b
        precond_block = wp.matrix(shape=(3, 3), dtype=type(h))
        if fixed[i] == 0:
            precond_block = invert_block(d + (mass_damped - m) * identity, block_jacobi)
        precond_out[i] = constraint_filter * precond_block * constraint_filter
        # Initial guess: the last step's dv minus its gravity part, plus this step's h g.
        # Springs do not resist a uniform velocity change (A (h g) = M h g), so the guess is
        # exact for free fall, and the first step needs no special case. Prescribed parts
        # of dv are 0: the iterate already satisfies the constraints.
        x0 = constraint_filter * (warm_scale * (dv_warm[i] + h * gravity))
        x_out[i] = x0
        ax_out[i] = mass_damped * x0
        bb = wp.dot(b, b)
    total = wp.tile_sum(wp.tile(bb))
    wp.tile_atomic_add(scalars_out, total, offset=BB)


@wp.func
def differs(a: vec3, b: vec3):
    return a[0] != b[0] or a[1] != b[1] or a[2] != b[2]


@wp.func
def touch_planes(
    w: int,
    xf: vec3,
    touching: int,
    normal: vec3,
    depth: Float,
    plane_first: wp.array(dtype=wp.int32),
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    plane_hole_radius: wp.array(dtype=Float),
    eps: Float,
):
    """(count, normal, distance) of the planes of world w that the free result xf touches, added
    to the arguments (normal and distance: the last one touched).

    World w's planes are plane_first[w] .. plane_first[w + 1] - 1 (sorted by world), as in
    contact.contact_planes.
    """
    for p in range(plane_first[w], plane_first[w + 1]):
        nrm = plane_normal[p]
        phi = plane_distance(xf, plane_point[p], nrm, plane_hole_center[p], plane_hole_radius[p])
        if phi < eps:
            touching = touching + 1
            normal = nrm
            depth = phi
    return touching, normal, depth


@wp.func
def touch_round(
    w: int,
    xf: vec3,
    xp: vec3,
    touching: int,
    normal: vec3,
    depth: Float,
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    eps: Float,
):
    """The same for bowls and spheres; a bowl holds only what began inside it (contact.bowl_holds, as collide_bowls)."""
    for b in range(bowl_first[w], bowl_first[w + 1]):
        c = bowl_center[b]
        radius = bowl_radius[b]
        holds, _n_prev = bowl_holds(xp, c, radius, eps)
        if holds:
            phi, nrm = bowl_distance(xf, c, radius, bowl_cut_height[b])
            if phi < eps:
                touching = touching + 1
                normal = nrm
                depth = phi
    for s in range(sphere_first[w], sphere_first[w + 1]):
        phi, nrm = sphere_distance(xf, sphere_center[s], sphere_radius[s])
        if phi < eps:
            touching = touching + 1
            normal = nrm
            depth = phi
    return touching, normal, depth


@wp.func
def touch_meshes(
    w: int,
    xf: vec3,
    touching: int,
    normal: vec3,
    depth: Float,
    mesh_first: wp.array(dtype=wp.int32),
    mesh_id: wp.array(dtype=wp.uint64),
    mesh_closed: wp.array(dtype=wp.int32),
    mesh_reach: wp.array(dtype=Float),
    mesh_tri_start: wp.array(dtype=wp.int32),
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
    eps: Float,
):
    """The same for triangle-mesh terrain (as collide_meshes, kernels/mesh.py)."""
    for m in range(mesh_first[w], mesh_first[w + 1]):
        phi, nrm = mesh_distance(
            xf, mesh_id[m], mesh_closed[m], mesh_reach[m], mesh_tri_start[m], mesh_tris, mesh_points
        )
        if phi < eps:
            touching = touching + 1
            normal = nrm
            depth = phi
    return touching, normal, depth


@both_precisions
@wp.kernel(module="unique")
def constrain_contacts(
    h: Float,
    # Model:
    particle_world: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=Float),
    fixed: wp.array(dtype=wp.int32),
    plane_first: wp.array(dtype=wp.int32),
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    plane_hole_radius: wp.array(dtype=Float),
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    mesh_first: wp.array(dtype=wp.int32),
    mesh_id: wp.array(dtype=wp.uint64),
    mesh_closed: wp.array(dtype=wp.int32),
    mesh_reach: wp.array(dtype=Float),
    mesh_tri_start: wp.array(dtype=wp.int32),
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
    contact_epsilon: Float,
    eps_v: Float,
    # The step's start, and its result before and after the contact response:
    q_n: wp.array(dtype=vec3),
    qd_n: wp.array(dtype=vec3),
    q_free: wp.array(dtype=vec3),
    qd_free: wp.array(dtype=vec3),
    q_contact: wp.array(dtype=vec3),
    qd_contact: wp.array(dtype=vec3),
    # Out: filters, the constrained iterate (x_n + h v, v), whether anything touched, and per
    # colliding particle its restitution and approach momentum along the normal, m (-v_n) n
    filters_out: wp.array(dtype=mat33),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
    any_contact_out: wp.array(dtype=wp.int32),
    restitution_out: wp.array(dtype=Float),
    approach_out: wp.array(dtype=vec3),
    mass_eff_out: wp.array(dtype=Float),
):
    i = wp.tid()
    identity = wp.identity(n=3, dtype=type(h))
    v = qd_free[i]
    constraint_filter = identity
    e = type(h)(0.0)
    approach = wp.vector(length=3, dtype=type(h))
    m = particle_mass[i]
    damper = type(h)(0.0)
    if fixed[i] != 0:
        constraint_filter = wp.matrix(shape=(3, 3), dtype=type(h))
    elif differs(q_contact[i], q_free[i]) or differs(qd_contact[i], v):
        any_contact_out[0] = 1
        v_c = qd_contact[i]
        # The surface the particle touches (as the response saw it); more than one, or a contact
        # hook's primitive, gives no single normal.
        w = particle_world[i]
        xf = q_free[i]
        touching, nrm, depth = touch_planes(
            w,
            xf,
            0,
            wp.vector(length=3, dtype=type(h)),
            type(h)(0.0),
            plane_first,
            plane_point,
            plane_normal,
            plane_hole_center,
            plane_hole_radius,
            contact_epsilon,
        )
        touching, nrm, depth = touch_round(
            w,
            xf,
            q_n[i],
            touching,
            nrm,
            depth,
            bowl_first,
            bowl_center,
            bowl_radius,
            bowl_cut_height,
            sphere_first,
            sphere_center,
            sphere_radius,
            contact_epsilon,
        )
        touching, nrm, depth = touch_meshes(
            w, xf, touching, nrm, depth, mesh_first, mesh_id, mesh_closed, mesh_reach, mesh_tri_start, mesh_tris,
            mesh_points, contact_epsilon,
        )
        one_surface = touching == 1
        if touching != 1:
            # No single surface (several, or a contact hook's primitive): the direction in
            # which the response pushed the particle serves as the normal. Prescribing the
            # response's whole velocity instead (a reflected one included) makes a single
            # particle a velocity source for the stiff lattice: +89 J in one step of seed_bowl.
            pushed = v_c - v
            nrm = wp.vector(length=3, dtype=type(h))
            if wp.length_sq(pushed) > type(h)(0.0):
                nrm = wp.normalize(pushed)
                touching = 1
        # A position correction alone leaves the particle free.
        target = v
        if touching == 1:
            # One surface: only the normal velocity is prescribed, the tangential one is left
            # to the solve. An approaching particle is stopped (the compression phase of an
            # impact); a normal velocity of 0 takes no work from the constraint impulse, so
            # the step stays dissipative (docs/IMPLICIT.md). Prescribing whole velocities
            # instead (the response's tangential ones) forces the springs between particles
            # whose normals differ (a bowl) to follow incompatible velocities: up to 1e4 J
            # per step at ks = 1e5 in seed_bowl.
            vn = wp.dot(v, nrm)
            vt = v - vn * nrm
            vt_c = v_c - wp.dot(v_c, nrm) * nrm
            constraint_filter = identity - wp.outer(nrm, nrm)
            target = v
            if vn < type(h)(0.0):
                # Stopped: where the step began, or, for a particle at rest (slower than
                # contact_velocity_epsilon at the step's start) on a single surface, on the
                # surface: x = x_n + h v with v.n = -phi(x_n) / h (phi(x_n) = phi(xf) - h v.n,
                # exact for a plane), never faster than it came. Stopping a resting particle
                # where it began leaves it up to g h^2 above the ground for good (1 mm at
                # dt = 0.01). A moving one is not landed: prescribing it while its neighbours
                # are stopped where they began strains a stiff lattice (+1.4 J in a frame of
                # jelly_drop at ks = 1e5). The constraint impulse opposes the motion either way.
                land = type(h)(0.0)
                if one_surface and wp.dot(v_c, nrm) <= type(h)(0.0) and wp.length(qd_n[i]) < eps_v:
                    land = wp.min(wp.max(depth - h * vn, type(h)(0.0)) / h, -vn)
                target = vt - land * nrm
            if vn < type(h)(0.0) and wp.dot(v_c, nrm) > type(h)(0.0):
                # A collision (the response reflected the approach). Its restitution is applied
                # to the whole body after the solve (apply_restitution), not as a reflected
                # velocity of this one particle. The coefficient the response used
                # (v_c.n = -e v.n), so that whatever rule resolve_contact applies (resting
                # contact, thresholds) carries over. The impact's friction is not carried
                # into the solve.
                e = wp.clamp(wp.dot(v_c, nrm) / (-vn), type(h)(0.0), type(h)(1.0))
                approach = (m * (-vn)) * nrm
            elif differs(vt, vt_c):
                # Friction acted (resting contact). It enters the solve as a tangential
                # damper on the particle, c (I - n n^T) with c = m (1 - r) / r, r = |vt_c| / |vt|:
                # alone it would scale vt by r, as the response did; in the solve it is a
                # positive semi-definite term, so it only removes energy. r = 0 (sticking) is
                # taken as 1e-3.
                speed = wp.length(vt)
                ratio = wp.max(wp.length(vt_c) / wp.max(speed, type(h)(1.0e-30)), type(h)(1.0e-3))
                damper = m * (type(h)(1.0) - ratio) / ratio
        v = constraint_filter * v + (identity - constraint_filter) * target
    filters_out[i] = constraint_filter
    qd_out[i] = v
    q_out[i] = q_n[i] + h * v
    restitution_out[i] = e
    approach_out[i] = approach
    mass_eff_out[i] = m + damper


@wp.func
def add_vec(body_out: wp.array2d(dtype=Float), b: int, slot: int, v: vec3):
    for k in range(3):
        wp.atomic_add(body_out, b, slot + k, v[k])


@wp.func
def get_vec(body: wp.array2d(dtype=Float), b: int, slot: int):
    return wp.vector(body[b, slot], body[b, slot + 1], body[b, slot + 2])


@both_precisions
@wp.kernel(module="unique")
def measure_particle_restitution(
    h: Float,
    # Model:
    particle_body: wp.array(dtype=wp.int32),
    body_reference: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=Float),
    fixed: wp.array(dtype=wp.int32),
    gravity: vec3,
    # State: start of the step, the free result, and the constrained result with its forces
    qd_n: wp.array(dtype=vec3),
    q_free: wp.array(dtype=vec3),
    qd_free: wp.array(dtype=vec3),
    q: wp.array(dtype=vec3),
    qd: wp.array(dtype=vec3),
    f: wp.array(dtype=vec3),
    # Colliding particles (constrain_contacts):
    restitution: wp.array(dtype=Float),
    approach: wp.array(dtype=vec3),
    # Out, per body (zeroed by the caller): the BODY_* sums
    body_out: wp.array2d(dtype=Float),
):
    i = wp.tid()
    if fixed[i] != 0:
        return
    b = particle_body[i]
    m = particle_mass[i]
    x = q[i]
    v = qd[i]
    vf = qd_free[i]
    # Kinetic and gravity energy the contact solve removed from the free result.
    energy_removed = type(h)(0.5) * m * (wp.dot(vf, vf) - wp.dot(v, v)) - m * wp.dot(gravity, q_free[i] - x)
    wp.atomic_add(body_out, b, BODY_BUDGET, energy_removed)
    wp.atomic_add(body_out, b, BODY_KINETIC, type(h)(0.5) * m * wp.dot(vf, vf))
    r = x - q[body_reference[b]]
    add_vec(body_out, b, BODY_MOMENTUM, m * v)
    add_vec(body_out, b, BODY_MOMENT, m * r)
    add_vec(body_out, b, BODY_SECOND, type(r)(m * r[0] * r[0], m * r[1] * r[1], m * r[2] * r[2]))
    add_vec(body_out, b, BODY_SECOND + 3, type(r)(m * r[0] * r[1], m * r[0] * r[2], m * r[1] * r[2]))
    add_vec(body_out, b, BODY_ANGULAR, m * wp.cross(r, v))
    wp.atomic_add(body_out, b, BODY_KINETIC_AFTER, type(h)(0.5) * m * wp.dot(v, v))
    add_vec(body_out, b, BODY_MOMENTUM_FREE, m * vf)
    add_vec(body_out, b, BODY_ANGULAR_FREE, m * wp.cross(r, vf))
    a = approach[i]
    if wp.length_sq(a) > type(h)(0.0):
        # The contact impulse on the particle over the step: what backward Euler's equation
        # m (v - v_n) = h (f(x, v) + m g) leaves unexplained; its normal part, times e.
        nrm = wp.normalize(a)
        impulse = m * (v - qd_n[i]) - h * (f[i] + m * gravity)
        particle_impulse = (restitution[i] * wp.max(wp.dot(impulse, nrm), type(h)(0.0))) * nrm
        add_vec(body_out, b, BODY_IMPULSE, particle_impulse)
        add_vec(body_out, b, BODY_TORQUE, wp.cross(r, particle_impulse))


@both_precisions
@wp.kernel(module="unique")
def measure_spring_restitution(
    # Model:
    particle_body: wp.array(dtype=wp.int32),
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    # The free and the constrained result:
    q_free: wp.array(dtype=vec3),
    q: wp.array(dtype=vec3),
    # Out, per body: the spring energy the contact solve removed, added to the budget
    body_out: wp.array2d(dtype=Float),
):
    tid = wp.tid()
    pair = spring_indices[tid]
    a = pair[0]
    b = pair[1]
    rest = spring_rest_length[tid]
    stretch_free = wp.length(q_free[a] - q_free[b]) - rest
    stretch = wp.length(q[a] - q[b]) - rest
    energy_removed = type(rest)(0.5) * spring_stiffness[tid] * (stretch_free * stretch_free - stretch * stretch)
    wp.atomic_add(body_out, particle_body[a], BODY_BUDGET, energy_removed)


@both_precisions
@wp.kernel(module="unique")
def check_energy_budget(
    tol: Float,
    body: wp.array2d(dtype=Float),
    gained_out: wp.array(dtype=wp.int32),
):
    # One thread per body: flag a contact solve that ended above the free result's energy by more
    # than the CG tolerance's share of the kinetic energy (CG's error is relative to |b| ~ M v).
    b = wp.tid()
    if body[b, BODY_BUDGET] < -tol * body[b, BODY_KINETIC]:
        gained_out[0] = 1


@both_precisions
@wp.kernel(module="unique")
def apply_restitution(
    particle_body: wp.array(dtype=wp.int32),
    body_reference: wp.array(dtype=wp.int32),
    fixed: wp.array(dtype=wp.int32),
    body_mass: wp.array(dtype=Float),
    body: wp.array2d(dtype=Float),
    q: wp.array(dtype=vec3),
    # In/out: the body's velocities gain one rigid velocity field
    qd: wp.array(dtype=vec3),
):
    i = wp.tid()
    if fixed[i] != 0:
        return
    b = particle_body[i]
    restitution_impulse = get_vec(body, b, BODY_IMPULSE)
    if wp.length_sq(restitution_impulse) == body_mass.dtype(0.0):
        return
    mass = body_mass[b]
    if mass == type(mass)(0.0):
        return
    identity = wp.identity(n=3, dtype=type(mass))
    c = get_vec(body, b, BODY_MOMENT) / mass  # centre of mass, relative to the reference
    second_diagonal = get_vec(body, b, BODY_SECOND)
    second_off_diagonal = get_vec(body, b, BODY_SECOND + 3)
    second = type(identity)(
        second_diagonal[0], second_off_diagonal[0], second_off_diagonal[1],
        second_off_diagonal[0], second_diagonal[1], second_off_diagonal[2],
        second_off_diagonal[1], second_off_diagonal[2], second_diagonal[2],
    )
    second = second - mass * wp.outer(c, c)  # about the centre of mass
    inertia = wp.trace(second) * identity - second
    momentum = get_vec(body, b, BODY_MOMENTUM)
    angular = get_vec(body, b, BODY_ANGULAR) - wp.cross(c, momentum)
    torque = get_vec(body, b, BODY_TORQUE) - wp.cross(c, restitution_impulse)
    # Poisson's restitution for the body as a rigid whole: the impulses e_i J_i at the contact
    # points change its velocity by dV = sum / M and its angular velocity by I^-1 torque. A rigid
    # field strains no spring. (A body with a singular inertia, a single particle or a line of
    # them, gets the linear part only.)
    dv = restitution_impulse / mass
    dw = type(restitution_impulse)(type(mass)(0.0))
    inv_inertia = type(identity)(type(mass)(0.0))
    inertia_trace = wp.trace(inertia)
    if wp.determinant(inertia) > type(mass)(1.0e-9) * inertia_trace * inertia_trace * inertia_trace:
        inv_inertia = wp.inverse(inertia)
        dw = inv_inertia * torque
    # Poisson's law is a rigid-body law: it applies to the part of the impact the body took
    # as a rigid body. The part it took by deforming (the deformation kinetic energy the
    # contact solve created, against the kinetic energy it removed) comes back, or not,
    # through its springs; a restitution kick on top of that makes the contact chatter: the
    # kicked particles are pushed back into the ground by the springs and collide again
    # (a soft jelly lost 45 % of its rebound speed that way at dt = 4e-4).
    momentum_free = get_vec(body, b, BODY_MOMENTUM_FREE)
    angular_free = get_vec(body, b, BODY_ANGULAR_FREE) - wp.cross(c, momentum_free)
    kinetic_free = body[b, BODY_KINETIC]
    kinetic_after = body[b, BODY_KINETIC_AFTER]
    rigid_free = type(mass)(0.5) * (
        wp.dot(momentum_free, momentum_free) / mass + wp.dot(angular_free, inv_inertia * angular_free)
    )
    rigid_after = type(mass)(0.5) * (wp.dot(momentum, momentum) / mass + wp.dot(angular, inv_inertia * angular))
    deformation = (kinetic_after - rigid_after) - (kinetic_free - rigid_free)
    removed = kinetic_free - kinetic_after
    rigid_share = type(mass)(0.0)
    if removed > type(mass)(0.0):
        rigid_share = wp.clamp(type(mass)(1.0) - deformation / removed, type(mass)(0.0), type(mass)(1.0))
    dv = rigid_share * dv
    dw = rigid_share * dw
    # The field s (dV + dw x r) changes the kinetic energy by exactly s lin + s^2 quad, with
    # lin = P.dV + L.dw and quad = (M |dV|^2 + dw.I dw) / 2. s <= 1 is capped so that this is at
    # most the energy the contact solve removed from the free result (the budget), so the step
    # never ends above the free result's energy, which backward Euler keeps below E_n.
    lin = wp.dot(momentum, dv) + wp.dot(angular, dw)
    quad = type(mass)(0.5) * (mass * wp.dot(dv, dv) + wp.dot(dw, inertia * dw))
    budget = wp.max(body[b, BODY_BUDGET], type(mass)(0.0))
    s = type(mass)(1.0)
    if quad > type(mass)(0.0):
        s_max = (wp.sqrt(lin * lin + type(mass)(4.0) * quad * budget) - lin) / (type(mass)(2.0) * quad)
        s = wp.clamp(s_max, type(mass)(0.0), type(mass)(1.0))
    r = q[i] - q[body_reference[b]] - c
    qd[i] = qd[i] + s * (dv + wp.cross(dw, r))


@both_precisions
@wp.kernel(module="unique")
def constrain_last_system(
    n: int,
    block_jacobi: int,
    particle_mass: wp.array(dtype=Float),
    mass_eff: wp.array(dtype=Float),
    fixed: wp.array(dtype=wp.int32),
    filters: wp.array(dtype=mat33),
    diag_block: wp.array(dtype=mat33),
    # The last solve's result and the constrained iterate (constrain_contacts):
    qd_free: wp.array(dtype=vec3),
    qd_iter: wp.array(dtype=vec3),
    # In/out: the last solve's dv becomes the initial guess holding the prescribed parts;
    # b gains the friction dampers' -c v_k, and the preconditioner their c (filtered)
    x: wp.array(dtype=vec3),
    rhs: wp.array(dtype=vec3),
    precond: wp.array(dtype=mat33),
    # Out: the iterate the last system is relative to, M x0, b.b of the free part
    qd_k_out: wp.array(dtype=vec3),
    ax_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    bb = scalars_out.dtype(0.0)
    if i < n:
        constraint_filter = filters[i]
        dv = x[i]
        v_free = qd_free[i]
        v_k = v_free - dv
        qd_k_out[i] = v_k
        # The prescribed velocity differs from the solve's only in constrained directions.
        x0 = dv + (qd_iter[i] - v_free)
        x[i] = x0
        damper = mass_eff[i] - particle_mass[i]
        precond_block = wp.matrix(shape=(3, 3), dtype=scalars_out.dtype)
        if fixed[i] == 0:
            identity = wp.identity(n=3, dtype=scalars_out.dtype)
            precond_block = invert_block(diag_block[i] + damper * identity, block_jacobi)
        precond[i] = constraint_filter * precond_block * constraint_filter
        ax_out[i] = mass_eff[i] * x0
        b = constraint_filter * (rhs[i] - damper * v_k)
        rhs[i] = b
        bb = wp.dot(b, b)
    total = wp.tile_sum(wp.tile(bb))
    wp.tile_atomic_add(scalars_out, total, offset=BB)


@both_precisions
@wp.kernel(module="unique")
def spring_mv(
    count: int,
    slot: int,
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    # System:
    spring_block: wp.array(dtype=mat33),
    p: wp.array(dtype=vec3),
    # Out: y += (spring part of A) p, accumulated; scalars[slot] += p.(spring part of A) p
    y_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    tid = tile_index * TILE + lane
    quad = scalars_out.dtype(0.0)
    if tid < count:
        pair = spring_indices[tid]
        # Rows of constrained directions get values too; the filter drops them.
        quad = add_spring_product(spring_block[tid], p, pair[0], pair[1], y_out)
    if slot >= 0:
        total = wp.tile_sum(wp.tile(quad))
        wp.tile_atomic_add(scalars_out, total, offset=slot)


@both_precisions
@wp.kernel(module="unique")
def init_residual(
    n: int,
    filters: wp.array(dtype=mat33),
    rhs: wp.array(dtype=vec3),
    precond: wp.array(dtype=mat33),
    ax: wp.array(dtype=vec3),
    # Out:
    r_out: wp.array(dtype=vec3),
    z_out: wp.array(dtype=vec3),
    p_out: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    rz = scalars_out.dtype(0.0)
    rr = scalars_out.dtype(0.0)
    if i < n:
        r = filters[i] * (rhs[i] - ax[i])
        z = precond[i] * r
        r_out[i] = r
        z_out[i] = z
        # The first direction update is p = z + 0 p; p must be finite for that.
        p_out[i] = z
        rz = wp.dot(r, z)
        rr = wp.dot(r, r)
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(rz)), offset=RZ_NEW)
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(rr)), offset=RR_NEW)


@both_precisions
@wp.kernel(module="unique")
def cg_begin(
    tol: Float,
    max_iterations: int,
    step_bb: wp.array(dtype=Float),
    scalars: wp.array(dtype=Float),
    ints: wp.array(dtype=wp.int32),
):
    # One thread: tolerance, first r.z and r.r, and the loop condition. The tolerance is
    # relative to the larger of |b| and the step's first |b| (set_step_scale): a later solve of
    # the step (a Newton correction, the contact solve) only refines the first one's dv, and
    # needs its absolute accuracy, not a relative one on its own, smaller right-hand side.
    tol2 = tol * tol * wp.max(scalars[BB], step_bb[0])
    scalars[TOL2] = tol2
    scalars[RZ] = scalars[RZ_NEW]
    scalars[RR] = scalars[RR_NEW]
    scalars[RZ_NEW] = type(tol)(0.0)
    scalars[RR_NEW] = type(tol)(0.0)
    scalars[PAP] = type(tol)(0.0)
    scalars[BETA] = type(tol)(0.0)
    ints[ITER] = 0
    ints[COND] = wp.where(scalars[RR] > tol2 and max_iterations > 0, 1, 0)


@both_precisions
@wp.kernel(module="unique")
def set_step_scale(scalars: wp.array(dtype=Float), step_bb: wp.array(dtype=Float)):
    # One thread: the first solve's b.b sets the step's scale for the tolerance.
    step_bb[0] = scalars[BB]


@both_precisions
@wp.kernel(module="unique")
def cg_direction(
    n: int,
    mass_part: int,
    particle_mass: wp.array(dtype=Float),
    z: wp.array(dtype=vec3),
    # In/out: direction p <- z + beta p; out (if mass_part): M p, the start of A p (p.A p is
    # summed per particle once the springs have added theirs: dot_accumulate)
    p: wp.array(dtype=vec3),
    ap_out: wp.array(dtype=vec3),
    scalars: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    if i < n:
        # z and p are filtered, so p stays filtered.
        pi = z[i] + scalars[BETA] * p[i]
        p[i] = pi
        if mass_part != 0:
            ap_out[i] = particle_mass[i] * pi


@both_precisions
@wp.kernel(module="unique")
def dot_accumulate(
    n: int,
    slot: int,
    a: wp.array(dtype=vec3),
    b: wp.array(dtype=vec3),
    scalars_out: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    v = scalars_out.dtype(0.0)
    if i < n:
        v = wp.dot(a[i], b[i])
    wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(v)), offset=slot)


@both_precisions
@wp.kernel(module="unique")
def cg_update(
    n: int,
    use_precond: int,
    filters: wp.array(dtype=mat33),
    precond: wp.array(dtype=mat33),
    p: wp.array(dtype=vec3),
    ap: wp.array(dtype=vec3),
    # In/out: solution and residual; out: preconditioned residual, r.z and r.r accumulators
    x: wp.array(dtype=vec3),
    r: wp.array(dtype=vec3),
    z_out: wp.array(dtype=vec3),
    scalars: wp.array(dtype=Float),
):
    tile_index, lane = wp.tid()
    i = tile_index * TILE + lane
    rz = scalars.dtype(0.0)
    rr = scalars.dtype(0.0)
    if i < n:
        pap = scalars[PAP]
        # p.Ap <= 0 only when p = 0 (A is positive definite): take no step then.
        alpha = wp.where(pap > scalars.dtype(0.0), scalars[RZ] / pap, scalars.dtype(0.0))
        x[i] = x[i] + alpha * p[i]
        ri = r[i] - alpha * (filters[i] * ap[i])
        r[i] = ri
        if use_precond != 0:
            # (Without: a preconditioner applied after this kernel, multigrid's V-cycle, writes z
            # and r.z; reading P and writing z here would add a quarter to the kernel's traffic.)
            zi = precond[i] * ri
            z_out[i] = zi
            rz = wp.dot(ri, zi)
        rr = wp.dot(ri, ri)
    wp.tile_atomic_add(scalars, wp.tile_sum(wp.tile(rz)), offset=RZ_NEW)
    wp.tile_atomic_add(scalars, wp.tile_sum(wp.tile(rr)), offset=RR_NEW)


@both_precisions
@wp.kernel(module="unique")
def cg_end_iteration(
    max_iterations: int,
    scalars: wp.array(dtype=Float),
    ints: wp.array(dtype=wp.int32),
):
    # One thread: beta, the new r.z and r.r, fresh accumulators and the loop condition.
    rz_old = scalars[RZ]
    rz_new = scalars[RZ_NEW]
    pap = scalars[PAP]
    scalars[BETA] = wp.where(rz_old > scalars.dtype(0.0), rz_new / rz_old, scalars.dtype(0.0))
    scalars[RZ] = rz_new
    scalars[RR] = scalars[RR_NEW]
    scalars[RZ_NEW] = scalars.dtype(0.0)
    scalars[RR_NEW] = scalars.dtype(0.0)
    scalars[PAP] = scalars.dtype(0.0)
    it = ints[ITER] + 1
    ints[ITER] = it
    going = scalars[RR] > scalars[TOL2] and it < max_iterations and pap > scalars.dtype(0.0)
    ints[COND] = wp.where(going, 1, 0)


@both_precisions
@wp.kernel(module="unique")
def record_solve(
    iterations: wp.array(dtype=wp.int32),
    residual_sq: wp.array(dtype=Float),
    tolerance_sq: wp.array(dtype=Float),
    stats: wp.array(dtype=wp.int32),
):
    # One thread: add a solve's iteration count to the step's total; count unconverged solves.
    stats[STEP_ITERS] = stats[STEP_ITERS] + iterations[0]
    stats[SOLVES] = stats[SOLVES] + 1
    if residual_sq[0] > tolerance_sq[0]:
        stats[UNCONVERGED] = stats[UNCONVERGED] + 1


@both_precisions
@wp.kernel(module="unique")
def record_residual(
    tol: Float,
    residual_sq: wp.array(dtype=Float),
    tolerance_sq: wp.array(dtype=Float),
    # In/out: [largest, sum] of the solves' final relative residuals |r| / max(|b|, |b_1|)
    residual_stats: wp.array(dtype=Float),
):
    # One thread. tolerance_sq = tol^2 max(|b|^2, |b_1|^2), so the scale is tolerance_sq / tol^2.
    rel = type(tol)(0.0)
    if tolerance_sq[0] > type(tol)(0.0):
        rel = tol * wp.sqrt(residual_sq[0] / tolerance_sq[0])
    residual_stats[0] = wp.max(residual_stats[0], rel)
    residual_stats[1] = residual_stats[1] + rel


@wp.kernel(module="unique")
def record_step(stats: wp.array(dtype=wp.int32)):
    # One thread: close the step's CG iteration count.
    it = stats[STEP_ITERS]
    stats[TOTAL_ITERS] = stats[TOTAL_ITERS] + it
    stats[MAX_ITERS] = wp.max(stats[MAX_ITERS], it)
    stats[STEPS] = stats[STEPS] + 1
    stats[STEP_ITERS] = 0


@both_precisions
@wp.kernel(module="unique")
def apply_velocity_update(
    h: Float,
    dv_scale: Float,
    save_warm: int,
    fixed: wp.array(dtype=wp.int32),
    gravity: vec3,
    q_n: wp.array(dtype=vec3),
    qd_k: wp.array(dtype=vec3),
    dv: wp.array(dtype=vec3),
    # Out: v_{k+1} = v_k + dv_scale dv, x = x_n + h v_{k+1}, and the warm start of the next step
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
    dv_warm_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    v = qd_k[i] + dv_scale * dv[i]
    qd_out[i] = v
    q_out[i] = q_n[i] + h * v
    if save_warm != 0:
        # Without its gravity part, so the guess stays right when the step size changes.
        dv_warm_out[i] = dv[i] - wp.where(fixed[i] != 0, type(h)(0.0), h) * gravity


@both_precisions
@wp.kernel(module="unique")
def precondition(
    precond: wp.array(dtype=mat33),
    x: wp.array(dtype=vec3),
    y: wp.array(dtype=vec3),
    alpha: Float,
    beta: Float,
    z_out: wp.array(dtype=vec3),
):
    # z = alpha P x + beta y, the LinearOperator form that warp.optim.linear expects.
    i = wp.tid()
    z_out[i] = alpha * (precond[i] * x[i]) + beta * y[i]


@both_precisions
@wp.kernel(module="unique")
def assemble_bsr_diagonal(
    fixed: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=Float),
    mass_eff: wp.array(dtype=Float),
    diag_block: wp.array(dtype=mat33),
    diag_index: wp.array(dtype=wp.int32),
    values_out: wp.array(dtype=mat33),
):
    i = wp.tid()
    identity = wp.identity(n=3, dtype=particle_mass.dtype)
    # A fixed particle's row and column are eliminated: an identity block (and rhs 0) keeps
    # the assembled matrix nonsingular for solvers that do not filter. The friction damper
    # enters as c I: the filter keeps only its tangential part, as in the matrix-free product.
    d = diag_block[i] + (mass_eff[i] - particle_mass[i]) * identity
    values_out[diag_index[i]] = wp.where(fixed[i] != 0, identity, d)


@both_precisions
@wp.kernel(module="unique")
def assemble_bsr_offdiagonal(
    spring_indices: wp.array(dtype=wp.vec2i),
    fixed: wp.array(dtype=wp.int32),
    spring_block: wp.array(dtype=mat33),
    index_ab: wp.array(dtype=wp.int32),
    index_ba: wp.array(dtype=wp.int32),
    # Out: off-diagonal blocks (zeroed by the caller; two springs may join the same pair)
    values_out: wp.array(dtype=mat33),
):
    tid = wp.tid()
    pair = spring_indices[tid]
    if fixed[pair[0]] != 0 or fixed[pair[1]] != 0:
        return
    m = spring_block[tid]
    wp.atomic_sub(values_out, index_ab[tid], m)
    wp.atomic_sub(values_out, index_ba[tid], m)
