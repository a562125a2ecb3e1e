"""The terrain contact functions of kernels/contact.py and kernels/mesh.py alone, in both precisions.

Each function runs in a small test kernel (one thread a case) and is checked against what it must
do by its definition: an impact leaves the surface at -e times its approach speed, a resting
contact cancels the normal velocity, Coulomb friction takes at most mu times the normal impulse of
tangential speed and never reverses it, a moving surface's response is the static one in its frame,
and the distances are the closed forms of a plane (with its hole), a sphere, a bowl, a triangle and
a closed box mesh.
"""

import numpy as np
import pytest
import warp as wp

from softsim_warp.kernels import contact
from softsim_warp.kernels import mesh as mesh_kernels
from softsim_warp.kernels.precision import Float, both_precisions, vec3

PRECISIONS = [(wp.float32, np.float32, 1e-5), (wp.float64, np.float64, 1e-12)]
EPS = 1e-3  # contact_epsilon [m]
EPS_V = 1e-3  # the speed below which an approach is a contact [m/s]
REST_STEPS = 2.0


@both_precisions
@wp.kernel
def respond(
    x: wp.array(dtype=vec3),
    v: wp.array(dtype=vec3),
    vn_prev: wp.array(dtype=Float),
    phi: wp.array(dtype=Float),
    normal: wp.array(dtype=vec3),
    restitution: wp.array(dtype=Float),
    friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    stage: int,
    x_out: wp.array(dtype=vec3),
    v_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    xi, vi = contact.resolve_contact(x[i], v[i], vn_prev[i], phi[i], normal[i], restitution[i], friction[i], eps, eps_v,
                                     rest_steps, beta_h, stage)
    x_out[i] = xi
    v_out[i] = vi


@both_precisions
@wp.kernel
def respond_moving(
    x: wp.array(dtype=vec3),
    v: wp.array(dtype=vec3),
    v_prev: wp.array(dtype=vec3),
    vs: wp.array(dtype=vec3),
    phi: wp.array(dtype=Float),
    normal: wp.array(dtype=vec3),
    restitution: wp.array(dtype=Float),
    friction: wp.array(dtype=Float),
    eps: Float,
    eps_v: Float,
    rest_steps: Float,
    beta_h: Float,
    x_out: wp.array(dtype=vec3),
    v_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    xi, vi = contact.resolve_moving(x[i], v[i], v_prev[i], normal[i], vs[i], phi[i], normal[i], restitution[i],
                                    friction[i], eps, eps_v, rest_steps, beta_h, 0)
    x_out[i] = xi
    v_out[i] = vi


@both_precisions
@wp.kernel
def surface_velocities(
    x: wp.array(dtype=vec3),
    motion: wp.array(dtype=wp.int32),
    center_now: wp.array(dtype=vec3),
    velocity_step: wp.array(dtype=vec3),
    spin: wp.array(dtype=vec3),
    out: wp.array(dtype=vec3),
):
    i = wp.tid()
    out[i] = contact.surface_velocity(x[i], motion[i], center_now, velocity_step, spin)


@both_precisions
@wp.kernel
def distances(
    x: wp.array(dtype=vec3),
    point: vec3,
    normal: vec3,
    hole_center: vec3,
    hole_radius: Float,
    center: vec3,
    radius: Float,
    cut_height: Float,
    plane_out: wp.array(dtype=Float),
    sphere_out: wp.array(dtype=Float),
    sphere_normal_out: wp.array(dtype=vec3),
    bowl_out: wp.array(dtype=Float),
    bowl_normal_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    plane_out[i] = contact.plane_distance(x[i], point, normal, hole_center, hole_radius)
    phi, n = contact.sphere_distance(x[i], center, radius)
    sphere_out[i] = phi
    sphere_normal_out[i] = n
    phi, n = contact.bowl_distance(x[i], center, radius, cut_height)
    bowl_out[i] = phi
    bowl_normal_out[i] = n


def launch_response(scalar, np_dtype, device, x, v, vn_prev, phi, normal, restitution, friction, beta_h=0.0, stage=0):
    vec = wp.types.vector(3, scalar)
    n = len(x)
    vecs = lambda a: wp.array(np.asarray(a, dtype=np_dtype).reshape(n, 3), dtype=vec, device=device)  # noqa: E731
    scalars = lambda a: wp.array(np.broadcast_to(np.asarray(a, dtype=np_dtype), n).copy(), dtype=scalar,  # noqa: E731
                                 device=device)
    x_out, v_out = wp.zeros(n, dtype=vec, device=device), wp.zeros(n, dtype=vec, device=device)
    wp.launch(respond, n, inputs=[vecs(x), vecs(v), scalars(vn_prev), scalars(phi), vecs(normal), scalars(restitution),
                                  scalars(friction), scalar(EPS), scalar(EPS_V), scalar(REST_STEPS), scalar(beta_h),
                                  stage, x_out, v_out], device=device)
    return x_out.numpy(), v_out.numpy()


def random_cases(rng, n, np_dtype):
    """n particles just through a tilted surface, approaching it, with tangential velocity."""
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tangent = np.cross(normal, rng.normal(size=(n, 3)))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    speed_n = rng.uniform(0.01, 3.0, n)
    v = -speed_n[:, None] * normal + rng.uniform(0.0, 2.0, n)[:, None] * tangent
    x = rng.normal(size=(n, 3))
    phi = -rng.uniform(0.0, 1e-3, n)
    return x.astype(np_dtype), v.astype(np_dtype), phi.astype(np_dtype), normal.astype(np_dtype)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_impact_leaves_at_minus_e_times_the_approach_speed(device, scalar, np_dtype, tol):
    """An approach brought into the step (vn_prev = vn, nothing added by the step's forces) is an
    impact: the normal velocity comes out at -e times what went in, and the particle is put back on
    the surface (x - phi n)."""
    rng = np.random.default_rng(1)
    n = 64
    x, v, phi, normal = random_cases(rng, n, np_dtype)
    restitution = rng.uniform(0.0, 1.0, n).astype(np_dtype)
    vn = np.einsum("ij,ij->i", normal.astype(np.float64), v.astype(np.float64))
    x_out, v_out = launch_response(scalar, np_dtype, device, x, v, vn, phi, normal, restitution, 0.0)
    assert v_out.dtype == np_dtype
    vn_out = np.einsum("ij,ij->i", normal.astype(np.float64), v_out.astype(np.float64))
    np.testing.assert_allclose(vn_out, -restitution * vn, rtol=tol * 10, atol=tol * 10)
    # Without friction the tangential velocity passes unchanged.
    vt_in = v - vn[:, None] * normal
    vt_out = v_out - vn_out[:, None] * normal
    np.testing.assert_allclose(vt_out, vt_in, rtol=0, atol=tol * 10)
    # Put back on the surface: the distance after is 0 (to rounding).
    moved = np.einsum("ij,ij->i", normal.astype(np.float64), (x_out - x).astype(np.float64))
    np.testing.assert_allclose(moved, -phi, rtol=0, atol=tol)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_resting_contact_cancels_the_normal_velocity(device, scalar, np_dtype, tol):
    """An approach that only the step's forces made (vn_prev = 0, below eps_v) is a contact: the
    normal velocity is cancelled whatever the restitution."""
    rng = np.random.default_rng(2)
    n = 32
    x, v, phi, normal = random_cases(rng, n, np_dtype)
    _x_out, v_out = launch_response(scalar, np_dtype, device, x, v, 0.0, phi, normal, 0.9, 0.0)
    vn_out = np.einsum("ij,ij->i", normal.astype(np.float64), v_out.astype(np.float64))
    np.testing.assert_allclose(vn_out, 0.0, atol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
@pytest.mark.parametrize("impact", [False, True])
def test_friction_obeys_the_coulomb_bound_and_never_reverses(device, scalar, np_dtype, tol, impact):
    """Friction removes at most mu times the normal impulse per unit mass of tangential speed
    ((1 + e)(-vn) at an impact, -vn at a contact), exactly that much while the particle slides, and
    never turns the tangential velocity around: a slower one sticks (comes out zero)."""
    rng = np.random.default_rng(3 + impact)
    n = 256
    x, v, phi, normal = random_cases(rng, n, np_dtype)
    e = np.full(n, 0.5, dtype=np_dtype)
    mu = rng.uniform(0.0, 2.0, n).astype(np_dtype)
    vn = np.einsum("ij,ij->i", normal.astype(np.float64), v.astype(np.float64))
    vn_prev = vn if impact else np.zeros(n)
    _x_out, v_out = launch_response(scalar, np_dtype, device, x, v, vn_prev, phi, normal, e, mu)
    vt_in = v.astype(np.float64) - vn[:, None] * normal
    vn_out = np.einsum("ij,ij->i", normal.astype(np.float64), v_out.astype(np.float64))
    vt_out = v_out.astype(np.float64) - vn_out[:, None] * normal
    speed_in = np.linalg.norm(vt_in, axis=1)
    speed_out = np.linalg.norm(vt_out, axis=1)
    budget = mu * (-vn) * ((1.0 + e) if impact else 1.0)
    # Never reversed: the same direction or stopped.
    assert np.all(np.einsum("ij,ij->i", vt_in, vt_out) >= -tol)
    # The Coulomb bound, met with equality while sliding; a speed within the budget sticks.
    np.testing.assert_allclose(speed_out, np.maximum(speed_in - budget, 0.0), rtol=0, atol=tol * 10)
    sticks = speed_in < budget
    assert sticks.any() and not sticks.all()  # both regimes were exercised


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_a_particle_above_the_touch_distance_is_left_alone(device, scalar, np_dtype, tol):
    """Above TOUCH_FRACTION of the contact layer the step has not brought the particle to the
    surface: (x, v) come back bit for bit; within the layer the implicit solve's pick
    (stage LAYER_TOUCH) does respond."""
    x = np.array([[0.1, 0.2, 0.3]] * 2, dtype=np_dtype)
    v = np.array([[0.5, -1.0, 0.0]] * 2, dtype=np_dtype)
    normal = np.array([[0.0, 1.0, 0.0]] * 2, dtype=np_dtype)
    phi = np.array([2.0 * contact.TOUCH_FRACTION * EPS, 2.0 * EPS], dtype=np_dtype)  # in the layer, beyond it
    x_out, v_out = launch_response(scalar, np_dtype, device, x, v, -1.0, phi, normal, 0.5, 0.3)
    assert np.array_equal(x_out, x) and np.array_equal(v_out, v)
    x_out, v_out = launch_response(scalar, np_dtype, device, x, v, -1.0, phi, normal, 0.5, 0.3,
                                   stage=contact.LAYER_TOUCH)
    assert v_out[0][1] == np_dtype(0.5)  # in the layer: an impact, reflected at e = 0.5
    assert np.array_equal(x_out[1], x[1]) and np.array_equal(v_out[1], v[1])  # beyond it: free


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_moving_surface_response_is_the_static_one_in_its_frame(device, scalar, np_dtype, tol):
    """resolve_moving against a surface moving at vs gives, relative to vs, what resolve_contact
    gives for the relative velocities (Galilean invariance), here at an impact with friction."""
    rng = np.random.default_rng(5)
    n = 64
    vec = wp.types.vector(3, scalar)
    x, v_rel, phi, normal = random_cases(rng, n, np_dtype)
    vs = rng.normal(size=(n, 3)).astype(np_dtype)
    v = (v_rel.astype(np.float64) + vs).astype(np_dtype)
    e = np.full(n, 0.7, dtype=np_dtype)
    mu = np.full(n, 0.4, dtype=np_dtype)
    vecs = lambda a: wp.array(np.asarray(a, dtype=np_dtype), dtype=vec, device=device)  # noqa: E731
    scalars = lambda a: wp.array(np.asarray(a, dtype=np_dtype), dtype=scalar, device=device)  # noqa: E731
    x_out, v_out = wp.zeros(n, dtype=vec, device=device), wp.zeros(n, dtype=vec, device=device)
    wp.launch(respond_moving, n, inputs=[vecs(x), vecs(v), vecs(v), vecs(vs), scalars(phi), vecs(normal), scalars(e),
                                         scalars(mu), scalar(EPS), scalar(EPS_V), scalar(REST_STEPS), scalar(0.0),
                                         x_out, v_out], device=device)
    got = v_out.numpy().astype(np.float64) - vs
    rel = v.astype(np.float64) - vs
    vn = np.einsum("ij,ij->i", normal.astype(np.float64), rel)
    vn_out = np.einsum("ij,ij->i", normal.astype(np.float64), got)
    np.testing.assert_allclose(vn_out, -e * vn, rtol=0, atol=tol * 100)
    speed_in = np.linalg.norm(rel - vn[:, None] * normal, axis=1)
    speed_out = np.linalg.norm(got - vn_out[:, None] * normal, axis=1)
    np.testing.assert_allclose(speed_out, np.maximum(speed_in - mu * (1.0 + e) * (-vn), 0.0), rtol=0, atol=tol * 100)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_surface_velocity_is_translation_plus_spin(device, scalar, np_dtype, tol):
    rng = np.random.default_rng(6)
    vec = wp.types.vector(3, scalar)
    x = rng.normal(size=(4, 3))
    center, velocity, spin = rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), rng.normal(size=(2, 3))
    motion = np.array([0, 1, -1, 1], dtype=np.int32)
    vecs = lambda a: wp.array(np.asarray(a, dtype=np_dtype), dtype=vec, device=device)  # noqa: E731
    out = wp.zeros(4, dtype=vec, device=device)
    wp.launch(surface_velocities, 4, inputs=[vecs(x), wp.array(motion, dtype=wp.int32, device=device), vecs(center),
                                             vecs(velocity), vecs(spin), out], device=device)
    expected = np.zeros((4, 3))
    for i, m in enumerate(motion):
        if m >= 0:
            expected[i] = velocity[m] + np.cross(spin[m], x[i] - center[m])
    np.testing.assert_allclose(out.numpy(), expected, rtol=0, atol=tol * 10)
    assert np.array_equal(out.numpy()[2], np.zeros(3))  # a static surface (m = -1) does not move


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_plane_sphere_and_bowl_distances_are_the_closed_forms(device, scalar, np_dtype, tol):
    rng = np.random.default_rng(7)
    vec = wp.types.vector(3, scalar)
    n = 200
    x = rng.uniform(-2.0, 2.0, size=(n, 3)).astype(np_dtype)
    point, normal = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, 2.0]) / 3.0
    hole_center, hole_radius = np.array([0.5, 0.0, 0.0]), 0.8
    center, radius, cut = np.array([0.2, 0.1, -0.1]), 1.5, 0.4
    outs = [wp.zeros(n, dtype=t, device=device) for t in (scalar, scalar, vec, scalar, vec)]
    wp.launch(distances, n, inputs=[wp.array(x, dtype=vec, device=device), vec(*point), vec(*normal), vec(*hole_center),
                                    scalar(hole_radius), vec(*center), scalar(radius), scalar(cut), *outs],
              device=device)
    plane, sphere, sphere_n, bowl, bowl_n = (o.numpy().astype(np.float64) for o in outs)
    xd = x.astype(np.float64)
    # Plane: the distance along its normal, except over the hole (the disc of the hole's radius
    # about its centre, measured in the plane), where there is no surface.
    along = (xd - point) @ normal
    r = xd - hole_center
    r -= np.outer(r @ normal, normal)
    over_hole = np.einsum("ij,ij->i", r, r) < hole_radius**2
    assert over_hole.any() and not over_hole.all()
    np.testing.assert_allclose(plane[~over_hole], along[~over_hole], rtol=0, atol=tol * 10)
    assert np.all(plane[over_hole] == np_dtype(contact.NO_SURFACE))
    # Sphere: |x - c| - R along (x - c) / |x - c|.
    d = xd - center
    dist = np.linalg.norm(d, axis=1)
    np.testing.assert_allclose(sphere, dist - radius, rtol=0, atol=tol * 10)
    np.testing.assert_allclose(sphere_n, d / dist[:, None], rtol=0, atol=tol * 10)
    # Bowl: the inside of the same sphere below the cut, R - |x - c| along the inward normal.
    below = xd[:, 1] < cut
    np.testing.assert_allclose(bowl[below], radius - dist[below], rtol=0, atol=tol * 10)
    np.testing.assert_allclose(bowl_n[below], -d[below] / dist[below, None], rtol=0, atol=tol * 10)
    assert np.all(bowl[~below] == np_dtype(contact.NO_SURFACE))


# -- Meshes (kernels/mesh.py): the same response, given the distance to the closest triangle ---------


@both_precisions
@wp.kernel
def closest_points(p: wp.array(dtype=vec3), a: vec3, b: vec3, c: vec3, out: wp.array(dtype=vec3)):
    i = wp.tid()
    out[i] = mesh_kernels.closest_on_triangle(p[i], a, b, c)


@both_precisions
@wp.kernel
def mesh_distances(
    x: wp.array(dtype=vec3),
    mesh_id: wp.uint64,
    closed: int,
    reach: Float,
    tris: wp.array(dtype=wp.vec3i),
    points: wp.array(dtype=vec3),
    phi_out: wp.array(dtype=Float),
    normal_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    phi, n = mesh_kernels.mesh_distance(x[i], mesh_id, closed, reach, 0, tris, points)
    phi_out[i] = phi
    normal_out[i] = n


@both_precisions
@wp.kernel
def face_velocities(x: wp.array(dtype=vec3), a: vec3, b: vec3, c: vec3, va: vec3, vb: vec3, vc: vec3,
                    out: wp.array(dtype=vec3)):
    i = wp.tid()
    out[i] = mesh_kernels.face_velocity(x[i], a, b, c, va, vb, vc)


def closest_on_segment(p, a, b):
    t = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    return a + np.outer(t, b - a)


def closest_on_triangle_reference(p, a, b, c):
    """The projection on the triangle's plane where it falls inside the triangle, else the closest
    of the three edges' closest points (float64)."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    proj = p - np.outer((p - a) @ n, n)
    inside = np.ones(len(p), dtype=bool)
    for u, w in ((a, b), (b, c), (c, a)):
        inside &= np.cross(w - u, proj - u) @ n >= 0.0
    best = proj.copy()
    edges = np.stack([closest_on_segment(p, u, w) for u, w in ((a, b), (b, c), (c, a))])
    nearest = edges[np.argmin(np.linalg.norm(edges - p, axis=2), axis=0), np.arange(len(p))]
    best[~inside] = nearest[~inside]
    return best, inside


TRIANGLE = (np.array([0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.0, -2.0]))  # normal +y


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_closest_point_on_a_triangle(device, scalar, np_dtype, tol):
    rng = np.random.default_rng(8)
    vec = wp.types.vector(3, scalar)
    a, b, c = (np.array([0.1, 0.2, -0.3]), np.array([1.7, -0.4, 0.2]), np.array([0.3, 1.1, 0.9]))
    p = rng.uniform(-2.0, 3.0, size=(400, 3)).astype(np_dtype).astype(np.float64)
    out = wp.zeros(len(p), dtype=vec, device=device)
    wp.launch(closest_points, len(p), inputs=[wp.array(p.astype(np_dtype), dtype=vec, device=device), vec(*a), vec(*b),
                                              vec(*c), out], device=device)
    expected, inside = closest_on_triangle_reference(p, a, b, c)
    assert inside.any() and not inside.all()  # the face and its edges and vertices
    np.testing.assert_allclose(out.numpy(), expected, rtol=0, atol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_open_sheet_distance_is_the_distance_to_the_triangle(device, scalar, np_dtype, tol):
    """One triangle as an open sheet: above its face the height over its plane (along its normal),
    beside it the distance to its closest point, signed by the side of the face's normal."""
    vec = wp.types.vector(3, scalar)
    a, b, c = TRIANGLE
    rng = np.random.default_rng(9)
    x = rng.uniform([-1.0, -1.0, -3.0], [3.0, 1.0, 1.0], size=(300, 3)).astype(np_dtype).astype(np.float64)
    points = np.stack([a, b, c])
    bvh = wp.Mesh(points=wp.array(points, dtype=wp.vec3, device=device),
                  indices=wp.array([0, 1, 2], dtype=wp.int32, device=device))
    phi, normal = wp.zeros(len(x), dtype=scalar, device=device), wp.zeros(len(x), dtype=vec, device=device)
    wp.launch(mesh_distances, len(x),
              inputs=[wp.array(x.astype(np_dtype), dtype=vec, device=device), wp.uint64(bvh.id), 0, scalar(10.0),
                      wp.array(np.array([[0, 1, 2]]), dtype=wp.vec3i, device=device),
                      wp.array(points.astype(np_dtype), dtype=vec, device=device), phi, normal], device=device)
    closest, over_face = closest_on_triangle_reference(x, a, b, c)
    d = x - closest
    dist = np.linalg.norm(d, axis=1)
    side = np.where(d[:, 1] >= 0.0, 1.0, -1.0)
    expected_normal = np.where(over_face[:, None], [0.0, 1.0, 0.0], d * (side / dist)[:, None])
    assert over_face.any() and not over_face.all()
    np.testing.assert_allclose(phi.numpy(), np.where(over_face, x[:, 1], side * dist), rtol=0, atol=tol * 10)
    np.testing.assert_allclose(normal.numpy(), expected_normal, rtol=0, atol=tol * 100)


def box_mesh():
    """The cube [-1, 1]^3 as 12 triangles wound outward."""
    corners = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    tris = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            face = [i for i, p in enumerate(corners) if p[axis] == sign]
            u, v = [k for k in range(3) if k != axis]
            centre = corners[face].mean(axis=0)
            face.sort(key=lambda i: np.arctan2(corners[i][v] - centre[v], corners[i][u] - centre[u]))
            for tri in ([face[0], face[1], face[2]], [face[0], face[2], face[3]]):
                n = np.cross(corners[tri[1]] - corners[tri[0]], corners[tri[2]] - corners[tri[0]])
                tris.append(tri if n[axis] * sign > 0 else tri[::-1])
    return corners, np.array(tris, dtype=np.int32)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_closed_mesh_distance_is_the_box_signed_distance(device, scalar, np_dtype, tol):
    """A closed cube: inside, minus the distance to the nearest face; outside, the distance to the
    box (to a face, an edge or a corner), the closed-form signed distance of a box."""
    vec = wp.types.vector(3, scalar)
    corners, tris = box_mesh()
    rng = np.random.default_rng(10)
    x = rng.uniform(-1.8, 1.8, size=(400, 3)).astype(np_dtype).astype(np.float64)
    x = x[np.abs(np.abs(x) - 1.0).min(axis=1) > 1e-3]  # not on a face's plane, where the sign is either
    bvh = wp.Mesh(points=wp.array(corners, dtype=wp.vec3, device=device),
                  indices=wp.array(tris.ravel(), dtype=wp.int32, device=device))
    phi, normal = wp.zeros(len(x), dtype=scalar, device=device), wp.zeros(len(x), dtype=vec, device=device)
    wp.launch(mesh_distances, len(x),
              inputs=[wp.array(x.astype(np_dtype), dtype=vec, device=device), wp.uint64(bvh.id), 1, scalar(10.0),
                      wp.array(tris, dtype=wp.vec3i, device=device),
                      wp.array(corners.astype(np_dtype), dtype=vec, device=device), phi, normal], device=device)
    q = np.abs(x) - 1.0
    expected = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    assert (expected < 0).any() and (expected > 0).any()
    np.testing.assert_allclose(phi.numpy(), expected, rtol=0, atol=tol * 10)
    # The normal is the box distance's gradient: outward, unit.
    np.testing.assert_allclose(np.linalg.norm(normal.numpy(), axis=1), 1.0, rtol=0, atol=tol * 10)
    outside = expected > 0
    grad = np.maximum(q, 0.0)[outside] / expected[outside, None] * np.sign(x[outside])
    np.testing.assert_allclose(normal.numpy()[outside], grad, rtol=0, atol=tol * 100)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_face_velocity_interpolates_a_linear_field_exactly(device, scalar, np_dtype, tol):
    """Barycentric interpolation reproduces a velocity field linear in position: a rigid motion
    (v = u + w x p) of the triangle gives every point of it its rigid velocity."""
    vec = wp.types.vector(3, scalar)
    a, b, c = np.array([0.1, 0.2, -0.3]), np.array([1.7, -0.4, 0.2]), np.array([0.3, 1.1, 0.9])
    u, w = np.array([0.3, -0.2, 0.5]), np.array([1.0, 0.5, -2.0])
    rigid = lambda p: u + np.cross(w, p)  # noqa: E731
    rng = np.random.default_rng(11)
    bary = rng.dirichlet([1.0, 1.0, 1.0], size=50)
    x = bary @ np.stack([a, b, c])
    out = wp.zeros(len(x), dtype=vec, device=device)
    wp.launch(face_velocities, len(x), inputs=[wp.array(x.astype(np_dtype), dtype=vec, device=device), vec(*a),
                                               vec(*b), vec(*c), vec(*rigid(a)), vec(*rigid(b)), vec(*rigid(c)), out],
              device=device)
    np.testing.assert_allclose(out.numpy(), u + np.cross(w, x), rtol=0, atol=tol * 10)
