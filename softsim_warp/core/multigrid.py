"""Geometric multigrid preconditioner for the implicit solve of a lattice jelly.

The implicit integrator (``core/implicit.py``) solves ``A dv = b`` by conjugate gradient, with A
the 3x3-block system of the springs, filtered by contact and pin constraints. Block-Jacobi, its
default preconditioner for general spring sets, leaves the long-wave part of the error to CG, so
the iterations grow with the jelly's resolution. On a lattice jelly this class applies one
V-cycle instead: coarse lattices (each axis halved, odd and even sizes alike) with Galerkin
coarse operators, damped block-Jacobi smoothing and an exact solve on the coarsest (at most 2 x 2
x 2) lattice. The method, and why each piece is what it is, is in ``kernels/multigrid.py``; the
measurements in docs/IMPLICIT.md.

Everything runs on the device without host reads: :meth:`LatticeMultigrid.jacobians` (the
system's spring part, from the linearisation point: no spring blocks are stored),
:meth:`setup` (before each linear solve: builds the hierarchy, or keeps the last one),
:meth:`product` and :meth:`apply` (once per CG iteration) only launch kernels, so all are
captured into the step's graph and the CG loop's ``wp.capture_while`` body.

Which models qualify (:func:`multigrid_support`): one jelly that is the whole model, on the
lattice path (its springs are the standard stencil). Everything else (several jellies or worlds,
loose particles, custom spring lists) keeps block-Jacobi.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import lattice
from ..kernels import implicit as implicit_kernels
from ..kernels import multigrid as multigrid_kernels
from ..kernels.lattice import REST_SLOTS

# Damping of the block-Jacobi sweeps, on the jelly's lattice and on the coarse levels. The fine
# level's D^-1 A has its spectrum in (0, 2] (each spring block B satisfies (u_a - u_b)^T B
# (u_a - u_b) <= 2 (u_a^T B u_a + u_b^T B u_b)); measured 1.73 on the stiff jelly. The Galerkin
# levels' reach 3.2 (tests/test_multigrid.py). omega lambda_max stays at most 1.6 on every level,
# so every sweep converges, which the V-cycle needs to be SPD.
DEFAULT_OMEGA = 0.8
DEFAULT_COARSE_OMEGA = 0.5
# Sweeps before and after the coarse correction on the first coarse level, and on the levels below
# it, where they cost little: a second deep sweep saves more CG iterations than it costs on large
# jellies (docs/IMPLICIT.md has the measured iterations and step times).
DEFAULT_SWEEPS = 1
DEFAULT_DEEP_SWEEPS = 2
# Free solves per hierarchy build (LatticeMultigrid.setup): a kept hierarchy is still a fixed SPD
# preconditioner, and rebuilding less often costs fewer builds than the CG iterations it adds
# (docs/IMPLICIT.md).
DEFAULT_SETUP_EVERY = 8
# Particles from which the default ("auto") preconditioner is multigrid: below these sizes
# block-Jacobi's cheaper iterations win, on the CPU and on CUDA (docs/IMPLICIT.md).
AUTO_MIN_PARTICLES = 12**3
AUTO_MIN_PARTICLES_CUDA = 20**3
# Coarse levels of at most this many nodes take their stencil products with LANES threads per node
# on CUDA (kernels/multigrid.py: mg_stencil_op_lanes), where one thread per node is bound by the
# latency of its 26 block loads (docs/IMPLICIT.md; benchmarks/bench_multigrid_kernels.py).
LANES_MAX_NODES = 14**3
LANES = 32


def auto_min_particles(device) -> int:
    """Particles from which "auto" takes multigrid on ``device``."""
    return AUTO_MIN_PARTICLES_CUDA if device.is_cuda else AUTO_MIN_PARTICLES


def multigrid_support(model) -> tuple[bool, str]:
    """Whether the multigrid preconditioner applies to ``model``, and why not when it does not."""
    lat = model.lattice
    if lat is None:
        return False, f"not a lattice model ({model.lattice_reason})"
    if lat.jelly_count != 1:
        return False, f"{lat.jelly_count} jellies (multigrid handles one jelly)"
    shape = lat.layout.shape[0]
    if int(lat.layout.start[0]) != 0 or int(np.prod(shape)) != model.particle_count:
        return False, "particles outside the jelly"
    return True, "lattice"


def level_shapes(shape) -> list[tuple[int, int, int]]:
    """Lattice shapes of the hierarchy, from the jelly's down to the coarsest (every axis <= 2)."""
    shapes = [tuple(int(n) for n in shape)]
    while max(shapes[-1]) > 2:
        shapes.append(tuple(multigrid_kernels.coarse_size(n) for n in shapes[-1]))
    return shapes


class LatticeMultigrid:
    """A V-cycle for the implicit system of a one-jelly lattice model.

    Args:
        model: the model (``multigrid_support`` must hold).
        system: the arrays of the implicit system it reads: ``filters`` and ``mass_eff`` (see
            ``kernels/implicit.py``), as attributes of an object (the integrator). The spring
            blocks are recomputed from the linearisation point that :meth:`jacobians` keeps.
        omega: damping of the block-Jacobi sweeps on the jelly's lattice.
        coarse_omega: the same on the coarse levels.
        sweeps: pre- and post-smoothing sweeps on the first coarse level (the jelly's lattice
            joins additively, with no sweep of its own).
        deep_sweeps: the same on the levels below the first (None: DEFAULT_DEEP_SWEEPS).
        setup_every: free solves per hierarchy build (None: DEFAULT_SETUP_EVERY).
        gather: the spring blocks recomputed from positions (None: on CUDA) or stored per spring.
        lanes: the products of levels of at most LANES_MAX_NODES nodes with a block of threads per
            node (None: on CUDA; on the CPU a block is one thread, and the same kernel runs there).
    """

    def __init__(
        self,
        model,
        system,
        omega: float = DEFAULT_OMEGA,
        coarse_omega: float = DEFAULT_COARSE_OMEGA,
        sweeps: int = DEFAULT_SWEEPS,
        deep_sweeps: int | None = None,
        setup_every: int | None = None,
        gather: bool | None = None,
        lanes: bool | None = None,
    ):
        ok, reason = multigrid_support(model)
        if not ok:
            raise ValueError(f"multigrid does not apply: {reason}")
        for name, value in (("omega", omega), ("coarse_omega", coarse_omega)):
            if not 0.0 < value < 1.0:
                raise ValueError(f"{name} must be in (0, 1) (got {value!r})")
        deep_sweeps = DEFAULT_DEEP_SWEEPS if deep_sweeps is None else deep_sweeps
        for name, value in (("sweeps", sweeps), ("deep_sweeps", deep_sweeps)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1 (got {value!r})")
        self.deep_sweeps = int(deep_sweeps)
        self.model = model
        self.system = system
        self.omega = model.scalar(omega)
        self.coarse_omega = model.scalar(coarse_omega)
        self.sweeps = int(sweeps)
        setup_every = DEFAULT_SETUP_EVERY if setup_every is None else setup_every
        if int(setup_every) != setup_every or setup_every < 1:
            raise ValueError(f"setup_every must be an integer >= 1 (got {setup_every!r})")
        self.setup_every = int(setup_every)
        # The spring blocks recomputed from positions by one thread per particle (CUDA), or stored
        # per spring and summed with atomics (the CPU, where Warp runs the threads one after
        # another and recomputing each block from both ends costs more: docs/IMPLICIT.md).
        self.gather = model.device.is_cuda if gather is None else bool(gather)
        self.lanes = model.device.is_cuda if lanes is None else bool(lanes)
        self.lane_width = LANES if model.device.is_cuda else 1
        if not self.gather and system.spring_block.shape[0] != model.spring_count:
            raise ValueError("gather=False needs the integrator's spring_block for every spring")
        device = model.device
        scalar, vec3 = model.scalar, model.vec3
        mat33 = wp.types.matrix((3, 3), scalar)
        layout = model.lattice.layout
        self.shapes = level_shapes(layout.shape[0])
        self.fine_shape = wp.vec3i(*self.shapes[0])
        n = model.particle_count
        # Level 0: smoother inverses, the split operator's stencil, and the V-cycle's vectors.
        self.dinv0 = wp.zeros(n, dtype=mat33, device=device)
        self.a0 = wp.zeros((multigrid_kernels.STENCIL, n), dtype=mat33, device=device) if len(self.shapes) > 1 else None
        self.rowsum0 = wp.zeros(n, dtype=mat33, device=device)
        self.x0 = wp.zeros(n, dtype=vec3, device=device)
        # A lattice of at most 2x2x2 has no coarse level and builds no stencil (mg_fine_setup_lattice writes here).
        self.dummy_stencil = wp.zeros((multigrid_kernels.STENCIL, n if self.a0 is None else 1), dtype=mat33, device=device)
        self.y0 = wp.zeros(n, dtype=vec3, device=device)
        # The linearisation point of the system (written by jacobians()): the products and the
        # setup recompute the spring blocks from it.
        self.q_lin = wp.zeros(n, dtype=vec3, device=device)
        self.h = scalar(0.0)
        lat = model.lattice
        self.types = int(layout.types[0])
        # The jelly's tables by value (kernels/multigrid.py: rest_vec): rest length per stencil
        # offset, ks and kd per spring type.
        rest_vec = wp.types.vector(REST_SLOTS, scalar)
        self.tables = [
            rest_vec(*(float(v) for v in layout.rest[0])),
            vec3(*(float(v) for v in layout.ks[0])),
            vec3(*(float(v) for v in layout.kd[0])),
        ]
        self.table_arrays = [lat.jelly_rest, lat.jelly_ks, lat.jelly_kd]
        # Lagged setup (setup_every > 1): [solves since the last build, hierarchy stale] and the
        # build flag, on the device.
        self.setup_state = wp.array([0, 1], dtype=wp.int32, device=device)
        self.setup_flag = wp.zeros(1, dtype=wp.int32, device=device)
        self.scratch = wp.zeros(1, dtype=scalar, device=device)
        # Coarse levels 1..L: stencils, inverses of their diagonal blocks, b, x, and a sweep's output.
        self.levels = []
        for shape in self.shapes[1:]:
            count = int(np.prod(shape))
            self.levels.append(
                {
                    "shape": wp.vec3i(*shape),
                    "count": count,
                    "a": wp.zeros((multigrid_kernels.STENCIL, count), dtype=mat33, device=device),
                    "dinv": wp.zeros(count, dtype=mat33, device=device),
                    "rowsum": wp.zeros(count, dtype=mat33, device=device),
                    "b": wp.zeros(count, dtype=vec3, device=device),
                    "x": wp.zeros(count, dtype=vec3, device=device),
                    "t": wp.zeros(count, dtype=vec3, device=device),
                }
            )
        coarsest = self.levels[-1]["count"] if self.levels else 0
        # The coarsest factorisation is float64 in either precision (kernels/multigrid.py: mg_coarse_factor).
        self.chol = wp.zeros((3 * coarsest, 3 * coarsest), dtype=wp.float64, device=device)
        self.coarse_inv = wp.zeros((3 * coarsest, 3 * coarsest), dtype=wp.float64, device=device)

    @property
    def level_count(self) -> int:
        """Levels, the jelly's lattice included."""
        return len(self.shapes)

    def nbytes(self) -> int:
        """Bytes of the device arrays held here."""
        arrays = [self.dinv0, self.rowsum0, self.x0, self.y0, self.q_lin, self.chol, self.coarse_inv] + ([self.a0] if self.a0 is not None else [])
        for lv in self.levels:
            arrays += [lv["a"], lv["dinv"], lv["rowsum"], lv["b"], lv["x"], lv["t"]]
        return sum(a.capacity for a in arrays)

    def jacobians(self, h, kv_scale, q: wp.array, qd_k: wp.array, diag_out: wp.array, rhs_out: wp.array):
        """The system's spring part at the linearisation point q, kept for :meth:`product` and :meth:`setup`.

        Writes each particle's sum of spring blocks into ``diag_out`` and ``kv_scale`` df/dx qd_k
        into ``rhs_out``. With ``gather`` every element is written and no spring block is stored;
        without, ``eval_spring_jacobians`` adds them (both zeroed by the caller) and stores the
        blocks in the integrator's ``spring_block``.
        """
        model = self.model
        self.h = model.scalar(h)
        if not self.gather:
            wp.copy(self.q_lin, q)
            wp.launch(
                implicit_kernels.eval_spring_jacobians,
                dim=model.spring_count,
                inputs=[self.h, model.scalar(kv_scale), model.spring_indices, model.spring_rest_length,
                        model.spring_stiffness, model.spring_damping, q, qd_k],
                outputs=[self.system.spring_block, diag_out, rhs_out],
                device=model.device,
            )
            return
        wp.launch(
            multigrid_kernels.mg_lattice_jacobians,
            dim=model.particle_count,
            inputs=[self.h, model.scalar(kv_scale), self.fine_shape, self.types, *self.tables, q, qd_k],
            outputs=[diag_out, rhs_out, self.q_lin],
            device=model.device,
        )

    def product(self, p: wp.array, y: wp.array, scalars: wp.array, slot: int):
        """y = A p (mass and springs, every element written) by the gather; scalars[slot] += p.A p."""
        model = self.model
        n = model.particle_count
        wp.launch(
            multigrid_kernels.mg_lattice_mv,
            dim=(implicit_kernels.tile_blocks(n), implicit_kernels.TILE),
            block_dim=implicit_kernels.TILE,
            inputs=[n, slot, self.h, self.fine_shape, self.types, *self.tables, self.q_lin,
                    self.system.mass_eff, p],
            outputs=[y, scalars],
            device=model.device,
        )

    def setup(self, constrained: bool = False):
        """Build the hierarchy for the current system, or keep the last one (``setup_every``).

        With ``setup_every`` = k > 1 the hierarchy of free solves is rebuilt every k-th solve
        (decided on the device); a solve with contact constraints (``constrained``) always
        rebuilds, and so does the free solve after it. A kept hierarchy is a fixed SPD
        preconditioner for the solve, so CG converges to the same tolerance.
        """
        if self.setup_every == 1:
            self.build()
            return
        wp.launch(
            multigrid_kernels.mg_setup_due,
            dim=1,
            inputs=[self.setup_every, int(constrained)],
            outputs=[self.setup_state, self.setup_flag],
            device=self.model.device,
        )
        wp.capture_if(self.setup_flag, self.build)

    def build(self):
        """Build the hierarchy for the current system (its linearisation point, filters, masses)."""
        model = self.model
        device = model.device
        s = self.system
        fine_shape = self.fine_shape
        fine_out = [self.a0 if self.a0 is not None else self.dummy_stencil, self.rowsum0, self.dinv0]
        wp.launch(
            multigrid_kernels.mg_fine_setup_lattice,
            dim=model.particle_count,
            inputs=[self.h, fine_shape, self.types, *self.table_arrays, self.q_lin, s.mass_eff, s.filters],
            outputs=fine_out,
            device=device,
        )
        if not self.levels:
            return
        below_shape, below_a, below_rowsum = fine_shape, self.a0, self.rowsum0
        for lv in self.levels:
            wp.launch(
                multigrid_kernels.mg_galerkin,
                dim=(multigrid_kernels.HALF, lv["count"]),
                inputs=[below_shape, lv["shape"], below_a, below_rowsum],
                outputs=[lv["a"], lv["rowsum"], lv["dinv"]],
                device=device,
            )
            below_shape, below_a, below_rowsum = lv["shape"], lv["a"], lv["rowsum"]
        last = self.levels[-1]
        wp.launch(
            multigrid_kernels.mg_coarse_factor, dim=1, inputs=[last["shape"], last["a"], last["rowsum"]], outputs=[self.chol],
            device=device,
        )
        wp.launch(multigrid_kernels.mg_coarse_inverse, dim=self.chol.shape[0], inputs=[self.chol], outputs=[self.coarse_inv], device=device)

    def apply(self, r: wp.array, z: wp.array, scalars: wp.array, slot: int):
        """z = V-cycle(r) for a filtered residual r; adds r.z to ``scalars[slot]``."""
        model = self.model
        device = model.device
        s = self.system
        n = model.particle_count
        omega = self.omega
        if not self.levels:
            # A lattice of at most 2 x 2 x 2: two block-Jacobi sweeps.
            wp.launch(multigrid_kernels.mg_fine_pre, dim=n, inputs=[omega, s.mass_eff, self.dinv0, r], outputs=[self.x0, self.y0],
                      device=device)
            self._spring_product(self.x0)
            self._fine_post(r, z, scalars, slot)
            return
        # The jelly's lattice joins additively: z = omega D^-1 r + S P V(P^T r), no spring product
        # on the lattice (docs/IMPLICIT.md).
        fine_shape = self.fine_shape
        first = self.levels[0]
        # Each restriction also takes the level's first sweep from zero (x = omega D^-1 b).
        self._restrict(fine_shape, r, first)
        # Coarse levels, down: the other sweeps, residual, restriction.
        for index, lv in enumerate(self.levels[:-1]):
            self._smooth(lv, first=1)
            self._stencil_op(lv, 0, lv["x"], lv["t"])
            self._restrict(lv["shape"], lv["t"], self.levels[index + 1])
        last = self.levels[-1]
        width = self.lane_width if self.lanes else 1
        wp.launch(
            multigrid_kernels.mg_coarse_solve,
            dim=(last["count"], width),
            block_dim=width,
            inputs=[width, last["shape"], self.coarse_inv, last["b"]],
            outputs=[last["x"]],
            device=device,
        )
        # Up: prolongate the correction, then the same sweeps again (a symmetric cycle). A level
        # whose products run in lanes takes the prolongation into its first sweep.
        for index in range(len(self.levels) - 2, -1, -1):
            lv, below = self.levels[index], self.levels[index + 1]
            if self._lanes(lv):
                self._stencil_op(lv, 2, lv["x"], lv["t"], below)
                lv["x"], lv["t"] = lv["t"], lv["x"]
                self._smooth(lv, first=1)
            else:
                wp.launch(
                    multigrid_kernels.mg_prolong, dim=lv["count"], inputs=[lv["shape"], below["shape"], below["x"]],
                    outputs=[lv["x"]], device=device,
                )
                self._smooth(lv, first=0)
        wp.launch(
            multigrid_kernels.mg_fine_additive,
            dim=(implicit_kernels.tile_blocks(n), implicit_kernels.TILE),
            block_dim=implicit_kernels.TILE,
            inputs=[n, slot, omega, fine_shape, first["shape"], s.filters, self.dinv0, r, first["x"]],
            outputs=[z, scalars],
            device=device,
        )

    # -- pieces ---------------------------------------------------------------------------------

    def _spring_product(self, x):
        """y0 = A x, y0 holding M x."""
        model = self.model
        if self.gather:
            self.product(x, self.y0, self.scratch, 0)
        elif model.spring_count:
            wp.launch(
                implicit_kernels.spring_mv,
                dim=(implicit_kernels.tile_blocks(model.spring_count), implicit_kernels.TILE),
                block_dim=implicit_kernels.TILE,
                inputs=[model.spring_count, -1, model.spring_indices, self.system.spring_block, x],
                outputs=[self.y0, self.scratch],
                device=model.device,
            )

    def _fine_post(self, r, z, scalars, slot):
        n = self.model.particle_count
        omega = self.omega
        wp.launch(
            multigrid_kernels.mg_fine_post,
            dim=(implicit_kernels.tile_blocks(n), implicit_kernels.TILE),
            block_dim=implicit_kernels.TILE,
            inputs=[n, slot, omega, self.system.filters, self.dinv0, r, self.x0, self.y0],
            outputs=[z, scalars],
            device=self.model.device,
        )

    def _restrict(self, shape, r, below):
        """below["b"] = R r, and the first sweep from zero on that level into below["x"]."""
        wp.launch(
            multigrid_kernels.mg_restrict,
            dim=below["count"],
            inputs=[shape, below["shape"], r, self.coarse_omega, below["dinv"]],
            outputs=[below["b"], below["x"]],
            device=self.model.device,
        )

    def _lanes(self, lv) -> bool:
        """Whether a coarse level's products run with LANES threads per node (small levels on CUDA)."""
        return self.lanes and lv["count"] <= LANES_MAX_NODES

    def _stencil_op(self, lv, mode: int, x, y, below=None):
        """On a coarse level, x into y: mode 0 the residual, 1 a sweep, 2 (lanes only) a sweep from
        x + P e, e the correction of the level ``below``."""
        device = self.model.device
        args = [mode, self.coarse_omega, lv["shape"], lv["a"], lv["rowsum"], lv["dinv"], lv["b"], x]
        if self._lanes(lv):
            coarse = [below["shape"], below["x"]] if below is not None else [lv["shape"], x]
            wp.launch(
                multigrid_kernels.mg_stencil_op_lanes, dim=(lv["count"], self.lane_width), block_dim=self.lane_width,
                inputs=[self.lane_width, *args, *coarse],
                outputs=[y], device=device,
            )
        else:
            wp.launch(multigrid_kernels.mg_stencil_op, dim=lv["count"], inputs=args, outputs=[y], device=device)

    def _smooth(self, lv, first: int):
        """Sweeps ``first`` .. of damped block-Jacobi on a coarse level (``sweeps`` on the first
        coarse level, ``deep_sweeps`` below it; sweep 0 from zero is the restriction's); the result
        is in lv["x"]."""
        sweeps = self.sweeps if lv is self.levels[0] else self.deep_sweeps
        for _ in range(first, sweeps):
            self._stencil_op(lv, 1, lv["x"], lv["t"])
            lv["x"], lv["t"] = lv["t"], lv["x"]

    def stats(self) -> dict:
        """The hierarchy, for the metrics summary."""
        return {
            "multigrid_levels": self.level_count,
            "multigrid_shapes": ["x".join(str(n) for n in shape) for shape in self.shapes],
            "multigrid_omega": float(self.omega),
            "multigrid_coarse_omega": float(self.coarse_omega),
            "multigrid_sweeps": self.sweeps,
            "multigrid_deep_sweeps": self.deep_sweeps,
            "multigrid_setup_every": self.setup_every,
            "multigrid_gather": self.gather,
        }
