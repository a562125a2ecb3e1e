"""Contact between jellies and of a jelly with itself: a post-step projection over candidate lists.

The response runs after the integrator's step, on its result, like terrain contact
(``core/particle_contact.py`` launches these kernels from ``model.contact_hooks``). Each step:

1. ``prepare_contact_particles`` copies the contact particles' positions, each with its contact
   radius, to a compact array, computes their boundary-face normals, and raises the rebuild flag
   when a particle has moved ``rebuild_distance`` or more since the candidate lists were built;
2. ``insert_contact_grid`` and ``build_contact_candidates`` (they return at once unless the flag is
   raised) rebuild each particle's candidate list: the particles of other jellies (or of its own
   jelly, with self-contact, far enough apart in the rest shape) of its world within the candidate
   reach plus a skin, in ascending index order, found through a hashed cell grid;
3. ``find_particle_contacts`` tests each candidate and stores the touching pairs with their normal,
   gap and, with a restitution above zero, approach speed before the step, each started from the
   pair's impulse of the step before (the warm start), and each particle in contact's record for
   the passes (its velocities after those impulses and before the response, its contacts and its
   inverse mass);
4. ``resolve_contact_velocities`` (Jacobi iterations, the pairs' impulses accumulated over the step;
   one fewer than ``jelly_contact_iterations``) and ``resolve_contact_last_pass`` (the last iteration,
   then the positions and velocities written back, each touching pair's remaining overlap projected
   out) apply them.

Why no contact is missed: a pair is left out of the lists only when its distance at the build was
at least ``CANDIDATE_REACH d + skin``; the lists are rebuilt before any particle has moved
``skin / 2`` (``rebuild_distance`` is slightly less, for the rounding of the distances), so until
then such a pair stays farther apart than ``CANDIDATE_REACH d``, where it is no candidate.

Every pair impulse is computed from the pair's own values only, so particle j receives exactly the
negative of what particle i does: linear momentum is conserved pair by pair. Each thread writes
only its own particle (no atomics in the response) and visits its contacts in ascending index order
of the partner, whatever the grid's or the threads' order: the sum is the same on every run and
device, and it does not depend on when the lists were last built. The grid is built with atomics,
so the order within a cell varies on CUDA; the lists are sorted, so nothing downstream sees it.

Jacobi accumulation with split masses (Tonge et al. 2012, "Mass splitting for jitter-free parallel
rigid body simulation"): a particle in k contacts would be corrected k times over if every pair
acted in full, so each pair's effective mass uses k_i / m_i and k_j / m_j for the inverse masses.
The impulse is still one number applied to both particles with opposite signs, so momentum is
exact (scaling each particle's correction by its own count, as constraint averaging does, would
not be). Iterations of the velocity pass converge towards the coupled solution; the last one also
projects out the overlap each pair expects to keep (:func:`projection_term`). Each pair's impulse
so far is kept: an iteration can take back what an earlier one (or the warm start) gave too much,
down to no push at all, and friction stays within mu times the push over the whole step. Starting
each step from the last one's impulses (Catto's warm starting) lets one iteration hold a resting
stack.
"""

import functools

import warp as wp

from . import integration

wp.set_module_options({"enable_backward": False})

# Pairs closer than this many pair distances are candidates: a particle resting on the other
# surface between its particles (up to s / sqrt(2) aside at pitch s) is farther than the pair
# distance from each of them, yet touches the surface along the normal.
CANDIDATE_REACH = wp.constant(1.25)
# A face's normal is the contact normal for particles at most this many pair distances aside of the
# face's particle (the half diagonal of a face cell is 0.71 lattice spacings).
FACE_REACH = wp.constant(0.75)
# Cells per axis before the cell coordinates wrap in the grid's hash (a wrapped cell only adds
# particles that the distance test rejects).
CELL_WRAP = wp.constant(1024)
# Multipliers of the grid's hash: the world's (a 32-bit mix constant) and Fibonacci hashing's
# (2^32 / golden ratio), whose product's top bits are the bucket.
WORLD_MIX = wp.constant(wp.uint32(0x85EBCA6B))
FIBONACCI = wp.constant(wp.uint32(0x9E3779B9))


@functools.cache
def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    ctype = "float" if scalar == wp.float32 else "double"
    integration_funcs = integration.build(scalar)
    # The hot loads and stores address the hook's arrays (and the contiguous particle state) from
    # their data pointers, with the element size a constant (integration.load_contiguous): Warp's
    # a[i] wraps a negative index and multiplies by the run-time 64-bit strides, on the chain of
    # dependent loads (list slot, partner, partner's values) that the passes wait on.
    ld3 = integration_funcs["load_contiguous"]
    st3 = integration_funcs["store_contiguous"]
    ldi = integration_funcs["int_contiguous"]
    lds = integration_funcs["scalar_contiguous"]
    lds2 = integration_funcs["entry_contiguous"]  # a[s, i] of a contiguous scalar table

    @wp.func_native(
        f"typedef {ctype} T; struct alignas(4 * sizeof(T)) Quad {{ T x, y, z, w; }};\n"
        "const Quad q = reinterpret_cast<const Quad*>(a.data)[i];\n"
        "return wp::vec_t<4, T>(q.x, q.y, q.z, q.w);"
    )
    def ld4(a: wp.array(dtype=vec4), i: int) -> vec4:
        """``a[i]`` of a contiguous vec4 array as one aligned load (the array starts aligned to its
        element: ParticleContact checks)."""

    @wp.func_native(
        f"typedef {ctype} T; struct alignas(4 * sizeof(T)) Quad {{ T x, y, z, w; }};\n"
        "Quad q; q.x = value[0]; q.y = value[1]; q.z = value[2]; q.w = value[3];\n"
        "reinterpret_cast<Quad*>(a.data)[i] = q;"
    )
    def st4(a: wp.array(dtype=vec4), i: int, value: vec4):
        """``a[i] = value`` of a contiguous vec4 array as one aligned store."""

    @wp.func
    def record(v: vec3, w: scalar):
        """(v, w) as one vec4: an entry of the passes' records (a velocity with a count or an inverse
        mass), or of the compact positions (a position with its contact radius)."""
        return vec4(v[0], v[1], v[2], w)

    @wp.func
    def xyz(r: vec4):
        """The vector of a record entry: its first three components (a velocity, a position)."""
        return vec3(r[0], r[1], r[2])

    @wp.func
    def split_mass(r: vec4, r0: vec4):
        """A particle's split inverse mass from its two record entries (find_particle_contacts): its
        number of contacts (``r[3]``) times its inverse mass (``r0[3]``)."""
        return r[3] * r0[3]

    @wp.func_native("return ((const int*)a.data)[s * a.shape[1] + i];")
    def ldi2(a: wp.array2d(dtype=wp.int32), s: int, i: int) -> int:
        """``a[s, i]`` of a contiguous int32 table from its data pointer."""

    @wp.func_native("((int*)a.data)[s * a.shape[1] + i] = value;")
    def sti2(a: wp.array2d(dtype=wp.int32), s: int, i: int, value: int):
        """``a[s, i] = value`` of a contiguous int32 table."""

    @wp.func_native(f"(({ctype}*)a.data)[s * a.shape[1] + i] = value;")
    def sts2(a: wp.array2d(dtype=scalar), s: int, i: int, value: scalar):
        """``a[s, i] = value`` of a contiguous scalar table."""

    @wp.func_native(
        f"const {ctype}* t = (const {ctype}*)a.data + 3 * (s * a.shape[1] + i);\n"
        f"return wp::vec_t<3, {ctype}>(t[0], t[1], t[2]);"
    )
    def ld32(a: wp.array2d(dtype=vec3), s: int, i: int) -> vec3:
        """``a[s, i]`` of a contiguous vec3 table."""

    @wp.func_native(
        f"{ctype}* t = ({ctype}*)a.data + 3 * (s * a.shape[1] + i);\nt[0] = value[0]; t[1] = value[1]; t[2] = value[2];"
    )
    def st32(a: wp.array2d(dtype=vec3), s: int, i: int, value: vec3):
        """``a[s, i] = value`` of a contiguous vec3 table."""

    @wp.func
    def pair_allowed(
        i: int,
        j: int,
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
    ):
        """Whether contact particles i and j (i != j) may touch at all, whatever their positions.

        Particles of different worlds never do. Particles of different jellies do when
        ``between_jellies`` is set; particles of one jelly only when that jelly has self contact
        and they are at least ``self_exclusion`` times the pair distance apart in the rest shape
        (closer pairs are the jelly's own elastic neighbourhood)."""
        if contact_world[i] != contact_world[j]:
            return False
        ji = contact_jelly[i]
        if ji == contact_jelly[j]:
            if jelly_self_contact[ji] == 0:
                return False
            d = contact_radius[i] + contact_radius[j]
            rr = contact_rest[i] - contact_rest[j]
            reach = self_exclusion * d
            return wp.dot(rr, rr) >= reach * reach
        return between_jellies != 0

    @wp.func
    def facing_normal(normal: wp.array2d(dtype=vec3), face_start: wp.vec3i, i: int, direction: vec3):
        """The outward face normal of contact particle i most aligned with ``direction`` (zero if none).

        ``normal[s, i]`` (slot-major) holds the particle's boundary-face normals in axis order, in
        the first slots; the slots after its last face are zero."""
        best = vec3(scalar(0.0))
        best_dot = scalar(-2.0)
        for s in range(3):
            if i < face_start[s]:
                break  # no face s (the contact order groups the particles by their number of faces)
            n = ld32(normal, s, i)
            if wp.length_sq(n) > scalar(0.0):
                c = wp.dot(n, direction)
                if c > best_dot:
                    best_dot = c
                    best = n
        return best

    @wp.func
    def pair_normal(
        i: int,
        j: int,
        xi: vec3,
        xj: vec3,
        dist: scalar,
        d: scalar,
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
    ):
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
        m = facing_normal(normal, face_start, j, u) - facing_normal(normal, face_start, i, -u)
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
    def near_pair(j: int, xi: vec3, ri: scalar, cq: wp.array(dtype=vec4)):
        """Whether candidate j lies within CANDIDATE_REACH d of particle i (position ``xi``, contact
        radius ``ri``) and not on it: the pairs that :func:`touching_pair` tests further. Every test
        of a pair goes through here, so all passes agree on it bit for bit."""
        xrj = ld4(cq, j)
        r = xi - xyz(xrj)
        dist2 = wp.dot(r, r)
        reach_d = scalar(CANDIDATE_REACH) * (ri + xrj[3])
        return dist2 < reach_d * reach_d and dist2 > scalar(0.0)

    @wp.func
    def touching_pair(
        i: int,
        j: int,
        xi: vec3,
        ri: scalar,
        cq: wp.array(dtype=vec4),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
    ):
        """Whether a near pair (i, j) (:func:`near_pair`) touches: closer than d along its contact
        normal. Returns (touches, normal from j to i, separation along it minus d: negative when
        touching)."""
        xrj = ld4(cq, j)
        d = ri + xrj[3]
        xj = xyz(xrj)
        r = xi - xj
        n = pair_normal(i, j, xi, xj, wp.sqrt(wp.dot(r, r)), d, normal, face_start)
        gap = wp.dot(r, n) - d
        return gap < scalar(0.0), n, gap

    @wp.func
    def pair_contact(
        i: int,
        j: int,
        xi: vec3,
        ri: scalar,
        cq: wp.array(dtype=vec4),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
    ):
        """Whether an allowed pair (i, j) touches: near (:func:`near_pair`) and closer than d along
        its contact normal. Returns (touches, normal from j to i, separation along it minus d:
        negative when touching)."""
        touches = False
        n = vec3(scalar(0.0))
        gap = scalar(0.0)
        if near_pair(j, xi, ri, cq):
            touches, n, gap = touching_pair(i, j, xi, ri, cq, normal, face_start)
        return touches, n, gap

    @wp.func
    def within_cone(lam: scalar, pt: vec3, n: vec3, friction: scalar):
        """The impulse of normal part ``lam`` (along ``n``, at least zero) and tangential part ``pt``,
        the tangential part shortened to at most mu times the normal part (Coulomb's cone)."""
        cap = friction * lam
        length = wp.length(pt)
        if length > cap:
            pt = pt * (cap / length)
        return lam * n + pt

    @wp.func
    def accumulated_impulse(
        n: vec3,
        vi: vec3,
        vj: vec3,
        p_old: vec3,
        u0: scalar,
        wi_split: scalar,
        wj_split: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
    ):
        """The pair's impulse on i so far this step after one more iteration (j's is its negative).

        ``n`` is the pair's normal (from j to i), ``vi`` and ``vj`` the two velocities of this
        iteration, ``p_old`` the pair's impulse on i so far (warm start included; zero for a pair
        whose impulse does not accumulate, which then gets this iteration's impulse alone). ``u0``
        is the pair's approach speed before the step, -(vi_prev - vj_prev) . n, and ``wi_split``,
        ``wj_split`` the split inverse masses (inverse mass times the particle's number of
        contacts), which set the pair's effective mass. The impulse cancels the approach (an impact,
        by the same restitution threshold as terrain, leaves at restitution times u0) and the
        tangential slip; the sum's normal part stays a push (at least zero), its tangential part
        within mu times the normal part, so an iteration can take back what an earlier one (or the
        warm start) gave too much. Swapping i and j negates every input vector and so the result,
        exactly: the pair conserves momentum."""
        vrel = vi - vj
        vn = wp.dot(vrel, n)
        m_eff = scalar(1.0) / (wi_split + wj_split)
        target = scalar(0.0)
        if restitution != scalar(0.0):
            w = -vn - u0
            if not (u0 < eps_v or u0 < rest_steps * w):
                target = restitution * u0
        lam_old = wp.dot(p_old, n)
        lam = wp.max(lam_old + (target - vn) * m_eff, scalar(0.0))
        return within_cone(lam, (p_old - lam_old * n) - (vrel - vn * n) * m_eff, n, friction)

    @wp.func
    def warm_impulse(p_prev: vec3, n: vec3, friction: scalar):
        """The last step's impulse of a pair, on its new normal: the push part (zero if it would
        pull), the tangential part within mu times it. Negates exactly with its inputs."""
        lam = wp.dot(p_prev, n)
        p = vec3(scalar(0.0))
        if lam > scalar(0.0):
            p = within_cone(lam, p_prev - lam * n, n, friction)
        return p

    @wp.func
    def cell_of(x: vec3, inv_cell: scalar):
        """Integer cell coordinates of a point, clamped far beyond any scene."""
        lim = scalar(1.0e9)
        return wp.vec3i(
            int(wp.clamp(wp.floor(x[0] * inv_cell), -lim, lim)),
            int(wp.clamp(wp.floor(x[1] * inv_cell), -lim, lim)),
            int(wp.clamp(wp.floor(x[2] * inv_cell), -lim, lim)),
        )

    @wp.func
    def cell_bucket(c: wp.vec3i, world: int, shift: int):
        """Bucket of cell ``c`` of ``world`` in a table of 2^(32 - shift) buckets (Fibonacci hashing
        of the wrapped cell coordinates)."""
        w = CELL_WRAP - 1
        key = wp.uint32((c[0] & w) + CELL_WRAP * ((c[1] & w) + CELL_WRAP * (c[2] & w)))
        key = key ^ (wp.uint32(world) * WORLD_MIX)
        return int((key * FIBONACCI) >> wp.uint32(shift))

    @wp.func
    def is_candidate(
        i: int,
        j: int,
        xi: vec3,
        x_build: wp.array(dtype=vec3),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
    ):
        """Whether j belongs to i's candidate list: an allowed pair closer than CANDIDATE_REACH d +
        skin at the build positions (``xi`` is i's)."""
        if j == i:
            return False
        r = xi - x_build[j]
        reach = scalar(CANDIDATE_REACH) * (contact_radius[i] + contact_radius[j]) + skin
        if wp.dot(r, r) >= reach * reach:
            return False
        return pair_allowed(
            i, j, contact_jelly, contact_world, contact_radius, contact_rest, jelly_self_contact, between_jellies,
            self_exclusion,
        )

    @wp.func
    def next_candidate(
        i: int,
        after: int,
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        x_build: wp.array(dtype=vec3),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
    ):
        """The smallest candidate of i above ``after`` (-1 if none), from the grid: the list of a
        particle with more candidates than it holds, in the list's order (ascending index). It walks
        both tables: the one of the last build, and the other one, which that build emptied."""
        xi = x_build[i]
        c = cell_of(xi, inv_cell)
        world = contact_world[i]
        best = int(-1)
        for cell in range(54):
            table = cell // 27
            o = cell % 27
            b = cell_bucket(wp.vec3i(c[0] + o % 3 - 1, c[1] + (o // 3) % 3 - 1, c[2] + o // 9 - 1), world, shift)
            j = grid_head[table, b]
            while j >= 0:
                if j > after and (best < 0 or j < best):
                    if is_candidate(
                        i, j, xi, x_build, contact_jelly, contact_world, contact_radius, contact_rest,
                        jelly_self_contact, between_jellies, self_exclusion, skin,
                    ):
                        best = j
                j = grid_next[j]
        return best

    @wp.func
    def candidate_after(
        i: int,
        j: int,
        a: int,
        nc: int,
        candidates: wp.array2d(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        x_build: wp.array(dtype=vec3),
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
    ):
        """The candidate of i after candidate j, the a-th (from 0) of i's ``nc`` candidates: from its
        list, or from the grid (:func:`next_candidate`) when the list overflowed (``nc`` above what
        it holds); -1 after the last. The velocity passes' paths for a particle with
        more contacts than its contact list holds visit the candidates through this, in ascending
        order (find, which tests the candidates again only for an overflowed list, walks the grid)."""
        if nc <= candidates.shape[0]:
            if a < nc:
                return candidates[a, i]
            return -1
        return next_candidate(
            i, j, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly, contact_world, contact_radius,
            contact_rest, jelly_self_contact, between_jellies, self_exclusion, skin,
        )

    @wp.kernel(module="unique")
    def prepare_contact_particles(
        contact_index: wp.array(dtype=wp.int32),
        contact_axis_neighbors: wp.array2d(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        x_build: wp.array(dtype=vec3),
        rebuild_distance: scalar,
        # Positions after the step (particle order):
        q: wp.array(dtype=vec3),
        # Out (contact order): positions after the step with the contact radius (:func:`record`:
        # one aligned load gives a partner's position and radius); the outward normals of
        # the particle's boundary faces, in axis order in the first slots (slot-major: a face
        # particle, most of them, writes one slot; the others stay zero from allocation); the
        # rebuild flag, raised when the particle moved too far
        cq_out: wp.array(dtype=vec4),
        normal_out: wp.array2d(dtype=vec3),
        rebuild_out: wp.array(dtype=wp.int32),
        phase: wp.array(dtype=wp.int32),
    ):
        k = wp.tid()
        if k == 0:
            phase[0] = 1 - phase[0]  # this step's half of the contact tables (nothing else here reads it)
        p = ldi(contact_index, k)
        x = ld3(q, p)
        st4(cq_out, k, record(x, lds(contact_radius, k)))
        moved = x - ld3(x_build, k)
        if wp.dot(moved, moved) >= rebuild_distance * rebuild_distance:
            rebuild_out[0] = 1  # every writer writes 1: no race in the result
        # contact_axis_neighbors[:, k] (slot-major) holds the lattice neighbours at -x, +x, -y, +y,
        # -z, +z (the particle itself where there is none) and, in slots 6..8, the inward neighbour
        # of each axis on whose boundary the particle lies (-1 elsewhere). A face's normal is the
        # cross product of its two in-face directions, so a sheared jelly's faces keep their own
        # normal (the inward lattice line tilts with the shear); it is oriented away from the
        # inward neighbour.
        faces = int(0)
        for a in range(3):
            inward = ldi2(contact_axis_neighbors, 6 + a, k)
            if inward >= 0:
                out = x - ld3(q, inward)
                b = (a + 1) % 3
                c = (a + 2) % 3
                tb = ld3(q, ldi2(contact_axis_neighbors, 2 * b + 1, k)) - ld3(q, ldi2(contact_axis_neighbors, 2 * b, k))
                tc = ld3(q, ldi2(contact_axis_neighbors, 2 * c + 1, k)) - ld3(q, ldi2(contact_axis_neighbors, 2 * c, k))
                m = wp.cross(tb, tc)
                if wp.length_sq(m) == scalar(0.0):
                    m = out  # a face one particle wide: the lattice line is all there is
                if wp.dot(m, out) < scalar(0.0):
                    m = -m
                n = vec3(scalar(0.0))
                length = wp.length(m)
                if length > scalar(0.0):
                    n = m / length
                st32(normal_out, faces, k, n)
                faces += 1

    @wp.kernel(module="unique")
    def insert_contact_grid(
        rebuild: wp.array(dtype=wp.int32),
        builds: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        cq: wp.array(dtype=vec4),
        # In and out: each particle's bucket (of the previous build, then of this one), the buckets'
        # first particles (two tables, this build's and the previous one's) and the links
        cell_bucket_io: wp.array(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
    ):
        # Only when the lists are rebuilt. The previous build's table is emptied (each particle
        # clears its old bucket) while this build fills the other one, so no launch empties a
        # table that another fills.
        if rebuild[0] == 0:
            return
        k = wp.tid()
        table = builds[0] % 2
        grid_head[1 - table, cell_bucket_io[k]] = -1
        b = cell_bucket(cell_of(xyz(ld4(cq, k)), inv_cell), contact_world[k], shift)
        cell_bucket_io[k] = b
        grid_next[k] = wp.atomic_exch(grid_head, table, b, k)

    @wp.kernel(module="unique")
    def build_contact_candidates(
        rebuild: wp.array(dtype=wp.int32),
        builds: wp.array(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        # Model:
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
        cq: wp.array(dtype=vec4),
        # Out: the build positions, each particle's candidates (slot-major, ascending) and their
        # number (one more than the list holds: the list overflowed, next_candidate walks the grid)
        x_build_out: wp.array(dtype=vec3),
        candidates_out: wp.array2d(dtype=wp.int32),
        candidate_count_out: wp.array(dtype=wp.int32),
    ):
        if rebuild[0] == 0:
            return
        i = wp.tid()
        xri = ld4(cq, i)
        xi = xyz(xri)
        x_build_out[i] = xi
        table = builds[0] % 2
        c = cell_of(xi, inv_cell)
        world = contact_world[i]
        cap = candidates_out.shape[0]
        n = int(0)
        # One loop over the 27 cells (x fastest), not three nested ones: Warp unrolls a constant
        # loop of up to max_unroll (16) iterations, and three loops of 3 became 27 copies of the
        # bucket walk (216 registers a thread, an eighth of the SM's threads resident).
        for o in range(27):
            b = cell_bucket(wp.vec3i(c[0] + o % 3 - 1, c[1] + (o // 3) % 3 - 1, c[2] + o // 9 - 1), world, shift)
            j = grid_head[table, b]
            while j >= 0:
                # Positions of this build: cq, which x_build holds for i only so far.
                if j != i and n <= cap:
                    xrj = ld4(cq, j)
                    r = xi - xyz(xrj)
                    reach = scalar(CANDIDATE_REACH) * (xri[3] + xrj[3]) + skin
                    if wp.dot(r, r) < reach * reach:
                        if pair_allowed(
                            i, j, contact_jelly, contact_world, contact_radius, contact_rest,
                            jelly_self_contact, between_jellies, self_exclusion,
                        ):
                            # Insert in ascending order; a bucket met twice (two cells
                            # hashed alike) gives the same particle twice: keep one.
                            s = int(0)
                            while s < n:
                                if candidates_out[s, i] >= j:
                                    break
                                s += 1
                            fresh = True
                            if s < n:
                                fresh = candidates_out[s, i] != j
                            if fresh:
                                if n == cap:
                                    n = cap + 1  # overflow: the grid walk takes over
                                else:
                                    t = n
                                    while t > s:
                                        candidates_out[t, i] = candidates_out[t - 1, i]
                                        t -= 1
                                    candidates_out[s, i] = j
                                    n += 1
                j = grid_next[j]
        candidate_count_out[i] = n

    @wp.func
    def store_contact(
        i: int,
        j: int,
        n: vec3,
        gap: scalar,
        p0: vec3,
        count: int,
        row: int,
        contact_index: wp.array(dtype=wp.int32),
        qd_prev: wp.array(dtype=vec3),
        contact_list_out: wp.array2d(dtype=wp.int32),
        contact_impulse_out: wp.array2d(dtype=vec3),
        contact_normal_out: wp.array2d(dtype=vec3),
        contact_gap_out: wp.array2d(dtype=scalar),
        contact_u0_out: wp.array2d(dtype=scalar),
        restitution: scalar,
    ):
        """Touching pair (i, j) into slot ``count`` of i's lists (this step's rows from ``row``, while they
        have room), with its starting impulse ``p0`` and its approach speed before the step from the
        velocities before it (``qd_prev``, particle order); returns the new count. Only a restitution
        above zero reads the approach speed (:func:`accumulated_impulse`): without one it is neither
        computed nor stored."""
        if count < contact_normal_out.shape[0]:
            sti2(contact_list_out, row + count, i, j)
            st32(contact_impulse_out, row + count, i, p0)
            st32(contact_normal_out, count, i, n)
            sts2(contact_gap_out, count, i, gap)
            if restitution != scalar(0.0):
                contact_u0_out[count, i] = -wp.dot(qd_prev[contact_index[i]] - qd_prev[contact_index[j]], n)
        return count + 1

    @wp.func
    def warm_start(
        i: int,
        j: int,
        n: vec3,
        prev_ci: int,
        b: int,
        prev_row: int,
        contact_list: wp.array2d(dtype=wp.int32),
        contact_impulse: wp.array2d(dtype=vec3),
        friction: scalar,
    ):
        """The warm start of touching pair (i, j): its impulse of the last step (:func:`warm_impulse`)
        where i kept its contacts in its list then, else zero. Where j did not (more contacts than
        its list holds), the pair did not accumulate and the velocity passes stored zero for it in
        i's list, so both particles start it from zero without reading j's count. ``b`` walks i's
        last list (ascending, like the new one). Returns (impulse, b)."""
        p = vec3(scalar(0.0))
        if prev_ci <= contact_impulse.shape[0] // 2:
            while b < prev_ci and ldi2(contact_list, prev_row + b, i) < j:
                b += 1
            if b < prev_ci:
                if ldi2(contact_list, prev_row + b, i) == j:
                    p = warm_impulse(ld32(contact_impulse, prev_row + b, i), n, friction)
        return p, b

    @wp.kernel(module="unique")
    def find_particle_contacts(
        # Candidates and the grid behind an overflowed list:
        candidates: wp.array2d(dtype=wp.int32),
        candidate_count: wp.array(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        x_build: wp.array(dtype=vec3),
        # Model:
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
        restitution: scalar,
        friction: scalar,
        phase: wp.array(dtype=wp.int32),
        # Positions and radii (contact order), and the velocities after and before the step
        # (particle order, through contact_index; after it read only for the particles in contact):
        cq: wp.array(dtype=vec4),
        contact_index: wp.array(dtype=wp.int32),
        qd: wp.array(dtype=vec3),
        qd_prev: wp.array(dtype=vec3),
        cw: wp.array(dtype=scalar),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
        # In and out: contacts per particle (this step's half, [phase n:], out; the last step's, in),
        # the contact lists and impulses (this step's rows [phase S:], out; the last step's, in)
        count_out: wp.array(dtype=wp.int32),
        contact_list_out: wp.array2d(dtype=wp.int32),
        contact_impulse_out: wp.array2d(dtype=vec3),
        # Out: the first MAX_CONTACTS contacts' normal, gap, and approach speed before the step;
        # the particle's record for the passes (:func:`record`): [2 i] its velocity after the warm
        # start and its number of contacts, [2 i + 1] its velocity before the response and its
        # inverse mass (one 32-byte block, so a pass reads all it needs of a partner in one sector)
        contact_normal_out: wp.array2d(dtype=vec3),
        contact_gap_out: wp.array2d(dtype=scalar),
        contact_u0_out: wp.array2d(dtype=scalar),
        rec_out: wp.array(dtype=vec4),
    ):
        i = wp.tid()
        cur = phase[0]
        prev = 1 - cur
        slots = contact_normal_out.shape[0]
        n_all = count_out.shape[0] // 2
        row = cur * slots
        prev_row = prev * slots
        prev_ci = ldi(count_out, prev * n_all + i)
        b = int(0)
        warm = vec3(scalar(0.0))
        xri = ld4(cq, i)
        xi = xyz(xri)
        ri = xri[3]
        count = int(0)
        nc = ldi(candidate_count, i)
        if nc <= candidates.shape[0]:
            # Two loops: the cheap distance test of every candidate first, then the contact normal
            # and gap of the near ones only (about 2 of 5 in a pile). A warp then runs the costly
            # test as often as its lanes have near candidates, not as often as they have candidates.
            near = int(0)
            near_count = int(0)
            for a in range(nc):
                if near_pair(ldi2(candidates, a, i), xi, ri, cq):
                    near = near | (1 << a)
                    near_count += 1
            # Iteration k takes each lane's k-th near candidate (in ascending order).
            a = int(0)
            for _k in range(near_count):
                while ((near >> a) & 1) == 0:
                    a += 1
                j = ldi2(candidates, a, i)
                a += 1
                touches, n, gap = touching_pair(i, j, xi, ri, cq, normal, face_start)
                if touches:
                    p0, b = warm_start(
                        i, j, n, prev_ci, b, prev_row, contact_list_out, contact_impulse_out, friction
                    )
                    warm = warm + p0
                    count = store_contact(
                        i, j, n, gap, p0, count, row, contact_index, qd_prev, contact_list_out, contact_impulse_out,
                        contact_normal_out, contact_gap_out, contact_u0_out, restitution,
                    )
        else:
            # The list overflowed: the grid walk.
            j = int(-1)
            while True:
                j = next_candidate(
                    i, j, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly, contact_world,
                    contact_radius, contact_rest, jelly_self_contact, between_jellies, self_exclusion, skin,
                )
                if j < 0:
                    break
                touches, n, gap = pair_contact(i, j, xi, ri, cq, normal, face_start)
                if touches:
                    p0, b = warm_start(
                        i, j, n, prev_ci, b, prev_row, contact_list_out, contact_impulse_out, friction
                    )
                    warm = warm + p0
                    count = store_contact(
                        i, j, n, gap, p0, count, row, contact_index, qd_prev, contact_list_out, contact_impulse_out,
                        contact_normal_out, contact_gap_out, contact_u0_out, restitution,
                    )
        count_out[cur * n_all + i] = count
        if count > 0:
            wi = lds(cw, i)
            v0 = ld3(qd, ldi(contact_index, i))
            st4(rec_out, 2 * i, record(v0 + wi * warm, scalar(count)))
            st4(rec_out, 2 * i + 1, record(v0, wi))

    @wp.func
    def retested_pair(
        i: int,
        j: int,
        xi: vec3,
        ri: scalar,
        vi: vec3,
        vi_prev: vec3,
        wi_split: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        cq: wp.array(dtype=vec4),
        contact_index: wp.array(dtype=wp.int32),
        qd_prev: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
        rec: wp.array(dtype=vec4),
    ):
        """Candidate j of i in a pass, tested afresh: for a particle with more contacts than its list
        holds, whose pairs take each pass's impulse alone. Returns (acts: they touch and can move,
        normal, gap, j's two record entries, the pair's impulse on i: zero unless it acts)."""
        touches, n, gap = pair_contact(i, j, xi, ri, cq, normal, face_start)
        acts = False
        rj = vec4(scalar(0.0))
        rj0 = vec4(scalar(0.0))
        p = vec3(scalar(0.0))
        if touches:
            rj = ld4(rec, 2 * j)
            rj0 = ld4(rec, 2 * j + 1)
            wj_split = split_mass(rj, rj0)
            if wi_split + wj_split > scalar(0.0):
                acts = True
                u0 = -wp.dot(vi_prev - qd_prev[contact_index[j]], n)
                p = accumulated_impulse(
                    n, vi, xyz(rj), vec3(scalar(0.0)), u0, wi_split, wj_split, friction, restitution, eps_v,
                    rest_steps,
                )
        return acts, n, gap, rj, rj0, p

    @wp.func
    def listed_impulse(
        i: int,
        a: int,
        row: int,
        slots: int,
        n: vec3,
        vi: vec3,
        rj: vec4,
        wi_split: scalar,
        wj_split: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        contact_u0: wp.array2d(dtype=scalar),
        contact_impulse: wp.array2d(dtype=vec3),
    ):
        """This pass's impulse on i of its a-th listed contact (normal ``n``, partner's record entry
        ``rj``), with the pair's impulse so far updated in ``contact_impulse[row + a, i]``. Where both
        keep the pair in their lists (the partner's count, ``rj[3]``, at most ``slots``) its impulse
        accumulates (warm started); otherwise the pair takes this pass's impulse alone, and zero is
        stored, so that the next step starts it from zero (:func:`warm_start`)."""
        u0 = scalar(0.0)
        if restitution != scalar(0.0):
            u0 = contact_u0[a, i]  # stored by find only with a restitution (store_contact)
        accumulates = rj[3] <= scalar(slots)
        p_old = vec3(scalar(0.0))
        if accumulates:
            p_old = ld32(contact_impulse, row + a, i)
        p_new = accumulated_impulse(
            n, vi, xyz(rj), p_old, u0, wi_split, wj_split, friction, restitution, eps_v, rest_steps
        )
        st32(contact_impulse, row + a, i, wp.where(accumulates, p_new, vec3(scalar(0.0))))
        return p_new - p_old

    @wp.kernel(module="unique")
    def resolve_contact_velocities(
        # Candidates and the grid behind an overflowed list:
        candidates: wp.array2d(dtype=wp.int32),
        candidate_count: wp.array(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        x_build: wp.array(dtype=vec3),
        # Model:
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        # State and contacts (contact order; the velocities before the step in particle order):
        cq: wp.array(dtype=vec4),
        contact_index: wp.array(dtype=wp.int32),
        qd_prev: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
        count: wp.array(dtype=wp.int32),
        contact_list: wp.array2d(dtype=wp.int32),
        contact_normal: wp.array2d(dtype=vec3),
        contact_u0: wp.array2d(dtype=scalar),
        phase: wp.array(dtype=wp.int32),
        # The records of this iteration (velocities; see find_particle_contacts)
        rec: wp.array(dtype=vec4),
        # In and out: the impulses of the contacts so far (this step's rows)
        contact_impulse: wp.array2d(dtype=vec3),
        # Out: the records after this iteration's impulses (contact order)
        rec_out: wp.array(dtype=vec4),
    ):
        i = wp.tid()
        cur = phase[0]
        slots = contact_normal.shape[0]
        n_all = count.shape[0] // 2
        ci = ldi(count, cur * n_all + i)
        if ci == 0:
            # Nothing reads a velocity of a particle without contacts from these buffers: its
            # partners would be in contact with it, and the last pass leaves it alone.
            return
        ri = ld4(rec, 2 * i)
        ri0 = ld4(rec, 2 * i + 1)
        vi = xyz(ri)
        wi = ri0[3]
        wi_split = split_mass(ri, ri0)
        impulse = vec3(scalar(0.0))
        if ci <= slots:
            for a in range(ci):
                j = ldi2(contact_list, cur * slots + a, i)
                rj = ld4(rec, 2 * j)
                wj_split = split_mass(rj, ld4(rec, 2 * j + 1))
                if wi_split + wj_split > scalar(0.0):
                    impulse = impulse + listed_impulse(
                        i, a, cur * slots, slots, ld32(contact_normal, a, i), vi, rj, wi_split, wj_split, friction,
                        restitution, eps_v, rest_steps, contact_u0, contact_impulse,
                    )
        else:
            # More contacts than the list holds: the candidates again, in the same order.
            xri = ld4(cq, i)
            vi_prev = qd_prev[contact_index[i]]
            nc = candidate_count[i]
            j = int(-1)
            a = int(0)
            while True:
                j = candidate_after(
                    i, j, a, nc, candidates, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly,
                    contact_world, contact_radius, contact_rest, jelly_self_contact, between_jellies,
                    self_exclusion, skin,
                )
                a += 1
                if j < 0:
                    break
                _acts, _n, _gap, _rj, _rj0, p = retested_pair(
                    i, j, xyz(xri), xri[3], vi, vi_prev, wi_split, friction, restitution, eps_v, rest_steps,
                    cq, contact_index, qd_prev, normal, face_start, rec,
                )
                impulse = impulse + p
        st4(rec_out, 2 * i, record(vi + wi * impulse, ri[3]))
        st4(rec_out, 2 * i + 1, ri0)

    @wp.func
    def projection_term(
        n: vec3,
        gap: scalar,
        dp: vec3,
        vi: vec3,
        vj: vec3,
        vi0: vec3,
        vj0: vec3,
        wi: scalar,
        wj: scalar,
        split: scalar,
        beta_h: scalar,
        h: scalar,
        friction: scalar,
    ):
        """Position and velocity change of i from touching pair (i, j) after the last pass: (dx, dv).

        ``dp`` is the pair's impulse on i in this pass, ``vi``, ``vj`` the velocities the pass
        started from and ``vi0``, ``vj0`` those before the contact response (so ``v - v0`` is what
        the impulses changed); ``wi``, ``wj`` the inverse masses, ``split`` the pair's split inverse
        mass. The pair estimates the two velocities after the pass from its own impulse,
        ``vi + wi dp`` and ``vj - wj dp`` (the partner's other pairs act in the same launch, unseen),
        and so the gap after the positions move by beta h dv. The overlap left is projected out
        along the normal, split like the impulses (positions only: no momentum). The approach
        velocity left is taken off up to the projected distance per step, with Coulomb friction up
        to mu times it (a normal impulse, as in the iterations): a pressed particle does not keep a
        velocity it never moves by. Swapping i and j negates ``n``, ``dp``, the dv impulse and dx's
        direction and keeps the gap: the pair's dv conserves momentum exactly."""
        dx = vec3(scalar(0.0))
        dv = vec3(scalar(0.0))
        vie = vi + wi * dp
        vje = vj - wj * dp
        moved = gap + beta_h * wp.dot((vie - vi0) - (vje - vj0), n)
        if moved < scalar(0.0):
            dx = (-moved * wi / split) * n
            vrel = vie - vje
            vn = wp.dot(vrel, n)
            if vn < scalar(0.0):
                jn = wp.min(-vn, -moved / h)
                dv = within_cone(jn, -(vrel - vn * n), n, friction) * (wi / split)
        return dx, dv

    @wp.kernel(module="unique")
    def resolve_contact_last_pass(
        # Candidates and the grid behind an overflowed list:
        candidates: wp.array2d(dtype=wp.int32),
        candidate_count: wp.array(dtype=wp.int32),
        grid_head: wp.array2d(dtype=wp.int32),
        grid_next: wp.array(dtype=wp.int32),
        inv_cell: scalar,
        shift: int,
        x_build: wp.array(dtype=vec3),
        # Model:
        contact_jelly: wp.array(dtype=wp.int32),
        contact_world: wp.array(dtype=wp.int32),
        contact_radius: wp.array(dtype=scalar),
        contact_rest: wp.array(dtype=vec3),
        jelly_self_contact: wp.array(dtype=wp.int32),
        between_jellies: int,
        self_exclusion: scalar,
        skin: scalar,
        friction: scalar,
        restitution: scalar,
        eps_v: scalar,
        rest_steps: scalar,
        h: scalar,
        world_contact_beta: wp.array(dtype=scalar),
        # State and contacts (contact order; the velocities before the step in particle order):
        cq: wp.array(dtype=vec4),
        contact_index: wp.array(dtype=wp.int32),
        qd_prev: wp.array(dtype=vec3),
        normal: wp.array2d(dtype=vec3),
        face_start: wp.vec3i,
        count: wp.array(dtype=wp.int32),
        contact_list: wp.array2d(dtype=wp.int32),
        contact_normal: wp.array2d(dtype=vec3),
        contact_gap: wp.array2d(dtype=scalar),
        contact_u0: wp.array2d(dtype=scalar),
        phase: wp.array(dtype=wp.int32),
        # The records this pass starts from (the velocities before the contact response and those
        # of this pass; see find_particle_contacts)
        rec: wp.array(dtype=vec4),
        # In and out: the impulses of the contacts so far (this step's rows), the rebuild flag
        # (lowered) and the count of builds (one more after a build)
        contact_impulse: wp.array2d(dtype=vec3),
        rebuild: wp.array(dtype=wp.int32),
        builds: wp.array(dtype=wp.int32),
        # Out: the step's result, corrected in place (each thread writes its own particle only)
        q_out: wp.array(dtype=vec3),
        qd_out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        if i == 0 and rebuild[0] != 0:
            # No other thread of this launch reads these two (the grid walk reads both tables).
            builds[0] = builds[0] + 1
            rebuild[0] = 0
        cur = phase[0]
        slots = contact_normal.shape[0]
        n_all = count.shape[0] // 2
        ci = ldi(count, cur * n_all + i)
        if ci == 0:
            # Nothing to correct: the step's result stays as the integrator (and terrain) left it.
            return
        ri = ld4(rec, 2 * i)
        ri0 = ld4(rec, 2 * i + 1)
        vi = xyz(ri)
        vi0 = xyz(ri0)
        wi = ri0[3]
        wi_split = split_mass(ri, ri0)
        # The impulses act over the whole step: positions move by what the integrator makes of a
        # velocity change, beta h dv (as for terrain, kernels/contact.py).
        beta_h = h * world_contact_beta[contact_world[i]]
        impulse = vec3(scalar(0.0))
        dx = vec3(scalar(0.0))
        dv = vec3(scalar(0.0))
        if ci <= slots:
            for a in range(ci):
                j = ldi2(contact_list, cur * slots + a, i)
                rj = ld4(rec, 2 * j)  # the partner's two entries: one 32-byte block
                rj0 = ld4(rec, 2 * j + 1)
                wj = rj0[3]
                wj_split = split_mass(rj, rj0)
                split = wi_split + wj_split
                if split > scalar(0.0):
                    n = ld32(contact_normal, a, i)
                    dp = listed_impulse(
                        i, a, cur * slots, slots, n, vi, rj, wi_split, wj_split, friction, restitution, eps_v,
                        rest_steps, contact_u0, contact_impulse,
                    )
                    impulse = impulse + dp
                    ddx, ddv = projection_term(
                        n, lds2(contact_gap, a, i), dp, vi, xyz(rj), vi0, xyz(rj0), wi, wj, split, beta_h, h,
                        friction,
                    )
                    dx = dx + ddx
                    dv = dv + ddv
        else:
            # More contacts than the list holds: the candidates again, in the same order, each
            # pair's impulse this pass's alone.
            xri = ld4(cq, i)
            vi_prev = qd_prev[contact_index[i]]
            nc = candidate_count[i]
            j = int(-1)
            a = int(0)
            while True:
                j = candidate_after(
                    i, j, a, nc, candidates, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly,
                    contact_world, contact_radius, contact_rest, jelly_self_contact, between_jellies,
                    self_exclusion, skin,
                )
                a += 1
                if j < 0:
                    break
                acts, n, gap, rj, rj0, dp = retested_pair(
                    i, j, xyz(xri), xri[3], vi, vi_prev, wi_split, friction, restitution, eps_v, rest_steps,
                    cq, contact_index, qd_prev, normal, face_start, rec,
                )
                if acts:
                    impulse = impulse + dp
                    ddx, ddv = projection_term(
                        n, gap, dp, vi, xyz(rj), vi0, xyz(rj0), wi, rj0[3], wi_split + split_mass(rj, rj0), beta_h, h,
                        friction,
                    )
                    dx = dx + ddx
                    dv = dv + ddv
        v_new = vi + wi * impulse
        p = ldi(contact_index, i)
        st3(q_out, p, xyz(ld4(cq, i)) + beta_h * (v_new - vi0) + dx)
        st3(qd_out, p, v_new + dv)

    return {
        "pair_allowed": pair_allowed,
        "pair_contact": pair_contact,
        "facing_normal": facing_normal,
        "pair_normal": pair_normal,
        "accumulated_impulse": accumulated_impulse,
        "prepare_contact_particles": prepare_contact_particles,
        "insert_contact_grid": insert_contact_grid,
        "build_contact_candidates": build_contact_candidates,
        "find_particle_contacts": find_particle_contacts,
        "resolve_contact_velocities": resolve_contact_velocities,
        "resolve_contact_last_pass": resolve_contact_last_pass,
    }
