"""Per-frame reductions: energies, centre of mass and speed, one slot per jelly.

``reduce_particles`` and ``reduce_springs`` sum with atomic adds. For ``--deterministic`` runs the
chunk kernels sum in a fixed order instead: per chunk of consecutive particles (springs) by one
thread each, then per jelly over its chunks in order. ``max`` and integer counts need no fixed order.

Per world, for ``softsim sweep`` (one value per world a frame, so the host never reads particles):
``measure_penetration`` and ``combine_shell_depths`` find the deepest particle inside terrain with the
contact kernels' own signed distances (kernels/contact.py, kernels/mesh.py), and
``measure_position_error`` the RMS distance to a reference run's particles, summed in particle order
by one thread per world (the same on the CPU and on CUDA).
"""

import warp as wp

# NO_SURFACE: what the contact distances return where a primitive does not collide (a plane's hole,
# above a bowl's cut, a mesh beyond reach), no penetration; io/metrics.py seeds the bowls' depths with it.
from .contact import NO_SURFACE, bowl_distance, plane_distance, sphere_distance
from .mesh import mesh_distance
from .pins import rotate
from .precision import Float, both_precisions, vec3
from .springs import spring_energy

wp.set_module_options({"enable_backward": False})


@both_precisions
@wp.kernel
def reduce_particles(
    # Model:
    particle_mass: wp.array(dtype=Float),
    particle_jelly: wp.array(dtype=wp.int32),
    gravity: vec3,
    # State in:
    particle_q: wp.array(dtype=vec3),
    particle_qd: wp.array(dtype=vec3),
    # Out, per jelly (zeroed by the caller): kinetic, gravity energy, mass-weighted position, max speed
    kinetic_out: wp.array(dtype=Float),
    gravity_energy_out: wp.array(dtype=Float),
    moment_out: wp.array(dtype=vec3),
    max_speed_out: wp.array(dtype=Float),
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
    wp.atomic_add(kinetic_out, j, type(m)(0.5) * m * speed_sq)
    wp.atomic_add(gravity_energy_out, j, -m * wp.dot(gravity, x))
    wp.atomic_add(moment_out, j, m * x)
    wp.atomic_max(max_speed_out, j, wp.sqrt(speed_sq))


@both_precisions
@wp.kernel
def reduce_springs(
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    particle_jelly: wp.array(dtype=wp.int32),
    # State in:
    particle_q: wp.array(dtype=vec3),
    # Out, per jelly (zeroed by the caller):
    spring_energy_out: wp.array(dtype=Float),
):
    tid = wp.tid()
    pair = spring_indices[tid]
    e = spring_energy(particle_q[pair[0]], particle_q[pair[1]], spring_rest_length[tid], spring_stiffness[tid])
    if wp.isfinite(e):
        wp.atomic_add(spring_energy_out, particle_jelly[pair[0]], e)


@both_precisions
@wp.kernel
def reduce_particle_chunks(
    # Chunks: particles [chunk_start[c], chunk_end[c]) all of one jelly
    chunk_start: wp.array(dtype=wp.int32),
    chunk_end: wp.array(dtype=wp.int32),
    # Model:
    particle_mass: wp.array(dtype=Float),
    gravity: vec3,
    # State in:
    particle_q: wp.array(dtype=vec3),
    particle_qd: wp.array(dtype=vec3),
    # Out, per chunk:
    kinetic_out: wp.array(dtype=Float),
    gravity_energy_out: wp.array(dtype=Float),
    moment_out: wp.array(dtype=vec3),
    max_speed_out: wp.array(dtype=Float),
    nonfinite_out: wp.array(dtype=wp.int32),
):
    c = wp.tid()
    ke = particle_mass.dtype(0.0)
    ge = particle_mass.dtype(0.0)
    mom = particle_q.dtype(particle_mass.dtype(0.0))
    vmax = particle_mass.dtype(0.0)
    bad = int(0)
    for i in range(chunk_start[c], chunk_end[c]):
        m = particle_mass[i]
        x = particle_q[i]
        v = particle_qd[i]
        if not (wp.isfinite(x) and wp.isfinite(v)):
            bad += 1
            continue
        speed_sq = wp.dot(v, v)
        ke += type(m)(0.5) * m * speed_sq
        ge += -m * wp.dot(gravity, x)
        mom += m * x
        vmax = wp.max(vmax, wp.sqrt(speed_sq))
    kinetic_out[c] = ke
    gravity_energy_out[c] = ge
    moment_out[c] = mom
    max_speed_out[c] = vmax
    nonfinite_out[c] = bad


@both_precisions
@wp.kernel
def reduce_spring_chunks(
    # Chunks: springs [chunk_start[c], chunk_end[c]) whose first particles are all of one jelly
    chunk_start: wp.array(dtype=wp.int32),
    chunk_end: wp.array(dtype=wp.int32),
    # Model:
    spring_indices: wp.array(dtype=wp.vec2i),
    spring_rest_length: wp.array(dtype=Float),
    spring_stiffness: wp.array(dtype=Float),
    # State in:
    particle_q: wp.array(dtype=vec3),
    # Out, per chunk:
    spring_energy_out: wp.array(dtype=Float),
):
    c = wp.tid()
    total = spring_rest_length.dtype(0.0)
    for s in range(chunk_start[c], chunk_end[c]):
        pair = spring_indices[s]
        e = spring_energy(particle_q[pair[0]], particle_q[pair[1]], spring_rest_length[s], spring_stiffness[s])
        if wp.isfinite(e):
            total += e
    spring_energy_out[c] = total


@both_precisions
@wp.kernel
def combine_particle_chunks(
    # Chunks of jelly j: [jelly_chunk_start[j], jelly_chunk_start[j + 1])
    jelly_chunk_start: wp.array(dtype=wp.int32),
    kinetic: wp.array(dtype=Float),
    gravity_energy: wp.array(dtype=Float),
    moment: wp.array(dtype=vec3),
    max_speed: wp.array(dtype=Float),
    nonfinite: wp.array(dtype=wp.int32),
    # Out, per jelly:
    kinetic_out: wp.array(dtype=Float),
    gravity_energy_out: wp.array(dtype=Float),
    moment_out: wp.array(dtype=vec3),
    max_speed_out: wp.array(dtype=Float),
    nonfinite_out: wp.array(dtype=wp.int32),
):
    j = wp.tid()
    ke = kinetic.dtype(0.0)
    ge = kinetic.dtype(0.0)
    mom = moment.dtype(kinetic.dtype(0.0))
    vmax = kinetic.dtype(0.0)
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


@both_precisions
@wp.kernel
def combine_spring_chunks(
    jelly_chunk_start: wp.array(dtype=wp.int32),
    chunk_spring_energy: wp.array(dtype=Float),
    # Out, per jelly:
    spring_energy_out: wp.array(dtype=Float),
):
    j = wp.tid()
    total = chunk_spring_energy.dtype(0.0)
    for c in range(jelly_chunk_start[j], jelly_chunk_start[j + 1]):
        total += chunk_spring_energy[c]
    spring_energy_out[j] = total


@wp.func
def is_surface(phi: Float):
    return wp.isfinite(phi) and phi < type(phi)(NO_SURFACE)


@both_precisions
@wp.kernel
def measure_penetration(
    # Model:
    particle_world: wp.array(dtype=wp.int32),
    particle_jelly: wp.array(dtype=wp.int32),
    plane_first: wp.array(dtype=wp.int32),
    plane_point: wp.array(dtype=vec3),
    plane_normal: wp.array(dtype=vec3),
    plane_hole_center: wp.array(dtype=vec3),
    plane_hole_radius: wp.array(dtype=Float),
    sphere_first: wp.array(dtype=wp.int32),
    sphere_center: wp.array(dtype=vec3),
    sphere_radius: wp.array(dtype=Float),
    mesh_first: wp.array(dtype=wp.int32),
    mesh_id: wp.array(dtype=wp.uint64),
    mesh_closed: wp.array(dtype=wp.int32),
    mesh_reach: wp.array(dtype=Float),
    mesh_tri_start: wp.array(dtype=wp.int32),
    mesh_tris: wp.array(dtype=wp.vec3i),
    mesh_points: wp.array(dtype=vec3),
    bowl_first: wp.array(dtype=wp.int32),
    bowl_center: wp.array(dtype=vec3),
    bowl_radius: wp.array(dtype=Float),
    bowl_cut_height: wp.array(dtype=Float),
    # Per bowl its moving index (-1: static), and the moving primitives' turn and rest point:
    # a moving bowl's cut is a height in its own frame (as ``collide_moving_bowls`` reads it).
    bowl_motion: wp.array(dtype=wp.int32),
    motion_turn_now: wp.array(dtype=vec3),
    motion_rest_point: wp.array(dtype=vec3),
    bowl_slots: int,
    # State in:
    particle_q: wp.array(dtype=vec3),
    # Out, zeroed by the caller: per world the deepest particle inside solid terrain (planes,
    # spheres, meshes) [m]; per jelly and bowl slot (jelly * bowl_slots + the bowl's index in its
    # world) the least and largest signed distance to the bowl, set to +/-NO_SURFACE by the caller.
    depth_out: wp.array(dtype=Float),
    shell_lo_out: wp.array(dtype=Float),
    shell_hi_out: wp.array(dtype=Float),
):
    i = wp.tid()
    w = particle_world[i]
    x = particle_q[i]
    worst = type(x[0])(0.0)
    for p in range(plane_first[w], plane_first[w + 1]):
        phi = plane_distance(x, plane_point[p], plane_normal[p], plane_hole_center[p], plane_hole_radius[p])
        if is_surface(phi):
            worst = wp.max(worst, -phi)
    for s in range(sphere_first[w], sphere_first[w + 1]):
        phi, _n = sphere_distance(x, sphere_center[s], sphere_radius[s])
        if is_surface(phi):
            worst = wp.max(worst, -phi)
    for m in range(mesh_first[w], mesh_first[w + 1]):
        # A closed mesh's inside is all of it (the winding number says which), however deep; an
        # open sheet is solid only as far behind it as it pushes particles out (its reach), or
        # all space below a ground sheet's plane, beside it too, would count.
        reach = mesh_reach[m]
        if mesh_closed[m] != 0:
            reach = type(reach)(NO_SURFACE)
        phi, _n = mesh_distance(x, mesh_id[m], mesh_closed[m], reach, mesh_tri_start[m], mesh_tris, mesh_points)
        if is_surface(phi):
            worst = wp.max(worst, -phi)
    if worst > type(worst)(0.0):
        wp.atomic_max(depth_out, w, worst)
    first = bowl_first[w]
    for b in range(first, bowl_first[w + 1]):
        c = bowl_center[b]
        cut = bowl_cut_height[b]
        above = False
        mo = bowl_motion[b]
        if mo >= 0:
            above = rotate(-motion_turn_now[mo], x - c)[1] + motion_rest_point[mo][1] >= cut
            cut = type(cut)(NO_SURFACE)
        phi, _n = bowl_distance(x, c, bowl_radius[b], cut)
        if is_surface(phi) and not above:
            slot = particle_jelly[i] * bowl_slots + (b - first)
            wp.atomic_min(shell_lo_out, slot, phi)
            wp.atomic_max(shell_hi_out, slot, phi)


@both_precisions
@wp.kernel
def combine_shell_depths(
    jelly_world: wp.array(dtype=wp.int32),
    bowl_first: wp.array(dtype=wp.int32),
    bowl_slots: int,
    shell_lo: wp.array(dtype=Float),
    shell_hi: wp.array(dtype=Float),
    # In and out, per world: the deepest particle inside terrain [m].
    depth: wp.array(dtype=Float),
):
    # A bowl is a shell, free space on both sides: a jelly is inside it only when the shell cuts
    # it, some particles on each side, and then by the shallower of its two excursions.
    t = wp.tid()
    j = t // bowl_slots
    w = jelly_world[j]
    if t % bowl_slots < bowl_first[w + 1] - bowl_first[w]:
        lo = shell_lo[t]
        hi = shell_hi[t]
        if lo < type(lo)(0.0) and hi > type(lo)(0.0):
            wp.atomic_max(depth, w, wp.min(-lo, hi))


@both_precisions
@wp.kernel
def measure_position_error(
    world_start: wp.array(dtype=wp.int32),
    particle_q: wp.array(dtype=vec3),
    reference_q: wp.array(dtype=wp.vec3d),
    # Out, per world: RMS over its particles of |x - x_ref| [m], in float64.
    error_out: wp.array(dtype=wp.float64),
):
    w = wp.tid()
    a = world_start[w]
    b = world_start[w + 1]
    total = wp.float64(0.0)
    for i in range(a, b):
        x = particle_q[i]
        d = wp.vec3d(wp.float64(x[0]), wp.float64(x[1]), wp.float64(x[2])) - reference_q[i]
        total += wp.dot(d, d)
    error_out[w] = wp.sqrt(total / wp.float64(wp.max(b - a, 1)))
