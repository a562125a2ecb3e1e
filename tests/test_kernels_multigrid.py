"""kernels/multigrid.py's module-level funcs and kernels, each checked alone in float32 and float64.

pair_product, the CG product's own form of a spring's block, is checked against the one
definition of that block (springs.spring_jacobian) on random springs.

The references are built here independently: the 1-D interpolation rule (coarse nodes on the even
fine nodes and on the last one, linear in between) and trilinear interpolation, which reproduces
every field linear in the lattice coordinates exactly. The weights are 0, 1/2 and 1 and the fields
small integers, so both precisions must agree with the reference exactly, not to a tolerance.
"""

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels import multigrid as multigrid_kernels
from softsim_warp.kernels.precision import Float, both_precisions, vec3
from softsim_warp.kernels.springs import spring_jacobian

from tests.test_multigrid import interpolation_1d

PRECISIONS = [(wp.float32, np.float32), (wp.float64, np.float64)]


@both_precisions
@wp.kernel(module="unique")
def axis_weights_of(n: int, nc: int, one: Float, weights_out: wp.array2d(dtype=Float)):
    # One thread: the 1-D interpolation matrix from the func, with a border of indices outside the
    # axis (row and column 0 and the last ones).
    for i in range(-1, n + 1):
        for c in range(-1, nc + 1):
            weights_out[i + 1, c + 1] = multigrid_kernels.axis_weight(i, c, n, nc, one)


@pytest.mark.parametrize("scalar, np_scalar", PRECISIONS)
def test_axis_weight_is_the_interpolation_rule(scalar, np_scalar):
    for n in (1, 2, 3, 4, 5, 8, 9):
        nc = multigrid_kernels.coarse_size(n)
        weights = wp.zeros((n + 2, nc + 2), dtype=scalar, device="cpu")
        wp.launch(axis_weights_of, dim=1, inputs=[n, nc, scalar(1.0)], outputs=[weights], device="cpu")
        got = weights.numpy()
        assert got.dtype == np_scalar
        # Indices outside the axis weigh zero (the kernels' branch-free loads rely on it).
        expected = np.zeros((n + 2, nc + 2), dtype=np_scalar)
        expected[1:-1, 1:-1] = interpolation_1d(n)
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("scalar, np_scalar", PRECISIONS)
def test_prolongation_reproduces_linear_fields(device, scalar, np_scalar):
    """mg_prolong (x += P e) on a coarse field linear in the lattice coordinates gives that field on
    the fine lattice, exactly: an odd, an even and a two-node axis."""
    shape = (7, 6, 2)
    coarse = tuple(multigrid_kernels.coarse_size(n) for n in shape)
    fine_coord = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), -1).reshape(-1, 3)
    # Coarse node c sits on fine node min(2 c, n - 1) (or on c itself on an axis it does not coarsen).
    positions = [np.minimum(2 * np.arange(nc), n - 1) if nc != n else np.arange(n) for n, nc in zip(shape, coarse)]
    coarse_coord = np.stack(np.meshgrid(*positions, indexing="ij"), -1).reshape(-1, 3)
    field = np.array([[2.0, -1.0, 4.0], [1.0, 3.0, -2.0], [-4.0, 1.0, 1.0]])
    vec = wp.types.vector(3, scalar)
    e = wp.array((coarse_coord @ field.T).astype(np_scalar), dtype=vec, device=device)
    x = wp.zeros(len(fine_coord), dtype=vec, device=device)
    wp.launch(multigrid_kernels.mg_prolong, dim=len(fine_coord), inputs=[wp.vec3i(*shape), wp.vec3i(*coarse), e], outputs=[x],
              device=device)
    np.testing.assert_array_equal(x.numpy(), (fine_coord @ field.T).astype(np_scalar))


@both_precisions
@wp.kernel(module="unique")
def pair_products_of(
    h: Float,
    qi: wp.array(dtype=vec3),
    qj: wp.array(dtype=vec3),
    pi: wp.array(dtype=vec3),
    pj: wp.array(dtype=vec3),
    rest: wp.array(dtype=Float),
    ks: wp.array(dtype=Float),
    kd: wp.array(dtype=Float),
    product_out: wp.array(dtype=vec3),
    quad_out: wp.array(dtype=Float),
    jacobian_product_out: wp.array(dtype=vec3),
):
    k = wp.tid()
    t, e = multigrid_kernels.pair_product(qi[k], qj[k], pi[k], pj[k], rest[k], ks[k], kd[k], h)
    product_out[k] = t
    quad_out[k] = e
    block, _stiffness = spring_jacobian(qi[k] - qj[k], rest[k], ks[k], kd[k], h)
    jacobian_product_out[k] = block * (pi[k] - pj[k])


@pytest.mark.parametrize("scalar, np_scalar, rtol", [(wp.float32, np.float32, 2e-6), (wp.float64, np.float64, 1e-14)])
def test_pair_product_is_the_spring_jacobians_block(scalar, np_scalar, rtol):
    """The CG product's branch-free form of a spring's block (pair_product) applies the block of
    springs.spring_jacobian, on random springs stretched and compressed, to the rounding of the
    precision (relative to |B| |p_i - p_j|); coincident ends give exactly zero, as the kernels'
    stand-in for an absent neighbour needs."""
    rng = np.random.default_rng(5)
    count = 300
    qi = rng.standard_normal((count, 3))
    direction = rng.standard_normal((count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    rest = rng.uniform(0.01, 1.0, count)
    qj = qi + direction * (rest * rng.uniform(0.3, 2.0, count))[:, None]
    qj[:5] = qi[:5]
    pi, pj = rng.standard_normal((count, 3)), rng.standard_normal((count, 3))
    ks, kd, h = 10.0 ** rng.uniform(0, 6, count), 10.0 ** rng.uniform(-3, 1, count), 0.01
    vec = wp.types.vector(3, scalar)
    vectors = [wp.array(v.astype(np_scalar), dtype=vec, device="cpu") for v in (qi, qj, pi, pj)]
    scalars = [wp.array(v.astype(np_scalar), dtype=scalar, device="cpu") for v in (rest, ks, kd)]
    product, reference = wp.zeros(count, dtype=vec, device="cpu"), wp.zeros(count, dtype=vec, device="cpu")
    quad = wp.zeros(count, dtype=scalar, device="cpu")
    wp.launch(pair_products_of, dim=count, inputs=[scalar(h), *vectors, *scalars], outputs=[product, quad, reference],
              device="cpu")
    t, t_ref, e = product.numpy(), reference.numpy(), quad.numpy()
    dp = (pi - pj).astype(np_scalar)
    size = (h * kd + h * h * ks) * np.linalg.norm(dp, axis=1)
    assert np.all(np.linalg.norm(t - t_ref, axis=1) <= rtol * size)
    np.testing.assert_allclose(e, np.einsum("ij,ij->i", dp, t), rtol=4 * rtol)
    assert not np.any(t[:5]) and not np.any(t_ref[:5]) and not np.any(e[:5])
