"""Implicit (backward) Euler, linearised as in Baraff and Witkin, "Large steps in cloth simulation" (1998).

Backward Euler advances ``v_{n+1} = v_n + h M^-1 (f(x_{n+1}, v_{n+1}) + M g)`` and
``x_{n+1} = x_n + h v_{n+1}``. Its stability function is ``1/(1 - h lambda)``: every decaying or
oscillating mode decays, at any step, which is why stiff springs and large steps do not explode.
The price is numerical damping: an undamped oscillator of frequency omega keeps only the factor
``1/(1 + (h omega)^2)`` of its energy per step (see docs/IMPLICIT.md).

Each step solves, once per Newton iteration, ``(M - h df/dv - h^2 df/dx) delta = rhs`` for a
velocity correction. Two linearisations are offered (``linearization``):

* ``"baraff_witkin"``: the forces are linearised about the start of the step (x_n, v_n):

      (M - h df/dv - h^2 df/dx) dv = h (f(x_n, v_n) + M g + h df/dx v_n).

  This is Baraff and Witkin's step. It sees a spring's length only to first order, so a spinning
  stiff body (springs rotated by h omega per step) is stretched by the second-order amount
  ~ h^2 omega^2 |d| / 2 every step, which adds energy ~ ks (h^2 omega^2 |d|)^2 / 8 per spring:
  with ks = 1e5 at h = 0.01 a jelly spinning at 7 rad/s gains more energy in one step than it has.
* ``"predictor"`` (default): Newton's method on the exact backward Euler equations, started from
  v_0 = v_n, so every iteration linearises about (x_n + h v_k, v_k):

      (M - h df/dv - h^2 df/dx) delta = M (v_n - v_k) + h (f(x_n + h v_k, v_k) + M g),
      v_{k+1} = v_k + delta.

  Its first iteration differs from Baraff-Witkin's only by the force's nonlinear remainder
  f(x_n + h v_n) - f(x_n) - h df/dx v_n: it costs the same, and the energy never rises.

More Newton iterations (``newton_iterations > 1``) continue from the current iterate with the
second formula in either mode, converging to the exact backward Euler step. The Jacobian blocks,
the definiteness fix and which derivative terms are left out are described in
``kernels/implicit.py``.

The linear system is solved on the device with preconditioned conjugate gradient. The default,
``solver="matrix_free"``, computes A p from the spring list; ``"bsr"`` assembles a ``warp.sparse``
block matrix for the same loop and ``"warp_cg"`` hands that matrix to ``warp.optim.linear.cg``
(both slower, kept for the comparison in docs/IMPLICIT.md). This module's loop keeps its scalars on
the device and runs under ``wp.capture_while``: on CUDA the loop is a conditional graph node (no
host synchronisation), on the CPU the condition is read directly from memory.

Contact: the shared post-step response (:func:`~softsim_warp.core.integrators.apply_contacts`:
collision, resting contact, Coulomb friction) decides which particles touch and what happens to
them, as for the explicit integrators; but on its own it breaks a stiff jelly at a large step.
A stiff jelly is nearly rigid within one step, yet the response changes only the particles that
touch: at dt = 0.01 a jelly falling at 3 m/s sinks 3 cm per step, the response lifts its bottom
layer back by those 3 cm, and springs squeezed by half a lattice spacing invert the lattice (with
ks = 1e5 the jelly_drop jelly ended with 4e4 J of spring energy from 10 J). So a step with
contact goes on after the free solve (Baraff and Witkin's constraints, section 5 of the paper):

1. the response runs on the free result, a particle touching anywhere within contact_epsilon
   (kernels/contact.py: LAYER_TOUCH; a stiff lattice needs the particles about to reach the
   surface in the solve too); every particle it changed becomes constrained along
   the normal of the surface it touches (or, with several surfaces or a contact hook, the
   direction the response pushed it): its normal velocity is prescribed (0 for an approaching
   particle: the compression phase of an impact; for one at rest on a single surface, the one that
   lands it there), its tangential velocity is left to the solve.
   Where the response applied friction, the particle gets a tangential damper in the solve
   instead (kernels/implicit.py: constrain_contacts). Prescribed normal velocities of 0 take no
   work from the constraint impulses, so the step stays dissipative. (Prescribing whole
   velocities, as before, made a curved contact patch a velocity source: +1e4 J in a frame of
   seed_bowl at ks = 1e5; reflected velocities on a few particles of a stiff lattice added up to
   40 J to the 10 J jelly_drop jelly.)
2. The last linear system is solved again with these constraints: it is linearised where the
   free solve ended, close to the answer.
3. ``newton_iterations`` Newton iterations re-linearise at the result: an impact can turn the jelly
   by ~0.1 rad in one step, which a single linearisation turns into spring stretch. Up to
   ``EXTRA_CONTACT_ITERATIONS`` more run, only when the result's energy is above the free
   result's (measured per body on the device).
4. Restitution (Poisson's hypothesis): each body (a jelly, or a particle outside every jelly)
   receives e_i times the normal contact impulse of each colliding particle as a rigid-body
   impulse (one velocity and angular velocity change for all its particles, which strains no
   spring), scaled down if needed so that it returns at most the energy the contact solve
   removed: E_{n+1} <= E_free <= E_n.

The springs carry the impact through the whole jelly in the step it happens. Steps 2 to 4 run
under ``wp.capture_if`` on a device flag set when anything touched, so a step without contact pays
only for the response and one small kernel. The response then runs once more on the final state,
as the post-step impulse every integrator gets.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp
import warp.optim.linear
import warp.sparse

from .contact import apply_contacts
from .forces import check_force_terms, eval_forces
from .integrators import Integrator
from .mesh_terrain import mesh_touch_arrays
from .methods import IMPLICIT
from ..kernels import implicit as implicit_kernels
from .model import Model, State
from .pins import drive
from .multigrid import LatticeMultigrid, auto_min_particles, multigrid_support

# "jacobi": 3x3 block-Jacobi; "diagonal": the inverse of the diagonal; "multigrid": a V-cycle on
# the lattice of a one-jelly model (core/multigrid.py); "auto": multigrid where it applies and pays
# (multigrid.auto_min_particles: 12^3 on the CPU, 20^3 on CUDA), else jacobi. "block_jacobi" is another name of "jacobi".
PRECONDITIONERS = ("auto", "multigrid", "jacobi", "diagonal", "block_jacobi")
LINEARIZATIONS = ("predictor", "baraff_witkin")
SOLVERS = ("matrix_free", "bsr", "warp_cg")

# Defaults; the scene's optional [implicit] table overrides them (softsim_warp/io/scene.py).
DEFAULT_NEWTON_ITERATIONS = 1
DEFAULT_CG_TOLERANCE = 1.0e-4
DEFAULT_CG_MAX_ITERATIONS = 200
DEFAULT_LINEARIZATION = "predictor"
# Newton iterations a contact solve may add when it ended above the free result's energy.
EXTRA_CONTACT_ITERATIONS = 2


def _particle_bodies(model: Model) -> np.ndarray:
    """Body index of each particle: its jelly's index, or a body of its own outside every jelly."""
    n = model.particle_count
    body = np.full(n, -1, dtype=np.int64)
    for j, info in enumerate(model.jellies):
        body[info.particle_start : info.particle_start + info.particle_count] = j
    loose = body < 0
    body[loose] = len(model.jellies) + np.arange(int(loose.sum()))
    return body.astype(np.int32)


class ImplicitIntegrator(Integrator):
    """Linearised backward Euler with a preconditioned conjugate-gradient solve on the device.

    Args:
        model: the model to advance.
        newton_iterations: linear solves per step (before the contact solve); more iterate
            Newton's method towards the exact backward Euler step.
        cg_tolerance: CG stops when ``|b - A dv| <= cg_tolerance max(|b|, |b_1|)`` (2-norms over free
            rows; b_1 is the right-hand side of the step's first solve).
        cg_max_iterations: iteration cap of each CG solve.
        linearization: ``"predictor"`` (Newton from v_n, forces linearised about x_n + h v_n) or
            ``"baraff_witkin"`` (the first solve linearises about x_n); see the module docstring.
        preconditioner: ``"jacobi"`` (inverse of each particle's 3x3 diagonal block; also called
            ``"block_jacobi"``), ``"diagonal"`` (inverse of the diagonal), ``"multigrid"`` (a
            geometric multigrid V-cycle, ``core/multigrid.py``: one-jelly lattice models with the
            matrix-free solver; any other model falls back to ``"jacobi"``, and
            ``stats()["cg_preconditioner_note"]`` says why) or ``"auto"`` (multigrid where it
            applies from ``multigrid.auto_min_particles(device)`` particles on, else jacobi).
        solver: ``"matrix_free"`` (A p from the spring list, this module's PCG loop), ``"bsr"``
            (an assembled ``warp.sparse`` block matrix, ``bsr_mv`` in the same PCG loop) or
            ``"warp_cg"`` (the assembled matrix solved by ``warp.optim.linear.cg``). The last two
            are kept for the benchmark comparison: matrix-free is the fastest. ``"warp_cg"`` has no
            constraint filter, so it skips the contact solve (contact is the post-step response
            only).
        warm_start: start each step's first solve from the last step's dv (gravity part
            updated to this step) instead of 0; off only to measure what it saves.
    """

    name = IMPLICIT.name

    def __init__(
        self,
        model: Model,
        newton_iterations: int = DEFAULT_NEWTON_ITERATIONS,
        cg_tolerance: float = DEFAULT_CG_TOLERANCE,
        cg_max_iterations: int = DEFAULT_CG_MAX_ITERATIONS,
        linearization: str = DEFAULT_LINEARIZATION,
        preconditioner: str = "auto",
        solver: str = "matrix_free",
        warm_start: bool = True,
    ):
        super().__init__(model)
        # Its Newton solve needs every force's Jacobian; core/forces.ForceTerm carries none.
        check_force_terms(model, "implicit solve")
        if model.terrain_motion is not None or model.mesh_animation is not None:
            # Its contact solve prescribes a touching particle's normal velocity as 0 and damps its
            # tangential one towards 0, the terrain's own velocity being unknown to it.
            raise ValueError("the implicit integrator does not take moving terrain; use an explicit one")
        # x_{n+1} = x_n + h v_{n+1}: a force held over the step moves x by h^2 a (contact gain 1).
        self.world_contact_beta = wp.full(model.world_count, model.scalar(1.0), dtype=model.scalar, device=model.device)
        if int(newton_iterations) != newton_iterations or newton_iterations < 1:
            raise ValueError(f"newton_iterations must be an integer >= 1 (got {newton_iterations!r})")
        if not (math.isfinite(cg_tolerance) and 0.0 < cg_tolerance < 1.0):
            raise ValueError(f"cg_tolerance must be > 0 and < 1 (got {cg_tolerance!r})")
        if int(cg_max_iterations) != cg_max_iterations or cg_max_iterations < 1:
            raise ValueError(f"cg_max_iterations must be an integer >= 1 (got {cg_max_iterations!r})")
        if linearization not in LINEARIZATIONS:
            raise ValueError(f"linearization must be one of {', '.join(LINEARIZATIONS)} (got {linearization!r})")
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"preconditioner must be one of {', '.join(PRECONDITIONERS)} (got {preconditioner!r})")
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(SOLVERS)} (got {solver!r})")
        self.newton_iterations = int(newton_iterations)
        self.cg_tolerance = float(cg_tolerance)
        self.cg_max_iterations = int(cg_max_iterations)
        self.linearization = linearization
        self.preconditioner, self.preconditioner_note = self._choose_preconditioner(model, preconditioner, solver)
        self.solver = solver
        self.warm_start = bool(warm_start)

        device = model.device
        scalar, vec3 = model.scalar, model.vec3
        self.mat33 = wp.types.matrix((3, 3), scalar)
        n, s = model.particle_count, model.spring_count

        def vectors():
            return wp.zeros(n, dtype=vec3, device=device)

        # Solver buffers, allocated once. dv_warm keeps the last step's dv as the next initial guess.
        self.f = vectors()
        self.rhs = vectors()
        self.x = vectors()
        self.dv_warm = vectors()
        self.step_bb = wp.zeros(1, dtype=scalar, device=device)  # b.b of the step's first solve
        self.r = vectors()
        self.z = vectors()
        self.p = vectors()
        self.ap = vectors()
        self.diag_block = wp.zeros(n, dtype=self.mat33, device=device)
        self.precond = wp.zeros(n, dtype=self.mat33, device=device)
        # Multigrid on CUDA recomputes the spring blocks from positions (core/multigrid.py) and stores none.
        gather = self.preconditioner == "multigrid" and device.is_cuda
        self.spring_block = wp.zeros(0 if gather else s, dtype=self.mat33, device=device)
        self.scalars = wp.zeros(implicit_kernels.SCALAR_SLOTS, dtype=scalar, device=device)
        self.ints = wp.zeros(2, dtype=wp.int32, device=device)
        self.stats_array = wp.zeros(implicit_kernels.STAT_SLOTS, dtype=wp.int32, device=device)
        # Largest and summed final relative residual of this module's CG solves (record_residual).
        self.residual_stats = wp.zeros(2, dtype=model.scalar, device=device)
        self._condition = self.ints[implicit_kernels.COND : implicit_kernels.COND + 1]
        # Fixed particles (inverse mass 0) and each particle's constraint filter (see kernels/implicit.py).
        fixed = (model.particle_inv_mass.numpy() == 0).astype(np.int32)
        self.fixed = wp.array(fixed, dtype=wp.int32, device=device)
        self.filters = wp.zeros(n, dtype=self.mat33, device=device)
        hooks = [h for h in self.run.contact_hooks if getattr(h, "in_contact_solve", True)]
        terrain = model.plane_count or model.bowl_count or model.sphere_count or model.mesh_count or hooks
        self.contact_solve = bool(terrain) and solver != "warp_cg"
        if self.contact_solve:
            # The step's result before the contact response, and the iterate of the last solve.
            self.q_free = vectors()
            self.qd_free = vectors()
            self.qd_k = vectors()
            self.any_contact = wp.zeros(1, dtype=wp.int32, device=device)
            # Restitution acts on bodies: each jelly, and each particle outside a jelly.
            body = _particle_bodies(model)
            body_count = int(body.max()) + 1 if n else 0
            body_mass = np.bincount(body, weights=model.particle_mass_host, minlength=body_count)
            # A body held by a fixed particle cannot move rigidly: no restitution impulse (mass 0).
            body_mass[np.unique(body[fixed != 0])] = 0.0
            self.particle_body = wp.array(body, dtype=wp.int32, device=device)
            _, first = np.unique(body, return_index=True)  # each body's first particle
            self.body_reference = wp.array(first.astype(np.int32), dtype=wp.int32, device=device)
            self.body_mass = wp.array(body_mass, dtype=scalar, device=device)
            self.body_data = wp.zeros((body_count, implicit_kernels.BODY_SLOTS), dtype=scalar, device=device)
            self.contact_restitution = wp.zeros(n, dtype=scalar, device=device)
            self.contact_approach = vectors()
            self.energy_gained = wp.zeros(1, dtype=wp.int32, device=device)
            if s:
                # measure_spring_restitution reads the spring list, which a lattice model copies to
                # the device on first use: copy it now, not inside a captured step (multigrid reads
                # no spring list, and a CPU graph replayed that copy from freed host memory).
                _ = model.spring_indices
        # Mass plus the contact friction damper per particle (kernels/implicit.py: constrain_contacts);
        # the plain mass outside the contact solve.
        self.mass_eff = wp.clone(model.particle_mass) if self.contact_solve else model.particle_mass
        self._solve_graph = None
        self._loop_ran = False
        # On CUDA outside a capture, the PCG loop is captured once and replayed; that needs
        # conditional graph nodes (CUDA 12.4+), otherwise capture_while reads the condition back.
        self._graph_ok = device.is_cuda and wp.is_conditional_graph_supported()
        self._host_stats = np.zeros(implicit_kernels.STAT_SLOTS, dtype=np.int64)
        if solver in ("bsr", "warp_cg"):
            self._setup_bsr()
        # Multigrid: the V-cycle replaces z = P r in the CG loop; init_residual gets a zero block
        # array as P (its r.z is 0), cg_update skips P, and the V-cycle adds r.z itself.
        self.multigrid = None
        if self.preconditioner == "multigrid":
            self.multigrid = LatticeMultigrid(model, self)
            self.no_precond = wp.zeros(n, dtype=self.mat33, device=device)

    @staticmethod
    def _choose_preconditioner(model: Model, name: str, solver: str) -> tuple[str, str]:
        """The preconditioner used for ``name`` ("auto" and "multigrid" may fall back to jacobi), and why."""
        name = "jacobi" if name == "block_jacobi" else name
        if name not in ("auto", "multigrid"):
            return name, "requested"
        ok, reason = multigrid_support(model)
        if ok and solver != "matrix_free":
            ok, reason = False, f"solver {solver} (multigrid needs matrix_free)"
        least = auto_min_particles(model.device)
        if ok and name == "auto" and model.particle_count < least:
            ok, reason = False, f"{model.particle_count} particles (auto: multigrid from {least} on {model.device})"
        if ok:
            return "multigrid", f"{name}: lattice"
        return "jacobi", f"{name}: jacobi, since multigrid does not apply: {reason}"

    # -- assembled block-sparse variants --------------------------------------------------------

    def _setup_bsr(self):
        model = self.model
        device = model.device
        n = model.particle_count
        pairs = model.spring_indices_host.astype(np.int64)
        diag = np.arange(n, dtype=np.int64)
        rows = np.concatenate([diag, pairs[:, 0], pairs[:, 1]])
        cols = np.concatenate([diag, pairs[:, 1], pairs[:, 0]])
        self.bsr = wp.sparse.bsr_zeros(n, n, block_type=self.mat33, device=device)
        wp.sparse.bsr_set_from_triplets(
            self.bsr,
            wp.array(rows.astype(np.int32), dtype=wp.int32, device=device),
            wp.array(cols.astype(np.int32), dtype=wp.int32, device=device),
            None,
        )
        # Where each block sits in the matrix's values: row r's blocks are offsets[r]:offsets[r+1],
        # sorted by column.
        offsets = self.bsr.offsets.numpy()[: n + 1].astype(np.int64)
        columns = self.bsr.columns.numpy()[: offsets[-1]].astype(np.int64)

        def locate(r, c):
            out = np.empty(len(r), dtype=np.int32)
            for k, (ri, ci) in enumerate(zip(r, c, strict=True)):
                lo, hi = offsets[ri], offsets[ri + 1]
                out[k] = lo + np.searchsorted(columns[lo:hi], ci)
            return out

        self.bsr_diag_index = wp.array(locate(diag, diag), dtype=wp.int32, device=device)
        self.bsr_index_ab = wp.array(locate(pairs[:, 0], pairs[:, 1]), dtype=wp.int32, device=device)
        self.bsr_index_ba = wp.array(locate(pairs[:, 1], pairs[:, 0]), dtype=wp.int32, device=device)
        scalar = model.scalar

        def apply_preconditioner(x, y, z, alpha, beta):
            wp.launch(
                implicit_kernels.precondition,
                dim=n,
                inputs=[self.precond, x, y, scalar(alpha), scalar(beta)],
                outputs=[z],
                device=device,
            )

        self.bsr_precond = wp.optim.linear.LinearOperator(self.bsr.shape, self.mat33, device, apply_preconditioner)
        self._bsr_solvers = {}

    def _bsr_solver(self, check_every: int):
        solver = self._bsr_solvers.get(check_every)
        if solver is None:
            # atol = 0: stop on the relative tolerance only, as this module's loop does.
            solver = wp.optim.linear.cg(
                self.bsr,
                self.rhs,
                self.x,
                tol=self.cg_tolerance,
                atol=0.0,
                maxiter=self.cg_max_iterations,
                M=self.bsr_precond,
                check_every=check_every,
                run=False,
            )
            self._bsr_solvers[check_every] = solver
        return solver

    def _assemble_bsr(self):
        model = self.model
        device = model.device
        self.bsr.values.zero_()
        wp.launch(
            implicit_kernels.assemble_bsr_diagonal,
            dim=model.particle_count,
            inputs=[self.fixed, model.particle_mass, self.mass_eff, self.diag_block, self.bsr_diag_index],
            outputs=[self.bsr.values],
            device=device,
        )
        if model.spring_count:
            wp.launch(
                implicit_kernels.assemble_bsr_offdiagonal,
                dim=model.spring_count,
                inputs=[model.spring_indices, self.fixed, self.spring_block, self.bsr_index_ab, self.bsr_index_ba],
                outputs=[self.bsr.values],
                device=device,
            )

    def _solve_warp_cg(self):
        model = self.model
        device = model.device
        if device.is_cuda or device.is_capturing:
            # Device-side convergence checks (a conditional graph node on CUDA).
            iters, r2, tol2 = self._bsr_solver(0)()
            wp.launch(implicit_kernels.record_solve, dim=1, inputs=[iters, r2, tol2], outputs=[self.stats_array], device=device)
        else:
            # On the CPU, reading the residual is a plain memory read; checking every iteration
            # stops the loop as soon as it converges.
            iters, err, atol = self._bsr_solver(1)()
            self._host_stats[implicit_kernels.STEP_ITERS] += iters
            self._host_stats[implicit_kernels.SOLVES] += 1
            self._host_stats[implicit_kernels.UNCONVERGED] += int(err > atol)

    # -- this module's PCG loop (matrix-free or on the assembled matrix) ------------------------

    def _spring_mv(self, vec):
        """ap += (spring part of A) vec.

        p.Ap is summed per particle afterwards (``dot_accumulate``), not per spring: in float32 the
        spring sum's atomic partial sums (one per 256 springs: 61,000 at 100^3) lost 2 % of it, and
        CG broke down (the 100^3 jelly's residual went to inf on the CPU)."""
        model = self.model
        s = model.spring_count
        if s:
            wp.launch(
                implicit_kernels.spring_mv,
                dim=(implicit_kernels.tile_blocks(s), implicit_kernels.TILE),
                block_dim=implicit_kernels.TILE,
                inputs=[s, -1, model.spring_indices, self.spring_block, vec],
                outputs=[self.ap, self.scalars],
                device=model.device,
            )

    def _pcg_loop(self):
        """Solve from the initial guess in ``x``; ``ap`` must hold M x (0 in constrained rows)."""
        model = self.model
        device = model.device
        n = model.particle_count
        pblocks = implicit_kernels.tile_blocks(n)
        matrix_free = self.solver == "matrix_free"

        profile = self.profile
        spring_mv = self._spring_mv
        mg = self.multigrid
        precond = self.precond if mg is None else self.no_precond
        # The lattice product writes all of A p (mass included) and p.A p.
        lattice_product = mg is not None and mg.gather
        if lattice_product:
            def spring_mv(vec):
                mg.product(vec, self.ap, self.scalars, implicit_kernels.PAP)

        # r = b - A x0, z = P r, tolerance and condition.
        with profile.part("cg_spring_product"):
            if matrix_free:
                spring_mv(self.x)
            else:
                wp.sparse.bsr_mv(self.bsr, self.x, self.ap, alpha=1.0, beta=0.0)
        wp.launch(
            implicit_kernels.init_residual,
            dim=(pblocks, implicit_kernels.TILE),
            block_dim=implicit_kernels.TILE,
            inputs=[n, self.filters, self.rhs, precond, self.ap],
            outputs=[self.r, self.z, self.p, self.scalars],
            device=device,
        )
        if mg is not None:
            with profile.part("multigrid_vcycle"):
                mg.apply(self.r, self.z, self.scalars, implicit_kernels.RZ_NEW)
        wp.launch(
            implicit_kernels.cg_begin,
            dim=1,
            inputs=[model.scalar(self.cg_tolerance), self.cg_max_iterations, self.step_bb],
            outputs=[self.scalars, self.ints],
            device=device,
        )

        def iteration():
            wp.launch(
                implicit_kernels.cg_direction,
                dim=(pblocks, implicit_kernels.TILE),
                block_dim=implicit_kernels.TILE,
                inputs=[n, int(matrix_free and not lattice_product), self.mass_eff, self.z],
                outputs=[self.p, self.ap, self.scalars],
                device=device,
            )
            # A p and p.A p (the lattice product sums p.A p itself).
            with profile.part("cg_spring_product"):
                if matrix_free:
                    spring_mv(self.p)
                else:
                    wp.sparse.bsr_mv(self.bsr, self.p, self.ap, alpha=1.0, beta=0.0)
                if not lattice_product:
                    wp.launch(
                        implicit_kernels.dot_accumulate,
                        dim=(pblocks, implicit_kernels.TILE),
                        block_dim=implicit_kernels.TILE,
                        inputs=[n, implicit_kernels.PAP, self.p, self.ap],
                        outputs=[self.scalars],
                        device=device,
                    )
            wp.launch(
                implicit_kernels.cg_update,
                dim=(pblocks, implicit_kernels.TILE),
                block_dim=implicit_kernels.TILE,
                inputs=[n, int(mg is None), self.filters, precond, self.p, self.ap],
                outputs=[self.x, self.r, self.z, self.scalars],
                device=device,
            )
            if mg is not None:
                with profile.part("multigrid_vcycle"):
                    mg.apply(self.r, self.z, self.scalars, implicit_kernels.RZ_NEW)
            wp.launch(
                implicit_kernels.cg_end_iteration,
                dim=1,
                inputs=[self.cg_max_iterations],
                outputs=[self.scalars, self.ints],
                device=device,
            )

        wp.capture_while(self._condition, iteration)
        wp.launch(
            implicit_kernels.record_solve,
            dim=1,
            inputs=[
                self.ints[implicit_kernels.ITER : implicit_kernels.ITER + 1],
                self.scalars[implicit_kernels.RR : implicit_kernels.RR + 1],
                self.scalars[implicit_kernels.TOL2 : implicit_kernels.TOL2 + 1],
            ],
            outputs=[self.stats_array],
            device=device,
        )
        wp.launch(
            implicit_kernels.record_residual,
            dim=1,
            inputs=[
                model.scalar(self.cg_tolerance),
                self.scalars[implicit_kernels.RR : implicit_kernels.RR + 1],
                self.scalars[implicit_kernels.TOL2 : implicit_kernels.TOL2 + 1],
            ],
            outputs=[self.residual_stats],
            device=device,
        )

    def _solve_pcg(self):
        device = self.model.device
        # A profiled step launches the loop's kernels from Python, so each part can be timed.
        if self._graph_ok and not device.is_capturing and self._loop_ran and not self.profile.active:
            # The loop only touches this integrator's buffers, so one captured graph serves every
            # solve. (Captured from the second call on, when every kernel module is loaded.)
            if self._solve_graph is None:
                with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                    self._pcg_loop()
                self._solve_graph = capture.graph
            wp.capture_launch(self._solve_graph)
        else:
            self._pcg_loop()
            self._loop_ran = True

    def _solve(self, constrained: bool = False):
        profile = self.profile
        if self.multigrid is not None:
            # The whole setup: the device-side decision (mg_setup_due, capture_if) and any build.
            with profile.part("multigrid_setup"):
                self.multigrid.setup(constrained)
        if self.solver != "matrix_free":
            with profile.part("system_assembly"):
                self._assemble_bsr()
        if self.solver == "warp_cg":
            with profile.part("warp_cg_solve"):
                self._solve_warp_cg()
        else:
            # The loop's own kernels and control; its products and V-cycles are parts of their own.
            with profile.part("cg_vector_update"):
                self._solve_pcg()

    # -- the step -------------------------------------------------------------------------------

    def _update(self, h, state_in: State, qd_k: wp.array, state_out: State, save_warm: bool, dv_scale=1.0):
        """v_out = qd_k + dv_scale x, q_out = q_n + h v_out; optionally keep x as the next warm start."""
        model = self.model
        with self.profile.part("velocity_update"):
            wp.launch(
                implicit_kernels.apply_velocity_update,
                dim=model.particle_count,
                inputs=[
                    h,
                    model.scalar(dv_scale),
                    int(save_warm),
                    self.fixed,
                    model.gravity,
                    state_in.particle_q,
                    qd_k,
                    self.x,
                ],
                outputs=[state_out.particle_q, state_out.particle_qd, self.dv_warm],
                device=model.device,
            )

    def _newton_iteration(self, h, state_in: State, state_out: State, at_start: bool, first: bool, reset_filters: bool):
        """Linearise, build and solve one system; write v = v_k + dv and x = x_n + h v to state_out."""
        model = self.model
        device = model.device
        scalar = model.scalar
        n = model.particle_count
        # Linearisation point: (x_n, v_n) for Baraff-Witkin's solve, else the iterate (x_n + h v_k, v_k).
        q, qd = (
            (state_in.particle_q, state_in.particle_qd) if at_start else (state_out.particle_q, state_out.particle_qd)
        )
        with self.profile.part("forces_jacobians"):
            eval_forces(model, q, qd, self.f, self.run.forces)
            self.diag_block.zero_()
            self.rhs.zero_()
            if model.spring_count and self.multigrid is not None:
                # A lattice jelly: per-particle gather, no spring blocks stored (core/multigrid.py).
                self.multigrid.jacobians(h, h * h if at_start else scalar(0.0), q, qd, self.diag_block, self.rhs)
            elif model.spring_count:
                wp.launch(
                    implicit_kernels.eval_spring_jacobians,
                    dim=model.spring_count,
                    inputs=[
                        h,
                        h * h if at_start else scalar(0.0),
                        model.spring_indices,
                        model.spring_rest_length,
                        model.spring_stiffness,
                        model.spring_damping,
                        q,
                        qd,
                    ],
                    outputs=[self.spring_block, self.diag_block, self.rhs],
                    device=device,
                )
        with self.profile.part("system_assembly"):
            self.scalars.zero_()
            wp.launch(
                implicit_kernels.build_system,
                dim=(implicit_kernels.tile_blocks(n), implicit_kernels.TILE),
                block_dim=implicit_kernels.TILE,
                inputs=[
                    n,
                    h,
                    scalar(1.0) if first and self.warm_start else scalar(0.0),
                    int(self.preconditioner != "diagonal"),
                    int(reset_filters),
                    model.particle_mass,
                    model.gravity,
                    self.fixed,
                    self.mass_eff,
                    state_in.particle_qd,
                    qd,
                    self.f,
                    self.dv_warm,
                    self.diag_block,
                    self.rhs,
                    self.filters,
                ],
                outputs=[self.precond, self.x, self.ap, self.scalars],
                device=device,
            )
            if first:
                wp.launch(implicit_kernels.set_step_scale, dim=1, inputs=[self.scalars], outputs=[self.step_bb], device=device)
        self._solve(constrained=not reset_filters)
        self._update(h, state_in, qd, state_out, first)

    def step(self, state_in: State, state_out: State, dt: float):
        self.check_states(state_in, state_out)
        drive(self.model, self.run, state_in, dt)
        model = self.model
        h = model.scalar(dt)
        baraff_witkin = self.linearization == "baraff_witkin"
        if self.contact_solve:
            wp.copy(self.mass_eff, model.particle_mass)
        if not baraff_witkin:
            # Newton's starting iterate v_0 = v_n, x_n + h v_0 (dv_scale 0: x holds no dv yet).
            self._update(h, state_in, state_in.particle_qd, state_out, False, dv_scale=0.0)
        for it in range(self.newton_iterations):
            first = it == 0
            self._newton_iteration(h, state_in, state_out, first and baraff_witkin, first, True)
        if self.contact_solve:
            # Its forces, setups, solves and updates count under their own parts; this part keeps
            # the constraints, the energy measurements and restitution.
            with self.profile.part("contact_solve"):
                self._contact_solve(h, state_in, state_out, dt)
        self._record_step()
        with self.profile.part("contact"):
            apply_contacts(model, self.run, state_in, state_out, dt, self.world_contact_beta)

    def _contact_solve(self, h, state_in: State, state_out: State, dt: float):
        """Newton iterations again, with the contact response's velocities as constraints."""
        model = self.model
        wp.copy(self.q_free, state_out.particle_q)
        wp.copy(self.qd_free, state_out.particle_qd)
        with self.profile.part("contact"):
            apply_contacts(model, self.run, state_in, state_out, dt, self.world_contact_beta, solve_hooks_only=True,
                           layer_touch=True)
        self.any_contact.zero_()
        wp.launch(
            implicit_kernels.constrain_contacts,
            dim=model.particle_count,
            inputs=[
                h,
                model.particle_world,
                model.particle_mass,
                self.fixed,
                model.plane_first,
                self.run.terrain.plane_point,
                self.run.terrain.plane_normal,
                self.run.terrain.plane_hole_center,
                model.plane_hole_radius,
                model.bowl_first,
                self.run.terrain.bowl_center,
                model.bowl_radius,
                model.bowl_cut_height,
                model.sphere_first,
                self.run.terrain.sphere_center,
                model.sphere_radius,
                *mesh_touch_arrays(model, self.run),
                model.contact_epsilon,
                model.contact_velocity_epsilon,
                state_in.particle_q,
                state_in.particle_qd,
                self.q_free,
                self.qd_free,
                state_out.particle_q,
                state_out.particle_qd,
            ],
            outputs=[
                self.filters,
                state_out.particle_q,
                state_out.particle_qd,
                self.any_contact,
                self.contact_restitution,
                self.contact_approach,
                self.mass_eff,
            ],
            device=model.device,
        )

        def constrained_iterations():
            # First the last linear system again, now with the constraints: it is linearised
            # where the free solve ended, close to the answer. Linearising at the constrained
            # iterate instead (particles bounced by the response, their neighbours not yet)
            # would start Newton from a distorted lattice and can diverge.
            n = model.particle_count
            with self.profile.part("system_assembly"):
                self.scalars.zero_()
                wp.launch(
                    implicit_kernels.constrain_last_system,
                    dim=(implicit_kernels.tile_blocks(n), implicit_kernels.TILE),
                    block_dim=implicit_kernels.TILE,
                    inputs=[
                        n,
                        int(self.preconditioner != "diagonal"),
                        model.particle_mass,
                        self.mass_eff,
                        self.fixed,
                        self.filters,
                        self.diag_block,
                        self.qd_free,
                        state_out.particle_qd,
                    ],
                    outputs=[self.x, self.rhs, self.precond, self.qd_k, self.ap, self.scalars],
                    device=model.device,
                )
            self._solve(constrained=True)
            self._update(h, state_in, self.qd_k, state_out, False)
            # Then Newton iterations at the result, which take the springs' nonlinearity into
            # account (an impact can turn the jelly by ~0.1 rad in one step).
            for _ in range(self.newton_iterations):
                self._newton_iteration(h, state_in, state_out, False, False, False)
            self._measure_bodies(h, state_in, state_out)

            # A contact solve should only remove energy from the free result. One linearisation
            # can miss that when an impact turns a stiff jelly quickly (jelly_drop at ks = 1e5 gained
            # 2.6 J in one step after a corner bounce); another Newton iteration, only then, fixes it.
            def extra_iteration():
                self._newton_iteration(h, state_in, state_out, False, False, False)
                self._measure_bodies(h, state_in, state_out)

            for _ in range(EXTRA_CONTACT_ITERATIONS):
                wp.capture_if(self.energy_gained, extra_iteration)
            self._apply_restitution(state_out)

        # Skipped on the device when nothing touched (a conditional graph node on CUDA).
        wp.capture_if(self.any_contact, constrained_iterations)

    def _measure_bodies(self, h, state_in: State, state_out: State):
        """Per body: the energy the contact solve removed from the free result, momentum, restitution impulse.

        Sets ``energy_gained`` when some body ended the contact solve with more energy than the
        free result, beyond the CG tolerance's share of its kinetic energy.
        """
        model = self.model
        device = model.device
        eval_forces(model, state_out.particle_q, state_out.particle_qd, self.f, self.run.forces)
        self.body_data.zero_()
        self.energy_gained.zero_()
        wp.launch(
            implicit_kernels.measure_particle_restitution,
            dim=model.particle_count,
            inputs=[
                h,
                self.particle_body,
                self.body_reference,
                model.particle_mass,
                self.fixed,
                model.gravity,
                state_in.particle_qd,
                self.q_free,
                self.qd_free,
                state_out.particle_q,
                state_out.particle_qd,
                self.f,
                self.contact_restitution,
                self.contact_approach,
            ],
            outputs=[self.body_data],
            device=device,
        )
        if model.spring_count:
            wp.launch(
                implicit_kernels.measure_spring_restitution,
                dim=model.spring_count,
                inputs=[
                    self.particle_body,
                    model.spring_indices,
                    model.spring_rest_length,
                    model.spring_stiffness,
                    self.q_free,
                    state_out.particle_q,
                ],
                outputs=[self.body_data],
                device=device,
            )
        wp.launch(
            implicit_kernels.check_energy_budget,
            dim=self.body_data.shape[0],
            inputs=[model.scalar(self.cg_tolerance), self.body_data],
            outputs=[self.energy_gained],
            device=device,
        )

    def _apply_restitution(self, state_out: State):
        """Poisson's restitution for each body that collided in this step, as one common velocity change.

        The contact solve stopped the colliding particles (the compression phase of the impact).
        Per body, the restitution impulse is the sum of e_i times each colliding particle's contact
        impulse (the residual of the backward Euler equation on it), along the approach-weighted
        contact normal; it is given to every particle of the body alike, which strains no spring.
        It is capped by the energy the contact solve removed from the free result, so the step
        never ends above the free step's energy (see kernels/implicit.py: apply_restitution).
        """
        model = self.model
        wp.launch(
            implicit_kernels.apply_restitution,
            dim=model.particle_count,
            inputs=[
                self.particle_body,
                self.body_reference,
                self.fixed,
                self.body_mass,
                self.body_data,
                state_out.particle_q,
            ],
            outputs=[state_out.particle_qd],
            device=model.device,
        )

    def _record_step(self):
        model = self.model
        device = model.device
        if self.solver == "warp_cg" and not (device.is_cuda or device.is_capturing):
            self._host_stats[implicit_kernels.TOTAL_ITERS] += self._host_stats[implicit_kernels.STEP_ITERS]
            self._host_stats[implicit_kernels.MAX_ITERS] = max(self._host_stats[implicit_kernels.MAX_ITERS], self._host_stats[implicit_kernels.STEP_ITERS])
            self._host_stats[implicit_kernels.STEPS] += 1
            self._host_stats[implicit_kernels.STEP_ITERS] = 0
        else:
            wp.launch(implicit_kernels.record_step, dim=1, inputs=[], outputs=[self.stats_array], device=device)

    # -- statistics -----------------------------------------------------------------------------

    def reset_stats(self):
        """Forget the CG iteration counts so far (e.g. those of a warm-up step)."""
        self.stats_array.zero_()
        self.residual_stats.zero_()
        self._host_stats[:] = 0

    def stats(self) -> dict:
        """CG iterations per step (summed over all solves of a step), for the metrics summary."""
        a = self.stats_array.numpy().astype(np.int64) + self._host_stats
        res = self.residual_stats.numpy().astype(np.float64)
        steps = int(a[implicit_kernels.STEPS])
        return {
            "newton_iterations": self.newton_iterations,
            "linearization": self.linearization,
            "cg_tolerance": self.cg_tolerance,
            "cg_max_iterations": self.cg_max_iterations,
            "cg_preconditioner": self.preconditioner,
            "cg_preconditioner_note": self.preconditioner_note,
            **(self.multigrid.stats() if self.multigrid is not None else {}),
            "cg_solver": self.solver,
            "cg_steps": steps,
            "cg_iterations_mean": float(a[implicit_kernels.TOTAL_ITERS]) / steps if steps else 0.0,
            "cg_iterations_max": int(a[implicit_kernels.MAX_ITERS]),
            "cg_solves": int(a[implicit_kernels.SOLVES]),
            "cg_unconverged_solves": int(a[implicit_kernels.UNCONVERGED]),
            # Final |r| / max(|b|, |b_1|) of the solves (this module's loop; not warp_cg's).
            "cg_relative_residual_max": float(res[0]),
            "cg_relative_residual_mean": float(res[1]) / int(a[implicit_kernels.SOLVES]) if a[implicit_kernels.SOLVES] else 0.0,
        }

    def profile_notes(self) -> list[str]:
        if self.solver == "warp_cg":
            return ["warp_cg: warp.optim.linear.cg's products, preconditioner and updates are one part, warp_cg_solve"]
        if self.multigrid is None:
            return [f"the {self.preconditioner} preconditioner is applied inside init_residual and cg_update: its "
                    "time is part of cg_vector_update"]
        return []
