# SPDX-License-Identifier: Apache-2.0
"""Example: drop a jelly onto the ground and write the animation to USD.

Shows the API's loop from a built-in scene to a USD file:

    scene -> Model -> integrator -> Stepper (whole frames, replayed as captured graphs) -> UsdWriter

The built-in scene ``jelly_drop`` holds a 10x10x10 jelly (1 kg, 0.5 m) released at 1 m above a
ground plane, tilted by 20 degrees so that it lands on an edge, bounces and settles. Every output
frame is written to the USD stage (``/World/Jelly_0/Particles`` and ``/World/Jelly_0/Surface`` move,
``/World/Plane_0`` stays); view it in usdview or with ``softsim preview OUT.usdc --gif anim.gif``.

Run (the first run compiles the kernels, which takes a while; later runs load them from Warp's
kernel cache)::

    python examples/example_drop_jelly_usd.py
    python examples/example_drop_jelly_usd.py --device cuda:0 --integrator rk4 --frames 300
    python examples/example_drop_jelly_usd.py --resolution 4 --frames 5 --out /tmp/drop.usda

It prints where the file went and the final centre-of-mass height.
"""

import argparse
import math

import numpy as np

import softsim_warp as ss


def center_of_mass(model, state) -> np.ndarray:
    """Mass-weighted mean position of all particles [m]."""
    m = model.particle_mass_host
    return m @ state.particle_q.numpy().astype(np.float64) / m.sum()


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0")
    parser.add_argument("--frames", type=int, default=120, help="output frames after frame 0")
    parser.add_argument("--fps", type=int, default=60, help="output frames per second")
    parser.add_argument("--resolution", type=int, default=10, help="particles per jelly edge")
    parser.add_argument("--integrator", choices=ss.INTEGRATORS, default=None, help="default: the scene's (symplectic)")
    parser.add_argument("--out", default="example_drop_jelly.usdc", help="USD file (.usdc or .usda)")
    args = parser.parse_args(argv)

    # Scene values can be overridden by dotted key, as with `softsim run --set`; the scene is validated
    # after the override, so total_mass is spread over the new particle count.
    n = args.resolution
    scene = ss.load_scene("jelly_drop", [f"jelly.0.resolution=[{n}, {n}, {n}]"])
    model = ss.build_model(scene, device=args.device)
    integrator = ss.make_integrator(args.integrator or scene.sim["integrator"], model)

    # Whole frames of equal length: the smallest number of steps per frame that keeps dt at or
    # below the scene's (a larger step could leave the integrator's stability range).
    steps_per_frame = math.ceil(1.0 / (args.fps * scene.sim["dt"]))
    dt = 1.0 / (args.fps * steps_per_frame)
    stepper = ss.Stepper(model, integrator, dt)

    writer = ss.UsdWriter(args.out, model, args.fps)
    writer.write_frame(0, 0.0, stepper.state.particle_q.numpy())
    for frame in range(1, args.frames + 1):
        # The first call captures steps_per_frame steps as a graph; every later frame replays it.
        stepper.advance(steps_per_frame)
        writer.write_frame(frame, frame / args.fps, stepper.state.particle_q.numpy())
    writer.close()

    com = center_of_mass(model, stepper.state)
    print(f"{integrator.name}: {model.particle_count} particles, dt {dt:.3g} s, {steps_per_frame} steps per frame")
    print(f"wrote {args.frames + 1} frames ({args.frames / args.fps:.3g} s) to {writer.path.resolve()}")
    print(f"final centre-of-mass height: {com[1]:.6f} m")


if __name__ == "__main__":
    main()
