# SPDX-License-Identifier: Apache-2.0
"""Example: many independent worlds in one model, advanced together in the same kernel launches.

Every particle and terrain primitive belongs to a world (``world=`` of ``ModelBuilder.add_jelly`` and
``add_plane``); particles only collide with their own world's terrain, and jellies never touch each
other, so worlds can overlap in space. One model holding K worlds costs one launch per kernel, not K,
which is how ``softsim compare`` runs its variants side by side.

Here the same jelly is dropped onto its own ground plane once per (integrator, spring stiffness)
pair: ``ExplicitIntegrator`` takes one explicit method per world, so symplectic Euler and RK4 worlds
step in the same launches (a world stops after its method's last stage). At the end it prints one
row per world: the centre-of-mass height at the first impact (the squash, deeper for softer
springs), the highest after it (the rebound) and the final one.

Run::

    python examples/example_batched_worlds.py
    python examples/example_batched_worlds.py --ks 50,200,800,3200 --integrators euler,midpoint,rk4
    python examples/example_batched_worlds.py --device cuda:0 --resolution 10 --out batched.usdc

``--out`` (off by default) writes a USD stage with each world under its own Xform, side by side.
"""

import argparse
import itertools

import numpy as np

import softsim_warp as ss

SIZE = 0.4  # jelly edge [m]
DROP_HEIGHT = 0.6  # initial centre height [m]; the jelly's bottom starts 0.4 m above the ground
DAMPING_RATIO = 0.1  # of each spring with one particle on it


def build(resolution, total_mass, variants, device):
    """One world per (method, ks) variant: the same jelly above its own ground plane."""
    builder = ss.ModelBuilder(gravity=(0.0, -9.8, 0.0))
    particle_mass = total_mass / resolution**3
    for world, (_, ks) in enumerate(variants):
        # Dampers at one damping ratio for every stiffness, zeta = kd / (2 sqrt(ks m)) = DAMPING_RATIO,
        # so that the worlds differ in stiffness only.
        kd = 2.0 * DAMPING_RATIO * (ks * particle_mass) ** 0.5
        springs = {name: {"ks": ks, "kd": kd} for name in ("structural", "shear", "bending")}
        builder.add_jelly(
            (resolution,) * 3, SIZE, particle_mass, springs, center=(0.0, DROP_HEIGHT, 0.0), world=world, name="Jelly"
        )
        builder.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=0.5, friction=0.5, size=2.0, world=world)
    return builder.finalize(device=device)


def world_com_heights(model, state) -> np.ndarray:
    """Centre-of-mass height of each world [m], shape [world_count]."""
    y = state.particle_q.numpy()[:, 1].astype(np.float64)
    m = model.particle_mass_host
    world = model.particle_world.numpy()
    return np.bincount(world, m * y, model.world_count) / np.bincount(world, m, model.world_count)


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0")
    parser.add_argument("--frames", type=int, default=90, help="output frames after frame 0")
    parser.add_argument("--fps", type=int, default=60, help="frames per second")
    parser.add_argument("--steps-per-frame", type=int, default=64, help="steps per frame (dt = 1 / (fps * steps))")
    parser.add_argument("--resolution", type=int, default=5, help="particles per jelly edge")
    parser.add_argument("--mass", type=float, default=1.0, help="jelly mass [kg]")
    parser.add_argument("--ks", default="30,100,300,1000", help="comma-separated spring stiffnesses [N/m]")
    parser.add_argument(
        "--integrators", default="symplectic,rk4", help="comma-separated explicit methods (euler, symplectic, ...)"
    )
    parser.add_argument("--out", default=None, help="optional USD file with the worlds side by side")
    args = parser.parse_args(argv)

    methods = args.integrators.split(",")
    stiffnesses = [float(k) for k in args.ks.split(",")]
    variants = list(itertools.product(methods, stiffnesses))  # world w is variants[w]
    model = build(args.resolution, args.mass, variants, args.device)
    # One method per world: all worlds advance in the same launches.
    integrator = ss.ExplicitIntegrator(model, [method for method, _ in variants])
    dt = 1.0 / (args.fps * args.steps_per_frame)
    stepper = ss.Stepper(model, integrator, dt)

    writer = None
    if args.out:
        # Each world under /World/<name>, shifted along x so that the copies stand side by side.
        groups = {
            w: (f"{m}_ks_{ks:g}".replace(".", "_"), (1.5 * SIZE * w, 0.0, 0.0))
            for w, (m, ks) in enumerate(variants)
        }
        writer = ss.UsdWriter(args.out, model, args.fps, groups=groups)
        writer.write_frame(0, 0.0, stepper.state.particle_q.numpy())

    heights = [world_com_heights(model, stepper.state)]
    for frame in range(1, args.frames + 1):
        stepper.advance(args.steps_per_frame)
        heights.append(world_com_heights(model, stepper.state))
        if writer is not None:
            writer.write_frame(frame, frame / args.fps, stepper.state.particle_q.numpy())
    if writer is not None:
        writer.close()
        print(f"wrote {args.frames + 1} frames to {writer.path.resolve()}")

    heights = np.array(heights)  # [frame, world]
    print(
        f"{model.world_count} worlds x {model.particle_count // model.world_count} particles in one model, "
        f"dt {dt:.3g} s, {args.frames} frames ({args.frames / args.fps:.3g} s)"
    )
    print("centre-of-mass height [m] per world: at the first impact, highest after it (rebound), at the end")
    print(f"{'world':>5}  {'integrator':<10} {'ks [N/m]':>9}  {'impact COM':>10}  {'rebound':>9}  {'final COM':>9}")
    for w, (method, ks) in enumerate(variants):
        h = heights[:, w]
        # The first impact is the first frame after which the centre of mass rises again.
        rising = np.nonzero(np.diff(h) > 0.0)[0]
        impact = int(rising[0]) if rising.size else len(h) - 1
        print(f"{w:>5}  {method:<10} {ks:>9g}  {h[impact]:>10.4f}  {h[impact:].max():>9.4f}  {h[-1]:>9.4f}")


if __name__ == "__main__":
    main()
