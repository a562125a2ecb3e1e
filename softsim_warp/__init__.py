"""softsim-warp: a mass-spring jelly simulator on NVIDIA Warp.

Typical use::

    import softsim_warp as ss
    scene = ss.load_scene("jelly_drop")
    model = ss.build_model(scene, device="cpu")
    integrator = ss.make_integrator("rk4", model)
    state_0, state_1 = model.state(), model.state()
    integrator.step(state_0, state_1, scene.sim["dt"])
"""

from .errors import ExplosionError, SceneError, UserError
from .integrators import ExplicitIntegrator, Integrator, eval_forces, make_integrator
from .model import Model, ModelBuilder, State, build_model
from .scene import INTEGRATORS, Scene, builtin_scenes, load_scene, scene_from_dict
from .simulate import FrameMetrics, RunResult, Simulator

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
