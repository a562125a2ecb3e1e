"""The simulation loop: steps between output frames, per-frame metrics, explosion checks, writers.

Frame k is the state after step ``round(k / (fps * dt))``: the output frame rate and the step size
are independent, and the time recorded with a frame is the exact simulated time of its step. A run
whose duration is not a whole number of frames (``end_time``) ends with a shorter frame, at the step
``round(end_time / dt)``, written at its own time (USD time code ``t * fps``).

A stop request (a signal) is honoured after the frame in progress; a frame of more than one chunk still running
:data:`STOP_GRACE_SECONDS` after the request is dropped instead, so a stop acts within about a
second however many steps a frame has (the steps are taken in chunks, the request read between).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import warp as wp

from ..core import stepper as stepper_mod
from ..core.integrators import Integrator
from ..core.model import Model, State
from ..core.stepper import Stepper
from .metrics import FrameMetrics, explosion_reason, make_probe, speed_bound  # noqa: F401 - FrameMetrics re-exported

# Seconds a frame may go on after a stop request before it is dropped (see the module docstring).
STOP_GRACE_SECONDS = 0.5


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


class Simulator(Stepper):
    """Advances a model frame by frame and hands each frame to writers.

    Args:
        model: the model.
        integrator: an :class:`~softsim_warp.core.integrators.Integrator` for it.
        dt: step size [s].
        fps: output frames per second.
        frames: number of frames after frame 0.
        use_graph: capture each frame's steps as a graph (or graphs of at most
            ``core.stepper.MAX_GRAPH_STEPS`` steps each) and replay it (CUDA and CPU; default on:
            on the CPU, Warp replays a captured graph in C++, which removes the Python launch
            overhead; its gain is in docs/PERFORMANCE.md).
        max_speed: speed treated as an explosion [m/s]; ``None`` derives it from the scene.
        profile: time the parts of every step, launched one by one
            (:class:`~softsim_warp.core.stepper.Stepper`); the run's summary then holds them.
        on_warm_up: entered around the warm-up (:class:`~softsim_warp.core.stepper.Stepper`).
    """

    def __init__(self, model: Model, integrator: Integrator, dt: float, fps: float, frames: int, use_graph=None,
                 max_speed=None, profile=False, end_time=None, on_warm_up=None):
        super().__init__(model, integrator, dt, use_graph, profile, on_warm_up)
        self.fps = float(fps)
        self.frames = int(frames)
        # The last frame's time when the duration is not a whole number of frames (Scene.end_time).
        self.end_time = None if end_time is None else float(end_time)
        self._stop_seen = None
        self.max_speed = speed_bound(model) if max_speed is None else float(max_speed)
        self.probe = make_probe(model)
        self.stop_requested = None  # a callable returning a reason (e.g. a signal) to stop after this frame
        self.writing = False  # True while writers take a frame

    def step_of_frame(self, k: int) -> int:
        step = round(k / (self.fps * self.dt))
        if self.end_time is not None:
            step = min(step, round(self.end_time / self.dt))
        return step

    def time_code_of_frame(self, k: int, t: float):
        """USD time code of frame ``k`` at time ``t``: ``k``, or ``t * fps`` for a shorter last frame."""
        if self.end_time is not None and k == self.frames and self.step_of_frame(k) != round(k / (self.fps * self.dt)):
            return t * self.fps
        return k

    def stop_within_frame(self) -> bool:
        """True when a stop was requested more than STOP_GRACE_SECONDS ago (read between chunks of steps)."""
        if self.stop_requested is None or not self.stop_requested():
            return False
        now = time.perf_counter()
        if self._stop_seen is None:
            self._stop_seen = now
        return now - self._stop_seen > STOP_GRACE_SECONDS

    def advance_frame(self, n: int, stop=None) -> bool:
        """Take a frame's ``n`` steps; False when a stop cut them short (the frame is then dropped).

        A frame of more than one chunk (``core.stepper.MAX_GRAPH_STEPS`` steps) asks ``stop`` (by
        default: a request from ``stop_requested`` older than STOP_GRACE_SECONDS) between chunks;
        the chunks are the same either way, so is the result. ``softsim run``, ``compare`` and the
        tasks of ``sweep`` all step their frames here."""
        if stop is None and self.stop_requested is not None:
            stop = self.stop_within_frame
        if stop is not None and n > stepper_mod.MAX_GRAPH_STEPS:
            return self.advance(n, stop=stop) == n
        self.advance(n)
        return True

    def warm_up(self) -> float:
        """Compile and load every kernel a run needs, the metrics' too; returns the seconds it took
        (the first warm-up's, when called again)."""
        if self.warmed_up:
            return getattr(self, "warm_up_seconds", 0.0)
        self.warm_up_seconds = super().warm_up()
        return self.warm_up_seconds

    def _warm_up_step(self):
        super()._warm_up_step()
        self.probe.measure(self.state, 0, 0.0)

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
                if not self.advance_frame(n):
                    result.interrupted = True  # stopped within a long frame: it is dropped
                    break
                t_frame = self.step_of_frame(k) * self.dt
                metrics = self.probe.measure(self.state, k, t_frame)  # synchronises: the frame is done
            except KeyboardInterrupt:
                # Stop now (e.g. a second Ctrl-C): the frame in progress is dropped, the ones written stay.
                result.interrupted = True
                break
            sim_seconds += time.perf_counter() - ts
            prev_step += n
            # Energies that overflow (a speed of 1e38 m/s squared in float32) are an explosion too,
            # even while every coordinate is still finite: no result after them means anything.
            reason = explosion_reason(metrics.nonfinite, metrics.max_speed, metrics.kinetic_energy,
                                      metrics.spring_energy, metrics.gravity_energy, metrics.total_energy,
                                      self.max_speed, self.model.precision)
            if reason is not None:
                result.steps = prev_step  # the steps done, up to the frame that exploded
                result.exploded = True
                bad = [i for i, j in enumerate(metrics.jellies) if j["nonfinite"] or j["max_speed"] > self.max_speed
                       or not math.isfinite(j["total_energy"])]
                result.explosion = {"frame": k, "time": t_frame, "jelly": bad[0] if bad else 0, "reason": reason}
                if not metrics.nonfinite and not metrics.max_speed > self.max_speed:
                    result.explosion["overflow"] = True  # the values, not the step, are out of range
                break
            positions = self.state.particle_q.numpy()
            # Velocities only for writers that record them (UsdWriter: motion blur).
            velocities = self.state.particle_qd.numpy() if any(getattr(w, "wants_velocities", False) for w in writers) else None
            # A frame is written whole: a stop-now request waits until it is (see commands/common.Signals).
            self.writing = True
            code = self.time_code_of_frame(k, t_frame)
            try:
                for w in writers:
                    extra = {"time_code": code} if code != k and getattr(w, "takes_time_code", False) else {}
                    if getattr(w, "wants_velocities", False):
                        w.write_frame(k, t_frame, positions, metrics, velocities=velocities, **extra)
                    else:
                        w.write_frame(k, t_frame, positions, metrics, **extra)
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
