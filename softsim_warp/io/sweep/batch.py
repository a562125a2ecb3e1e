"""Running one batch of a sweep on a device, in a Dask worker: variants as worlds of one model.

One model holds the batch's variants as worlds (:mod:`~softsim_warp.io.worlds`, what ``softsim
compare`` does) and one launch of each kernel steps them all. Each world is judged frame by frame as
``softsim run`` judges its run: the same explosion test (:func:`~softsim_warp.io.metrics.explosion_reason`)
and the same metrics, so on the CPU a row equals a single run bit for bit. Everything a row records
is reduced per world on the device (:mod:`~softsim_warp.io.metrics`): the per-jelly energies, centre
of mass, largest speed and non-finite count, the penetration into terrain and the error against the
reference run; the host reads a few numbers per world a frame, never the particles. A sweep without
terrain launches nothing for penetration, and one without ``--reference`` nothing for the error.
"""

from __future__ import annotations

import math
import os
import time
import types

import numpy as np

from ...core import methods
from .. import scene as scene_mod
from ..checks import TERRAIN_SDF
from ..warp_init import init_warp
from .plan import SweepVariant

# Seconds between a task's asks whether the sweep was stopped (each ask is a round trip to the scheduler).
STOP_POLL_SECONDS = 0.2


class _Worlds:
    """What the worlds of a batch accumulate frame by frame (what ``Simulator.run`` records for a run),
    one column per world: frame k of every world that recorded it is row k of ``total``, ``gravity``,
    ``max_speed`` and ``com``, so judging a frame is a few NumPy operations over all worlds."""

    def __init__(self, bounds, precision, frames):
        worlds = len(bounds)
        self.bound = np.asarray(bounds, dtype=np.float64)
        self.precision = precision
        self.total = np.zeros((frames + 1, worlds))
        self.gravity = np.zeros((frames + 1, worlds))
        self.max_speed = np.zeros((frames + 1, worlds))
        self.com = np.zeros((frames + 1, worlds, 3))
        self.alive = np.ones(worlds, dtype=bool)
        self.frames = np.zeros(worlds, dtype=np.int64)  # frames recorded: rows 0 .. frames - 1
        self.steps = np.zeros(worlds, dtype=np.int64)
        self.sim_time = np.zeros(worlds)
        self.exploded = [None] * worlds

    def record(self, cols: dict, k: int, step: int, t: float, among=None) -> np.ndarray:
        """Judge frame ``k`` (:func:`~softsim_warp.io.worlds.world_columns`) of the worlds still alive (and
        in the mask ``among``) as ``Simulator.run`` does; returns the mask of the worlds that recorded it."""
        from ..metrics import exploded_mask, explosion_reason  # noqa: PLC0415

        live = self.alive if among is None else self.alive & among
        energies = (cols["kinetic_energy"], cols["spring_energy"], cols["gravity_energy"], cols["total_energy"])
        bad = live & exploded_mask(cols["nonfinite"], cols["max_speed"], *energies, self.bound, self.precision)
        for w in np.flatnonzero(bad).tolist():  # the words of the few that exploded, as a single run words them
            reason = explosion_reason(int(cols["nonfinite"][w]), float(cols["max_speed"][w]),
                                      *(float(e[w]) for e in energies), float(self.bound[w]), self.precision)
            self.exploded[w] = {"frame": k, "time": t, "reason": reason}
        ok = live & ~bad
        self.total[k, ok] = cols["total_energy"][ok]
        self.gravity[k, ok] = cols["gravity_energy"][ok]
        self.max_speed[k, ok] = cols["max_speed"][ok]
        self.com[k, ok] = cols["com"][ok]
        self.frames[ok] = k + 1
        self.steps[live] = step
        self.sim_time[ok] = t
        self.alive = self.alive & ~bad
        return ok

    def metrics(self, w: int) -> list:
        """World ``w``'s recorded frames as ``energy_drift`` reads a run's metrics."""
        n = int(self.frames[w])
        return [types.SimpleNamespace(total_energy=e, gravity_energy=g)
                for e, g in zip(self.total[:n, w].tolist(), self.gravity[:n, w].tolist())]


class _Batch:
    """A batch's model, integrator and stepper, with each world's ranges and explosion bound, and the
    device probes of what its rows record."""

    def __init__(self, datas, device, use_graph, penetration=True):
        from ...core.integrators import ExplicitIntegrator  # noqa: PLC0415
        from ...core.stepper import make_integrator  # noqa: PLC0415
        from ..metrics import PenetrationProbe  # noqa: PLC0415
        from ..simulate import Simulator  # noqa: PLC0415
        from ..worlds import make_builder, world_jellies, world_ranges, world_speed_bound  # noqa: PLC0415

        sim = datas[0]["simulation"]
        self.datas = datas
        self.model = make_builder(datas).finalize(device, sim["precision"])
        method = sim["integrator"]
        if not methods.method(method).explicit:
            self.integrator = make_integrator(method, self.model, datas[0].get(methods.IMPLICIT.name))
        else:
            self.integrator = ExplicitIntegrator(self.model, [method] * len(datas))
        first = scene_mod.Scene(datas[0])
        frames = first.frame_count()
        self.sim = Simulator(self.model, self.integrator, sim["dt"], sim["fps"], frames, use_graph=use_graph,
                             max_speed=math.inf, end_time=first.end_time())
        self.frames = frames
        self.ranges = world_ranges(self.model)
        self.jellies = world_jellies(self.model)
        bounds = []
        for w, data in enumerate(datas):
            bound = data["simulation"].get("max_speed")
            a, b = self.ranges[w]
            bounds.append(float(bound) if bound is not None else world_speed_bound(self.model, a, b, w))
        self.worlds = _Worlds(bounds, sim["precision"], frames)
        # Penetration is measured into terrain only: without any, nothing is launched for it.
        has_terrain = any(d.get(kind) for d in datas for kind in TERRAIN_SDF)
        self.penetration = PenetrationProbe(self.model, self.integrator.run) if penetration and has_terrain else None
        self.done_steps = 0
        self.step_seconds = 0.0
        self.stop = None  # asked between chunks of a long frame (stop_check): the sweep was stopped

    def launch_frame(self, k: int):
        """Launch the steps up to frame ``k``: asynchronous on CUDA, so the host can work meanwhile."""
        target = self.sim.step_of_frame(k)
        if not self.sim.advance_frame(target - self.done_steps, stop=self.stop):
            raise TaskStopped("the sweep was stopped, or the worker lost its scheduler")
        self.done_steps = target

    def measure(self):
        """Launch the reductions of the frame the launched steps reach (asynchronous)."""
        self.sim.probe.reduce(self.sim.state)
        if self.penetration is not None:
            self.penetration.launch(self.sim.state)

    def read_frame(self):
        """The measured frame on the host (synchronises): ``(step, time, per-jelly arrays, per-world
        penetration or None)``; a few numbers per jelly and per world, no particle."""
        from ..worlds import probe_arrays  # noqa: PLC0415

        t = self.done_steps * self.sim.dt
        depth = self.penetration.read() if self.penetration is not None else None
        return self.done_steps, t, probe_arrays(self.sim.probe), depth


class _Captured:
    """The per-frame reductions of a batch (``launch``) replayed as a captured graph, one for each
    state buffer the frame can end in (a graph reads fixed buffers), captured on first use: one
    launch a frame instead of one per kernel. Without graphs, or on a first use, launched directly."""

    def __init__(self, device, launch, use_graph):
        self.device = device
        self.launch = launch
        self.use_graph = use_graph
        self.graphs = {}

    def __call__(self, key):
        import warp as wp  # noqa: PLC0415

        graph = self.graphs.get(key)
        if graph is not None:
            wp.capture_launch(graph)
            return
        # Launched directly first (it loads the kernels, and its results are this frame's); the
        # capture records the same launches for the next frames. Every reduction starts from zero,
        # so running them twice gives the same values.
        self.launch()
        if self.use_graph:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self.launch()
            self.graphs[key] = capture.graph


class TaskStopped(Exception):
    """The client stopped the sweep while this task ran, or the worker could not ask (``stop_check``).
    Raised out of the task, not returned as no rows: a task that stopped gives no row, and when the
    client still listens it counts the task's variants as lost, for ``--resume``."""


def stop_check(name: str | None):
    """In a task: a callable that is true once the client has set the sweep's stop event ``name``
    (``run_tasks``), or the worker has lost its scheduler. It asks the scheduler at most every
    STOP_POLL_SECONDS, the first time that long after the task started, so a task of short frames
    never asks. None without a name."""
    if not name:
        return None
    seen = {"at": time.perf_counter(), "set": False, "event": None}

    def stop():
        now = time.perf_counter()
        if not seen["set"] and now - seen["at"] >= STOP_POLL_SECONDS:
            seen["at"] = now
            try:
                if seen["event"] is None:
                    from distributed import Event, get_worker  # noqa: PLC0415

                    get_worker()  # ValueError outside a worker
                    seen["event"] = Event(name)
                seen["set"] = seen["event"].is_set()
            except ValueError:  # not in a worker (a task run directly): nothing can stop it
                seen["at"] = math.inf
            except Exception:  # noqa: BLE001 - the worker lost its scheduler (closing): no one takes the rows
                seen["set"] = True
        return seen["set"]

    return stop


def _simulate(variants: list[dict], device, use_graph=True, timings=None, stop=None) -> list[dict]:
    """Run one batch (all of one group) as worlds of one model; one result dict per variant.
    ``stop``: asked between chunks of a long frame; when true the task ends (``TaskStopped``).

    ``timings``: a dict that gets the seconds of the batch's build (its models, the reference's
    too), of loading its kernels and of its frames (benchmarks/bench_sweep.py).
    """
    from ..metrics import PositionErrorProbe  # noqa: PLC0415
    from ..runinfo import energy_drift  # noqa: PLC0415
    from ..worlds import world_columns  # noqa: PLC0415

    t_build = time.perf_counter()
    batch = _Batch([v["data"] for v in variants], device, use_graph)
    batch.stop = stop
    ref = errors = None
    if variants[0].get("reference") is not None:
        ref = _Batch([v["reference"] for v in variants], device, use_graph, penetration=False)
        ref.stop = stop
        errors = PositionErrorProbe(batch.model, batch.ranges)
    t_compile = time.perf_counter()
    build_seconds = t_compile - t_build
    batch.sim.warm_up()
    if ref is not None:
        ref.sim.warm_up()
    compile_seconds = time.perf_counter() - t_compile
    # Frame k+1's steps are launched before frame k is judged on the host: on CUDA the host work
    # (judging all worlds) overlaps the device's; on the CPU launches run at once.
    t_start = time.perf_counter()
    for b in (batch, ref):
        if b is not None:
            b.launch_frame(0)
    def launch_reductions():
        for b in (batch, ref):
            if b is not None:
                b.measure()
        if errors is not None:
            errors.launch(batch.sim.state.particle_q, ref.sim.state.particle_q)

    measure = _Captured(batch.model.device, launch_reductions, use_graph)
    worlds = batch.worlds
    penetration = np.zeros(len(variants))
    ref_error = np.zeros(len(variants))
    com_gap = np.zeros((len(variants), 3))  # batch minus reference centre of mass, the last frame both recorded
    has_gap = np.zeros(len(variants), dtype=bool)
    # Where a frame's time goes (benchmarks/bench_sweep.py): launching the steps (on the CPU: taking
    # them), the reductions and reading them (on CUDA: mostly waiting for the steps), judging.
    phase = {"launch_seconds": 0.0, "read_seconds": 0.0, "judge_seconds": 0.0}
    for k in range(batch.frames + 1):
        t0 = time.perf_counter()
        # The batch and its reference take the same steps: their current buffers agree.
        measure(batch.sim.current)
        step, t, arrays, depth = batch.read_frame()
        if ref is not None:
            _, _, ref_arrays, _ = ref.read_frame()
            errors_now = errors.read()
        t1 = time.perf_counter()
        if k < batch.frames:
            for b in (batch, ref):
                if b is not None:
                    b.launch_frame(k + 1)
        t2 = time.perf_counter()
        phase["read_seconds"] += t1 - t0
        phase["launch_seconds"] += t2 - t1
        # Every world at once; each column holds the numbers a single run of its variant computes, and
        # a running largest keeps the earlier value unless the new one is larger, as max() does.
        cols = world_columns(arrays, batch.jellies)
        ok = worlds.record(cols, k, step, t)
        if depth is not None:
            deeper = ok & (depth > penetration)
            penetration[deeper] = depth[deeper]
        if ref is not None:
            ref_cols = world_columns(ref_arrays, ref.jellies)
            both = ref.worlds.record(ref_cols, k, step, t, among=ok)
            larger = both & (errors_now > ref_error)
            ref_error[larger] = errors_now[larger]
            com_gap[both] = cols["com"][both] - ref_cols["com"][both]
            has_gap |= both
        phase["judge_seconds"] += time.perf_counter() - t2
        if not worlds.alive.any():
            break
    batch.step_seconds = time.perf_counter() - t_start
    if timings is not None:
        timings.update(build_seconds=build_seconds, compile_seconds=compile_seconds, step_seconds=batch.step_seconds,
                       model=batch.model, integrator=batch.integrator, **phase)
    particles = [b - a for a, b in batch.ranges]
    work = sum(n * steps for n, steps in zip(particles, worlds.steps.tolist()))
    out = []
    for w, v in enumerate(variants):
        drift, rel = energy_drift(worlds.metrics(w))
        n = int(worlds.frames[w])
        last = n - 1
        exploded = worlds.exploded[w]
        row = {
            "variant_id": v["id"],
            "status": "exploded" if exploded else "completed",
            "explosion_time": exploded["time"] if exploded else None,
            "explosion_frame": exploded["frame"] if exploded else None,
            "explosion_reason": exploded["reason"] if exploded else None,
            "error": None,
            "steps": int(worlds.steps[w]),
            "frames": n,
            "sim_time": float(worlds.sim_time[w]),
            "particles": particles[w],
            "batch_size": len(variants),
            "wall_seconds": batch.step_seconds,
            "compile_seconds": compile_seconds,
            "particle_steps_per_second": work / batch.step_seconds if batch.step_seconds > 0 else 0.0,
            "energy_start": float(worlds.total[0, w]) if n else None,
            "energy_end": float(worlds.total[last, w]) if n else None,
            "energy_change": drift,
            "energy_change_relative": rel,
            "com_x": float(worlds.com[last, w, 0]) if n else None,
            "com_y": float(worlds.com[last, w, 1]) if n else None,
            "com_z": float(worlds.com[last, w, 2]) if n else None,
            "max_speed": max(worlds.max_speed[:n, w].tolist()) if n else None,
            "max_penetration": float(penetration[w]),
        }
        if ref is not None:
            row["ref_status"] = "exploded" if ref.worlds.exploded[w] else "completed"
            row["ref_position_error"] = float(ref_error[w]) if n else None
            row["ref_com_error"] = float(np.linalg.norm(com_gap[w])) if has_gap[w] else None
        out.append(row)
    return out


def _failed(v: dict, error: BaseException, batch_size: int) -> dict:
    return {"variant_id": v["id"], "status": "failed", "error": f"{type(error).__name__}: {error}".strip(),
            "batch_size": batch_size}


def run_batch(spec: dict) -> list[dict]:
    """A Dask task: simulate the batch ``spec["variants"]`` on ``spec["device"]``; one result per variant.

    A batch that fails as a whole is rerun variant by variant, so one bad variant fails alone.
    """
    wp = init_warp()
    device = wp.get_device(spec["device"])
    variants = spec["variants"]
    use_graph = spec.get("use_graph", True)
    stop = stop_check(spec.get("stop_event"))
    try:
        rows = _simulate(variants, device, use_graph, stop=stop)
    except TaskStopped:
        raise
    except Exception as e:  # noqa: BLE001 - a variant's failure is its row's result
        if len(variants) == 1:
            rows = [_failed(variants[0], e, 1)]
        else:
            rows = []
            for v in variants:
                try:
                    rows += _simulate([v], device, use_graph, stop=stop)
                except TaskStopped:
                    raise
                except Exception as e1:  # noqa: BLE001
                    rows.append(_failed(v, e1, len(variants)))
    host = os.uname().nodename
    for r in rows:
        r["device"] = str(device)
        r["worker"] = f"{host}:{os.getpid()}"
    return rows


def task_spec(batch: list[SweepVariant], device: str, number: int, use_graph=True) -> dict:
    """What a task needs: plain data only (it travels to the worker)."""
    return {
        "task": f"task{number:06d}",
        "device": device,
        "use_graph": use_graph,
        "variants": [{"id": v.id, "data": v.data, "reference": v.reference} for v in batch],
    }

