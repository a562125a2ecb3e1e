"""Integrators: explicit Euler, symplectic Euler, midpoint and RK4 (and the seam for implicit).

Force evaluation (:func:`eval_forces`) is apart from integration: every method only combines
evaluations of it. Contact (:func:`apply_contacts`) runs once per step on the result; see
``kernels/contact.py`` for why it is not part of the stages. ``step`` only launches kernels: no
NumPy, no host synchronisation, so a run of steps can be captured as a graph and replayed.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import deterministic
from .model import NUMPY_SCALARS, Model, State

# Butcher tableaux of the explicit methods, as (c, b): stage s is evaluated at
# y_n + h c_s k_{s-1}, and y_{n+1} = y_n + h sum_s b_s k_s. All of them have a_{s,j} = 0 except the
# subdiagonal, which is why c alone describes the stages.
TABLEAUX = {
    "euler": ((0.0,), (1.0,)),
    "midpoint": ((0.0, 0.5), (0.0, 1.0)),
    "rk4": ((0.0, 0.5, 0.5, 1.0), (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)),
    # Symplectic Euler is a partitioned method with one force evaluation; the stage kernel
    # special-cases it (v first, then x with the new v), so its tableau is only a placeholder.
    "symplectic": ((0.0,), (1.0,)),
}
EXPLICIT = tuple(TABLEAUX)
ORDER = {"euler": 1, "symplectic": 1, "midpoint": 2, "rk4": 4, "implicit": 1}
# Position gain of a constant acceleration a over one step, x_{n+1} = ... + beta h^2 a, that the post-step
# contact response adds to positions for the contact force it applies: 1 when x is updated with v_{n+1},
# 0 for explicit Euler (x_{n+1} = x_n + h v_n). Midpoint and RK4 would need sum_s b_s c_s = 1/2, but their
# stage states already hold the contact force of particles resting on terrain (filter_stage_contacts),
# so their positions carry it and the response adds nothing.
CONTACT_BETA = {"euler": 0.0, "midpoint": 0.0, "rk4": 0.0, "symplectic": 1.0, "implicit": 1.0}
MAX_STAGES = 4


def eval_forces(model: Model, q: wp.array, qd: wp.array, f_out: wp.array):
    """Internal forces (springs and dampers) of the state (q, qd) into ``f_out``; gravity is added as an acceleration."""
    if getattr(model, "deterministic", False) and model.lattice is None:
        # Atomic-free: per-spring forces, then a fixed-order gather per particle (deterministic.py).
        deterministic.eval_spring_forces(model, q, qd, f_out)
        return
    if model.lattice is not None:
        from .lattice_model import eval_lattice_forces  # noqa: PLC0415

        eval_lattice_forces(model, q, qd, f_out)
        return
    f_out.zero_()
    if model.spring_count:
        wp.launch(
            model.kernels.eval_springs,
            dim=model.spring_count,
            inputs=[
                model.spring_indices,
                model.spring_rest_length,
                model.spring_stiffness,
                model.spring_damping,
                q,
                qd,
            ],
            outputs=[f_out],
            device=model.device,
        )


def apply_contacts(
    model: Model, state_in: State, state_out: State, dt: float, world_contact_beta: wp.array, planes=True
):
    """Terrain contact on ``state_out`` after a step of ``dt`` from ``state_in``; one launch per primitive type present.

    ``world_contact_beta`` is, per world, the integrator's position gain for a force held constant
    over the step (x_{n+1} gains beta h^2 a): resting contact and friction shift positions by it.
    ``planes=False`` skips the planes (a fused lattice stage has already applied them).
    """
    h = model.scalar(dt)
    _launch_contacts(model, state_in, state_out.particle_q, state_out.particle_qd, h, world_contact_beta, planes, 0)
    for hook in getattr(model, "contact_hooks", ()):
        hook(model, state_in, state_out, h, world_contact_beta)


def filter_stage_contacts(
    model: Model, state_in: State, q_s: wp.array, qd_s: wp.array, world_contact_beta: wp.array, planes=True
):
    """Contact on an intermediate Runge-Kutta stage state (q_s, qd_s) = y_n + h c_s k, velocities only.

    Only particles that the contact response would hold (resting contact, not an impact) change:
    their stage velocity loses its approaching normal part and what friction takes of the
    tangential one. Without this, a particle resting on terrain moves into it within the stage
    (the stage state ignores the surface), and the dampers of its springs answer that fictitious
    velocity: at the seed's kd = 60 that takes ~18 % off the normal force that the step's contact
    then sees, but less off the tangential force, so friction holds less than mu and a resting
    jelly creeps (7 mm/s on a 30 degree slope with mu = 0.7 under midpoint, where symplectic Euler,
    one stage at y_n, holds). Impacts and positions are left to the post-step response, so no
    impulse enters a stage state. Contact hooks are not applied here. ``planes=False`` skips the
    planes (a fused lattice stage with contact has filtered them already).
    """
    _launch_contacts(model, state_in, q_s, qd_s, model.scalar(0.0), world_contact_beta, planes, 1)


def _launch_contacts(model: Model, state_in: State, q_out, qd_out, h, world_contact_beta, planes, stage):
    # (count, kernel, the kind's arrays): every collide_* kernel takes the same arguments around them.
    kinds = (
        (
            model.plane_count if planes else 0,
            model.kernels.collide_planes,
            (
                model.plane_first,
                model.plane_point,
                model.plane_normal,
                model.plane_hole_center,
                model.plane_hole_radius,
                model.plane_restitution,
                model.plane_friction,
            ),
        ),
        (
            model.bowl_count,
            model.kernels.collide_bowls,
            (
                model.bowl_first,
                model.bowl_center,
                model.bowl_radius,
                model.bowl_cut_height,
                model.bowl_restitution,
                model.bowl_friction,
            ),
        ),
        (
            model.sphere_count,
            model.kernels.collide_spheres,
            (
                model.sphere_first,
                model.sphere_center,
                model.sphere_radius,
                model.sphere_restitution,
                model.sphere_friction,
            ),
        ),
    )
    for count, kernel, arrays in kinds:
        if count:
            wp.launch(
                kernel,
                dim=model.particle_count,
                inputs=[
                    model.particle_inv_mass,
                    model.particle_world,
                    *arrays,
                    model.contact_epsilon,
                    model.contact_velocity_epsilon,
                    model.restitution_threshold_steps,
                    h,
                    world_contact_beta,
                    stage,
                    state_in.particle_q,
                    state_in.particle_qd,
                ],
                outputs=[q_out, qd_out],
                device=model.device,
            )


class Integrator:
    """Base class: ``step(state_in, state_out, dt)`` advances one step, contact included."""

    name = "base"

    def __init__(self, model: Model):
        self.model = model

    def step(self, state_in: State, state_out: State, dt: float):
        raise NotImplementedError

    def stats(self) -> dict:
        """Per-run statistics for the metrics file (e.g. linear-solver iterations)."""
        return {}


class ExplicitIntegrator(Integrator):
    """Explicit Euler, symplectic Euler, midpoint or RK4, one method per world.

    Args:
        model: the model to advance.
        method: a method name for every world, or a list with one name per world (the copies of
            a side-by-side comparison advance in the same launches).
        fused, fuse_contact, block_dim, uniform, alternate: the lattice fast path's options
            (:func:`softsim_warp.fastpath.configure_fused`); None picks what pays.
    """

    def __init__(
        self,
        model: Model,
        method="symplectic",
        fused=None,
        fuse_contact=None,
        block_dim=None,
        uniform=None,
        alternate=None,
    ):
        super().__init__(model)
        methods = [method] * model.world_count if isinstance(method, str) else list(method)
        if len(methods) != model.world_count:
            raise ValueError(f"need one method per world ({model.world_count}), got {len(methods)}")
        for name in methods:
            if name not in TABLEAUX:
                raise ValueError(f"unknown explicit integrator {name!r}; choose from {', '.join(TABLEAUX)}")
        self.methods = methods
        self.name = methods[0] if len(set(methods)) == 1 else "mixed"
        np_scalar = NUMPY_SCALARS[model.precision]
        c = np.zeros((model.world_count, MAX_STAGES), dtype=np_scalar)
        b = np.zeros((model.world_count, MAX_STAGES), dtype=np_scalar)
        counts = np.zeros(model.world_count, dtype=np.int32)
        symplectic = np.zeros(model.world_count, dtype=np.int32)
        for w, name in enumerate(methods):
            cw, bw = TABLEAUX[name]
            counts[w] = len(cw)
            c[w, : len(cw)] = cw
            b[w, : len(bw)] = bw
            symplectic[w] = name == "symplectic"
        self.stage_count = int(counts.max())
        device = model.device
        self.world_stage_count = wp.array(counts, dtype=wp.int32, device=device)
        self.world_symplectic = wp.array(symplectic, dtype=wp.int32, device=device)
        self.world_stage_c = wp.array2d(c, dtype=model.scalar, device=device)
        self.world_stage_b = wp.array2d(b, dtype=model.scalar, device=device)
        self.world_contact_beta = wp.array(
            np.array([CONTACT_BETA[name] for name in methods], dtype=np_scalar), dtype=model.scalar, device=device
        )
        # Lattice fast path: one fused kernel per stage (forces + stage update, plane contact on the
        # last stage) where it pays; see softsim_warp/fastpath.py and docs/PERFORMANCE.md.
        from .fastpath import configure_fused  # noqa: PLC0415

        configure_fused(self, fused, fuse_contact, block_dim, uniform, alternate)
        # Stage buffers, allocated once: forces, the stage state and the RK accumulators.
        n = model.particle_count
        # A fused gather stage keeps forces in registers; the row kernel and the plain path need f.
        gather_fused = self.fused and model.lattice.per_particle
        self.f = wp.zeros(0 if gather_fused else n, dtype=model.vec3, device=device)
        multi = self.stage_count > 1
        # Stage states are gathered from like the state itself, so they are made the same way.
        self.q_s = model.particle_array() if multi else wp.zeros(0, dtype=model.vec3, device=device)
        self.qd_s = model.particle_array() if multi else wp.zeros(0, dtype=model.vec3, device=device)
        self.acc_q = wp.zeros(n if multi else 0, dtype=model.vec3, device=device)
        self.acc_qd = wp.zeros(n if multi else 0, dtype=model.vec3, device=device)
        if self.fused:
            from .fastpath import stage_buffers  # noqa: PLC0415

            stage_buffers(self)

    def step(self, state_in: State, state_out: State, dt: float):
        if self.fused:
            from .fastpath import step_fused  # noqa: PLC0415

            step_fused(self, state_in, state_out, dt)
            return
        model = self.model
        h = model.scalar(dt)
        q, qd = state_in.particle_q, state_in.particle_qd
        for stage in range(self.stage_count):
            eval_forces(model, q, qd, self.f)
            wp.launch(
                model.kernels.integrate_stage,
                dim=model.particle_count,
                inputs=[
                    stage,
                    h,
                    model.particle_inv_mass,
                    model.particle_world,
                    model.gravity,
                    self.world_stage_count,
                    self.world_symplectic,
                    self.world_stage_c,
                    self.world_stage_b,
                    state_in.particle_q,
                    state_in.particle_qd,
                    q,
                    qd,
                    self.f,
                ],
                outputs=[self.acc_q, self.acc_qd, self.q_s, self.qd_s, state_out.particle_q, state_out.particle_qd],
                device=model.device,
            )
            q, qd = self.q_s, self.qd_s
            if stage < self.stage_count - 1:
                filter_stage_contacts(model, state_in, q, qd, self.world_contact_beta)
        apply_contacts(model, state_in, state_out, dt, self.world_contact_beta)


def make_integrator(name, model: Model, options: dict | None = None) -> Integrator:
    """The integrator called ``name`` (or one name per world) for ``model``."""
    if isinstance(name, str) and name == "implicit":
        from .implicit import ImplicitIntegrator  # noqa: PLC0415 - optional until it exists

        return ImplicitIntegrator(model, **(options or {}))
    return ExplicitIntegrator(model, name)
