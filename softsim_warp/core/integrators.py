"""Integrators: the ``Integrator`` interface and explicit Euler, symplectic Euler, midpoint and RK4.

Force evaluation (:func:`softsim_warp.core.forces.eval_forces`) is apart from integration: every method only combines
evaluations of it. Contact (:func:`softsim_warp.core.contact.apply_contacts`) runs once per step on the result; see
``kernels/contact.py`` for why it is not part of the stages. ``step`` only launches kernels: no
NumPy, no host synchronisation, so a run of steps can be captured as a graph and replayed.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .contact import apply_contacts, filter_stage_contacts, move_terrain
from .forces import eval_forces
from .fused import configure_fused, stage_buffers, step_fused
from .methods import DEFAULT, EXPLICIT_NAMES, MAX_STAGES
from .methods import method as method_of  # ``method`` is ExplicitIntegrator's argument
from .model import NUMPY_SCALARS, Model, State
from .pins import drive
from .profile import NO_PROFILE
from ..kernels import integration as integration_kernels


class Integrator:
    """Base class: ``step(state_in, state_out, dt)`` advances one step, contact included.

    Each integrator owns its run state (``self.run``, a :class:`~softsim_warp.core.model.RunState`
    made here): the pin, terrain and animation clocks, the current terrain poses, the jelly contact
    lists and impulses, the force scratch. The model is only read, so integrators of one model step
    independently. The run state is not a ``step`` argument (Newton's ``step(state_in, state_out,
    control, contacts, dt)``) because a captured graph binds the buffers it recorded: a run state
    given per call could not change under a graph, and tying it to the integrator, as Newton's
    solvers own their scratch, says so. ``run.reset()`` puts it back at t = 0.
    """

    name = "base"
    # Times the parts of each step when a stepper profiles it (core/profile.py); a no-op otherwise.
    profile = NO_PROFILE

    def __init__(self, model: Model):
        self.model = model
        self.run = model.run_state()

    def step(self, state_in: State, state_out: State, dt: float):
        """Advance ``state_in`` by ``dt`` into ``state_out``. Implementations start with
        ``pins.drive(model, self.run, state_in, dt)`` (driven pins) and
        ``contact.move_terrain(model, self.run, dt)`` (moving terrain) and end with ``apply_contacts``."""
        raise NotImplementedError

    def stats(self) -> dict:
        """Per-run statistics for the metrics file (e.g. linear-solver iterations)."""
        return {}

    def profile_notes(self) -> list[str]:
        """Work that a profile cannot time apart because a kernel of another part does it."""
        return []

    def check_states(self, state_in: State, state_out: State):
        """Refuse states whose arrays live on another device than the model's, or have another
        particle count: Warp would launch on them anyway and read or write out of place (a crash on
        the CPU with CUDA arrays)."""
        model = self.model
        for name, state in (("state_in", state_in), ("state_out", state_out)):
            for attr in ("particle_q", "particle_qd"):
                a = getattr(state, attr)
                if a.device != model.device:
                    raise ValueError(f"{name}.{attr} is on {a.device}, the model on {model.device}; make states "
                                     "with model.state()")
                if a.shape[0] != model.particle_count:
                    raise ValueError(f"{name}.{attr} has {a.shape[0]} particles, the model {model.particle_count}")


class ExplicitIntegrator(Integrator):
    """Explicit Euler, symplectic Euler, midpoint or RK4, one method per world.

    Args:
        model: the model to advance.
        method: a method name for every world, or a list with one name per world (the copies of
            a side-by-side comparison advance in the same launches).
        fused, fuse_contact, single: the lattice fast path's options
            (:func:`softsim_warp.core.fused.configure_fused`); None picks what pays.
    """

    def __init__(
        self,
        model: Model,
        method=DEFAULT.name,
        fused=None,
        fuse_contact=None,
        single=None,
    ):
        super().__init__(model)
        methods = [method] * model.world_count if isinstance(method, str) else list(method)
        if len(methods) != model.world_count:
            raise ValueError(f"need one method per world ({model.world_count}), got {len(methods)}")
        for name in methods:
            if not method_of(name).explicit:
                raise ValueError(f"{name} is not an explicit integrator; choose from {', '.join(EXPLICIT_NAMES)}")
        self.methods = methods
        self.name = methods[0] if len(set(methods)) == 1 else "mixed"
        np_scalar = NUMPY_SCALARS[model.precision]
        c = np.zeros((model.world_count, MAX_STAGES), dtype=np_scalar)
        b = np.zeros((model.world_count, MAX_STAGES), dtype=np_scalar)
        counts = np.zeros(model.world_count, dtype=np.int32)
        symplectic = np.zeros(model.world_count, dtype=np.int32)
        for w, name in enumerate(methods):
            c_method, b_method = method_of(name).tableau
            counts[w] = len(c_method)
            c[w, : len(c_method)] = c_method
            b[w, : len(b_method)] = b_method
            symplectic[w] = method_of(name).partitioned
        self.stage_count = int(counts.max())
        device = model.device
        self.world_stage_count = wp.array(counts, dtype=wp.int32, device=device)
        self.world_symplectic = wp.array(symplectic, dtype=wp.int32, device=device)
        self.world_stage_c = wp.array2d(c, dtype=model.scalar, device=device)
        self.world_stage_b = wp.array2d(b, dtype=model.scalar, device=device)
        self.world_contact_beta = wp.array(
            np.array([method_of(name).contact_beta for name in methods], dtype=np_scalar), dtype=model.scalar, device=device
        )
        # Lattice fast path: one fused kernel per stage (forces + stage update, plane contact on the
        # last stage) where it pays; see softsim_warp/core/fused.py and docs/PERFORMANCE.md.
        configure_fused(self, fused, fuse_contact, single)
        # Stage buffers, allocated once: forces, the stage state and the RK accumulators.
        n = model.particle_count
        # A fused gather stage keeps forces in registers; the row kernel and the plain path need f.
        gather_fused = self.fused and (model.lattice is None or model.lattice.per_particle)  # None: masked
        self.f = wp.zeros(0 if gather_fused else n, dtype=model.vec3, device=device)
        multi = self.stage_count > 1
        # Stage states are gathered from like the state itself, so they are made the same way.
        self.q_s = model.particle_array() if multi else wp.zeros(0, dtype=model.vec3, device=device)
        self.qd_s = model.particle_array() if multi else wp.zeros(0, dtype=model.vec3, device=device)
        self.acc_q = wp.zeros(n if multi else 0, dtype=model.vec3, device=device)
        self.acc_qd = wp.zeros(n if multi else 0, dtype=model.vec3, device=device)
        if self.fused:
            stage_buffers(self)

    def step(self, state_in: State, state_out: State, dt: float):
        self.check_states(state_in, state_out)
        drive(self.model, self.run, state_in, dt)
        move_terrain(self.model, self.run, dt)
        if self.fused:
            step_fused(self, state_in, state_out, dt)
            return
        model = self.model
        profile = self.profile
        h = model.scalar(dt)
        q, qd = state_in.particle_q, state_in.particle_qd
        for stage in range(self.stage_count):
            with profile.part("stages"):
                eval_forces(model, q, qd, self.f, self.run.forces)
                wp.launch(
                    integration_kernels.integrate_stage,
                    dim=model.particle_count,
                    inputs=[
                        stage,
                        h,
                        model.particle_inv_mass,
                        model.particle_world,
                        model.gravity,
                        self.world_stage_count,
                        self.world_symplectic,
                        self.world_stage_c,
                        self.world_stage_b,
                        state_in.particle_q,
                        state_in.particle_qd,
                        q,
                        qd,
                        self.f,
                    ],
                    outputs=[self.acc_q, self.acc_qd, self.q_s, self.qd_s, state_out.particle_q, state_out.particle_qd],
                    device=model.device,
                )
            q, qd = self.q_s, self.qd_s
            if stage < self.stage_count - 1:
                with profile.part("contact"):
                    filter_stage_contacts(model, self.run, state_in, q, qd, self.world_contact_beta)
        with profile.part("contact"):
            apply_contacts(model, self.run, state_in, state_out, dt, self.world_contact_beta)

    def profile_notes(self) -> list[str]:
        if self.fused and self.fuse_contact:
            return ["plane contact (and its filter between stages) runs inside the fused stage kernel: its time is part of stages"]
        return []
