"""kernels/particle_contact/ alone: the physics of one pair and the table accessors, float32 and float64.

Each check is one that cannot agree by accident: the impulse of a pair cancels its approach (or
leaves at restitution times it) and its slip within Coulomb's cone, swapping the pair negates it
bit for bit (momentum), an accumulated impulse is a fixed point of the next iteration, the contact
normal is the faces' where they face each other and the direction between the particles where
there are none, and the projection removes exactly the overlap left.
"""

import numpy as np
import pytest
import warp as wp

from softsim_warp.kernels import particle_contact
from softsim_warp.kernels.particle_contact import tables
from softsim_warp.kernels.precision import Float, both_precisions, vec3

PRECISIONS = [(wp.float32, np.float32, 2.0e-5), (wp.float64, np.float64, 1.0e-12)]
vec4 = tables.vec4


@both_precisions
@wp.kernel
def impulses_of(
    n: wp.array(dtype=vec3),
    vi: wp.array(dtype=vec3),
    vj: wp.array(dtype=vec3),
    p_old: wp.array(dtype=vec3),
    u0: wp.array(dtype=Float),
    wi_split: wp.array(dtype=Float),
    wj_split: wp.array(dtype=Float),
    friction: Float,
    restitution: Float,
    eps_v: Float,
    rest_steps: Float,
    # Out: the pair's impulse on i, and on j computed with i and j swapped
    on_i: wp.array(dtype=vec3),
    on_j: wp.array(dtype=vec3),
):
    t = wp.tid()
    on_i[t] = particle_contact.accumulated_impulse(
        n[t], vi[t], vj[t], p_old[t], u0[t], wi_split[t], wj_split[t], friction, restitution, eps_v, rest_steps
    )
    on_j[t] = particle_contact.accumulated_impulse(
        -n[t], vj[t], vi[t], -p_old[t], u0[t], wj_split[t], wi_split[t], friction, restitution, eps_v, rest_steps
    )


@both_precisions
@wp.kernel
def warm_impulses_of(p_prev: wp.array(dtype=vec3), n: wp.array(dtype=vec3), friction: Float, out: wp.array(dtype=vec3)):
    t = wp.tid()
    out[t] = particle_contact.warm_impulse(p_prev[t], n[t], friction)


@both_precisions
@wp.kernel
def normals_of(
    x: wp.array(dtype=vec3),
    pair: wp.array(dtype=wp.vec2i),
    d: Float,
    normal: wp.array2d(dtype=vec3),
    face_start: wp.vec3i,
    # Out: the pair's normal from j to i, and from i to j (the pair swapped)
    n_ij: wp.array(dtype=vec3),
    n_ji: wp.array(dtype=vec3),
):
    t = wp.tid()
    i = pair[t][0]
    j = pair[t][1]
    r = x[i] - x[j]
    dist = wp.length(r)
    n_ij[t] = particle_contact.pair_normal(i, j, x[i], x[j], dist, d, normal, face_start)
    n_ji[t] = particle_contact.pair_normal(j, i, x[j], x[i], dist, d, normal, face_start)


@both_precisions
@wp.kernel
def projections_of(
    n: wp.array(dtype=vec3),
    gap: Float,
    dp: wp.array(dtype=vec3),
    vi: wp.array(dtype=vec3),
    vj: wp.array(dtype=vec3),
    wi: Float,
    wj: Float,
    beta_h: Float,
    h: Float,
    friction: Float,
    # Out: (dx, dv) of i, and of j (the pair swapped)
    dx_i: wp.array(dtype=vec3),
    dv_i: wp.array(dtype=vec3),
    dx_j: wp.array(dtype=vec3),
    dv_j: wp.array(dtype=vec3),
):
    t = wp.tid()
    split = wi + wj
    # The velocities before the response are those the pass starts from (no earlier iteration).
    dx, dv = particle_contact.projection_term(
        n[t], gap, dp[t], vi[t], vj[t], vi[t], vj[t], wi, wj, split, beta_h, h, friction
    )
    dx_i[t] = dx
    dv_i[t] = dv
    dx, dv = particle_contact.projection_term(
        -n[t], gap, -dp[t], vj[t], vi[t], vj[t], vi[t], wj, wi, split, beta_h, h, friction
    )
    dx_j[t] = dx
    dv_j[t] = dv


def _arr(values, dtype, device):
    return wp.array(np.asarray(values), dtype=dtype, device=device)


def _impulses(device, scalar, np_dtype, n, vi, vj, p_old, u0, wi, wj, friction, restitution, eps_v=1e-3, steps=2.0):
    vec = wp.types.vector(3, scalar)
    count = len(n)
    on_i, on_j = (wp.zeros(count, dtype=vec, device=device) for _ in range(2))
    wp.launch(
        impulses_of,
        count,
        inputs=[
            *(_arr(np.asarray(a, np_dtype), vec, device) for a in (n, vi, vj, p_old)),
            *(_arr(np.asarray(a, np_dtype), scalar, device) for a in (u0, wi, wj)),
            scalar(friction),
            scalar(restitution),
            scalar(eps_v),
            scalar(steps),
        ],
        outputs=[on_i, on_j],
        device=device,
    )
    return on_i.numpy(), on_j.numpy()


def _random_pairs(rng, count, np_dtype):
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    vi = rng.normal(size=(count, 3))
    vj = rng.normal(size=(count, 3))
    wi = rng.uniform(0.2, 3.0, count)
    wj = rng.uniform(0.2, 3.0, count)
    return [np.asarray(a, np_dtype) for a in (n, vi, vj, wi, wj)]


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_impulse_cancels_approach_and_slip_and_conserves_momentum(device, scalar, np_dtype, tol):
    """A fresh pair (no impulse so far), friction ample: after i gets w_i p and j gets -w_j p, the
    relative velocity is zero where they approach; separating pairs get nothing. Swapping the pair
    negates the impulse bit for bit, so the pair's momentum change is zero exactly."""
    rng = np.random.default_rng(1)
    count = 64
    n, vi, vj, wi, wj = _random_pairs(rng, count, np_dtype)
    zeros = np.zeros((count, 3), np_dtype)
    p, p_swapped = _impulses(device, scalar, np_dtype, n, vi, vj, zeros, np.zeros(count), wi, wj, 1.0e6, 0.0)
    assert p.dtype == np_dtype
    np.testing.assert_array_equal(p_swapped, -p)
    n64, vi64, vj64, wi64, wj64, p64 = (a.astype(np.float64) for a in (n, vi, vj, wi, wj, p))
    vn = np.einsum("ij,ij->i", vi64 - vj64, n64)
    approaching = vn < 0.0
    assert 10 < approaching.sum() < count - 10
    after = (vi64 + wi64[:, None] * p64) - (vj64 - wj64[:, None] * p64)
    scale = np.linalg.norm(vi64 - vj64, axis=1, keepdims=True)
    np.testing.assert_allclose(after[approaching] / scale[approaching], 0.0, atol=tol * 10)
    # The closed form: p = -m_eff (v_i - v_j), m_eff = 1 / (w_i + w_j).
    m_eff = 1.0 / (wi64 + wj64)
    np.testing.assert_allclose(p64[approaching], (-m_eff[:, None] * (vi64 - vj64))[approaching], rtol=tol * 10,
                               atol=tol * 10)
    np.testing.assert_array_equal(p[~approaching], 0.0)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_impulse_stays_in_coulomb_cone(device, scalar, np_dtype, tol):
    """With little friction the tangential part is mu times the normal part, against the slip."""
    rng = np.random.default_rng(2)
    count = 64
    n, vi, vj, wi, wj = _random_pairs(rng, count, np_dtype)
    mu = 0.1
    zeros = np.zeros((count, 3), np_dtype)
    p, p_swapped = _impulses(device, scalar, np_dtype, n, vi, vj, zeros, np.zeros(count), wi, wj, mu, 0.0)
    np.testing.assert_array_equal(p_swapped, -p)
    n64, p64 = n.astype(np.float64), p.astype(np.float64)
    vrel = (vi - vj).astype(np.float64)
    vn = np.einsum("ij,ij->i", vrel, n64)
    lam = np.einsum("ij,ij->i", p64, n64)
    tangential = p64 - lam[:, None] * n64
    slip = vrel - vn[:, None] * n64
    pushed = vn < 0.0
    m_eff = 1.0 / (wi + wj).astype(np.float64)
    np.testing.assert_allclose(lam[pushed], -vn[pushed] * m_eff[pushed], rtol=tol * 10)
    # Where cancelling the whole slip would take more than mu times the push, the impulse lies on
    # the cone's rim, against the slip; elsewhere it cancels the slip.
    slip_speed = np.linalg.norm(slip, axis=1)
    rim = pushed & (slip_speed > mu * -vn * 1.001)
    inside = pushed & (slip_speed < mu * -vn * 0.999)
    assert rim.sum() > 10 and inside.sum() > 0
    np.testing.assert_allclose(np.linalg.norm(tangential[rim], axis=1), mu * lam[rim], rtol=tol * 10)
    cos = np.einsum("ij,ij->i", tangential[rim], slip[rim])
    cos /= np.linalg.norm(tangential[rim], axis=1) * slip_speed[rim]
    np.testing.assert_allclose(cos, -1.0, atol=tol * 10)
    np.testing.assert_allclose(tangential[inside], -slip[inside] * m_eff[inside, None], rtol=tol * 10, atol=tol)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_impact_leaves_at_restitution_times_approach(device, scalar, np_dtype, tol):
    """An impact (approach speed u0 above the threshold) leaves at e u0 along the normal; a slow
    approach (below eps_v) is only stopped."""
    e = 0.5
    n = np.array([[0.0, 1.0, 0.0]] * 2, np_dtype)
    vi = np.array([[0.0, -2.0, 0.0], [0.0, -1.0e-4, 0.0]], np_dtype)
    vj = np.zeros((2, 3), np_dtype)
    u0 = np.array([2.0, 1.0e-4])
    w = np.array([1.0, 1.0])
    p, p_swapped = _impulses(device, scalar, np_dtype, n, vi, vj, np.zeros((2, 3), np_dtype), u0, w, w, 0.5, e)
    np.testing.assert_array_equal(p_swapped, -p)
    separation = (vi + p - (vj - p))[:, 1].astype(np.float64)
    np.testing.assert_allclose(separation, [e * 2.0, 0.0], atol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_accumulated_impulse_is_a_fixed_point(device, scalar, np_dtype, tol):
    """Started from its own result with the velocities it produced, the next iteration keeps the
    impulse (nothing left to cancel), also where friction caps it."""
    rng = np.random.default_rng(3)
    count = 32
    n, vi, vj, wi, wj = _random_pairs(rng, count, np_dtype)
    zeros = np.zeros((count, 3), np_dtype)
    mu = 0.3
    p, _ = _impulses(device, scalar, np_dtype, n, vi, vj, zeros, np.zeros(count), wi, wj, mu, 0.0)
    vi1 = (vi + wi[:, None] * p).astype(np_dtype)
    vj1 = (vj - wj[:, None] * p).astype(np_dtype)
    again, _ = _impulses(device, scalar, np_dtype, n, vi1, vj1, p, np.zeros(count), wi, wj, mu, 0.0)
    scale = np.linalg.norm(p.astype(np.float64), axis=1, keepdims=True) + 1.0
    np.testing.assert_allclose((again - p) / scale, 0.0, atol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_warm_impulse_keeps_push_drops_pull(device, scalar, np_dtype, tol):
    vec = wp.types.vector(3, scalar)
    n = np.array([[0.0, 1.0, 0.0]] * 3, np_dtype)
    p_prev = np.array([[0.05, 1.0, 0.0], [1.0, 1.0, 0.0], [0.1, -1.0, 0.0]], np_dtype)
    out = wp.zeros(3, dtype=vec, device=device)
    wp.launch(warm_impulses_of, 3, inputs=[_arr(p_prev, vec, device), _arr(n, vec, device), scalar(0.5)],
              outputs=[out], device=device)
    p = out.numpy()
    np.testing.assert_array_equal(p[0], p_prev[0])  # inside the cone: kept as it was
    np.testing.assert_allclose(p[1], [0.5, 1.0, 0.0], rtol=tol)  # tangential part cut to mu times the push
    np.testing.assert_array_equal(p[2], 0.0)  # it would pull


def _normals(device, scalar, np_dtype, x, pairs, d, normal, face_start):
    vec = wp.types.vector(3, scalar)
    count = len(pairs)
    n_ij, n_ji = (wp.zeros(count, dtype=vec, device=device) for _ in range(2))
    wp.launch(
        normals_of,
        count,
        inputs=[
            _arr(np.asarray(x, np_dtype), vec, device),
            _arr(np.asarray(pairs, np.int32), wp.vec2i, device),
            scalar(d),
            wp.array(np.asarray(normal, np_dtype), dtype=vec, device=device),
            wp.vec3i(*face_start),
        ],
        outputs=[n_ij, n_ji],
        device=device,
    )
    return n_ij.numpy(), n_ji.numpy()


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_pair_normal_is_faces_normal_or_the_direction_between(device, scalar, np_dtype, tol):
    """Particle 1 on the top face of a lower jelly (normal +y), particle 0 on the bottom face of an
    upper one (-y), 0.3 d aside: the contact normal is +y, not the tilted direction between them.
    Without faces, or far aside, it is that direction. Swapping the pair negates it exactly."""
    d = 0.1
    x = np.array(
        [[0.03, 0.095, 0.0], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5 + 0.06, 0.5 + 0.08, 0.5], [0.3, 0.06, 0.0]],
        np.float64,
    )
    # Slot 0 of every particle may hold a face normal (face_start[0] = 0), no particle has a second or
    # third face; 2 and 3 have zero normals, which pair_normal takes as no face.
    normal = np.zeros((3, 5, 3))
    normal[0, 0] = [0.0, -1.0, 0.0]
    normal[0, 1] = [0.0, 1.0, 0.0]
    normal[0, 4] = [0.0, -1.0, 0.0]
    face_start = (0, 5, 5)
    n_ij, n_ji = _normals(device, scalar, np_dtype, x, [[0, 1], [3, 2], [4, 1]], d, normal, face_start)
    np.testing.assert_array_equal(n_ji, -n_ij)
    np.testing.assert_allclose(n_ij[0], [0.0, 1.0, 0.0], atol=tol)
    u = (x[3] - x[2]) / np.linalg.norm(x[3] - x[2])
    np.testing.assert_allclose(n_ij[1], u, rtol=tol, atol=tol)
    # 3 d aside of the face (beyond FACE_REACH d + 0.25 d): the direction between them.
    u4 = (x[4] - x[1]) / np.linalg.norm(x[4] - x[1])
    np.testing.assert_allclose(n_ij[2], u4, rtol=tol, atol=tol)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_pair_normal_antisymmetric_on_random_pairs(device, scalar, np_dtype, tol):
    rng = np.random.default_rng(4)
    count = 40
    x = rng.uniform(-0.1, 0.1, (2 * count, 3))
    normal = np.zeros((3, 2 * count, 3))
    faces = rng.normal(size=(2, 2 * count, 3))
    normal[:2] = faces / np.linalg.norm(faces, axis=2, keepdims=True)
    pairs = [[2 * k, 2 * k + 1] for k in range(count)]
    n_ij, n_ji = _normals(device, scalar, np_dtype, x, pairs, 0.1, normal, (0, 0, 2 * count))
    np.testing.assert_array_equal(n_ji, -n_ij)
    np.testing.assert_allclose(np.linalg.norm(n_ij.astype(np.float64), axis=1), 1.0, rtol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_projection_removes_the_overlap_and_conserves_momentum(device, scalar, np_dtype, tol):
    """Case 0, at rest and overlapping by 1 cm: the positions move apart by the overlap, split by
    inverse mass, and no velocity changes. Case 1, i still approaching at 1 m/s: the approach is
    taken off up to the projected distance per step (0.01 / h), and m_i dv_i + m_j dv_j = 0."""
    vec = wp.types.vector(3, scalar)
    n = np.array([[0.0, 1.0, 0.0]] * 2, np_dtype)
    vi = np.array([[0.0, 0.0, 0.0], [0.0, -1.0, 0.0]], np_dtype)
    vj = np.zeros((2, 3), np_dtype)
    dp = np.zeros((2, 3), np_dtype)
    wi, wj, gap, h = 1.0, 0.25, -0.01, 0.02
    outs = [wp.zeros(2, dtype=vec, device=device) for _ in range(4)]
    wp.launch(
        projections_of,
        2,
        inputs=[_arr(n, vec, device), scalar(gap), _arr(dp, vec, device), _arr(vi, vec, device), _arr(vj, vec, device),
                scalar(wi), scalar(wj), scalar(0.0), scalar(h), scalar(0.5)],
        outputs=outs,
        device=device,
    )
    dx_i, dv_i, dx_j, dv_j = (o.numpy().astype(np.float64) for o in outs)
    split = wi + wj
    for case in range(2):
        np.testing.assert_allclose(dx_i[case], [0.0, 0.01 * wi / split, 0.0], rtol=tol * 10)
        np.testing.assert_allclose(dx_j[case], [0.0, -0.01 * wj / split, 0.0], rtol=tol * 10)
        np.testing.assert_allclose(dx_i[case][1] - dx_j[case][1], 0.01, rtol=tol * 10)  # the overlap, all of it
    np.testing.assert_array_equal(dv_i[0], 0.0)
    np.testing.assert_array_equal(dv_j[0], 0.0)
    jn = min(1.0, 0.01 / h)
    np.testing.assert_allclose(dv_i[1], [0.0, jn * wi / split, 0.0], rtol=tol * 10)
    np.testing.assert_allclose(dv_i[1] / wi + dv_j[1] / wj, 0.0, atol=tol * 10)  # masses 1/w


@both_precisions
@wp.kernel
def copy_through_tables(
    records: wp.array(dtype=vec4),
    table: wp.array2d(dtype=vec3),
    ints: wp.array2d(dtype=wp.int32),
    # Out: the same values written back through the native stores
    records_out: wp.array(dtype=vec4),
    table_out: wp.array2d(dtype=vec3),
    scalars_out: wp.array2d(dtype=Float),
    ints_out: wp.array2d(dtype=wp.int32),
):
    i = wp.tid()
    r = tables.load_vec4(records, i)
    tables.store_vec4(records_out, i, r)
    for s in range(table.shape[0]):
        tables.set_vec3_entry(table_out, s, i, tables.vec3_entry(table, s, i))
        tables.set_scalar_entry(scalars_out, s, i, tables.split_inv_mass(r, r) + type(r[0])(s))
        tables.set_int_entry(ints_out, s, i, tables.int_entry(ints, s, i) + 1)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_table_accessors_match_indexing(device, scalar, np_dtype, tol):
    """The data-pointer loads and stores address the same elements as Warp's ``a[s, i]``."""
    vec = wp.types.vector(3, scalar)
    v4 = wp.types.vector(4, scalar)
    rng = np.random.default_rng(5)
    n, slots = 7, 3
    records = rng.normal(size=(n, 4)).astype(np_dtype)
    table = rng.normal(size=(slots, n, 3)).astype(np_dtype)
    ints = rng.integers(-100, 100, (slots, n)).astype(np.int32)
    records_out = wp.zeros(n, dtype=v4, device=device)
    table_out = wp.zeros((slots, n), dtype=vec, device=device)
    scalars_out = wp.zeros((slots, n), dtype=scalar, device=device)
    ints_out = wp.zeros((slots, n), dtype=wp.int32, device=device)
    wp.launch(
        copy_through_tables,
        n,
        inputs=[_arr(records, v4, device), _arr(table, vec, device), _arr(ints, wp.int32, device)],
        outputs=[records_out, table_out, scalars_out, ints_out],
        device=device,
    )
    np.testing.assert_array_equal(records_out.numpy(), records)
    np.testing.assert_array_equal(table_out.numpy(), table)
    np.testing.assert_array_equal(ints_out.numpy(), ints + 1)
    expected = (records[:, 3] * records[:, 3])[None, :] + np.arange(slots, dtype=np_dtype)[:, None]
    np.testing.assert_allclose(scalars_out.numpy(), expected, rtol=tol)
