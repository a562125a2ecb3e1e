"""Terrain contact of a step: the post-step response and the Runge-Kutta stage filter.

One launch per terrain primitive type the model has (planes, bowls, spheres); a scene without a
bowl launches no bowl kernel. The kernels are in ``kernels/contact.py``, which explains why contact
is applied once per step on the result rather than inside the stages.
"""

from __future__ import annotations

import warp as wp

from ..kernels.contact import LAYER_TOUCH
from .mesh_terrain import mesh_arrays


def apply_contacts(
    model: Model,
    state_in: State,
    state_out: State,
    dt: float,
    world_contact_beta: wp.array,
    planes=True,
    solve_hooks_only=False,
    layer_touch=False,
):
    """Terrain contact on ``state_out`` after a step of ``dt`` from ``state_in``; one launch per primitive type present.

    ``world_contact_beta`` is, per world, the integrator's position gain for a force held constant
    over the step (x_{n+1} gains beta h^2 a): resting contact and friction shift positions by it.
    ``planes=False`` skips the planes (a fused lattice stage has already applied them).
    ``solve_hooks_only`` runs only the hooks whose ``in_contact_solve`` is true (the default for a
    hook): the implicit contact solve constrains what they change, while a hook that conserves
    momentum pair by pair (jelly contact) runs only after the step. ``layer_touch``: a particle
    touches anywhere within ``contact_epsilon`` (``kernels.contact.LAYER_TOUCH``; the implicit
    integrator's response on its free result), not only once its step has reached the surface.
    """
    h = model.scalar(dt)
    stage = LAYER_TOUCH if layer_touch else 0
    _launch_contacts(model, state_in, state_out.particle_q, state_out.particle_qd, h, world_contact_beta, planes, stage)
    for hook in getattr(model, "contact_hooks", ()):
        if not solve_hooks_only or getattr(hook, "in_contact_solve", True):
            hook(model, state_in, state_out, h, world_contact_beta)


def forget_contact_history(model: Model):
    """Make the next step start from no history of the contact hooks (the warm start of jelly
    contact): for a step that is not part of the run (the warm-up) and for a run restarted from its
    initial state, so that it is bitwise the run without them."""
    for hook in getattr(model, "contact_hooks", ()):
        forget = getattr(hook, "forget_history", None)
        if forget is not None:
            forget()


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


def plane_arrays(model) -> tuple:
    """The planes' arrays in the order every plane-contact kernel takes them (``collide_planes``, the fused stage)."""
    return (
        model.plane_first,
        model.plane_point,
        model.plane_normal,
        model.plane_hole_center,
        model.plane_hole_radius,
        model.plane_restitution,
        model.plane_friction,
    )


def _launch_contacts(model: Model, state_in: State, q_out, qd_out, h, world_contact_beta, planes, stage):
    # (count, kernel, the kind's arrays): every collide_* kernel takes the same arguments around them.
    kinds = (
        (
            model.plane_count if planes else 0,
            model.kernels.collide_planes,
            plane_arrays(model),
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
    if getattr(model, "mesh_count", 0):  # triangle-mesh terrain (core/mesh_terrain.py)
        kinds += ((model.mesh_count, model.kernels.collide_meshes, mesh_arrays(model)),)
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
