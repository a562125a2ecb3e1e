"""softsim-warp: a mass-spring jelly simulator on NVIDIA Warp.

Typical use::

    import softsim_warp as ss
    scene = ss.load_scene("jelly_drop")
    model = ss.build_model(scene, device="cpu")
    integrator = ss.make_integrator("rk4", model)
    state_0, state_1 = model.state(), model.state()
    integrator.step(state_0, state_1, scene.sim["dt"])
"""

import os as _os

# In an installed package, kernels/ and scenes/ sit inside softsim_warp/ (pyproject maps them there).
# Run from a source checkout (python -m softsim_warp in the repository), they sit beside it instead.
_here = _os.path.dirname(_os.path.abspath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "kernels")) and _os.path.isfile(_os.path.join(_root, "kernels", "__init__.py")):
    __path__.append(_root)

from .errors import ExplosionError  # noqa: E402, SceneError, UserError
from .integrators import ExplicitIntegrator, Integrator, eval_forces, make_integrator  # noqa: E402
from .model import Model, ModelBuilder, State, build_model  # noqa: E402
from .scene import INTEGRATORS, Scene, builtin_scenes, load_scene, scene_from_dict  # noqa: E402
from .simulate import FrameMetrics, RunResult, Simulator  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "INTEGRATORS",
    "ExplicitIntegrator",
    "ExplosionError",
    "FrameMetrics",
    "Integrator",
    "Model",
    "ModelBuilder",
    "RunResult",
    "Scene",
    "SceneError",
    "Simulator",
    "State",
    "UserError",
    "build_model",
    "builtin_scenes",
    "eval_forces",
    "load_scene",
    "make_integrator",
    "scene_from_dict",
]
