"""Fused explicit stages on the lattice path: one kernel per stage evaluates forces and updates.

``ExplicitIntegrator`` calls :func:`configure_fused` from its constructor and, when ``fused`` is
set, :func:`step_fused` from ``step``. The kernel follows the lattice kernel the model chose:

* gather (CUDA): ``integrate_lattice_stage`` gathers each particle's spring force, adds gravity
  and writes the particle's stage update; on a world's last stage it also applies plane contact
  (and between stages the resting-contact filter), so a symplectic or Euler step over planes is a
  single launch. A model of one jelly of one particle mass with shared coefficients, from
  ``SINGLE_FROM`` particles on, steps with the shape-compiled stage (``make_single_stage``)
  instead: the same kernel compiled for the jelly's shape and spring types, reading no
  per-particle jelly, world or mass and no bounds (its states are padded,
  ``Model.particle_array``); docs/PERFORMANCE.md has the gain.
* masked (mesh jellies, ``model.masked``, core/masked_lattice.py): the same stage kernel around the
  masked gather (``make_masked_stage``, kernels/lattice.py), each neighbour read through the jelly's
  index grid, coefficients from the per-jelly tables.
* rows (CPU): ``integrate_lattice_rows_stage`` computes a jelly's forces with the vectorised row
  loops and then its particles' stage update; contact follows as its own kernel.

Other terrain (``model.contact_hooks``) always runs after the step.

A fused stage reads neighbours from the stage state and writes the next stage state, so the two
must be different buffers: multi-stage methods ping-pong between two stage buffers.

``eval_forces`` stays the one force routine for everything else (the implicit integrator, tests).
"""

from __future__ import annotations

import warp as wp

from .contact import apply_contacts, filter_stage_contacts, moves, plane_arrays
from .lattice_model import LatticeData
from ..kernels import lattice as lattice_kernels

# Particles from which a one-jelly model steps with the shape-compiled stage (``make_single_stage``).
# Below, a few blocks per SM leave the latency to the loads each thread has in flight, and the
# shape-compiled stage does not pay (docs/PERFORMANCE.md).
SINGLE_FROM = 1 << 18


def configure_fused(integrator, fused=None, fuse_contact=None, single=None):
    """Decide whether ``integrator`` uses fused stages (default: whenever the model takes the lattice
    path), whether plane contact joins them (default: yes, where the gather kernel runs) and whether
    a one-jelly model steps with the shape-compiled stage (``single``; default: from ``SINGLE_FROM``
    particles on)."""
    model = integrator.model
    lat = model.lattice
    masked = model.masked
    if fused is None:
        fused = lat is not None or masked is not None
    if fused and lat is None and masked is None:
        raise ValueError(f"fused stages need the lattice path ({model.lattice_reason})")
    integrator.fused = bool(fused)
    if fused and lat is None:
        masked.make_stage_tables()
    # Only the gather kernel can apply contact per particle; the row kernel works per jelly. On by
    # default: the fused stage calls the same contact_planes as collide_planes on the same values
    # (tests/test_perf_paths.py: bitwise on the CPU), one launch fewer per stage with planes.
    gather = fused and (lat is None or lat.per_particle)
    if fuse_contact is None:
        fuse_contact = True
    # Moving planes take their own kernel after the stage (core/contact.py), which reads their motion.
    integrator.fuse_contact = bool(gather and model.plane_count and bool(fuse_contact) and not moves(model, "plane"))
    eligible = lat is not None and lat.single
    if single is None:
        single = eligible and model.particle_count >= SINGLE_FROM
    elif single and not eligible:
        raise ValueError("the one-jelly stage needs a model of one lattice jelly of one particle mass")
    integrator.single = bool(gather and single)
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
    rows = lat is not None and lat.kernel == "rows"
    q, qd = state_in.particle_q, state_in.particle_qd
    stage_kernel = None
    tables, coef = (lat.stencil_tables, lat.stencil_coef) if lat is not None else (None, None)
    if not rows:
        gathered = [q, qd] + [a for pair in bufs[: stage_buffer_count(integrator)] for a in pair]
        # The fused stages address every per-particle array from its data pointer.
        LatticeData.check_contiguous(*gathered, state_out.particle_q, state_out.particle_qd)
        if lat is None:
            # Masked lattice: neighbours through the index grid, every load valid (no padding needed).
            masked_tables = model.masked
            tables, coef = masked_tables.stage_tables, masked_tables.stencil_coef
            stage_kernel = lattice_kernels.make_masked_stage(model.scalar)
        elif integrator.single and lat.padded(*gathered):
            # Compiled for the jelly's shape and spring types (kernels/lattice.py make_single_stage).
            stage_kernel = lattice_kernels.make_single_stage(model.scalar, lat.layout.shape[0], lat.layout.types[0])
        else:
            stage_kernel = lattice_kernels.make_integrate_lattice_stage(model.scalar, lattice_kernels.make_gather_native(model.scalar))
    for stage in range(integrator.stage_count):
        q_next, qd_next = bufs[stage % 2]
        outputs = [integrator.acc_q, integrator.acc_qd, q_next, qd_next, state_out.particle_q, state_out.particle_qd]
        with integrator.profile.part("stages"):
            if rows:
                wp.launch(
                    lattice_kernels.integrate_lattice_rows_stage,
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
                        integrator.run.forces.lattice_scratch,
                        integrator.f,
                    ],
                    outputs=outputs,
                    device=model.device,
                )
            else:
                wp.launch(
                    stage_kernel,
                    dim=model.particle_count,
                    inputs=[
                        stage,
                        h,
                        int(integrator.fuse_contact),
                        model.particle_inv_mass,
                        model.particle_world,
                        model.particle_jelly,
                        model.gravity,
                        *tables,
                        integrator.world_stage_count,
                        integrator.world_symplectic,
                        integrator.world_stage_c,
                        integrator.world_stage_b,
                        *plane_arrays(model, integrator.run),
                        model.contact_epsilon,
                        model.contact_velocity_epsilon,
                        model.restitution_threshold_steps,
                        integrator.world_contact_beta,
                        coef,
                        state_in.particle_q,
                        state_in.particle_qd,
                        q,
                        qd,
                    ],
                    outputs=outputs,
                    device=model.device,
                )
        q, qd = q_next, qd_next
        if stage < integrator.stage_count - 1:
            with integrator.profile.part("contact"):
                filter_stage_contacts(
                    model, integrator.run, state_in, q, qd, integrator.world_contact_beta, planes=not integrator.fuse_contact
                )
    with integrator.profile.part("contact"):
        apply_contacts(model, integrator.run, state_in, state_out, dt, integrator.world_contact_beta,
                       planes=not integrator.fuse_contact)
