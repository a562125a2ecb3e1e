"""Contact response: each step's touching pairs found among the candidates, their impulses
accumulated over Jacobi iterations, and the positions and velocities written back.

Each thread writes only its own particle (no atomics in the response) and visits its contacts in
ascending index order of the partner, whatever the grid's or the threads' order: the sum is the
same on every run and device, and it does not depend on when the lists were last built.

The passes exchange velocities through records, two vec4 per contact particle
(:func:`~.tables.record`): ``[2 i]`` its velocity so far this step and its number of contacts,
``[2 i + 1]`` its velocity before the response and its inverse mass. The two entries are one
32-byte block in float32, so a pass reads all it needs of a partner in one memory sector.

Contact tables come in two halves, this step's and the last step's (``phase`` says which is this
step's), so a pair found again starts from its impulse of the last step (the warm start).
"""

import warp as wp

from ..integration import entry_contiguous, int_contiguous, load_contiguous, scalar_contiguous, store_contiguous
from ..precision import Float, both_precisions, vec3
from .candidates import candidate_after, next_candidate
from .pairs import (
    accumulated_impulse,
    near_pair,
    pair_contact,
    projection_term,
    touching_pair,
    warm_impulse,
)
from .tables import (
    int_entry,
    load_vec4,
    record,
    record_vector,
    set_int_entry,
    set_scalar_entry,
    set_vec3_entry,
    split_inv_mass,
    store_vec4,
    vec3_entry,
    vec4,
)

wp.set_module_options({"enable_backward": False})


@wp.func
def store_contact(
    i: int,
    j: int,
    n: vec3,
    gap: Float,
    p0: vec3,
    count: int,
    row: int,
    contact_index: wp.array(dtype=wp.int32),
    qd_prev: wp.array(dtype=vec3),
    contact_list_out: wp.array2d(dtype=wp.int32),
    contact_impulse_out: wp.array2d(dtype=vec3),
    contact_normal_out: wp.array2d(dtype=vec3),
    contact_gap_out: wp.array2d(dtype=Float),
    contact_u0_out: wp.array2d(dtype=Float),
    restitution: Float,
):
    """Touching pair (i, j) into slot ``count`` of i's lists (this step's rows from ``row``, while they
    have room), with its starting impulse ``p0`` and its approach speed before the step from the
    velocities before it (``qd_prev``, particle order); returns the new count. Only a restitution
    above zero reads the approach speed (:func:`~.pairs.accumulated_impulse`): without one it is
    neither computed nor stored."""
    if count < contact_normal_out.shape[0]:
        set_int_entry(contact_list_out, row + count, i, j)
        set_vec3_entry(contact_impulse_out, row + count, i, p0)
        set_vec3_entry(contact_normal_out, count, i, n)
        set_scalar_entry(contact_gap_out, count, i, gap)
        if restitution != type(restitution)(0.0):
            contact_u0_out[count, i] = -wp.dot(qd_prev[contact_index[i]] - qd_prev[contact_index[j]], n)
    return count + 1


@wp.func
def warm_start(
    i: int,
    j: int,
    n: vec3,
    prev_contacts: int,
    b: int,
    prev_row: int,
    contact_list: wp.array2d(dtype=wp.int32),
    contact_impulse: wp.array2d(dtype=vec3),
    friction: Float,
):
    """The warm start of touching pair (i, j): its impulse of the last step
    (:func:`~.pairs.warm_impulse`) where i kept its ``prev_contacts`` contacts in its list then,
    else zero. Where j did not (more contacts than its list holds), the pair did not accumulate and
    the velocity passes stored zero for it in i's list, so both particles start it from zero
    without reading j's count. ``b`` walks i's last list (ascending, like the new one). Returns
    (impulse, b)."""
    p = type(n)(type(friction)(0.0))
    if prev_contacts <= contact_impulse.shape[0] // 2:
        while b < prev_contacts and int_entry(contact_list, prev_row + b, i) < j:
            b += 1
        if b < prev_contacts:
            if int_entry(contact_list, prev_row + b, i) == j:
                p = warm_impulse(vec3_entry(contact_impulse, prev_row + b, i), n, friction)
    return p, b


@both_precisions
@wp.kernel(module="unique")
def find_particle_contacts(
    # Candidates and the grid behind an overflowed list:
    candidates: wp.array2d(dtype=wp.int32),
    candidate_count: wp.array(dtype=wp.int32),
    grid_head: wp.array2d(dtype=wp.int32),
    grid_next: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    x_build: wp.array(dtype=vec3),
    # Model:
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
    restitution: Float,
    friction: Float,
    phase: wp.array(dtype=wp.int32),
    # Contact spheres (contact order), and the velocities after and before the step (particle
    # order, through contact_index; after it read only for the particles in contact), the inverse
    # masses (contact order) and the boundary-face normals:
    spheres: wp.array(dtype=vec4),
    contact_index: wp.array(dtype=wp.int32),
    qd: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    contact_inv_mass: wp.array(dtype=Float),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
    # In and out: contacts per particle (this step's half, [phase n:], out; the last step's, in),
    # the contact lists and impulses (this step's rows [phase S:], out; the last step's, in)
    count_out: wp.array(dtype=wp.int32),
    contact_list_out: wp.array2d(dtype=wp.int32),
    contact_impulse_out: wp.array2d(dtype=vec3),
    # Out: the first MAX_CONTACTS contacts' normal, gap, and approach speed before the step; the
    # particle's two records for the passes: its velocity after the warm start with its number of
    # contacts, and its velocity before the response with its inverse mass
    contact_normal_out: wp.array2d(dtype=vec3),
    contact_gap_out: wp.array2d(dtype=Float),
    contact_u0_out: wp.array2d(dtype=Float),
    records_out: wp.array(dtype=vec4),
):
    i = wp.tid()
    half = phase[0]
    prev = 1 - half
    slots = contact_normal_out.shape[0]
    n_all = count_out.shape[0] // 2
    row = half * slots
    prev_row = prev * slots
    prev_contacts = int_contiguous(count_out, prev * n_all + i)
    b = int(0)
    sphere_i = load_vec4(spheres, i)
    xi = record_vector(sphere_i)
    ri = sphere_i[3]
    warm = type(xi)(type(ri)(0.0))
    count = int(0)
    candidate_total = int_contiguous(candidate_count, i)
    if candidate_total <= candidates.shape[0]:
        # Two loops: the cheap distance test of every candidate first, then the contact normal
        # and gap of the near ones only (about 2 of 5 in a pile). A warp then runs the costly
        # test as often as its lanes have near candidates, not as often as they have candidates.
        near = int(0)
        near_count = int(0)
        for a in range(candidate_total):
            if near_pair(int_entry(candidates, a, i), xi, ri, spheres):
                near = near | (1 << a)
                near_count += 1
        # Iteration k takes each lane's k-th near candidate (in ascending order).
        a = int(0)
        for _k in range(near_count):
            while ((near >> a) & 1) == 0:
                a += 1
            j = int_entry(candidates, a, i)
            a += 1
            touches, n, gap = touching_pair(i, j, xi, ri, spheres, normal, face_start)
            if touches:
                p0, b = warm_start(i, j, n, prev_contacts, b, prev_row, contact_list_out, contact_impulse_out, friction)
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
            touches, n, gap = pair_contact(i, j, xi, ri, spheres, normal, face_start)
            if touches:
                p0, b = warm_start(i, j, n, prev_contacts, b, prev_row, contact_list_out, contact_impulse_out, friction)
                warm = warm + p0
                count = store_contact(
                    i, j, n, gap, p0, count, row, contact_index, qd_prev, contact_list_out, contact_impulse_out,
                    contact_normal_out, contact_gap_out, contact_u0_out, restitution,
                )
    count_out[half * n_all + i] = count
    if count > 0:
        wi = scalar_contiguous(contact_inv_mass, i)
        v0 = load_contiguous(qd, int_contiguous(contact_index, i))
        store_vec4(records_out, 2 * i, record(v0 + wi * warm, type(wi)(count)))
        store_vec4(records_out, 2 * i + 1, record(v0, wi))


@wp.func
def retested_pair(
    i: int,
    j: int,
    xi: vec3,
    ri: Float,
    vi: vec3,
    vi_prev: vec3,
    wi_split: Float,
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
    spheres: wp.array(dtype=vec4),
    contact_index: wp.array(dtype=wp.int32),
    qd_prev: wp.array(dtype=vec3),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
    records: wp.array(dtype=vec4),
):
    """Candidate j of i in a pass, tested afresh: for a particle with more contacts than its list
    holds, whose pairs take each pass's impulse alone. Returns (acts: they touch and can move,
    normal, gap, j's two record entries, the pair's impulse on i: zero unless it acts)."""
    zero = type(ri)(0.0)
    touches, n, gap = pair_contact(i, j, xi, ri, spheres, normal, face_start)
    acts = False
    current_j = wp.vector(zero, zero, zero, zero)
    initial_j = wp.vector(zero, zero, zero, zero)
    p = type(xi)(zero)
    if touches:
        current_j = load_vec4(records, 2 * j)
        initial_j = load_vec4(records, 2 * j + 1)
        wj_split = split_inv_mass(current_j, initial_j)
        if wi_split + wj_split > zero:
            acts = True
            u0 = -wp.dot(vi_prev - qd_prev[contact_index[j]], n)
            p = accumulated_impulse(
                n, vi, record_vector(current_j), type(xi)(zero), u0, wi_split, wj_split, friction, restitution, eps_v,
                rest_steps,
            )
    return acts, n, gap, current_j, initial_j, p


@wp.func
def listed_impulse(
    i: int,
    a: int,
    row: int,
    slots: int,
    n: vec3,
    vi: vec3,
    current_j: vec4,
    wi_split: Float,
    wj_split: Float,
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
    contact_u0: wp.array2d(dtype=Float),
    contact_impulse: wp.array2d(dtype=vec3),
):
    """This pass's impulse on i of its a-th listed contact (normal ``n``, partner's record entry
    ``current_j``), with the pair's impulse so far updated in ``contact_impulse[row + a, i]``.
    Where both keep the pair in their lists (the partner's count, ``current_j[3]``, at most
    ``slots``) its impulse accumulates (warm started); otherwise the pair takes this pass's
    impulse alone, and zero is stored, so that the next step starts it from zero
    (:func:`warm_start`)."""
    zero = type(wi_split)(0.0)
    u0 = zero
    if restitution != zero:
        u0 = contact_u0[a, i]  # stored by find only with a restitution (store_contact)
    accumulates = current_j[3] <= type(wi_split)(slots)
    p_old = type(n)(zero)
    if accumulates:
        p_old = vec3_entry(contact_impulse, row + a, i)
    p_new = accumulated_impulse(
        n, vi, record_vector(current_j), p_old, u0, wi_split, wj_split, friction, restitution, eps_v, rest_steps
    )
    set_vec3_entry(contact_impulse, row + a, i, wp.where(accumulates, p_new, type(n)(zero)))
    return p_new - p_old


@both_precisions
@wp.kernel(module="unique")
def resolve_contact_velocities(
    # Candidates and the grid behind an overflowed list:
    candidates: wp.array2d(dtype=wp.int32),
    candidate_count: wp.array(dtype=wp.int32),
    grid_head: wp.array2d(dtype=wp.int32),
    grid_next: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    x_build: wp.array(dtype=vec3),
    # Model:
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
    # State and contacts (contact order; the velocities before the step in particle order):
    spheres: wp.array(dtype=vec4),
    contact_index: wp.array(dtype=wp.int32),
    qd_prev: wp.array(dtype=vec3),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
    count: wp.array(dtype=wp.int32),
    contact_list: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=vec3),
    contact_u0: wp.array2d(dtype=Float),
    phase: wp.array(dtype=wp.int32),
    # The records of this iteration (velocities; see find_particle_contacts)
    records: wp.array(dtype=vec4),
    # In and out: the impulses of the contacts so far (this step's rows)
    contact_impulse: wp.array2d(dtype=vec3),
    # Out: the records after this iteration's impulses (contact order)
    records_out: wp.array(dtype=vec4),
):
    i = wp.tid()
    half = phase[0]
    slots = contact_normal.shape[0]
    n_all = count.shape[0] // 2
    contacts_i = int_contiguous(count, half * n_all + i)
    if contacts_i == 0:
        # Nothing reads a velocity of a particle without contacts from these buffers: its
        # partners would be in contact with it, and the last pass leaves it alone.
        return
    zero = type(skin)(0.0)
    current_i = load_vec4(records, 2 * i)
    initial_i = load_vec4(records, 2 * i + 1)
    vi = record_vector(current_i)
    wi = initial_i[3]
    wi_split = split_inv_mass(current_i, initial_i)
    impulse = type(vi)(zero)
    if contacts_i <= slots:
        for a in range(contacts_i):
            j = int_entry(contact_list, half * slots + a, i)
            current_j = load_vec4(records, 2 * j)
            wj_split = split_inv_mass(current_j, load_vec4(records, 2 * j + 1))
            if wi_split + wj_split > zero:
                impulse = impulse + listed_impulse(
                    i, a, half * slots, slots, vec3_entry(contact_normal, a, i), vi, current_j, wi_split, wj_split,
                    friction, restitution, eps_v, rest_steps, contact_u0, contact_impulse,
                )
    else:
        # More contacts than the list holds: the candidates again, in the same order.
        sphere_i = load_vec4(spheres, i)
        vi_prev = qd_prev[contact_index[i]]
        candidate_total = candidate_count[i]
        j = int(-1)
        a = int(0)
        while True:
            j = candidate_after(
                i, j, a, candidate_total, candidates, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly,
                contact_world, contact_radius, contact_rest, jelly_self_contact, between_jellies,
                self_exclusion, skin,
            )
            a += 1
            if j < 0:
                break
            _acts, _n, _gap, _current_j, _initial_j, p = retested_pair(
                i, j, record_vector(sphere_i), sphere_i[3], vi, vi_prev, wi_split, friction, restitution, eps_v,
                rest_steps, spheres, contact_index, qd_prev, normal, face_start, records,
            )
            impulse = impulse + p
    store_vec4(records_out, 2 * i, record(vi + wi * impulse, current_i[3]))
    store_vec4(records_out, 2 * i + 1, initial_i)


@both_precisions
@wp.kernel(module="unique")
def resolve_contact_last_pass(
    # Candidates and the grid behind an overflowed list:
    candidates: wp.array2d(dtype=wp.int32),
    candidate_count: wp.array(dtype=wp.int32),
    grid_head: wp.array2d(dtype=wp.int32),
    grid_next: wp.array(dtype=wp.int32),
    inv_cell: Float,
    shift: int,
    x_build: wp.array(dtype=vec3),
    # Model:
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
    skin: Float,
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    # State and contacts (contact order; the velocities before the step in particle order):
    spheres: wp.array(dtype=vec4),
    contact_index: wp.array(dtype=wp.int32),
    qd_prev: wp.array(dtype=vec3),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
    count: wp.array(dtype=wp.int32),
    contact_list: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=vec3),
    contact_gap: wp.array2d(dtype=Float),
    contact_u0: wp.array2d(dtype=Float),
    phase: wp.array(dtype=wp.int32),
    # The records this pass starts from (the velocities before the contact response and those
    # of this pass; see find_particle_contacts)
    records: wp.array(dtype=vec4),
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
    half = phase[0]
    slots = contact_normal.shape[0]
    n_all = count.shape[0] // 2
    contacts_i = int_contiguous(count, half * n_all + i)
    if contacts_i == 0:
        # Nothing to correct: the step's result stays as the integrator (and terrain) left it.
        return
    zero = type(h)(0.0)
    current_i = load_vec4(records, 2 * i)
    initial_i = load_vec4(records, 2 * i + 1)
    vi = record_vector(current_i)
    vi0 = record_vector(initial_i)
    wi = initial_i[3]
    wi_split = split_inv_mass(current_i, initial_i)
    # The impulses act over the whole step: positions move by what the integrator makes of a
    # velocity change, beta h dv (as for terrain, kernels/contact.py).
    beta_h = h * world_contact_beta[contact_world[i]]
    impulse = type(vi)(zero)
    dx = type(vi)(zero)
    dv = type(vi)(zero)
    if contacts_i <= slots:
        for a in range(contacts_i):
            j = int_entry(contact_list, half * slots + a, i)
            current_j = load_vec4(records, 2 * j)  # the partner's two entries: one 32-byte block
            initial_j = load_vec4(records, 2 * j + 1)
            wj = initial_j[3]
            wj_split = split_inv_mass(current_j, initial_j)
            split = wi_split + wj_split
            if split > zero:
                n = vec3_entry(contact_normal, a, i)
                dp = listed_impulse(
                    i, a, half * slots, slots, n, vi, current_j, wi_split, wj_split, friction, restitution, eps_v,
                    rest_steps, contact_u0, contact_impulse,
                )
                impulse = impulse + dp
                ddx, ddv = projection_term(
                    n, entry_contiguous(contact_gap, a, i), dp, vi, record_vector(current_j), vi0,
                    record_vector(initial_j), wi, wj, split, beta_h, h, friction,
                )
                dx = dx + ddx
                dv = dv + ddv
    else:
        # More contacts than the list holds: the candidates again, in the same order, each
        # pair's impulse this pass's alone.
        sphere_i = load_vec4(spheres, i)
        vi_prev = qd_prev[contact_index[i]]
        candidate_total = candidate_count[i]
        j = int(-1)
        a = int(0)
        while True:
            j = candidate_after(
                i, j, a, candidate_total, candidates, grid_head, grid_next, inv_cell, shift, x_build, contact_jelly,
                contact_world, contact_radius, contact_rest, jelly_self_contact, between_jellies,
                self_exclusion, skin,
            )
            a += 1
            if j < 0:
                break
            acts, n, gap, current_j, initial_j, dp = retested_pair(
                i, j, record_vector(sphere_i), sphere_i[3], vi, vi_prev, wi_split, friction, restitution, eps_v,
                rest_steps, spheres, contact_index, qd_prev, normal, face_start, records,
            )
            if acts:
                impulse = impulse + dp
                ddx, ddv = projection_term(
                    n, gap, dp, vi, record_vector(current_j), vi0, record_vector(initial_j), wi, initial_j[3],
                    wi_split + split_inv_mass(current_j, initial_j), beta_h, h, friction,
                )
                dx = dx + ddx
                dv = dv + ddv
    v_new = vi + wi * impulse
    p = int_contiguous(contact_index, i)
    store_contiguous(q_out, p, record_vector(load_vec4(spheres, i)) + beta_h * (v_new - vi0) + dx)
    store_contiguous(qd_out, p, v_new + dv)
