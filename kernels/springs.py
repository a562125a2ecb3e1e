"""Spring and damper forces over a spring list: atomic adds, or a fixed-order gather.

* ``eval_springs``: one thread per spring adds its force to both particles with atomic adds. On
  CUDA the order in which contributions land on one particle changes from launch to launch, so the
  forces differ in the last bits from run to run.
* ``eval_spring_forces`` + ``gather_spring_forces`` (``--deterministic``): each spring writes its
  force on its first particle to its own slot; then each particle sums the forces of its incident
  springs in ascending spring order, read from a CSR list built once on the host
  (``core/forces.attach``). On the CPU, Warp runs a launch's threads in ``tid`` order, so the atomic
  kernel already adds in that order, starting from zero: the gather reproduces it bit for bit.
"""

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})


@functools.cache  # one set of Warp objects per precision, shared by every module that builds on it
def build(scalar):
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def spring_force(xa: vec3, xb: vec3, va: vec3, vb: vec3, rest: scalar, ks: scalar, kd: scalar):
        """Force on particle a: -ks(|d| - r) d^ - kd((va - vb).d^) d^ with d = xa - xb; b gets the negative."""
        d = xa - xb
        length = wp.length(d)
        # Coincident particles have no direction to push along; returning zero avoids 0/0 = NaN.
        if length == scalar(0.0):
            return vec3(scalar(0.0))
        dhat = d / length
        magnitude = ks * (length - rest) + kd * wp.dot(va - vb, dhat)
        return -magnitude * dhat

    @wp.func
    def spring_of(
        s: int,
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        spring_damping: wp.array(dtype=scalar),
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
    ):
        """(a, b, force on a) of spring s of the spring list; b gets the negative.

        Shared by the atomic kernel here and the deterministic per-spring kernel, so both paths
        evaluate each spring with the same arithmetic (the same bits).
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
    def spring_energy(xa: vec3, xb: vec3, rest: scalar, ks: scalar):
        """Potential energy 1/2 ks (|xa - xb| - rest)^2 of one spring."""
        stretch = wp.length(xa - xb) - rest
        return scalar(0.5) * ks * stretch * stretch

    @wp.kernel(module="unique")
    def eval_springs(
        # Model:
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        spring_damping: wp.array(dtype=scalar),
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

    @wp.kernel(module="unique")
    def eval_spring_forces(
        # Model:
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        spring_damping: wp.array(dtype=scalar),
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

    @wp.kernel(module="unique")
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
        f = vec3(scalar(0.0))
        for k in range(csr_offsets[i], csr_offsets[i + 1]):
            e = csr_springs[k]
            if e >= 0:
                f = f + spring_f[e]
            else:
                f = f - spring_f[-e - 1]
        particle_f_out[i] = f

    return {
        "spring_force": spring_force,
        "spring_of": spring_of,
        "spring_energy": spring_energy,
        "eval_springs": eval_springs,
        "eval_spring_forces": eval_spring_forces,
        "gather_spring_forces": gather_spring_forces,
    }
