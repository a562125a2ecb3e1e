"""Timing of benchmark cases: a step function run as one timed unit of ``steps`` steps.

``softsim bench``'s cases and the scripts in ``benchmarks/`` time their steps with this one class.
Each timed run records the wall time, the process's CPU time and the calling thread's CPU time:
Warp runs CPU kernels on the calling thread, so on the CPU the thread's time is the cost of the
steps, unaffected by other processes taking turns on the cores.
"""

from __future__ import annotations

import time

import numpy as np


class TimedSteps:
    """A stepper whose ``steps`` steps run as one timed unit (a graph replay or a Python loop)."""

    def __init__(self, device, step_fn, steps, use_graph):
        import warp as wp  # noqa: PLC0415

        self.wp = wp
        self.device = device
        self.step_fn = step_fn
        self.steps = steps + (steps % 2)  # even: double-buffered states end where they began
        self.use_graph = use_graph
        self.graph = None
        self.wall = []
        self.cpu = []
        self.thread = []

    def prepare(self) -> float:
        """First step (module load or compile), graph capture, warm-up; returns the first step's seconds."""
        wp = self.wp
        t0 = time.perf_counter()
        self.step_fn(2)
        wp.synchronize_device(self.device)
        compile_s = time.perf_counter() - t0
        if self.use_graph:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                self.step_fn(self.steps)
            self.graph = capture.graph
        self.run()
        wp.synchronize_device(self.device)
        return compile_s

    def run(self):
        if self.graph is not None:
            self.wp.capture_launch(self.graph)
        else:
            self.step_fn(self.steps)

    def time_once(self):
        wp = self.wp
        wp.synchronize_device(self.device)
        c0, h0, t0 = time.process_time(), time.thread_time(), time.perf_counter()
        self.run()
        wp.synchronize_device(self.device)
        self.wall.append(time.perf_counter() - t0)
        self.cpu.append(time.process_time() - c0)
        self.thread.append(time.thread_time() - h0)

    def ms_per_step(self) -> float:
        return 1e3 * float(np.median(self.wall)) / self.steps

    def cpu_ms_per_step(self) -> float:
        return 1e3 * float(np.median(self.cpu)) / self.steps
