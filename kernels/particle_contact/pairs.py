"""The physics of one pair of particles in contact: which pairs may touch, their contact normal, and
the impulse and position correction between them.

Every function here takes the pair's own values only, and swapping i and j negates each vector
result exactly: what particle j receives is the negative of what particle i does, so linear
momentum is conserved pair by pair. A new contact model changes these functions; the kernels that
find the pairs and sum their impulses (``candidates``, ``response``) stay as they are.
"""

import warp as wp

from ..precision import Float, vec3
from .tables import load_vec4, record_vector, vec3_entry, vec4

wp.set_module_options({"enable_backward": False})

# Pairs closer than this many pair distances are candidates: a particle resting on the other
# surface between its particles (up to s / sqrt(2) aside at pitch s) is farther than the pair
# distance from each of them, yet touches the surface along the normal.
CANDIDATE_REACH = wp.constant(1.25)
# A face's normal is the contact normal for particles at most this many pair distances aside of the
# face's particle (the half diagonal of a face cell is 0.71 lattice spacings).
FACE_REACH = wp.constant(0.75)


@wp.func
def pair_allowed(
    i: int,
    j: int,
    contact_jelly: wp.array(dtype=wp.int32),
    contact_world: wp.array(dtype=wp.int32),
    contact_radius: wp.array(dtype=Float),
    contact_rest: wp.array(dtype=vec3),
    jelly_self_contact: wp.array(dtype=wp.int32),
    between_jellies: int,
    self_exclusion: Float,
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
    zero = type(direction[0])(0.0)
    best = type(direction)(zero)
    best_dot = type(zero)(-2.0)
    for s in range(3):
        if i < face_start[s]:
            break  # no face s (the contact order groups the particles by their number of faces)
        n = vec3_entry(normal, s, i)
        if wp.length_sq(n) > zero:
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
    dist: Float,
    d: Float,
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
):
    """Contact normal of a touching pair, from j to i; swapping i and j negates it exactly.

    It is the difference of the outward normals of the two faces that face each other,
    n_j - n_i (each particle's boundary face most aligned with the other particle), so two
    surfaces meet as smooth surfaces. The direction between the particles, u, would tilt by up
    to 30 degrees where a particle sits between the particles of the other surface (an egg
    crate of pitch one lattice spacing): lattices would interlock and resist sliding far beyond
    Coulomb friction (a block on a slab with mu = 0.2 stuck at 25 degrees, where it should slide
    at 2.4 m/s^2). Adding even a quarter of u to n made resting stacks jitter (the two pairs
    under a particle between two others push it sideways in turn). The faces' normals rather
    than a particle's mean normal keep an edge particle of a block from pushing at 45 degrees.
    The faces' normal holds over the faces only: where particle i lies more than FACE_REACH d
    aside of particle j along it (beyond the half diagonal of a face cell at pitch d), or more
    than 30 degrees from u (no faces face each other: an edge meeting a face side-on, a fold's
    tip), the normal turns smoothly to u, which it reaches 0.25 d farther aside or at 45
    degrees. Without that bound a particle beside the other jelly's edge, below its face's
    plane, is thrown up onto the face (in the pile scene); with a sudden switch instead of the
    blend, particles at the edge of a face jump between the two normals every few steps.
    """
    one = type(dist)(1.0)
    zero = type(dist)(0.0)
    u = (xi - xj) / dist
    m = facing_normal(normal, face_start, j, u) - facing_normal(normal, face_start, i, -u)
    length = wp.length(m)
    if length > zero:
        n = m / length
        c = wp.dot(n, u)
        aside = dist * wp.sqrt(wp.max(one - c * c, zero)) / d
        # Blend weight of u: 0 within the face (aside <= FACE_REACH d, within 30 degrees of u),
        # 1 from 0.25 d farther aside or from 45 degrees, smooth in between so that the normal
        # and the separation along it change continuously with the positions. The constants are
        # cos 30 degrees and cos 30 - cos 45 degrees.
        t = wp.max(
            wp.clamp((aside - type(dist)(FACE_REACH)) / type(dist)(0.25), zero, one),
            wp.clamp((type(dist)(0.8660254037844386) - c) / type(dist)(0.1589186225978631), zero, one),
        )
        t = t * t * (type(dist)(3.0) - type(dist)(2.0) * t)
        m = (one - t) * n + t * u
        length = wp.length(m)
        if length > zero:
            return m / length
    return u


@wp.func
def near_pair(j: int, xi: vec3, ri: Float, spheres: wp.array(dtype=vec4)):
    """Whether candidate j lies within CANDIDATE_REACH d of particle i (position ``xi``, contact
    radius ``ri``) and not on it: the pairs that :func:`touching_pair` tests further. Every test
    of a pair goes through here, so all passes agree on it bit for bit. ``spheres`` holds each
    contact particle's position with its contact radius."""
    sphere_j = load_vec4(spheres, j)
    r = xi - record_vector(sphere_j)
    dist2 = wp.dot(r, r)
    reach_d = type(ri)(CANDIDATE_REACH) * (ri + sphere_j[3])
    return dist2 < reach_d * reach_d and dist2 > type(ri)(0.0)


@wp.func
def touching_pair(
    i: int,
    j: int,
    xi: vec3,
    ri: Float,
    spheres: wp.array(dtype=vec4),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
):
    """Whether a near pair (i, j) (:func:`near_pair`) touches: closer than d along its contact
    normal. Returns (touches, normal from j to i, separation along it minus d: negative when
    touching)."""
    sphere_j = load_vec4(spheres, j)
    d = ri + sphere_j[3]
    xj = record_vector(sphere_j)
    r = xi - xj
    n = pair_normal(i, j, xi, xj, wp.sqrt(wp.dot(r, r)), d, normal, face_start)
    gap = wp.dot(r, n) - d
    return gap < type(ri)(0.0), n, gap


@wp.func
def pair_contact(
    i: int,
    j: int,
    xi: vec3,
    ri: Float,
    spheres: wp.array(dtype=vec4),
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
):
    """Whether an allowed pair (i, j) touches: near (:func:`near_pair`) and closer than d along
    its contact normal. Returns (touches, normal from j to i, separation along it minus d:
    negative when touching)."""
    touches = False
    n = type(xi)(type(ri)(0.0))
    gap = type(ri)(0.0)
    if near_pair(j, xi, ri, spheres):
        touches, n, gap = touching_pair(i, j, xi, ri, spheres, normal, face_start)
    return touches, n, gap


@wp.func
def within_cone(lam: Float, pt: vec3, n: vec3, friction: Float):
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
    u0: Float,
    wi_split: Float,
    wj_split: Float,
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
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
    zero = type(u0)(0.0)
    vrel = vi - vj
    vn = wp.dot(vrel, n)
    m_eff = type(u0)(1.0) / (wi_split + wj_split)
    target = zero
    if restitution != zero:
        w = -vn - u0
        if not (u0 < eps_v or u0 < rest_steps * w):
            target = restitution * u0
    lam_old = wp.dot(p_old, n)
    lam = wp.max(lam_old + (target - vn) * m_eff, zero)
    return within_cone(lam, (p_old - lam_old * n) - (vrel - vn * n) * m_eff, n, friction)


@wp.func
def warm_impulse(p_prev: vec3, n: vec3, friction: Float):
    """The last step's impulse of a pair, on its new normal: the push part (zero if it would
    pull), the tangential part within mu times it. Negates exactly with its inputs."""
    lam = wp.dot(p_prev, n)
    p = type(n)(type(friction)(0.0))
    if lam > type(friction)(0.0):
        p = within_cone(lam, p_prev - lam * n, n, friction)
    return p


@wp.func
def projection_term(
    n: vec3,
    gap: Float,
    dp: vec3,
    vi: vec3,
    vj: vec3,
    vi0: vec3,
    vj0: vec3,
    wi: Float,
    wj: Float,
    split: Float,
    beta_h: Float,
    h: Float,
    friction: Float,
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
    zero = type(gap)(0.0)
    dx = type(n)(zero)
    dv = type(n)(zero)
    vie = vi + wi * dp
    vje = vj - wj * dp
    moved = gap + beta_h * wp.dot((vie - vi0) - (vje - vj0), n)
    if moved < zero:
        dx = (-moved * wi / split) * n
        vrel = vie - vje
        vn = wp.dot(vrel, n)
        if vn < zero:
            jn = wp.min(-vn, -moved / h)
            dv = within_cone(jn, -(vrel - vn * n), n, friction) * (wi / split)
    return dx, dv
