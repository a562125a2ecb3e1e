"""Measure the landmarks of the seed_bowl story (docs/SCENES.md) from a run.

Usage: python docs/seed_bowl_story.py [INTEGRATOR] [DURATION] [--set KEY=VALUE ...]

Runs the built-in scene on the CPU, records every particle 200 times per simulated second and
prints: first contact, the bounce, the tip over the hole's edge, the slide into the bowl, the
climb up the far wall, the centre of mass at 5 s and at the end, and when the particles stop
moving (speeds from positions 1/200 s apart).
"""

import math
import sys

import numpy as np
import warp as wp

from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.model import build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.io.simulate import Simulator

HOLE_RADIUS = 9.0 / math.sqrt(2.0)
AXIS = np.array([2.0, 1.0])  # (x, z) of the hole's centre and the bowl's axis
BOWL_CENTER = np.array([2.0, HOLE_RADIUS, 1.0])
FPS = 200


class _Recorder:
    def __init__(self):
        self.t, self.q = [], []

    def write_frame(self, k, t, q, metrics):
        self.t.append(t)
        self.q.append(q.astype(np.float64))


def main(argv):
    wp.config.quiet = True
    integrator = argv[0] if argv else "midpoint"
    duration = float(argv[1]) if len(argv) > 1 else 8.0
    extra = [a.split("=", 1)[0] + "=" + a.split("=", 1)[1] for a in argv[2:] if a != "--set"]
    scene = load_scene("seed_bowl", [f'simulation.integrator="{integrator}"', f"simulation.duration={duration}",
                                     f"simulation.fps={FPS}", *extra])
    model = build_model(scene, "cpu")
    eps = scene.sim["contact_epsilon"]
    sim = Simulator(model, make_integrator(integrator, model), scene.sim["dt"], FPS, scene.frame_count())
    rec = _Recorder()
    result = sim.run([rec])
    t, q = np.array(rec.t), np.array(rec.q)
    radial = np.hypot(q[..., 0] - AXIS[0], q[..., 2] - AXIS[1])
    # Within the contact tolerance (and 1% over it: implicit Euler holds a resting particle at its edge).
    on_plane = (q[..., 1] < 1.01 * eps) & (radial >= HOLE_RADIUS)
    on_bowl = (9.0 - np.linalg.norm(q - BOWL_CENTER, axis=-1) < 1.01 * eps) & (q[..., 1] < 0.0)
    com = q.mean(axis=1)
    com_radial = np.hypot(com[:, 0] - AXIS[0], com[:, 2] - AXIS[1])

    def first(mask):
        i = int(np.argmax(mask))
        return float(t[i]) if mask[i] else float("nan")

    print(f"seed_bowl, {integrator}, dt = {scene.sim['dt']:g} s, {len(t)} samples, exploded: {result.exploded}")
    tc = first((on_plane | on_bowl).any(axis=1))
    k = int(np.argmax((on_plane | on_bowl).any(axis=1)))
    bottom = q[0, :, 1] < q[0, :, 1].min() + 1e-3
    print(f"first contact          t = {tc:.3f} s (free fall of {q[0, :, 1].min():.3f}: "
          f"{math.sqrt(2 * q[0, :, 1].min() / 9.8):.3f} s); {100 * (radial[k][bottom] < HOLE_RADIUS).mean():.0f}% "
          "of the bottom face over the hole")
    late = (t > tc + 0.05) & (t < 2.5)
    apex = int(np.argmax(np.where(late, com[:, 1], -np.inf)))
    print(f"bounce                 COM rises to y = {com[apex, 1]:.2f} at t = {t[apex]:.2f} s")
    print(f"tips over the edge     t = {first((t > t[apex]) & (q[..., 1].min(axis=1) < -0.05)):.3f} s "
          "(first particle 5 cm below the plane)")
    print(f"slides into the bowl   t = {first(radial.max(axis=1) < HOLE_RADIUS):.3f} s (every particle inside the rim), "
          f"COM below y = 0 at t = {first(com[:, 1] < 0.0):.3f} s")
    window = (t > 3.5) & (t < 6.5)
    top = int(np.argmax(np.where(window, com_radial, -np.inf)))
    print(f"far wall               COM reaches {com_radial[top]:.2f} from the axis (rim at {HOLE_RADIUS:.2f}) at "
          f"t = {t[top]:.2f} s, y = {com[top, 1]:.2f}, {100 * (radial[top] >= HOLE_RADIUS).mean():.0f}% of the "
          "particles beyond the rim")
    for when in sorted({5.0, duration}):
        i = int(np.argmin(np.abs(t - when)))
        print(f"t = {t[i]:5.2f} s            COM = ({com[i, 0]:.3f}, {com[i, 1]:.3f}, {com[i, 2]:.3f}), "
              f"{com_radial[i]:.3f} from the axis (inside the hole radius: {com_radial[i] < HOLE_RADIUS})")
    speed = np.linalg.norm(np.diff(q, axis=0), axis=-1) * FPS
    moving = np.nonzero(speed.mean(axis=1) > 0.01)[0]
    if len(moving):
        print(f"at rest                mean particle speed last above 0.01 m/s at t = {t[moving[-1] + 1]:.2f} s; "
              f"at the end mean {speed[-1].mean():.4f} m/s, max {speed[-1].max():.4f} m/s")
    last = t >= t[-1] - 1.0
    drift = np.linalg.norm(com[last][-1] - com[last][0])
    print(f"last second            the centre of mass moved {1000 * drift:.1f} mm")
    # The stored velocities (what the metrics' max_speed reads), not the positions' differences.
    qd = sim.state.particle_qd.numpy().astype(np.float64)
    print(f"stored velocities      at the end max |v| {np.linalg.norm(qd, axis=1).max():.4f} m/s")


if __name__ == "__main__":
    main(sys.argv[1:])
