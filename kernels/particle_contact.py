"""Contact between jellies and of a jelly with itself: a post-step projection over hash-grid neighbours.

The response runs after the integrator's step, on its result, like terrain contact
(``core/particle_contact.py`` launches these kernels from ``model.contact_hooks``). Each particle
taking part gathers its neighbours from a ``wp.HashGrid`` (one group per world, so worlds never
meet) and sums the impulses of its contacts; every pair impulse is computed from the pair's own
values only, so particle j receives exactly the negative of what particle i does: linear momentum is
conserved pair by pair. The gather writes only its own particle (no atomics) and visits neighbours
in the grid's order, which is a stable radix sort by cell and index: the sum is the same on every
run and on every device count of threads, so the response is deterministic on CUDA as on the CPU.

Jacobi accumulation: a particle in k contacts would be corrected k times over if every pair acted
in full, so each pair's impulse and position correction is scaled by 1 / max(k_i, k_j). The factor
is the same for both particles of the pair, which keeps the impulses equal and opposite (scaling
each particle by its own count, as constraint averaging does, would not).
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})


@functools.cache
def build(scalar):
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def pair_touches(
        i: int,
        j: int,
        xi: vec3,
        xj: vec3,
        contact_jelly: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
    ):
        """Whether contact particles i and j (i != j) touch; returns (touches, distance, pair distance).

        Particles of different jellies touch when ``between_jellies`` is set; particles of one jelly
        only when that jelly has self contact and they are at least ``self_exclusion`` times their
        pair distance apart in the rest shape (closer pairs are the jelly's own elastic neighbourhood).
        """
        d = contact_radius[i] + contact_radius[j]
        r = xi - xj
        dist2 = wp.dot(r, r)
        if dist2 >= d * d or dist2 == scalar(0.0):
            return False, scalar(0.0), d
        ji = contact_jelly[i]
        if ji != contact_jelly[j]:
            if between_jellies == 0:
                return False, scalar(0.0), d
        else:
            if jelly_self_contact[ji] == 0:
                return False, scalar(0.0), d
            rr = contact_rest[i] - contact_rest[j]
            reach = self_exclusion * d
            if wp.dot(rr, rr) < reach * reach:
                return False, scalar(0.0), d
        return True, wp.sqrt(dist2), d

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
        # State after the step (contact order):
        cq: wp.array(dtype=vec3),
        # Out: contacts per contact particle
        count_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        xi = cq[i]
        count = int(0)
        query = wp.hash_grid_query(grid, xi, max_distance, contact_world[i])
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j != i:
                touches, dist, d = pair_touches(
                    i, j, xi, cq[j], contact_jelly, contact_radius, contact_rest, jelly_self_contact,
                    between_jellies, self_exclusion,
                )
                if touches:
                    count += 1
        count_out[i] = count

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
        # Velocities before the step (particle order); positions after it, the contact counts and
        # the velocities of this iteration (contact order):
        qd_prev: wp.array(dtype=vec3),
        cq: wp.array(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        cqd: wp.array(dtype=vec3),
        # Out: the velocities after this iteration's impulses (contact order)
        cqd_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        ci = count[i]
        vi = cqd[i]
        if ci == 0:
            cqd_out[i] = vi
            return
        pi = contact_index[i]
        wi = particle_inv_mass[pi]
        xi = cq[i]
        vi_prev = qd_prev[pi]
        impulse = vec3(scalar(0.0))
        query = wp.hash_grid_query(grid, xi, max_distance, contact_world[i])
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j != i:
                xj = cq[j]
                touches, dist, d = pair_touches(
                    i, j, xi, xj, contact_jelly, contact_radius, contact_rest, jelly_self_contact,
                    between_jellies, self_exclusion,
                )
                if touches:
                    pj = contact_index[j]
                    wj = particle_inv_mass[pj]
                    if wi + wj > scalar(0.0):
                        impulse = impulse + pair_impulse(
                            (xi - xj) / dist, vi, cqd[j], vi_prev, qd_prev[pj], scalar(ci) * wi,
                            scalar(count[j]) * wj, friction, restitution, eps_v, rest_steps,
                        )
        cqd_out[i] = vi + wi * impulse

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
        # The step's result (contact order), the contact counts and the velocities after the impulses:
        cq: wp.array(dtype=vec3),
        cqd: wp.array(dtype=vec3),
        count: wp.array(dtype=wp.int32),
        cqd_new: wp.array(dtype=vec3),
        # Out: the step's result, corrected in place (each thread writes its own particle only)
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
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
        yi = xi + beta_h * (cqd_new[i] - cqd[i])
        dx = vec3(scalar(0.0))
        query = wp.hash_grid_query(grid, xi, max_distance, world)
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            if j != i:
                xj = cq[j]
                touches, dist, d = pair_touches(
                    i, j, xi, xj, contact_jelly, contact_radius, contact_rest, jelly_self_contact,
                    between_jellies, self_exclusion,
                )
                if touches:
                    wj = particle_inv_mass[contact_index[j]]
                    split = scalar(ci) * wi + scalar(count[j]) * wj
                    if split > scalar(0.0):
                        # What overlap the moved positions keep is projected out along the pair's
                        # normal, split like the impulses (positions only: no momentum).
                        n = (xi - xj) / dist
                        yj = xj + beta_h * (cqd_new[j] - cqd[j])
                        gap = wp.dot(yi - yj, n) - d
                        if gap < scalar(0.0):
                            dx = dx - (gap * wi / split) * n
        q_out[pi] = yi + dx
        qd_out[pi] = cqd_new[i]

    return {
        "pair_touches": pair_touches,
        "pair_impulse": pair_impulse,
        "gather_contact_particles": gather_contact_particles,
        "count_particle_contacts": count_particle_contacts,
        "resolve_contact_velocities": resolve_contact_velocities,
        "resolve_contact_positions": resolve_contact_positions,
    }
