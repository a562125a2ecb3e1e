"""Fused explicit stages on the lattice path: one kernel per stage evaluates forces and updates.

``ExplicitIntegrator`` calls :func:`configure_fused` from its constructor and, when ``fused`` is
set, :func:`step_fused` from ``step``. The kernel follows the lattice kernel the model chose:

* gather (CUDA): ``integrate_lattice_stage`` gathers each particle's spring force, adds gravity
  and writes the particle's stage update; on a world's last stage it also applies plane contact
  (and between stages the resting-contact filter), so a symplectic or Euler step over planes is a
  single launch. When every array it gathers from is padded (``Model.particle_array``: the
  model's states and the integrator's stage buffers are), ``integrate_lattice_stage_padded``
  runs instead: the same sums without bounds-checked loads; and for large models whose jellies
  share their coefficients, ``integrate_lattice_stage_padded_uniform``, which takes them as a
  kernel argument (same bits); and when the model is also one jelly of one particle mass, the
  one-jelly stage, which reads no per-particle jelly, world or mass, compiled for the jelly's
  shape and spring types (``single_stage``: constant neighbour offsets, 48 registers instead of
  64 on an H200, 1.08-1.12x; docs/PERFORMANCE.md).
* rows (CPU): ``integrate_lattice_rows_stage`` computes a jelly's forces with the vectorised row
  loops and then its particles' stage update; contact follows as its own kernel.

Other terrain (``model.contact_hooks``) always runs after the step.

A fused stage reads neighbours from the stage state and writes the next stage state, so the two
must be different buffers: multi-stage methods ping-pong between two stage buffers. Successive
gather launches sweep the particles in opposite directions (``alternate``), so that each starts
on what the previous one wrote last, still in L2; the order changes no result.

``eval_forces`` stays the one force routine for everything else (the implicit integrator, tests).
"""

from __future__ import annotations

import warp as wp

from .contact import apply_contacts, filter_stage_contacts

# Threads per block of the fused stage: Warp's 256, except 128 for the Warp-loop gather ("stencil",
# 96 registers) from this many particles on. H200, fused symplectic / rk4 step at 100^3: stencil
# 0.102 / 0.466 ms at 128 against 0.111 / 0.515 at 256 (third session); the padded native gather
# 0.0679 / 0.3014 ms at 128 against 0.0654 / 0.2903 at 256 (docs/PERFORMANCE.md, fifth session).
SMALL_BLOCKS_FROM = 1 << 18

# Particles from which the padded stage takes its coefficients as a kernel argument when the
# jellies share them (``integrate_lattice_stage_padded_uniform``; 48 registers instead of 64 in the
# seventh session's build).
# H200, seventh session (docs/PERFORMANCE.md): 1.07x symplectic, 1.06x rk4 at 100^3, but 0.96x /
# 0.95x at 40^3, where a few blocks per SM leave the latency to the loads each thread has in flight.
UNIFORM_FROM = 1 << 18


def configure_fused(integrator, fused=None, fuse_contact=None, block_dim=None, uniform=None, alternate=None):
    """Decide whether ``integrator`` uses fused stages (default: whenever the model takes the lattice
    path), whether plane contact joins them, the gather stage's threads per block, whether the
    padded gather takes the jellies' shared coefficients as a kernel argument (``uniform``; default:
    when they share them, from ``UNIFORM_FROM`` particles on), and whether successive gather stages
    sweep the particles in alternating directions (``alternate``, default on; see ``step_fused``)."""
    model = integrator.model
    lat = model.lattice
    if fused is None:
        fused = lat is not None
    if fused and lat is None:
        raise ValueError(f"fused stages need the lattice path ({model.lattice_reason})")
    integrator.fused = bool(fused)
    # Only the gather kernel can apply contact per particle; the row kernel works per jelly. On by
    # default: the fused stage calls the same contact_planes as collide_planes on the same values
    # (tests/test_perf_paths.py: bitwise on the CPU), one launch fewer per stage with planes.
    gather = fused and lat.per_particle
    if fuse_contact is None:
        fuse_contact = True
    integrator.fuse_contact = bool(gather and model.plane_count and bool(fuse_contact))
    if block_dim is None:
        stencil = lat is not None and lat.kernel == "stencil"
        block_dim = 128 if stencil and model.particle_count >= SMALL_BLOCKS_FROM else 256
    integrator.block_dim = int(block_dim)
    shared = lat is not None and lat.uniform
    if uniform is None:
        uniform = shared and model.particle_count >= UNIFORM_FROM
    elif uniform and not shared:
        raise ValueError("uniform coefficients need jellies that share their ks, kd and rest lengths")
    integrator.uniform = bool(gather and uniform)
    # One jelly of one mass: the uniform stage that reads no per-particle jelly, world or mass.
    integrator.single = bool(integrator.uniform and lat.single)
    integrator.alternate = bool(gather and (True if alternate is None else alternate))
    integrator._reverse = 0
    integrator._stage_buffers = None


def stage_buffer_count(integrator) -> int:
    """How many of the two stage states a step uses: none for one stage, the second from three on."""
    return min(integrator.stage_count - 1, 2)


def stage_buffers(integrator):
    """Two stage states (q, qd) to ping-pong between; the second only for methods of three or more stages.

    Made once (the integrator's constructor calls this after allocating its own stage state).
    """
    if integrator._stage_buffers is None:
        model = integrator.model
        count = stage_buffer_count(integrator)
        bufs = []
        for k in range(2):
            if k == 0:
                bufs.append((integrator.q_s, integrator.qd_s))
            elif k < count:
                bufs.append((model.particle_array(), model.particle_array()))
            else:
                empty = wp.zeros(0, dtype=model.vec3, device=model.device)
                bufs.append((empty, empty))
        integrator._stage_buffers = bufs
    return integrator._stage_buffers


def step_fused(integrator, state_in, state_out, dt):
    """One step with one fused kernel per stage (see the module docstring)."""
    model = integrator.model
    lat = model.lattice
    h = model.scalar(dt)
    bufs = stage_buffers(integrator)
    rows = lat.kernel == "rows"
    q, qd = state_in.particle_q, state_in.particle_qd
    stage_kernel = None
    if not rows:
        gathered = [q, qd] + [a for pair in bufs[: stage_buffer_count(integrator)] for a in pair]
        # The fused stages address every per-particle array from its data pointer.
        lat.check_contiguous(*gathered, state_out.particle_q, state_out.particle_qd)
        if lat.kernel == "stencil":
            stage_kernel = model.kernels.integrate_lattice_stage_stencil
        elif lat.padded(*gathered):
            stage_kernel = model.kernels.integrate_lattice_stage_padded
            if integrator.uniform:
                stage_kernel = model.kernels.integrate_lattice_stage_padded_uniform
                if integrator.single:
                    # Compiled for the jelly's shape and spring types (kernels/lattice.py single_stage).
                    stage_kernel = model.kernels.single_stage(lat.layout.shape[0], lat.layout.types[0])
        else:
            stage_kernel = model.kernels.integrate_lattice_stage
    for stage in range(integrator.stage_count):
        q_next, qd_next = bufs[stage % 2]
        outputs = [integrator.acc_q, integrator.acc_qd, q_next, qd_next, state_out.particle_q, state_out.particle_qd]
        if rows:
            wp.launch(
                model.kernels.integrate_lattice_rows_stage,
                dim=lat.jelly_count,
                inputs=[
                    stage,
                    h,
                    *lat.stencil_tables,
                    lat.jelly_world,
                    lat.particle_coord_k,
                    model.particle_inv_mass,
                    model.gravity,
                    integrator.world_stage_count,
                    integrator.world_symplectic,
                    integrator.world_stage_c,
                    integrator.world_stage_b,
                    state_in.particle_q,
                    state_in.particle_qd,
                    q,
                    qd,
                    lat.scratch,
                    integrator.f,
                ],
                outputs=outputs,
                device=model.device,
            )
        else:
            # Alternate sweeps: each launch visits the particles in the direction opposite to the
            # previous one (across steps too), so it first reads the stage state the previous launch
            # wrote last, still in L2. Order does not change the arithmetic: the same bits. A
            # captured graph keeps the directions it was recorded with.
            reverse = integrator._reverse
            if integrator.alternate:
                integrator._reverse = 1 - reverse
            wp.launch(
                stage_kernel,
                dim=model.particle_count,
                inputs=[
                    stage,
                    h,
                    int(integrator.fuse_contact),
                    reverse,
                    model.particle_inv_mass,
                    model.particle_world,
                    model.particle_jelly,
                    model.gravity,
                    *lat.stencil_tables,
                    integrator.world_stage_count,
                    integrator.world_symplectic,
                    integrator.world_stage_c,
                    integrator.world_stage_b,
                    model.plane_first,
                    model.plane_point,
                    model.plane_normal,
                    model.plane_hole_center,
                    model.plane_hole_radius,
                    model.plane_restitution,
                    model.plane_friction,
                    model.contact_epsilon,
                    model.contact_velocity_epsilon,
                    model.restitution_threshold_steps,
                    integrator.world_contact_beta,
                    lat.stencil_coef,
                    state_in.particle_q,
                    state_in.particle_qd,
                    q,
                    qd,
                ],
                outputs=outputs,
                device=model.device,
                block_dim=integrator.block_dim,
            )
        q, qd = q_next, qd_next
        if stage < integrator.stage_count - 1:
            filter_stage_contacts(
                model, state_in, q, qd, integrator.world_contact_beta, planes=not integrator.fuse_contact
            )
    apply_contacts(model, state_in, state_out, dt, integrator.world_contact_beta, planes=not integrator.fuse_contact)
