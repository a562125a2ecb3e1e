"""Per-frame reductions: energies, centre of mass and speed, one slot per jelly."""

import warp as wp

from . import springs

wp.set_module_options({"enable_backward": False})


def build(scalar):
    vec3 = wp.types.vector(3, scalar)
    spring_energy = springs.build(scalar)["spring_energy"]

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

    return {"reduce_particles": reduce_particles, "reduce_springs": reduce_springs}
