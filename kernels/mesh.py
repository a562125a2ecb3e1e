"""Triangle-mesh terrain and mesh voxelisation, through Warp's BVH queries (``wp.Mesh``).

Contact with a mesh gives ``resolve_contact`` (kernels/contact.py) the same two things an analytic
primitive does: the signed distance at the particle and the outward normal there. The BVH finds the
closest triangle (in float32, as ``wp.Mesh`` stores it); the distance is then measured in the
model's precision from that triangle's own vertices: over a face's interior it is the distance to
the face's plane, so a flat mesh gives exactly what an analytic plane gives; over an edge or a vertex
it is the distance to the closest point, signed by the winding number (closed meshes) or by the side
the face's normal points to (open sheets, which collide from that side only).
"""

import warp as wp

from .contact import NO_SURFACE, resolve_contact, resolve_moving, surface_velocity
from .pins import key_interval, rotate
from .precision import Float, both_precisions, vec3

wp.set_module_options({"enable_backward": False})


# Voxelisation does not depend on the model's precision: one kernel, in float32 as wp.Mesh is.
@wp.kernel
def mark_inside_mesh(
    mesh: wp.uint64,
    origin: wp.vec3,
    spacing: wp.vec3,
    shape: wp.vec3i,
    on_surface: float,
    threshold: float,
    # out: 1 where the lattice point lies inside the mesh (generalized winding number above
    # ``threshold``, 1/2 for the inside) or within ``on_surface`` of it (a box mesh's faces hold
    # lattice points)
    inside_out: wp.array(dtype=wp.int32),
):
    k = wp.tid()
    nz = shape[2]
    ny = shape[1]
    iz = k % nz
    iy = (k // nz) % ny
    ix = k // (nz * ny)
    p = origin + wp.cw_mul(spacing, wp.vec3(float(ix), float(iy), float(iz)))
    # The whole mesh is within reach: the winding number needs no distance bound.
    q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e30, 2.0, threshold)
    inside = 0
    if q.result:
        if q.sign < 0.0:
            inside = 1
        elif wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v)) <= on_surface:
            inside = 1
    inside_out[k] = inside


@wp.func
def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
    """Closest point of triangle (a, b, c) to p (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = type(d1)(0.0)
    if d1 <= zero and d2 <= zero:
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return a + ab * (d1 / (d1 - d3))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return a + ac * (d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    denom = type(va)(1.0) / (va + vb + vc)
    return a + ab * (vb * denom) + ac * (vc * denom)


@wp.func
def mesh_face_distance(
    x: vec3,
    mesh: wp.uint64,
    closed: int,
    reach: Float,
    tri_start: int,
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
):
    """Signed distance (positive outside / in front) and outward normal of a mesh at x, and the
    closest face (-1 when none): (phi, normal, face). phi is a huge value farther than ``reach``
    from every face."""
    xf = wp.vec3(wp.float32(x[0]), wp.float32(x[1]), wp.float32(x[2]))
    q = wp.mesh_query_point_no_sign(mesh, xf, wp.float32(reach))
    if closed != 0:
        q = wp.mesh_query_point_sign_winding_number(mesh, xf, wp.float32(reach))
    up = type(x)(type(reach)(0.0), type(reach)(1.0), type(reach)(0.0))
    if not q.result:
        return type(reach)(NO_SURFACE), up, -1
    t = mesh_tris[tri_start + q.face]
    a = mesh_points[t[0]]
    b = mesh_points[t[1]]
    c = mesh_points[t[2]]
    nf = wp.cross(b - a, c - a)
    area2 = wp.length(nf)
    if area2 > type(reach)(0.0):
        nf = nf / area2
    # Over the face, its edges included (the point's projection on the face's plane inside the
    # triangle, to a relative 1e-5 of its size, far above rounding): the distance to the face's
    # plane, as an analytic plane measures it. The BVH's float32 barycentrics only chose the face.
    phi = wp.dot(x - a, nf)
    pp = x - phi * nf
    tol = -type(reach)(1.0e-5) * area2
    if (
        wp.dot(wp.cross(b - a, pp - a), nf) >= tol
        and wp.dot(wp.cross(c - b, pp - b), nf) >= tol
        and wp.dot(wp.cross(a - c, pp - c), nf) >= tol
    ):
        return phi, nf, q.face
    d = x - closest_on_triangle(x, a, b, c)
    dist = wp.length(d)
    if dist == type(reach)(0.0):
        return type(reach)(0.0), nf, q.face
    # Beside an edge or a vertex: the distance to the closest point, signed.
    side = type(reach)(1.0)
    if closed != 0:
        if q.sign < wp.float32(0.0):
            side = type(reach)(-1.0)
    elif wp.dot(d, nf) < type(reach)(0.0):
        side = type(reach)(-1.0)
    return side * dist, d * (side / dist), q.face


@wp.func
def mesh_distance(
    x: vec3,
    mesh: wp.uint64,
    closed: int,
    reach: Float,
    tri_start: int,
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
):
    """Signed distance (positive outside / in front) and outward normal of a mesh at x:
    (phi, normal). phi is a huge value farther than ``reach`` from every face."""
    phi, n, _face = mesh_face_distance(x, mesh, closed, reach, tri_start, mesh_tris, mesh_points)
    return phi, n


@both_precisions
@wp.kernel
def collide_meshes(
    # Model:
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    mesh_first: wp.array(dtype=wp.int32),
    mesh_id: wp.array(dtype=wp.uint64),
    mesh_closed: wp.array(dtype=wp.int32),
    mesh_reach: wp.array(dtype=Float),
    mesh_tri_start: wp.array(dtype=wp.int32),
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
    mesh_restitution: wp.array(dtype=Float),
    mesh_friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    # State before the step:
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    # State after the step, corrected in place:
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        # The meshes of world w are mesh_first[w] .. mesh_first[w + 1] - 1 (sorted by world).
        for m in range(mesh_first[w], mesh_first[w + 1]):
            phi, n = mesh_distance(x, mesh_id[m], mesh_closed[m], mesh_reach[m], mesh_tri_start[m], mesh_tris,
                                   mesh_points)
            if phi < eps:
                x, v = resolve_contact(
                    x,
                    v,
                    wp.dot(n, qd_prev[i]),
                    phi,
                    n,
                    mesh_restitution[m],
                    mesh_friction[m],
                    eps,
                    eps_v,
                    rest_steps,
                    h * world_contact_beta[w],
                    stage,
                )
        q_out[i] = x
        qd_out[i] = v


# -- Moving and animated meshes -----------------------------------------------------------------
# A mesh with a rigid motion (a pin's, as moving planes take: ``move_terrain`` puts its pose at
# the step's end in the motion arrays) keeps its BVH where it was built and is queried in its
# own frame: the particle is carried there by the inverse of the pose, and the normal back. So
# a rigid motion needs no refit, and the step stays a fixed list of launches that a graph
# captures. An animated asset (time-sampled points) moves its vertices instead
# (``deform_mesh``, then ``wp.Mesh.refit`` on the host: core/mesh_terrain.py). Contact is
# resolved in the surface's frame at the contact point as on the analytic terrain
# (``resolve_moving``): the rigid motion's velocity there plus, for an animated mesh, its
# vertices' velocities over the step interpolated at the closest point.


@wp.func
def sample_points(t: Float, first: int, count: int, times: wp.array(dtype=Float),
                  samples: wp.array2d(dtype=vec3), k: int):
    """Vertex ``k`` of an animated mesh at ``t``: linear between its samples, held outside them."""
    s, u, held = key_interval(t, first, count, times)
    if held != 0:
        return samples[s - first, k]
    p0 = samples[s - first, k]
    return p0 + (samples[s + 1 - first, k] - p0) * u


@both_precisions
@wp.kernel
def deform_mesh(
    clock: wp.array(dtype=wp.int32),
    h: Float,
    first: int,
    count: int,
    times: wp.array(dtype=Float),
    samples: wp.array2d(dtype=vec3),
    point_start: int,
    # Out: the vertices at the step's end (the model's and the BVH's) and their velocity over it.
    mesh_points: wp.array(dtype=vec3),
    bvh_points: wp.array(dtype=wp.vec3),
    point_velocity: wp.array(dtype=vec3),
):
    k = wp.tid()
    t0 = type(h)(clock[0]) * h
    p0 = sample_points(t0, first, count, times, samples, k)
    p1 = sample_points(t0 + h, first, count, times, samples, k)
    mesh_points[point_start + k] = p1
    bvh_points[k] = wp.vec3(wp.float32(p1[0]), wp.float32(p1[1]), wp.float32(p1[2]))
    point_velocity[point_start + k] = (p1 - p0) / h


@wp.func
def face_velocity(x: vec3, a: vec3, b: vec3, c: vec3, va: vec3, vb: vec3, vc: vec3):
    """The vertices' velocities interpolated at ``x`` (a point of triangle (a, b, c)) by its
    barycentric coordinates."""
    v0 = b - a
    v1 = c - a
    v2 = x - a
    d00 = wp.dot(v0, v0)
    d01 = wp.dot(v0, v1)
    d11 = wp.dot(v1, v1)
    d20 = wp.dot(v2, v0)
    d21 = wp.dot(v2, v1)
    den = d00 * d11 - d01 * d01
    if den == type(den)(0.0):
        return (va + vb + vc) / type(den)(3.0)
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    return va * (type(den)(1.0) - wb - wc) + vb * wb + vc * wc


@both_precisions
@wp.kernel
def collide_moving_meshes(
    particle_inv_mass: wp.array(dtype=Float),
    particle_world: wp.array(dtype=wp.int32),
    mesh_first: wp.array(dtype=wp.int32),
    mesh_id: wp.array(dtype=wp.uint64),
    mesh_closed: wp.array(dtype=wp.int32),
    mesh_reach: wp.array(dtype=Float),
    mesh_tri_start: wp.array(dtype=wp.int32),
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
    mesh_restitution: wp.array(dtype=Float),
    mesh_friction: wp.array(dtype=Float),
    # Per mesh its moving index (-1: no rigid motion) and whether it is animated; per vertex
    # its velocity over the step (animated meshes); the rigid motions' arrays (move_terrain's).
    mesh_motion: wp.array(dtype=wp.int32),
    mesh_animated: wp.array(dtype=wp.int32),
    mesh_point_velocity: wp.array(dtype=vec3),
    motion_center: wp.array(dtype=vec3),
    motion_center_now: wp.array(dtype=vec3),
    motion_turn_now: wp.array(dtype=vec3),
    motion_velocity_step: wp.array(dtype=vec3),
    motion_spin: wp.array(dtype=vec3),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    h: Float,
    world_contact_beta: wp.array(dtype=Float),
    stage: int,
    q_prev: wp.array(dtype=vec3),
    qd_prev: wp.array(dtype=vec3),
    q_out: wp.array(dtype=vec3),
    qd_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    if particle_inv_mass[i] != type(h)(0.0):
        w = particle_world[i]
        x = q_out[i]
        v = qd_out[i]
        beta_h = h * world_contact_beta[w]
        for m in range(mesh_first[w], mesh_first[w + 1]):
            motion = mesh_motion[m]
            # The particle in the mesh's own frame (where its BVH was built).
            x_local = x
            turn = type(x)(type(h)(0.0))
            if motion >= 0:
                turn = motion_turn_now[motion]
                x_local = motion_center[motion] + rotate(-turn, x - motion_center_now[motion])
            phi, normal_local, face = mesh_face_distance(x_local, mesh_id[m], mesh_closed[m], mesh_reach[m],
                                                         mesh_tri_start[m], mesh_tris, mesh_points)
            if phi < eps:
                n = rotate(turn, normal_local)
                v_surface = surface_velocity(x, motion, motion_center_now, motion_velocity_step, motion_spin)
                if mesh_animated[m] != 0 and face >= 0:
                    t = mesh_tris[mesh_tri_start[m] + face]
                    v_local = face_velocity(x_local - phi * normal_local, mesh_points[t[0]], mesh_points[t[1]],
                                            mesh_points[t[2]], mesh_point_velocity[t[0]], mesh_point_velocity[t[1]],
                                            mesh_point_velocity[t[2]])
                    v_surface = v_surface + rotate(turn, v_local)
                x, v = resolve_moving(x, v, qd_prev[i], n, v_surface, phi, n, mesh_restitution[m], mesh_friction[m],
                                      eps, eps_v, rest_steps, beta_h, stage)
        q_out[i] = x
        qd_out[i] = v
