"""One scene under several integrators or parameter values, side by side (``softsim compare``).

Every variant becomes one *world* (a copy) of a single model, so one launch of each kernel
advances all copies: :class:`~softsim_warp.core.integrators.ExplicitIntegrator` takes one method per
world, and springs and contacts only ever join particles and terrain of the same world. The
copies are laid out in a grid in one USD stage, each under ``/World/<variant>``, in the order
given (four variants make the report's 2x2: explicit Euler, implicit Euler / midpoint, RK4).

Implicit variants cannot share those launches: the implicit integrator solves one linear system
for its whole model and stops its conjugate-gradient iterations on a residual norm over all
particles, so copies in one system would change each other's iteration counts. Each implicit
variant therefore runs as a model of its own, stepped frame by frame in lockstep with the
explicit batch; the stage and the metrics do not show the difference.

All copies share one clock and one model-wide setting: the ``[simulation]`` table (dt, duration,
fps, gravity, contact tolerances, precision) must be the same for every variant; varying one of
its keys is refused with a one-line error (run those values as separate ``softsim run``s).
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import SceneError
from ..core.integrators import ExplicitIntegrator
from ..core.methods import EULER, IMPLICIT, MIDPOINT, RK4, method
from ..core.stepper import make_integrator
from ..io import scene as scene_mod
from ..io import stable_step
from ..io.metrics import explosion_reason
from ..io.outputs import kept_partial_path, save_atomic, write_json_atomic
from ..io.simulate import Simulator
from ..io.usd import UsdWriter
from ..io.worlds import make_builder, world_speed_bound

DEFAULT_INTEGRATORS = tuple(m.name for m in (EULER, IMPLICIT, MIDPOINT, RK4))  # the report's 2x2


# ---------------------------------------------------------------------------------------------
# Variants


@dataclass
class Variant:
    """One copy: its validated scene data, name and the overrides that made it."""

    name: str
    data: dict
    overrides: dict
    world: int = 0

    @property
    def integrator(self) -> str:
        return self.data["simulation"]["integrator"]


@dataclass
class Plan:
    source: str
    name: str
    variants: list
    dt: float
    fps: float
    frames: int
    sim: dict
    end_time: float | None = None
    """The last frame's time when the duration is not a whole number of frames (Scene.end_time)."""


def prim_token(value) -> str:
    """A value as part of a USD prim name: ``1000`` -> ``1000``, ``0.5`` -> ``0p5``, ``-2`` -> ``m2``."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        text = str(int(value))
    elif isinstance(value, float):
        text = f"{value:g}"
    elif isinstance(value, (list, tuple)):
        text = "_".join(prim_token(v) for v in value)
    else:
        text = str(value)
    text = text.replace("-", "m").replace(".", "p").replace("+", "")
    return re.sub(r"[^A-Za-z0-9_]", "_", text)


def short_keys(keys: list[str]) -> dict:
    """The shortest dotted suffix of each key that tells it apart from the others, joined by ``_``."""
    out = {}
    for key in keys:
        parts = key.split(".")
        for n in range(1, len(parts) + 1):
            suffix = parts[-n:]
            if sum(1 for k in keys if k.split(".")[-n:] == suffix) == 1 or n == len(parts):
                out[key] = "_".join(p for p in suffix if not p.isdigit()) or "_".join(suffix)
                break
    return out


def expand_variants(base: dict, path, source: str, integrators, varies, *, blame=None) -> Plan:
    """One validated copy of the scene ``base`` per integrator and combination of ``varies`` values.

    Args:
        base: the scene's data (overrides applied, not yet validated).
        path: the scene file (its stem names the plan when the scene has no ``name``).
        source: the scene's name in messages.
        integrators: one copy per name, in grid order; ``[None]``: the scene's own integrator.
        varies: ``[(dotted key, [values])]``; several keys make a product.
        blame: ``blame(error)``, the error to raise for a copy that fails validation (a command names
            the flag that set the value); default the error itself.

    Raises:
        SceneError: a copy is invalid; with source ``--vary`` where the copies cannot share one
            model (``[simulation]`` differs) or two would get the same name.
    """
    keys = [k for k, _ in varies]
    labels = short_keys(keys)
    variants = []
    for combo in itertools.product(integrators, *[vals for _, vals in varies]):
        integrator, values = combo[0], combo[1:]
        data = copy.deepcopy(base)
        overrides = {}
        parts = []
        if integrator is not None:
            scene_mod.apply_override(data, "simulation.integrator", integrator, source="--integrators")
            overrides["simulation.integrator"] = integrator
            if len(integrators) > 1:
                parts.append(integrator)
        for key, value in zip(keys, values):
            scene_mod.apply_override(data, key, value, source="--vary")
            overrides[key] = value
            parts.append(prim_token(value) if key == "simulation.integrator" else f"{labels[key]}_{prim_token(value)}")
        try:
            validated = scene_mod.validate(data, source)
        except SceneError as e:
            raise (blame(e) if blame is not None else e) from None
        name = "_".join(parts) or validated["simulation"]["integrator"]
        if not re.match(r"[A-Za-z_]", name):
            name = "v_" + name
        variants.append(Variant(name=name, data=validated, overrides=overrides))

    stable_step.share_auto_dt([v.data for v in variants])  # one clock: an "auto" dt is the copies' smallest
    # One clock and one model: [simulation] must agree (the integrator aside).
    first = variants[0].data["simulation"]
    for v in variants[1:]:
        for key in sorted(set(first) | set(v.data["simulation"])):
            if key != "integrator" and first.get(key) != v.data["simulation"].get(key):
                raise SceneError("--vary", f"simulation.{key}", "must be the same for every copy", v.data["simulation"].get(key))
    names = [v.name for v in variants]
    if len(set(names)) != len(names):
        raise SceneError("--vary", None, "two copies would get the same prim name", ", ".join(names))
    for w, v in enumerate(variants):
        v.world = w
    sim = first
    if sim["dt"] > 1.0 / sim["fps"]:
        raise SceneError(source, "simulation.dt", f"must not exceed the frame interval 1/fps = {1.0 / sim['fps']:g} s", sim["dt"])
    first_scene = scene_mod.Scene(variants[0].data)
    frames = first_scene.frame_count()
    name = variants[0].data.get("name", path.stem)
    return Plan(source=source, name=name, variants=variants, dt=sim["dt"], fps=sim["fps"], frames=frames, sim=sim,
                end_time=first_scene.end_time())


# ---------------------------------------------------------------------------------------------
# Layout


def layout(data: dict, count: int, columns=None, gap=None):
    """Grid offsets for ``count`` copies of the scene ``data``, and the drawn plane size.

    The cell is a square around the horizontal centre of the first plane's hole (or its point),
    or of the scene's bounding box when it has no plane, big enough for the jellies' start, the
    holes, bowls and spheres. Planes are drawn one cell wide, so neighbours never overlap.

    Returns:
        ``(offsets [(x, y, z)] in grid order, row by row; plane size [m] or None; cell [m])``.
    """
    pts = []
    for j in data["jelly"]:
        half = 0.5 * math.sqrt(sum(s * s for s in j["size"]))
        c = np.asarray(j["center"])
        pts += [c - half, c + half]
    for p in data.get("plane", []):
        if p.get("hole"):
            c = np.asarray(p["hole"]["center"])
            pts += [c - p["hole"]["radius"], c + p["hole"]["radius"]]
    for b in data.get("bowl", []):
        c = np.asarray(b["center"])
        pts += [c - b["radius"], c + b["radius"]]
    for s in data.get("sphere", []):
        c = np.asarray(s["center"])
        pts += [c - s["radius"], c + s["radius"]]
    pts = np.array(pts)[:, [0, 2]]
    planes = data.get("plane", [])
    if planes:
        p = planes[0]
        centre = np.asarray(p["hole"]["center"] if p.get("hole") else p["point"])[[0, 2]]
    else:
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    half = 1.1 * float(np.max(np.abs(pts - centre)))
    cell = 2.0 * half
    gap = 0.25 * cell if gap is None else float(gap)
    columns = columns or math.ceil(math.sqrt(count))
    pitch = cell + gap
    offsets = [(float((w % columns) * pitch), 0.0, float((w // columns) * pitch)) for w in range(count)]
    return offsets, (cell if planes else None), cell


# ---------------------------------------------------------------------------------------------
# Running


@dataclass
class VariantResult:
    name: str
    integrator: str
    overrides: dict
    world: int
    prim: str
    offset: tuple
    frames: list = field(default_factory=list)
    exploded: dict | None = None
    stats: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "integrator": self.integrator,
            "overrides": self.overrides,
            "world": self.world,
            "prim": self.prim,
            "offset": list(self.offset),
            "exploded": self.exploded,
            "stats": self.stats,
            "frames": self.frames,
        }


@dataclass
class ComparisonResult:
    variants: list
    frames_written: int = 0
    steps: int = 0
    wall_seconds: float = 0.0
    interrupted: bool = False
    written_path: Path | None = None  # where the stage went (<stem>.partial<suffix> when it could not replace --out)


class _Group:
    """Variants advanced by one model and one integrator (the explicit batch, or one implicit copy)."""

    def __init__(self, variants, builder_fn, device, precision, dt, fps, frames, use_graph, max_speed, end_time=None,
                 on_warm_up=None):
        self.variants = variants
        self.model = builder_fn([v.data for v in variants]).finalize(device, precision)
        if all(method(v.integrator).explicit for v in variants):
            integrator = ExplicitIntegrator(self.model, [v.integrator for v in variants])
        else:
            assert len(variants) == 1
            integrator = make_integrator(variants[0].integrator, self.model, variants[0].data.get(IMPLICIT.name))
        self.integrator = integrator
        self.sim = Simulator(self.model, integrator, dt, fps, frames, use_graph=use_graph, max_speed=max_speed,
                             end_time=end_time, on_warm_up=on_warm_up)
        self.done_steps = 0
        # Particle range of each local world (populate adds a variant's jellies one after another).
        self.ranges = []
        for w in range(len(variants)):
            infos = [j for j in self.model.jellies if j.world == w]
            self.ranges.append((infos[0].particle_start, infos[-1].particle_start + infos[-1].particle_count))


def rigid_deviation(rest: np.ndarray, current: np.ndarray, mass: np.ndarray) -> float:
    """RMS distance [m] of the particles from the best-fit rigid motion of their rest shape.

    Kabsch: with both point sets centred on their centres of mass, the rotation maximising
    sum m_i x_i . R r_i comes from the SVD of the mass-weighted covariance (a reflection is
    excluded by the sign of the determinant).
    """
    w = mass / mass.sum()
    r = rest - w @ rest
    x = current - w @ current
    h = (r * w[:, None]).T @ x
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    resid = x - r @ rot.T
    return float(math.sqrt(max(float(w @ np.einsum("ij,ij->i", resid, resid)), 0.0)))


def run_comparison(plan: Plan, device, out, metrics_path=None, plot_path=None, columns=None, gap=None,
                   springs=False, use_graph=None, progress=None, stop_requested=None, stoppable=None,
                   on_warm_up=None) -> ComparisonResult:
    """Run every variant of ``plan`` and write the stage (and metrics / plot when asked).

    ``stoppable()``: a context manager around the steps, the only place a stop-now signal may
    interrupt (``common.Signals(regions=True).stoppable``); writing and closing are never cut short.
    ``on_warm_up``: entered around each group's warm-up (``Simulator``'s).
    """
    import time  # noqa: PLC0415

    import warp as wp  # noqa: PLC0415

    wp.config.quiet = True

    variants = plan.variants
    precision = plan.sim["precision"]
    offsets, plane_size, _ = layout(variants[0].data, len(variants), columns, gap)
    if plane_size is not None:
        for v in variants:
            for p in v.data.get("plane", []):
                p["size"] = min(p["size"], plane_size)

    # The stage's model holds every copy, in variant order; the groups that compute them are the
    # explicit batch (all explicit variants, one world each) and one model per implicit variant.
    display = make_builder([v.data for v in variants]).finalize("cpu", precision)
    explicit = [v for v in variants if method(v.integrator).explicit]
    implicit = [v for v in variants if not method(v.integrator).explicit]
    groups = []
    max_speed = plan.sim.get("max_speed")
    if explicit:
        groups.append(_Group(explicit, make_builder, device, precision, plan.dt, plan.fps, plan.frames, use_graph, max_speed,
                             plan.end_time, on_warm_up))
    for v in implicit:
        groups.append(_Group([v], make_builder, device, precision, plan.dt, plan.fps, plan.frames, use_graph, max_speed,
                             plan.end_time, on_warm_up))

    display_ranges = []
    for v in variants:
        infos = [j for j in display.jellies if j.world == v.world]
        display_ranges.append((infos[0].particle_start, infos[-1].particle_start + infos[-1].particle_count))
    # (group, local world) of each variant, and its explosion bound and rest shape.
    where = {}
    for g in groups:
        for lw, v in enumerate(g.variants):
            where[v.world] = (g, lw)
    results, bounds, rest, masses = [], [], [], []
    for v, off in zip(variants, offsets):
        g, lw = where[v.world]
        start, end = g.ranges[lw]
        bounds.append(max_speed if max_speed is not None else world_speed_bound(g.model, start, end, lw))
        jellies = [(j.particle_start - start, j.particle_count) for j in g.model.jellies if j.world == lw]
        rest.append([(display.particle_q_host[display_ranges[v.world][0] + s: display_ranges[v.world][0] + s + n],
                      display.particle_mass_host[display_ranges[v.world][0] + s: display_ranges[v.world][0] + s + n])
                     for s, n in jellies])
        results.append(VariantResult(v.name, v.integrator, v.overrides, v.world, f"/World/{v.name}", off))

    groups_usd = {v.world: (v.name, off) for v, off in zip(variants, offsets)}
    metadata = {
        "softsim:scene": plan.name,
        "softsim:variants": ", ".join(v.name for v in variants),
        "softsim:dt": plan.dt,
    }
    writer = UsdWriter(out, display, plan.fps, springs=springs, groups=groups_usd, metadata=metadata)
    result = ComparisonResult(results)
    positions = display.particle_q_host.copy()
    velocities = np.zeros_like(positions)  # a variant that exploded keeps its last velocities, as its positions
    try:
        stoppable = stoppable or contextlib.nullcontext
        with stoppable():
            for g in groups:
                g.sim.warm_up()
        t0 = time.perf_counter()
        # A stop request is read between chunks of a long frame, as in softsim run; one grace clock
        # (the first group's) for all groups, so the stop acts within about a second however many.
        groups[0].sim.stop_requested = stop_requested
        stop = groups[0].sim.stop_within_frame if stop_requested is not None else None
        for k in range(plan.frames + 1):
            target = groups[0].sim.step_of_frame(k)
            with stoppable():
                for g in groups:
                    if not g.sim.advance_frame(target - g.done_steps, stop=stop):
                        result.interrupted = True  # stopped within a long frame: it is dropped
                        break
                    g.done_steps = target
            if result.interrupted:
                break
            t_frame = target * plan.dt
            per_group = {}
            for g in groups:
                m = g.sim.probe.measure(g.sim.state, k, t_frame)
                per_group[id(g)] = (m, g.sim.state.particle_q.numpy(), g.sim.state.particle_qd.numpy())
            for v, res in zip(variants, results):
                g, lw = where[v.world]
                m, q, qd = per_group[id(g)]
                start, end = g.ranges[lw]
                ds, de = display_ranges[v.world]
                if res.exploded is None:
                    jm = [m.jellies[i] for i, j in enumerate(g.model.jellies) if j.world == lw]
                    # The world judged as Simulator.run judges a run, from the probe's per-jelly values.
                    reason = explosion_reason(
                        sum(x["nonfinite"] for x in jm), max(x["max_speed"] for x in jm),
                        *(sum(x[e] for x in jm) for e in ("kinetic_energy", "spring_energy", "gravity_energy",
                                                           "total_energy")),
                        bounds[v.world], g.model.precision)
                    if reason is not None:
                        res.exploded = {"frame": k, "time": t_frame, "reason": reason}
                    else:
                        positions[ds:de] = q[start:end]
                        velocities[ds:de] = qd[start:end]
                        res.frames.append(_frame_metrics(k, t_frame, jm, q[start:end], rest[v.world]))
            writer.write_frame(k, t_frame, positions, velocities=velocities,
                               time_code=groups[0].sim.time_code_of_frame(k, t_frame))
            result.frames_written = k + 1
            result.steps = target
            if progress is not None:
                progress.update(1)
            if all(r.exploded for r in results):
                break
            if stop_requested is not None and stop_requested():
                result.interrupted = True
                break
        result.wall_seconds = time.perf_counter() - t0
    except BaseException as exc:
        writer.close(status="interrupted" if isinstance(exc, KeyboardInterrupt) else "failed")
        raise
    for g in groups:
        stats = g.integrator.stats()
        for v in g.variants:
            results[v.world].stats = stats
    status = "interrupted" if result.interrupted else ("exploded" if any(r.exploded for r in results) else "complete")
    written = writer.close(status=status, extra={"softsim:frames": result.frames_written})
    result.written_path = written
    if written != Path(out):  # did not complete and may not replace the outputs: all kept as <stem>.partial
        metrics_path = kept_partial_path(metrics_path) if metrics_path else None
        plot_path = kept_partial_path(plot_path) if plot_path else None
    if metrics_path:
        write_json_atomic(metrics_path, {
            "scene": plan.name,
            "source": plan.source,
            "dt": plan.dt,
            "fps": plan.fps,
            "precision": precision,
            "device": str(device),
            "frames": result.frames_written,
            "steps": result.steps,
            "wall_seconds": result.wall_seconds,
            "variants": [r.as_dict() for r in results],
        })
    if plot_path:
        plot_comparison(results, plot_path, title=f"{plan.name}: dt = {plan.dt:g} s")
    return result


def _frame_metrics(k, t, jelly_metrics, q, rest) -> dict:
    mass = sum(sum(m) for _, m in rest)
    com = sum(np.asarray(j["com"]) * float(m.sum()) for j, (_, m) in zip(jelly_metrics, rest)) / mass
    ke = sum(j["kinetic_energy"] for j in jelly_metrics)
    se = sum(j["spring_energy"] for j in jelly_metrics)
    ge = sum(j["gravity_energy"] for j in jelly_metrics)
    offset, sq = 0, 0.0
    for r, m in rest:
        n = len(r)
        dev = rigid_deviation(r, q[offset: offset + n].astype(np.float64), m)
        sq += dev * dev * float(m.sum())
        offset += n
    return {
        "frame": k,
        "time": t,
        "com": [float(c) for c in com],
        "kinetic_energy": ke,
        "spring_energy": se,
        "gravity_energy": ge,
        "total_energy": ke + se + ge,
        "max_speed": max(j["max_speed"] for j in jelly_metrics),
        "deformation": math.sqrt(sq / mass),
    }


def plot_comparison(results, path, title=""):
    """COM height, total energy and deformation over time, one line per copy (matplotlib Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
    from matplotlib.figure import Figure  # noqa: PLC0415

    fig = Figure(figsize=(8.0, 8.0), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True)
    rows = (
        ("centre of mass height [m]", lambda f: f["com"][1]),
        ("total energy [J]", lambda f: f["total_energy"]),
        ("deformation: RMS from rigid fit [m]", lambda f: f["deformation"]),
    )
    for ax, (label, get) in zip(axes, rows):
        for r in results:
            t = [f["time"] for f in r.frames]
            ax.plot(t, [get(f) for f in r.frames], label=r.name + (" (exploded)" if r.exploded else ""), linewidth=1.2)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].legend(loc="best", fontsize="small")
    if title:
        axes[0].set_title(title)
    fig.tight_layout()
    save_atomic(path, lambda tmp: fig.savefig(tmp, format="png"), "--plot")
