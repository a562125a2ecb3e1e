"""Measure the `slide` scene: the jelly's acceleration down the slope against the rigid-block law.

Usage: python docs/slide_story.py [INTEGRATOR] [DURATION] [--scene NAME] [--set KEY=VALUE ...]

NAME is another scene with a jelly sliding on its first plane (seed_tilted); default slide.

Runs the built-in scene on the CPU, records the centre of mass 100 times per simulated second and
prints its speed along the slope over time, the acceleration fitted over the sliding phase
(a quadratic fit of the downhill displacement from FIT_START to the end) and the rigid block's
a = g (sin theta - mu cos theta), plus the largest stored particle speed and normal speed at the end.
"""

import math
import sys

import numpy as np
import warp as wp

from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.model import build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.io.simulate import Simulator

FPS = 100
FIT_START = 2.5  # s: the landing (0.33 s) and its rebounds (COM height settles by 2.5 s) are over


class _Recorder:
    def __init__(self):
        self.t, self.com, self.qd = [], [], []

    def write_frame(self, k, t, q, metrics):
        self.t.append(t)
        self.com.append(q.astype(np.float64).mean(axis=0))


def main(argv):
    wp.config.quiet = True
    integrator = argv[0] if argv else "midpoint"
    duration = float(argv[1]) if len(argv) > 1 else 4.0
    rest = list(argv[2:])
    name = "slide"
    if "--scene" in rest:
        k = rest.index("--scene")
        name = rest[k + 1]
        del rest[k : k + 2]
    extra = [a for a in rest if a != "--set"]
    scene = load_scene(name, [f'simulation.integrator="{integrator}"', f"simulation.duration={duration}",
                                 f"simulation.fps={FPS}", *extra])
    model = build_model(scene, "cpu")
    sim = Simulator(model, make_integrator(integrator, model), scene.sim["dt"], FPS, scene.frame_count())
    rec = _Recorder()
    result = sim.run([rec])
    plane = scene.data["plane"][0]
    n = np.asarray(plane["normal"], dtype=np.float64)
    n /= np.linalg.norm(n)
    g = np.asarray(scene.sim["gravity"], dtype=np.float64)
    downhill = g - np.dot(g, n) * n
    g_along = np.linalg.norm(downhill)
    downhill /= g_along
    mu = plane["friction"]
    a_block = g_along - mu * abs(np.dot(g, n))  # g (sin theta - mu cos theta)
    t, com = np.array(rec.t), np.array(rec.com)
    s = com @ downhill
    v = np.gradient(s, t)
    print(f"{name}, {integrator}, dt = {scene.sim['dt']:g} s, mu = {mu:g}, exploded: {result.exploded}")
    for when in np.arange(0.5, duration + 1e-9, 0.5):
        i = int(np.argmin(np.abs(t - when)))
        print(f"t = {t[i]:4.2f} s   downhill speed {v[i]:7.3f} m/s   COM height above the plane {com[i] @ n:.3f}")
    fit = t >= FIT_START
    if fit.sum() > 3:
        a_fit = 2.0 * np.polyfit(t[fit], s[fit], 2)[0]
        rel = (a_fit - a_block) / a_block if a_block != 0 else float("nan")
        print(f"acceleration {FIT_START:g}..{t[-1]:g} s: {a_fit:.4f} m/s^2; rigid block g (sin - mu cos) = "
              f"{a_block:.4f} m/s^2 ({100 * rel:+.1f} %)")
        last = t >= t[-1] - 1.0
        print(f"last second: COM moved {1000 * abs(s[last][-1] - s[last][0]):.3f} mm downhill")
    qd = sim.state.particle_qd.numpy().astype(np.float64)
    print(f"stored velocities at the end: max |v| {np.linalg.norm(qd, axis=1).max():.4f} m/s, "
          f"max |v.n| {np.abs(qd @ n).max():.4f} m/s")


if __name__ == "__main__":
    main(sys.argv[1:])
