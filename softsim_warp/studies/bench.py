"""Particle-steps per second per jelly size and integrator, optionally against Newton (``softsim bench``).

Each case is a cubic jelly of size^3 particles with all three spring types resting 1 mm above a
ground plane (:class:`JellySpec`), or a scene file (``--scene``). For every case and integrator
:func:`measure` reports particles, springs, ms per step, particle-steps/s, spring evaluations/s
(springs x force evaluations per step / time), the compile time of the first step (apart from
the rate), the device memory the run holds, the bytes a step must move (:func:`step_bytes`) and
the fraction of the copy bandwidth measured in the same run that this represents.

Timing: one untimed step loads (or compiles) the kernels; ``--steps`` steps are captured as one
graph (``wp.ScopedCapture``, CPU and CUDA) unless ``--no-graph``; after a warm-up replay, every
repeat synchronises, reads the clock, replays, synchronises and reads the clock again; the median
over ``--repeats`` is reported. Cases of one size (ours and Newton's) run their repeats in turn,
so load from other processes on a shared machine hits them alike. On CUDA, nvidia-smi (where
present) samples the clock and power meanwhile (:class:`ClockMonitor`): a run long enough to
reach the GPU's power cap is clocked down, and the report says so.

Nothing here imports pxr (the GPU machine has no usd-core) or Newton unless ``--peer newton``.
"""

from __future__ import annotations

import math
import platform
import shutil
import subprocess
import time
from dataclasses import dataclass

import numpy as np

from ..core.methods import EXPLICIT_NAMES, METHODS
from ..core.integrators import ExplicitIntegrator
from ..core.mesh_terrain import steps_on_host
from ..core.model import ModelBuilder, build_model
from ..core.stepper import make_integrator
from .bench_newton import NewtonJelly, newton_version
from .timing import TimedSteps

DEFAULT_INTEGRATORS = EXPLICIT_NAMES
# Force evaluations per step of the methods that have a fixed number (the explicit ones).
STAGES = {m.name: m.stages for m in METHODS if m.stages is not None}
BATCH_MAX_PARTICLES = 1_000_000


@dataclass(frozen=True)
class JellySpec:
    """The benchmark jelly (the issue's setting: dt 1e-4, particle mass 0.01, ground contact on)."""

    spacing: float = 0.05
    """Rest spacing of the lattice [m]."""
    particle_mass: float = 0.01
    """[kg]"""
    ks: float = 1000.0
    """Stiffness of every spring type [N/m]."""
    kd: float = 1.0
    """Damping of every spring type [N s/m]."""
    dt: float = 1.0e-4
    """Step [s]."""
    gravity: float = -9.81
    """[m/s^2] along y."""
    gap: float = 1.0e-3
    """Height of the jelly's bottom above the ground plane y = 0 [m]."""
    restitution: float = 0.5
    friction: float = 0.5


def build_jelly_model(size: int, spec: JellySpec, device, force_path="auto", precision="float32", copies=1):
    """The benchmark jelly (``copies`` of it, one per world, each on its own ground plane) as a Model."""
    builder = ModelBuilder((0.0, spec.gravity, 0.0))
    edge = spec.spacing * (size - 1)
    springs = {t: {"ks": spec.ks, "kd": spec.kd} for t in ("structural", "shear", "bending")}
    for w in range(copies):
        builder.add_jelly(
            (size,) * 3, edge, spec.particle_mass, springs, center=(0.0, spec.gap + 0.5 * edge, 0.0), world=w
        )
        builder.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), spec.restitution, spec.friction, world=w)
    return builder.finalize(device, precision, force_path=force_path)


# -- accounting ----------------------------------------------------------------------------------


def device_arrays_bytes(*objects) -> int:
    """Bytes of the distinct Warp allocations held (one level deep, lists and tuples included) by ``objects``.

    A view (a padded state array, ``Model.particle_array``) counts as the allocation it is a view of.
    """
    import warp as wp  # noqa: PLC0415

    seen = {}

    def visit(value):
        if isinstance(value, wp.array):
            while isinstance(getattr(value, "_ref", None), wp.array):
                value = value._ref
            if value.ptr is not None:
                seen[value.ptr] = value.capacity
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item)

    for obj in objects:
        for value in vars(obj).values():
            visit(value)
    return int(sum(seen.values()))


def step_bytes(model, integrator) -> int:
    """Bytes one step must move between the device memory and the cores, for the kernels it launches.

    The model counts every per-particle or per-spring array a launch reads or writes once (a
    read-modify-write twice, an array read twice in one launch once: on a method's first stage
    the stage state is y_n), neighbour reads as cache hits, and small per-jelly or per-world tables
    as free: the least traffic these kernels can cause. N particles, S springs, s the scalar size,
    v = 3 s the vector size:

    * spring list, per stage: zero f (N v), ``eval_springs`` (S (8 + 3 s) index and parameters,
      x and v 2 N v, f read-modify-write 2 N v), ``integrate_stage`` (inverse mass and world
      N (s + 4), f and the stage velocity 2 N v, plus the stage I/O below);
    * lattice rows (CPU), per stage: x, v of the stage state 2 N v, lattice k-coordinate 4 N,
      the force buffer written and read 2 N v, inverse mass N s, plus the stage I/O;
    * lattice gather (CUDA), per stage: x, v of the stage state 2 N v, jelly and world 8 N,
      inverse mass N s (none of these three for one jelly of one mass,
      ``single_stage``), plus the stage I/O (contact fused into the last stage
      moves nothing more);
    * stage I/O: y_n 2 N v on stages after the first (on the first it is the stage state, which
      the unfused ``integrate_stage`` reads the velocity of only: x_n N v more); the velocity
      accumulator N v and, from stage 2 on, the position accumulator N v, read on stages after the
      first and written before the last (stage 0's position term b_0 v_n is recomputed at stage 1
      from v_n); the next stage state written before the last 2 N v; y_{n+1} written 2 N v;
    * contact when not fused: inverse mass and world N (s + 4), y_n 2 N v, y_{n+1} read and
      written 4 N v.

    A batch of methods is counted as its longest method.
    """
    n, springs = model.particle_count, model.spring_count
    s = 8 if model.precision == "float64" else 4
    v = 3 * s
    count = integrator.stage_count
    lattice = model.lattice
    fused = lattice is not None and integrator.fused
    total = 0
    for stage in range(count):
        if lattice is None:
            total += n * v + springs * (8 + 3 * s) + 4 * n * v + n * (s + 4) + 2 * n * v
        elif lattice.kernel == "rows" and fused:
            total += 2 * n * v + 4 * n + 2 * n * v + n * s
        elif fused:
            total += 2 * n * v + (0 if getattr(integrator, "single", False) else 8 * n + n * s)
        else:  # lattice forces (f written), then integrate_stage (f and stage velocity read)
            total += 2 * n * v + (4 * n if lattice.kernel == "rows" else 8 * n) + n * v + 2 * n * v + n * (s + 4)
        if stage == 0:
            total += 0 if fused else n * v  # x_n: the unfused update reads the stage velocity only
        else:
            total += 2 * n * v
        if count == 1:
            total += 2 * n * v
            continue
        accumulators = 1 if stage == 0 else 2  # vectors of them kept from this stage on
        if stage > 0:
            total += (1 if stage == 1 else 2) * n * v
        total += 2 * n * v if stage == count - 1 else accumulators * n * v + 2 * n * v
    if model.plane_count and not getattr(integrator, "fuse_contact", False):
        total += n * (s + 4) + 6 * n * v
    return int(total)


# nvidia-smi's clock event reasons (``clocks_event_reasons.active``) that slow the clock down.
POWER_CAP = 0x4  # software power cap
SLOWDOWN = 0x8 | 0x20 | 0x40 | 0x80  # hardware slowdown, software and hardware thermal, power brake


class ClockMonitor:
    """Samples the GPU's SM clock, power draw and clock event reasons with nvidia-smi while cases are timed.

    A fused stage keeps every SM busy: run long enough, a GPU reaches its power cap and lowers its
    clock, and the step gets slower (docs/PERFORMANCE.md, "Sustained load"). ``summary()`` tells
    whether that happened during the timing: the clock range, the power, and the fraction of
    samples at the power cap or otherwise slowed down. None where there is no nvidia-smi (the CPU,
    another vendor), or it printed nothing usable. ``-i`` takes the CUDA ordinal, which is
    nvidia-smi's index unless CUDA_VISIBLE_DEVICES or CUDA_DEVICE_ORDER reorders the devices.
    """

    QUERY = "clocks.sm,clocks.max.sm,power.draw,power.limit,clocks_event_reasons.active"

    def __init__(self, device, period_ms=100):
        self.command = None
        smi = shutil.which("nvidia-smi") if device.is_cuda else None
        if smi:
            self.command = [smi, f"--query-gpu={self.QUERY}", "--format=csv,noheader,nounits"]
            self.command += ["-i", str(device.ordinal), "-lms", str(int(period_ms))]
        self.process = None
        self.lines = []

    def __enter__(self):
        if self.command:
            try:
                self.process = subprocess.Popen(
                    self.command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
                )
            except OSError:
                self.process = None
        return self

    def __exit__(self, *exc):
        if self.process is not None:
            self.process.terminate()
            try:
                out, _ = self.process.communicate(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                out, _ = self.process.communicate()
            self.lines = out.splitlines()
        return False

    def summary(self) -> dict | None:
        samples = []
        for line in self.lines:
            fields = [f.strip() for f in line.split(",")]
            try:
                clock, max_clock, power, limit = (float(f) for f in fields[:4])
                reasons = int(fields[4], 16)
            except (ValueError, IndexError):
                continue  # "[N/A]", a header, a cut line
            if reasons & 0x1:
                continue  # idle: between cases, not under load
            samples.append((clock, max_clock, power, limit, reasons))
        if not samples:
            return None
        clock, max_clock, power, limit, reasons = (np.array(c) for c in zip(*samples))
        return {
            "samples": len(samples),
            "sm_clock_mhz": {"min": float(clock.min()), "median": float(np.median(clock)), "max": float(clock.max())},
            "max_sm_clock_mhz": float(max_clock.max()),
            "power_w": {"median": float(np.median(power)), "max": float(power.max())},
            "power_limit_w": float(limit.max()),
            "power_capped_fraction": float(np.mean((reasons & POWER_CAP) != 0)),
            "slowed_down_fraction": float(np.mean((reasons & SLOWDOWN) != 0)),
        }


def measure_copy_bandwidth(device, nbytes=None, repeats=5) -> float:
    """Copy bandwidth of ``device`` [bytes/s], counting bytes read plus bytes written (median of ``repeats``)."""
    import warp as wp  # noqa: PLC0415

    if nbytes is None:
        nbytes = (1 << 30) if device.is_cuda else (256 << 20)
    count = nbytes // 4
    src = wp.zeros(count, dtype=wp.float32, device=device)
    dst = wp.empty(count, dtype=wp.float32, device=device)
    wp.copy(dst, src)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        wp.copy(dst, src)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    del src, dst
    return 2.0 * count * 4 / float(np.median(times))


# -- timed cases ---------------------------------------------------------------------------------


class CaseRefused(ValueError):
    """A case that cannot be built: ``what`` names the parameter ("integrator" or "path"), ``value`` its value."""

    def __init__(self, what: str, message: str, value):
        super().__init__(message)
        self.what, self.message, self.value = what, message, value


class IntegratorCase(TimedSteps):
    """Our integrator on one model; ``options`` (fused, fuse_contact, single) go to ExplicitIntegrator."""

    def __init__(self, model, method, dt, steps, use_graph, options=None):
        options = dict(options or {})
        self.model = model
        self.method = method
        try:
            self.integrator = (
                ExplicitIntegrator(model, method, **options) if options else make_integrator(method, model)
            )
        except ImportError as exc:  # the implicit integrator lives in its own module
            raise CaseRefused("integrator", f"{method} is not available here ({exc})", method) from None
        self.states = [model.state(), model.state()]

        def step(count):
            for k in range(count):
                self.integrator.step(self.states[k % 2], self.states[1 - k % 2], dt)

        # An animated mesh's refit is host work that no graph records: such a model is timed unreplayed.
        super().__init__(model.device, step, steps, use_graph and not steps_on_host(model))

    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.states[0].particle_q.numpy())))


class SeparateModelsCase(TimedSteps):
    """Several models stepped one after another (the unbatched reference for ``--variants``)."""

    def __init__(self, models, method, dt, steps, use_graph):
        self.parts = [IntegratorCase(m, method, dt, steps, False) for m in models]

        def step(count):
            for part in self.parts:
                part.step_fn(count)

        super().__init__(models[0].device, step, steps, use_graph)

    def finite(self) -> bool:
        return all(p.finite() for p in self.parts)


class NewtonCase(TimedSteps):
    """Newton's ``SolverSemiImplicit`` on the spring list of one of our models (building it is not timed)."""

    def __init__(self, model, spec: JellySpec, steps, use_graph):
        t0 = time.perf_counter()
        self.jelly = NewtonJelly(
            model.particle_q_host,
            model.spring_indices_host,
            model.spring_rest_host,
            model.spring_stiffness_host,
            model.spring_damping_host,
            model.particle_mass_host,
            model.gravity_host,
            0.0,
            model.device,
        )
        self.build_s = time.perf_counter() - t0
        dt = spec.dt
        super().__init__(model.device, lambda count: self.jelly.step(dt, count), steps, use_graph)

    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.jelly.positions())))


def versions(peer):
    """Versions of softsim, Warp, NumPy and Python (and Newton with ``peer``) for a report."""
    import warp as wp  # noqa: PLC0415

    from importlib.metadata import version  # noqa: PLC0415

    versions = {
        "softsim": version("softsim-warp"),
        "warp": wp.config.version,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }
    if peer:
        versions["newton"] = newton_version()
    return versions


def device_name(device) -> str:
    """The device as a report names it: the GPU's name, or the CPU's model."""
    if device.is_cuda:
        return f"{device.name} ({device.alias})"
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    name = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{name} (Warp runs a CPU kernel on one core)"




# -- the measurement -----------------------------------------------------------------------------


def size_groups(sizes, spec: JellySpec, device, precision="float32", copies=1):
    """``(label, make_model(path, copies), dt)`` per jelly size of the size sweep."""
    return [
        (
            f"{n}^3",
            lambda path, copies=copies, n=n: build_jelly_model(n, spec, device, path, precision, copies),
            spec.dt,
        )
        for n in sizes
    ]


def scene_group(scene, device, precision="float32"):
    """``(label, make_model(path, copies), dt)`` of one scene, at the scene's dt (one copy)."""
    return (scene.name, lambda path, copies=1: build_model(scene, device, precision, force_path=path), scene.sim["dt"])


def measure(groups, methods, paths, spec: JellySpec, device, bandwidth, *, steps, repeats, copies=1, variants=False,
            batch=True, peer=False, use_graph=True, progress=None):
    """Time every integrator of ``methods`` on every group's models; returns ``(results, peers, gpu_clocks)``.

    Args:
        groups: ``(label, make_model(path, copies), dt)`` (:func:`size_groups`, :func:`scene_group`).
        methods: integrator names.
        paths: force paths ("auto", "lattice", "springs"), each a case (not with ``variants``).
        spec: the benchmark jelly (Newton's step is ``spec.dt``).
        device: Warp device.
        bandwidth: the device's copy bandwidth [bytes/s] (:func:`measure_copy_bandwidth`).
        steps: steps per timed repeat (rounded up to even).
        repeats: timed repeats; the median is reported.
        copies: copies of the jelly per model (one per world).
        variants: the fast paths one by one (:func:`fast_path_variants`) instead of ``paths``.
        batch: with ``variants``, also batched copies against separate models (the size sweep).
        peer: also step each group's first model with Newton's ``SolverSemiImplicit``.
        use_graph: replay the steps from a captured graph.
        progress: ``progress(total)`` returning a bar (``set_description``, ``update``, ``close``),
            advanced once per group, or None.

    Raises:
        CaseRefused: an integrator that is not available here, or a force path the model cannot take.
    """
    results, peers, gpu_clocks = [], [], []
    bar = progress(len(groups)) if progress else None
    for label, make_model, dt in groups:
        if bar is not None:
            bar.set_description(f"bench {label}")
        if variants:
            cases = _variant_cases(label, make_model, dt, methods, device, steps, copies, batch, use_graph)
        else:
            cases = _standard_cases(label, make_model, dt, methods, paths, steps, use_graph)
        newton = None
        if peer:
            # Newton gets the spring list of the same jelly; building it is not timed.
            newton = NewtonCase(cases[0].model, spec, steps, use_graph)
        everyone = cases + ([newton] if newton else [])
        for case in everyone:
            case.compile_s = case.prepare()
        with ClockMonitor(device) as monitor:
            for _ in range(repeats):
                for case in everyone:
                    case.time_once()
        clocks = monitor.summary()
        if clocks is not None:
            gpu_clocks.append({"case": label, **clocks})
        peer_row = None
        if newton is not None:
            peer_row = {
                "case": label,
                "particles": cases[0].model.particle_count,
                "springs": cases[0].model.spring_count,
                "solver": "newton.SolverSemiImplicit",
                "ms_per_step": newton.ms_per_step(),
                "steps_per_s": 1e3 / newton.ms_per_step(),
                "particle_steps_per_s": cases[0].model.particle_count * 1e3 / newton.ms_per_step(),
                "compile_s": newton.compile_s,
                "build_s": newton.build_s,
                "graph": use_graph,
                "finite": newton.finite(),
            }
            peers.append(peer_row)
        rows = [
            _result_row(case, bandwidth, peer_row, case.use_graph, case.meta.get("copies", copies))
            for case in cases
        ]
        if variants:
            _relative_speeds(rows)
        results += rows
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    return results, peers, gpu_clocks


def _standard_cases(label, make_model, dt, methods, paths, steps, use_graph):
    """Every integrator on every requested force path, with the model's own choices (the defaults)."""
    cases = []
    for path in paths:
        t0 = time.perf_counter()
        try:
            model = make_model(path)
        except ValueError as exc:  # e.g. --paths lattice for a scene with custom springs
            raise CaseRefused("path", str(exc), path) from None
        build_s = time.perf_counter() - t0
        for method in methods:
            case = IntegratorCase(model, method, dt, steps, use_graph)
            case.meta = {
                "case": label,
                "path": path,
                "resolved_path": _path_name(model),
                "integrator": method,
                "build_s": build_s,
            }
            cases.append(case)
    return cases


def fast_path_variants(device):
    """The ``--variants`` ablation: (label, force path, lattice kernel, integrator options, graph), slowest first.

    The CPU row kernel is left out on CUDA, where one thread per jelly would leave the GPU idle.
    """
    variants = [
        ("springs, plain launches", "springs", None, None, False),
        ("springs, graph", "springs", None, None, True),
        ("lattice gather, unfused, graph", "lattice", "gather", {"fused": False}, True),
        ("lattice gather, fused, graph", "lattice", "gather", {"fused": True, "fuse_contact": False}, True),
        (
            "lattice gather, fused+contact, generic stage, graph",
            "lattice",
            "gather",
            {"fused": True, "fuse_contact": True, "single": False},
            True,
        ),
        ("lattice gather, fused+contact, graph", "lattice", "gather", {"fused": True, "fuse_contact": True}, True),
    ]
    if device.is_cpu:
        variants += [
            ("lattice rows, unfused, graph", "lattice", "rows", {"fused": False}, True),
            ("lattice rows, fused, plain launches", "lattice", "rows", {"fused": True}, False),
            ("lattice rows, fused, graph", "lattice", "rows", {"fused": True}, True),
        ]
    else:
        variants.append(
            (
                "lattice gather, fused+contact, plain launches",
                "lattice",
                "gather",
                {"fused": True, "fuse_contact": True},
                False,
            )
        )
    return variants


def _variant_cases(label, make_model, dt, methods, device, steps, copies, batch, use_graph):
    """Fast paths one by one (see :func:`fast_path_variants`) and, with ``batch`` (the size sweep), batching."""
    cases = []
    for name, path, kernel, options, graph in fast_path_variants(device):
        model = make_model(path, 1)
        if kernel is not None:
            model.lattice.set_kernel(kernel)
        for method in methods:
            case = IntegratorCase(model, method, dt, steps, graph, options)
            case.meta = {"case": label, "path": path, "resolved_path": name, "integrator": method, "copies": 1}
            cases.append(case)
    copies = copies if copies > 1 else 8
    # Batching is about many small scenes; past a million particles one copy fills the device.
    if batch and copies * cases[0].model.particle_count <= BATCH_MAX_PARTICLES:
        for method in methods:
            batched = IntegratorCase(make_model("auto", copies), method, dt, steps, use_graph)
            batched.meta = {
                "case": label,
                "path": "auto",
                "resolved_path": f"batch: {copies} copies, one model",
                "integrator": method,
                "copies": copies,
            }
            separate = SeparateModelsCase([make_model("auto", 1) for _ in range(copies)], method, dt, steps, use_graph)
            separate.model, separate.integrator = separate.parts[0].model, separate.parts[0].integrator
            separate.states = separate.parts[0].states
            separate.method = method
            separate.meta = {
                "case": label,
                "path": "auto",
                "resolved_path": f"batch: {copies} separate models",
                "integrator": method,
                "copies": copies,
                "separate_models": copies,
            }
            cases += [separate, batched]
    return cases


def _relative_speeds(rows):
    """Per integrator: speed over the first variant (springs, plain launches) and over the previous row."""
    by_method = {}
    for r in rows:
        by_method.setdefault(r["integrator"], []).append(r)
    for group in by_method.values():
        base = group[0]["ms_per_step"] / group[0]["particles"]
        prev = None
        for r in group:
            per_particle = r["ms_per_step"] / r["particles"]
            r["speedup_vs_baseline"] = base / per_particle
            r["speedup_vs_previous"] = prev / per_particle if prev else None
            prev = per_particle


def _path_name(model) -> str:
    if model.lattice is None:
        return "springs"
    return f"lattice-{model.lattice.kernel}"


def _result_row(case, bandwidth, peer_row, use_graph, copies) -> dict:
    parts = getattr(case, "parts", [case])  # K separate models step as one case
    ms = case.ms_per_step()
    n = sum(p.model.particle_count for p in parts)
    springs = sum(p.model.spring_count for p in parts)
    moved = sum(step_bytes(p.model, p.integrator) for p in parts) if case.method in STAGES else None
    held = 0
    for p in parts:
        held += device_arrays_bytes(p.model, p.integrator, *p.states)
        held += device_arrays_bytes(p.model.lattice) if p.model.lattice is not None else 0
    integrator = case.integrator
    row = dict(case.meta)
    row.update(
        {
            "particles": n,
            "springs": springs,
            "copies": copies,
            "graph": use_graph,
            "fused": bool(getattr(integrator, "fused", False)),
            "single_stage": bool(getattr(integrator, "single", False)),
            "ms_per_step": ms,
            "cpu_ms_per_step": case.cpu_ms_per_step() if case.device.is_cpu else None,
            "steps_per_s": 1e3 / ms,
            "particle_steps_per_s": n * 1e3 / ms,
            # Force evaluations per step: the explicit methods' stage counts (unknown for implicit).
            "spring_evals_per_s": springs * STAGES[case.method] * 1e3 / ms if case.method in STAGES else None,
            "compile_s": case.compile_s,
            "memory_bytes": held,
            "memory_method": "sum of the Warp arrays of model, integrator and states",
            "bytes_per_step": moved,
            "bandwidth_fraction": (moved / (ms * 1e-3)) / bandwidth if moved else None,
            "finite": case.finite(),
            "repeats_ms_per_step": [1e3 * t / case.steps for t in case.wall],
        }
    )
    if case.device.is_cuda:
        import warp as wp  # noqa: PLC0415

        row["mempool_used_bytes"] = int(wp.get_mempool_used_mem_current(case.device))
        row["mempool_high_bytes"] = int(wp.get_mempool_used_mem_high(case.device))
    if peer_row is not None:
        row["newton_ms_per_step"] = peer_row["ms_per_step"]
        # Per particle-step, so that rows of several copies compare too (one copy: the step ratio).
        row["speedup_vs_newton"] = (peer_row["ms_per_step"] / peer_row["particles"]) / (ms / n)
    return row


def _si(x: float) -> str:
    if x is None:
        return "-"
    if x == 0:
        return "0"
    exp = math.floor(math.log10(abs(x)) / 3)
    exp = max(min(exp, 4), -2)
    prefix = {-2: "u", -1: "m", 0: "", 1: "k", 2: "M", 3: "G", 4: "T"}[exp]
    return f"{x / 10 ** (3 * exp):.3g}{prefix}"


def format_table(results, bandwidth, device) -> str:
    """The results as ``softsim bench`` prints them: one row per case, then Newton's step per case."""
    lines = [f"device {device} ({device_name(device)}), copy bandwidth {bandwidth / 1e9:.1f} GB/s (read + write)"]
    variants = any("speedup_vs_baseline" in r for r in results)
    header = [
        "case",
        "integrator",
        "variant" if variants else "path",
        "particles",
        "springs",
        "ms/step",
        "particle-steps/s",
        "spring-evals/s",
        "compile s",
        "memory",
        "bytes/step",
        "% bw",
    ]
    header += ["x base", "x prev"] if variants else []
    header += ["x newton"] if any("speedup_vs_newton" in r for r in results) else []
    rows = []
    for r in results:
        row = [
            r["case"],
            r["integrator"],
            r["resolved_path"] if variants else r["resolved_path"] + ("+fused" if r["fused"] else ""),
            str(r["particles"]),
            str(r["springs"]),
            f"{r['ms_per_step']:.4g}",
            _si(r["particle_steps_per_s"]),
            _si(r["spring_evals_per_s"]) if r["spring_evals_per_s"] else "-",
            f"{r['compile_s']:.3g}",
            _si(r["memory_bytes"]) + "B",
            _si(r["bytes_per_step"]) + "B" if r["bytes_per_step"] else "-",
            f"{100 * r['bandwidth_fraction']:.1f}" if r["bandwidth_fraction"] else "-",
        ]
        if variants:
            row += [
                f"{r['speedup_vs_baseline']:.2f}",
                f"{r['speedup_vs_previous']:.2f}" if r.get("speedup_vs_previous") else "-",
            ]
        if "x newton" in header:
            row.append(f"{r['speedup_vs_newton']:.2f}" if "speedup_vs_newton" in r else "-")
        rows.append(row)
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(header)]

    def line(cells):
        # Text columns left-aligned, numbers right-aligned.
        return "  ".join(c.ljust(w) if i < 3 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    lines.append(line(header))
    lines += [line(row) for row in rows]
    newton = {}
    for r in results:
        if "newton_ms_per_step" in r:
            newton[r["case"]] = r["newton_ms_per_step"]
    for case, ms in newton.items():
        lines.append(f"newton SolverSemiImplicit {case}: {ms:.4g} ms/step ({1e3 / ms:.4g} steps/s)")
    return "\n".join(lines)


def format_implicit_peer(rows, ks, dt) -> str:
    """The implicit integrator against Newton's VBD (:func:`~.bench_newton.implicit_peer` rows), as printed."""
    lines = [f"\nimplicit vs newton.SolverVBD: stiff jelly in free flight, ks = {ks:.0e}, "
             f"dt = {dt}; error: max distance to the float64 backward Euler result after 10 "
             "steps, over the edge"]
    for r in rows:
        extra = f", CG it/step {r['cg_iterations_mean']:.1f}" if "cg_iterations_mean" in r else ""
        lines.append(
            f"  {r['size']}^3 {r['solver']:>38}: {r['ms_per_step']:9.3f} ms/step, "
            f"error {r['error_over_edge']:.2e}{extra}"
        )
    return "\n".join(lines)


def format_gpu_clocks(gpu_clocks) -> list[str]:
    """One line per timed size: the SM clock and power while it was timed (:class:`ClockMonitor`)."""
    lines = []
    for c in gpu_clocks:
        clock = c["sm_clock_mhz"]
        lines.append(
            f"gpu while timing {c['case']}: SM clock {clock['min']:.0f}-{clock['max']:.0f} MHz (median"
            f" {clock['median']:.0f}, max {c['max_sm_clock_mhz']:.0f}), power up to {c['power_w']['max']:.0f}"
            f" of {c['power_limit_w']:.0f} W, at the power cap in {100 * c['power_capped_fraction']:.0f} %"
            f" of {c['samples']} samples"
        )
    return lines


def plot(data: dict, path: str):
    """Log-log plot of particle-steps/s over particle count, one line per integrator and path (and Newton)."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(9, 4.5))
    lines = {}
    for r in data["results"]:
        key = f"{r['integrator']} ({r['resolved_path']}{'+fused' if r['fused'] else ''})"
        lines.setdefault(key, []).append((r["particles"], r["particle_steps_per_s"]))
    for key, pts in sorted(lines.items()):
        pts.sort()
        ax.plot(*zip(*pts), marker="o", label=key)
    if data.get("peer"):
        pts = sorted((p["particles"], p["particle_steps_per_s"]) for p in data["peer"])
        ax.plot(*zip(*pts), marker="s", linestyle="--", color="black", label="Newton SolverSemiImplicit")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("particles")
    ax.set_ylabel("particle-steps / s")
    ax.set_title(f"softsim bench on {data['device_name']}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

