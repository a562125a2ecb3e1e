"""Candidate search: each step's contact spheres and face normals, and each particle's candidate
list, rebuilt through a hashed cell grid when a particle has moved far enough.

A candidate list holds the particles of other jellies (or of the particle's own jelly, with
self-contact, far enough apart in the rest shape) of its world within CANDIDATE_REACH d plus a skin
at the build, in ascending index order. The grid is built with atomics, so the order within a cell
varies on CUDA; the lists are sorted, so nothing downstream sees it. A particle with more
candidates than its list holds walks the grid of the last build instead (:func:`next_candidate`),
in the same order.
"""

import warp as wp

from ..integration import int_contiguous, load_contiguous, scalar_contiguous
from ..precision import Float, both_precisions, vec3
from .pairs import CANDIDATE_REACH, pair_allowed
from .tables import int_entry, load_vec4, record, record_vector, set_vec3_entry, store_vec4, vec4

wp.set_module_options({"enable_backward": False})

# Cells per axis before the cell coordinates wrap in the grid's hash (a wrapped cell only adds
# particles that the distance test rejects).
CELL_WRAP = wp.constant(1024)
# Multipliers of the grid's hash: the world's (a 32-bit mix constant) and Fibonacci hashing's
# (2^32 / golden ratio), whose product's top bits are the bucket.
WORLD_MIX = wp.constant(wp.uint32(0x85EBCA6B))
FIBONACCI = wp.constant(wp.uint32(0x9E3779B9))


@wp.func
def cell_of(x: vec3, inv_cell: Float):
    """Integer cell coordinates of a point, clamped far beyond any scene."""
    lim = type(inv_cell)(1.0e9)
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
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
):
    """Whether j belongs to i's candidate list: an allowed pair closer than CANDIDATE_REACH d +
    skin at the build positions (``xi`` is i's)."""
    if j == i:
        return False
    r = xi - x_build[j]
    reach = type(skin)(CANDIDATE_REACH) * (contact_radius[i] + contact_radius[j]) + skin
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
    inv_cell: Float,
    shift: int,
    x_build: wp.array(dtype=vec3),
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
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
    candidate_total: int,
    candidates: wp.array2d(dtype=wp.int32),
    grid_head: wp.array2d(dtype=wp.int32),
    grid_next: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    x_build: wp.array(dtype=vec3),
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
):
    """The candidate of i after candidate j, the a-th (from 0) of i's ``candidate_total``
    candidates: from its list, or from the grid (:func:`next_candidate`) when the list overflowed
    (``candidate_total`` above what it holds); -1 after the last. The velocity passes' paths for a
    particle with more contacts than its contact list holds visit the candidates through this, in
    ascending order (find, which tests the candidates again only for an overflowed list, walks the
    grid)."""
    if candidate_total <= candidates.shape[0]:
        if a < candidate_total:
            return candidates[a, i]
        return -1
    return next_candidate(
        i, j, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly, contact_world, contact_radius,
        contact_rest, jelly_self_contact, between_jellies, self_exclusion, skin,
    )


@wp.func
def lattice_direction(q: wp.array(dtype=vec3), contact_axis_neighbors: wp.array2d(dtype=wp.int32), axis: int, k: int):
    """The lattice line through contact particle k along ``axis``: its neighbour at + minus its
    neighbour at - (the particle itself where it has none; see prepare_contact_particles)."""
    plus = load_contiguous(q, int_entry(contact_axis_neighbors, 2 * axis + 1, k))
    return plus - load_contiguous(q, int_entry(contact_axis_neighbors, 2 * axis, k))


@both_precisions
@wp.kernel(module="unique")
def prepare_contact_particles(
    contact_index: wp.array(dtype=wp.int32),
    contact_axis_neighbors: wp.array2d(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    x_build: wp.array(dtype=vec3),
    rebuild_distance: Float,
    # Positions after the step (particle order):
    q: wp.array(dtype=vec3),
    # Out (contact order): the contact spheres, positions after the step with the contact radius
    # (:func:`record`: one aligned load gives a partner's position and radius); the outward normals
    # of the particle's boundary faces, in axis order in the first slots (slot-major: a face
    # particle, most of them, writes one slot; the others stay zero from allocation); the
    # rebuild flag, raised when the particle moved too far
    spheres_out: wp.array(dtype=vec4),
    normal_out: wp.array2d(dtype=vec3),
    rebuild_out: wp.array(dtype=wp.int32),
    phase: wp.array(dtype=wp.int32),
):
    k = wp.tid()
    if k == 0:
        phase[0] = 1 - phase[0]  # this step's half of the contact tables (nothing else here reads it)
    p = int_contiguous(contact_index, k)
    x = load_contiguous(q, p)
    store_vec4(spheres_out, k, record(x, scalar_contiguous(contact_radius, k)))
    moved = x - load_contiguous(x_build, k)
    if wp.dot(moved, moved) >= rebuild_distance * rebuild_distance:
        rebuild_out[0] = 1  # every writer writes 1: no race in the result
    # contact_axis_neighbors[:, k] (slot-major) holds the lattice neighbours at -x, +x, -y, +y,
    # -z, +z (the particle itself where there is none) and, in slots 6..8, the inward neighbour
    # of each axis on whose boundary the particle lies (-1 elsewhere). A face's normal is the
    # cross product of its two in-face directions, so a sheared jelly's faces keep their own
    # normal (the inward lattice line tilts with the shear); it is oriented away from the
    # inward neighbour.
    zero = type(rebuild_distance)(0.0)
    faces = int(0)
    for a in range(3):
        inward = int_entry(contact_axis_neighbors, 6 + a, k)
        if inward >= 0:
            out = x - load_contiguous(q, inward)
            b = (a + 1) % 3
            c = (a + 2) % 3
            tb = lattice_direction(q, contact_axis_neighbors, b, k)
            tc = lattice_direction(q, contact_axis_neighbors, c, k)
            m = wp.cross(tb, tc)
            if wp.length_sq(m) == zero:
                m = out  # a face one particle wide: the lattice line is all there is
            if wp.dot(m, out) < zero:
                m = -m
            n = type(x)(zero)
            length = wp.length(m)
            if length > zero:
                n = m / length
            set_vec3_entry(normal_out, faces, k, n)
            faces += 1


@both_precisions
@wp.kernel(module="unique")
def insert_contact_grid(
    rebuild: wp.array(dtype=wp.int32),
    builds: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    spheres: wp.array(dtype=vec4),
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
    b = cell_bucket(cell_of(record_vector(load_vec4(spheres, k)), inv_cell), contact_world[k], shift)
    cell_bucket_io[k] = b
    grid_next[k] = wp.atomic_exch(grid_head, table, b, k)


@both_precisions
@wp.kernel(module="unique")
def build_contact_candidates(
    rebuild: wp.array(dtype=wp.int32),
    builds: wp.array(dtype=wp.int32),
    grid_head: wp.array2d(dtype=wp.int32),
    grid_next: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    # Model:
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
    spheres: wp.array(dtype=vec4),
    # Out: the build positions, each particle's candidates (slot-major, ascending) and their
    # number (one more than the list holds: the list overflowed, next_candidate walks the grid)
    x_build_out: wp.array(dtype=vec3),
    candidates_out: wp.array2d(dtype=wp.int32),
    candidate_count_out: wp.array(dtype=wp.int32),
):
    if rebuild[0] == 0:
        return
    i = wp.tid()
    sphere_i = load_vec4(spheres, i)
    xi = record_vector(sphere_i)
    x_build_out[i] = xi
    table = builds[0] % 2
    c = cell_of(xi, inv_cell)
    world = contact_world[i]
    cap = candidates_out.shape[0]
    n = int(0)
    # One loop over the 27 cells (x fastest), not three nested ones: Warp unrolls a constant
    # loop of up to max_unroll (16) iterations, and three loops of 3 would become 27 copies of the
    # bucket walk (many more registers a thread, fewer threads resident).
    for o in range(27):
        b = cell_bucket(wp.vec3i(c[0] + o % 3 - 1, c[1] + (o // 3) % 3 - 1, c[2] + o // 9 - 1), world, shift)
        j = grid_head[table, b]
        while j >= 0:
            # Positions of this build: the spheres, which x_build holds for i only so far.
            if j != i and n <= cap:
                sphere_j = load_vec4(spheres, j)
                r = xi - record_vector(sphere_j)
                reach = type(skin)(CANDIDATE_REACH) * (sphere_i[3] + sphere_j[3]) + skin
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
