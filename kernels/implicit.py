"""Linearised backward Euler (Baraff and Witkin 1998): spring Jacobians and a filtered PCG.

One step solves ``A dv = b`` with

    A = M - h df/dv - h^2 df/dx,   b = M (v_n - v_k) + h (f(X, V) + M g) + c_kv df/dx v_k

where (X, V) is the point the forces are linearised about and v_k the current velocity iterate
(see ``softsim_warp/implicit.py``). Every spring (a, b) contributes the symmetric 3x3 block

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
(inverse mass 0) or one whose velocity the contact response decided, I - n n^T for one whose
velocity along the contact normal n is prescribed. The initial guess holds the prescribed part,
(I - S_i) dv_i; residuals, preconditioned residuals and search directions are filtered, so CG
solves for the free part only, and the prescribed part enters the free rows through the springs.
The preconditioner is stored already filtered, S_i P_i S_i.

CG reductions (dot products) are tile sums over blocks of ``TILE`` threads with one atomic add per
block; the kernels that reduce are launched with ``dim=(blocks, TILE)`` and ``block_dim=TILE``.
The scalars of the iteration live in a small device array (slots below), so the loop runs without
reading anything back to the host and can be captured with ``wp.capture_while``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Threads per reduction block; the launcher in softsim_warp/implicit.py uses the same value.
TILE = 256

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


def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    mat33 = wp.types.matrix((3, 3), scalar)

    @wp.func
    def spring_jacobian(d: vec3, rest: scalar, ks: scalar, kd: scalar, h: scalar):
        """(B, S) of one spring: B = h kd d^d^T + h^2 S, S = ks [d^d^T + max(0, 1 - r/|d|)(I - d^d^T)].

        -S is df_a/dx_a and -kd d^d^T is df_a/dv_a. Coincident particles (|d| = 0) have no
        direction, and the force there is defined as zero (``spring_force``); both blocks are
        zero then, which avoids 0/0 = NaN.
        """
        length = wp.length(d)
        zero = mat33(scalar(0.0))
        if length == scalar(0.0):
            return zero, zero
        dhat = d / length
        along = wp.outer(dhat, dhat)
        # Definiteness fix: clamp the transverse factor to >= 0 (it is negative under compression).
        transverse = wp.max(scalar(1.0) - rest / length, scalar(0.0))
        identity = wp.identity(n=3, dtype=scalar)
        s = ks * (along + transverse * (identity - along))
        b = (h * kd) * along + (h * h) * s
        return b, s

    @wp.kernel(module="unique")
    def eval_spring_jacobians(
        h: scalar,
        kv_scale: scalar,
        # Model:
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        spring_damping: wp.array(dtype=scalar),
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
        blk, s = spring_jacobian(
            particle_q[a] - particle_q[b],
            spring_rest_length[tid],
            spring_stiffness[tid],
            spring_damping[tid],
            h,
        )
        spring_block_out[tid] = blk
        wp.atomic_add(diag_block_out, a, blk)
        wp.atomic_add(diag_block_out, b, blk)
        if kv_scale != scalar(0.0):
            # kv_scale df/dx v: df_a/dx v = -S (v_a - v_b), and b gets the opposite.
            t = kv_scale * (s * (particle_qd_k[a] - particle_qd_k[b]))
            wp.atomic_sub(rhs_out, a, t)
            wp.atomic_add(rhs_out, b, t)

    @wp.func
    def diagonal_inverse(m: mat33):
        """Jacobi: the inverse of m's diagonal, as a matrix."""
        out = mat33(scalar(0.0))
        for k in range(3):
            if m[k, k] != scalar(0.0):
                out[k, k] = scalar(1.0) / m[k, k]
        return out

    @wp.kernel(module="unique")
    def build_system(
        n: int,
        h: scalar,
        warm_scale: scalar,
        block_jacobi: int,
        reset_filters: int,
        # Model:
        particle_mass: wp.array(dtype=scalar),
        gravity: vec3,
        fixed: wp.array(dtype=wp.int32),
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
        scalars_out: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        bb = scalar(0.0)
        if i < n:
            identity = wp.identity(n=3, dtype=scalar)
            sf = filters[i]
            if reset_filters != 0:
                # Fixed particles have dv = 0: nothing of them is solved for.
                sf = wp.where(fixed[i] != 0, mat33(scalar(0.0)), identity)
                filters[i] = sf
            m = particle_mass[i]
            d = m * identity + diag_block[i]
            diag_block[i] = d
            b = sf * (m * (qd_n[i] - qd_k[i]) + h * (f[i] + m * gravity) + rhs[i])
            rhs[i] = b
            pre = mat33(scalar(0.0))
            if fixed[i] == 0:
                if block_jacobi != 0:
                    pre = wp.inverse(d)
                else:
                    pre = diagonal_inverse(d)
            precond_out[i] = sf * pre * sf
            # Initial guess: the last step's dv minus its gravity part, plus this step's h g.
            # Springs do not resist a uniform velocity change (A (h g) = M h g), so the guess is
            # exact for free fall, and the first step needs no special case. Prescribed parts
            # of dv are 0: the iterate already satisfies the constraints.
            x0 = sf * (warm_scale * (dv_warm[i] + h * gravity))
            x_out[i] = x0
            ax_out[i] = m * x0
            bb = wp.dot(b, b)
        total = wp.tile_sum(wp.tile(bb))
        wp.tile_atomic_add(scalars_out, total, offset=BB)

    @wp.func
    def differs(a: vec3, b: vec3):
        return a[0] != b[0] or a[1] != b[1] or a[2] != b[2]

    @wp.kernel(module="unique")
    def constrain_contacts(
        h: scalar,
        # Model:
        particle_world: wp.array(dtype=wp.int32),
        fixed: wp.array(dtype=wp.int32),
        plane_count: int,
        plane_world: wp.array(dtype=wp.int32),
        plane_point: wp.array(dtype=vec3),
        plane_normal: wp.array(dtype=vec3),
        plane_hole_center: wp.array(dtype=vec3),
        plane_hole_radius: wp.array(dtype=scalar),
        contact_epsilon: scalar,
        # The step's start, and its result before and after the contact response:
        q_n: wp.array(dtype=vec3),
        q_free: wp.array(dtype=vec3),
        qd_free: wp.array(dtype=vec3),
        q_contact: wp.array(dtype=vec3),
        qd_contact: wp.array(dtype=vec3),
        # Out: filters, the constrained iterate (x_n + h v, v), and whether anything touched
        filters_out: wp.array(dtype=mat33),
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
        any_contact_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        identity = wp.identity(n=3, dtype=scalar)
        v = qd_free[i]
        sf = identity
        if fixed[i] != 0:
            sf = mat33(scalar(0.0))
        elif differs(q_contact[i], q_free[i]) or differs(qd_contact[i], v):
            any_contact_out[0] = 1
            v_c = qd_contact[i]
            # The plane the particle touches (as the response saw it); more than one, or a contact
            # primitive other than a plane (a contact hook), gives no single normal.
            touching = int(0)
            plane = int(-1)
            w = particle_world[i]
            xf = q_free[i]
            for p in range(plane_count):
                if plane_world[p] == w:
                    nrm = plane_normal[p]
                    phi = wp.dot(xf - plane_point[p], nrm)
                    hr = plane_hole_radius[p]
                    if hr > scalar(0.0):
                        off = xf - plane_hole_center[p]
                        off = off - wp.dot(off, nrm) * nrm
                        if wp.length_sq(off) < hr * hr:
                            phi = scalar(1.0e30)
                    if phi < contact_epsilon:
                        touching = touching + 1
                        plane = p
            # Otherwise (friction acted, or no single normal) the whole velocity is prescribed.
            sf = mat33(scalar(0.0))
            target = v_c
            if touching == 1:
                nrm = plane_normal[plane]
                vn = wp.dot(v, nrm)
                vt = v - vn * nrm
                if not differs(vt, v_c - wp.dot(v_c, nrm) * nrm):
                    # The response changed only the normal velocity (a collision keeps the
                    # tangential one): prescribe the normal part, leave the tangential part to
                    # the solve; prescribing it too would act like an impact with unlimited
                    # friction, which can add energy. An approaching particle is stopped: the
                    # impact is inelastic (see softsim_warp/implicit.py on restitution).
                    sf = identity - wp.outer(nrm, nrm)
                    target = wp.where(vn < scalar(0.0), vt, v)
            v = sf * v + (identity - sf) * target
        filters_out[i] = sf
        qd_out[i] = v
        q_out[i] = q_n[i] + h * v

    @wp.kernel(module="unique")
    def constrain_last_system(
        n: int,
        particle_mass: wp.array(dtype=scalar),
        filters: wp.array(dtype=mat33),
        rhs: wp.array(dtype=vec3),
        # The last solve's result and the constrained iterate (constrain_contacts):
        qd_free: wp.array(dtype=vec3),
        qd_iter: wp.array(dtype=vec3),
        # In/out: the last solve's dv becomes the initial guess holding the prescribed parts;
        # the preconditioner gets filtered
        x: wp.array(dtype=vec3),
        precond: wp.array(dtype=mat33),
        # Out: the iterate the last system is relative to, M x0, b.b of the free part
        qd_k_out: wp.array(dtype=vec3),
        ax_out: wp.array(dtype=vec3),
        scalars_out: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        bb = scalar(0.0)
        if i < n:
            sf = filters[i]
            dv = x[i]
            v_free = qd_free[i]
            qd_k_out[i] = v_free - dv
            # The prescribed velocity differs from the solve's only in constrained directions.
            x0 = dv + (qd_iter[i] - v_free)
            x[i] = x0
            precond[i] = sf * precond[i] * sf
            ax_out[i] = particle_mass[i] * x0
            b = sf * rhs[i]
            bb = wp.dot(b, b)
        total = wp.tile_sum(wp.tile(bb))
        wp.tile_atomic_add(scalars_out, total, offset=BB)

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
        scalars_out: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        tid = blk * TILE + lane
        quad = scalar(0.0)
        if tid < count:
            pair = spring_indices[tid]
            a = pair[0]
            b = pair[1]
            # Rows of constrained directions get values too; the filter drops them.
            delta = p[a] - p[b]
            t = spring_block[tid] * delta
            wp.atomic_add(y_out, a, t)
            wp.atomic_sub(y_out, b, t)
            quad = wp.dot(delta, t)
        total = wp.tile_sum(wp.tile(quad))
        wp.tile_atomic_add(scalars_out, total, offset=slot)

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
        scalars_out: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        rz = scalar(0.0)
        rr = scalar(0.0)
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

    @wp.kernel(module="unique")
    def cg_begin(
        tol: scalar,
        max_iterations: int,
        scalars: wp.array(dtype=scalar),
        ints: wp.array(dtype=wp.int32),
    ):
        # One thread: tolerance from |b|, first r.z and r.r, and the loop condition.
        tol2 = tol * tol * scalars[BB]
        scalars[TOL2] = tol2
        scalars[RZ] = scalars[RZ_NEW]
        scalars[RR] = scalars[RR_NEW]
        scalars[RZ_NEW] = scalar(0.0)
        scalars[RR_NEW] = scalar(0.0)
        scalars[PAP] = scalar(0.0)
        scalars[BETA] = scalar(0.0)
        ints[ITER] = 0
        ints[COND] = wp.where(scalars[RR] > tol2 and max_iterations > 0, 1, 0)

    @wp.kernel(module="unique")
    def cg_direction(
        n: int,
        mass_part: int,
        particle_mass: wp.array(dtype=scalar),
        z: wp.array(dtype=vec3),
        # In/out: direction p <- z + beta p; out (if mass_part): M p, and p.(M p) into PAP
        p: wp.array(dtype=vec3),
        ap_out: wp.array(dtype=vec3),
        scalars: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        quad = scalar(0.0)
        if i < n:
            # z and p are filtered, so p stays filtered.
            pi = z[i] + scalars[BETA] * p[i]
            p[i] = pi
            if mass_part != 0:
                mp = particle_mass[i] * pi
                ap_out[i] = mp
                quad = wp.dot(pi, mp)
        wp.tile_atomic_add(scalars, wp.tile_sum(wp.tile(quad)), offset=PAP)

    @wp.kernel(module="unique")
    def dot_accumulate(
        n: int,
        slot: int,
        a: wp.array(dtype=vec3),
        b: wp.array(dtype=vec3),
        scalars_out: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        v = scalar(0.0)
        if i < n:
            v = wp.dot(a[i], b[i])
        wp.tile_atomic_add(scalars_out, wp.tile_sum(wp.tile(v)), offset=slot)

    @wp.kernel(module="unique")
    def cg_update(
        n: int,
        filters: wp.array(dtype=mat33),
        precond: wp.array(dtype=mat33),
        p: wp.array(dtype=vec3),
        ap: wp.array(dtype=vec3),
        # In/out: solution and residual; out: preconditioned residual, r.z and r.r accumulators
        x: wp.array(dtype=vec3),
        r: wp.array(dtype=vec3),
        z_out: wp.array(dtype=vec3),
        scalars: wp.array(dtype=scalar),
    ):
        blk, lane = wp.tid()
        i = blk * TILE + lane
        rz = scalar(0.0)
        rr = scalar(0.0)
        if i < n:
            pap = scalars[PAP]
            # p.Ap <= 0 only when p = 0 (A is positive definite): take no step then.
            alpha = wp.where(pap > scalar(0.0), scalars[RZ] / pap, scalar(0.0))
            x[i] = x[i] + alpha * p[i]
            ri = r[i] - alpha * (filters[i] * ap[i])
            zi = precond[i] * ri
            r[i] = ri
            z_out[i] = zi
            rz = wp.dot(ri, zi)
            rr = wp.dot(ri, ri)
        wp.tile_atomic_add(scalars, wp.tile_sum(wp.tile(rz)), offset=RZ_NEW)
        wp.tile_atomic_add(scalars, wp.tile_sum(wp.tile(rr)), offset=RR_NEW)

    @wp.kernel(module="unique")
    def cg_end_iteration(
        max_iterations: int,
        scalars: wp.array(dtype=scalar),
        ints: wp.array(dtype=wp.int32),
    ):
        # One thread: beta, the new r.z and r.r, fresh accumulators and the loop condition.
        rz_old = scalars[RZ]
        rz_new = scalars[RZ_NEW]
        pap = scalars[PAP]
        scalars[BETA] = wp.where(rz_old > scalar(0.0), rz_new / rz_old, scalar(0.0))
        scalars[RZ] = rz_new
        scalars[RR] = scalars[RR_NEW]
        scalars[RZ_NEW] = scalar(0.0)
        scalars[RR_NEW] = scalar(0.0)
        scalars[PAP] = scalar(0.0)
        it = ints[ITER] + 1
        ints[ITER] = it
        going = scalars[RR] > scalars[TOL2] and it < max_iterations and pap > scalar(0.0)
        ints[COND] = wp.where(going, 1, 0)

    @wp.kernel(module="unique")
    def record_solve(
        iterations: wp.array(dtype=wp.int32),
        residual_sq: wp.array(dtype=scalar),
        tolerance_sq: wp.array(dtype=scalar),
        stats: wp.array(dtype=wp.int32),
    ):
        # One thread: add a solve's iteration count to the step's total; count unconverged solves.
        stats[STEP_ITERS] = stats[STEP_ITERS] + iterations[0]
        stats[SOLVES] = stats[SOLVES] + 1
        if residual_sq[0] > tolerance_sq[0]:
            stats[UNCONVERGED] = stats[UNCONVERGED] + 1

    @wp.kernel(module="unique")
    def record_step(stats: wp.array(dtype=wp.int32)):
        # One thread: close the step's CG iteration count.
        it = stats[STEP_ITERS]
        stats[TOTAL_ITERS] = stats[TOTAL_ITERS] + it
        stats[MAX_ITERS] = wp.max(stats[MAX_ITERS], it)
        stats[STEPS] = stats[STEPS] + 1
        stats[STEP_ITERS] = 0

    @wp.kernel(module="unique")
    def apply_velocity_update(
        h: scalar,
        dv_scale: scalar,
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
            dv_warm_out[i] = dv[i] - wp.where(fixed[i] != 0, scalar(0.0), h) * gravity

    @wp.kernel(module="unique")
    def precondition(
        precond: wp.array(dtype=mat33),
        x: wp.array(dtype=vec3),
        y: wp.array(dtype=vec3),
        alpha: scalar,
        beta: scalar,
        z_out: wp.array(dtype=vec3),
    ):
        # z = alpha P x + beta y, the LinearOperator form that warp.optim.linear expects.
        i = wp.tid()
        z_out[i] = alpha * (precond[i] * x[i]) + beta * y[i]

    @wp.kernel(module="unique")
    def assemble_bsr_diagonal(
        fixed: wp.array(dtype=wp.int32),
        diag_block: wp.array(dtype=mat33),
        diag_index: wp.array(dtype=wp.int32),
        values_out: wp.array(dtype=mat33),
    ):
        i = wp.tid()
        # A fixed particle's row and column are eliminated: an identity block (and rhs 0) keeps
        # the assembled matrix nonsingular for solvers that do not filter.
        values_out[diag_index[i]] = wp.where(fixed[i] != 0, wp.identity(n=3, dtype=scalar), diag_block[i])

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

    return {
        "spring_jacobian": spring_jacobian,
        "eval_spring_jacobians": eval_spring_jacobians,
        "build_system": build_system,
        "constrain_contacts": constrain_contacts,
        "constrain_last_system": constrain_last_system,
        "spring_mv": spring_mv,
        "init_residual": init_residual,
        "cg_begin": cg_begin,
        "cg_direction": cg_direction,
        "dot_accumulate": dot_accumulate,
        "cg_update": cg_update,
        "cg_end_iteration": cg_end_iteration,
        "record_solve": record_solve,
        "record_step": record_step,
        "apply_velocity_update": apply_velocity_update,
        "precondition": precondition,
        "assemble_bsr_diagonal": assemble_bsr_diagonal,
        "assemble_bsr_offdiagonal": assemble_bsr_offdiagonal,
    }
