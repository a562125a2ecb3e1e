"""kernels/springs.py alone: the spring force, its energy and the spring-list kernels, float32 and float64."""

import numpy as np
import pytest
import warp as wp

from softsim_warp.kernels import springs
from softsim_warp.kernels.precision import Float, both_precisions, vec3

PRECISIONS = [(wp.float32, np.float32), (wp.float64, np.float64)]


def random_springs(n, np_dtype, seed=3):
    """n random springs: endpoints and velocities in a unit box, rest lengths about the distance,
    ks over four decades and kd over three; a few with coincident endpoints."""
    rng = np.random.default_rng(seed)
    xa, xb, va, vb = (rng.uniform(-1.0, 1.0, (n, 3)) for _ in range(4))
    xb[:3] = xa[:3]  # coincident particles: zero force by definition
    rest = np.linalg.norm(xa - xb, axis=1) * rng.uniform(0.5, 1.5, n) + 0.01
    ks = 10.0 ** rng.uniform(1.0, 5.0, n)
    kd = 10.0 ** rng.uniform(-2.0, 1.0, n)
    return tuple(np.asarray(t, dtype=np_dtype) for t in (xa, xb, va, vb, rest, ks, kd))


def reference_force(xa, xb, va, vb, rest, ks, kd):
    """-ks (|d| - r) d^ - kd ((va - vb) . d^) d^, d = xa - xb, in float64 (zero where d = 0)."""
    xa, xb, va, vb, rest, ks, kd = (np.asarray(t, dtype=np.float64) for t in (xa, xb, va, vb, rest, ks, kd))
    d = xa - xb
    length = np.linalg.norm(d, axis=1)
    dhat = np.divide(d, length[:, None], out=np.zeros_like(d), where=length[:, None] > 0)
    magnitude = ks * (length - rest) + kd * np.sum((va - vb) * dhat, axis=1)
    return -magnitude[:, None] * dhat


@both_precisions
@wp.kernel
def spring_force_of(
    xa: wp.array(dtype=vec3),
    xb: wp.array(dtype=vec3),
    va: wp.array(dtype=vec3),
    vb: wp.array(dtype=vec3),
    rest: wp.array(dtype=Float),
    ks: wp.array(dtype=Float),
    kd: wp.array(dtype=Float),
    f_out: wp.array(dtype=vec3),
    energy_out: wp.array(dtype=Float),
):
    i = wp.tid()
    f_out[i] = springs.spring_force(xa[i], xb[i], va[i], vb[i], rest[i], ks[i], kd[i])
    energy_out[i] = springs.spring_energy(xa[i], xb[i], rest[i], ks[i])


def launch_spring_force(device, scalar, springs_data):
    vec = wp.types.vector(3, scalar)
    xa, xb, va, vb, rest, ks, kd = springs_data
    n = len(rest)
    f = wp.zeros(n, dtype=vec, device=device)
    e = wp.zeros(n, dtype=scalar, device=device)
    inputs = [wp.array(t, dtype=vec, device=device) for t in (xa, xb, va, vb)]
    inputs += [wp.array(t, dtype=scalar, device=device) for t in (rest, ks, kd)]
    wp.launch(spring_force_of, n, inputs=inputs, outputs=[f, e], device=device)
    return f.numpy(), e.numpy()


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
def test_spring_force_and_energy_match_float64_closed_form(device, scalar, np_dtype):
    data = random_springs(200, np_dtype)
    f, e = launch_spring_force(device, scalar, data)
    assert f.dtype == np_dtype and e.dtype == np_dtype
    ref = reference_force(*data)
    eps = np.finfo(np_dtype).eps
    # A handful of roundings on terms of size ks |d| and kd |dv|: relative to that scale.
    xa, xb, va, vb, rest, ks, kd = (np.asarray(t, dtype=np.float64) for t in data)
    scale = ks * (np.linalg.norm(xa - xb, axis=1) + rest) + kd * np.linalg.norm(va - vb, axis=1)
    assert np.all(np.abs(f - ref) <= 16 * eps * scale[:, None])
    np.testing.assert_array_equal(f[:3], 0.0)  # coincident endpoints
    stretch = np.linalg.norm(xa - xb, axis=1) - rest
    assert np.all(np.abs(e - 0.5 * ks * stretch**2) <= 16 * eps * ks * (np.linalg.norm(xa - xb, axis=1) + rest) ** 2)


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
def test_spring_force_is_minus_the_energy_gradient(device, scalar, np_dtype):
    """Without damping, the force on a is -dE/dxa: a central difference of spring_energy in float64."""
    data = list(random_springs(50, np.float64, seed=11))
    data[6] = np.zeros_like(data[6])  # kd = 0
    f, _ = launch_spring_force(device, wp.float64, data)
    xa, xb, _va, _vb, rest, ks, _kd = data
    h = 1e-6
    grad = np.zeros_like(xa)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        e_plus = 0.5 * ks * (np.linalg.norm(xa + step - xb, axis=1) - rest) ** 2
        e_minus = 0.5 * ks * (np.linalg.norm(xa - step - xb, axis=1) - rest) ** 2
        grad[:, axis] = (e_plus - e_minus) / (2 * h)
    np.testing.assert_allclose(f[3:], -grad[3:], rtol=1e-6, atol=1e-6 * ks.max())


def spring_list(device, scalar, np_dtype, n_particles=12, n_springs=40, seed=5):
    rng = np.random.default_rng(seed)
    vec = wp.types.vector(3, scalar)
    pairs = np.array([rng.choice(n_particles, 2, replace=False) for _ in range(n_springs)], dtype=np.int32)
    q = rng.uniform(-1.0, 1.0, (n_particles, 3)).astype(np_dtype)
    qd = rng.uniform(-1.0, 1.0, (n_particles, 3)).astype(np_dtype)
    rest = rng.uniform(0.2, 1.0, n_springs).astype(np_dtype)
    ks = rng.uniform(10.0, 1000.0, n_springs).astype(np_dtype)
    kd = rng.uniform(0.0, 2.0, n_springs).astype(np_dtype)
    arrays = [
        wp.array(pairs, dtype=wp.vec2i, device=device),
        *(wp.array(t, dtype=scalar, device=device) for t in (rest, ks, kd)),
        wp.array(q, dtype=vec, device=device),
        wp.array(qd, dtype=vec, device=device),
    ]
    return arrays, (pairs, q, qd, rest, ks, kd)


@pytest.mark.parametrize("scalar,np_dtype", PRECISIONS)
def test_atomic_and_gathered_spring_list_forces_agree_with_the_reference(device, scalar, np_dtype):
    """eval_springs (atomic adds) and eval_spring_forces + gather_spring_forces (CSR in spring order)
    both give the per-spring reference summed per particle; on the CPU they agree bit for bit."""
    vec = wp.types.vector(3, scalar)
    arrays, (pairs, q, qd, rest, ks, kd) = spring_list(device, scalar, np_dtype)
    n, m = len(q), len(pairs)
    atomic = wp.zeros(n, dtype=vec, device=device)
    wp.launch(springs.eval_springs, m, inputs=arrays, outputs=[atomic], device=device)

    per_spring = wp.zeros(m, dtype=vec, device=device)
    wp.launch(springs.eval_spring_forces, m, inputs=arrays, outputs=[per_spring], device=device)
    incident = [[] for _ in range(n)]
    for s, (a, b) in enumerate(pairs):
        incident[a].append(s)
        incident[b].append(-(s + 1))
    offsets = np.cumsum([0] + [len(x) for x in incident]).astype(np.int32)
    csr = np.array([e for x in incident for e in sorted(x, key=lambda e: e if e >= 0 else -e - 1)], dtype=np.int32)
    gathered = wp.zeros(n, dtype=vec, device=device)
    wp.launch(
        springs.gather_spring_forces,
        n,
        inputs=[wp.array(offsets, device=device), wp.array(csr, device=device), per_spring],
        outputs=[gathered],
        device=device,
    )
    ref_spring = reference_force(q[pairs[:, 0]], q[pairs[:, 1]], qd[pairs[:, 0]], qd[pairs[:, 1]], rest, ks, kd)
    ref = np.zeros((n, 3))
    np.add.at(ref, pairs[:, 0], ref_spring)
    np.add.at(ref, pairs[:, 1], -ref_spring)
    tol = 64 * np.finfo(np_dtype).eps * float(ks.max())
    np.testing.assert_allclose(gathered.numpy(), ref, rtol=0, atol=tol)
    np.testing.assert_allclose(atomic.numpy(), ref, rtol=0, atol=tol)
    if device.is_cpu:
        np.testing.assert_array_equal(gathered.numpy(), atomic.numpy())
