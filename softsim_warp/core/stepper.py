"""Integrator factory and whole-frame stepping, the API's loop: scene -> Model -> States -> steps.

:class:`Stepper` holds two states and advances them ``n`` steps at a time. On the first call for a
given ``n`` it captures the steps' launches as a graph (``wp.ScopedCapture``) and afterwards
replays it with one ``wp.capture_launch``: a Python loop over frames then costs one launch per
frame, on CUDA and on the CPU (Warp replays a CPU graph in C++), as fast as ``softsim run``.
"""

from __future__ import annotations

import time

import warp as wp

from .implicit import ImplicitIntegrator
from .integrators import ExplicitIntegrator, Integrator
from .model import Model, State


def make_integrator(name, model: Model, options: dict | None = None) -> Integrator:
    """The integrator called ``name`` (``"implicit"``, an explicit method, or one explicit method per world)."""
    if isinstance(name, str) and name == "implicit":
        return ImplicitIntegrator(model, **(options or {}))
    return ExplicitIntegrator(model, name)


class Stepper:
    """Advances a model's state with ``integrator`` in fixed steps of ``dt``, whole frames at a time.

    Args:
        model: the model.
        integrator: an :class:`~softsim_warp.core.integrators.Integrator` for it.
        dt: step size [s].
        use_graph: capture each distinct step count as a graph and replay it (default on).

    ``state`` is the current state; ``advance(n)`` takes ``n`` steps. Between calls the state may be
    read (``state.particle_q.numpy()``) or written; a captured graph reads whichever of the two
    state buffers is current, so writes to ``state`` take effect on the next call. Before the first
    capture, :meth:`warm_up` takes one step into a spare state, so every kernel is compiled and
    loaded outside the capture (the implicit integrator's conditional graph nodes need that).
    """

    def __init__(self, model: Model, integrator: Integrator, dt: float, use_graph=None):
        self.model = model
        self.integrator = integrator
        self.dt = float(dt)
        self.use_graph = True if use_graph is None else bool(use_graph)
        self.states = [model.state(), model.state()]
        self.current = 0
        self._graphs = {}
        self.warmed_up = False

    def warm_up(self) -> float:
        """Compile and load every kernel a step launches (one step into a spare state, which leaves
        ``state`` as it was); returns the seconds it took."""
        t0 = time.perf_counter()
        self.integrator.step(self.state, self.model.state(), self.dt)
        wp.synchronize_device(self.model.device)
        reset_stats = getattr(self.integrator, "reset_stats", None)  # the warm-up step is not part of the run
        if reset_stats is not None:
            reset_stats()
        self.warmed_up = True
        return time.perf_counter() - t0

    @property
    def state(self) -> State:
        return self.states[self.current]

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
            if not self.warmed_up:
                self.warm_up()
            start = self.current
            with wp.ScopedCapture(device=self.model.device, force_module_load=False) as capture:
                self._advance_plain(n)
            graph = self._graphs[key] = capture.graph
            self.current = start  # capture recorded the launches; the replay below runs them
        wp.capture_launch(graph)
        self.current = (self.current + n) % 2
