"""Memory a scene needs, estimated from its counts before anything is allocated.

A scene's size is known from its resolutions alone: particle and spring counts follow from the
lattice stencils (:func:`scene_counts`, pure Python integers, so a resolution of 10^6 per axis costs
nothing to count). :func:`estimate` turns the counts into bytes, split into host memory (the NumPy
builder and the USD time samples, which a USD layer keeps in memory until the run ends) and device
memory (model, states, integrator stage buffers); on the CPU device both live in host RAM.
:func:`check_fits` compares that with what is available and raises a one-line
:class:`~softsim_warp.core.errors.SceneError` naming the estimate and the space available; it
also refuses, with :func:`check_steps`, a run whose step count (frames / fps / dt) could not
finish in :data:`MAX_RUN_DAYS` days even at a lower bound of the time a step takes.

The per-item byte counts below follow the arrays that ``model.py``, ``softsim_warp/core/integrators.py``,
``softsim_warp/io/simulate.py`` and ``softsim_warp/io/usd.py`` allocate; the builder's peak was measured with ``tracemalloc``
(about 87 bytes per spring while the lattice stencils are expanded in int64 and the builder's
float64 copies exist side by side) and is rounded up here.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from ..core import lattice
from ..core.errors import CommandLineError, SceneError
from ..core.methods import method

# Bytes per item. S: scalar size (4 for float32, 8 for float64).
HOST_BUILD_PER_SPRING = 192  # the above plus the lattice-path detection in finalize (per-spring offsets and checks; measured ~179)
HOST_BUILD_PER_PARTICLE = 96  # float64 q, qd, mass, int32 jelly/world, lattice meshgrids
# A box jelly is recorded as a whole lattice (no spring list at build time): its placed rest pose,
# surface quads and the lattice tables finalize makes from it (measured ~355 B a particle at 16^3 to 32^3).
HOST_BUILD_PER_LATTICE_PARTICLE = 320
USD_ADDRESS_RESERVE = 640 << 20  # address space usd-core maps when a stage opens (measured ~600 MiB)
WARP_ADDRESS_RESERVE = 384 << 20  # address space Warp's initialisation maps (measured ~360 MiB)
HOST_MODEL_PER_SPRING = 44  # host copies kept in the Model: pairs, type, rest/ks/kd (float64)
HOST_MODEL_PER_PARTICLE = 32  # q and mass (float64) kept in the Model
USD_POINT_BYTES = 12  # one float32 point of one time sample
# Particles of one model at most: kernels index particles (and springs) with 32-bit integers.
MAX_MODEL_PARTICLES = 2**31 - 1
# Contact between jellies (core/particle_contact.py), per contact particle, in scalars of S bytes
# (all its arrays are 4-byte ints or scalars): candidate lists (32), contact lists and impulses
# (2 x 16 slots, 4 scalars each), contact normals and gaps (16 x 4), approach speeds (16), face
# normals (9), records and compact positions (16), grid and counts (6): about 290, rounded up.
CONTACT_PER_PARTICLE = 300

# Lower bounds of the time one step takes, for refusing a run that cannot finish (check_steps).
# They are floors, not estimates: every step launches at least two kernels (symplectic; RK4 eight,
# implicit fourteen) over every particle and moves at least q and qd, read and written; each floor
# lies well below the cheapest step measured on its device (docs/PERFORMANCE.md, "The smallest
# step"), so a run is refused only when it surely cannot finish.
STEP_FLOOR_SECONDS = {"cpu": 0.5e-6, "cuda": 2.0e-6}
STEP_SECONDS_PER_PARTICLE = {"cpu": 5.0e-9, "cuda": 1.0e-11}
MAX_RUN_DAYS = 30


def heaviest(names) -> str:
    """The method of ``names`` whose step holds the most memory (the implicit one, else the one with
    the most stages): what a size check before building anything must assume."""
    return max(names, key=lambda name: (not method(name).explicit, method(name).stages or 0))


def _device_per_particle(s: int, integrator: str) -> int:
    # Model: q, qd (vec3), mass, inv_mass (scalar), jelly, world (int32).
    model = 6 * s + 2 * s + 8
    # Two states plus the spare state of Simulator.warm_up, each q and qd.
    states = 3 * 6 * s
    if method(integrator).explicit:
        # f, and for multi-stage methods the stage state and the RK accumulators (4 vec3).
        stage = 3 * s + (12 * s if method(integrator).stages > 1 else 0)
    else:
        # Implicit: forces, a Newton/CG working set of about eight vec3 vectors (x, r, p, Ap, z,
        # diagonal, rhs, dv) and the diagonal 3x3 blocks of the system matrix.
        stage = 3 * s + 8 * 3 * s + 9 * s
    return model + states + stage


def _device_per_spring(s: int, integrator: str, deterministic: bool) -> int:
    # Model: pair (vec2i), rest length, stiffness, damping.
    per = 8 + 3 * s
    if not method(integrator).explicit:
        per += 2 * 9 * s  # implicit: off-diagonal 3x3 blocks of df/dx and df/dv per spring
    if deterministic:
        per += 3 * s + 2 * 4  # per-spring force (vec3) + two CSR entries (signed spring id)
    return per


@dataclass
class Counts:
    """Particle, spring and surface-point counts of a scene (Python ints, never overflow)."""

    particles: int = 0
    springs: int = 0
    surface: int = 0
    jellies: list = field(default_factory=list)
    """Per jelly: (particles, springs)."""


def lattice_spring_count(shape, types=("structural", "shear", "bending")) -> int:
    """Springs of a lattice of ``shape`` for the given types, counted from the stencils alone."""

    total = 0
    for t, stencil in lattice.STENCILS.items():
        if lattice.SPRING_TYPE_NAMES[t] not in types:
            continue
        for off in stencil:
            total += math.prod(max(n - abs(o), 0) for n, o in zip(shape, off))
    return total


def scene_counts(data: dict) -> Counts:
    """Counts of a validated scene dictionary (``Scene.data``), without building anything."""
    c = Counts()
    for j in data["jelly"]:
        shape = [int(n) for n in j["resolution"]]
        n = math.prod(shape)
        s = lattice_spring_count(shape, tuple(j.get("springs", {})))
        interior = math.prod(max(k - 2, 0) for k in shape)
        c.particles += n
        c.springs += s
        c.surface += n - interior
        c.jellies.append((n, s))
    return c


@dataclass
class Estimate:
    """Bytes a run needs; ``host`` and ``device`` are what must fit where."""

    counts: Counts
    host_build: int
    host_model: int
    usd: int
    device: int

    def on(self, is_cuda: bool) -> tuple[int, int]:
        """Peak (host bytes, device bytes) of a run on a CUDA device, or (peak of all of it, 0) on the CPU.

        The builder is freed once the model exists, so the host peak is the larger of building
        (with, on the CPU, the device arrays that ``finalize`` creates meanwhile) and running
        (the model's host copies, the device arrays on the CPU, and every USD frame).
        """
        if is_cuda:
            return max(self.host_build, self.host_model + self.usd), self.device
        return max(self.host_build + self.device, self.host_model + self.device + self.usd), 0


def estimate(data: dict, integrator=None, frames=0, usd_springs=False, deterministic=False, precision=None) -> Estimate:
    """Estimated memory of a run of the validated scene ``data``.

    Args:
        data: ``Scene.data``.
        integrator: method name; defaults to the scene's.
        frames: output frames after frame 0 written to USD (0: the model alone).
        usd_springs: springs written as curves too (two points per spring per frame).
        deterministic: the atomic-free force path (per-spring forces and a CSR gather list).
        precision: "float32" or "float64"; defaults to the scene's.
    """
    sim = data["simulation"]
    integrator = integrator or sim["integrator"]
    s = 8 if (precision or sim["precision"]) == "float64" else 4
    c = scene_counts(data)
    # Springs are listed at build time only for mesh jellies; a box jelly is a recorded lattice.
    listed = sum(ns for j, (_, ns) in zip(data["jelly"], c.jellies) if "mesh" in j)
    recorded = sum(n for j, (n, _) in zip(data["jelly"], c.jellies) if "mesh" not in j)
    host_build = (HOST_BUILD_PER_SPRING * listed + HOST_BUILD_PER_PARTICLE * c.particles
                  + HOST_BUILD_PER_LATTICE_PARTICLE * recorded)
    host_model = HOST_MODEL_PER_SPRING * c.springs + HOST_MODEL_PER_PARTICLE * c.particles
    per_frame = c.particles + c.surface + (2 * c.springs if usd_springs else 0)
    usd = (frames + 1) * per_frame * USD_POINT_BYTES if frames else 0
    device = (
        _device_per_particle(s, integrator) * c.particles + _device_per_spring(s, integrator, deterministic) * c.springs
    )
    return Estimate(c, host_build, host_model, usd, device)


# Where the cgroup file system is mounted (a test points it at a folder of its own).
CGROUP_ROOT = "/sys/fs/cgroup"
# A cgroup v1 "no limit" is the largest page-aligned 64-bit value; anything above this is no limit.
_CGROUP_UNLIMITED = 1 << 60


def _free_memory_bytes() -> int | None:
    """Memory the kernel says can be allocated without swapping (MemAvailable), else free pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _read_int(path: str) -> int | None:
    """The integer in a one-value kernel file, or None (missing, unreadable, ``max``)."""
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    try:
        return int(text)
    except ValueError:
        return None


def _own_cgroup_dirs() -> list[str]:
    """This process's cgroup folders under :data:`CGROUP_ROOT`, innermost first, the root last:
    each level's limit applies (the v2 path from ``/proc/self/cgroup``, else the root alone)."""
    dirs = []
    try:
        with open("/proc/self/cgroup") as f:
            for line in f:
                hid, _, rest = line.rstrip("\n").partition(":")
                controllers, _, rel = rest.partition(":")
                if hid == "0" and controllers == "" and rel.startswith("/"):
                    parts = [p for p in rel.split("/") if p]
                    dirs = [os.path.join(CGROUP_ROOT, *parts[:i]) for i in range(len(parts), 0, -1)]
    except OSError:
        pass
    return dirs + [CGROUP_ROOT]


def _cgroup_available() -> int | None:
    """Bytes left under the cgroup memory limits of this process (the tightest level), or None.

    cgroup v2: ``memory.max`` minus ``memory.current`` at each level from this process's cgroup up
    to the root of the mount (a container sees its own cgroup as the root); cgroup v1:
    ``memory/memory.limit_in_bytes`` minus ``memory/memory.usage_in_bytes``."""
    left = None
    seen = set()
    for d in _own_cgroup_dirs():
        if d in seen:
            continue
        seen.add(d)
        limit = _read_int(os.path.join(d, "memory.max"))
        if limit is not None and limit < _CGROUP_UNLIMITED:
            used = _read_int(os.path.join(d, "memory.current")) or 0
            left = max(limit - used, 0) if left is None else min(left, max(limit - used, 0))
    v1 = os.path.join(CGROUP_ROOT, "memory")
    limit = _read_int(os.path.join(v1, "memory.limit_in_bytes"))
    if limit is not None and limit < _CGROUP_UNLIMITED:
        used = _read_int(os.path.join(v1, "memory.usage_in_bytes")) or 0
        left = max(limit - used, 0) if left is None else min(left, max(limit - used, 0))
    return left


def _address_space_available() -> int | None:
    """Bytes this process may still map under its address-space limit (``ulimit -v``,
    ``RLIMIT_AS``): the soft limit minus the address space already mapped (VmSize), or None."""
    try:
        import resource  # noqa: PLC0415 - POSIX only

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    mapped = 0
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    mapped = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    # Libraries a run maps after this check take address space that no estimate counts: opening a
    # USD stage maps about 600 MiB (usd-core's plugins and thread stacks), Warp's initialisation about
    # 360 MiB; under a tight limit they crash in native code rather than raise.
    import sys  # noqa: PLC0415

    reserve = (0 if "pxr.Usd" in sys.modules else USD_ADDRESS_RESERVE) + (
        0 if _warp_initialized() else WARP_ADDRESS_RESERVE)
    return max(soft - mapped - reserve, 0)


def _warp_initialized() -> bool:
    import sys  # noqa: PLC0415

    wp = sys.modules.get("warp")
    context = getattr(wp, "context", None) if wp is not None else None
    return getattr(context, "runtime", None) is not None


def host_memory_limits() -> dict:
    """Each bound on the host memory a run can still allocate, by name: ``free memory``
    (MemAvailable), ``address-space limit`` (RLIMIT_AS, ``ulimit -v``) and ``cgroup memory
    limit``; a bound that is not set or cannot be read is left out."""
    found = {
        "free memory": _free_memory_bytes(),
        "address-space limit": _address_space_available(),
        "cgroup memory limit": _cgroup_available(),
    }
    return {k: v for k, v in found.items() if v is not None}


def available_host_bytes() -> int | None:
    """Host memory that can still be allocated: the least of :func:`host_memory_limits`, or None."""
    limits = host_memory_limits()
    return min(limits.values()) if limits else None


def _available(n: int) -> str:
    """``n`` bytes available, naming the limit that gives it when it is not free memory."""
    limits = host_memory_limits()
    names = [k for k, v in limits.items() if v == n and k != "free memory"]
    return f"{format_bytes(n)} available" + (f" under the {names[0]}" if names and limits.get("free memory") != n else "")


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PiB"  # pragma: no cover


def _count(n: int) -> str:
    return f"{n:,}" if n < 10**15 else f"{float(n):.3g}"


def _largest_jelly_key(c: Counts) -> tuple[str, list]:
    k = max(range(len(c.jellies)), key=lambda i: c.jellies[i][0] + c.jellies[i][1])
    return f"jelly.{k}.resolution", k


def check_host_build(data: dict, source: str, available=None):
    """Refuse a scene whose builder alone would not fit in host memory (called by validation)."""

    est = estimate(data)
    need = est.host_build
    available = available_host_bytes() if available is None else available
    if available is not None and need > available:
        key, k = _largest_jelly_key(est.counts)
        raise SceneError(
            source,
            key,
            f"scene too large: building {_count(est.counts.particles)} particles and {_count(est.counts.springs)} springs needs "
            f"about {format_bytes(need)} of host memory, {_available(available)}",
            data["jelly"][k]["resolution"],
        )
    # Memory unknown or enough: particle indices are 32-bit. (Box jellies: a mesh jelly's particles
    # are a voxelised part of its lattice, counted when it is voxelised.)
    box = [(k, n) for k, (j, (n, _)) in enumerate(zip(data["jelly"], est.counts.jellies)) if "mesh" not in j]
    if box and sum(n for _, n in box) > MAX_MODEL_PARTICLES:
        k = max(box, key=lambda kn: kn[1])[0]
        raise SceneError(source, f"jelly.{k}.resolution", f"scene too large: {_count(sum(n for _, n in box))} particles, "
                         f"more than a model indexes ({MAX_MODEL_PARTICLES:,})", data["jelly"][k]["resolution"])


# The most points one lattice may have: kernels index them (and Warp counts a launch) in int32.
MAX_LATTICE_POINTS = 2**31 - 1


def check_lattice_build(shape, types, source: str, key: str, value, available=None):
    """Refuse a mesh jelly whose box lattice of ``shape`` (spring ``types``) could not be built in
    host memory, before it is voxelised (the voxeliser allocates per point of the box; the box's
    counts bound the jelly's). ``key`` and ``value``: what the user gave (resolution or spacing)."""
    particles = math.prod(int(n) for n in shape)
    springs = lattice_spring_count(shape, types)
    need = HOST_BUILD_PER_SPRING * springs + HOST_BUILD_PER_PARTICLE * particles
    available = available_host_bytes() if available is None else available
    if available is not None and need > available:
        raise SceneError(
            source,
            key,
            f"scene too large: a lattice of {' x '.join(str(int(n)) for n in shape)} points ({_count(particles)} "
            f"particles and {_count(springs)} springs at most) needs about {format_bytes(need)} of host memory, "
            f"{_available(available)}; use a coarser lattice",
            value,
        )


def check_counts(particles, springs, device, integrator, flag, value, host_available=None, device_free=None,
                 contact_particles=0):
    """Refuse ``particles`` and ``springs`` (a benchmark size, say) that would not fit on ``device``:
    a one-line :class:`CommandLineError` naming ``flag`` and ``value``. ``contact_particles``: particles
    that take part in contact between jellies (:data:`CONTACT_PER_PARTICLE` bytes each on the device)."""
    s = 4
    device_bytes = _device_per_particle(s, integrator) * particles + _device_per_spring(s, integrator, False) * springs
    device_bytes += CONTACT_PER_PARTICLE * s * contact_particles
    host_bytes = HOST_BUILD_PER_SPRING * springs + HOST_BUILD_PER_PARTICLE * particles
    if not device.is_cuda:
        host_bytes += device_bytes
    host_available = available_host_bytes() if host_available is None else host_available
    if host_available is not None and host_bytes > host_available:
        raise CommandLineError(flag, f"too large: {_count(particles)} particles and {_count(springs)} springs need about "
                               f"{format_bytes(host_bytes)} of host memory, {_available(host_available)}", value)
    if device.is_cuda:
        free = device.free_memory if device_free is None else device_free
        if device_bytes > free:
            raise CommandLineError(flag, f"too large: {_count(particles)} particles and {_count(springs)} springs need "
                                   f"about {format_bytes(device_bytes)} on {device}, {format_bytes(free)} free", value)


def check_bench_size(n: int, copies: int, device, integrator, copies_flag="--copies", copies_value=None,
                     host_available=None, device_free=None):
    """Refuse a benchmark jelly of ``n``^3 particles times ``copies`` that would not fit: the error
    names ``--sizes`` when one copy is already too large, else ``copies_flag`` (``--copies``)."""
    springs = lattice_spring_count((n, n, n))
    check_counts(n**3, springs, device, integrator, "--sizes", n, host_available, device_free)
    if copies > 1:
        check_counts(copies * n**3, copies * springs, device, integrator, copies_flag,
                     copies if copies_value is None else copies_value, host_available, device_free)


def step_seconds_floor(particles: int, is_cuda: bool) -> float:
    """A lower bound of the seconds one step of ``particles`` particles takes on a CUDA device or the CPU."""
    kind = "cuda" if is_cuda else "cpu"
    return max(STEP_FLOOR_SECONDS[kind], particles * STEP_SECONDS_PER_PARTICLE[kind])


def check_steps(scene, device, frames, max_days=MAX_RUN_DAYS, counts=None):
    """Refuse a run of ``frames`` frames after frame 0 whose steps (frames / fps / dt) would take more
    than ``max_days`` days on ``device`` even at :func:`step_seconds_floor` a step.

    The error names ``simulation.dt`` and its value, the step count and the least time it would take.
    Returns the step count (a float: a tiny dt gives more steps than an int should hold).
    """
    sim = scene.data["simulation"]
    dt, fps = float(sim["dt"]), float(sim["fps"])
    steps = float(frames) / fps / dt  # not frames / (fps * dt): fps * dt may round to 0
    end = scene.end_time() if hasattr(scene, "end_time") else None
    if end is not None and frames >= scene.frame_count():  # the last frame ends at the duration
        steps = min(steps, float(end) / dt)
    if not steps > 0:
        return 0.0
    counts = counts or scene_counts(scene.data)
    floor = step_seconds_floor(counts.particles, device.is_cuda)
    days = steps * floor / 86400.0
    if days > max_days:
        raise SceneError(
            scene.source,
            "simulation.dt",
            f"too many steps: {frames} frames at {fps:g} fps are {_steps(steps)} steps, which would take at least "
            f"{_days(days)} on {device} at <= {1.0 / floor:.3g} steps/s (at most {max_days:g} days allowed); "
            f"raise simulation.dt or shorten the run",
            sim["dt"],
        )
    return steps


def _days(days: float) -> str:
    if not math.isfinite(days):
        return "more than 1e300 days"
    return f"{days:,.0f} days" if days < 1e9 else f"{days:.3g} days"


def _steps(steps: float) -> str:
    if not math.isfinite(steps):
        return "more than 1e300"
    return f"{steps:,.0f}" if steps < 1e15 else f"{steps:.3g}"


def check_fits(
    scene,
    device,
    integrator=None,
    frames=0,
    usd_springs=False,
    deterministic=False,
    host_available=None,
    device_free=None,
    copies=None,
):
    """Refuse a run that would not fit on ``device`` (a ``wp.Device`` or anything with ``is_cuda``),
    or whose ``frames`` frames take too many steps to finish (:func:`check_steps`).

    ``copies``: the scenes of a side-by-side comparison (``softsim compare``), run at once: their
    memory is summed, and ``scene`` names the file in the message. ``host_available`` and
    ``device_free`` override what is measured (for tests).
    """
    parts = [(c, c.sim["integrator"]) for c in copies] if copies else [(scene, integrator)]
    ests = [estimate(s.data, m, frames, usd_springs, deterministic) for s, m in parts]
    est = ests[0]
    if len(ests) > 1:
        total = Counts(
            sum(e.counts.particles for e in ests), sum(e.counts.springs for e in ests), sum(e.counts.surface for e in ests),
            [j for e in ests for j in e.counts.jellies],
        )
        est = Estimate(total, *(sum(getattr(e, f) for e in ests) for f in ("host_build", "host_model", "usd", "device")))
    host_need, device_need = est.on(device.is_cuda)
    key, k = _largest_jelly_key(ests[0].counts)
    value = scene.data["jelly"][k]["resolution"]
    what = f"{_count(est.counts.particles)} particles, {_count(est.counts.springs)} springs and {_count(frames + 1)} USD frames"
    if len(ests) > 1:
        what = f"{len(ests)} copies with {what}"
    host_available = available_host_bytes() if host_available is None else host_available
    if host_available is not None and host_need > host_available:
        where = "host memory" if device.is_cuda else f"memory on {device}"
        if est.usd * 2 > host_need:  # the frames kept for the USD file, not the jellies, are too many
            key, value = "simulation.frames", frames
        raise SceneError(
            scene.source,
            key,
            f"scene too large: {what} need about {format_bytes(host_need)} of {where}, "
            f"{_available(host_available)}",
            value,
        )
    if device.is_cuda:
        free = device.free_memory if device_free is None else device_free
        if device_need > free:
            raise SceneError(
                scene.source,
                key,
                f"scene too large: {what} need about {format_bytes(device_need)} on {device}, "
                f"{format_bytes(free)} free of {format_bytes(device.total_memory)}",
                value,
            )
    check_steps(scene, device, frames, counts=est.counts)
    return est
