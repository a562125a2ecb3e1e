"""Per-frame metrics: energies, centre of mass, peak speed and non-finite counts, reduced on the device.

:class:`MetricsProbe` sums with atomics; :class:`DeterministicMetricsProbe` (``--deterministic``
runs) sums in a fixed order, chunks of particles and then jellies, so the metrics of two runs
agree bit for bit on CUDA too. :func:`make_probe` picks the one the model asks for.

For a batch of worlds (``softsim sweep``), :class:`PenetrationProbe` and :class:`PositionErrorProbe`
reduce the rest of what a row records on the device too, one number per world a frame, so the host
never reads the particles. :func:`explosion_reason` is the one explosion test of a run and of a
sweep's world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..core.contact import terrain_speed
from ..core.mesh_terrain import mesh_touch_arrays
from ..core.model import Model, State
from ..kernels.metrics import NO_SURFACE
from ..kernels import lattice as lattice_kernels
from ..kernels import metrics as metrics_kernels


@dataclass
class FrameMetrics:
    """Whole-scene quantities of one output frame (SI units)."""

    frame: int
    time: float
    com: list
    kinetic_energy: float
    spring_energy: float
    gravity_energy: float
    total_energy: float
    max_speed: float
    nonfinite: int
    jellies: list = field(default_factory=list)

    def as_dict(self) -> dict:
        d = {
            "frame": self.frame,
            "time": self.time,
            "com": self.com,
            "kinetic_energy": self.kinetic_energy,
            "spring_energy": self.spring_energy,
            "gravity_energy": self.gravity_energy,
            "total_energy": self.total_energy,
            "max_speed": self.max_speed,
        }
        if len(self.jellies) > 1:
            d["jellies"] = [{k: v for k, v in j.items() if k != "nonfinite"} for j in self.jellies]
        return d


class MetricsProbe:
    """Reduces a state to :class:`FrameMetrics` on the device; one small device-to-host copy per call."""

    def __init__(self, model: Model):
        self.model = model
        j = max(len(model.jellies), 1)
        dev = model.device
        self.kinetic = wp.zeros(j, dtype=model.scalar, device=dev)
        self.gravity_energy = wp.zeros(j, dtype=model.scalar, device=dev)
        self.spring_energy = wp.zeros(j, dtype=model.scalar, device=dev)
        self.moment = wp.zeros(j, dtype=model.vec3, device=dev)
        self.max_speed = wp.zeros(j, dtype=model.scalar, device=dev)
        self.nonfinite = wp.zeros(j, dtype=wp.int32, device=dev)
        masses = np.zeros(j)
        for k, info in enumerate(model.jellies):
            masses[k] = model.particle_mass_host[info.particle_start : info.particle_start + info.particle_count].sum()
        self.jelly_mass = masses

    def reduce(self, state: State):
        """Fill the per-jelly arrays for ``state`` on the device (launches only; ``measure`` reads them)."""
        self._reduce(state)

    def _reduce(self, state: State):
        """Fill the per-jelly arrays for ``state`` (atomics; see DeterministicMetricsProbe for fixed order)."""
        m = self.model
        for a in (self.kinetic, self.gravity_energy, self.spring_energy, self.moment, self.max_speed, self.nonfinite):
            a.zero_()
        wp.launch(
            metrics_kernels.reduce_particles,
            dim=m.particle_count,
            inputs=[m.particle_mass, m.particle_jelly, m.gravity, state.particle_q, state.particle_qd],
            outputs=[self.kinetic, self.gravity_energy, self.moment, self.max_speed, self.nonfinite],
            device=m.device,
        )
        if m.spring_count and m.lattice is not None:
            # Lattice path: the same energy from the stencil, without making the spring arrays.
            lat = m.lattice
            wp.launch(
                lattice_kernels.reduce_lattice_springs,
                dim=m.particle_count,
                inputs=[m.particle_jelly, lat.jelly_start, lat.jelly_shape, lat.jelly_types, lat.jelly_rest, lat.jelly_ks,
                        state.particle_q],
                outputs=[self.spring_energy],
                device=m.device,
            )
        elif m.spring_count:
            wp.launch(
                metrics_kernels.reduce_springs,
                dim=m.spring_count,
                inputs=[m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.particle_jelly, state.particle_q],
                outputs=[self.spring_energy],
                device=m.device,
            )

    def measure(self, state: State, frame: int, t: float) -> FrameMetrics:
        # An exploding run's sums overflow (inf + -inf is nan): the caller reads that as an explosion,
        # NumPy need not warn about it.
        with np.errstate(all="ignore"):
            return self._measure(state, frame, t)

    def _measure(self, state: State, frame: int, t: float) -> FrameMetrics:
        self._reduce(state)
        ke = self.kinetic.numpy().astype(np.float64)
        ge = self.gravity_energy.numpy().astype(np.float64)
        se = self.spring_energy.numpy().astype(np.float64)
        mom = self.moment.numpy().astype(np.float64)
        vmax = self.max_speed.numpy().astype(np.float64)
        bad = self.nonfinite.numpy()
        total_mass = self.jelly_mass.sum()
        com = (mom.sum(axis=0) / total_mass).tolist() if total_mass > 0 else [0.0, 0.0, 0.0]
        jellies = []
        for k in range(len(ke)):
            mk = self.jelly_mass[k]
            jellies.append(
                {
                    "com": (mom[k] / mk).tolist() if mk > 0 else [0.0, 0.0, 0.0],
                    "kinetic_energy": float(ke[k]),
                    "spring_energy": float(se[k]),
                    "gravity_energy": float(ge[k]),
                    "total_energy": float(ke[k] + se[k] + ge[k]),
                    "max_speed": float(vmax[k]),
                    "nonfinite": int(bad[k]),
                }
            )
        return FrameMetrics(
            frame=frame,
            time=t,
            com=com,
            kinetic_energy=float(ke.sum()),
            spring_energy=float(se.sum()),
            gravity_energy=float(ge.sum()),
            total_energy=float(ke.sum() + se.sum() + ge.sum()),
            max_speed=float(vmax.max()) if len(vmax) else 0.0,
            nonfinite=int(bad.sum()),
            jellies=jellies,
        )


def explosion_reason(nonfinite, max_speed, kinetic, spring, gravity, total, bound, precision) -> str | None:
    """Why a frame with these whole-scene (or whole-world) metrics is an explosion, or None.

    Non-finite particles, a speed above ``bound``, or energies that overflow ``precision`` (a speed
    of 1e38 m/s squared in float32 is infinite while every coordinate is still finite: no result
    after it means anything).
    """
    if nonfinite:
        return f"{nonfinite} particles with non-finite state"
    if max_speed > bound:
        return f"max speed {max_speed:.4g} m/s exceeds the bound {bound:.4g} m/s"
    # An energy beyond the square root of the largest number has overflowed in all but name: the
    # products it is made of (m v^2, m g h, ks dx^2) are a step from infinity, and the sums that
    # compare two of them (the energy change) mean nothing (gravity of 1e308 in float64).
    safe = math.sqrt(float(np.finfo(np.dtype(str(precision))).max))
    if not all(math.isfinite(e) and abs(e) < safe for e in (kinetic, spring, gravity, total)):
        return (f"the energy overflows the {precision} range (kinetic {kinetic:.4g} J, "
                f"spring {spring:.4g} J, gravity {gravity:.4g} J; the range's safe end is {safe:.3g} J)")
    return None


def exploded_mask(nonfinite, max_speed, kinetic, spring, gravity, total, bound, precision) -> np.ndarray:
    """:func:`explosion_reason` of many worlds at once, as a mask: True where it gives a reason.

    Arguments are arrays over worlds (``bound`` one per world too). A batch tests every world a
    frame with this and asks :func:`explosion_reason` for the words only where it is True.
    """
    safe = math.sqrt(float(np.finfo(np.dtype(str(precision))).max))
    with np.errstate(invalid="ignore"):
        # As the scalar test: NaN speeds are not above the bound; NaN or infinite energies overflow.
        out = (np.asarray(nonfinite) != 0) | (np.asarray(max_speed) > np.asarray(bound))
        for e in (kinetic, spring, gravity, total):
            e = np.asarray(e, dtype=np.float64)
            out |= ~(np.isfinite(e) & (np.abs(e) < safe))
    return out


class PenetrationProbe:
    """Deepest particle of each world inside terrain [m], reduced on the device: one number per world.

    Solid terrain (planes, spheres, meshes): the largest ``-phi`` over the world's particles with
    signed distance ``phi < 0``, measured by the contact kernels' own distance functions against
    the terrain where it is now (moving terrain included). A closed mesh is solid however deep; an
    open sheet only as far behind it as its ``thickness`` (the depth from which contact pushes
    particles out). A bowl is a shell with free space on both
    sides, so a particle behind it is not by itself inside anything: a jelly that the bowl cuts, some
    particles on each side, penetrates by the smaller of its deepest excursions on the two sides (0
    when it lies on one side). Distances are in the model's precision.
    """

    def __init__(self, model: Model, run):
        self.model = model
        # The terrain where the integrator's run state (``integrator.run``) has it now.
        self.run = run
        dev = model.device
        worlds = model.world_count
        self.depth = wp.zeros(worlds, dtype=model.scalar, device=dev)
        bowls_per_world = np.diff(model.bowl_first.numpy()) if model.bowl_count else np.zeros(1, np.int32)
        self.bowl_slots = max(int(bowls_per_world.max()), 1)
        jellies = max(len(model.jellies), 1)
        np_scalar = np.float32 if model.scalar == wp.float32 else np.float64
        slots = jellies * self.bowl_slots
        self._shell_lo_init = wp.array(np.full(slots, NO_SURFACE, np_scalar), dtype=model.scalar, device=dev)
        self._shell_hi_init = wp.array(np.full(slots, -NO_SURFACE, np_scalar), dtype=model.scalar, device=dev)
        self.shell_lo = wp.empty_like(self._shell_lo_init)
        self.shell_hi = wp.empty_like(self._shell_hi_init)
        world_of = np.array([j.world for j in model.jellies] or [0], dtype=np.int32)
        self.jelly_world = wp.array(world_of, dtype=wp.int32, device=dev)
        motion = model.terrain_motion
        if motion is not None:
            self._motion = (model.bowl_motion, run.terrain.turn_now, motion.rest_point)
        else:
            self._motion = (wp.array(np.full(model.bowl_count, -1, np.int32), dtype=wp.int32, device=dev),
                            wp.zeros(0, dtype=model.vec3, device=dev), wp.zeros(0, dtype=model.vec3, device=dev))

    def launch(self, state: State):
        """Reduce ``state``'s penetration per world into ``depth`` (launches only)."""
        m = self.model
        t = self.run.terrain
        self.depth.zero_()
        if m.bowl_count:
            wp.copy(self.shell_lo, self._shell_lo_init)
            wp.copy(self.shell_hi, self._shell_hi_init)
        wp.launch(
            metrics_kernels.measure_penetration,
            dim=m.particle_count,
            inputs=[m.particle_world, m.particle_jelly,
                    m.plane_first, t.plane_point, t.plane_normal, t.plane_hole_center, m.plane_hole_radius,
                    m.sphere_first, t.sphere_center, m.sphere_radius,
                    *mesh_touch_arrays(m, self.run),
                    m.bowl_first, t.bowl_center, m.bowl_radius, m.bowl_cut_height, *self._motion, self.bowl_slots,
                    state.particle_q],
            outputs=[self.depth, self.shell_lo, self.shell_hi],
            device=m.device,
        )
        if m.bowl_count:
            wp.launch(
                metrics_kernels.combine_shell_depths,
                dim=self.shell_lo.shape[0],
                inputs=[self.jelly_world, m.bowl_first, self.bowl_slots, self.shell_lo, self.shell_hi],
                outputs=[self.depth],
                device=m.device,
            )

    def read(self) -> np.ndarray:
        """The last :meth:`launch`'s depths, one per world (float64; synchronises)."""
        return self.depth.numpy().astype(np.float64)


class PositionErrorProbe:
    """RMS over each world's particles of the distance to a reference run's [m], on the device.

    ``world_ranges``: each world's ``(first particle, end)``, consecutive; the reference model holds
    the same worlds in the same order (float64). Each world is summed in particle order by one
    thread, in float64, so the result is the same on the CPU and on CUDA.
    """

    def __init__(self, model: Model, world_ranges):
        starts = [a for a, _ in world_ranges] + [world_ranges[-1][1]]
        if any(b != a2 for (_, b), a2 in zip(world_ranges, starts[1:])):
            raise ValueError("the worlds' particle ranges are not consecutive")
        self.model = model
        self.world_start = wp.array(np.asarray(starts, dtype=np.int32), dtype=wp.int32, device=model.device)
        self.error = wp.zeros(len(world_ranges), dtype=wp.float64, device=model.device)

    def launch(self, q, q_ref):
        wp.launch(metrics_kernels.measure_position_error, dim=self.error.shape[0],
                  inputs=[self.world_start, q, q_ref], outputs=[self.error], device=self.model.device)

    def read(self) -> np.ndarray:
        return self.error.numpy()


def speed_bound(model: Model) -> float:
    """Speed above which a run is called exploded [m/s].

    Ten times the largest speed the scene can reach by falling: its initial particle speed plus
    sqrt(2 |g| D), D the diagonal of the box holding the initial particles and the terrain
    anchors, plus twice the fastest moving terrain's surface speed within D (what a full bounce
    off it adds), plus 1 m/s so that a scene at rest has a sensible bound.
    """
    pts = [model.particle_q_host]
    pts += [np.atleast_2d(p["point"]) for p in model.planes]
    pts += [np.atleast_2d(np.asarray(p)) for p in model.terrain_anchor_points]
    allp = np.concatenate(pts)
    diag = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    v0 = float(np.linalg.norm(model.particle_qd.numpy(), axis=1).max()) if model.particle_count else 0.0
    g = float(np.linalg.norm(model.gravity_host))
    v0 += 2.0 * terrain_speed(model, diag)
    return 10.0 * (v0 + math.sqrt(2.0 * g * diag) + 1.0)


CHUNK = 256
"""Consecutive particles (springs) summed by one thread of a deterministic metrics reduction."""


def _chunks(owner: np.ndarray, jelly_count: int, chunk: int = CHUNK):
    """Split indices 0..len(owner) into runs of one owner (jelly) of at most ``chunk``; group them by owner.

    Returns:
        ``(start, end, jelly_chunk_start)`` int32 arrays: chunk c covers [start[c], end[c]); the
        chunks of jelly j are jelly_chunk_start[j]:jelly_chunk_start[j + 1], in ascending index order.
    """
    n = owner.shape[0]
    if n == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(jelly_count + 1, np.int32)
    breaks = np.flatnonzero(np.diff(owner)) + 1
    run_start = np.concatenate([[0], breaks])
    run_end = np.concatenate([breaks, [n]])
    starts, ends = [], []
    for a, b in zip(run_start, run_end):
        s = np.arange(a, b, chunk)
        starts.append(s)
        ends.append(np.minimum(s + chunk, b))
    start = np.concatenate(starts)
    end = np.concatenate(ends)
    jelly = owner[start]
    order = np.argsort(jelly, kind="stable")
    start, end, jelly = start[order], end[order], jelly[order]
    jelly_chunk_start = np.searchsorted(jelly, np.arange(jelly_count + 1), side="left")
    return start.astype(np.int32), end.astype(np.int32), jelly_chunk_start.astype(np.int32)


class DeterministicMetricsProbe(MetricsProbe):
    """:class:`MetricsProbe` with fixed-order sums (chunks, then jellies)."""

    def __init__(self, model):
        super().__init__(model)
        dev = model.device
        j = max(len(model.jellies), 1)
        jelly_of = model.particle_jelly.numpy()
        ps, pe, pj = _chunks(jelly_of, j)
        self._p_chunks = [wp.array(a, dtype=wp.int32, device=dev) for a in (ps, pe, pj)]
        n = ps.shape[0]
        self._p_partial = [
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=model.vec3, device=dev),
            wp.zeros(n, dtype=model.scalar, device=dev),
            wp.zeros(n, dtype=wp.int32, device=dev),
        ]
        spring_owner = jelly_of[model.spring_indices_host[:, 0]] if model.spring_count else np.zeros(0, np.int32)
        ss, se, sj = _chunks(spring_owner, j)
        self._s_chunks = [wp.array(a, dtype=wp.int32, device=dev) for a in (ss, se, sj)]
        self._s_partial = wp.zeros(ss.shape[0], dtype=model.scalar, device=dev)

    def _reduce(self, state):
        m = self.model
        start, end, jelly_start = self._p_chunks
        if start.shape[0]:
            wp.launch(
                metrics_kernels.reduce_particle_chunks,
                dim=start.shape[0],
                inputs=[start, end, m.particle_mass, m.gravity, state.particle_q, state.particle_qd],
                outputs=self._p_partial,
                device=m.device,
            )
        wp.launch(
            metrics_kernels.combine_particle_chunks,
            dim=jelly_start.shape[0] - 1,
            inputs=[jelly_start, *self._p_partial],
            outputs=[self.kinetic, self.gravity_energy, self.moment, self.max_speed, self.nonfinite],
            device=m.device,
        )
        start, end, jelly_start = self._s_chunks
        if start.shape[0]:
            wp.launch(
                metrics_kernels.reduce_spring_chunks,
                dim=start.shape[0],
                inputs=[start, end, m.spring_indices, m.spring_rest_length, m.spring_stiffness, state.particle_q],
                outputs=[self._s_partial],
                device=m.device,
            )
        wp.launch(
            metrics_kernels.combine_spring_chunks,
            dim=jelly_start.shape[0] - 1,
            inputs=[jelly_start, self._s_partial],
            outputs=[self.spring_energy],
            device=m.device,
        )


def make_probe(model: Model) -> MetricsProbe:
    """The metrics probe for ``model``: fixed-order sums when the model is deterministic."""
    return DeterministicMetricsProbe(model) if model.deterministic else MetricsProbe(model)
