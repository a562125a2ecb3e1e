"""softsim-warp: a mass-spring jelly simulator on NVIDIA Warp.

Typical use::

    import softsim_warp as ss
    scene = ss.load_scene("jelly_drop")
    model = ss.build_model(scene, device="cpu")
    integrator = ss.make_integrator("rk4", model)
    state_0, state_1 = model.state(), model.state()
    integrator.step(state_0, state_1, scene.sim["dt"])   # one step, state_0 -> state_1

    stepper = ss.Stepper(model, integrator, scene.sim["dt"])
    stepper.advance(100)                                  # 100 steps, replayed as one captured graph
    positions = stepper.state.particle_q.numpy()

Layers: ``softsim_warp.core`` (model, forces, contact, integrators; imports only ``kernels``),
``softsim_warp.io`` (scenes, USD, metrics, the frame loop) and ``softsim_warp.commands`` (the CLI);
see docs/ARCHITECTURE.md.
"""

import os as _os

# In an installed package, kernels/ and scenes/ sit inside softsim_warp/ (pyproject maps them there).
# Run from a source checkout (python -m softsim_warp in the repository), they sit beside it instead.
_here = _os.path.dirname(_os.path.abspath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "kernels")) and _os.path.isfile(_os.path.join(_root, "kernels", "__init__.py")):
    __path__.append(_root)

from .core.errors import ExplosionError, SceneError, UserError  # noqa: E402
from .core.forces import eval_forces  # noqa: E402
from .core.integrators import ExplicitIntegrator, Integrator  # noqa: E402
from .core.model import Model, ModelBuilder, State, build_model  # noqa: E402
from .core.stepper import Stepper, make_integrator  # noqa: E402
from .io.scene import INTEGRATORS, Scene, builtin_scenes, load_scene, scene_from_dict  # noqa: E402
from .io.simulate import FrameMetrics, RunResult, Simulator  # noqa: E402
from .io.usd import UsdWriter  # noqa: E402

from importlib.metadata import PackageNotFoundError as _NotFound, version as _version  # noqa: E402

try:
    __version__ = _version("softsim-warp")
except _NotFound:  # a source checkout run without installing
    __version__ = "0+source"

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
    "Stepper",
    "UserError",
    "UsdWriter",
    "build_model",
    "builtin_scenes",
    "eval_forces",
    "load_scene",
    "make_integrator",
    "scene_from_dict",
]
