"""Spring and damper forces over a spring list: atomic adds, or a fixed-order gather.

``spring_force`` is THE spring force of the project: every other path (the lattice gathers in
kernels/lattice.py, the native C++ gathers, the masked lattice) calls it or is checked against it
on random springs (tests/test_kernels_springs.py).

* ``eval_springs``: one thread per spring adds its force to both particles with atomic adds. On
  CUDA the order in which contributions land on one particle changes from launch to launch, so the
  forces differ in the last bits from run to run.
* ``eval_spring_forces`` + ``gather_spring_forces`` (``--deterministic``): each spring writes its
  force on its first particle to its own slot; then each particle sums the forces of its incident
  springs in ascending spring order, read from a CSR list built once on the host
  (``core/forces.attach``). On the CPU, Warp runs a launch's threads in ``tid`` order, so the atomic
  kernel already adds in that order, starting from zero: the gather reproduces it bit for bit.

Generic over float32 and float64 (kernels/precision.py).
"""

import warp as wp

from .precision import Float, both_precisions, vec3

wp.set_module_options({"enable_backward": False})


@wp.func
def spring_force(xa: vec3, xb: vec3, va: vec3, vb: vec3, rest: Float, ks: Float, kd: Float):
    """Force on particle a: -ks(|d| - r) d^ - kd((va - vb).d^) d^ with d = xa - xb; b gets the negative."""
    d = xa - xb
    length = wp.length(d)
    # Coincident particles have no direction to push along; returning zero avoids 0/0 = NaN.
    if length == type(rest)(0.0):
        return type(xa)(type(rest)(0.0))
    dhat = d / length
    magnitude = ks * (length - rest) + kd * wp.dot(va - vb, dhat)
    return -magnitude * dhat


@wp.func
def spring_of(
    s: int,
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    spring_damping: wp.array(dtype=Float),
    particle_q: wp.array(dtype=vec3),
    particle_qd: wp.array(dtype=vec3),
):
    """(a, b, force on a) of spring s of the spring list; b gets the negative.

    Shared by the atomic kernel and the deterministic per-spring kernel, so both paths evaluate
    each spring with the same arithmetic (the same bits).
    """
    pair = spring_indices[s]
    a = pair[0]
    b = pair[1]
    f = spring_force(
        particle_q[a],
        particle_q[b],
        particle_qd[a],
        particle_qd[b],
        spring_rest_length[s],
        spring_stiffness[s],
        spring_damping[s],
    )
    return a, b, f


@wp.func
def spring_energy(xa: vec3, xb: vec3, rest: Float, ks: Float):
    """Potential energy 1/2 ks (|xa - xb| - rest)^2 of one spring."""
    stretch = wp.length(xa - xb) - rest
    return type(rest)(0.5) * ks * stretch * stretch


@both_precisions
@wp.kernel
def eval_springs(
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    spring_damping: wp.array(dtype=Float),
    # State in:
    particle_q: wp.array(dtype=vec3),
    particle_qd: wp.array(dtype=vec3),
    # Out:
    particle_f_out: wp.array(dtype=vec3),
):
    a, b, f = spring_of(
        wp.tid(),
        spring_indices,
        spring_rest_length,
        spring_stiffness,
        spring_damping,
        particle_q,
        particle_qd,
    )
    wp.atomic_add(particle_f_out, a, f)
    wp.atomic_sub(particle_f_out, b, f)


@both_precisions
@wp.kernel
def eval_spring_forces(
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    spring_damping: wp.array(dtype=Float),
    # State in:
    particle_q: wp.array(dtype=vec3),
    particle_qd: wp.array(dtype=vec3),
    # Out: force of each spring on its first particle (the second gets the negative)
    spring_f_out: wp.array(dtype=vec3),
):
    tid = wp.tid()
    _a, _b, f = spring_of(
        tid, spring_indices, spring_rest_length, spring_stiffness, spring_damping, particle_q, particle_qd
    )
    spring_f_out[tid] = f


@both_precisions
@wp.kernel
def gather_spring_forces(
    # Model: incident springs of particle i are csr_springs[csr_offsets[i]:csr_offsets[i + 1]],
    # ascending; entry s >= 0 means i is the spring's first particle, -(s + 1) its second.
    csr_offsets: wp.array(dtype=wp.int32),
    csr_springs: wp.array(dtype=wp.int32),
    # In:
    spring_f: wp.array(dtype=vec3),
    # Out:
    particle_f_out: wp.array(dtype=vec3),
):
    i = wp.tid()
    f = type(spring_f).dtype(type(spring_f).dtype.dtype(0.0))  # zero, in the arrays' precision
    for k in range(csr_offsets[i], csr_offsets[i + 1]):
        e = csr_springs[k]
        if e >= 0:
            f = f + spring_f[e]
        else:
            f = f - spring_f[-e - 1]
    particle_f_out[i] = f
# -- the spring's Jacobian: the blocks of the implicit solve (kernels/implicit.py, kernels/multigrid.py)


@wp.func
def spring_jacobian(d: vec3, rest: Float, ks: Float, kd: Float, h: Float):
    """(B, S) of one spring: B = h kd d^d^T + h^2 S, S = ks [d^d^T + max(0, 1 - r/|d|)(I - d^d^T)].

    With d = x_a - x_b, -S is df_a/dx_a of ``spring_force`` and -kd d^d^T is df_a/dv_a; the
    damper's dependence on x through d^ is left out (it is not symmetric, and CG needs a symmetric
    matrix: kernels/implicit.py). Under compression (|d| < r) the transverse factor 1 - r/|d| is
    negative, which makes S indefinite; it is clamped to >= 0, so every B is positive
    semi-definite. Coincident particles (|d| = 0) have no direction and zero force; both blocks are
    zero there, which avoids 0/0 = NaN. core/stability_model.py computes the same S and kd d^d^T in
    NumPy (tests/test_kernels_implicit.py compares them).
    """
    length = wp.length(d)
    zero = wp.matrix(shape=(3, 3), dtype=type(rest))
    if length == type(rest)(0.0):
        return zero, zero
    dhat = d / length
    along = wp.outer(dhat, dhat)
    transverse = wp.max(type(rest)(1.0) - rest / length, type(rest)(0.0))
    identity = wp.identity(n=3, dtype=type(rest))
    s = ks * (along + transverse * (identity - along))
    b = (h * kd) * along + (h * h) * s
    return b, s
