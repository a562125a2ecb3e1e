"""Largest energy rise per frame of the implicit integrator on the stiff jelly_drop, per force path.

    python benchmarks/implicit_energy_probe.py --device cuda:0 --paths gather,stencil,springs

The scene and criterion of tests/test_implicit.py::test_stiff_jelly_drop_is_stable_at_dt_0_01
(every spring type at --ks, dt 0.01, 50 frames; nothing supplies energy, so the total must not
rise between frames by more than the CG tolerance's share). Paths: "gather" / "stencil" (the
lattice model's force kernel; eval_forces uses the Warp-loop gather for both), "native" (the
native gather in eval_forces, as tried in the fourth session), "springs" (the spring list).
Results: docs/PERFORMANCE.md, "What the native gather is not used for".
"""

import argparse
import types

import numpy as np

from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.model import build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.io.simulate import Simulator

SPRING_TYPES = ("structural", "shear", "bending")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--paths", default="gather,native,springs")
    parser.add_argument("--ks", type=float, default=1.0e6)
    parser.add_argument("--runs", type=int, default=1)
    args = parser.parse_args()
    print(f"{'path':<10}{'run':>4}{'largest rise':>14}{'frame':>7}{'allowed':>10}{'E end':>9}")
    for path in args.paths.split(","):
        for run in range(args.runs):
            scene = load_scene("jelly_drop", [f"jelly.0.springs.{t}.ks={args.ks}" for t in SPRING_TYPES])
            model = build_model(scene, args.device, force_path="springs" if path == "springs" else "auto")
            if model.lattice is not None:
                model.lattice.set_kernel("stencil" if path == "stencil" else "gather")
                if path == "native":
                    model.kernels = types.SimpleNamespace(**vars(model.kernels))
                    model.kernels.eval_lattice_springs = model.kernels.make_eval_lattice_springs(
                        model.kernels.gather_native
                    )
            integrator = make_integrator("implicit", model)
            result = Simulator(model, integrator, dt=0.01, fps=50.0, frames=50).run()
            e = np.array([m.total_energy for m in result.metrics])
            rise = (e[1:] - e[:-1]) / np.abs(e[:-1])
            k = int(np.argmax(rise))
            print(f"{path:<10}{run:>4}{rise[k]:>+14.2e}{k + 1:>7}{integrator.cg_tolerance:>10.0e}{e[-1]:>9.4f}")


if __name__ == "__main__":
    main()
