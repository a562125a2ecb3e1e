"""kernels/lattice.py alone: every lattice path against the one spring force and the one stage update.

``springs.spring_force`` is the spring force and ``integration.stage_values`` the stage update
(issue 48). The lattice paths that do not call them are checked against them here, on random
springs, in float32 and float64:

* ``stencil_spring_force`` (the Warp gathers) and the ``SOFTSIM_SPRING`` macro (the native C++
  gathers) are ``spring_force`` rewritten with one reciprocal square root and a precomputed ks r:
  against ``spring_force`` to a few ulps of the spring's scale, and against each other bit for bit
  on the CPU (the same operations in the same order).
* ``_ROWS_FORCES`` (``eval_lattice_rows``, the CPU path): a random lattice jelly's forces against the
  spring list evaluated with ``spring_force`` (``eval_springs``) and a float64 reference.
* ``_ROWS_STAGE`` (``integrate_lattice_rows_stage``): each stage of each method against
  ``eval_lattice_rows`` followed by ``integration.integrate_stage`` (``stage_values``): bit for bit
  on the CPU, a few ulps on CUDA (fused multiply-adds).
"""

import itertools

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels import integration, lattice, springs
from softsim_warp.kernels.precision import Float, both_precisions, vec3

from tests.test_kernels_springs import random_springs, reference_force

PRECISIONS = [(wp.float32, np.float32), (wp.float64, np.float64)]
CTYPES = {wp.float32: "float", wp.float64: "double"}


@both_precisions
@wp.kernel
def spring_forms(
    xa: wp.array(dtype=vec3),
    xb: wp.array(dtype=vec3),
    va: wp.array(dtype=vec3),
    vb: wp.array(dtype=vec3),
    rest: wp.array(dtype=Float),
    ks: wp.array(dtype=Float),
    kd: wp.array(dtype=Float),
    spring_out: wp.array(dtype=vec3),
    stencil_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    spring_out[i] = springs.spring_force(xa[i], xb[i], va[i], vb[i], rest[i], ks[i], kd[i])
    stencil_out[i] = lattice.stencil_spring_force(xa[i], xb[i], va[i], vb[i], rest[i] * ks[i], -ks[i], kd[i])


def macro_kernel(scalar):
    """A kernel evaluating one spring per thread with the native gathers' ``SOFTSIM_SPRING`` macro."""
    vec = wp.types.vector(3, scalar)
    body = lattice._spring_macros(CTYPES[scalar]) + (
        f"typedef {CTYPES[scalar]} T;\n"
        "const T x0 = x[0], x1 = x[1], x2 = x[2], v0 = v[0], v1 = v[1], v2 = v[2];\n"
        "const T bx = xb[0], by = xb[1], bz = xb[2], ux = vb[0], uy = vb[1], uz = vb[2];\n"
        "T f0 = T(0), f1 = T(0), f2 = T(0);\n"
        "SOFTSIM_SPRING(kr, nks, kd, true);\n"
        "return wp::vec_t<3, T>(f0, f1, f2);\n#undef SOFTSIM_SPRING\n#undef SOFTSIM_RSQRT\n"
    )

    @wp.func_native(body)
    def macro_spring_force(x: vec, xb: vec, v: vec, vb: vec, kr: scalar, nks: scalar, kd: scalar) -> vec: ...

    @wp.kernel(module="unique")
    def macro_forces(
        xa: wp.array(dtype=vec),
        xb: wp.array(dtype=vec),
        va: wp.array(dtype=vec),
        vb: wp.array(dtype=vec),
        rest: wp.array(dtype=scalar),
        ks: wp.array(dtype=scalar),
        kd: wp.array(dtype=scalar),
        f_out: wp.array(dtype=vec),
    ):
        i = wp.tid()
        f_out[i] = macro_spring_force(xa[i], xb[i], va[i], vb[i], rest[i] * ks[i], -ks[i], kd[i])

    return macro_forces


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
def test_stencil_and_native_spring_forces_are_spring_force(device, scalar, np_dtype):
    data = random_springs(500, np_dtype, seed=17)
    vec = wp.types.vector(3, scalar)
    n = len(data[4])
    inputs = [wp.array(t, dtype=vec, device=device) for t in data[:4]]
    inputs += [wp.array(t, dtype=scalar, device=device) for t in data[4:]]
    spring, stencil, macro = (wp.zeros(n, dtype=vec, device=device) for _ in range(3))
    wp.launch(spring_forms, n, inputs=inputs, outputs=[spring, stencil], device=device)
    wp.launch(macro_kernel(scalar), n, inputs=inputs, outputs=[macro], device=device)
    spring, stencil, macro = spring.numpy(), stencil.numpy(), macro.numpy()

    # Against spring_force: both forms round differently (rsqrt and ks r instead of sqrt, a division
    # and ks (l - r)); each is within a few roundings of the exact force, measured on the scale
    # ks (|d| + r) + kd |dv| of its terms. On CUDA float32 rsqrtf adds its 2 ulp.
    xa, xb, va, vb, rest, ks, kd = (np.asarray(t, dtype=np.float64) for t in data)
    scale = ks * (np.linalg.norm(xa - xb, axis=1) + rest) + kd * np.linalg.norm(va - vb, axis=1)
    bound = 16 * np.finfo(np_dtype).eps * scale[:, None]
    exact = reference_force(*data)
    for form in (spring, stencil, macro):
        assert np.all(np.abs(form - exact) <= bound)
        assert np.all(np.abs(form - spring) <= 2 * bound)
    np.testing.assert_array_equal(stencil[:3], 0.0)  # coincident endpoints: zero force in every form
    np.testing.assert_array_equal(macro[:3], 0.0)
    if device.is_cpu:
        # The same operations in the same order: the Warp stencil force is the C++ macro.
        np.testing.assert_array_equal(stencil, macro)


def random_jelly(device, scalar, np_dtype, shape=(3, 4, 5), types=7, seed=0):
    """One lattice jelly with random rest lengths, ks and kd per type, a jittered placement and random
    velocities: the lattice tables, its spring list, and the state."""
    rng = np.random.default_rng(seed)
    vec = wp.types.vector(3, scalar)
    nx, ny, nz = shape
    n = nx * ny * nz
    grid = np.array(list(itertools.product(range(nx), range(ny), range(nz))), dtype=np.float64)
    spacing = 0.1
    q = grid * spacing + rng.normal(scale=0.01, size=(n, 3))
    qd = rng.normal(size=(n, 3))
    ks = rng.uniform(100.0, 2000.0, 3)
    kd = rng.uniform(0.0, 3.0, 3)
    rest = np.zeros(lattice.REST_SLOTS)
    pairs, pair_rest, pair_ks, pair_kd = [], [], [], []
    for off, ty in lattice.HALF_OFFSETS:
        r = spacing * np.linalg.norm(off) * rng.uniform(0.9, 1.1)
        rest[lattice.rest_slot(*off)] = rest[lattice.rest_slot(*(-o for o in off))] = r
        if not (types >> ty) & 1:
            continue
        for p, (a, b, c) in enumerate(grid.astype(int)):
            if 0 <= a + off[0] < nx and 0 <= b + off[1] < ny and 0 <= c + off[2] < nz:
                pairs.append((p, p + (off[0] * ny + off[1]) * nz + off[2]))
                pair_rest.append(r)
                pair_ks.append(ks[ty])
                pair_kd.append(kd[ty])
    def to(x, dtype):
        return wp.array(np.asarray(x, dtype=np_dtype if dtype is scalar else None), dtype=dtype, device=device)

    tables = [
        wp.array([0], dtype=wp.int32, device=device),
        wp.array([shape], dtype=wp.vec3i, device=device),
        wp.array([types], dtype=wp.int32, device=device),
        wp.array2d(rest[None, :].astype(np_dtype), dtype=scalar, device=device),
        wp.array2d(ks[None, :].astype(np_dtype), dtype=scalar, device=device),
        wp.array2d(kd[None, :].astype(np_dtype), dtype=scalar, device=device),
    ]
    coord_k = wp.array((np.arange(n) % nz).astype(np.int32), dtype=wp.int32, device=device)
    spring_list = [
        wp.array(np.asarray(pairs, dtype=np.int32), dtype=wp.vec2i, device=device),
        *(to(t, scalar) for t in (pair_rest, pair_ks, pair_kd)),
    ]
    state = [to(q, vec), to(qd, vec)]
    lists = (np.asarray(t, dtype=np_dtype) for t in (pair_rest, pair_ks, pair_kd))
    host = (np.asarray(pairs), q.astype(np_dtype), qd.astype(np_dtype), *lists)
    return tables, coord_k, spring_list, state, host


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
@pytest.mark.parametrize("types", [7, 1, 6])
def test_row_loops_are_the_spring_list_of_spring_force(device, scalar, np_dtype, types):
    vec = wp.types.vector(3, scalar)
    tables, coord_k, spring_list, (q, qd), host = random_jelly(device, scalar, np_dtype, types=types, seed=types)
    n = q.shape[0]
    rows = wp.zeros(n, dtype=vec, device=device)
    wp.launch(
        lattice.eval_lattice_rows,
        1,
        inputs=[*tables, coord_k, q, qd, wp.zeros(n, dtype=vec, device=device)],
        outputs=[rows],
        device=device,
    )
    listed = wp.zeros(n, dtype=vec, device=device)
    wp.launch(springs.eval_springs, len(host[0]), inputs=[*spring_list, q, qd], outputs=[listed], device=device)
    gathered = wp.zeros(n, dtype=vec, device=device)
    wp.launch(
        lattice.eval_lattice_springs,
        n,
        inputs=[wp.zeros(n, dtype=wp.int32, device=device), *tables, q, qd],
        outputs=[gathered],
        device=device,
    )
    pairs, xq, xqd, rest, ks, kd = host
    per_spring = reference_force(xq[pairs[:, 0]], xq[pairs[:, 1]], xqd[pairs[:, 0]], xqd[pairs[:, 1]], rest, ks, kd)
    exact = np.zeros((n, 3))
    np.add.at(exact, pairs[:, 0], per_spring)
    np.add.at(exact, pairs[:, 1], -per_spring)
    # Up to 32 springs a particle, each within a few roundings of its scale, summed in three orders.
    x64 = xq.astype(np.float64)
    scale = ks * (np.linalg.norm(x64[pairs[:, 0]] - x64[pairs[:, 1]], axis=1) + rest) + kd * np.linalg.norm(
        xqd[pairs[:, 0]].astype(np.float64) - xqd[pairs[:, 1]], axis=1
    )
    bound = 64 * np.finfo(np_dtype).eps * scale.max()
    for forces in (rows, listed, gathered):
        assert np.abs(forces.numpy() - exact).max() <= bound
    assert np.abs(rows.numpy() - listed.numpy()).max() <= 2 * bound


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
@pytest.mark.parametrize("method", ["euler", "symplectic", "midpoint", "rk4"])
def test_row_stage_is_stage_values(device, scalar, np_dtype, method):
    """``_ROWS_STAGE`` against ``stage_values``: every stage of a step from the same forces."""
    c, b = {
        "euler": ((0.0,), (1.0,)),
        "symplectic": ((0.0,), (1.0,)),
        "midpoint": ((0.0, 0.5), (0.0, 1.0)),
        "rk4": ((0.0, 0.5, 0.5, 1.0), (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)),
    }[method]
    vec = wp.types.vector(3, scalar)
    tables, coord_k, _list, (q, qd), _host = random_jelly(device, scalar, np_dtype, seed=4)
    n = q.shape[0]
    rng = np.random.default_rng(9)
    inv_mass = rng.uniform(0.5, 2.0, n)
    inv_mass[::7] = 0.0  # pinned particles
    world = [
        wp.array(inv_mass.astype(np_dtype), dtype=scalar, device=device),
        vec(scalar(0.0), scalar(-9.81), scalar(0.0)),
        wp.array([len(c)], dtype=wp.int32, device=device),
        wp.array([int(method == "symplectic")], dtype=wp.int32, device=device),
        wp.array2d(np.asarray([c], dtype=np_dtype), dtype=scalar, device=device),
        wp.array2d(np.asarray([b], dtype=np_dtype), dtype=scalar, device=device),
    ]
    h = scalar(1.0e-3)
    zeros = lambda: wp.zeros(n, dtype=vec, device=device)
    runs = {}
    for fused in (True, False):
        out = [zeros() for _ in range(6)]  # acc_q, acc_qd, q_next, qd_next, q_out, qd_out
        q_s, qd_s = q, qd
        history = []
        for stage in range(len(c)):
            if fused:
                wp.launch(
                    lattice.integrate_lattice_rows_stage,
                    1,
                    inputs=[
                        stage, h, *tables, wp.zeros(1, dtype=wp.int32, device=device), coord_k, *world,
                        q, qd, q_s, qd_s, zeros(), zeros(),
                    ],
                    outputs=out,
                    device=device,
                )
            else:
                f = zeros()
                wp.launch(lattice.eval_lattice_rows, 1, inputs=[*tables, coord_k, q_s, qd_s, zeros()], outputs=[f],
                          device=device)
                wp.launch(
                    integration.integrate_stage,
                    n,
                    inputs=[
                        stage, h, world[0], wp.zeros(n, dtype=wp.int32, device=device), *world[1:],
                        q, qd, q_s, qd_s, f,
                    ],
                    outputs=out,
                    device=device,
                )
            history.append([a.numpy().copy() for a in out])
            q_s, qd_s = wp.clone(out[2]), wp.clone(out[3])
        runs[fused] = history
    for fused_stage, plain_stage in zip(runs[True], runs[False]):
        for fused_array, plain_array in zip(fused_stage, plain_stage):
            if device.is_cpu:
                # Warp's CPU build does not contract a * b + c: the same operations, the same bits.
                np.testing.assert_array_equal(fused_array, plain_array)
            else:
                # nvcc may contract a * b + c into one fused multiply-add in one kernel and not in the
                # other: at most one rounding of the largest term a stage, a few ulps.
                scale = np.abs(plain_array).max() + 1.0
                assert np.abs(fused_array - plain_array).max() <= 4 * np.finfo(np_dtype).eps * scale
