"""Atomic-free kernels for ``--deterministic`` runs: spring forces by gather, metrics by fixed-order sums.

Float addition is not associative, and on CUDA the order in which ``wp.atomic_add`` contributions
land on one particle changes from launch to launch, so the atomic spring kernel gives forces that
differ in the last bits from run to run, and so do the trajectories. These kernels fix the order:

* ``eval_spring_forces`` writes each spring's force on its first particle to its own slot (no
  sharing, no atomics); ``gather_spring_forces`` then sums, per particle, the forces of its
  incident springs in ascending spring order, read from a CSR list built once on the host. The
  spring force itself is ``springs.spring_of``, the same function as the atomic path.
* Metrics are summed per chunk of consecutive particles (springs) by one thread each, then per
  jelly over its chunks in order. ``max`` and integer counts need no fixed order.

On the CPU, Warp runs a launch's threads one after another in ``tid`` order, so the atomic path
already adds each particle's spring forces in ascending spring order, starting from zero: the
gather reproduces it bit for bit there.
"""

import warp as wp

from . import springs

wp.set_module_options({"enable_backward": False})


def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    spring_funcs = springs.build(scalar)  # cached per precision: the same functions as the atomic path
    spring_of = spring_funcs["spring_of"]
    spring_energy = spring_funcs["spring_energy"]

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

    @wp.kernel(module="unique")
    def reduce_particle_chunks(
        # Chunks: particles [chunk_start[c], chunk_end[c]) all of one jelly
        chunk_start: wp.array(dtype=wp.int32),
        chunk_end: wp.array(dtype=wp.int32),
        # Model:
        particle_mass: wp.array(dtype=scalar),
        gravity: vec3,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Out, per chunk:
        kinetic_out: wp.array(dtype=scalar),
        gravity_energy_out: wp.array(dtype=scalar),
        moment_out: wp.array(dtype=vec3),
        max_speed_out: wp.array(dtype=scalar),
        nonfinite_out: wp.array(dtype=wp.int32),
    ):
        c = wp.tid()
        ke = scalar(0.0)
        ge = scalar(0.0)
        mom = vec3(scalar(0.0))
        vmax = scalar(0.0)
        bad = int(0)
        for i in range(chunk_start[c], chunk_end[c]):
            m = particle_mass[i]
            x = particle_q[i]
            v = particle_qd[i]
            if not (wp.isfinite(x) and wp.isfinite(v)):
                bad += 1
                continue
            speed_sq = wp.dot(v, v)
            ke += scalar(0.5) * m * speed_sq
            ge += -m * wp.dot(gravity, x)
            mom += m * x
            vmax = wp.max(vmax, wp.sqrt(speed_sq))
        kinetic_out[c] = ke
        gravity_energy_out[c] = ge
        moment_out[c] = mom
        max_speed_out[c] = vmax
        nonfinite_out[c] = bad

    @wp.kernel(module="unique")
    def reduce_spring_chunks(
        # Chunks: springs [chunk_start[c], chunk_end[c]) whose first particles are all of one jelly
        chunk_start: wp.array(dtype=wp.int32),
        chunk_end: wp.array(dtype=wp.int32),
        # Model:
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        # State in:
        particle_q: wp.array(dtype=vec3),
        # Out, per chunk:
        spring_energy_out: wp.array(dtype=scalar),
    ):
        c = wp.tid()
        total = scalar(0.0)
        for s in range(chunk_start[c], chunk_end[c]):
            pair = spring_indices[s]
            e = spring_energy(particle_q[pair[0]], particle_q[pair[1]], spring_rest_length[s], spring_stiffness[s])
            if wp.isfinite(e):
                total += e
        spring_energy_out[c] = total

    @wp.kernel(module="unique")
    def combine_particle_chunks(
        # Chunks of jelly j: [jelly_chunk_start[j], jelly_chunk_start[j + 1])
        jelly_chunk_start: wp.array(dtype=wp.int32),
        kinetic: wp.array(dtype=scalar),
        gravity_energy: wp.array(dtype=scalar),
        moment: wp.array(dtype=vec3),
        max_speed: wp.array(dtype=scalar),
        nonfinite: wp.array(dtype=wp.int32),
        # Out, per jelly:
        kinetic_out: wp.array(dtype=scalar),
        gravity_energy_out: wp.array(dtype=scalar),
        moment_out: wp.array(dtype=vec3),
        max_speed_out: wp.array(dtype=scalar),
        nonfinite_out: wp.array(dtype=wp.int32),
    ):
        j = wp.tid()
        ke = scalar(0.0)
        ge = scalar(0.0)
        mom = vec3(scalar(0.0))
        vmax = scalar(0.0)
        bad = int(0)
        for c in range(jelly_chunk_start[j], jelly_chunk_start[j + 1]):
            ke += kinetic[c]
            ge += gravity_energy[c]
            mom += moment[c]
            vmax = wp.max(vmax, max_speed[c])
            bad += nonfinite[c]
        kinetic_out[j] = ke
        gravity_energy_out[j] = ge
        moment_out[j] = mom
        max_speed_out[j] = vmax
        nonfinite_out[j] = bad

    @wp.kernel(module="unique")
    def combine_spring_chunks(
        jelly_chunk_start: wp.array(dtype=wp.int32),
        spring_energy: wp.array(dtype=scalar),
        # Out, per jelly:
        spring_energy_out: wp.array(dtype=scalar),
    ):
        j = wp.tid()
        total = scalar(0.0)
        for c in range(jelly_chunk_start[j], jelly_chunk_start[j + 1]):
            total += spring_energy[c]
        spring_energy_out[j] = total

    return {
        "eval_spring_forces": eval_spring_forces,
        "gather_spring_forces": gather_spring_forces,
        "reduce_particle_chunks": reduce_particle_chunks,
        "reduce_spring_chunks": reduce_spring_chunks,
        "combine_particle_chunks": combine_particle_chunks,
        "combine_spring_chunks": combine_spring_chunks,
    }
