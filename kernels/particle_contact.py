"""Contact between jellies and of a jelly with itself: a post-step projection over hash-grid neighbours.

The response runs after the integrator's step, on its result, like terrain contact
(``core/particle_contact.py`` launches these kernels from ``model.contact_hooks``). Each particle
taking part gathers its neighbours from a ``wp.HashGrid`` (one group per world, so worlds never
meet) and sums the impulses of its contacts; every pair impulse is computed from the pair's own
values only, so particle j receives exactly the negative of what particle i does: linear momentum is
conserved pair by pair. The gather writes only its own particle (no atomics) and visits neighbours
in the grid's order, which is a stable radix sort by cell and index: the sum is the same on every
run and on every device count of threads, so the response is deterministic on CUDA as on the CPU.

Jacobi accumulation with split masses (Tonge et al. 2012, "Mass splitting for jitter-free parallel
rigid body simulation"): a particle in k contacts would be corrected k times over if every pair
acted in full, so each pair's effective mass uses k_i / m_i and k_j / m_j for the inverse masses.
The impulse is still one number applied to both particles with opposite signs, so momentum is
exact (scaling each particle's correction by its own count, as constraint averaging does, would
not be). Several iterations of the velocity pass converge towards the coupled solution; one
position pass then projects out the remaining overlap.
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})

# Pairs closer than this many pair distances are candidates: a particle resting on the other
# surface between its particles (up to s / sqrt(2) aside at pitch s) is farther than the pair
# distance from each of them, yet touches the surface along the normal.
CANDIDATE_REACH = wp.constant(1.25)
# A face's normal is the contact normal for particles at most this many pair distances aside of the
# face's particle (the half diagonal of a face cell is 0.71 lattice spacings).
FACE_REACH = wp.constant(0.75)


@functools.cache
def build(scalar):
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def pair_touches(
        i: int,
        j: int,
        xi: vec3,
        cq: wp.array(dtype=vec3),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
    ):
        """Whether contact particles i and j (i != j) are a candidate pair; returns (candidate,
        distance, pair distance d).

        Candidates are closer than CANDIDATE_REACH d. Particles of different jellies are candidates
        when ``between_jellies`` is set; particles of one jelly only when that jelly has self
        contact and they are at least ``self_exclusion`` times d apart in the rest shape (closer
        pairs are the jelly's own elastic neighbourhood). The jelly test comes first: most of a
        particle's grid neighbours are of its own jelly, and it needs no position.
        """
        ji = contact_jelly[i]
        same = ji == contact_jelly[j]
        if same:
            if jelly_self_contact[ji] == 0:
                return False, scalar(0.0), scalar(0.0)
        elif between_jellies == 0:
            return False, scalar(0.0), scalar(0.0)
        d = contact_radius[i] + contact_radius[j]
        r = xi - cq[j]
        dist2 = wp.dot(r, r)
        reach_d = scalar(CANDIDATE_REACH) * d
        if dist2 >= reach_d * reach_d or dist2 == scalar(0.0):
            return False, scalar(0.0), d
        if same:
            rr = contact_rest[i] - contact_rest[j]
            reach = self_exclusion * d
            if wp.dot(rr, rr) < reach * reach:
                return False, scalar(0.0), d
        return True, wp.sqrt(dist2), d

    @wp.func
    def facing_normal(normal: wp.array2d(dtype=vec3), i: int, direction: vec3):
        """The outward face normal of contact particle i most aligned with ``direction`` (zero if none)."""
        best = vec3(scalar(0.0))
        best_dot = scalar(-2.0)
        for a in range(3):
            n = normal[i, a]
            if wp.length_sq(n) > scalar(0.0):
                c = wp.dot(n, direction)
                if c > best_dot:
                    best_dot = c
                    best = n
        return best

    @wp.func
    def pair_normal(i: int, j: int, xi: vec3, xj: vec3, dist: scalar, d: scalar, normal: wp.array2d(dtype=vec3)):
        """Contact normal of a touching pair, from j to i; swapping i and j negates it exactly.

        It is the difference of the outward normals of the two faces that face each other,
        n_j - n_i (each particle's boundary face most aligned with the other particle), so two
        surfaces meet as smooth surfaces. The direction between the particles, u, would tilt by up
        to 30 degrees where a particle sits between the particles of the other surface (an egg
        crate of pitch one lattice spacing): lattices would interlock and resist sliding far beyond
        Coulomb friction (measured: a block on a slab with mu = 0.2 stuck at 25 degrees, where it
        should slide at 2.4 m/s^2). Adding even a quarter of u to n made resting stacks jitter
        (the two pairs under a particle between two others push it sideways in turn). The faces'
        normals rather than a particle's mean normal keep an edge particle of a block from pushing
        at 45 degrees. The faces' normal holds over the faces only: where particle i lies more than
        FACE_REACH d aside of particle j along it (beyond the half diagonal of a face cell at pitch
        d), or more than 30 degrees from u (no faces face each other: an edge meeting a face
        side-on, a fold's tip), the normal turns smoothly to u, which it reaches 0.25 d farther
        aside or at 45 degrees. Without that bound a particle beside the other jelly's edge, below
        its face's plane, was thrown up onto the face (1.5 cm in a step, every 14 steps, in the
        pile scene); with a sudden switch instead of the blend, particles at the edge of a face
        jumped between the two normals every few steps.
        """
        u = (xi - xj) / dist
        m = facing_normal(normal, j, u) - facing_normal(normal, i, -u)
        length = wp.length(m)
        if length > scalar(0.0):
            n = m / length
            c = wp.dot(n, u)
            aside = dist * wp.sqrt(wp.max(scalar(1.0) - c * c, scalar(0.0))) / d
            # Blend weight of u: 0 within the face (aside <= FACE_REACH d, within 30 degrees of u),
            # 1 from 0.25 d farther aside or from 45 degrees, smooth in between so that the normal
            # and the separation along it change continuously with the positions.
            t = wp.max(
                wp.clamp((aside - scalar(FACE_REACH)) / scalar(0.25), scalar(0.0), scalar(1.0)),
                wp.clamp((scalar(0.8660254037844386) - c) / scalar(0.1589186225978631), scalar(0.0), scalar(1.0)),
            )
            t = t * t * (scalar(3.0) - scalar(2.0) * t)
            m = (scalar(1.0) - t) * n + t * u
            length = wp.length(m)
            if length > scalar(0.0):
                return m / length
        return u

    @wp.func
    def pair_contact(
        i: int,
        j: int,
        xi: vec3,
        cq: wp.array(dtype=vec3),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        normal: wp.array2d(dtype=vec3),
    ):
        """Whether particles i and j touch: a candidate pair closer than d along its contact normal.
        Returns (touches, normal from j to i, separation along it minus d: negative when touching)."""
        candidate, dist, d = pair_touches(
            i, j, xi, cq, contact_jelly, contact_radius, contact_rest, jelly_self_contact, between_jellies,
            self_exclusion,
        )
        n = vec3(scalar(0.0))
        gap = scalar(0.0)
        if candidate:
            xj = cq[j]
            n = pair_normal(i, j, xi, xj, dist, d, normal)
            gap = wp.dot(xi - xj, n) - d
        return candidate and gap < scalar(0.0), n, gap

    @wp.func
    def pair_impulse(
        n: vec3,
        vi: vec3,
        vj: vec3,
        vi_prev: vec3,
        vj_prev: vec3,
        wi_split: scalar,
        wj_split: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
    ):
        """Impulse on particle i of a touching pair with normal ``n`` (from j to i); j gets its negative.

        ``wi_split``, ``wj_split`` are the split inverse masses (inverse mass times the particle's
        number of contacts), which set the pair's effective mass. Swapping i and j negates the
        impulse exactly (the normal and the relative velocity both change sign), which is what
        makes the pair conserve momentum.
        """
        vrel = vi - vj
        vn = wp.dot(vrel, n)
        p = vec3(scalar(0.0))
        if vn < scalar(0.0):
            m_eff = scalar(1.0) / (wi_split + wj_split)
            # Impact or contact: the same restitution threshold as terrain (kernels/contact.py,
            # resolve_contact), on the relative normal velocity before (u0) and after the step.
            u0 = -wp.dot(vi_prev - vj_prev, n)
            w = -vn - u0
            if restitution == scalar(0.0) or u0 < eps_v or u0 < rest_steps * w:
                # Inelastic: cancel the approach, and Coulomb friction takes at most mu times that
                # normal impulse of the tangential relative momentum, never reversing it.
                jn = -vn * m_eff
                vt = vrel - vn * n
                speed = wp.length(vt)
                p = jn * n
                if speed > scalar(0.0):
                    jt = wp.min(speed * m_eff, friction * jn)
                    p = p - (jt / speed) * vt
            else:
                p = (-(scalar(1.0) + restitution) * vn * m_eff) * n
        return p

    @wp.kernel(module="unique")
    def gather_contact_particles(
        contact_index: wp.array(dtype=wp.int32),
        q: wp.array(dtype=vec3),
        qd: wp.array(dtype=vec3),
        # Out: the contact particles' positions and velocities, in contact order
        cq_out: wp.array(dtype=vec3),
        cqd_out: wp.array(dtype=vec3),
    ):
        k = wp.tid()
        p = contact_index[k]
        cq_out[k] = q[p]
        cqd_out[k] = qd[p]

    @wp.kernel(module="unique")
    def contact_surface_normals(
        contact_index: wp.array(dtype=wp.int32),
        contact_axis_neighbors: wp.array2d(dtype=wp.int32),
        q: wp.array(dtype=vec3),
        # Out: each contact particle's outward normal of its boundary face on each lattice axis
        # (zero on an axis where it is not on the boundary)
        normal_out: wp.array2d(dtype=vec3),
    ):
        # contact_axis_neighbors[k] holds the lattice neighbours at -x, +x, -y, +y, -z, +z (the
        # particle itself where there is none) and, in slots 6..8, the inward neighbour of each axis
        # on whose boundary the particle lies (-1 elsewhere). A face's normal is the cross product
        # of its two in-face directions, so a sheared jelly's faces keep their own normal (the
        # inward lattice line tilts with the shear); it is oriented away from the inward neighbour.
        k = wp.tid()
        x = q[contact_index[k]]
        for a in range(3):
            inward = contact_axis_neighbors[k, 6 + a]
            n = vec3(scalar(0.0))
            if inward >= 0:
                out = x - q[inward]
                b = (a + 1) % 3
                c = (a + 2) % 3
                tb = q[contact_axis_neighbors[k, 2 * b + 1]] - q[contact_axis_neighbors[k, 2 * b]]
                tc = q[contact_axis_neighbors[k, 2 * c + 1]] - q[contact_axis_neighbors[k, 2 * c]]
                m = wp.cross(tb, tc)
                if wp.length_sq(m) == scalar(0.0):
                    m = out  # a face one particle wide: the lattice line is all there is
                if wp.dot(m, out) < scalar(0.0):
                    m = -m
                length = wp.length(m)
                if length > scalar(0.0):
                    n = m / length
            normal_out[k, a] = n

    @wp.kernel(module="unique")
    def count_particle_contacts(
        grid: wp.uint64,
        # Model:
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        max_distance: scalar,
        # State after the step and surface normals (contact order):
        cq: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        # Out: contacts per contact particle, and the first MAX_CONTACTS of them (grid order)
        count_out: wp.array(dtype=wp.int32),
        contact_list_out: wp.array2d(dtype=wp.int32),
    ):
        # Threads in the grid's order (by cell): neighbouring threads read neighbouring particles.
        i = wp.hash_grid_point_id(grid, wp.tid())
        xi = cq[i]
        count = int(0)
        query = wp.hash_grid_query(grid, xi, max_distance, contact_world[i])
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j != i:
                touches, n, gap = pair_contact(
                    i, j, xi, cq, contact_jelly, contact_radius, contact_rest, jelly_self_contact,
                    between_jellies, self_exclusion, normal,
                )
                if touches:
                    if count < contact_list_out.shape[1]:
                        contact_list_out[i, count] = j
                    count += 1
        count_out[i] = count

    @wp.func
    def velocity_term(
        i: int,
        j: int,
        xi: vec3,
        vi: vec3,
        vi_prev: vec3,
        wi_split: scalar,
        contact_index: wp.array(dtype=wp.int32),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        particle_inv_mass: wp.array(dtype=scalar),
        between_jellies: int,
        self_exclusion: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        qd_prev: wp.array(dtype=vec3),
        cq: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        cqd: wp.array(dtype=vec3),
    ):
        """The impulse of pair (i, j) on i in a velocity iteration (zero if they do not touch)."""
        touches, n, gap = pair_contact(
            i, j, xi, cq, contact_jelly, contact_radius, contact_rest, jelly_self_contact, between_jellies,
            self_exclusion, normal,
        )
        p = vec3(scalar(0.0))
        if touches:
            pj = contact_index[j]
            wj_split = scalar(count[j]) * particle_inv_mass[pj]
            if wi_split + wj_split > scalar(0.0):
                p = pair_impulse(
                    n, vi, cqd[j], vi_prev, qd_prev[pj], wi_split, wj_split, friction, restitution, eps_v, rest_steps
                )
        return p

    @wp.kernel(module="unique")
    def resolve_contact_velocities(
        grid: wp.uint64,
        # Model:
        contact_index: wp.array(dtype=wp.int32),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        particle_inv_mass: wp.array(dtype=scalar),
        between_jellies: int,
        self_exclusion: scalar,
        max_distance: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        # Velocities before the step (particle order); positions after it, surface normals, the
        # contact counts and lists and the velocities of this iteration (contact order):
        qd_prev: wp.array(dtype=vec3),
        cq: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        contact_list: wp.array2d(dtype=wp.int32),
        cqd: wp.array(dtype=vec3),
        # Out: the velocities after this iteration's impulses (contact order)
        cqd_out: wp.array(dtype=vec3),
    ):
        # Threads in the grid's order (by cell): neighbouring threads read neighbouring particles.
        i = wp.hash_grid_point_id(grid, wp.tid())
        ci = count[i]
        vi = cqd[i]
        if ci == 0:
            cqd_out[i] = vi
            return
        pi = contact_index[i]
        wi = particle_inv_mass[pi]
        xi = cq[i]
        vi_prev = qd_prev[pi]
        wi_split = scalar(ci) * wi
        impulse = vec3(scalar(0.0))
        # The contacts found by count_particle_contacts, in the grid's order; a particle with more
        # than the list holds queries the grid again (the same pairs, the same order).
        if ci <= contact_list.shape[1]:
            for a in range(ci):
                impulse = impulse + velocity_term(
                    i, contact_list[i, a], xi, vi, vi_prev, wi_split, contact_index, contact_jelly,
                    contact_radius, contact_rest, jelly_self_contact, particle_inv_mass, between_jellies,
                    self_exclusion, friction, restitution, eps_v, rest_steps, qd_prev, cq, normal, count, cqd,
                )
        else:
            query = wp.hash_grid_query(grid, xi, max_distance, contact_world[i])
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                if j != i:
                    impulse = impulse + velocity_term(
                        i, j, xi, vi, vi_prev, wi_split, contact_index, contact_jelly,
                        contact_radius, contact_rest, jelly_self_contact, particle_inv_mass, between_jellies,
                        self_exclusion, friction, restitution, eps_v, rest_steps, qd_prev, cq, normal, count, cqd,
                    )
        cqd_out[i] = vi + wi * impulse

    @wp.func
    def position_term(
        i: int,
        j: int,
        xi: vec3,
        yi: vec3,
        vi: vec3,
        wi: scalar,
        wi_split: scalar,
        h: scalar,
        beta_h: scalar,
        contact_index: wp.array(dtype=wp.int32),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        particle_inv_mass: wp.array(dtype=scalar),
        between_jellies: int,
        self_exclusion: scalar,
        cq: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        cqd: wp.array(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        cqd_new: wp.array(dtype=vec3),
    ):
        """Position and velocity change of i from pair (i, j) in the position pass: (dx, dv)."""
        touches, n, gap = pair_contact(
            i, j, xi, cq, contact_jelly, contact_radius, contact_rest, jelly_self_contact, between_jellies,
            self_exclusion, normal,
        )
        dx = vec3(scalar(0.0))
        dv = vec3(scalar(0.0))
        if touches:
            xj = cq[j]
            split = wi_split + scalar(count[j]) * particle_inv_mass[contact_index[j]]
            if split > scalar(0.0):
                # What overlap the moved positions keep is projected out along the pair's normal,
                # split like the impulses (positions only: no momentum).
                vj = cqd_new[j]
                yj = xj + beta_h * (vj - cqd[j])
                moved = gap + wp.dot((yi - xi) - (yj - xj), n)
                if moved < scalar(0.0):
                    dx = (-moved * wi / split) * n
                    # The projection is a motion of the step: what approach velocity the
                    # iterations left (they converge slowly where a particle presses on one with
                    # many contacts) is taken off up to the projected distance per step, so a
                    # pressed particle does not keep a velocity it never moves by. Only approach
                    # is removed, never separation added.
                    vn = wp.dot(vi - vj, n)
                    if vn < scalar(0.0):
                        dv = (wp.min(-vn, -moved / h) * wi / split) * n
        return dx, dv

    @wp.kernel(module="unique")
    def resolve_contact_positions(
        grid: wp.uint64,
        # Model:
        contact_index: wp.array(dtype=wp.int32),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        particle_inv_mass: wp.array(dtype=scalar),
        between_jellies: int,
        self_exclusion: scalar,
        max_distance: scalar,
        h: scalar,
        world_contact_beta: wp.array(dtype=scalar),
        # The step's result, surface normals, the contact counts and lists, and the velocities
        # before and after the impulses (contact order):
        cq: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        cqd: wp.array(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        contact_list: wp.array2d(dtype=wp.int32),
        cqd_new: wp.array(dtype=vec3),
        # Out: the step's result, corrected in place (each thread writes its own particle only)
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        # Threads in the grid's order (by cell): neighbouring threads read neighbouring particles.
        i = wp.hash_grid_point_id(grid, wp.tid())
        ci = count[i]
        if ci == 0:
            return
        pi = contact_index[i]
        wi = particle_inv_mass[pi]
        world = contact_world[i]
        # The impulses act over the whole step: positions move by what the integrator makes of a
        # velocity change, beta h dv (as for terrain, kernels/contact.py).
        beta_h = h * world_contact_beta[world]
        xi = cq[i]
        vi = cqd_new[i]
        yi = xi + beta_h * (vi - cqd[i])
        wi_split = scalar(ci) * wi
        dx = vec3(scalar(0.0))
        dv = vec3(scalar(0.0))
        if ci <= contact_list.shape[1]:
            for a in range(ci):
                ddx, ddv = position_term(
                    i, contact_list[i, a], xi, yi, vi, wi, wi_split, h, beta_h, contact_index, contact_jelly,
                    contact_radius, contact_rest, jelly_self_contact, particle_inv_mass, between_jellies,
                    self_exclusion, cq, normal, cqd, count, cqd_new,
                )
                dx = dx + ddx
                dv = dv + ddv
        else:
            query = wp.hash_grid_query(grid, xi, max_distance, world)
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                if j != i:
                    ddx, ddv = position_term(
                        i, j, xi, yi, vi, wi, wi_split, h, beta_h, contact_index, contact_jelly,
                        contact_radius, contact_rest, jelly_self_contact, particle_inv_mass, between_jellies,
                        self_exclusion, cq, normal, cqd, count, cqd_new,
                    )
                    dx = dx + ddx
                    dv = dv + ddv
        q_out[pi] = yi + dx
        qd_out[pi] = vi + dv

    return {
        "pair_touches": pair_touches,
        "pair_contact": pair_contact,
        "facing_normal": facing_normal,
        "pair_normal": pair_normal,
        "pair_impulse": pair_impulse,
        "contact_surface_normals": contact_surface_normals,
        "gather_contact_particles": gather_contact_particles,
        "count_particle_contacts": count_particle_contacts,
        "velocity_term": velocity_term,
        "position_term": position_term,
        "resolve_contact_velocities": resolve_contact_velocities,
        "resolve_contact_positions": resolve_contact_positions,
    }
