"""Model (immutable, on a device), State (positions and velocities) and the builder that makes them.

The builder collects jellies and terrain in NumPy; :meth:`ModelBuilder.finalize` copies them to a
device once. Integrators and writers read the model and never change it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import lattice, particle_contact
from .errors import SceneError
from .forces import ForceWork, force_path_for_terms, incident_springs_csr
from .lattice_model import LatticeData, LatticeSprings, detect_lattice, recorded_lattice, spring_arrays
from .pins import PinDrive, make_motion, path_position
from .masked_lattice import masked_lattice
from .mesh_assets import load_mesh, load_mesh_samples, mesh_options, transform_matrix
from .mesh_terrain import MeshPoses, attach_meshes, mesh_anchors, mesh_output, mesh_paths, sample_points
from .particle_contact import ParticleContact, ParticleContactState
from .terrain import bowl_mesh, sphere_mesh
from .contact import TerrainMotion, TerrainPoses, terrain_at
from .voxelize import add_mesh_jelly

SCALARS = {"float32": wp.float32, "float64": wp.float64}
NUMPY_SCALARS = {"float32": np.float32, "float64": np.float64}


def rotation_matrix(axis, degrees) -> np.ndarray:
    """Rotation by ``degrees`` about ``axis`` (Rodrigues' formula), float64 3x3."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    t = math.radians(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def jelly_points(shape, size, center, axis, degrees, initial_scale=None, local=None) -> np.ndarray:
    """Start positions ``(N, 3)`` [m] of a jelly lattice (``ModelBuilder.add_jelly``'s placement):
    the lattice of ``size`` scaled by ``initial_scale`` in its own frame, rotated by ``degrees``
    about ``axis`` and centred on ``center``. ``local``: that lattice unplaced
    (``lattice.lattice_points``), when the caller has it already."""
    shape = tuple(int(n) for n in shape)
    if local is None:
        local = lattice.lattice_points(shape, np.broadcast_to(np.asarray(size, dtype=np.float64), (3,)))
    scale = np.ones(3) if initial_scale is None else np.broadcast_to(np.asarray(initial_scale, dtype=np.float64), (3,))
    if np.any(scale == 0.0):
        raise ValueError(f"initial_scale components must be nonzero (got {scale.tolist()})")
    return (local * scale) @ rotation_matrix(axis, degrees).T + np.asarray(center, dtype=np.float64)


@dataclass
class JellyInfo:
    """Host-side description of one jelly inside a model."""

    shape: tuple
    """Particles per axis (nx, ny, nz)."""
    particle_start: int
    """Index of the jelly's first particle."""
    particle_count: int
    spring_start: int
    spring_count: int
    spacing: tuple
    """Rest spacing per axis [m]."""
    surface_quads: np.ndarray
    """Boundary quads, jelly-local particle indices, shape [Q, 4], int32."""
    world: int = 0
    name: str = ""
    embedding: object = None
    """A mesh jelly's surface in its lattice (``core.voxelize.SurfaceEmbedding``), else None."""
    lattice_index: np.ndarray = None
    """A masked jelly's particles' indices in its box lattice, shape [particle_count], else None (all points)."""
    self_contact: bool = False
    """Whether the jelly collides with itself (``core/particle_contact.py``)."""


class ModelBuilder:
    """Collects particles, springs and terrain in NumPy (float64) before :meth:`finalize`."""

    def __init__(self, gravity=(0.0, -9.8, 0.0)):
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.contact_epsilon = 0.01
        self.contact_velocity_epsilon = 0.01
        self.restitution_threshold_steps = 1.0
        # Contact between jellies (core/particle_contact.py, made by finalize): on/off, pair distance [m] (None:
        # from the lattice spacing), Coulomb friction and restitution between particles, Jacobi
        # iterations per step.
        self.jelly_contact = False
        self.jelly_contact_thickness = None
        self.jelly_contact_friction = particle_contact.DEFAULT_FRICTION
        self.jelly_contact_restitution = particle_contact.DEFAULT_RESTITUTION
        self.jelly_contact_iterations = particle_contact.DEFAULT_ITERATIONS
        self._q, self._qd, self._mass, self._jelly_of, self._world_of = [], [], [], [], []
        # The springs: blocks in the order added, each a whole lattice jelly (LatticeSprings) or
        # add_spring's (pairs, rest, ks, kd, type). Reading the lists (_pairs, ...) turns the
        # blocks into them for good (_lists); the builder then no longer vouches for the lattices.
        self._spring_blocks = []
        self._lists = None
        # Placed lattices by placement (add_jelly), shared read-only by jellies placed alike.
        self._placements = {}
        self._lattice_tables = {}
        self.jellies: list[JellyInfo] = []
        self.planes: list[dict] = []
        self.bowls: list[dict] = []
        self.spheres: list[dict] = []
        self.pins: list[dict] = []
        self.meshes: list[dict] = []
        self.device = None  # where mesh jellies are voxelised (build_model sets the model's device)
        self.world_count = 1
        self._particle_count = 0
        self._spring_count = 0

    # -- particles and springs ------------------------------------------------------------------

    def add_particles(self, q, qd, mass, world=0) -> int:
        """Add loose particles (no jelly springs); returns the index of the first one."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        n = q.shape[0]
        start = self._particle_count
        self._q.append(q)
        self._qd.append(np.broadcast_to(np.asarray(qd, dtype=np.float64), (n, 3)).copy())
        self._mass.append(np.broadcast_to(np.asarray(mass, dtype=np.float64), (n,)).copy())
        self._jelly_of.append(np.full(n, max(len(self.jellies) - 1, 0), dtype=np.int32))
        self._world_of.append(np.full(n, world, dtype=np.int32))
        self._particle_count += n
        self.world_count = max(self.world_count, world + 1)
        return start

    def add_spring(self, a, b, ks, kd, spring_type=lattice.STRUCTURAL, rest=None):
        """Add springs between particle arrays ``a`` and ``b``; rest length defaults to the current distance."""
        a = np.atleast_1d(np.asarray(a, dtype=np.int32))
        b = np.atleast_1d(np.asarray(b, dtype=np.int32))
        q = np.concatenate(self._q)
        if rest is None:
            rest = np.linalg.norm(q[a] - q[b], axis=1)
        n = a.shape[0]
        self._add_spring_block(
            (
                np.stack([a, b], axis=1),
                np.broadcast_to(np.asarray(rest, dtype=np.float64), (n,)).copy(),
                np.full(n, ks, dtype=np.float64),
                np.full(n, kd, dtype=np.float64),
                np.full(n, spring_type, dtype=np.int32),
            )
        )
        self._spring_count += n

    def _add_spring_block(self, block):
        if self._lists is None:
            self._spring_blocks.append(block)
            return
        for part in block.arrays() if isinstance(block, LatticeSprings) else [block]:
            for values, array in zip(self._lists, part):
                values.append(array)

    def _spring_lists(self) -> tuple:
        """The five spring lists (pairs, rest, ks, kd, type), one array per block of springs added."""
        if self._lists is None:
            lists = ([], [], [], [], [])
            springs_of, rest_of = {}, {}
            for block in self._spring_blocks:
                parts = block.arrays(springs_of, rest_of) if isinstance(block, LatticeSprings) else [block]
                for part in parts:
                    for values, array in zip(lists, part):
                        values.append(array)
            self._lists, self._spring_blocks = lists, None
        return self._lists

    # The spring lists as add_spring made them, for code that reads or edits them (tests,
    # detect_lattice, the masked path); reading them gives up the recorded lattices.
    _pairs = property(lambda self: self._spring_lists()[0])
    _rest = property(lambda self: self._spring_lists()[1])
    _ks = property(lambda self: self._spring_lists()[2])
    _kd = property(lambda self: self._spring_lists()[3])
    _type = property(lambda self: self._spring_lists()[4])

    def lattice_records(self) -> list | None:
        """The :class:`~softsim_warp.core.lattice_model.LatticeSprings` of every jelly, in order, when
        each jelly's springs are one such record and there are no other springs; else None."""
        blocks = self._spring_blocks
        if blocks is None or len(blocks) != len(self.jellies):
            return None
        if not all(isinstance(b, LatticeSprings) and b.start == j.particle_start for b, j in zip(blocks, self.jellies)):
            return None
        return blocks

    def _placed(self, shape, size, center, axis, degrees, initial_scale, velocity, angular_velocity):
        """``(rest_pose, q, qd)`` of a lattice jelly, the arrays shared (read-only) by jellies placed
        alike (the worlds of a batch); keyed by the exact bytes of the placement."""
        key = (shape, *(np.asarray(v, dtype=np.float64).tobytes() for v in (size, center, axis, degrees)),
               None if initial_scale is None else np.asarray(initial_scale, dtype=np.float64).tobytes(),
               *(np.asarray(v, dtype=np.float64).tobytes() for v in (velocity, angular_velocity)))
        placed = self._placements.get(key)
        if placed is None:
            rest_key = key[:5]
            rest_pose = self._placements.get(rest_key)
            local_key = key[:2]
            local = self._placements.get(local_key)
            if local is None:
                local = self._placements[local_key] = lattice.lattice_points(shape, size)
            if rest_pose is None:
                rest_pose = jelly_points(shape, size, center, axis, degrees, local=local)
                rest_pose.setflags(write=False)
                self._placements[rest_key] = rest_pose
            q = rest_pose
            if initial_scale is not None:
                q = jelly_points(shape, size, center, axis, degrees, initial_scale, local=local)
            qd = np.asarray(velocity, dtype=np.float64) + np.cross(
                np.asarray(angular_velocity, dtype=np.float64), q - center
            )
            for a in (q, qd):
                a.setflags(write=False)
            placed = self._placements[key] = (rest_pose, q, qd)
        return placed

    def _shape_tables(self, shape):
        """Per lattice shape: spring count per type, the surface quads (read-only, shared)."""
        tables = self._lattice_tables.get(shape)
        if tables is None:
            counts = lattice.spring_counts(shape)
            quads = lattice.surface_quads(shape)
            quads.setflags(write=False)
            tables = self._lattice_tables[shape] = ([counts[n] for n in lattice.SPRING_TYPE_NAMES], quads)
        return tables

    def add_jelly(
        self,
        resolution,
        size,
        particle_mass,
        springs: dict,
        center=(0.0, 0.0, 0.0),
        axis=(0.0, 1.0, 0.0),
        degrees=0.0,
        velocity=(0.0, 0.0, 0.0),
        angular_velocity=(0.0, 0.0, 0.0),
        world=0,
        name="",
        initial_scale=None,
        mask=None,
        self_contact=False,
    ) -> JellyInfo:
        """Add a lattice jelly.

        Args:
            resolution: particles per axis (nx, ny, nz).
            size: edge lengths [m]; a scalar means a cube.
            particle_mass: mass of each particle [kg], one value or one per particle (lattice order,
                ``lattice.lattice_index``). A particle of mass 0 has infinite mass: no force
                accelerates it, so it keeps its initial velocity (zero: it stays pinned where it is)
                while its springs pull on the others (examples/example_pinned_and_custom_force.py).
            springs: ``{"structural"|"shear"|"bending": {"ks": N/m, "kd": N s/m}}``; a type that is
                absent gets no springs at all.
            center, axis, degrees: placement: the lattice is centred on ``center`` and rotated about
                ``axis`` by ``degrees``.
            velocity, angular_velocity: initial rigid motion, v = velocity + omega x (x - center).
            initial_scale: per-axis factor (or one for all axes) applied to the lattice in its own
                frame before the rotation, for the start only: rest lengths stay those of the
                unscaled lattice, so the jelly starts stretched (> 1), crushed (< 1) or mirrored
                (negative on one axis). Components must be nonzero.
            mask: optional bool per lattice point (lattice order): only those points become
                particles, with the stencil springs between them (a mesh jelly, core/voxelize.py);
                ``particle_mass`` is then one value or one per kept particle.
            self_contact: the jelly collides with itself (``core/particle_contact.py``).
        """
        unknown = sorted(set(springs) - set(lattice.SPRING_TYPE_NAMES))
        if unknown:
            raise ValueError(f"unknown spring type {unknown[0]!r}; use {', '.join(lattice.SPRING_TYPE_NAMES)}")
        for type_name, params in springs.items():
            unknown = sorted(set(params) - {"ks", "kd"})
            if "ks" not in params or unknown:
                raise ValueError(f"springs[{type_name!r}] takes ks [N/m] and optionally kd [N s/m] (got {dict(params)})")
        shape = tuple(int(n) for n in resolution)
        size = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,))
        center = np.asarray(center, dtype=np.float64)
        # Rest lengths come from the unscaled lattice, so an initial_scale starts the springs out of rest.
        rest_pose, q, qd = self._placed(shape, size, center, axis, degrees, initial_scale, velocity, angular_velocity)
        start = self._particle_count
        spring_start = self._spring_count
        if mask is not None:
            pairs, types = lattice.lattice_springs(shape)
            rest = np.linalg.norm(rest_pose[pairs[:, 0]] - rest_pose[pairs[:, 1]], axis=1)
            # Keep the masked points and the springs whose both ends are kept, renumbered.
            mask = np.asarray(mask, dtype=bool)
            kept = mask[pairs[:, 0]] & mask[pairs[:, 1]]
            pairs, types, rest = (np.cumsum(mask) - 1)[pairs[kept]].astype(np.int32), types[kept], rest[kept]
            q, qd = q[mask], qd[mask]
        # The builder's own copy of the shared placement (its lists are open to edits).
        self.add_particles(q.copy() if mask is None else q, qd, particle_mass, world=world)
        self._jelly_of[-1][:] = len(self.jellies)
        if mask is not None:
            for t, type_name in enumerate(lattice.SPRING_TYPE_NAMES):
                params = springs.get(type_name)
                sel = types == t
                if params is None or not sel.any():
                    continue
                self.add_spring(
                    pairs[sel, 0] + start, pairs[sel, 1] + start, params["ks"], params.get("kd", 0.0), t, rest=rest[sel]
                )
            quads = np.zeros((0, 4), dtype=np.int32)
        else:
            # A whole lattice: the record of its stencil springs, no list (LatticeSprings.arrays).
            counts, quads = self._shape_tables(shape)
            present = [springs.get(n) is not None and c > 0 for n, c in zip(lattice.SPRING_TYPE_NAMES, counts)]
            params = [springs.get(n) or {} for n in lattice.SPRING_TYPE_NAMES]
            record = LatticeSprings(
                shape=shape,
                start=start,
                types=sum(1 << t for t in range(3) if present[t]),
                ks=np.array([float(p["ks"]) if on else 0.0 for p, on in zip(params, present)]),
                kd=np.array([float(p.get("kd", 0.0)) if on else 0.0 for p, on in zip(params, present)]),
                rest_pose=rest_pose,
                world=world,
                count=sum(c for c, on in zip(counts, present) if on),
            )
            self._add_spring_block(record)
            self._spring_count += record.count
        spacing = tuple(float(s / (n - 1)) if n > 1 else 0.0 for s, n in zip(size, shape))
        info = JellyInfo(
            shape=shape,
            particle_start=start,
            particle_count=q.shape[0],
            spring_start=spring_start,
            spring_count=self._spring_count - spring_start,
            spacing=spacing,
            surface_quads=quads,
            world=world,
            name=name or f"Jelly_{len(self.jellies)}",
            lattice_index=None if mask is None else np.flatnonzero(mask),
            self_contact=bool(self_contact),
        )
        self.jellies.append(info)
        return info

    def add_pin(self, particles, velocity=(0.0, 0.0, 0.0), spin=(0.0, 0.0, 0.0), center=None, key_times=(),
                key_offsets=(), interpolation="linear") -> int:
        """Hold or drive particles (global indices); returns the pin's index.

        The particles get mass 0 (no force accelerates them, terrain contact skips them; their
        springs still pull the others). Without motion they are held where they are, at rest. With
        motion they follow ``P(t) = c + velocity t + d(t) + R(spin t) (x0 - c)`` exactly at every
        step (``kernels/pins.py``), whatever the integrator.

        Args:
            particles: global particle indices.
            velocity: [m/s].
            spin: angular velocity [rad/s] about ``center`` (which moves with ``velocity``).
            center: centre of the spin [m]; default the particles' mean start position.
            key_times: keyframe times [s], strictly increasing.
            key_offsets: offsets ``d`` [m] at the key times, one 3-vector each.
            interpolation: "linear" or "smooth" (Catmull-Rom) between keys.
        """
        idx = np.unique(np.asarray(particles, dtype=np.int64).ravel())
        if idx.size == 0:
            raise ValueError("a pin needs at least one particle")
        if idx.min() < 0 or idx.max() >= self._particle_count:
            raise ValueError(f"pin particle indices must be in [0, {self._particle_count}) (got {idx.min()}..{idx.max()})")
        pin = make_motion(velocity, spin, center, key_times, key_offsets, interpolation)
        pin["particles"] = idx
        if pin["center"] is None:
            pin["center"] = np.concatenate(self._q)[idx].mean(axis=0)
        self.pins.append(pin)
        return len(self.pins) - 1

    # -- terrain --------------------------------------------------------------------------------

    def add_plane(
        self, point, normal, restitution=0.5, friction=0.3, hole_center=None, hole_radius=0.0, size=20.0, world=0,
        motion=None,
    ):
        """Add a collision plane; particles within ``hole_radius`` of ``hole_center`` pass through it.

        ``motion`` (every terrain primitive takes it): None for terrain that stays put, or the
        keyword arguments of :func:`~softsim_warp.core.pins.make_motion` (a pin's motion: velocity,
        spin about a centre, keyframes); the centre defaults to ``point`` (a sphere's or bowl's
        ``center``). The primitive, as given here, is carried by the motion's rigid map
        (``kernels/contact.py`` ``move_terrain``)."""
        normal = np.asarray(normal, dtype=np.float64)
        normal = normal / np.linalg.norm(normal)
        self.planes.append(
            {
                "point": np.asarray(point, dtype=np.float64),
                "normal": normal,
                "restitution": float(restitution),
                "friction": float(friction),
                "hole_center": np.zeros(3) if hole_center is None else np.asarray(hole_center, dtype=np.float64),
                "hole_radius": float(hole_radius),
                "size": float(size),
                "world": int(world),
                "motion": _terrain_motion(motion, point),
            }
        )

    def add_bowl(self, center, radius, cut_height=None, restitution=0.5, friction=0.3, world=0, motion=None):
        """Add a bowl: the inside of a sphere below ``cut_height`` (``None``: the whole sphere).

        Particles inside the sphere stay inside where y < cut_height; at or above the cut, and
        for particles that start a step outside the sphere, the bowl does not collide.
        """
        self.bowls.append(
            {
                "center": np.asarray(center, dtype=np.float64),
                "radius": float(radius),
                "cut_height": math.inf if cut_height is None else float(cut_height),
                "restitution": float(restitution),
                "friction": float(friction),
                "world": int(world),
                "motion": _terrain_motion(motion, center),
            }
        )

    def add_sphere(self, center, radius, restitution=0.5, friction=0.3, world=0, motion=None):
        """Add a solid sphere: particles stay outside it."""
        self.spheres.append(
            {
                "center": np.asarray(center, dtype=np.float64),
                "radius": float(radius),
                "restitution": float(restitution),
                "friction": float(friction),
                "world": int(world),
                "motion": _terrain_motion(motion, center),
            }
        )

    def add_mesh(self, asset, restitution=0.5, friction=0.3, thickness=0.1, world=0, name="Mesh", motion=None,
                 samples=None):
        """Add triangle-mesh terrain (a :class:`~softsim_warp.core.mesh_assets.MeshAsset` in
        world space). A closed mesh keeps particles outside it (its faces are turned outward if
        they wind inward); an open sheet collides from the side its faces' normals point to and
        pushes out particles up to ``thickness`` [m] behind it.

        ``motion``: as :meth:`add_plane`'s (a rigid motion; the spin's centre defaults to the
        mesh's bounding-box centre). ``samples``: ``(times [S] in s, points [S, V, 3] in m)``, the
        asset's vertices at increasing times (an animated asset, ``mesh_assets.load_mesh_samples``):
        the mesh follows them, linear between samples, held outside them."""
        if samples is not None:
            times = np.asarray(samples[0], dtype=np.float64)
            points = np.asarray(samples[1], dtype=np.float64)
            if points.ndim != 3 or points.shape[1:] != asset.points.shape or points.shape[0] != times.size:
                raise ValueError(f"samples must be times [S] and points [S, {asset.points.shape[0]}, 3] "
                                 f"(got {times.shape} and {points.shape})")
            if np.any(np.diff(times) <= 0):
                raise ValueError("sample times must increase")
            samples = (times, points)
            asset = type(asset)(sample_points(times, points, 0.0), asset.counts, asset.indices, asset.primvars,
                                asset.name)
        center = 0.5 * (asset.points.min(axis=0) + asset.points.max(axis=0))
        self.meshes.append(
            {
                "motion": _terrain_motion(motion, center),
                "samples": samples,
                "asset": asset.outward(),
                "restitution": float(restitution),
                "friction": float(friction),
                "thickness": float(thickness),
                "world": int(world),
                "name": name,
            }
        )

    # -- finalize -------------------------------------------------------------------------------

    def finalize(self, device=None, precision="float32", force_path="auto", deterministic=False, masked_kernel=None,
                 contact_hooks=(), force_terms=()) -> Model:
        """Copy everything to ``device`` as a :class:`Model` in ``precision`` ("float32" or "float64"),
        with every optional part made here (the lattice or masked tables, meshes, moving terrain,
        pins, contact between jellies, the deterministic CSR), and freeze it.

        Args:
            force_path: "auto" takes the lattice path (no spring arrays, see ``lattice_model``)
                when every spring is a standard lattice spring, "lattice" requires it, "springs"
                keeps the general spring list.
            deterministic: atomic-free force evaluation (``core/forces.py``): a model on the spring
                list gets the incident-spring CSR (``spring_csr_offsets``, ``spring_csr_springs``).
            masked_kernel: "gather" takes the masked-lattice path for mesh jellies on any device
                (tests, benchmarks); None: on CUDA only (``core/masked_lattice.py``).
            contact_hooks: callables run after terrain contact at every step's end
                (``Model.contact_hooks``).
            force_terms: internal forces beyond the springs (``core/forces.ForceTerm``); only the
                spring list evaluates them, so "auto" then takes it and "lattice" is refused.
        """
        if force_path not in ("auto", "lattice", "springs"):
            raise ValueError(f"force_path must be auto, lattice or springs (got {force_path!r})")
        force_terms = tuple(force_terms)
        force_path = force_path_for_terms(force_path, force_terms)
        if precision not in SCALARS:
            raise ValueError(f"precision must be one of {', '.join(SCALARS)} (got {precision!r})")
        device = wp.get_device(device)
        scalar = SCALARS[precision]
        np_scalar = NUMPY_SCALARS[precision]
        vec3 = wp.types.vector(3, scalar)

        def arr(values, dtype, np_dtype=None):
            values = np.asarray(values, dtype=np_dtype) if np_dtype is not None else values
            return wp.array(values, dtype=dtype, device=device)

        m = Model()
        m.force_terms = force_terms
        m.device = device
        m.precision = precision
        m.scalar = scalar
        m.vec3 = vec3
        m.world_count = self.world_count
        m.jellies = list(self.jellies)
        driven = [p for p in self.pins if p["driven"]]
        m.pinned_count = int(sum(len(p["particles"]) for p in self.pins))

        q = np.concatenate(self._q) if self._q else np.zeros((0, 3))
        m.particle_count = q.shape[0]
        mass = np.concatenate(self._mass) if self._mass else np.zeros(0)
        qd = np.concatenate(self._qd) if self._qd else np.zeros((0, 3))
        for pin in self.pins:  # pinned: mass 0, and the path's velocity at t = 0 (0 when held)
            idx = pin["particles"]
            mass[idx] = 0.0
            qd[idx] = 0.0
            if pin["driven"]:
                h = 1e-6
                qd[idx] = (path_position(pin, q[idx], h) - path_position(pin, q[idx], 0.0)) / h
        inv_mass = np.where(mass > 0, 1.0 / np.where(mass > 0, mass, 1.0), 0.0)
        m.particle_q_host = q.copy()
        m.particle_mass_host = mass.copy()
        m.particle_q = arr(q, vec3, np_scalar)
        m.particle_qd = arr(qd, vec3, np_scalar)
        m.particle_mass = arr(mass, scalar, np_scalar)
        m.particle_inv_mass = arr(inv_mass, scalar, np_scalar)
        m.particle_jelly = arr(np.concatenate(self._jelly_of) if self._jelly_of else np.zeros(0), wp.int32, np.int32)
        m.pins = PinDrive(driven, q, device, scalar, vec3) if driven else None
        m.particle_world = arr(np.concatenate(self._world_of) if self._world_of else np.zeros(0), wp.int32, np.int32)

        m.spring_count = self._spring_count
        # --- lattice fast path (perf): without it the spring arrays go to the device now; with it
        # they are made on first use only (Model.__getattr__), e.g. by an implicit integrator. A
        # builder whose jellies are all recorded whole (add_jelly) gives the lattice tables and,
        # on first use only, the spring list from its records; any other is searched
        # (detect_lattice) and keeps its list as given.
        m.lattice = None
        m.lattice_reason = "force_path=springs" if not force_terms else "force terms need the spring list (core/forces.py)"
        if force_path != "springs":
            recorded = self.lattice_records() is not None
            layout, m.lattice_reason = recorded_lattice(self) if recorded else detect_lattice(self)
            if layout is None and force_path == "lattice":
                raise ValueError(f"the lattice path does not apply: {m.lattice_reason}")
            if layout is not None:
                m.lattice = LatticeData(layout, device, scalar, np_scalar, m.particle_count, particle_mass=mass)
        if self._lists is None:
            m._spring_blocks = list(self._spring_blocks)
        else:
            m._spring_blocks = None
            m._set_spring_host(*(np.concatenate(values) if values else None for values in self._lists))
        if m.lattice is None:
            m._make_spring_arrays()
        # Mesh jellies: the lattice stencil over present points.
        m.masked, m.masked_reason = masked_lattice(self, m, force_path, masked_kernel)
        # --- end lattice fast path
        # Deterministic forces: the lattice kernels use no atomics; the spring list gathers each
        # particle's springs in a fixed order from a CSR list.
        m.deterministic = bool(deterministic)
        m.spring_csr_offsets = m.spring_csr_springs = None
        if m.deterministic and m.lattice is None:
            offsets, entries = incident_springs_csr(m.spring_indices_host, m.particle_count)
            m.spring_csr_offsets = arr(offsets, wp.int32)
            m.spring_csr_springs = arr(entries, wp.int32)

        m.gravity = vec3(*[scalar(g) for g in self.gravity])
        m.gravity_host = self.gravity.copy()
        m.contact_epsilon = scalar(self.contact_epsilon)
        m.contact_velocity_epsilon = scalar(self.contact_velocity_epsilon)
        m.restitution_threshold_steps = scalar(self.restitution_threshold_steps)

        # Terrain sorted by world (stable: a world's own order is kept), with the index of each
        # world's first primitive per kind, so a particle's contact loop visits only its world's
        # primitives (a batch of K copies would otherwise test K times as many).
        planes = sorted(self.planes, key=lambda p: p["world"])
        bowls = sorted(self.bowls, key=lambda b: b["world"])
        spheres = sorted(self.spheres, key=lambda q: q["world"])

        def first(items):
            worlds = np.array([it["world"] for it in items], dtype=np.int64)
            return arr(np.searchsorted(worlds, np.arange(m.world_count + 1)).astype(np.int32), wp.int32, np.int32)

        m.planes = [dict(p) for p in planes]
        m.plane_count = len(planes)
        m.plane_first = first(planes)

        # The device arrays hold the terrain where it is at t = 0 (moving terrain is moved there at
        # every step's start, core/contact.py TerrainMotion); the host lists keep it as given.
        planes_now = [terrain_at(p, 0.0) for p in planes]

        def col(name, shape):
            return np.array([p[name] for p in planes_now]).reshape(shape)

        n = m.plane_count
        m.plane_point = arr(col("point", (n, 3)), vec3, np_scalar)
        m.plane_normal = arr(col("normal", (n, 3)), vec3, np_scalar)
        m.plane_hole_center = arr(col("hole_center", (n, 3)), vec3, np_scalar)
        m.plane_hole_radius = arr(col("hole_radius", (n,)), scalar, np_scalar)
        m.plane_restitution = arr(col("restitution", (n,)), scalar, np_scalar)
        m.plane_friction = arr(col("friction", (n,)), scalar, np_scalar)

        # Bowls and spheres; float32 cannot hold an infinite cut, so "no cut" is stored as 1e30.
        m.bowls = [dict(b) for b in bowls]
        m.bowl_count = len(bowls)
        m.bowl_first = first(bowls)
        m.spheres = [dict(s) for s in spheres]
        m.sphere_count = len(spheres)
        m.sphere_first = first(spheres)

        def cols(items, name, shape):
            return np.array([it[name] for it in items], dtype=np.float64).reshape(shape)

        nb, ns = m.bowl_count, m.sphere_count
        m.bowl_center = arr(cols([terrain_at(b, 0.0) for b in bowls], "center", (nb, 3)), vec3, np_scalar)
        m.bowl_radius = arr(cols(bowls, "radius", (nb,)), scalar, np_scalar)
        m.bowl_cut_height = arr(np.minimum(cols(bowls, "cut_height", (nb,)), 1.0e30), scalar, np_scalar)
        m.bowl_restitution = arr(cols(bowls, "restitution", (nb,)), scalar, np_scalar)
        m.bowl_friction = arr(cols(bowls, "friction", (nb,)), scalar, np_scalar)
        m.sphere_center = arr(cols([terrain_at(q, 0.0) for q in spheres], "center", (ns, 3)), vec3, np_scalar)
        m.sphere_radius = arr(cols(spheres, "radius", (ns,)), scalar, np_scalar)
        m.sphere_restitution = arr(cols(spheres, "restitution", (ns,)), scalar, np_scalar)
        m.sphere_friction = arr(cols(spheres, "friction", (ns,)), scalar, np_scalar)
        # Contact between jellies and self-contact: nothing at all unless the scene has it.
        m.particle_contact = None
        if particle_contact.wanted(self.jelly_contact, m.jellies):
            m.particle_contact = ParticleContact(
                m,
                self.jelly_contact,
                self.jelly_contact_thickness,
                self.jelly_contact_friction,
                self.jelly_contact_restitution,
                self.jelly_contact_iterations,
            )
        m.contact_hooks = tuple(contact_hooks)
        attach_meshes(m, self.meshes, arr, first)
        # None when no terrain moves; else it gives each kind its index among the moving terrain.
        m.terrain_motion = TerrainMotion.of(m, device, scalar, vec3)
        if m.terrain_motion is None:
            m.plane_motion = m.bowl_motion = m.sphere_motion = None
        m._freeze()
        return m


class Model:
    """Everything about a scene that does not change while it runs, on one device.

    Every field is declared below with its unit and shape (device arrays unless marked host) and is
    present on every model: an optional part that a scene lacks (a lattice, meshes, pins, moving
    terrain, contact between jellies, the deterministic force path's CSR) is None, never absent.
    :meth:`ModelBuilder.finalize` makes the model and then freezes it: setting or deleting an
    attribute afterwards raises ``AttributeError``. The arrays' contents are not guarded, but
    nothing in the library writes them: what a run writes (the clocks of pins, moving terrain and
    animated meshes, the current terrain poses, contact lists and impulses, force scratch) is a
    :class:`RunState` that each integrator makes for itself (:meth:`run_state`), so any number of
    integrators step one model independently.

    Derived data may be made lazily, through the one cache that the freeze leaves writable
    (``_derived``, filled by :meth:`derived`): the spring list on the lattice path (its host and
    device arrays, made on first access by an implicit integrator, ``--springs`` or metrics) and
    host summaries such as a batch's per-world speed-bound inputs. Nothing made there changes once made.
    """

    # -- device and precision -------------------------------------------------------------------
    device: wp.context.Device
    """The Warp device every array lives on."""
    precision: str
    """"float32" or "float64"."""
    scalar: type
    """The Warp scalar type of the precision (``wp.float32`` or ``wp.float64``)."""
    vec3: type
    """The Warp 3-vector type of the precision."""
    world_count: int
    """Worlds (independent copies in a comparison or batch); particles of different worlds never interact."""
    jellies: list
    """Host list of :class:`JellyInfo`, one per jelly."""

    # -- particles ------------------------------------------------------------------------------
    particle_count: int
    """Number of particles N."""
    particle_q: wp.array
    """Initial positions [m], shape [N], vec3."""
    particle_qd: wp.array
    """Initial velocities [m/s], shape [N], vec3."""
    particle_mass: wp.array
    """Mass [kg] (0 for a pinned particle), shape [N], scalar."""
    particle_inv_mass: wp.array
    """1/mass [1/kg] (0 for a pinned particle), shape [N], scalar."""
    particle_jelly: wp.array
    """Jelly index of each particle, shape [N], int32."""
    particle_world: wp.array
    """World index of each particle, shape [N], int32."""
    particle_q_host: np.ndarray
    """Host copy of the initial positions [m], shape [N, 3], float64."""
    particle_mass_host: np.ndarray
    """Host copy of the masses [kg], shape [N], float64."""
    pins: object
    """The driven pins' arrays (:class:`~softsim_warp.core.pins.PinDrive`), or None; held pins
    need none (their particles have mass 0 and start at rest)."""
    pinned_count: int
    """Particles held or driven by pins."""
    gravity: object
    """Acceleration of gravity [m/s^2], vec3 value."""
    gravity_host: np.ndarray
    """The same on the host, shape [3], float64."""

    # -- springs --------------------------------------------------------------------------------
    spring_count: int
    """Number of springs S (on the lattice path too, where no list is stored until read)."""
    lattice: object
    """Per-jelly tables of the lattice force path (:class:`~softsim_warp.core.lattice_model.LatticeData`),
    or None when the model keeps a spring list."""
    lattice_reason: str
    """Host string: why the lattice path does or does not apply."""
    masked: object
    """Tables of the masked-lattice force path (mesh jellies, :class:`~softsim_warp.core.masked_lattice.MaskedLattice`),
    or None."""
    masked_reason: str
    """Host string: why the masked path does or does not apply."""
    force_terms: tuple
    """Internal forces beyond the springs (:class:`~softsim_warp.core.forces.ForceTerm`), evaluated on
    the spring list only; () for none."""
    deterministic: bool
    """Forces without atomics (``softsim run --deterministic``; ``finalize(deterministic=True)``)."""
    spring_csr_offsets: wp.array
    """Deterministic spring list: start of each particle's incident springs, shape [N + 1], int32;
    None on the lattice paths or without ``deterministic``."""
    spring_csr_springs: wp.array
    """Deterministic spring list: signed incident spring ids (``forces.incident_springs_csr``),
    shape [2 S], int32; None with ``spring_csr_offsets``."""

    # -- contact parameters ---------------------------------------------------------------------
    contact_epsilon: object
    """The layer within which a surface is tested for a particle [m], scalar value; it touches once
    its step brings it within kernels.contact.TOUCH_FRACTION of it, or through it."""
    contact_velocity_epsilon: object
    """Approach speed below which a touching particle rests [m/s], scalar value."""
    restitution_threshold_steps: object
    """An approach slower than this many steps of a particle's own pressing impulse (h |f.n| / m)
    is a contact, not an impact [1], scalar value; see resolve_contact."""
    particle_contact: object
    """Tables of contact between jellies and self-contact
    (:class:`~softsim_warp.core.particle_contact.ParticleContact`), or None without either; its
    lists and impulses are each integrator's (:class:`RunState`)."""
    contact_hooks: tuple
    """Callables ``hook(model, state_in, state_out, h, world_contact_beta)`` run after terrain
    contact at every step's end, after jelly contact (``finalize(contact_hooks=...)``; a custom
    force, examples/example_pinned_and_custom_force.py); empty by default."""

    # -- terrain: planes, bowls, spheres (sorted by world) -------------------------------------
    planes: list
    """Host list of the planes' dicts as given (``ModelBuilder.add_plane``, float64, with ``motion``), sorted by world."""
    plane_count: int
    """Number of planes."""
    plane_first: wp.array
    """Index of each world's first plane, shape [world_count + 1], int32 (world w: first[w] .. first[w + 1] - 1)."""
    plane_point: wp.array
    """A point of each plane at t = 0 [m], shape [plane_count], vec3."""
    plane_normal: wp.array
    """Unit normal of each plane at t = 0, shape [plane_count], vec3."""
    plane_hole_center: wp.array
    """Centre of each plane's hole at t = 0 [m], shape [plane_count], vec3."""
    plane_hole_radius: wp.array
    """Radius of each plane's hole [m] (0: none), shape [plane_count], scalar."""
    plane_restitution: wp.array
    """Restitution [1], shape [plane_count], scalar."""
    plane_friction: wp.array
    """Coulomb friction coefficient [1], shape [plane_count], scalar."""
    bowls: list
    """Host list of the bowls' dicts as given, sorted by world."""
    bowl_count: int
    """Number of bowls."""
    bowl_first: wp.array
    """Index of each world's first bowl, shape [world_count + 1], int32."""
    bowl_center: wp.array
    """Sphere centre of each bowl at t = 0 [m], shape [bowl_count], vec3."""
    bowl_radius: wp.array
    """Sphere radius [m], shape [bowl_count], scalar."""
    bowl_cut_height: wp.array
    """The bowl exists where y < cut height [m] (1e30: the whole sphere), shape [bowl_count], scalar."""
    bowl_restitution: wp.array
    """Restitution [1], shape [bowl_count], scalar."""
    bowl_friction: wp.array
    """Coulomb friction coefficient [1], shape [bowl_count], scalar."""
    spheres: list
    """Host list of the solid spheres' dicts as given, sorted by world."""
    sphere_count: int
    """Number of solid spheres."""
    sphere_first: wp.array
    """Index of each world's first sphere, shape [world_count + 1], int32."""
    sphere_center: wp.array
    """Centre of each sphere at t = 0 [m], shape [sphere_count], vec3."""
    sphere_radius: wp.array
    """Radius [m], shape [sphere_count], scalar."""
    sphere_restitution: wp.array
    """Restitution [1], shape [sphere_count], scalar."""
    sphere_friction: wp.array
    """Coulomb friction coefficient [1], shape [sphere_count], scalar."""

    # -- terrain: triangle meshes (core/mesh_terrain.py) ----------------------------------------
    meshes: list
    """Host list of the meshes' dicts (``asset`` in world space, coefficients, world, ``motion``,
    ``samples``), sorted by world."""
    mesh_count: int
    """Number of terrain meshes M."""
    mesh_first: wp.array
    """Index of each world's first mesh, shape [world_count + 1], int32."""
    mesh_bvh: list
    """Host list of the ``wp.Mesh`` objects at t = 0 (kept alive for their ids)."""
    mesh_id: wp.array
    """``wp.Mesh`` ids, shape [M], uint64."""
    mesh_closed: wp.array
    """1 for a closed mesh (inside by winding number), 0 for an open sheet, shape [M], int32."""
    mesh_reach: wp.array
    """How far behind its surface a mesh still pushes particles out [m], shape [M], scalar."""
    mesh_tri_start: wp.array
    """Each mesh's first triangle in ``mesh_tris``, shape [M], int32."""
    mesh_tris: wp.array
    """Vertex indices into ``mesh_points`` of every triangle, shape [sum of triangles], vec3i."""
    mesh_points: wp.array
    """Every mesh's vertices at t = 0 [m], shape [sum of vertices], vec3."""
    mesh_restitution: wp.array
    """Restitution [1], shape [M], scalar."""
    mesh_friction: wp.array
    """Coulomb friction coefficient [1], shape [M], scalar."""
    mesh_animated: wp.array
    """1 for a mesh that follows its asset's time samples, shape [M], int32; None without meshes."""
    mesh_animation: object
    """The animated meshes' time samples (:class:`~softsim_warp.core.mesh_terrain.MeshAnimation`), or None."""

    # -- moving terrain (core/contact.py) -------------------------------------------------------
    terrain_motion: object
    """The motions of the moving planes, bowls, spheres and meshes
    (:class:`~softsim_warp.core.contact.TerrainMotion`), or None when no terrain moves."""
    plane_motion: wp.array
    """Each plane's index among the moving terrain (-1: it stays put), shape [plane_count], int32;
    None without moving terrain (``bowl_motion``, ``sphere_motion`` alike)."""
    bowl_motion: wp.array
    """Each bowl's index among the moving terrain (-1: static), shape [bowl_count], int32, or None."""
    sphere_motion: wp.array
    """Each sphere's index among the moving terrain (-1: static), shape [sphere_count], int32, or None."""
    mesh_motion: wp.array
    """Each mesh's index among the moving terrain (-1: static), shape [M], int32; None without meshes."""

    def __init__(self):
        object.__setattr__(self, "_frozen", False)
        # The lazily made spring list (see the class docstring); the freeze leaves it writable.
        object.__setattr__(self, "_derived", {})

    @classmethod
    def fields(cls) -> tuple:
        """The names of the declared fields, in declaration order."""
        return tuple(name for name in cls.__annotations__ if not name.startswith("_"))

    def _freeze(self):
        """Check that every declared field is set (None for an absent part) and forbid changes."""
        missing = [name for name in self.fields() if name not in self.__dict__]
        if missing:
            raise RuntimeError(f"Model fields not set by finalize: {', '.join(missing)}")
        undeclared = sorted(set(self.__dict__) - set(self.fields()) - {"_frozen", "_derived", "_spring_blocks"})
        if undeclared:
            raise RuntimeError(f"Model attributes not declared: {', '.join(undeclared)}")
        object.__setattr__(self, "_frozen", True)

    def __setattr__(self, name, value):
        if self._frozen:
            raise AttributeError(
                f"a finalized Model is frozen: cannot set {name!r} (give ModelBuilder.finalize what the model needs; "
                "what a run changes belongs to the integrator's RunState)")
        object.__setattr__(self, name, value)

    def __delattr__(self, name):
        if self._frozen:
            raise AttributeError(f"a finalized Model is frozen: cannot delete {name!r}")
        object.__delattr__(self, name)

    def derived(self, key: str, make):
        """Data derived from the model, made by ``make()`` on first use and kept (the freeze allows
        this cache): what is kept must be a function of the model alone, never run state."""
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]

    def has_derived(self, key: str) -> bool:
        """Whether the derived data ``key`` (a lazy spring array's name, or a :meth:`derived` key) has been made."""
        return key in self._derived

    # -- the spring list, lazy on the lattice path ----------------------------------------------

    def _set_spring_host(self, pairs, rest, ks, kd, types):
        """The host spring list (None: empty)."""
        d = self._derived
        d["spring_indices_host"] = pairs if pairs is not None else np.zeros((0, 2), dtype=np.int32)
        d["spring_rest_host"] = rest if rest is not None else np.zeros(0)
        d["spring_stiffness_host"] = ks if ks is not None else np.zeros(0)
        d["spring_damping_host"] = kd if kd is not None else np.zeros(0)
        d["spring_type_host"] = types if types is not None else np.zeros(0, dtype=np.int32)

    def _spring_host(self, name):
        if name not in self._derived:
            self._set_spring_host(*spring_arrays(self.__dict__["_spring_blocks"]))
        return self._derived[name]

    def _make_spring_arrays(self):
        """Copy the spring list to the device (at finalize, or lazily on the lattice path)."""
        np_scalar = NUMPY_SCALARS[self.precision]
        d = self._derived
        d["spring_indices"] = wp.array(np.asarray(self.spring_indices_host, np.int32), dtype=wp.vec2i,
                                       device=self.device)
        for name, host in (
            ("spring_rest_length", self.spring_rest_host),
            ("spring_stiffness", self.spring_stiffness_host),
            ("spring_damping", self.spring_damping_host),
        ):
            d[name] = wp.array(np.asarray(host, np_scalar), dtype=self.scalar, device=self.device)

    def _spring_device(self, name):
        if name not in self._derived:
            self._make_spring_arrays()
        return self._derived[name]

    spring_indices_host = property(lambda self: self._spring_host("spring_indices_host"),
                                   doc="Particle pair (a, b) of each spring, host, shape [S, 2], int32.")
    spring_rest_host = property(lambda self: self._spring_host("spring_rest_host"),
                                doc="Rest length of each spring [m], host, shape [S], float64.")
    spring_stiffness_host = property(lambda self: self._spring_host("spring_stiffness_host"),
                                     doc="ks of each spring [N/m], host, shape [S], float64.")
    spring_damping_host = property(lambda self: self._spring_host("spring_damping_host"),
                                   doc="kd of each spring [N s/m], host, shape [S], float64.")
    spring_type_host = property(lambda self: self._spring_host("spring_type_host"),
                                doc="Type of each spring (lattice.STRUCTURAL, SHEAR, BENDING), host, shape [S], int32.")
    spring_indices = property(lambda self: self._spring_device("spring_indices"),
                              doc="Particle pair (a, b) of each spring, shape [S], vec2i.")
    spring_rest_length = property(lambda self: self._spring_device("spring_rest_length"),
                                  doc="Rest length [m], shape [S], scalar.")
    spring_stiffness = property(lambda self: self._spring_device("spring_stiffness"),
                                doc="ks [N/m], shape [S], scalar.")
    spring_damping = property(lambda self: self._spring_device("spring_damping"),
                              doc="kd [N s/m], shape [S], scalar.")

    # -- terrain on the host (output, metrics) --------------------------------------------------

    @property
    def terrain_anchor_points(self) -> list:
        """Host points spanning the bowls and spheres [m] (for the explosion speed bound)."""
        return terrain_anchors(self.bowls, self.spheres) + mesh_anchors(self.meshes)

    def terrain_meshes(self, roots=None) -> list:
        """Static meshes of the bowls (their cap below the cut) and spheres, for the USD stage.

        Args:
            roots: optional ``{world: prim path}`` under which each world's terrain goes
                (default ``/World``).

        Returns:
            A list of ``(prim_path, points (V, 3), face counts (F,), face indices)``.
        """

        out = []
        for path, kind, it in self._round_terrain(roots):
            if kind == "Bowl":
                mesh = bowl_mesh(it["center"], it["radius"], it["cut_height"])
            else:
                mesh = sphere_mesh(it["center"], it["radius"])
            out.append((path, *mesh))
        return out + mesh_output(self.meshes, roots)

    def terrain_motions(self, roots=None) -> list:
        """``(prim_path, motion)`` of each moving bowl, sphere and mesh among :meth:`terrain_meshes`
        (their meshes are written as given; the motion's rigid map carries them)."""
        meshes = self.meshes
        return [(path, it["motion"]) for path, _kind, it in self._round_terrain(roots) if it.get("motion") is not None] + [
            (path, it["motion"]) for path, it in zip(mesh_paths(meshes, roots or {}), meshes)
            if it.get("motion") is not None]

    def terrain_animations(self, roots=None) -> list:
        """``(prim_path, times [S] s, points [S, V, 3] m)`` of each animated mesh among
        :meth:`terrain_meshes` (its points in its own frame; a rigid motion carries them too)."""
        meshes = self.meshes
        return [(path, *it["samples"]) for path, it in zip(mesh_paths(meshes, roots or {}), meshes)
                if it.get("samples") is not None]

    def _round_terrain(self, roots):
        roots = roots or {}
        for kind, items in (("Bowl", self.bowls), ("Sphere", self.spheres)):
            index = {}  # numbered within each world: every copy of a comparison has Bowl_0
            for it in items:
                i = index[it["world"]] = index.get(it["world"], -1) + 1
                yield f"{roots.get(it['world'], '/World')}/{kind}_{i}", kind, it

    # -- states and run state -------------------------------------------------------------------

    def particle_array(self, values: wp.array | None = None) -> wp.array:
        """A per-particle vec3 array (zeros, or a copy of ``values``) for states and stage buffers.

        On the lattice path it is a view into an allocation ``lattice.pad`` elements longer at both
        ends (zeroed), so the fused stage can read every stencil neighbour without bounds-checked
        loads (``single_stage``); an array made any other way still works, through
        the checked gather.
        """
        pad = self.lattice.pad if self.lattice is not None else 0
        n = self.particle_count
        a = wp.zeros(n + 2 * pad, dtype=self.vec3, device=self.device)
        if pad:
            a = a[pad : pad + n]
        if values is not None:
            wp.copy(a, values)
        return a

    def state(self) -> State:
        """A new state holding the model's initial positions and velocities."""
        s = State()
        s.particle_q = self.particle_array(self.particle_q)
        s.particle_qd = self.particle_array(self.particle_qd)
        return s

    def run_state(self) -> RunState:
        """A new :class:`RunState` at t = 0 for one integrator of this model."""
        return RunState(self)


def _terrain_motion(motion, reference):
    """A terrain primitive's motion (``ModelBuilder.add_plane``): None unless it moves."""
    if motion is None:
        return None
    made = make_motion(**motion)
    if not made["driven"]:
        return None
    if made["center"] is None:
        made["center"] = np.asarray(reference, dtype=np.float64)
    return made


def terrain_anchors(bowls, spheres) -> list:
    """Points spanning bowls (lowest point and rim) and spheres (bounding-box corners) [m]."""
    pts = []
    for b in bowls:
        c, r = b["center"], b["radius"]
        bottom = c - np.array([0.0, r, 0.0])
        top = c + np.array([0.0, min(r, max(b["cut_height"] - c[1], -r)), 0.0])
        pts += [bottom, top]
    for s in spheres:
        pts += [s["center"] - s["radius"], s["center"] + s["radius"]]
    return pts


class State:
    """Positions and velocities of all particles.

    Attributes:
        particle_q: positions [m], shape [particle_count], vec3.
        particle_qd: velocities [m/s], shape [particle_count], vec3.
    """

    def assign(self, other: State):
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)


class RunState:
    """What a run writes besides the particles' positions and velocities, for one integrator.

    ``Integrator.__init__`` makes one (``model.run_state()``) and owns it, so two integrators of one
    model (two :class:`~softsim_warp.core.stepper.Stepper`) never share a clock, a terrain pose or a
    contact impulse, and the :class:`Model` stays as ``finalize`` made it. The step keeps its
    signature ``integrator.step(state_in, state_out, dt)`` instead of taking this object as an
    argument: a captured graph binds the buffers it was captured with, so a run state passed per
    call could not be swapped under a graph anyway, and the integrator already owns its other
    scratch (stage buffers, the implicit solver's vectors), as Newton's solvers own theirs.

    Attributes:
        pin_clock: steps taken by the driven pins (``t = clock dt``), shape [1], int32; None
            without driven pins.
        terrain: the terrain's current poses (:class:`~softsim_warp.core.contact.TerrainPoses`):
            the moving terrain's own geometry arrays and clock, or the model's arrays when nothing moves.
        meshes: the terrain meshes' current vertices and BVHs
            (:class:`~softsim_warp.core.mesh_terrain.MeshPoses`): an animated mesh's own, the
            model's otherwise.
        particle_contact: the candidate lists and impulses of contact between jellies
            (:class:`~softsim_warp.core.particle_contact.ParticleContactState`), or None.
        forces: the force evaluation's scratch (:class:`~softsim_warp.core.forces.ForceWork`).
        contact_hooks: the hooks a step runs after terrain contact: ``particle_contact`` (when
            present), then ``model.contact_hooks``. A list the owner may change (a benchmark
            turns jelly contact off); a graph already captured keeps the hooks it recorded.
    """

    def __init__(self, model: Model):
        self.pin_clock = wp.zeros(1, dtype=wp.int32, device=model.device) if model.pins is not None else None
        self.terrain = TerrainPoses(model)
        self.meshes = MeshPoses(model)
        self.particle_contact = (ParticleContactState(model.particle_contact, model)
                                 if model.particle_contact is not None else None)
        self.forces = ForceWork(model)
        self.contact_hooks = ([self.particle_contact] if self.particle_contact is not None else []) + list(
            model.contact_hooks)

    def reset(self):
        """Back to t = 0: the clocks of pins, moving terrain and animated meshes restart, and no
        contact impulse of an earlier step warm-starts the next one."""
        if self.pin_clock is not None:
            self.pin_clock.zero_()
        self.terrain.reset()
        self.meshes.reset()
        self.forget_contact_history()

    def forget_contact_history(self):
        """Make the next step start from no history of the contact hooks (the warm start of jelly
        contact): for a run restarted from its initial state, so that it is bitwise the run
        without the steps before."""
        for hook in self.contact_hooks:
            forget = getattr(hook, "forget_history", None)
            if forget is not None:
                forget()


def build_model(scene, device=None, precision=None, worlds=None, deterministic=False, force_path="auto") -> Model:
    """Build a :class:`Model` from a validated :class:`~softsim_warp.io.scene.Scene`.

    ``deterministic`` selects atomic-free force evaluation (see ``ModelBuilder.finalize``);
    ``force_path``: see ``ModelBuilder.finalize``.
    """
    builder = ModelBuilder(scene.sim["gravity"])
    builder.device = device
    populate(builder, scene.data)
    return builder.finalize(device, precision or scene.sim["precision"], force_path=force_path,
                            deterministic=deterministic)


def populate(builder: ModelBuilder, data: dict, world=0):
    """Add a validated scene's jellies and terrain to ``builder`` as world ``world``."""
    sim = data["simulation"]
    builder.contact_epsilon = sim["contact_epsilon"]
    builder.contact_velocity_epsilon = sim["contact_velocity_epsilon"]
    builder.restitution_threshold_steps = sim["restitution_threshold_steps"]
    infos = []
    # "auto": contact between jellies when the scene (one world's worth) has two or more. The
    # settings are the model's, one for all worlds: copies that differ in them are refused.
    jelly_contact = sim.get("jelly_contact", "auto")
    settings = (
        len(data["jelly"]) >= 2 if jelly_contact == "auto" else bool(jelly_contact),
        sim.get("jelly_contact_thickness"),
        sim.get("jelly_contact_friction", particle_contact.DEFAULT_FRICTION),
        sim.get("jelly_contact_restitution", particle_contact.DEFAULT_RESTITUTION),
        sim.get("jelly_contact_iterations", particle_contact.DEFAULT_ITERATIONS),
    )
    if builder.jellies and getattr(builder, "_jelly_contact_settings", settings) != settings:
        raise SceneError(
            "scene",
            "simulation.jelly_contact",
            "contact between jellies (jelly_contact and its thickness, friction, restitution, iterations) "
            "must be the same in every copy",
            list(settings),
        )
    builder._jelly_contact_settings = settings
    (
        builder.jelly_contact,
        builder.jelly_contact_thickness,
        builder.jelly_contact_friction,
        builder.jelly_contact_restitution,
        builder.jelly_contact_iterations,
    ) = settings
    for i, j in enumerate(data["jelly"]):
        if "mesh" in j:  # a mesh voxelised into a masked lattice (the cells its solid touches)
            infos.append(add_mesh_jelly(builder, j, world=world, name=f"Jelly_{i}", key=f"jelly.{i}"))
            continue
        info = builder.add_jelly(
            j["resolution"],
            j["size"],
            j["particle_mass"],
            j["springs"],
            center=j["center"],
            axis=j["rotation"]["axis"],
            degrees=j["rotation"]["degrees"],
            velocity=j["velocity"],
            angular_velocity=j["angular_velocity"],
            world=world,
            name=f"Jelly_{i}",
            initial_scale=j.get("initial_scale"),
            self_contact=j.get("self_contact", False),
        )
        infos.append(info)
    for p in data.get("plane", []):
        hole = p.get("hole")
        builder.add_plane(
            p["point"],
            p["normal"],
            p["restitution"],
            p["friction"],
            hole_center=hole["center"] if hole else None,
            hole_radius=hole["radius"] if hole else 0.0,
            size=p["size"],
            world=world,
            motion=motion_arguments(p["motion"]) if "motion" in p else None,
        )
    for b in data.get("bowl", []):
        builder.add_bowl(b["center"], b["radius"], b.get("cut_height"), b["restitution"], b["friction"], world=world,
                         motion=motion_arguments(b["motion"]) if "motion" in b else None)
    for s in data.get("sphere", []):
        builder.add_sphere(s["center"], s["radius"], s["restitution"], s["friction"], world=world,
                           motion=motion_arguments(s["motion"]) if "motion" in s else None)
    for i, t in enumerate(data.get("mesh", [])):
        asset = load_mesh(t["path"], t.get("prim"), key=f"mesh.{i}.path", **mesh_options(t))
        asset = asset.transformed(*transform_matrix(t.get("transform")))
        # The output prim is named after the asset's Mesh (Stairs_0); several merged Meshes: Mesh_0.
        name = asset.name if asset.name.isidentifier() else "Mesh"
        samples = None
        if t.get("animated"):
            times, points = load_mesh_samples(t["path"], t.get("prim"), key=f"mesh.{i}.path", **mesh_options(t))
            matrix, shift = transform_matrix(t.get("transform"))
            samples = (times, points @ np.asarray(matrix, dtype=np.float64).T + np.asarray(shift, dtype=np.float64))
        builder.add_mesh(asset, t["restitution"], t["friction"], t["thickness"], world=world, name=name,
                         motion=motion_arguments(t["motion"]) if "motion" in t else None, samples=samples)
    for p in data.get("pin", []):
        builder.add_pin(np.asarray(p["indices"]) + infos[p["jelly"]].particle_start, **motion_arguments(p))


def motion_arguments(entry: dict) -> dict:
    """The keyword arguments of ``core/pins.make_motion`` from a validated scene's motion keys (a
    pin's, or a terrain entry's ``motion`` table)."""
    spin = entry.get("spin")
    keys = entry.get("keyframes", [])
    return {
        "velocity": entry["velocity"],
        "spin": np.asarray(spin["axis"]) * math.radians(spin["degrees_per_second"]) if spin else (0.0, 0.0, 0.0),
        "center": spin.get("center") if spin else None,
        "key_times": [k["time"] for k in keys],
        "key_offsets": [k["offset"] for k in keys],
        "interpolation": entry["interpolation"],
    }
