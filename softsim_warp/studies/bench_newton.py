"""Peer benchmark: the same mass-spring jelly stepped by Newton's ``SolverSemiImplicit``.

Newton (``pip install 'softsim-warp[bench]'``, Newton 1.8 on warp-lang 1.19) is imported lazily,
so this module imports without it. Everything is built from the same NumPy arrays our jelly uses.

Model-building recipe (Newton 1.8). ``ModelBuilder.add_spring`` is a Python loop that computes
each rest length with NumPy, far too slow for 10^6 particles, so the builder's per-particle and
per-spring lists are replaced wholesale by NumPy arrays before ``finalize`` (which accepts arrays:
it passes them to ``wp.array`` and validates them with ``np.asarray``):

* ``ModelBuilder(up_axis=newton.Axis.Y, gravity=g)``; ``add_ground_plane(height=ground_y, cfg=...)``
  is the plane ``y = ground_y`` (a static shape, ``body=-1``) with normal +y.
* ``builder.particle_q`` (N,3) f32, ``particle_qd`` (N,3) f32, ``particle_mass`` (N,) f32,
  ``particle_radius`` (N,) f32, ``particle_flags`` (N,) i32 = ``ParticleFlags.ACTIVE``,
  ``particle_world`` (N,) i32 = ``builder.current_world`` (-1: global, as ``add_particles`` does).
* ``builder.spring_indices`` (2S,) i32 flattened pairs, ``spring_rest_length``,
  ``spring_stiffness``, ``spring_damping``, ``spring_control`` (S,) f32 (control is unused by
  the semi-implicit solver).
* After ``finalize``: ``model.particle_grid = None`` (no particle self-contact; with radius 0 the
  builder already leaves it ``None``), ``model.set_gravity(g)``, and the soft-contact material
  ``model.soft_contact_ke/kd/kf/mu``.

Stepping, as in Newton's own examples::

    state_0.clear_forces()
    pipeline.collide(state_0, contacts)      # newton.CollisionPipeline(model), pipeline.contacts()
    solver.step(state_0, state_1, control, contacts, dt)
    state_0, state_1 = state_1, state_0

``SolverSemiImplicit.step(state_in, state_out, control, contacts, dt)`` has no ground of its own:
particle-ground contact comes only from the soft contacts (particle-shape pairs) that the
collision pipeline writes into ``contacts``; with ``contacts=None`` the jelly falls through the
plane. A soft contact is generated when a particle is within ``radius + soft_contact_gap`` of the
plane, so ``collide`` must run every step unless the gap covers the whole motion (see
``collide_every_step``).

Physics equivalence with our jelly:

* Springs (``eval_spring`` in ``newton/_src/solvers/semi_implicit/kernels_particle.py``): with
  ``d = x_i - x_j``, ``l = |d|``, ``d^ = d / l``, Newton applies to particle i
  ``f_i = -(ke (l - rest) + kd ((v_i - v_j) . d^)) d^`` and ``f_j = -f_i``: exactly our
  ``spring_force`` (``kernels/springs.py``). ``spring_stiffness`` is our ks [N/m] and
  ``spring_damping`` our kd [N s/m], passed through unscaled: no division by rest length or mass,
  no per-spring normalisation (``spring_control`` is not read). Newton has no guard for
  coincident particles (l = 0 gives NaN), ours returns zero; a lattice never hits it.
* Integration (``integrate_particles`` in ``newton/_src/solvers/solver.py``): symplectic Euler,
  ``v1 = v0 + (f/m + g) dt``, ``x1 = x0 + v1 dt``, gravity for particles with inverse mass > 0,
  speed clamped to ``model.particle_max_velocity`` (1e5 m/s, never reached here). Same as our
  ``symplectic`` stage.
* Ground: the one real difference. Newton's semi-implicit contact is a penalty spring-damper
  (``eval_particle_body_contact``): with ``c = n.(x - p) - radius < 0``, normal force
  ``-(c ke + min(v_n, 0) kd) n`` plus smooth Coulomb friction ``min(kf |v_t|, mu |c ke|)``;
  ke, kd, kf, mu are the averages of ``model.soft_contact_*`` and the plane's ``ShapeConfig``
  (both are set to the same value here, so the average is that value). Ours is an impulse
  (projection + restitution + Coulomb) applied after the step. The two agree on free fall and
  on the jelly coming to rest on the plane, not contact-by-contact; contact is a per-particle
  O(N) kernel in both and does not decide the step cost, which the S >> N springs dominate.
"""

from __future__ import annotations

import time

import numpy as np

_MISSING = "Newton is not installed: pip install 'softsim-warp[bench]'"


def _import_newton():
    try:
        import newton
        import newton.solvers
    except ImportError as exc:
        raise RuntimeError(_MISSING) from exc
    return newton


def newton_version():
    """Installed Newton version string; raises RuntimeError when Newton is missing."""
    newton = _import_newton()
    return str(getattr(newton, "__version__", "unknown"))


def _per_spring(value, count, name):
    arr = np.asarray(value, dtype=np.float32)
    if arr.ndim == 0:
        return np.full(count, arr, dtype=np.float32)
    if arr.shape != (count,):
        raise ValueError(f"{name} must be a scalar or have shape ({count},), got {arr.shape}")
    return np.ascontiguousarray(arr)


class NewtonJelly:
    """A mass-spring jelly on a ground plane ``y = ground_y``, built and stepped by Newton.

    Args:
        points: (N, 3) rest positions [m] (also the initial positions).
        pairs: (S, 2) spring particle indices.
        rest, ks, kd: (S,) rest lengths [m], stiffness [N/m], damping [N s/m] (scalars broadcast).
        masses: (N,) particle masses [kg].
        gravity: gravity vector [m/s^2], e.g. (0, -9.81, 0).
        ground_y: height of the ground plane [m]; y is up.
        device: Warp device ("cpu", "cuda:0", ...).
        velocities: optional (N, 3) initial velocities [m/s].
        contact_ke, contact_kd, contact_kf, contact_mu: Newton's penalty ground contact: normal
            stiffness [N/m], normal damping [N s/m], friction gain [N s/m], Coulomb coefficient.
        particle_radius: contact radius [m]; 0 makes particle centres touch the plane.
        soft_contact_gap: extra detection distance [m] of the collision pipeline.
        collide_every_step: run the collision pipeline every step (Newton's usual loop). When
            False, contacts are generated once with a gap covering the whole scene: for a static
            plane that is exact, because the contact force is evaluated from the current
            positions against the plane every step; only the pair list is reused.
        solver: ``"semi_implicit"`` (``SolverSemiImplicit``) or ``"vbd"`` (``SolverVBD``, Newton's
            implicit Euler solver for stiff particle systems: vertex block descent, ``vbd_iterations``
            Gauss-Seidel sweeps over ``color_groups`` per step; see :func:`lattice_coloring`).
        ground_y: None for no ground (free flight: no collision pipeline, contacts None).
    """

    def __init__(
        self,
        points,
        pairs,
        rest,
        ks,
        kd,
        masses,
        gravity,
        ground_y,
        device="cpu",
        *,
        velocities=None,
        contact_ke=1.0e3,
        contact_kd=5.0,
        contact_kf=10.0,
        contact_mu=0.5,
        particle_radius=0.0,
        soft_contact_gap=0.01,
        collide_every_step=True,
        solver="semi_implicit",
        vbd_iterations=10,
        color_groups=None,
    ):
        newton = _import_newton()
        import warp as wp

        self.wp = wp
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        pairs = np.asarray(pairs, dtype=np.int32).reshape(-1, 2)
        n, s = points.shape[0], pairs.shape[0]
        masses = np.asarray(masses, dtype=np.float32)
        if masses.ndim == 0:
            masses = np.full(n, masses, dtype=np.float32)
        if masses.shape != (n,):
            raise ValueError(f"masses must have shape ({n},), got {masses.shape}")
        gravity = tuple(float(c) for c in np.asarray(gravity, dtype=np.float64).reshape(3))
        self.device = wp.get_device(device)

        if solver not in ("semi_implicit", "vbd"):
            raise ValueError(f"solver must be semi_implicit or vbd (got {solver!r})")
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=gravity)
        shape_cfg = newton.ModelBuilder.ShapeConfig(ke=contact_ke, kd=contact_kd, kf=contact_kf, mu=contact_mu)
        if ground_y is not None:
            builder.add_ground_plane(height=float(ground_y), cfg=shape_cfg)

        # Bulk fill: NumPy arrays in place of the builder's Python lists.
        builder.particle_q = points
        builder.particle_qd = (
            np.zeros_like(points) if velocities is None else np.asarray(velocities, np.float32).reshape(n, 3)
        )
        builder.particle_mass = masses
        builder.particle_radius = np.full(n, particle_radius, dtype=np.float32)
        builder.particle_flags = np.full(n, int(newton.ParticleFlags.ACTIVE), dtype=np.int32)
        builder.particle_world = np.full(n, builder.current_world, dtype=np.int32)
        builder.spring_indices = np.ascontiguousarray(pairs.ravel())
        builder.spring_rest_length = _per_spring(rest, s, "rest")
        builder.spring_stiffness = _per_spring(ks, s, "ks")
        builder.spring_damping = _per_spring(kd, s, "kd")
        builder.spring_control = np.zeros(s, dtype=np.float32)
        if solver == "vbd":
            builder.set_coloring(color_groups)

        model = builder.finalize(device=self.device)
        model.particle_grid = None  # no particle-particle (self) contact
        model.set_gravity(gravity)
        model.soft_contact_ke = float(contact_ke)
        model.soft_contact_kd = float(contact_kd)
        model.soft_contact_kf = float(contact_kf)
        model.soft_contact_mu = float(contact_mu)

        if not collide_every_step and ground_y is not None:
            # One detection pass must see every particle-plane pair for the whole run.
            extent = float(np.ptp(points, axis=0).max()) if n else 0.0
            height = float(points[:, 1].max() - ground_y) if n else 0.0
            soft_contact_gap = max(soft_contact_gap, 10.0 * (extent + abs(height)) + 1.0)

        self.newton = newton
        self.model = model
        if solver == "vbd":
            self.solver = newton.solvers.SolverVBD(model, iterations=int(vbd_iterations))
        else:
            self.solver = newton.solvers.SolverSemiImplicit(model)
        self.pipeline, self.contacts = None, None
        if ground_y is not None:
            self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=soft_contact_gap)
            self.contacts = self.pipeline.contacts()
        self.state_0 = model.state()
        self.state_1 = model.state()
        self.control = model.control()
        self.collide_every_step = collide_every_step and self.pipeline is not None
        if self.pipeline is not None and not collide_every_step:
            self.pipeline.collide(self.state_0, self.contacts)

    def step(self, dt, count=1):
        """Advance ``count`` steps of ``dt``; states swap after each step, as in Newton's examples."""
        for _ in range(count):
            self.state_0.clear_forces()
            if self.collide_every_step:
                self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, dt)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def capture(self, dt, count):
        """Capture ``count`` steps (rounded up to even, so the swapped states end where they began)."""
        count = max(2, count + (count % 2))
        with self.wp.ScopedCapture(device=self.device) as capture:
            self.step(dt, count)
        return capture.graph, count

    def positions(self):
        return self.state_0.particle_q.numpy()

    def velocities(self):
        return self.state_0.particle_qd.numpy()


def newton_steps_per_second(
    points,
    pairs,
    rest,
    ks,
    kd,
    masses,
    dt,
    gravity,
    ground_y,
    device,
    steps,
    use_graph,
    warmup=20,
    *,
    graph_steps=50,
    collide_every_step=True,
    **contact,
):
    """Steps per second of Newton's ``SolverSemiImplicit`` on the given jelly.

    Building the model (builder, finalize, solver, collision pipeline, states) is timed apart as
    ``build_seconds`` and excluded from the rate; so is the first step, which loads or compiles
    Newton's kernel modules (``compile_seconds``, including graph capture when ``use_graph``).
    Then ``warmup`` steps run untimed and ``steps`` steps are timed, with
    ``wp.synchronize_device`` before each clock read. With ``use_graph`` the loop of
    ``graph_steps`` steps (even) is captured once with ``wp.ScopedCapture`` and replayed with
    ``wp.capture_launch`` (works on CPU with Warp 1.19 too); ``steps`` is rounded up to a whole
    number of replays and the rate uses the steps actually run (reported as ``steps``).

    Extra keyword arguments (``contact_ke``, ``contact_kd``, ``contact_kf``, ``contact_mu``,
    ``particle_radius``, ``soft_contact_gap``) go to :class:`NewtonJelly`.

    Returns:
        dict(steps_per_second, ms_per_step, build_seconds, compile_seconds, steps, use_graph,
        collide_every_step, particles, springs, newton_version, device).
    """
    _import_newton()
    import warp as wp

    steps = int(steps)
    if steps < 1:
        raise ValueError("steps must be >= 1")
    wp.init()
    dev = wp.get_device(device)

    t0 = time.perf_counter()
    jelly = NewtonJelly(
        points, pairs, rest, ks, kd, masses, gravity, ground_y, dev, collide_every_step=collide_every_step, **contact
    )
    wp.synchronize_device(dev)
    build_seconds = time.perf_counter() - t0

    # First step: module load / JIT compile (cached kernels load fast, fresh ones compile).
    t0 = time.perf_counter()
    jelly.step(dt, 2)
    graph = None
    if use_graph:
        graph, per_graph = jelly.capture(dt, int(graph_steps))
        wp.capture_launch(graph)
    wp.synchronize_device(dev)
    compile_seconds = time.perf_counter() - t0

    if use_graph:
        launches = -(-int(warmup) // per_graph)
        for _ in range(launches):
            wp.capture_launch(graph)
        wp.synchronize_device(dev)
        launches = -(-steps // per_graph)
        done = launches * per_graph
        t0 = time.perf_counter()
        for _ in range(launches):
            wp.capture_launch(graph)
        wp.synchronize_device(dev)
        elapsed = time.perf_counter() - t0
    else:
        jelly.step(dt, int(warmup))
        wp.synchronize_device(dev)
        done = steps
        t0 = time.perf_counter()
        jelly.step(dt, steps)
        wp.synchronize_device(dev)
        elapsed = time.perf_counter() - t0

    if not np.all(np.isfinite(jelly.positions())):
        raise RuntimeError("Newton jelly diverged (non-finite positions); lower dt or the stiffness")

    return {
        "steps_per_second": done / elapsed,
        "ms_per_step": 1e3 * elapsed / done,
        "build_seconds": build_seconds,
        "compile_seconds": compile_seconds,
        "steps": done,
        "use_graph": bool(use_graph),
        "collide_every_step": bool(collide_every_step),
        "particles": int(np.asarray(points).reshape(-1, 3).shape[0]),
        "springs": int(np.asarray(pairs).reshape(-1, 2).shape[0]),
        "newton_version": newton_version(),
        "device": str(dev),
    }


def lattice_coloring(shape) -> list:
    """VBD's particle colours for a lattice jelly: 27 groups by lattice coordinate mod 3.

    Particles of one group never share a spring (the stencil reaches at most 2 along an axis), so
    VBD can update a group in parallel. ``shape`` is (nx, ny, nz); indices in lattice order.
    """
    nx, ny, nz = (int(n) for n in shape)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    color = ((i % 3) * 9 + (j % 3) * 3 + (k % 3)).ravel()
    return [np.flatnonzero(color == c).astype(np.int32) for c in range(27) if np.any(color == c)]


def implicit_peer(size, ks, kd, dt, device, steps=20, error_steps=10, vbd_iterations=(10, 50), repeats=3):
    """Our implicit step against Newton's VBD on one stiff jelly in free flight: ms per step and error.

    The jelly: ``size``^3 particles, 0.5 m cube of 1 kg, every spring at ``ks``/``kd``, spinning
    (2, 4, 1) rad/s about a tilted axis, no ground (the two contact models differ; see the module
    docstring). Error: after ``error_steps`` steps of ``dt`` from the same start, the largest
    particle distance to the float64 reference (our backward Euler step solved to 1e-10 with 4
    Newton iterations, i.e. the exact backward Euler trajectory), over the cube's edge. ms per step:
    ``steps`` steps (graphs on CUDA), best of ``repeats``.

    Returns a list of rows (ours in float32 with the default settings, VBD per iteration count).
    """
    import warp as wp

    from ..core.implicit import ImplicitIntegrator
    from ..core.model import ModelBuilder

    edge, mass = 0.5, 1.0
    dev = wp.get_device(device)

    def jelly(precision):
        b = ModelBuilder(gravity=(0.0, -9.81, 0.0))
        springs = {t: {"ks": ks, "kd": kd} for t in ("structural", "shear", "bending")}
        b.add_jelly((size,) * 3, edge, mass / size**3, springs, center=(0.0, 1.0, 0.0), axis=(1.0, 0.0, 1.0),
                    degrees=20.0, angular_velocity=(2.0, 4.0, 1.0))
        return b.finalize(dev, precision)

    def timed(step_count, step):
        best = float("inf")
        graph = None
        if dev.is_cuda:
            try:
                with wp.ScopedCapture(device=dev, force_module_load=False) as capture:
                    step(step_count)
                graph = capture.graph
            except Exception:  # a solver that reads back to the host inside its step: plain launches
                graph = None
        for _ in range(repeats):
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            if graph is not None:
                wp.capture_launch(graph)
            else:
                step(step_count)
            wp.synchronize_device(dev)
            best = min(best, time.perf_counter() - t0)
        return 1e3 * best / step_count

    def ours(precision, **options):
        model = jelly(precision)
        integ = ImplicitIntegrator(model, **options)
        states = [model.state(), model.state()]

        def step(count):
            for _ in range(count):
                integ.step(states[0], states[1], dt)
                states.reverse()

        return model, integ, states, step

    ref_model, _, ref_states, ref_step = ours("float64", cg_tolerance=1e-10, cg_max_iterations=2000,
                                              newton_iterations=4)
    ref_step(error_steps)
    reference = ref_states[0].particle_q.numpy()

    rows = []
    model, integ, states, step = ours("float32")
    step(error_steps)
    error = float(np.abs(states[0].particle_q.numpy() - reference).max()) / edge
    integ.reset_stats()
    ms = timed(steps + steps % 2, step)
    stats = integ.stats()
    rows.append({"solver": f"softsim implicit ({stats['cg_preconditioner']})", "size": size,
                 "particles": model.particle_count, "ms_per_step": ms, "error_over_edge": error,
                 "cg_iterations_mean": stats["cg_iterations_mean"]})
    q0 = model.particle_q_host
    v0 = model.state().particle_qd.numpy()
    for iterations in vbd_iterations:
        peer = NewtonJelly(
            q0, model.spring_indices_host, model.spring_rest_host, model.spring_stiffness_host,
            model.spring_damping_host, model.particle_mass_host, model.gravity_host, None, dev,
            velocities=v0, solver="vbd", vbd_iterations=iterations,
            color_groups=lattice_coloring((size,) * 3),
        )
        peer.step(dt, error_steps)
        q = peer.positions()
        error = float(np.abs(q - reference).max()) / edge if np.all(np.isfinite(q)) else float("inf")
        ms = timed(steps + steps % 2, lambda count, peer=peer: peer.step(dt, count))
        rows.append({"solver": f"newton.SolverVBD ({iterations} iterations)", "size": size,
                     "particles": model.particle_count, "ms_per_step": ms, "error_over_edge": error})
    return rows
