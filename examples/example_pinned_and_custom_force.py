# SPDX-License-Identifier: Apache-2.0
"""Example: pinned particles and a custom force written as a Warp kernel.

(a) Pinning. A particle of mass 0 has inverse mass 0 (``Model.particle_inv_mass``), which every
    integrator reads as infinite mass: gravity and spring forces give it no acceleration, and the
    contact response leaves it alone. ``add_jelly`` takes one mass per particle as well as one for
    all, so a jelly whose four top corners have mass 0 hangs from them.

(b) A custom force. ``model.contact_hooks`` (given to ``ModelBuilder.finalize(contact_hooks=...)``) holds callables
    ``hook(model, state_in, state_out, h, world_contact_beta)`` that every integrator calls at the end
    of each step, after terrain contact (``softsim_warp.core.contact.apply_contacts``). A hook that
    only launches kernels is captured into ``Stepper``'s graphs with the rest of the step. Here a
    hook applies a linear drag towards a wind velocity, F = c (v_wind - v) on every free particle, as
    an impulse on the step's result (operator splitting: first order in dt, whatever the integrator;
    Runge-Kutta stages do not see the force). A force inside the stages needs a kernel in the library
    (docs/ARCHITECTURE.md, "How to add a force").

The jelly is run twice from the same start, without and with the wind, and the example prints how
far the pinned particles moved (exactly 0 m) and how far the wind pushed the jelly's centre of mass
downwind compared with the calm run.

Run::

    python examples/example_pinned_and_custom_force.py
    python examples/example_pinned_and_custom_force.py --wind 5 --drag 0.05 --integrator rk4
    python examples/example_pinned_and_custom_force.py --device cuda:0 --resolution 12

Only the explicit integrators are offered: the implicit one takes every particle a hook changed for
a contact (it constrains it and solves again) and runs the hooks twice a step, which suits a contact
response but not a force.
"""

import argparse

import numpy as np
import warp as wp

import softsim_warp as ss

SIZE = 0.4  # jelly edge [m]
CENTER = (0.0, 1.0, 0.0)  # initial jelly centre [m]
DAMPING_RATIO = 0.2  # of each spring with one particle on it, zeta = kd / (2 sqrt(ks m))


@wp.kernel
def wind_drag(
    wind: wp.vec3,
    drag: float,
    h: float,
    particle_inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_contact_beta: wp.array(dtype=float),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
):
    """Kick by the drag force F = drag (wind - v) over a step of h; fixed particles are left alone."""
    i = wp.tid()
    inv_mass = particle_inv_mass[i]
    if inv_mass == 0.0:
        return
    a = drag * (wind - qd[i]) * inv_mass
    qd[i] = qd[i] + h * a
    # The position gain of the contact response: beta = 1 for symplectic Euler, which moves x with
    # the new v (x gains h^2 a); 0 for the other methods, whose x picks the kick up in the next step.
    q[i] = q[i] + world_contact_beta[particle_world[i]] * h * h * a


class WindDrag:
    """A contact hook that applies ``wind_drag`` to the step's result in place (one launch)."""

    def __init__(self, wind, drag):
        self.wind = wp.vec3(*wind)
        self.drag = float(drag)

    def __call__(self, model, state_in, state_out, h, world_contact_beta):
        wp.launch(
            wind_drag,
            dim=model.particle_count,
            inputs=[self.wind, self.drag, h, model.particle_inv_mass, model.particle_world, world_contact_beta],
            outputs=[state_out.particle_q, state_out.particle_qd],
            device=model.device,
        )


def build(resolution, total_mass, ks, device, contact_hooks=()):
    """A cube jelly whose four top corners have mass 0; returns the model and the pinned indices."""
    n = resolution
    shape = (n, n, n)
    particle_mass = total_mass / n**3
    # Particle (i, j, k) has index (i n + j) n + k (softsim_warp.core.lattice); y grows with j.
    pinned = np.array([(i * n + (n - 1)) * n + k for i in (0, n - 1) for k in (0, n - 1)])
    mass = np.full(n**3, particle_mass)
    mass[pinned] = 0.0
    kd = 2.0 * DAMPING_RATIO * (ks * particle_mass) ** 0.5
    springs = {name: {"ks": ks, "kd": kd} for name in ("structural", "shear", "bending")}
    builder = ss.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    builder.add_jelly(shape, SIZE, mass, springs, center=CENTER)
    return builder.finalize(device=device, contact_hooks=contact_hooks), pinned


def simulate(args, wind):
    """Run the hanging jelly for ``args.frames`` frames, with the wind hook when ``wind`` is given.

    Returns the model, the pinned indices and the initial and final positions [m].
    """
    hooks = [WindDrag(wind, args.drag)] if wind is not None else []
    model, pinned = build(args.resolution, args.mass, args.ks, args.device, hooks)
    integrator = ss.make_integrator(args.integrator, model)
    dt = 1.0 / (args.fps * args.steps_per_frame)
    stepper = ss.Stepper(model, integrator, dt)
    q0 = stepper.state.particle_q.numpy().astype(np.float64)
    for _ in range(args.frames):
        stepper.advance(args.steps_per_frame)
    return model, pinned, q0, stepper.state.particle_q.numpy().astype(np.float64)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0")
    parser.add_argument("--frames", type=int, default=120, help="frames to simulate")
    parser.add_argument("--fps", type=int, default=60, help="frames per second")
    parser.add_argument("--steps-per-frame", type=int, default=64, help="steps per frame (dt = 1 / (fps * steps))")
    parser.add_argument("--resolution", type=int, default=6, help="particles per jelly edge")
    parser.add_argument("--mass", type=float, default=0.5, help="jelly mass [kg] (the pinned corners carry none)")
    parser.add_argument("--ks", type=float, default=25.0, help="spring stiffness [N/m]")
    parser.add_argument("--wind", type=float, default=3.0, help="wind speed along +x [m/s]")
    parser.add_argument("--drag", type=float, default=0.01, help="drag coefficient per particle [N s/m]")
    explicit = [name for name in ss.INTEGRATORS if name != "implicit"]
    parser.add_argument("--integrator", choices=explicit, default="symplectic", help="explicit method")
    args = parser.parse_args(argv)

    model, pinned, q0, calm = simulate(args, wind=None)
    _, _, _, windy = simulate(args, wind=(args.wind, 0.0, 0.0))

    m = model.particle_mass_host
    com0, com_calm, com_windy = (m @ q / m.sum() for q in (q0, calm, windy))
    moved = max(np.linalg.norm(q[pinned] - q0[pinned], axis=1).max() for q in (calm, windy))
    t = args.frames / args.fps
    print(f"{args.integrator}: {model.particle_count} particles, {len(pinned)} pinned, {t:.3g} s simulated")
    print(f"pinned particles moved: {float(moved)!r} m")
    print(f"centre of mass sagged under gravity by {com0[1] - com_calm[1]:.6f} m (calm run)")
    drift_calm, drift_windy = com_calm[0] - com0[0], com_windy[0] - com0[0]
    print(f"downwind centre-of-mass drift: calm {drift_calm:.3g} m, wind {args.wind:g} m/s {drift_windy:.3g} m")
    print(f"the custom force changed the drift by {drift_windy - drift_calm:.6f} m")


if __name__ == "__main__":
    main()
