"""Measure a tall stack against ``jelly_contact_iterations``: how still the top jelly rests.

Usage: python docs/stack_iterations.py [HEIGHT] [ITERATIONS] [DURATION]

Stacks HEIGHT (default 6) copies of the ``stack`` scene's 6^3 jelly on its plane, each dropped 5 cm
onto the one below and shifted by 5 cm sideways in turn (-, 0, +), and runs it on the CPU for
DURATION seconds (default 12) once for each count in ITERATIONS (comma-separated, default 1,2,4,8).
Over the last 2 s it prints the top jelly's height range and drift (mean of the last 0.5 s minus
that of the first 0.5 s), the smallest vertical gap between neighbouring jellies (the pair distance
is 0.1 m), and the largest particle speed at the end.
"""

import itertools
import os
import sys
import tempfile

import numpy as np
import warp as wp

import softsim_warp as ss

SCENE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "stack.toml")
PITCH = 0.65  # m between the jellies' centres at the start: 0.5 m of jelly, the pair distance, 5 cm


def stack_scene(height: int, duration: float) -> str:
    """A TOML scene of ``height`` stacked jellies, written to a temporary file; returns its path."""
    with open(SCENE) as f:
        text = f.read()
    first = text.index("[[jelly]]")
    jelly = text[first : text.index("[[jelly]]", first + 1)]
    parts = [text[:first].replace("duration = 4.0", f"duration = {duration}")]
    for k in range(height):
        centre = f"center = [{0.05 * (k % 3 - 1)}, {0.3 + PITCH * k:.3f}, 0.0]"
        parts.append(jelly.replace("center = [0.0, 0.3, 0.0]", centre))
    parts.append(text[text.index("[[plane]]") :])
    fd, path = tempfile.mkstemp(suffix=".toml", prefix=f"stack{height}_")
    with os.fdopen(fd, "w") as f:
        f.write("\n".join(parts))
    return path


def measure(path: str, iterations: int):
    scene = ss.load_scene(path, [f"simulation.jelly_contact_iterations={iterations}"])
    model = ss.build_model(scene, device="cpu")
    dt = scene.sim["dt"]
    stepper = ss.Stepper(model, ss.make_integrator(scene.sim["integrator"], model), dt)
    steps = round(1.0 / scene.sim["fps"] / dt)
    jellies = [slice(j.particle_start, j.particle_start + j.particle_count) for j in model.jellies]
    duration = scene.frame_count() / scene.sim["fps"]
    top, gap = [], []
    for f in range(scene.frame_count()):
        stepper.advance(steps)
        if (f + 1) / scene.sim["fps"] >= duration - 2.0:
            q = stepper.state.particle_q.numpy()
            top.append(q[jellies[-1], 1].mean())
            gap.append(min(q[b, 1].min() - q[a, 1].max() for a, b in itertools.pairwise(jellies)))
    speed = np.linalg.norm(stepper.state.particle_qd.numpy(), axis=1).max()
    top = np.array(top)
    quarter = len(top) // 4
    return np.ptp(top), top[-quarter:].mean() - top[:quarter].mean(), min(gap), speed


def main(argv) -> int:
    height = int(argv[0]) if argv else 6
    counts = [int(c) for c in argv[1].split(",")] if len(argv) > 1 else [1, 2, 4, 8]
    duration = float(argv[2]) if len(argv) > 2 else 12.0
    wp.config.quiet = True
    path = stack_scene(height, duration)
    try:
        print(f"{height} jellies stacked, {duration} s; over the last 2 s:")
        print("iterations  top range [mm]  top drift [mm]  smallest gap [m]  max speed at end [m/s]")
        for count in counts:
            span, drift, gap, speed = measure(path, count)
            print(f"{count:10d}  {1e3 * span:14.2f}  {1e3 * drift:+14.2f}  {gap:16.4f}  {speed:22.3f}")
    finally:
        os.remove(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
