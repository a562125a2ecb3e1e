"""The implicit solve's kernels and funcs checked alone, float32 and float64.

``spring_jacobian`` (kernels/springs.py) is the one definition of a spring's blocks; the stability
model (core/stability_model.py) computes the same blocks in NumPy from its own factors, so that a
scene's step is checked before any kernel compiles. The two must stay the same physics: they are
compared here on random springs, stretched and compressed (where the clamp of the transverse
factor acts), with coincident ends, in float64 to 1e-13 of the block's size. Both are float64
evaluations of the same closed form in a different order of operations, so they differ by a few
units in the last place; any change of the formula on one side (the clamp, a factor of h, the
damper's direction) is a difference of order one.
"""

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels import implicit as implicit_kernels
from softsim_warp.kernels.precision import Float, both_precisions, mat33, vec3
from softsim_warp.kernels.springs import spring_force, spring_jacobian

from softsim_warp.core.stability_model import SpringOperator

SPRINGS = 400


@both_precisions
@wp.kernel(module="unique")
def jacobians_of(
    h: Float,
    d: wp.array(dtype=vec3),
    rest: wp.array(dtype=Float),
    ks: wp.array(dtype=Float),
    kd: wp.array(dtype=Float),
    b_out: wp.array(dtype=mat33),
    s_out: wp.array(dtype=mat33),
):
    i = wp.tid()
    b, s = spring_jacobian(d[i], rest[i], ks[i], kd[i], h)
    b_out[i] = b
    s_out[i] = s


@both_precisions
@wp.kernel(module="unique")
def forces_of(
    x: wp.array(dtype=vec3),
    v: wp.array(dtype=vec3),
    rest: wp.array(dtype=Float),
    ks: wp.array(dtype=Float),
    kd: wp.array(dtype=Float),
    f_out: wp.array(dtype=vec3),
):
    # Particle a at x with velocity v, particle b at rest at the origin.
    i = wp.tid()
    r = rest[i]
    zero = type(x[i])(type(r)(0.0))
    f_out[i] = spring_force(x[i], zero, v[i], zero, r, ks[i], kd[i])


def random_springs(rng, count=SPRINGS):
    """Random directions and lengths around the rest length (0.3x to 2x), and a few coincident ends."""
    direction = rng.standard_normal((count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    rest = rng.uniform(0.01, 2.0, count)
    d = direction * (rest * rng.uniform(0.3, 2.0, count))[:, None]
    d[:4] = 0.0
    ks = 10.0 ** rng.uniform(0, 6, count)
    kd = 10.0 ** rng.uniform(-3, 1, count)
    return d, rest, ks, kd


def jacobians(h, d, rest, ks, kd, scalar, np_scalar):
    vec = wp.types.vector(3, scalar)
    mat = wp.types.matrix((3, 3), scalar)
    arrays = [wp.array(d.astype(np_scalar), dtype=vec, device="cpu")]
    arrays += [wp.array(v.astype(np_scalar), dtype=scalar, device="cpu") for v in (rest, ks, kd)]
    b = wp.zeros(len(d), dtype=mat, device="cpu")
    s = wp.zeros(len(d), dtype=mat, device="cpu")
    wp.launch(jacobians_of, dim=len(d), inputs=[scalar(h), *arrays], outputs=[b, s], device="cpu")
    return b.numpy(), s.numpy()


def test_spring_jacobian_equals_the_stability_models_numpy_blocks():
    rng = np.random.default_rng(48)
    d, rest, ks, kd = random_springs(rng)
    h = 0.004
    b, s = jacobians(h, d, rest, ks, kd, wp.float64, np.float64)
    # The operator takes points and pairs: spring k joins particle 2k (at d_k) and 2k + 1 (at 0).
    points = np.zeros((2 * len(d), 3))
    points[0::2] = d
    pairs = np.arange(2 * len(d)).reshape(-1, 2)
    stiffness, damping = SpringOperator(points, pairs, rest, ks, kd, np.ones(2 * len(d))).spring_blocks()
    scale = ks[:, None, None] * np.ones((1, 3, 3))
    assert np.all(np.abs(s - stiffness) <= 1e-13 * scale)
    assert np.all(np.abs(b - (h * damping + h * h * stiffness)) <= 1e-13 * (h * kd + h * h * ks)[:, None, None])
    # Coincident ends: both blocks zero on both sides; compressed springs: S positive semi-definite.
    assert not np.any(b[:4]) and not np.any(s[:4]) and not np.any(stiffness[:4])
    assert np.min(np.linalg.eigvalsh(s)) >= -1e-12 * ks.max()


@pytest.mark.parametrize("scalar, np_scalar, rtol", [(wp.float32, np.float32, 1e-5), (wp.float64, np.float64, 1e-12)])
def test_spring_jacobian_is_the_derivative_of_the_spring_force(scalar, np_scalar, rtol):
    """-S is df_a/dx_a of spring_force (the wp.func) at v = 0 on a stretched spring, by central
    differences in float64 (where the damper's x-dependence, left out of S, vanishes), and
    B - h^2 S = h kd d^d^T is -h df_a/dv_a (the force is linear in v: differences are exact);
    float32 blocks to float32 rounding."""
    rng = np.random.default_rng(7)
    d, rest, ks, kd = random_springs(rng, 40)
    d, rest, ks, kd = d[4:], rest[4:], ks[4:], kd[4:]
    stretched = np.linalg.norm(d, axis=1) > rest
    h = 0.01
    b, s = jacobians(h, d, rest, ks, kd, scalar, np_scalar)

    def force(x, v, k):
        """spring_force (the wp.func, float64) on particle a at x with velocity v."""
        f = wp.zeros(1, dtype=wp.vec3d, device="cpu")
        arrays = [wp.array([x], dtype=wp.vec3d, device="cpu"), wp.array([v], dtype=wp.vec3d, device="cpu")]
        arrays += [wp.array([value[k]], dtype=wp.float64, device="cpu") for value in (rest, ks, kd)]
        wp.launch(forces_of, dim=1, inputs=arrays, outputs=[f], device="cpu")
        return f.numpy()[0]

    zero = np.zeros(3)
    for k in np.flatnonzero(stretched):
        step = 1e-6 * rest[k]
        jac_x = np.stack([(force(d[k] + step * e, zero, k) - force(d[k] - step * e, zero, k)) / (2 * step)
                          for e in np.eye(3)], axis=1)
        jac_v = np.stack([(force(d[k], e, k) - force(d[k], -e, k)) / 2 for e in np.eye(3)], axis=1)
        np.testing.assert_allclose(-s[k], jac_x, rtol=0, atol=max(rtol, 1e-7) * ks[k])
        np.testing.assert_allclose(b[k] - h * h * s[k], -h * jac_v, rtol=0, atol=rtol * (h * kd[k] + h * h * ks[k]))


@pytest.mark.parametrize("scalar, np_scalar, rtol", [(wp.float32, np.float32, 1e-5), (wp.float64, np.float64, 1e-12)])
def test_spring_jacobians_and_product_equal_the_dense_system(scalar, np_scalar, rtol):
    """eval_spring_jacobians and spring_mv (module-level kernels) on a random spring set: the
    diagonal sums, the df/dx v term and A p (spring part) and p.A p equal the dense matrix assembled
    in NumPy from the stability model's blocks, to the precision's rounding."""
    rng = np.random.default_rng(3)
    particles, springs, h, kv_scale = 30, 90, 0.01, 0.7
    points = rng.standard_normal((particles, 3))
    pairs = np.array([rng.choice(particles, 2, replace=False) for _ in range(springs)])
    rest = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1) * rng.uniform(0.5, 1.5, springs)
    ks, kd = rng.uniform(10.0, 1000.0, springs), rng.uniform(0.0, 1.0, springs)
    velocity, p = rng.standard_normal((particles, 3)), rng.standard_normal((particles, 3))
    stiffness, damping = SpringOperator(points, pairs, rest, ks, kd, np.ones(particles)).spring_blocks()
    dense_b = np.zeros((3 * particles, 3 * particles))
    dense_s = np.zeros_like(dense_b)
    for (a, b), block_s, block_d in zip(pairs, stiffness, damping):
        block_b = h * block_d + h * h * block_s
        for dense, block in ((dense_b, block_b), (dense_s, block_s)):
            for row, col, sign in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                dense[3 * row:3 * row + 3, 3 * col:3 * col + 3] += sign * block

    vec, mat = wp.types.vector(3, scalar), wp.types.matrix((3, 3), scalar)
    as_vec = lambda v: wp.array(v.astype(np_scalar), dtype=vec, device="cpu")
    as_scalar = lambda v: wp.array(v.astype(np_scalar), dtype=scalar, device="cpu")
    indices = wp.array(pairs.astype(np.int32), dtype=wp.vec2i, device="cpu")
    blocks = wp.zeros(springs, dtype=mat, device="cpu")
    diag = wp.zeros(particles, dtype=mat, device="cpu")
    rhs = wp.zeros(particles, dtype=vec, device="cpu")
    wp.launch(implicit_kernels.eval_spring_jacobians, dim=springs,
              inputs=[scalar(h), scalar(kv_scale), indices, as_scalar(rest), as_scalar(ks), as_scalar(kd),
                      as_vec(points), as_vec(velocity)],
              outputs=[blocks, diag, rhs], device="cpu")
    y = wp.zeros(particles, dtype=vec, device="cpu")
    sums = wp.zeros(implicit_kernels.SCALAR_SLOTS, dtype=scalar, device="cpu")
    wp.launch(implicit_kernels.spring_mv, dim=(implicit_kernels.tile_blocks(springs), implicit_kernels.TILE),
              block_dim=implicit_kernels.TILE, inputs=[springs, implicit_kernels.PAP, indices, blocks, as_vec(p)],
              outputs=[y, sums], device="cpu")

    size = np.abs(dense_b).max()
    diagonal = np.stack([dense_b[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(particles)])
    np.testing.assert_allclose(diag.numpy(), diagonal, rtol=0, atol=rtol * size)
    np.testing.assert_allclose(rhs.numpy().ravel(), -kv_scale * dense_s @ velocity.ravel(), rtol=0,
                               atol=rtol * np.abs(dense_s).max() * np.abs(velocity).max() * 10)
    expected = dense_b @ p.ravel()
    np.testing.assert_allclose(y.numpy().ravel(), expected, rtol=0, atol=rtol * size * np.abs(p).max() * 10)
    np.testing.assert_allclose(sums.numpy()[implicit_kernels.PAP], p.ravel() @ expected, rtol=10 * rtol)
