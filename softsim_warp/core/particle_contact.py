"""Contact between jellies and self-contact: which particles take part, the candidate lists, the launches.

``ModelBuilder.finalize`` gives a model a :class:`ParticleContact` (``model.particle_contact``, its
fixed tables) when its scene asks for contact between jellies or for a jelly's self-contact; a model
without either gets nothing (no array, no launch). Each integrator's ``RunState`` holds a
:class:`ParticleContactState` (the candidate lists, contacts and impulses, which a step writes),
the hook that runs after every step, after terrain contact (``core/contact.apply_contacts``), and
launches (kernels/particle_contact/ explains each):

1. ``prepare_contact_particles``: the positions of the surface particles of the jellies that take
   part, each with its contact radius, copied to a compact array (a lattice's interior particles
   cannot touch anything before its surface does), their boundary-face normals, and the rebuild
   flag (a particle moved half the skin);
2. ``insert_contact_grid`` and ``build_contact_candidates``: the candidate lists, rebuilt only when
   the flag is raised (otherwise both return at once);
3. ``find_particle_contacts``: each particle's contacts among its candidates, each started from the
   pair's impulse of the step before (the warm start);
4. ``resolve_contact_velocities`` (``iterations - 1`` times: the pairs' impulses accumulate over the
   step) and ``resolve_contact_last_pass`` (the last iteration, and the positions and velocities
   written back).

Every launch has a fixed size and every array is allocated here, so a step with contact is captured
as a graph (CUDA and CPU) like any other.

Which pairs: particles of different jellies of one world (``jelly_contact``), and particles of one
jelly with ``self_contact`` that are at least :data:`SELF_EXCLUSION` pair distances apart in the
rest shape. Closer pairs are excluded: at rest they are the jelly's own neighbourhood (its springs
reach two lattice spacings, the bending springs), which its springs keep apart; a contact between
them would fight the springs whenever the jelly is compressed by half, where no surface meets
another. Surfaces that fold onto each other meet at particles many spacings apart.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from . import lattice
from .errors import SceneError
from .lattice_model import LatticeData
from ..kernels.particle_contact import CANDIDATE_REACH
from ..kernels import particle_contact as particle_contact_kernels

# Defaults of the scene keys [simulation] jelly_contact_friction and jelly_contact_restitution.
DEFAULT_FRICTION = 0.5
DEFAULT_RESTITUTION = 0.0
# Jacobi iterations of the velocity response per step (scene key jelly_contact_iterations).
DEFAULT_ITERATIONS = 1
# Pair distance of two particles of jellies whose largest lattice spacings are s1 and s2, without
# jelly_contact_thickness: (s1 + s2) / 2 * THICKNESS_PER_SPACING. One spacing keeps a particle from
# slipping through a face of the other lattice (it meets the face's corners at s / sqrt(2)).
THICKNESS_PER_SPACING = 1.0
# Same-jelly pairs closer than this many pair distances in the rest shape never touch.
SELF_EXCLUSION = 2.0
# Contacts a particle keeps in its list for the velocity passes; one with more (rare:
# a pair distance of one spacing gives a particle resting on a face 1 to 4) tests its candidates again.
MAX_CONTACTS = 16
# Candidates a particle's list holds; one with more (a jelly crushed to well below its spacing) walks
# the grid of the last build instead, in the same order. At most 32: find_particle_contacts marks a
# list's near candidates in the bits of an int32.
MAX_CANDIDATES = 32
# Threads a block of the per-step contact passes (find and the velocity passes), below Warp's 256: a
# thread's work varies with its contacts, and a block holds its share of the SM until its slowest
# warp is done, so smaller blocks waste less of it (measured in docs/CONTACT.md).
PASS_BLOCK = 128
# The kernels address their slot-major tables from the data pointer with 32-bit element offsets. For n
# contact particles the largest are 3 (2 MAX_CONTACTS n - 1) (the contacts' impulses, this step's and
# the last), MAX_CANDIDATES n - 1 and 9 n - 1 (the face normals, the lattice neighbours): at most
# 22,369,621 contact particles, about 45 million particles in jellies of 10^3. The particle state's
# largest offset is 3 (particles - 1).
MAX_CONTACT_PARTICLES = min((2**31 - 1 + 3) // (6 * MAX_CONTACTS), 2**31 // MAX_CANDIDATES, 2**31 // 9)
MAX_PARTICLES = (2**31 - 1) // 3 + 1

# The candidate lists' skin, in the smallest pair distance: a list holds the pairs within
# CANDIDATE_REACH d + skin, and it is rebuilt when a particle has moved skin / 2 since it was built.
# A larger skin means fewer builds but longer lists for the contacts' search to walk; 0.375 is where
# the two balance (docs/CONTACT.md, "The skin").
SKIN = 0.375
# What rebuild_distance keeps below skin / 2, in skins: room for the rounding of the distances.
SKIN_ROUNDING = 1.0 / 64.0


def surface_mask(shape, present=None) -> np.ndarray:
    """Boolean mask (lattice order) of a lattice's surface particles: present points with an axis
    neighbour missing, at the lattice's end (any coordinate at 0 or n - 1) or absent from ``present``
    (a mesh jelly's masked lattice; None: every point is present)."""
    shape = tuple(int(n) for n in shape)
    n = int(np.prod(shape))
    present = np.ones(n, dtype=bool) if present is None else np.asarray(present, dtype=bool)
    nb = axis_neighbors(shape, np.arange(n), present)
    return present & np.any(nb[:, :6] == np.arange(n)[:, None], axis=1)


def axis_neighbors(shape, local, present=None) -> np.ndarray:
    """Lattice neighbours of lattice points ``local``, shape [len(local), 9]: slots 0..5 the
    neighbours at -x, +x, -y, +y, -z, +z (the point itself where the lattice ends or the neighbour
    is absent from ``present``), slots 6..8 the neighbour one step inward on each axis where exactly
    one side is missing (-1 on an axis where neither or both are, or where the lattice has one
    particle). Indices are lattice indices; for a full lattice they are the jelly-local particles."""
    shape = np.array([int(n) for n in shape])
    local = np.asarray(local)
    if present is None:
        present = np.ones(int(np.prod(shape)), dtype=bool)
    ijk = np.stack(np.unravel_index(local, tuple(shape)), axis=1)
    out = np.full((ijk.shape[0], 9), -1, dtype=np.int64)
    for a in range(3):
        for slot, step in ((2 * a, -1), (2 * a + 1, 1)):
            nb = ijk.copy()
            nb[:, a] = np.clip(nb[:, a] + step, 0, shape[a] - 1)
            idx = np.ravel_multi_index(tuple(nb.T), tuple(shape))
            out[:, slot] = np.where(present[idx], idx, local)
        if shape[a] < 2:
            continue
        minus, plus = out[:, 2 * a] == local, out[:, 2 * a + 1] == local
        step = np.where(minus & ~plus, 1, np.where(plus & ~minus, -1, 0))
        nb = ijk.copy()
        nb[:, a] = np.clip(nb[:, a] + step, 0, shape[a] - 1)
        out[:, 6 + a] = np.where(step != 0, np.ravel_multi_index(tuple(nb.T), tuple(shape)), -1)
    return out


def face_order(surface, neighbors):
    """The order that groups lattice points ``surface`` (ascending) by the sides their lattice
    neighbours are missing on, from their :func:`axis_neighbors` rows: each face's points together,
    then each edge's, then each corner's, each group in lattice order. Returns the order and each
    ordered point's number of missing sides (1 on a face, 2 on an edge, 3 at a corner; more on a
    mesh jelly's thin parts)."""
    missing = neighbors[:, :6] == np.asarray(surface)[:, None]
    sides = missing.sum(axis=1)
    key = (missing * (1 << np.arange(6))).sum(axis=1)
    order = np.lexsort((surface, key, sides))
    return order, sides[order]


def _surface_tables(info):
    """A jelly's contact particles in contact order (:func:`face_order`), jelly-local: ``(particles,
    their axis neighbours as particles (-1: none), missing sides, boundary faces, rest points in the
    jelly's frame)``."""
    points = int(np.prod(info.shape))
    present, to_particle = np.ones(points, dtype=bool), np.arange(points)
    if getattr(info, "lattice_index", None) is not None:
        present = np.zeros(points, dtype=bool)
        present[info.lattice_index] = True
        to_particle = np.full(points, -1)
        to_particle[info.lattice_index] = np.arange(info.lattice_index.size)
    surface = np.flatnonzero(surface_mask(info.shape, present))
    nb = axis_neighbors(info.shape, surface, present)
    by_face, n_sides = face_order(surface, nb)
    surface, nb = surface[by_face], nb[by_face]
    n_faces = (nb[:, 6:9] >= 0).sum(axis=1)  # the boundary faces it lies on (its normals)
    size = [s * (n - 1) for s, n in zip(info.spacing, info.shape)]
    rest = lattice.lattice_points(info.shape, size)[surface]
    nb = np.where(nb >= 0, to_particle[np.maximum(nb, 0)], -1)
    return to_particle[surface], nb, n_sides, n_faces, rest


def jelly_radius(info, thickness=None) -> float:
    """Contact radius of a jelly's particles [m]: half the pair distance between two of its particles."""
    if thickness is not None:
        return 0.5 * float(thickness)
    return 0.5 * THICKNESS_PER_SPACING * max(info.spacing)


class ParticleContact:
    """The fixed tables of contact between jellies of a model (``Model.particle_contact``): the
    contact particles, their radii, neighbours and coefficients; what a step writes is each run's
    :class:`ParticleContactState`.

    Attributes:
        count: contact particles (surface particles of the jellies taking part).
        contact_index: particle index of each contact particle, shape [count], int32: the face
            particles of every jelly, then the edges', then the corners' (:func:`face_order`).
        contact_jelly, contact_world: its jelly and world, shape [count], int32.
        contact_radius: its contact radius [m] (a pair touches within the sum), shape [count], scalar.
        face_start: the first contact index of the particles on at least 1, 2 and 3 boundary faces
            (the contact order groups them by that number), wp.vec3i.
        contact_rest: its rest position in its jelly's frame [m] (self-contact exclusion), shape
            [count] with self-contact, [1] without, vec3.
        jelly_self_contact: 1 where a jelly has self-contact, shape [jelly_count], int32.
        between_jellies: 1 when particles of different jellies touch.
        friction, restitution: Coulomb coefficient and restitution between particles [1].
        skin: the candidate lists' skin [m]: a list holds the pairs within CANDIDATE_REACH d + skin
            at its build, and it is rebuilt once a particle has moved ``rebuild_distance`` (just
            under skin / 2) since.
        contact_inv_mass: each contact particle's inverse mass [1/kg], shape [count], scalar.
        iterations: Jacobi iterations of the velocity response per step.
    """

    def __init__(
        self, model, between_jellies: bool, thickness, friction: float, restitution: float, iterations=None
    ):
        iterations = DEFAULT_ITERATIONS if iterations is None else iterations
        jellies = model.jellies
        self_flags = [bool(getattr(j, "self_contact", False)) for j in jellies]
        taking_part = [between_jellies or s for s in self_flags]
        device, scalar, vec3 = model.device, model.scalar, model.vec3
        index, jelly, world, radius, rest, neighbors, sides, faces = [], [], [], [], [], [], [], []
        whole = {}  # a whole lattice's surface tables by shape and spacing: jellies alike share them
        for jid, (info, part) in enumerate(zip(jellies, taking_part)):
            if not part:
                continue
            # A mesh jelly is a lattice with points missing (info.lattice_index: its particles' points).
            masked = getattr(info, "lattice_index", None) is not None
            key = (tuple(int(n) for n in info.shape), tuple(info.spacing))
            if masked or key not in whole:
                tables = _surface_tables(info)
                if not masked:
                    whole[key] = tables
            else:
                tables = whole[key]
            local, nb, n_sides, n_faces, rest_points = tables
            sides.append(n_sides)
            faces.append(n_faces)
            index.append(local + info.particle_start)
            jelly.append(np.full(local.size, jid))
            world.append(np.full(local.size, info.world))
            radius.append(np.full(local.size, jelly_radius(info, thickness)))
            rest.append(rest_points)
            neighbors.append(np.where(nb >= 0, nb + info.particle_start, -1))
        # The contact order: every jelly's face particles first (jelly by jelly, face by face),
        # then the edges' and then the corners' (:func:`face_order`). The 32 threads of a warp then
        # lie on one face of one jelly, so they meet the same neighbouring surface, with about as
        # many candidates and contacts each and their partners close together in memory; a 10^3
        # jelly's 384 face particles are 12 whole warps. (Lattice order mixes four faces in a warp
        # of its middle layers, and a warp waits for its lane with the most pairs.) Grouped first by
        # their number of boundary faces (the sides for a box jelly), so a particle's number of face
        # normals follows from its index (face_start): a partner's empty normal slots are not read.
        if sides:
            n_faces = np.concatenate(faces)
            order = np.lexsort((np.concatenate(sides), n_faces))
            self.face_start = wp.vec3i(*(int(np.searchsorted(n_faces[order], f)) for f in (1, 2, 3)))
        else:
            order = np.zeros(0, dtype=np.int64)
            self.face_start = wp.vec3i(0, 0, 0)

        def cat(parts, shape):
            return np.concatenate(parts)[order] if parts else np.zeros(shape)

        np_index = cat(index, (0,)).astype(np.int32)
        self.count = int(np_index.size)
        check_capacity(self.count, model.particle_count)
        self.between_jellies = int(bool(between_jellies))
        self.friction = scalar(friction)
        self.restitution = scalar(restitution)
        self.self_exclusion = scalar(SELF_EXCLUSION)
        np_radius = cat(radius, (0,))
        # The skin from the smallest pair distance; the grid's cells are as wide as the largest
        # candidate reach, so a particle's candidates lie in its own and the 26 cells around it.
        self.skin_host = float(SKIN * 2.0 * np_radius.min()) if self.count else 0.0
        self.skin = scalar(self.skin_host)
        self.rebuild_distance = scalar(self.skin_host * (0.5 - SKIN_ROUNDING))
        cell = float(CANDIDATE_REACH * 2.0 * np_radius.max()) + self.skin_host if self.count else 1.0
        self.inv_cell = scalar(1.0 / cell)
        # About two buckets per contact particle (Fibonacci hashing keeps the top bits).
        bits = int(max(4, math.ceil(math.log2(max(2 * self.count, 1)))))
        self.shift = 32 - bits
        np_scalar = np.float64 if scalar == wp.float64 else np.float32

        def arr(values, dtype, np_dtype):
            return wp.array(np.asarray(values, dtype=np_dtype), dtype=dtype, device=device)

        self.contact_index = arr(np_index, wp.int32, np.int32)
        self.contact_jelly = arr(cat(jelly, (0,)), wp.int32, np.int32)
        self.contact_world = arr(cat(world, (0,)), wp.int32, np.int32)
        self.contact_radius = arr(np_radius, scalar, np_scalar)
        rest_host = cat(rest, (0, 3)) if any(self_flags) else np.zeros((1, 3))
        self.contact_rest = arr(rest_host, vec3, np_scalar)
        # Slot-major, [9, count]: a warp reads each slot of its particles in one coalesced load.
        neighbors_host = cat(neighbors, (0, 9)).astype(np.int32).reshape(-1, 9)
        self.contact_axis_neighbors = wp.array(np.ascontiguousarray(neighbors_host.T), dtype=wp.int32, device=device)
        self.jelly_self_contact = arr(np.asarray(self_flags, dtype=np.int32).reshape(-1), wp.int32, np.int32)
        # The inverse masses (fixed when the model is built).
        self.contact_inv_mass = arr(model.particle_inv_mass.numpy()[np_index], scalar, np_scalar)
        self.iterations = int(iterations)
        self.bucket_bits = bits
        self.np_scalar = np_scalar


class ParticleContactState:
    """The candidate lists, contacts and impulses of contact between jellies for one run (part of
    ``RunState``), and the hook that a step runs after terrain contact.

    Attributes other than the ones below are read from the model's fixed tables
    (:class:`ParticleContact`: ``count``, ``contact_index``, ...), so a test or benchmark reads one
    object.

    Attributes:
        tables: the model's :class:`ParticleContact`.
        normal: boundary-face normals of the contact particles, slot-major, shape [3, count], vec3.
        spheres: compact positions after the step with the contact radius, shape [count], vec4.
        candidates, candidate_count: each particle's candidates, shape [MAX_CANDIDATES, count]
            (slot-major, ascending), and their number (MAX_CANDIDATES + 1: more than the list
            holds, the grid walk takes over), int32.
        x_build, rebuild: the lists' build positions [m] and the flag that asks for a rebuild.
        builds: how many times the lists were built, shape [1], int32 (:meth:`builds_done`).
        contact_counts, contact_lists, contact_impulse: contacts per particle, shape [2 count], their
            partners (ascending) and the pairs' impulses on the particle, shape [2 MAX_CONTACTS,
            count], in two halves: the last step's (``phase``, flipped at the start of each step) and
            the one before, which the warm start reads. :attr:`contacts` and :attr:`contact_list`
            are the last step's halves.
    """

    # Not part of the implicit integrator's contact solve, which prescribes each touched particle's
    # own normal velocity (right for fixed terrain, but it would stop both jellies of a pair and
    # lose their momentum); the pair projection after the step conserves it.
    in_contact_solve = False

    def __init__(self, tables: ParticleContact, model):
        self.tables = tables
        device, scalar, vec3 = model.device, model.scalar, model.vec3
        n, bits, np_scalar = tables.count, tables.bucket_bits, tables.np_scalar
        # Boundary-face normals, slot-major: a particle's faces in its first slots
        # (prepare_contact_particles writes only those), the slots after them zero from here.
        self.normal = wp.zeros((3, n), dtype=vec3, device=device)
        # A compact copy of the positions after the step, each with its particle's contact radius
        # in a vec4 (a partner's position and radius in one aligned load; the passes read it, never
        # what they write). The velocities after and before the step are read where they are
        # (state_out, state_in, through contact_index): only for the particles in contact.
        vec4 = wp.types.vector(4, scalar)
        self.spheres = wp.zeros(n, dtype=vec4, device=device)
        # Candidate lists (slot-major), their build positions, the flag that asks for a rebuild
        # (raised: the first step builds) and the count of builds.
        self.x_build = wp.zeros(n, dtype=vec3, device=device)
        if not 0 < MAX_CANDIDATES <= 32:
            raise ValueError(f"MAX_CANDIDATES must lie in 1..32, got {MAX_CANDIDATES}")
        self.candidates = wp.zeros((MAX_CANDIDATES, n), dtype=wp.int32, device=device)
        self.candidate_count = wp.zeros(n, dtype=wp.int32, device=device)
        self.rebuild = wp.ones(1, dtype=wp.int32, device=device)
        self.builds = wp.zeros(1, dtype=wp.int32, device=device)
        # The hashed cell grid of the builds: two tables of bucket heads, the links, each
        # particle's bucket.
        self.grid_head = wp.full((2, 1 << bits), -1, dtype=wp.int32, device=device)
        self.grid_next = wp.full(n, -1, dtype=wp.int32, device=device)
        self.cell_bucket = wp.zeros(n, dtype=wp.int32, device=device)
        # Contacts: per particle its count; per contact (slot-major) its partner, normal, gap and
        # approach speed before the step.
        self.contact_counts = wp.zeros(2 * n, dtype=wp.int32, device=device)
        self.contact_lists = wp.zeros((2 * MAX_CONTACTS, n), dtype=wp.int32, device=device)
        self.contact_impulse = wp.zeros((2 * MAX_CONTACTS, n), dtype=vec3, device=device)
        self.phase = wp.zeros(1, dtype=wp.int32, device=device)
        # The passes' records (find_particle_contacts): per particle two vec4, 32 bytes in float32, so
        # a pass reads all it needs of a partner in one memory sector; the kernels load each entry
        # in one aligned load, which needs the array aligned to an entry.
        self.warm_records = wp.zeros(2 * n, dtype=vec4, device=device)
        self.contact_normal = wp.zeros((MAX_CONTACTS, n), dtype=vec3, device=device)
        self.contact_gap = wp.zeros((MAX_CONTACTS, n), dtype=scalar, device=device)
        # The approach speed only with a restitution, the one reader (store_contact writes it only then).
        u0_shape = (MAX_CONTACTS, n) if float(tables.restitution) != 0.0 else (1, 1)
        self.contact_u0 = wp.zeros(u0_shape, dtype=scalar, device=device)
        self.pass_records = [wp.zeros(2 * n, dtype=vec4, device=device) for _ in range(min(self.iterations - 1, 2))]
        for rec in [self.spheres, self.warm_records, *self.pass_records]:
            if rec.ptr % (4 * np.dtype(np_scalar).itemsize) != 0:
                raise RuntimeError("jelly contact: a vec4 array is not aligned to its entries")

    def __getattr__(self, name):
        # Only called for names this object lacks: the model's fixed tables.
        if name == "tables":
            raise AttributeError(name)
        return getattr(self.tables, name)

    def forget_history(self):
        """No pair starts the next step warm: the contact counts of the step before are zero."""
        self.contact_counts.zero_()

    @property
    def contacts(self):
        """Each particle's number of contacts in the last step, shape [count], int32 (a view)."""
        half = int(self.phase.numpy()[0])
        return self.contact_counts[half * self.count : (half + 1) * self.count]

    @property
    def contact_list(self):
        """The last step's contact lists, shape [MAX_CONTACTS, count] (a view)."""
        half = int(self.phase.numpy()[0])
        return self.contact_lists[half * MAX_CONTACTS : (half + 1) * MAX_CONTACTS]

    def builds_done(self) -> int:
        """How many times the candidate lists were built (a metric: reads the device)."""
        return int(self.builds.numpy()[0])

    def __call__(self, model, state_in, state_out, h, world_contact_beta):
        if self.count == 0:
            return
        device = model.device
        n = self.count
        # The kernels address the particle state from its data pointer, like the fused stages.
        LatticeData.check_contiguous(state_out.particle_q, state_out.particle_qd, who="the jelly contact kernels")
        wp.launch(
            particle_contact_kernels.prepare_contact_particles,
            dim=n,
            inputs=[
                self.contact_index,
                self.contact_axis_neighbors,
                self.contact_radius,
                self.x_build,
                self.rebuild_distance,
                state_out.particle_q,
            ],
            outputs=[self.spheres, self.normal, self.rebuild, self.phase],
            device=device,
        )
        wp.launch(
            particle_contact_kernels.insert_contact_grid,
            dim=n,
            inputs=[self.rebuild, self.builds, self.contact_world, self.inv_cell, self.shift, self.spheres],
            outputs=[self.cell_bucket, self.grid_head, self.grid_next],
            device=device,
        )
        pairs = [
            self.contact_jelly,
            self.contact_world,
            self.contact_radius,
            self.contact_rest,
            self.jelly_self_contact,
            self.between_jellies,
            self.self_exclusion,
            self.skin,
        ]
        wp.launch(
            particle_contact_kernels.build_contact_candidates,
            dim=n,
            inputs=[
                self.rebuild, self.builds, self.grid_head, self.grid_next, self.inv_cell, self.shift, *pairs, self.spheres
            ],
            outputs=[self.x_build, self.candidates, self.candidate_count],
            device=device,
        )
        walk = [
            self.candidates,
            self.candidate_count,
            self.grid_head,
            self.grid_next,
            self.inv_cell,
            self.shift,
            self.x_build,
            *pairs,
        ]
        wp.launch(
            particle_contact_kernels.find_particle_contacts,
            dim=n,
            inputs=[
                *walk, self.restitution, self.friction, self.phase, self.spheres, self.contact_index,
                state_out.particle_qd, state_in.particle_qd, self.contact_inv_mass, self.normal, self.face_start,
            ],
            outputs=[
                self.contact_counts, self.contact_lists, self.contact_impulse, self.contact_normal,
                self.contact_gap, self.contact_u0, self.warm_records,
            ],
            device=device,
            block_dim=PASS_BLOCK,
        )
        v_in = self.warm_records
        for it in range(self.iterations - 1):
            v_out = self.pass_records[it % 2]
            wp.launch(
                particle_contact_kernels.resolve_contact_velocities,
                dim=n,
                inputs=[
                    *walk,
                    self.friction,
                    self.restitution,
                    model.contact_velocity_epsilon,
                    model.restitution_threshold_steps,
                    self.spheres,
                    self.contact_index,
                    state_in.particle_qd,
                    self.normal,
                    self.face_start,
                    self.contact_counts,
                    self.contact_lists,
                    self.contact_normal,
                    self.contact_u0,
                    self.phase,
                    v_in,
                    self.contact_impulse,
                ],
                outputs=[v_out],
                device=device,
                block_dim=PASS_BLOCK,
            )
            v_in = v_out
        wp.launch(
            particle_contact_kernels.resolve_contact_last_pass,
            dim=n,
            inputs=[
                *walk,
                self.friction,
                self.restitution,
                model.contact_velocity_epsilon,
                model.restitution_threshold_steps,
                h,
                world_contact_beta,
                self.spheres,
                self.contact_index,
                state_in.particle_qd,
                self.normal,
                self.face_start,
                self.contact_counts,
                self.contact_lists,
                self.contact_normal,
                self.contact_gap,
                self.contact_u0,
                self.phase,
                v_in,
                self.contact_impulse,
                self.rebuild,
                self.builds,
            ],
            outputs=[state_out.particle_q, state_out.particle_qd],
            device=device,
            block_dim=PASS_BLOCK,
        )


def wanted(between_jellies: bool, jellies) -> bool:
    """Whether a model needs the hook: contact between jellies, or a jelly with self-contact."""
    return bool(between_jellies) or any(getattr(j, "self_contact", False) for j in jellies)


def check_capacity(count: int, particles: int):
    """Refuse more particles than the kernels' 32-bit element offsets address (a user error): the
    contact particles' tables, and the particle state, read and written at 3 scalars a particle."""
    if count > MAX_CONTACT_PARTICLES or particles > MAX_PARTICLES:
        raise SceneError(
            "scene",
            "simulation.jelly_contact",
            f"contact between jellies and self-contact take at most {MAX_CONTACT_PARTICLES:,} surface particles "
            f"in a model of at most {MAX_PARTICLES:,} particles; turn them off or use coarser jellies",
            [count, particles],
        )
