"""The geometric multigrid preconditioner of the implicit solve (core/multigrid.py, kernels/multigrid.py).

Checked against what cannot agree by accident: the Jacobi-preconditioned solve of the same step
(both converge to the same linear system's solution), a dense NumPy Galerkin product built from
the spring list independently of the kernels, and the two-grid convergence factor computed densely
from those matrices. The iteration counts at 8^3, 16^3 and 32^3 are the method's property that
block-Jacobi lacks (its counts double with each doubling of the resolution).
"""

import json

import numpy as np
import pytest
import warp as wp

from softsim_warp.commands.cli import main as cli_main

from softsim_warp.core.implicit import ImplicitIntegrator
from softsim_warp.core.lattice import SPRING_TYPE_NAMES, lattice_index
from softsim_warp.core.model import ModelBuilder
from softsim_warp.core import multigrid
from softsim_warp.core.multigrid import (
    AUTO_MIN_PARTICLES,
    DEFAULT_COARSE_OMEGA,
    DEFAULT_OMEGA,
    level_shapes,
    multigrid_support,
)
from softsim_warp.kernels import implicit as implicit_kernels
from softsim_warp.kernels.multigrid import coarse_size
from softsim_warp.kernels import multigrid as multigrid_kernels

# The benchmark's stiff jelly (benchmarks/bench_implicit.py): a 0.5 m cube of 1 kg, every spring
# at ks = 1e5, spinning in free flight; h^2 ks / m = 1e4 at 10^3 particles and dt = 0.01.
EDGE, TOTAL_MASS, KS, DT = 0.5, 1.0, 1.0e5, 0.01
DAMPING = {"structural": 0.5, "shear": 0.5, "bending": 0.25}


def stiff_jelly(size, device="cpu", precision="float64", plane=False, pinned=None, shape=None):
    shape = shape or (size,) * 3
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    count = int(np.prod(shape))
    mass = np.full(count, TOTAL_MASS / count)
    if pinned is not None:
        mass[pinned] = 0.0
    springs = {t: {"ks": KS, "kd": DAMPING[t]} for t in SPRING_TYPE_NAMES}
    if plane:
        # Resting on the ground: the lowest layer just inside the contact margin.
        b.add_jelly(shape, EDGE, mass, springs, center=(0.0, EDGE / 2, 0.0))
        b.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=0.0, friction=0.5)
    else:
        b.add_jelly(
            shape, EDGE, mass, springs, center=(0.0, 1.0, 0.0), axis=(1.0, 0.0, 1.0), degrees=20.0,
            angular_velocity=(2.0, 4.0, 1.0),
        )
    return b.finalize(device, precision)


def run(model, steps, **options):
    integ = ImplicitIntegrator(model, **options)
    a, b = model.state(), model.state()
    for _ in range(steps):
        integ.step(a, b, DT)
        a, b = b, a
    return integ, a


# -- the hierarchy's geometry --------------------------------------------------------------------


def test_coarse_sizes_keep_both_ends():
    assert [coarse_size(n) for n in (1, 2, 3, 4, 5, 6, 7, 8, 100)] == [1, 2, 2, 3, 3, 4, 4, 5, 51]
    assert level_shapes((100, 100, 100))[-1] == (2, 2, 2)
    assert level_shapes((100, 100, 100))[1] == (51, 51, 51)
    assert level_shapes((9, 4, 1)) == [(9, 4, 1), (5, 3, 1), (3, 2, 1), (2, 2, 1)]


def interpolation_1d(n):
    """P along one axis, [n, coarse_size(n)], from the rule in kernels/multigrid.py, built here independently."""
    nc = coarse_size(n)
    if nc == n:
        return np.eye(n)
    pos = np.minimum(2 * np.arange(nc), n - 1)
    p = np.zeros((n, nc))
    for i in range(n):
        hi = np.searchsorted(pos, i)
        if pos[hi] == i:
            p[i, hi] = 1.0
        else:
            t = (i - pos[hi - 1]) / (pos[hi] - pos[hi - 1])
            p[i, hi - 1], p[i, hi] = 1.0 - t, t
    return p


def interpolation(shape):
    px, py, pz = (interpolation_1d(n) for n in shape)
    return np.kron(np.kron(np.kron(px, py), pz), np.eye(3))


def test_interpolation_reproduces_linear_fields():
    for n in (3, 4, 5, 8):
        p = interpolation_1d(n)
        pos = np.minimum(2 * np.arange(coarse_size(n)), n - 1)
        np.testing.assert_allclose(p @ pos, np.arange(n), atol=1e-14)
        np.testing.assert_allclose(p.sum(axis=1), 1.0)


# -- dense references ------------------------------------------------------------------------------


def spring_blocks(model, q, h):
    """Each spring's block h kd d^d^T + h^2 ks [d^d^T + max(0, 1 - r/|d|) (I - d^d^T)] (kernels/implicit.py), float64."""
    pairs = model.spring_indices_host
    rest, ks, kd = (a.numpy().astype(np.float64) for a in (model.spring_rest_length, model.spring_stiffness,
                                                            model.spring_damping))
    d = q[pairs[:, 0]].astype(np.float64) - q[pairs[:, 1]].astype(np.float64)
    length = np.linalg.norm(d, axis=1)
    dhat = d / length[:, None]
    along = dhat[:, :, None] * dhat[:, None, :]
    transverse = np.maximum(1.0 - rest / length, 0.0)
    stiff = ks[:, None, None] * (along + transverse[:, None, None] * (np.eye(3) - along))
    return (h * kd)[:, None, None] * along + h * h * stiff


def dense_operators(integ):
    """(A, A_split, S): the fine system, the operator with split bending springs (projected), the filters.

    Built in float64 NumPy from the spring list, its rest lengths, ks and kd, and the integrator's
    linearisation point, masses and filters, independently of the multigrid kernels.
    """
    model = integ.model
    n = model.particle_count
    shape = tuple(model.lattice.layout.shape[0])
    coords = np.stack(np.unravel_index(np.arange(n), shape), axis=1)
    pairs = model.spring_indices_host
    blocks = spring_blocks(model, integ.multigrid.q_lin.numpy(), DT)
    me = integ.mass_eff.numpy().astype(np.float64)
    filters = integ.filters.numpy().astype(np.float64)

    def assemble(split):
        k = np.zeros((3 * n, 3 * n))

        def add(a, b, blk):
            sa, sb = slice(3 * a, 3 * a + 3), slice(3 * b, 3 * b + 3)
            k[sa, sa] += blk
            k[sb, sb] += blk
            k[sa, sb] -= blk
            k[sb, sa] -= blk

        for (a, b), blk in zip(pairs, blocks):
            off = coords[b] - coords[a]
            if split and np.abs(off).max() == 2:
                m = lattice_index(*((coords[a] + coords[b]) // 2), shape)
                add(a, m, 2 * blk)
                add(m, b, 2 * blk)
            else:
                add(a, b, blk)
        return k + np.kron(np.diag(me), np.eye(3))

    a = assemble(False)
    s = np.zeros((3 * n, 3 * n))
    scale = np.zeros(3 * n)
    for i in range(n):
        s[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = filters[i]
        scale[3 * i : 3 * i + 3] = np.trace(a[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]) / 3.0
    free = np.eye(3 * n) - s
    a_split = s @ assemble(True) @ s + np.diag(scale) @ free
    return a, a_split, s


def dense_stencil(level):
    """A level's 27-block stencil as a dense matrix."""
    shape = tuple(level["shape"])
    count = level["count"]
    st = level["a"].numpy().astype(np.float64)
    out = np.zeros((3 * count, 3 * count))
    for node in range(count):
        c = np.array(np.unravel_index(node, shape))
        for slot in range(27):
            o = np.array([slot // 9 - 1, (slot // 3) % 3 - 1, slot % 3 - 1])
            d = c + o
            if np.all(d >= 0) and np.all(d < shape):
                other = lattice_index(*d, shape)
                out[3 * node : 3 * node + 3, 3 * other : 3 * other + 3] = st[slot, node]
    return out


def block_diagonal(a):
    d = np.zeros_like(a)
    for i in range(0, a.shape[0], 3):
        d[i : i + 3, i : i + 3] = a[i : i + 3, i : i + 3]
    return d


def test_galerkin_levels_match_dense_products():
    """Every coarse operator is P^T A P of the level above (level 1 of the split, projected fine operator)."""
    model = stiff_jelly(6, pinned=[0, 1, 2])
    integ, _ = run(model, 1, preconditioner="multigrid")
    mg = integ.multigrid
    _, a_split, _ = dense_operators(integ)
    level0 = {"shape": mg.shapes[0], "count": model.particle_count, "a": mg.a0}
    np.testing.assert_allclose(dense_stencil(level0), a_split, rtol=1e-12, atol=1e-12 * np.abs(a_split).max())
    above, shape = a_split, mg.shapes[0]
    for lv in mg.levels:
        p = interpolation(shape)
        expected = p.T @ above @ p
        got = dense_stencil(lv)
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())
        above, shape = got, tuple(lv["shape"])


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_stencil_product_in_lanes_equals_one_thread(device, mode):
    """mg_stencil_op_lanes (a block per node, the small levels on CUDA; one thread on the CPU) gives
    the residual and the sweep of a NumPy reference to float64 rounding, on a random 27-block
    stencil of a 5 x 4 x 3 level (every boundary case: a neighbour outside the level adds nothing);
    mode 2, the sweep from x + P e, gives mg_prolong followed by mg_stencil_op's sweep."""
    shape = (5, 4, 3)
    coarse = tuple(coarse_size(v) for v in shape)
    count, coarse_count = int(np.prod(shape)), int(np.prod(coarse))
    rng = np.random.default_rng(11)
    mat33 = wp.types.matrix((3, 3), wp.float64)
    blocks = lambda *dims: wp.array(rng.standard_normal((*dims, 3, 3)), dtype=mat33, device=device)  # noqa: E731
    vecs = lambda m: wp.array(rng.standard_normal((m, 3)), dtype=wp.vec3d, device=device)  # noqa: E731
    a, rowsum, dinv, b, x, e = blocks(27, count), blocks(count), blocks(count), vecs(count), vecs(count), vecs(coarse_count)
    args = [min(mode, 1), wp.float64(0.5), wp.vec3i(*shape), a, rowsum, dinv, b]
    x_ref = wp.clone(x)
    if mode == 2:
        wp.launch(multigrid_kernels.mg_prolong, dim=count, inputs=[wp.vec3i(*shape), wp.vec3i(*coarse), e], outputs=[x_ref],
                  device=device)
    one = wp.zeros(count, dtype=wp.vec3d, device=device)
    wp.launch(multigrid_kernels.mg_stencil_op, dim=count, inputs=[*args, x_ref], outputs=[one], device=device)
    lanes = multigrid.LANES if device.is_cuda else 1
    out = wp.zeros(count, dtype=wp.vec3d, device=device)
    args[0] = mode
    wp.launch(multigrid_kernels.mg_stencil_op_lanes, dim=(count, lanes), block_dim=lanes,
              inputs=[lanes, *args, x, wp.vec3i(*coarse), e], outputs=[out], device=device)
    # The reference in NumPy: r = b - R x_I - sum_J A_IJ (x_J - x_I).
    a_h, x_h = a.numpy(), x_ref.numpy()
    r = b.numpy() - np.einsum("nij,nj->ni", rowsum.numpy(), x_h)
    for node in range(count):
        c = np.unravel_index(node, shape)
        for slot in range(27):
            o = np.array([slot // 9 - 1, (slot // 3) % 3 - 1, slot % 3 - 1])
            cj = np.array(c) + o
            if slot != 13 and np.all(cj >= 0) and np.all(cj < shape):
                j = np.ravel_multi_index(tuple(cj), shape)
                r[node] -= a_h[slot, node] @ (x_h[j] - x_h[node])
    expected = r if mode == 0 else x_h + 0.5 * np.einsum("nij,nj->ni", dinv.numpy(), r)
    np.testing.assert_allclose(one.numpy(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(out.numpy(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_lattice_gather_equals_the_stored_jacobians(device):
    """The per-particle gather (Jacobians, product) equals the spring-list kernels to float64 rounding.

    Reference: eval_spring_jacobians (one block per spring, atomically summed) and spring_mv over
    the spring list, at the same linearisation point, on a jelly deformed by a step and a random
    stretch, with a random p; the gather recomputes each block from the positions at both ends.
    """
    model = stiff_jelly(6, device=device)
    integ, _ = run(model, 1, preconditioner="multigrid")
    mg = multigrid.LatticeMultigrid(model, integ, gather=True)
    mg.q_lin.assign(integ.multigrid.q_lin)
    rng = np.random.default_rng(7)
    n, count = model.particle_count, model.spring_count
    q = mg.q_lin.numpy() * (1.0 + 0.05 * rng.standard_normal((n, 3)))
    qd = rng.standard_normal((n, 3))
    p = rng.standard_normal((n, 3))
    arr = lambda a: wp.array(a, dtype=model.vec3, device=device)  # noqa: E731
    q_w, qd_w, p_w = arr(q), arr(qd), arr(p)
    mat33 = wp.types.matrix((3, 3), model.scalar)
    blocks = wp.zeros(count, dtype=mat33, device=device)
    diag_ref = wp.zeros(n, dtype=mat33, device=device)
    rhs_ref = wp.zeros(n, dtype=model.vec3, device=device)
    h, kv = model.scalar(DT), model.scalar(DT * DT)
    wp.launch(
        implicit_kernels.eval_spring_jacobians, dim=count,
        inputs=[h, kv, model.spring_indices, model.spring_rest_length, model.spring_stiffness, model.spring_damping,
                q_w, qd_w],
        outputs=[blocks, diag_ref, rhs_ref], device=device,
    )
    diag = wp.zeros(n, dtype=mat33, device=device)
    rhs = wp.zeros(n, dtype=model.vec3, device=device)
    mg.jacobians(DT, DT * DT, q_w, qd_w, diag, rhs)
    scale = np.abs(diag_ref.numpy()).max()
    np.testing.assert_allclose(diag.numpy(), diag_ref.numpy(), rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(rhs.numpy(), rhs_ref.numpy(), rtol=0, atol=1e-13 * np.abs(rhs_ref.numpy()).max())
    # A p = M p + sum over springs (spring_mv accumulates onto y = M p).
    mass = integ.mass_eff.numpy()
    y_ref = arr(mass[:, None] * p)
    s_ref = wp.zeros(1, dtype=model.scalar, device=device)
    wp.launch(
        implicit_kernels.spring_mv, dim=(implicit_kernels.tile_blocks(count), implicit_kernels.TILE), block_dim=implicit_kernels.TILE,
        inputs=[count, 0, model.spring_indices, blocks, p_w], outputs=[y_ref, s_ref], device=device,
    )
    y = wp.empty(n, dtype=model.vec3, device=device)
    y.fill_(wp.inf)  # every element must be written
    s_fly = wp.zeros(1, dtype=model.scalar, device=device)
    mg.product(p_w, y, s_fly, 0)
    quad_ref = float(s_ref.numpy()[0]) + float((mass[:, None] * p * p).sum())
    np.testing.assert_allclose(y.numpy(), y_ref.numpy(), rtol=0, atol=1e-13 * np.abs(y_ref.numpy()).max())
    assert abs(float(s_fly.numpy()[0]) - quad_ref) < 1e-13 * quad_ref
    # And the product is that of the dense float64 operator built in NumPy.
    a_dense = np.zeros((3 * n, 3 * n))
    for (ia, ib), blk in zip(model.spring_indices_host, spring_blocks(model, q, DT)):
        for r, c, sign in ((ia, ia, 1), (ib, ib, 1), (ia, ib, -1), (ib, ia, -1)):
            a_dense[3 * r : 3 * r + 3, 3 * c : 3 * c + 3] += sign * blk
    a_dense += np.kron(np.diag(mass), np.eye(3))
    expected = (a_dense @ p.reshape(-1)).reshape(n, 3)
    np.testing.assert_allclose(y.numpy(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_setup_is_rebuilt_by_the_rule():
    """Free solves rebuild every setup_every-th time; a constrained solve and the free solve after it always."""
    model = stiff_jelly(3)
    integ = ImplicitIntegrator(model, preconditioner="multigrid")
    mg = multigrid.LatticeMultigrid(model, integ, setup_every=3)
    built = []
    mg.build = lambda: built.append(True)  # the rule only (capture_if calls build when due)
    flags = []
    for constrained in (False, False, False, False, False, True, False, False, True, True, False):
        before = len(built)
        mg.setup(constrained)
        flags.append(len(built) - before)
    assert flags == [1, 0, 0, 1, 0, 1, 1, 0, 1, 1, 1]


@pytest.mark.parametrize("every, gather", [(1, True), (5, True), (5, False)])
def test_lagged_setup_gives_the_same_step_as_jacobi(every, gather):
    """A hierarchy kept over several solves is a fixed SPD preconditioner: the same steps to the CG tolerance.

    Both products: the spring blocks recomputed per particle (gather, the CUDA default) and stored
    per spring (the CPU default).
    """
    tol = 1.0e-10
    out = {}
    for pc in ("jacobi", "multigrid"):
        model = stiff_jelly(7)
        integ = ImplicitIntegrator(model, preconditioner=pc, cg_tolerance=tol, cg_max_iterations=2000)
        if pc == "multigrid":
            integ.multigrid = multigrid.LatticeMultigrid(model, integ, setup_every=every, gather=gather)
        a, b = model.state(), model.state()
        for _ in range(6):
            integ.step(a, b, DT)
            a, b = b, a
        stats = integ.stats()
        assert stats["cg_unconverged_solves"] == 0 and stats["cg_relative_residual_max"] <= tol * (1 + 1e-6)
        out[pc] = a.particle_qd.numpy()
    assert np.abs(out["jacobi"] - out["multigrid"]).max() < 1e3 * tol * np.abs(out["jacobi"]).max()


def two_grid_factor(a, a_split, shape, omega):
    """Spectral radius of the two-grid error propagation: smooth, coarse correction with P^T A_split P, smooth."""
    p = interpolation(shape)
    coarse = p.T @ a_split @ p
    smoother = np.eye(len(a)) - omega * np.linalg.solve(block_diagonal(a), a)
    correction = np.eye(len(a)) - p @ np.linalg.solve(coarse, p.T @ a)
    return float(np.abs(np.linalg.eigvals(smoother @ correction @ smoother)).max())


def test_two_grid_convergence_factor():
    """The model problem: the stiff 7^3 jelly (h^2 ks / m = 3.4e3 per particle) after one step.

    One pre- and one post-sweep of block-Jacobi (omega = 0.8) around the exact coarse solve
    reduce every error component by at least 0.45 per cycle: measured 0.39 here (omega = 0.6:
    0.51; the smoother alone: 1 - 1e-4, the stiff system's near-rigid modes). With the bending
    springs split in the coarse operator the factor is the same to three digits as with the exact
    Galerkin product.
    """
    model = stiff_jelly(7)
    integ, _ = run(model, 1, preconditioner="multigrid")
    a, a_split, _ = dense_operators(integ)
    shape = integ.multigrid.shapes[0]
    rho = two_grid_factor(a, a_split, shape, DEFAULT_OMEGA)
    rho_exact = two_grid_factor(a, a, shape, DEFAULT_OMEGA)
    print(f"two-grid factor {rho:.3f} (exact Galerkin {rho_exact:.3f})")
    assert rho < 0.45
    assert abs(rho - rho_exact) < 0.01
    smoother_only = np.eye(len(a)) - DEFAULT_OMEGA * np.linalg.solve(block_diagonal(a), a)
    assert np.abs(np.linalg.eigvals(smoother_only)).max() > 0.99
    # The additive form (the default on the lattice): B = omega D^-1 + P A_c^-1 P^T. CG's
    # iterations follow the condition number of B A: measured 5.4, against 4.6e4 for block-Jacobi.
    dinv = np.linalg.inv(block_diagonal(a))
    p = interpolation(shape)
    b_add = DEFAULT_OMEGA * dinv + p @ np.linalg.solve(p.T @ a_split @ p, p.T)
    ev = np.linalg.eigvals(b_add @ a).real
    ev_jacobi = np.linalg.eigvals(dinv @ a).real
    kappa, kappa_jacobi = ev.max() / ev.min(), ev_jacobi.max() / ev_jacobi.min()
    print(f"condition numbers: additive two-level {kappa:.2f}, block-Jacobi {kappa_jacobi:.3g}")
    assert ev.min() > 0 and ev.max() / ev.min() < 6.0
    assert ev_jacobi.max() / ev_jacobi.min() > 1e4


def test_smoothers_converge_on_every_level():
    """omega lambda_max(D^-1 A) < 2 on every level, which makes the V-cycle SPD.

    Measured lambda_max: 1.73 on the jelly's lattice (at most 2 by construction), 2.5 to 3.2 on the
    Galerkin levels (9^3 and 12^3 jellies).
    """
    model = stiff_jelly(9)
    integ, _ = run(model, 1, preconditioner="multigrid")
    a, _, _ = dense_operators(integ)
    ops = [a] + [dense_stencil(lv) for lv in integ.multigrid.levels]
    for level, op in enumerate(ops):
        lam = np.linalg.eigvals(np.linalg.solve(block_diagonal(op), op)).real.max()
        if level == 0:
            assert lam <= 2.0 + 1e-9
        omega = DEFAULT_OMEGA if level == 0 else DEFAULT_COARSE_OMEGA
        assert omega * lam < 1.75, (level, lam)


@pytest.mark.parametrize("lanes", [False, True])
def test_vcycle_is_symmetric_positive_definite(lanes):
    """z = B r with B = V-cycle: B symmetric and positive definite, from its columns (float64);
    with ``lanes`` every coarse level takes the lane kernels (CUDA's path for small levels)."""
    model = stiff_jelly(5, pinned=[0])
    integ, _ = run(model, 1, preconditioner="multigrid")
    mg = multigrid.LatticeMultigrid(model, integ, lanes=lanes, deep_sweeps=2)
    mg.q_lin.assign(integ.multigrid.q_lin)
    mg.h = integ.multigrid.h
    mg.build()
    n = model.particle_count
    r = wp.zeros(n, dtype=model.vec3, device=model.device)
    z = wp.zeros(n, dtype=model.vec3, device=model.device)
    scalars = wp.zeros(8, dtype=model.scalar, device=model.device)
    cols = []
    for k in range(3 * n):
        e = np.zeros(3 * n)
        e[k] = 1.0
        if k // 3 == 0:
            e[:] = 0.0  # the pinned particle's row is filtered out
        r.assign(e.reshape(n, 3))
        mg.apply(r, z, scalars, 0)
        cols.append(z.numpy().reshape(-1).copy())
    b = np.array(cols).T
    np.testing.assert_allclose(b, b.T, atol=1e-12 * np.abs(b).max())
    free = b[3:, 3:]
    assert np.linalg.eigvalsh(0.5 * (free + free.T)).min() > 0.0
    assert np.abs(b[:3]).max() == 0.0 and np.abs(b[:, :3]).max() == 0.0


# -- the solve -------------------------------------------------------------------------------------


def test_same_step_as_jacobi(device):
    """Both preconditioners solve the same system: the steps agree to the CG tolerance (float64).

    At this tight tolerance (1e-10) block-Jacobi takes 82 CG iterations per step on the 8^3 jelly,
    multigrid 36.
    """
    tol = 1.0e-10
    out = {}
    for pc in ("jacobi", "multigrid"):
        model = stiff_jelly(8, device=device)
        integ, state = run(model, 3, preconditioner=pc, cg_tolerance=tol, cg_max_iterations=2000)
        assert integ.preconditioner == pc
        stats = integ.stats()
        assert stats["cg_unconverged_solves"] == 0
        assert 0.0 < stats["cg_relative_residual_max"] <= tol * (1 + 1e-6)
        assert stats["cg_relative_residual_mean"] <= stats["cg_relative_residual_max"]
        out[pc] = (state.particle_qd.numpy(), stats["cg_iterations_mean"])
    v_j, v_m = out["jacobi"][0], out["multigrid"][0]
    scale = np.abs(v_j).max()
    assert np.abs(v_j - v_m).max() < 1e3 * tol * scale
    assert out["multigrid"][1] < out["jacobi"][1] / 2.0


def test_iterations_do_not_grow_with_resolution(device):
    """CG iterations per step at 8^3, 16^3 and 32^3 stay within 1.5x of each other (block-Jacobi: about 4x)."""
    counts = []
    for size in (8, 16, 32):
        model = stiff_jelly(size, device=device, precision="float32")
        integ, state = run(model, 2, preconditioner="multigrid")
        stats = integ.stats()
        assert stats["cg_unconverged_solves"] == 0
        assert np.isfinite(state.particle_q.numpy()).all()
        counts.append(stats["cg_iterations_mean"])
    print("multigrid CG iterations per step at 8, 16, 32:", counts)
    assert max(counts) <= 1.5 * min(counts)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_contact_and_pins(device, precision):
    """A jelly resting on a plane, with one edge pinned: the same steps as with Jacobi."""
    shape = (6, 5, 4)
    pinned = [lattice_index(0, 4, k, shape) for k in range(4)]
    out = {}
    for pc in ("jacobi", "multigrid"):
        model = stiff_jelly(0, device=device, precision=precision, plane=True, pinned=pinned, shape=shape)
        # float32 solved to 1e-6: the resting jelly's velocities (4e-6 m/s) are of the size of what
        # a 1e-5 solve leaves undetermined, so the two preconditioners' answers differ by that much.
        tol = 1e-10 if precision == "float64" else 1e-6
        integ, state = run(model, 4, preconditioner=pc, cg_tolerance=tol, cg_max_iterations=2000)
        assert integ.preconditioner == pc
        assert integ.stats()["cg_unconverged_solves"] == 0
        q = state.particle_q.numpy()
        assert np.isfinite(q).all()
        out[pc] = (q, state.particle_qd.numpy())
    q0 = stiff_jelly(0, precision=precision, plane=True, pinned=pinned, shape=shape).state().particle_q.numpy()
    # Pinned particles stay put, nothing sinks below the plane's contact margin.
    np.testing.assert_array_equal(out["multigrid"][0][pinned], q0[pinned])
    assert out["multigrid"][0][:, 1].min() > -1e-3
    bound = 1e-6 if precision == "float64" else 1e-2
    assert np.abs(out["jacobi"][1] - out["multigrid"][1]).max() < bound * max(np.abs(out["jacobi"][1]).max(), 1e-3)


def test_captured_steps_with_contact_equal_launched_steps(device):
    """A jelly dropping onto a plane, stepped by replaying captured graphs (as `softsim run` does) and
    launch by launch: the same states. The lagged hierarchy's counter lives on the device, and the
    contact solve's kernels (restitution reads the spring list, which multigrid never makes) are
    first replayed inside a graph captured before any contact."""
    from softsim_warp.core.stepper import Stepper

    out = []
    for graph in (True, False):
        b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
        springs = {t: {"ks": KS, "kd": DAMPING[t]} for t in SPRING_TYPE_NAMES}
        b.add_jelly((5, 5, 5), 0.25, 0.5, springs, center=(0.0, 0.2, 0.0), axis=(1.0, 0.0, 1.0), degrees=20.0)
        b.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=0.5, friction=0.5)
        model = b.finalize(device, "float32")
        integ = ImplicitIntegrator(model, preconditioner="multigrid")
        assert model.has_derived("spring_indices")  # made before any capture
        stepper = Stepper(model, integ, DT, use_graph=graph)
        for _ in range(12):
            stepper.advance(2)
        stats = integ.stats()
        assert stats["cg_unconverged_solves"] == 0 and stats["cg_solves"] > stats["cg_steps"]  # contact solves ran
        out.append((stepper.state.particle_q.numpy(), stepper.state.particle_qd.numpy()))
    assert np.isfinite(out[0][0]).all() and out[0][0][:, 1].min() > -1e-2
    if device.is_cpu:  # the same kernels in the same order: the same bits
        assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])
    else:  # the implicit solve's sums use atomics, whose order varies on CUDA
        np.testing.assert_allclose(out[0][0], out[1][0], rtol=0, atol=1e-6)
        np.testing.assert_allclose(out[0][1], out[1][1], rtol=0, atol=1e-4)


def test_fallback_and_choice():
    """auto picks multigrid for a large enough lattice jelly; other models fall back to jacobi and say why."""
    assert multigrid_support(stiff_jelly(4))[0]
    integ = ImplicitIntegrator(stiff_jelly(4))
    assert integ.preconditioner == "jacobi" and "auto" in integ.preconditioner_note
    assert 8**3 < AUTO_MIN_PARTICLES <= 16**3
    assert ImplicitIntegrator(stiff_jelly(8)).preconditioner == "jacobi"
    assert ImplicitIntegrator(stiff_jelly(16)).preconditioner == "multigrid"
    b = ModelBuilder()
    springs = {t: {"ks": KS, "kd": 0.0} for t in SPRING_TYPE_NAMES}
    b.add_jelly((3, 3, 3), 0.2, 0.01, springs, center=(0, 0, 0))
    b.add_jelly((3, 3, 3), 0.2, 0.01, springs, center=(1, 0, 0))
    integ = ImplicitIntegrator(b.finalize("cpu"), preconditioner="multigrid")
    assert integ.preconditioner == "jacobi" and "2 jellies" in integ.preconditioner_note
    with pytest.raises(ValueError, match="preconditioner must be one of"):
        ImplicitIntegrator(stiff_jelly(4), preconditioner="amg")
    assert ImplicitIntegrator(stiff_jelly(8), preconditioner="block_jacobi").preconditioner == "jacobi"
    # The scalar Jacobi variant solves the same system as the block one.
    out = []
    for pc in ("diagonal", "jacobi"):
        integ, state = run(stiff_jelly(4), 2, preconditioner=pc, cg_tolerance=1e-10, cg_max_iterations=2000)
        assert integ.preconditioner == pc and integ.stats()["cg_unconverged_solves"] == 0
        out.append(state.particle_qd.numpy())
    assert np.abs(out[0] - out[1]).max() < 1e-6 * np.abs(out[1]).max()


# -- the scene key ----------------------------------------------------------------------------------


@pytest.mark.parametrize("choice, used", [("multigrid", "multigrid"), ("jacobi", "jacobi")])
def test_scene_key_chooses_the_preconditioner(tmp_path, choice, used):
    """``--set implicit.preconditioner=...`` reaches the integrator; the metrics say which one ran."""
    metrics = tmp_path / "m.json"
    rc = cli_main(
        [
            "run", "jelly_drop", "--integrator", "implicit", "--set", f"implicit.preconditioner={choice}",
            "--dt", "0.01", "--frames", "2", "--fps", "50", "--out", str(tmp_path / "x.usdc"),
            "--metrics", str(metrics), "--quiet",
        ]
    )
    assert rc == 0
    summary = json.loads(metrics.read_text())["summary"]
    assert summary["cg_preconditioner"] == used and summary["cg_unconverged_solves"] == 0
    assert summary["cg_relative_residual_max"] <= summary["cg_tolerance"] * (1 + 1e-3)
    assert ("multigrid_levels" in summary) == (used == "multigrid")


def test_bad_preconditioner_is_a_one_line_error(tmp_path, capsys):
    rc = cli_main(
        [
            "run", "jelly_drop", "--integrator", "implicit", "--set", "implicit.preconditioner=amg",
            "--out", str(tmp_path / "x.usdc"), "--quiet",
        ]
    )
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err
    assert "implicit.preconditioner: must be one of auto, multigrid, jacobi" in err
    assert len(err.strip().splitlines()) == 1


# -- the Newton peer (benchmark helpers) -----------------------------------------------------------


def test_lattice_coloring_separates_every_spring():
    from softsim_warp.studies.bench_newton import lattice_coloring
    from softsim_warp.core.lattice import lattice_springs

    shape = (5, 4, 6)
    groups = lattice_coloring(shape)
    color = np.full(int(np.prod(shape)), -1)
    for c, g in enumerate(groups):
        assert np.all(color[g] == -1)
        color[g] = c
    assert np.all(color >= 0)
    pairs, _ = lattice_springs(shape)
    assert np.all(color[pairs[:, 0]] != color[pairs[:, 1]])


def test_implicit_peer_reports_both_solvers():
    """``softsim bench --peer newton`` with implicit: our step is within its CG tolerance of the float64 reference."""
    pytest.importorskip("newton")
    from softsim_warp.studies.bench_newton import implicit_peer

    rows = implicit_peer(4, KS, 0.1, DT, "cpu", steps=2, error_steps=3, vbd_iterations=(10,), repeats=1)
    assert [r["solver"].split()[0] for r in rows] == ["softsim", "newton.SolverVBD"]
    assert all(np.isfinite(r["ms_per_step"]) and r["ms_per_step"] > 0 for r in rows)
    assert rows[0]["error_over_edge"] < 1e-3
    assert np.isfinite(rows[1]["error_over_edge"])
