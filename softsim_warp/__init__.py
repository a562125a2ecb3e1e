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
``softsim_warp.io`` (scenes, USD, metrics, the frame loop), ``softsim_warp.studies`` (the measurements of
bench, accuracy, compare, stability) and ``softsim_warp.commands`` (the CLI); see docs/ARCHITECTURE.md.
"""

import os as _os

# In an installed package, kernels/ and scenes/ sit inside softsim_warp/ (pyproject maps them there).
# Run from a source checkout (python -m softsim_warp in the repository), they sit beside it instead.
_here = _os.path.dirname(_os.path.abspath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "kernels")) and _os.path.isfile(_os.path.join(_root, "kernels", "__init__.py")):
    __path__.append(_root)

# The public API, imported on first use (PEP 562): ``import softsim_warp`` stays cheap, and the
# command line can install its signal handlers before Warp loads (``__main__.entry``).
_API = {
    "ExplosionError": "core.errors", "SceneError": "core.errors", "UserError": "core.errors",
    "eval_forces": "core.forces",
    "ExplicitIntegrator": "core.integrators", "Integrator": "core.integrators",
    "Model": "core.model", "ModelBuilder": "core.model", "RunState": "core.model", "State": "core.model",
    "build_model": "core.model",
    "Stepper": "core.stepper", "make_integrator": "core.stepper",
    "INTEGRATORS": "io.scene", "Scene": "io.scene", "builtin_scenes": "io.scene", "load_scene": "io.scene",
    "scene_from_dict": "io.scene",
    "FrameMetrics": "io.simulate", "RunResult": "io.simulate", "Simulator": "io.simulate",
    "UsdWriter": "io.usd",
}  # fmt: skip


def __getattr__(name):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'softsim_warp' has no attribute {name!r}")
    import importlib  # noqa: PLC0415

    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))


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
    "RunState",
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
