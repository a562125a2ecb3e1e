"""kernels/metrics.py alone: each reduction against a float64 NumPy reference, float32 and float64.

The atomic kernels and the fixed-order chunk kernels give the same sums (to rounding), a particle
that is not finite is counted and left out, and the penetration of a particle below a plane, inside
a sphere or cut by a bowl's shell is its signed distance's closed form.
"""

import numpy as np
import pytest
import warp as wp

from softsim_warp.kernels import metrics

PRECISIONS = [(wp.float32, np.float32, 2.0e-5), (wp.float64, np.float64, 1.0e-12)]


def _particles(np_dtype, count=300, jellies=3, seed=0):
    rng = np.random.default_rng(seed)
    jelly = np.sort(rng.integers(0, jellies, count)).astype(np.int32)
    mass = rng.uniform(0.1, 2.0, count).astype(np_dtype)
    q = rng.normal(size=(count, 3)).astype(np_dtype)
    qd = rng.normal(size=(count, 3)).astype(np_dtype)
    qd[17] = [np.nan, 0.0, 0.0]  # a particle that is not finite: counted, left out of the sums
    return jelly, mass, q, qd


def _reference_particles(jelly, mass, q, qd, gravity, jellies):
    """Per jelly: kinetic energy, gravity energy, mass-weighted position, max speed, non-finite count."""
    m, x, v, g = (np.asarray(a, np.float64) for a in (mass, q, qd, gravity))
    ok = np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1)
    out = []
    for j in range(jellies):
        s = (jelly == j) & ok
        speed = np.linalg.norm(v[s], axis=1)
        out.append((
            0.5 * np.sum(m[s] * speed**2),
            -np.sum(m[s] * (x[s] @ g)),
            (m[s, None] * x[s]).sum(axis=0),
            speed.max(),
            int(np.sum((jelly == j) & ~ok)),
            np.sum(m[s] * np.abs(x[s]).sum(axis=1)) * np.abs(g).sum(),  # the sums' scale: terms cancel
        ))
    return out


def _chunks(owner, chunk=16):
    """Chunks of at most ``chunk`` consecutive items of one owner, and each owner's first chunk."""
    starts, ends, first = [], [], [0]
    for j in range(owner.max() + 1):
        idx = np.flatnonzero(owner == j)
        for a in range(idx[0], idx[-1] + 1, chunk):
            starts.append(a)
            ends.append(min(a + chunk, idx[-1] + 1))
        first.append(len(starts))
    return [np.asarray(a, np.int32) for a in (starts, ends, first)]


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
@pytest.mark.parametrize("fixed_order", [False, True])
def test_particle_reductions_match_float64(device, scalar, np_dtype, tol, fixed_order):
    vec = wp.types.vector(3, scalar)
    jellies = 3
    jelly, mass, q, qd = _particles(np_dtype)
    gravity = np.array([0.3, -9.81, 0.1], np_dtype)
    arr = lambda a, dt: wp.array(a, dtype=dt, device=device)  # noqa: E731
    outs = [wp.zeros(jellies, dtype=dt, device=device) for dt in (scalar, scalar, vec, scalar, wp.int32)]
    inputs = [arr(mass, scalar), vec(*gravity), arr(q, vec), arr(qd, vec)]
    if fixed_order:
        start, end, first = _chunks(jelly)
        chunk_outs = [wp.zeros(len(start), dtype=dt, device=device) for dt in (scalar, scalar, vec, scalar, wp.int32)]
        chunks = [arr(start, wp.int32), arr(end, wp.int32)]
        wp.launch(metrics.reduce_particle_chunks, len(start), inputs=[*chunks, *inputs], outputs=chunk_outs,
                  device=device)
        wp.launch(metrics.combine_particle_chunks, jellies, inputs=[arr(first, wp.int32), *chunk_outs], outputs=outs,
                  device=device)
    else:
        wp.launch(metrics.reduce_particles, len(mass), inputs=[inputs[0], arr(jelly, wp.int32), *inputs[1:]],
                  outputs=outs, device=device)
    kinetic, gravity_energy, moment, max_speed, nonfinite = (o.numpy() for o in outs)
    assert kinetic.dtype == np_dtype
    for j, (ke, ge, mom, vmax, bad, scale) in enumerate(_reference_particles(jelly, mass, q, qd, gravity, jellies)):
        assert kinetic[j] == pytest.approx(ke, rel=tol * 10)
        assert abs(gravity_energy[j] - ge) <= tol * 10 * scale
        np.testing.assert_allclose(moment[j], mom, rtol=0, atol=tol * 10 * scale)
        assert max_speed[j] == pytest.approx(vmax, rel=tol)
        assert nonfinite[j] == bad
    assert nonfinite.sum() == 1


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
@pytest.mark.parametrize("fixed_order", [False, True])
def test_spring_energy_matches_float64(device, scalar, np_dtype, tol, fixed_order):
    """1/2 k (|x_a - x_b| - L)^2 summed per jelly of each spring's first particle."""
    vec = wp.types.vector(3, scalar)
    rng = np.random.default_rng(1)
    jelly, _, q, _ = _particles(np_dtype, seed=1)
    q[17] = 0.0  # finite positions here
    pairs = []
    for j in range(3):
        idx = np.flatnonzero(jelly == j)
        for _ in range(120):
            a, b = rng.choice(idx, 2, replace=False)
            pairs.append((a, b))
    pairs = np.asarray(pairs, np.int32)
    rest = rng.uniform(0.5, 1.5, len(pairs)).astype(np_dtype)
    ks = rng.uniform(10.0, 1000.0, len(pairs)).astype(np_dtype)
    x = q.astype(np.float64)
    length = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    per_spring = 0.5 * ks.astype(np.float64) * (length - rest.astype(np.float64)) ** 2
    expected = np.bincount(jelly[pairs[:, 0]], weights=per_spring, minlength=3)
    arr = lambda a, dt: wp.array(a, dtype=dt, device=device)  # noqa: E731
    out = wp.zeros(3, dtype=scalar, device=device)
    springs = [arr(pairs, wp.vec2i), arr(rest, scalar), arr(ks, scalar)]
    if fixed_order:
        start, end, first = _chunks(jelly[pairs[:, 0]])
        chunk_energy = wp.zeros(len(start), dtype=scalar, device=device)
        wp.launch(metrics.reduce_spring_chunks, len(start),
                  inputs=[arr(start, wp.int32), arr(end, wp.int32), *springs, arr(q, vec)], outputs=[chunk_energy],
                  device=device)
        wp.launch(metrics.combine_spring_chunks, 3, inputs=[arr(first, wp.int32), chunk_energy], outputs=[out],
                  device=device)
    else:
        wp.launch(metrics.reduce_springs, len(pairs), inputs=[*springs, arr(jelly, wp.int32), arr(q, vec)],
                  outputs=[out], device=device)
    np.testing.assert_allclose(out.numpy(), expected, rtol=tol * 10)


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_position_error_is_the_float64_rms(device, scalar, np_dtype, tol):
    vec = wp.types.vector(3, scalar)
    rng = np.random.default_rng(2)
    q = rng.normal(size=(50, 3)).astype(np_dtype)
    ref = q.astype(np.float64) + rng.normal(scale=1e-3, size=(50, 3))
    starts = np.array([0, 20, 50], np.int32)
    err = wp.zeros(2, dtype=wp.float64, device=device)
    wp.launch(metrics.measure_position_error, 2,
              inputs=[wp.array(starts, dtype=wp.int32, device=device), wp.array(q, dtype=vec, device=device),
                      wp.array(ref, dtype=wp.vec3d, device=device)],
              outputs=[err], device=device)
    d = q.astype(np.float64) - ref
    expected = [np.sqrt(np.mean(np.sum(d[a:b] ** 2, axis=1))) for a, b in zip(starts[:-1], starts[1:])]
    np.testing.assert_allclose(err.numpy(), expected, rtol=1e-12)  # summed in float64 in both precisions


@pytest.mark.parametrize("scalar,np_dtype,tol", PRECISIONS)
def test_penetration_closed_forms(device, scalar, np_dtype, tol):
    """World 0: a ground plane (deepest particle 0.3 below it) and a sphere of radius 1 at (5, 0, 0)
    (a particle 0.25 from its centre: 0.75 deep). World 1: a bowl of radius 2 at the origin; jelly 1
    straddles its shell, 0.1 inside and 0.05 outside at most: 0.05. Jelly 2 lies inside only: 0."""
    vec = wp.types.vector(3, scalar)
    x = np.array(
        [
            [0.0, -0.3, 0.0], [1.0, -0.1, 0.0], [0.0, 2.0, 0.0],  # jelly 0, world 0
            [5.0, 0.25, 0.0],  # jelly 0, world 0: inside the sphere
            [0.0, -1.9, 0.0], [0.0, -2.05, 0.0],  # jelly 1, world 1: both sides of the bowl's shell
            [0.5, -1.0, 0.0], [0.2, -1.5, 0.0],  # jelly 2, world 1: inside the bowl only
        ],
        np_dtype,
    )
    world = np.array([0, 0, 0, 0, 1, 1, 1, 1], np.int32)
    jelly = np.array([0, 0, 0, 0, 1, 1, 2, 2], np.int32)
    arr = lambda a, dt: wp.array(np.asarray(a), dtype=dt, device=device)  # noqa: E731
    empty_vec = wp.zeros(0, dtype=vec, device=device)
    empty_scalar = wp.zeros(0, dtype=scalar, device=device)
    empty_int = wp.zeros(0, dtype=wp.int32, device=device)
    origin, up = arr([[0.0, 0.0, 0.0]], vec), arr([[0.0, 1.0, 0.0]], vec)
    bowl_slots = 1
    depth = wp.zeros(2, dtype=scalar, device=device)
    shell_lo = arr(np.full(3, metrics.NO_SURFACE, np_dtype), scalar)
    shell_hi = arr(np.full(3, -metrics.NO_SURFACE, np_dtype), scalar)
    wp.launch(
        metrics.measure_penetration,
        len(x),
        inputs=[
            arr(world, wp.int32), arr(jelly, wp.int32),
            arr([0, 1, 1], wp.int32), origin, up, origin, arr([0.0], scalar),
            arr([0, 1, 1], wp.int32), arr([[5.0, 0.0, 0.0]], vec), arr([1.0], scalar),
            arr([0, 0, 0], wp.int32), wp.zeros(0, dtype=wp.uint64, device=device), empty_int, empty_scalar, empty_int,
            wp.zeros(0, dtype=wp.vec3i, device=device), empty_vec,
            arr([0, 0, 1], wp.int32), origin, arr([2.0], scalar), arr([1.0], scalar),
            arr([-1], wp.int32), empty_vec, empty_vec, bowl_slots,
            arr(x, vec),
        ],
        outputs=[depth, shell_lo, shell_hi],
        device=device,
    )
    wp.launch(metrics.combine_shell_depths, 3,
              inputs=[arr([0, 1, 1], wp.int32), arr([0, 0, 1], wp.int32), bowl_slots, shell_lo, shell_hi],
              outputs=[depth], device=device)
    np.testing.assert_allclose(depth.numpy(), [0.75, 0.05], rtol=tol * 10)
