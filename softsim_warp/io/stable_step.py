"""The stable step before the run: ``dt = "auto"``, and the refusal of a dt the jellies cannot take.

Each jelly's largest stable step is predicted for the scene's integrator by the linear analysis of
the jelly, free and at rest (:func:`softsim_warp.core.stability_model.predict_jelly_dt`: Lanczos on
its own spring list in NumPy, so no Warp kernel compiles before the answer). Pinned particles are
held fixed, as in the run; gravity, terrain and contact are left out.

* ``softsim run``, ``compare`` and ``sweep`` refuse a dt above :data:`REFUSE_FACTOR` times a jelly's
  prediction (exit 2, one line naming the jelly, the integrator and the largest stable dt). The
  factor covers the prediction's error against limits measured by stepping (docs/STABILITY.md):
  within 5 % for whole jellies, so a refused dt is unstable, while a dt between the prediction and
  the factor is let through (it may still explode; the explosion message then says so). Implicit
  Euler is unconditionally stable and never refused.
* ``dt = "auto"`` (``--dt auto``) is :data:`AUTO_FRACTION` times the smallest prediction over the
  jellies, rounded down to a whole number of steps per frame (``1/fps / n``), so frames stay whole.
  With implicit Euler it is the frame interval ``1/fps``.

A box jelly of more than :data:`BLOCK` particles along an axis is analysed as a block of at most
:data:`BLOCK` per axis at its own spacing, masses and springs, without its pins (pins only raise the
limit): the highest frequencies, which set the limit, belong to the finest modes and hardly depend on
the jelly's extent (jelly_drop's springs: symplectic 9.410e-4 s at 24^3, 9.389e-4 at 32^3, 9.384e-4
at 40^3, 0.3 % apart, well inside :data:`REFUSE_FACTOR`), while the whole jelly's analysis would
cost host memory and time in proportion to its particles, all of it before the run starts.

Predictions are cached per jelly (springs, masses, lattice, pins), so the variants of a sweep or a
comparison that differ elsewhere share them.
"""

from __future__ import annotations

import json
import math
import os

from ..core.errors import SceneError
from ..core.methods import method as method_of  # ``method`` names a method in this module
from ..core.stability_model import predict_jelly_dt

REFUSE_FACTOR = 1.1
AUTO_FRACTION = 0.9
# The pre-flight's Lanczos settings: each method's step to 1e-3 (relative) over 5 iterations, far
# inside the factors above; the bound on its work is what tests/test_stable_step.py checks.
PREFLIGHT = {"tol": 1e-3, "dt_tol": 1e-3, "min_iterations": 20, "check_every": 5}
BLOCK = 24

_CACHE: dict = {}


def _jelly_key(jelly: dict, pinned) -> str:
    keys = ("resolution", "size", "particle_mass", "springs", "mesh", "mesh_prim", "_mesh_scale", "_mesh_center")
    parts = {k: jelly.get(k) for k in keys}
    if "mesh" in jelly:
        try:
            st = os.stat(jelly["mesh"])
            parts["_file"] = (st.st_mtime_ns, st.st_size)
        except OSError:
            parts["_file"] = None
    parts["_pinned"] = sorted(pinned)
    return json.dumps(parts, sort_keys=True, default=str)


def _pinned(data: dict, i: int) -> list:
    return [k for p in data.get("pin", []) if p["jelly"] == i for k in p["indices"]]


def jelly_limit(data: dict, i: int, method: str) -> float:
    """Largest stable dt [s] of ``method`` predicted for jelly ``i`` of a validated scene (``inf``:
    no limit; ``0.0``: unstable at every dt, an undamped mode with euler or midpoint)."""
    if not method_of(method).explicit:  # unconditionally stable
        return math.inf
    jelly = data["jelly"][i]
    block = "mesh" not in jelly and max(jelly["resolution"]) > BLOCK
    pinned = [] if block else _pinned(data, i)
    key = _jelly_key(jelly, pinned)
    dts = _CACHE.setdefault(key, {})
    if method not in dts:
        if len(_CACHE) > 256:
            _CACHE.pop(next(iter(_CACHE)))
        max_n = BLOCK if block else None
        dts[method] = predict_jelly_dt(jelly, (method,), max_n=max_n, pinned=pinned, **PREFLIGHT).dt[method]
    return dts[method]


def describe(data: dict, i: int) -> str:
    """``jelly.2 (mesh bunny.obj)`` or ``jelly.0 (box lattice 10x10x10)``."""
    jelly = data["jelly"][i]
    if "mesh" in jelly:
        return f"jelly.{i} (mesh {os.path.basename(str(jelly['mesh']))})"
    return f"jelly.{i} (box lattice {'x'.join(str(n) for n in jelly['resolution'])})"


def _floor2(x: float) -> float:
    """``x`` rounded down to two significant digits (a printed limit is never above the prediction)."""
    if not (math.isfinite(x) and x > 0):
        return x
    e = math.floor(math.log10(x)) - 1
    return math.floor(x / 10.0**e) * 10.0**e


def limit_problem(data: dict, dt: float, method: str) -> str | None:
    """What is wrong with ``dt`` for the scene's jellies, or None: the first jelly whose predicted
    limit times :data:`REFUSE_FACTOR` is below ``dt``."""
    for i in range(len(data["jelly"])):
        lim = jelly_limit(data, i, method)
        if lim == 0.0:
            return (f"{describe(data, i)} is unstable with {method} at every dt (a spring mode without damping); "
                    "give its springs kd > 0, or use symplectic, rk4 or implicit")
        if dt > REFUSE_FACTOR * lim:
            shown = f"{_floor2(lim):.2g}"
            return f'{describe(data, i)} is unstable with {method} above {shown} s; use dt <= {shown} or dt = "auto"'
    return None


def check_stable_dt(data: dict, source: str, blame=None, refuse=True) -> None:
    """Refuse a validated scene whose dt is above a jelly's stable step (see the module docstring);
    nothing with ``refuse`` False (``--allow-unstable``).

    Raises:
        SceneError (``simulation.dt``), or what ``blame`` makes of it (a flag's error).
    """
    if not refuse:
        return
    sim = data["simulation"]
    problem = limit_problem(data, sim["dt"], sim["integrator"])
    if problem is not None:
        err = SceneError(source, "simulation.dt", problem, sim["dt"])
        raise (blame(err) if blame is not None else err) from None


def auto_dt(data: dict) -> tuple[float, str | None]:
    """``(dt, None)``: the ``"auto"`` step of a validated scene; ``(0.0, why)`` when there is none."""
    sim = data["simulation"]
    frame = 1.0 / sim["fps"]
    method = sim["integrator"]
    smallest = math.inf
    for i in range(len(data["jelly"])):
        lim = jelly_limit(data, i, method)
        if lim == 0.0:
            return 0.0, (f"no stable dt: {describe(data, i)} is unstable with {method} at every dt (a spring mode "
                         "without damping); give its springs kd > 0, or use symplectic, rk4 or implicit")
        smallest = min(smallest, lim)
    target = AUTO_FRACTION * smallest
    if target >= frame:
        return frame, None
    return frame / math.ceil(frame / target - 1e-9), None


def resolve_auto(out: dict, ctx) -> None:
    """Replace ``simulation.dt = "auto"`` of a validated scene by its step (``_dt_auto`` records it)."""
    sim = out["simulation"]
    if sim.get("dt") != "auto":
        return
    dt, why = auto_dt(out)
    if why is not None:
        ctx.fail("simulation.dt", why, "auto")
    sim["dt"] = dt
    sim["_dt_auto"] = True


def share_auto_dt(datas: list) -> None:
    """The copies of a comparison share one clock: an ``"auto"`` dt becomes the smallest of their
    auto steps (each for its own integrator)."""
    auto = [d for d in datas if d["simulation"].get("_dt_auto")]
    if auto:
        shared = min(d["simulation"]["dt"] for d in auto)
        for d in auto:
            d["simulation"]["dt"] = shared


def check_variants(datas: list, source: str, names=None, blame=None, refuse=True) -> None:
    """Every copy of a comparison checked as a run is (nothing without ``refuse``): the first copy
    above its limit refuses the comparison."""
    for k, d in enumerate(datas if refuse else ()):
        sim = d["simulation"]
        problem = limit_problem(d, sim["dt"], sim["integrator"])
        if problem is not None:
            which = f"copy {names[k]}: " if names and len(datas) > 1 else ""
            err = SceneError(source, "simulation.dt", which + problem, sim["dt"])
            raise (blame(err) if blame is not None else err) from None


def check_sweep(variants: list, source: str, mode: str, explore: bool, blame=None) -> int:
    """A sweep's variants against their stable steps; returns how many are above their limit.

    A sweep that explores the step is never refused: ``--find-stable-dt`` (``mode`` ``"stable_dt"``)
    finds the limit itself and is not checked, and with ``--dts`` or ``--allow-unstable``
    (``explore``) the variants above their limit run (and explode, which their rows record) and are
    counted for a warning. Otherwise the first variant above its limit refuses the whole sweep,
    before anything runs (``dt = "auto"`` gives each variant a stable step of its own).
    """
    if mode == "stable_dt":
        return 0
    above = 0
    for v in variants:
        d = v.data
        sim = d["simulation"]
        problem = limit_problem(d, sim["dt"], sim["integrator"])
        if problem is None:
            continue
        if not explore:
            values = ", ".join(f"{k}={val}" for k, val in v.values.items() if k not in ("integrator", "dt"))
            which = f"variant {v.index}" + (f" ({values})" if values else "")
            err = SceneError(source, "simulation.dt", f"{which}: {problem}", sim["dt"])
            raise (blame(err) if blame is not None else err) from None
        above += 1
    return above
