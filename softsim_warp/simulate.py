"""The simulation loop: steps between output frames, per-frame metrics, explosion checks, writers.

Frame k is the state after step ``round(k / (fps * dt))``: the output frame rate and the step size
are independent, and the time recorded with a frame is the exact simulated time of its step.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .integrators import Integrator
from .model import Model, State


@dataclass
class FrameMetrics:
    """Whole-scene quantities of one output frame (SI units)."""

    frame: int
    time: float
    com: list
    kinetic_energy: float
    spring_energy: float
    gravity_energy: float
    total_energy: float
    max_speed: float
    nonfinite: int
    jellies: list = field(default_factory=list)

    def as_dict(self) -> dict:
        d = {
            "frame": self.frame,
            "time": self.time,
            "com": self.com,
            "kinetic_energy": self.kinetic_energy,
            "spring_energy": self.spring_energy,
            "gravity_energy": self.gravity_energy,
            "total_energy": self.total_energy,
            "max_speed": self.max_speed,
        }
        if len(self.jellies) > 1:
            d["jellies"] = [{k: v for k, v in j.items() if k != "nonfinite"} for j in self.jellies]
        return d


class MetricsProbe:
    """Reduces a state to :class:`FrameMetrics` on the device; one small device-to-host copy per call."""

    def __init__(self, model: Model):
        self.model = model
        j = max(len(model.jellies), 1)
        dev = model.device
        self.kinetic = wp.zeros(j, dtype=model.scalar, device=dev)
        self.gravity_energy = wp.zeros(j, dtype=model.scalar, device=dev)
        self.spring_energy = wp.zeros(j, dtype=model.scalar, device=dev)
        self.moment = wp.zeros(j, dtype=model.vec3, device=dev)
        self.max_speed = wp.zeros(j, dtype=model.scalar, device=dev)
        self.nonfinite = wp.zeros(j, dtype=wp.int32, device=dev)
        masses = np.zeros(j)
        for k, info in enumerate(model.jellies):
            masses[k] = model.particle_mass_host[info.particle_start : info.particle_start + info.particle_count].sum()
        self.jelly_mass = masses

    def _reduce(self, state: State):
        """Fill the per-jelly arrays for ``state`` (atomics; see deterministic_metrics.py for fixed order)."""
        m = self.model
        for a in (self.kinetic, self.gravity_energy, self.spring_energy, self.moment, self.max_speed, self.nonfinite):
            a.zero_()
        wp.launch(
            m.kernels.reduce_particles,
            dim=m.particle_count,
            inputs=[m.particle_mass, m.particle_jelly, m.gravity, state.particle_q, state.particle_qd],
            outputs=[self.kinetic, self.gravity_energy, self.moment, self.max_speed, self.nonfinite],
            device=m.device,
        )
        if m.spring_count and m.lattice is not None:
            # Lattice path: the same energy from the stencil, without making the spring arrays.
            lat = m.lattice
            wp.launch(
                m.kernels.reduce_lattice_springs,
                dim=m.particle_count,
                inputs=[m.particle_jelly, lat.jelly_start, lat.jelly_shape, lat.jelly_types, lat.jelly_rest, lat.jelly_ks,
                        state.particle_q],
                outputs=[self.spring_energy],
                device=m.device,
            )
        elif m.spring_count:
            wp.launch(
                m.kernels.reduce_springs,
                dim=m.spring_count,
                inputs=[m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.particle_jelly, state.particle_q],
                outputs=[self.spring_energy],
                device=m.device,
            )

    def measure(self, state: State, frame: int, t: float) -> FrameMetrics:
        self._reduce(state)
        ke = self.kinetic.numpy().astype(np.float64)
        ge = self.gravity_energy.numpy().astype(np.float64)
        se = self.spring_energy.numpy().astype(np.float64)
        mom = self.moment.numpy().astype(np.float64)
        vmax = self.max_speed.numpy().astype(np.float64)
        bad = self.nonfinite.numpy()
        total_mass = self.jelly_mass.sum()
        com = (mom.sum(axis=0) / total_mass).tolist() if total_mass > 0 else [0.0, 0.0, 0.0]
        jellies = []
        for k in range(len(ke)):
            mk = self.jelly_mass[k]
            jellies.append(
                {
                    "com": (mom[k] / mk).tolist() if mk > 0 else [0.0, 0.0, 0.0],
                    "kinetic_energy": float(ke[k]),
                    "spring_energy": float(se[k]),
                    "gravity_energy": float(ge[k]),
                    "total_energy": float(ke[k] + se[k] + ge[k]),
                    "max_speed": float(vmax[k]),
                    "nonfinite": int(bad[k]),
                }
            )
        return FrameMetrics(
            frame=frame,
            time=t,
            com=com,
            kinetic_energy=float(ke.sum()),
            spring_energy=float(se.sum()),
            gravity_energy=float(ge.sum()),
            total_energy=float(ke.sum() + se.sum() + ge.sum()),
            max_speed=float(vmax.max()) if len(vmax) else 0.0,
            nonfinite=int(bad.sum()),
            jellies=jellies,
        )


def speed_bound(model: Model) -> float:
    """Speed above which a run is called exploded [m/s].

    Ten times the largest speed the scene can reach by falling: its initial particle speed plus
    sqrt(2 |g| D), D the diagonal of the box holding the initial particles and the terrain
    anchors, plus 1 m/s so that a scene at rest has a sensible bound.
    """
    pts = [model.particle_q_host]
    pts += [np.atleast_2d(p["point"]) for p in model.planes]
    pts += [np.atleast_2d(np.asarray(p)) for p in getattr(model, "terrain_anchor_points", [])]
    allp = np.concatenate(pts)
    diag = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    v0 = float(np.linalg.norm(model.particle_qd.numpy(), axis=1).max()) if model.particle_count else 0.0
    g = float(np.linalg.norm(model.gravity_host))
    return 10.0 * (v0 + math.sqrt(2.0 * g * diag) + 1.0)


@dataclass
class RunResult:
    frames_written: int
    steps: int
    sim_time: float
    wall_seconds: float
    compile_seconds: float
    exploded: bool = False
    interrupted: bool = False
    explosion: dict | None = None
    metrics: list = field(default_factory=list)


class Simulator:
    """Advances a model frame by frame and hands each frame to writers.

    Args:
        model: the model.
        integrator: an :class:`~softsim_warp.integrators.Integrator` for it.
        dt: step size [s].
        fps: output frames per second.
        frames: number of frames after frame 0.
        use_graph: capture each frame's steps as a graph and replay it (CUDA and CPU; default on:
            on the CPU, Warp 1.19 replays a captured graph in C++, which removes the Python
            launch overhead, 2.6x faster on a 10^3 jelly, see docs/PERFORMANCE.md).
        max_speed: speed treated as an explosion [m/s]; ``None`` derives it from the scene.
    """

    def __init__(self, model: Model, integrator: Integrator, dt: float, fps: float, frames: int, use_graph=None, max_speed=None):
        self.model = model
        self.integrator = integrator
        self.dt = float(dt)
        self.fps = float(fps)
        self.frames = int(frames)
        self.use_graph = True if use_graph is None else bool(use_graph)
        self.max_speed = speed_bound(model) if max_speed is None else float(max_speed)
        self.states = [model.state(), model.state()]
        self.current = 0
        if getattr(model, "deterministic", False):
            from .deterministic_metrics import DeterministicMetricsProbe  # noqa: PLC0415 - imports this module

            self.probe = DeterministicMetricsProbe(model)
        else:
            self.probe = MetricsProbe(model)
        self._graphs = {}
        self.stop_requested = None  # a callable returning a reason (e.g. a signal) to stop after this frame
        self.writing = False  # True while writers take a frame

    @property
    def state(self) -> State:
        return self.states[self.current]

    def step_of_frame(self, k: int) -> int:
        return round(k / (self.fps * self.dt))

    def _advance_plain(self, n: int):
        for _ in range(n):
            self.integrator.step(self.states[self.current], self.states[1 - self.current], self.dt)
            self.current = 1 - self.current

    def advance(self, n: int):
        """Take ``n`` steps, replaying a captured graph when enabled."""
        if n == 0:
            return
        if not self.use_graph:
            self._advance_plain(n)
            return
        key = (n, self.current)
        graph = self._graphs.get(key)
        if graph is None:
            start = self.current
            with wp.ScopedCapture(device=self.model.device, force_module_load=False) as capture:
                self._advance_plain(n)
            graph = self._graphs[key] = capture.graph
            self.current = start  # capture recorded the launches; the replay below runs them
        wp.capture_launch(graph)
        self.current = (self.current + n) % 2

    def warm_up(self) -> float:
        """Compile and load every kernel a run needs; returns the seconds it took."""
        t0 = time.perf_counter()
        spare = self.model.state()
        self.integrator.step(self.states[self.current], spare, self.dt)
        self.probe.measure(spare, 0, 0.0)
        wp.synchronize_device(self.model.device)
        reset_stats = getattr(self.integrator, "reset_stats", None)  # the warm-up step is not part of the run
        if reset_stats is not None:
            reset_stats()
        return time.perf_counter() - t0

    def run(self, writers=(), progress=None, label="") -> RunResult:
        """Run all frames. Each writer gets ``write_frame(k, time, positions, metrics)``.

        Stops early, keeping everything written so far, on an explosion or when ``stop_requested``
        returns a reason.
        """
        result = RunResult(0, 0, 0.0, 0.0, 0.0)
        try:
            result.compile_seconds = self.warm_up()
        except KeyboardInterrupt:  # stopped before the first frame
            result.interrupted = True
            result.step_seconds = 0.0
            return result
        t0 = time.perf_counter()
        sim_seconds = 0.0
        prev_step = 0
        for k in range(self.frames + 1):
            n = self.step_of_frame(k) - prev_step
            ts = time.perf_counter()
            try:
                self.advance(n)
                t_frame = self.step_of_frame(k) * self.dt
                metrics = self.probe.measure(self.state, k, t_frame)  # synchronises: the frame is done
            except KeyboardInterrupt:
                # Stop now (e.g. a second Ctrl-C): the frame in progress is dropped, the ones written stay.
                result.interrupted = True
                break
            sim_seconds += time.perf_counter() - ts
            prev_step += n
            if metrics.nonfinite or metrics.max_speed > self.max_speed:
                result.exploded = True
                bad = [i for i, j in enumerate(metrics.jellies) if j["nonfinite"] or j["max_speed"] > self.max_speed]
                result.explosion = {
                    "frame": k,
                    "time": t_frame,
                    "jelly": bad[0] if bad else 0,
                    "reason": (
                        f"{metrics.nonfinite} particles with non-finite state"
                        if metrics.nonfinite
                        else f"max speed {metrics.max_speed:.4g} m/s exceeds the bound {self.max_speed:.4g} m/s"
                    ),
                }
                break
            positions = self.state.particle_q.numpy()
            # A frame is written whole: a stop-now request waits until it is (see cli._Signals).
            self.writing = True
            try:
                for w in writers:
                    w.write_frame(k, t_frame, positions, metrics)
            finally:
                self.writing = False
            result.metrics.append(metrics)
            result.frames_written = k + 1
            result.steps = prev_step
            result.sim_time = t_frame
            if progress is not None:
                progress.update(1)
            if self.stop_requested is not None and self.stop_requested():
                result.interrupted = True
                break
        result.wall_seconds = time.perf_counter() - t0
        result.step_seconds = sim_seconds
        return result
