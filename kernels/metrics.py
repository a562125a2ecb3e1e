"""Per-frame reductions: energies, centre of mass and speed, one slot per jelly.

``reduce_particles`` and ``reduce_springs`` sum with atomic adds. For ``--deterministic`` runs the
chunk kernels sum in a fixed order instead: per chunk of consecutive particles (springs) by one
thread each, then per jelly over its chunks in order. ``max`` and integer counts need no fixed order.
"""

import warp as wp

from . import springs

wp.set_module_options({"enable_backward": False})


def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    spring_funcs = springs.build(scalar)
    spring_energy = spring_funcs["spring_energy"]

    @wp.kernel(module="unique")
    def reduce_particles(
        # Model:
        particle_mass: wp.array(dtype=scalar),
        particle_jelly: wp.array(dtype=wp.int32),
        gravity: vec3,
        # State in:
        particle_q: wp.array(dtype=vec3),
        particle_qd: wp.array(dtype=vec3),
        # Out, per jelly (zeroed by the caller): kinetic, gravity energy, mass-weighted position, max speed
        kinetic_out: wp.array(dtype=scalar),
        gravity_energy_out: wp.array(dtype=scalar),
        moment_out: wp.array(dtype=vec3),
        max_speed_out: wp.array(dtype=scalar),
        nonfinite_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        j = particle_jelly[i]
        m = particle_mass[i]
        x = particle_q[i]
        v = particle_qd[i]
        speed_sq = wp.dot(v, v)
        if not (wp.isfinite(x) and wp.isfinite(v)):
            wp.atomic_add(nonfinite_out, j, 1)
            return
        wp.atomic_add(kinetic_out, j, scalar(0.5) * m * speed_sq)
        wp.atomic_add(gravity_energy_out, j, -m * wp.dot(gravity, x))
        wp.atomic_add(moment_out, j, m * x)
        wp.atomic_max(max_speed_out, j, wp.sqrt(speed_sq))

    @wp.kernel(module="unique")
    def reduce_springs(
        # Model:
        spring_indices: wp.array(dtype=wp.vec2i),
        spring_rest_length: wp.array(dtype=scalar),
        spring_stiffness: wp.array(dtype=scalar),
        particle_jelly: wp.array(dtype=wp.int32),
        # State in:
        particle_q: wp.array(dtype=vec3),
        # Out, per jelly (zeroed by the caller):
        spring_energy_out: wp.array(dtype=scalar),
    ):
        tid = wp.tid()
        pair = spring_indices[tid]
        e = spring_energy(particle_q[pair[0]], particle_q[pair[1]], spring_rest_length[tid], spring_stiffness[tid])
        if wp.isfinite(e):
            wp.atomic_add(spring_energy_out, particle_jelly[pair[0]], e)

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
        "reduce_particles": reduce_particles,
        "reduce_springs": reduce_springs,
        "reduce_particle_chunks": reduce_particle_chunks,
        "reduce_spring_chunks": reduce_spring_chunks,
        "combine_particle_chunks": combine_particle_chunks,
        "combine_spring_chunks": combine_spring_chunks,
    }
