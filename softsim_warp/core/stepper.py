"""Integrator factory and whole-frame stepping, the API's loop: scene -> Model -> States -> steps.

:class:`Stepper` holds two states and advances them ``n`` steps at a time. On the first call for a
given ``n`` it captures the steps' launches as a graph (``wp.ScopedCapture``) and afterwards
replays it with one ``wp.capture_launch``: a Python loop over frames then costs one launch per
frame, on CUDA and on the CPU (Warp replays a CPU graph in C++), as fast as ``softsim run``.

A graph holds at most :data:`MAX_GRAPH_STEPS` steps: a longer call replays that graph as often as
it fits and a graph of the remainder after it, so the memory of the captured graphs is bounded
whatever the step count (a tiny ``dt`` once made a frame's capture try 10^10 steps and abort the
process in ``std::bad_alloc``).
"""

from __future__ import annotations

import contextlib

import time

import warp as wp

from .implicit import ImplicitIntegrator
from .integrators import ExplicitIntegrator, Integrator
from .methods import method
from .mesh_terrain import steps_on_host
from .model import Model, State
from .profile import NO_PROFILE, StepProfile

# Steps captured in one graph at most. A graph's host memory and capture time grow with its steps
# (an implicit step records the most launches), while a replay costs about as little as one launch;
# at 100 steps the replay's share of even the cheapest step is small, and much longer graphs stop
# fitting in the CPU's caches (docs/PERFORMANCE.md, the graph capture fast path). Read at call time
# (tests lower it).
MAX_GRAPH_STEPS = 100

# Graphs of other sizes than MAX_GRAPH_STEPS kept at most (a frame loop needs up to four: two step
# counts per frame, each from either buffer); a call of yet another size once this many are held
# launches its steps one by one, so calls of ever new sizes cannot grow the memory without bound.
MAX_CACHED_GRAPHS = 8


def make_integrator(name, model: Model, options: dict | None = None) -> Integrator:
    """The integrator called ``name`` (a name of :data:`.methods.NAMES`), or one explicit method per
    world when ``name`` is a list; ``options`` are the implicit integrator's settings (the scene's
    ``[implicit]`` table; explicit methods take none), None for defaults."""
    if isinstance(name, str) and not method(name).explicit:
        return ImplicitIntegrator(model, **(options or {}))
    return ExplicitIntegrator(model, name)  # it checks each name


class Stepper:
    """Advances a model's state with ``integrator`` in fixed steps of ``dt``, whole frames at a time.

    Args:
        model: the model.
        integrator: an :class:`~softsim_warp.core.integrators.Integrator` for it.
        dt: step size [s].
        use_graph: capture each distinct step count (up to :data:`MAX_GRAPH_STEPS`) as a graph and
            replay it (default on; off when profiling).
        profile: time the parts of every step (:class:`~softsim_warp.core.profile.StepProfile`,
            given to the integrator as ``integrator.profile`` and kept as ``self.profile``). Each
            part is bracketed by a synchronise, which a captured graph cannot hold, so the steps are
            launched one by one.
        on_warm_up: a callable returning a context manager that :meth:`warm_up` enters around its
            step (the command line passes its "compiling kernels" notice), or None.

    ``state`` is the current state; ``advance(n)`` takes ``n`` steps. Between calls the state may be
    read (``state.particle_q.numpy()``) or written; a captured graph reads whichever of the two
    state buffers is current, so writes to ``state`` take effect on the next call (jelly contact keeps
    its pairs' last impulses to start the next step from; after writing a new start into ``state``,
    ``integrator.run.forget_contact_history()`` drops them). Before the first capture,
    :meth:`warm_up` takes one step into a spare state, so every kernel is compiled and loaded
    outside the capture (the implicit integrator's conditional graph nodes need that), and then
    puts the integrator's run state back at t = 0 (``integrator.run.reset()``).

    The model is only read: what a run writes is the integrator's (``integrator.run``), so two
    steppers of one model, each with its own integrator, run independently.
    """

    def __init__(self, model: Model, integrator: Integrator, dt: float, use_graph=None, profile=False,
                 on_warm_up=None):
        if profile and use_graph:
            raise ValueError("a profiled stepper launches its steps one by one: use_graph must be off")
        self.model = model
        self.integrator = integrator
        self.dt = float(dt)
        self.use_graph = (not profile) if use_graph is None else bool(use_graph)
        # An animated mesh's BVH is refit by a host call every step, which no graph records.
        self.use_graph = self.use_graph and not steps_on_host(model)
        # The integrator times its parts into the profile; without one (NO_PROFILE, also replacing
        # an earlier stepper's) it may be captured.
        self.profile = StepProfile(model.device) if profile else None
        integrator.profile = NO_PROFILE if self.profile is None else self.profile
        self.states = [model.state(), model.state()]
        self.current = 0
        # A run from the initial state: no contact impulses of another run of this integrator.
        integrator.run.forget_contact_history()
        self._graphs = {}
        self.warmed_up = False
        self.on_warm_up = on_warm_up

    def warm_up(self) -> float:
        """Compile and load every kernel a step launches (one step into a spare state, which leaves
        ``state`` as it was); returns the seconds it took."""
        t0 = time.perf_counter()
        with self.on_warm_up() if self.on_warm_up is not None else contextlib.nullcontext():
            self._warm_up_step()
        self.warmed_up = True
        return time.perf_counter() - t0

    def _warm_up_step(self):
        self.integrator.step(self.state, self.model.state(), self.dt)
        # The warm-up step is not part of the run: the pins', moving terrain's and animated meshes'
        # clocks restart at t = 0, and its contact impulses do not start the first step.
        self.integrator.run.reset()
        wp.synchronize_device(self.model.device)
        reset_stats = getattr(self.integrator, "reset_stats", None)  # the warm-up step is not part of the run
        if reset_stats is not None:
            reset_stats()
        self.integrator.profile.reset()  # nor is its time, which includes compiling

    @property
    def state(self) -> State:
        return self.states[self.current]

    def _advance_plain(self, n: int):
        profile = self.integrator.profile
        for _ in range(n):
            with profile.step():
                self.integrator.step(self.states[self.current], self.states[1 - self.current], self.dt)
            self.current = 1 - self.current

    def advance(self, n: int, stop=None) -> int:
        """Take ``n`` steps, replaying captured graphs when enabled: ``n // MAX_GRAPH_STEPS`` replays of
        a graph of ``MAX_GRAPH_STEPS`` steps, then one graph of the remainder.

        ``stop``: a callable asked before each chunk of at most ``MAX_GRAPH_STEPS`` steps; when it
        returns true the remaining steps are not taken (a stop acts within a chunk however many
        steps ``n`` is). Returns the steps taken. The chunks are the same with and without it, so
        the result is too."""
        if n <= 0:
            return 0
        n = int(n)
        chunk = max(1, int(MAX_GRAPH_STEPS))
        if not self.use_graph:
            if self.profile is not None and not self.warmed_up:
                self.warm_up()  # compiling is not part of any step's time
            if stop is None:
                self._advance_plain(n)
                return n
            for done in range(0, n, chunk):
                if stop():
                    return done
                self._advance_plain(min(chunk, n - done))
            return n
        full, rest = divmod(n, chunk)
        for i in range(full):
            if stop is not None and stop():
                return i * chunk
            self._replay(chunk, chunk)
        if rest:
            if stop is not None and stop():
                return full * chunk
            self._replay(rest, chunk)
        return n

    def _replay(self, n: int, chunk: int):
        """Take ``n`` steps by replaying the graph of ``n`` steps from the current buffer, captured on
        first use. A graph reads and writes fixed buffers: one of an odd step count starts from the
        buffer that is current and ends in the other, so the key holds the current buffer's index."""
        key = (n, self.current)
        graph = self._graphs.get(key)
        if graph is None:
            if n != chunk and sum(1 for m, _ in self._graphs if m != chunk) >= MAX_CACHED_GRAPHS:
                self._advance_plain(n)
                return
            if not self.warmed_up:
                self.warm_up()
            start = self.current
            try:
                with wp.ScopedCapture(device=self.model.device, force_module_load=False) as capture:
                    self._advance_plain(n)
            finally:
                self.current = start  # capture recorded the launches; the replay below runs them
            graph = self._graphs[key] = capture.graph
        wp.capture_launch(graph)
        self.current = (self.current + n) % 2
