"""When a model's springs are regular lattices: detection and the per-jelly tables of the lattice path.

A model takes the lattice path (``kernels/lattice.py``) when every particle belongs to a jelly and
every spring is one of its jelly's standard stencil springs (``lattice.lattice_springs``), each
present spring type complete, with one ks and kd per type and one rest length per stencil offset.
Rest lengths are read from the springs themselves, so a jelly started rotated (rest = initial
distance, equal for every spring of an offset) or with rest lengths scaled per offset still
qualifies; springs with individual rest lengths, extra springs or loose particles do not, and
the model keeps the general spring list.

``ModelBuilder.add_jelly`` records a whole lattice jelly as one :class:`LatticeSprings` instead of
a spring list; :func:`recorded_lattice` makes the tables from those records (the same tables
:func:`detect_lattice` finds in the list), and :func:`spring_arrays` makes the list itself only
for a consumer that reads it (the spring-list force path, the implicit integrator, ``--springs``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from . import lattice
from ..kernels.lattice import COEF_LENGTH, HALF_OFFSETS, REST_SLOTS, common_coefficients, rest_slot
from ..kernels import lattice as lattice_kernels

# Rest lengths of one stencil offset count as one value when they agree to this relative
# tolerance: float64 rounding of initial distances in a rotated lattice is ~1e-16.
REST_TOLERANCE = 1e-9

# The spring type whose offsets use each rest slot (0 for a slot no offset uses: it stays 0).
_SLOT_TYPE = np.zeros(REST_SLOTS, dtype=np.int64)
for _off, _t in HALF_OFFSETS:
    _SLOT_TYPE[[rest_slot(*_off), rest_slot(*(-o for o in _off))]] = _t


@dataclass
class LatticeLayout:
    """Host tables of the lattice path, one row per jelly."""

    start: np.ndarray
    """First particle of each jelly, shape [J], int32."""
    shape: np.ndarray
    """Particles per axis (nx, ny, nz), shape [J, 3], int32."""
    types: np.ndarray
    """Bit t set when spring type t (lattice.STRUCTURAL, SHEAR, BENDING) is present, shape [J], int32."""
    rest: np.ndarray
    """Rest length per stencil offset [m], shape [J, REST_SLOTS], float64 (see kernels.lattice.rest_slot)."""
    ks: np.ndarray
    """Stiffness per spring type [N/m], shape [J, 3], float64."""
    kd: np.ndarray
    """Damping per spring type [N s/m], shape [J, 3], float64."""
    world: np.ndarray
    """World of each jelly, shape [J], int32."""


@dataclass(eq=False)
class LatticeSprings:
    """One whole lattice jelly's springs as ``ModelBuilder.add_jelly`` records them: for each
    present spring type, every standard stencil spring of ``shape`` (``lattice.lattice_springs``)
    with the type's ks and kd and the rest length of its ends in ``rest_pose``."""

    shape: tuple
    """Particles per axis (nx, ny, nz)."""
    start: int
    """Index of the jelly's first particle."""
    types: int
    """Bit t set when spring type t has springs."""
    ks: np.ndarray
    """Stiffness per spring type [N/m], shape [3], float64 (0 for an absent type)."""
    kd: np.ndarray
    """Damping per spring type [N s/m], shape [3], float64."""
    rest_pose: np.ndarray
    """The unscaled placed lattice the rest lengths are measured in [m], shape [N, 3], float64;
    shared, read-only, by jellies placed alike."""
    world: int
    count: int
    """Springs in all."""

    def arrays(self, springs_of=None, rest_of=None) -> list[tuple]:
        """The spring list ``add_spring`` makes for this jelly: one ``(pairs, rest, ks, kd, type)``
        block per present type, in type order.

        ``springs_of`` and ``rest_of``: optional dicts that keep ``lattice_springs`` per shape and the
        rest lengths per pose between calls (jellies of one shape or one pose share them).
        """
        springs_of = {} if springs_of is None else springs_of
        rest_of = {} if rest_of is None else rest_of
        if self.shape not in springs_of:
            pairs, types = lattice.lattice_springs(self.shape)
            springs_of[self.shape] = pairs, types, [types == t for t in range(3)]
        pairs, types, selected = springs_of[self.shape]
        key = id(self.rest_pose)
        if key not in rest_of:
            q = self.rest_pose
            rest_of[key] = (q, np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1))
        rest = rest_of[key][1]
        out = []
        for t in range(3):
            if not (self.types >> t) & 1:
                continue
            sel = selected[t]
            n = int(np.count_nonzero(sel))
            out.append((pairs[sel] + np.int32(self.start), rest[sel], np.full(n, self.ks[t]), np.full(n, self.kd[t]),
                        np.full(n, t, dtype=np.int32)))
        return out


def spring_arrays(blocks) -> tuple:
    """The spring list of a builder's blocks (each a ``LatticeSprings`` or a ``(pairs, rest, ks, kd,
    type)`` tuple), concatenated: ``(pairs [S, 2] int32, rest, ks, kd [S] float64, type [S] int32)``."""
    springs_of, rest_of = {}, {}
    parts = []
    for block in blocks:
        parts += block.arrays(springs_of, rest_of) if isinstance(block, LatticeSprings) else [block]
    if not parts:
        return (np.zeros((0, 2), dtype=np.int32), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int32))
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


def rest_tables(poses, shape) -> tuple[np.ndarray, np.ndarray]:
    """Rest length per stencil offset of lattices of one ``shape`` placed at ``poses`` ([G, N, 3]).

    Returns ``(rest [G, REST_SLOTS], varies [G, len(HALF_OFFSETS)] bool)``: the median of the
    offset's spring lengths (detect_lattice's value, from the same lengths) in both slots of the
    offset, and whether they vary beyond ``REST_TOLERANCE``. The springs are not listed: an
    offset's springs join the lattice sliced at both ends.
    """
    g = poses.shape[0]
    # One contiguous grid per axis: the length is summed as np.linalg.norm sums (x^2 + y^2) + z^2,
    # so every length is the spring list's to the bit (tests/test_build_arrays.py holds them equal).
    axes = [np.ascontiguousarray(poses[:, :, c]).reshape(g, *shape) for c in range(3)]
    rest = np.zeros((g, REST_SLOTS))
    varies = np.zeros((g, len(HALF_OFFSETS)), dtype=bool)
    for n, (off, _) in enumerate(HALF_OFFSETS):
        a = (slice(None), *(slice(max(0, -o), s - max(0, o)) for o, s in zip(off, shape)))
        b = (slice(None), *(slice(max(0, o), s - max(0, -o)) for o, s in zip(off, shape)))
        if any(x.stop <= x.start for x in a[1:]):
            continue  # the lattice is too thin along this offset
        square = [np.square(x[a] - x[b]) for x in axes]
        r = np.sqrt((square[0] + square[1]) + square[2]).reshape(g, -1)
        m = r.shape[1]
        # Smallest, middle one(s) and largest in one pass; the median as np.median takes it.
        part = np.partition(r, sorted({0, (m - 1) // 2, m // 2, m - 1}), axis=1)
        lo, hi = part[:, 0], part[:, m - 1]
        varies[:, n] = hi - lo > REST_TOLERANCE * np.maximum(np.abs(hi), 1e-30)
        value = part[:, m // 2] if m % 2 else (part[:, m // 2 - 1] + part[:, m // 2]) / 2.0
        rest[:, rest_slot(*off)] = value
        rest[:, rest_slot(*(-o for o in off))] = value
    return rest, varies


def recorded_lattice(builder) -> tuple[LatticeLayout | None, str]:
    """:func:`detect_lattice`'s answer for a builder whose jellies are all recorded whole
    (``builder.lattice_records()``), from the records, without a spring list.

    Jellies placed alike share one pose, measured once; poses of one shape are measured together.
    """
    records = builder.lattice_records()
    jellies = builder.jellies
    if not jellies:
        return None, "no jellies"
    if sum(j.particle_count for j in jellies) != builder._particle_count:
        return None, "some particles belong to no jelly"
    count = len(jellies)
    layout = LatticeLayout(
        start=np.array([r.start for r in records], dtype=np.int32).reshape(count),
        shape=np.array([r.shape for r in records], dtype=np.int32).reshape(count, 3),
        types=np.array([r.types for r in records], dtype=np.int32).reshape(count),
        rest=np.zeros((count, REST_SLOTS)),
        ks=np.array([r.ks for r in records], dtype=np.float64).reshape(count, 3),
        kd=np.array([r.kd for r in records], dtype=np.float64).reshape(count, 3),
        world=np.array([info.world for info in jellies], dtype=np.int32).reshape(count),
    )
    # A type's ks and kd are kept only where it has springs (detect_lattice reads them off springs).
    present = ((layout.types[:, None] >> np.arange(3)) & 1).astype(bool)
    layout.ks[~present] = 0.0
    layout.kd[~present] = 0.0
    # One measurement per distinct pose, poses grouped by shape.
    pose_of, poses = [], {}
    for r in records:
        pose_of.append(poses.setdefault(id(r.rest_pose), (len(poses), r)))
    by_shape = {}
    for k, r in poses.values():
        by_shape.setdefault(r.shape, []).append((k, r))
    rest = np.zeros((len(poses), REST_SLOTS))
    varies = np.zeros((len(poses), len(HALF_OFFSETS)), dtype=bool)
    for shape, group in by_shape.items():
        index = [k for k, _ in group]
        rest[index], varies[index] = rest_tables(np.stack([r.rest_pose for _, r in group]), shape)
    which = np.array([k for k, _ in pose_of], dtype=np.int64)
    layout.rest = rest[which]
    # Only a present type's offsets count (detect_lattice measures only those).
    offset_type = np.array([t for _, t in HALF_OFFSETS])
    bad = varies[which] & present[:, offset_type]
    layout.rest[~present[:, _SLOT_TYPE]] = 0.0
    if bad.any():
        j, n = np.argwhere(bad)[0]
        name = jellies[j].name or f"jelly {j}"
        return None, f"{name}: rest lengths of offset {HALF_OFFSETS[n][0]} vary per spring"
    return layout, "lattice"


def detect_lattice(builder) -> tuple[LatticeLayout | None, str]:
    """The lattice tables of ``builder``'s springs, or ``(None, reason)`` when the lattice path does not apply."""
    jellies = builder.jellies
    if not jellies:
        return None, "no jellies"
    n_particles = builder._particle_count
    if sum(j.particle_count for j in jellies) != n_particles:
        return None, "some particles belong to no jelly"
    if sum(j.spring_count for j in jellies) != builder._spring_count:
        return None, "some springs belong to no jelly"
    pairs = np.concatenate(builder._pairs) if builder._pairs else np.zeros((0, 2), dtype=np.int32)
    types = np.concatenate(builder._type) if builder._type else np.zeros(0, dtype=np.int32)
    rest = np.concatenate(builder._rest) if builder._rest else np.zeros(0)
    ks = np.concatenate(builder._ks) if builder._ks else np.zeros(0)
    kd = np.concatenate(builder._kd) if builder._kd else np.zeros(0)

    count = len(jellies)
    layout = LatticeLayout(
        start=np.zeros(count, dtype=np.int32),
        shape=np.zeros((count, 3), dtype=np.int32),
        types=np.zeros(count, dtype=np.int32),
        rest=np.zeros((count, REST_SLOTS)),
        ks=np.zeros((count, 3)),
        kd=np.zeros((count, 3)),
        world=np.array([info.world for info in jellies], dtype=np.int32),
    )
    for j, info in enumerate(jellies):
        name = info.name or f"jelly {j}"
        if int(np.prod(info.shape)) != info.particle_count:
            return None, f"{name}: particle count is not the lattice's"
        layout.start[j] = info.particle_start
        layout.shape[j] = info.shape
        sl = slice(info.spring_start, info.spring_start + info.spring_count)
        j_pairs, j_types = pairs[sl] - info.particle_start, types[sl]
        std_pairs, std_types = lattice.lattice_springs(info.shape)
        present = [t for t in range(3) if np.any(j_types == t)]
        keep = np.isin(std_types, present)
        # The builder adds a jelly's springs type by type in stencil order; anything else is custom.
        if not (np.array_equal(j_pairs, std_pairs[keep]) and np.array_equal(j_types, std_types[keep])):
            return None, f"{name}: springs are not the standard lattice stencil"
        for t in present:
            sel = j_types == t
            for name_k, values, table in (("ks", ks[sl][sel], layout.ks), ("kd", kd[sl][sel], layout.kd)):
                if values.min() != values.max():
                    return None, f"{name}: {lattice.SPRING_TYPE_NAMES[t]} {name_k} varies per spring"
                table[j, t] = values[0]
            layout.types[j] |= 1 << t
        # One rest length per stencil offset. The standard list holds each offset's springs as one
        # block, in stencil order, so the blocks are found from counts alone.
        j_rest = rest[sl]
        at = 0
        for t in present:
            for off in lattice.STENCILS[t]:
                size = int(np.prod([max(n - abs(o), 0) for n, o in zip(info.shape, off)]))
                r = j_rest[at : at + size]
                at += size
                if size == 0:
                    continue  # the lattice is too thin along this offset
                if r.max() - r.min() > REST_TOLERANCE * max(abs(r.max()), 1e-30):
                    return None, f"{name}: rest lengths of offset {off} vary per spring"
                value = float(np.median(r))
                layout.rest[j, rest_slot(*off)] = value
                layout.rest[j, rest_slot(*(-o for o in off))] = value
    return layout, "lattice"


class LatticeData:
    """Device tables of the lattice path (see :class:`LatticeLayout` for the host side).

    Attributes:
        jelly_start: first particle per jelly, shape [J], int32.
        jelly_shape: particles per axis, shape [J], vec3i.
        jelly_types: bit mask of present spring types, shape [J], int32.
        jelly_rest: rest length per stencil offset [m], shape [J, REST_SLOTS], scalar.
        jelly_ks: stiffness per spring type [N/m], shape [J, 3], scalar.
        jelly_kd: damping per spring type [N s/m], shape [J, 3], scalar.
        jelly_world: world of each jelly, shape [J], int32.
        uniform: whether every jelly that has a spring type has the same ks, kd and rest lengths for
            it (copies of one jelly in several worlds, the benchmark's single jelly).
        stencil_coef: those shared coefficients as one vector (``kernels.lattice.common_coefficients``),
            passed by value to the fused stage kernels (read by the shape-compiled stage,
            ``kernels.lattice.make_single_stage``); zeros when not ``uniform``.
        single: whether the model is one jelly whose particles all have one mass (the benchmark's
            jelly, a one-jelly scene) with shared coefficients; then large models step with
            ``kernels.lattice.make_single_stage``'s stage, which reads no per-particle jelly, world or mass.
        particle_coord_k: third lattice coordinate k of each particle, shape [particle_count],
            int32; allocated only for the CPU row kernel, which reads it.
        kernel: "rows" (CPU: one vectorised native loop per jelly) or "gather" (one thread per
            particle; the fused stages gather with straight-line native code; the CUDA default);
            chosen by device, overridable for tests and benchmarks. The plain force kernel of the
            gather is the Warp-loop gather (``eval_lattice_springs``).
        layout: the host :class:`LatticeLayout`.
        pad: elements a state array's allocation must reach past both its ends for the padded
            one-jelly stage (``make_single_stage``) to read every stencil address of every
            particle: 2 ny nz + nz + 2 of the largest jelly, a bound on |di ny nz + dj nz + dk|
            over the stencil. ``Model.particle_array`` allocates that way.
    """

    def __init__(
        self, layout: LatticeLayout, device, scalar, np_scalar, particle_count: int, kernel=None, particle_mass=None
    ):
        self.layout = layout
        self.device = device
        self.jelly_count = len(layout.start)
        self.jelly_start = wp.array(layout.start, dtype=wp.int32, device=device)
        self.jelly_shape = wp.array(layout.shape, dtype=wp.vec3i, device=device)
        self.jelly_types = wp.array(layout.types, dtype=wp.int32, device=device)
        self.jelly_rest = wp.array2d(layout.rest.astype(np_scalar), dtype=scalar, device=device)
        self.jelly_ks = wp.array2d(layout.ks.astype(np_scalar), dtype=scalar, device=device)
        self.jelly_kd = wp.array2d(layout.kd.astype(np_scalar), dtype=scalar, device=device)
        self.jelly_world = wp.array(layout.world, dtype=wp.int32, device=device)
        self._particle_count = particle_count
        # The uniform gather's coefficients, when the jellies share them (common_coefficients; the
        # kernels take the argument either way, as zeros when they do not).
        coef = common_coefficients(layout.rest, layout.ks, layout.kd, layout.types, np_scalar)
        self.uniform = coef is not None
        if coef is None:
            coef = np.zeros(COEF_LENGTH, dtype=np_scalar)
        coef_type = wp.types.vector(COEF_LENGTH, scalar)
        self.stencil_coef = coef_type(*coef)
        mass = np.asarray(particle_mass if particle_mass is not None else [])
        self.single = bool(
            self.uniform
            and self.jelly_count == 1
            and int(layout.start[0]) == 0
            and int(np.prod(layout.shape[0])) == particle_count == mass.shape[0]
            and np.all(mass == mass[0])
        )
        self.pad = max((int(2 * ny * nz + nz + 2) for _, ny, nz in layout.shape), default=0)
        self.layout_vec3 = wp.types.vector(3, scalar)
        self.particle_coord_k = None
        self.kernel = None
        self.set_kernel(kernel or ("rows" if device.is_cpu else "gather"))

    def set_kernel(self, kernel: str):
        """Choose the force kernel: "rows" (native CPU loop) or "gather" (thread per particle).

        Choose before making integrators: they size their buffers for the kernel in use (the row
        kernel's scratch is each integrator's, ``forces.ForceWork``).
        """
        if kernel not in ("rows", "gather"):
            raise ValueError(f"lattice kernel must be 'rows' or 'gather' (got {kernel!r})")
        if kernel == "rows" and self.particle_coord_k is None:
            coord_k = np.zeros(self._particle_count, dtype=np.int32)
            counts = np.prod(self.layout.shape, axis=1, dtype=np.int64)
            first = np.repeat(np.cumsum(counts) - counts, counts)  # each point's jelly's first point
            local = np.arange(int(counts.sum()), dtype=np.int64) - first
            coord_k[np.repeat(self.layout.start.astype(np.int64), counts) + local] = local % np.repeat(
                self.layout.shape[:, 2], counts
            )
            self.particle_coord_k = wp.array(coord_k, dtype=wp.int32, device=self.device)
        self.kernel = kernel

    @property
    def per_particle(self) -> bool:
        """Whether the kernel runs one thread per particle (gather), so contact can fuse."""
        return self.kernel != "rows"

    def padded(self, *arrays) -> bool:
        """Whether every array is a contiguous view whose allocation reaches ``pad`` elements past both ends.

        Only views made by slicing a 1-D array (``Model.particle_array``) qualify: their parent
        (``_ref``) is the allocation, so its extent is known. Anything else (a user's own array, a
        clone) is not padded, and the fused stage uses the gather that never reads outside the array
        (``integrate_lattice_stage``).
        """
        for a in arrays:
            parent = getattr(a, "_ref", None)
            if not isinstance(parent, wp.array) or parent.ndim != 1 or not parent.is_contiguous:
                return False
            if not a.is_contiguous or a.ndim != 1 or parent.dtype != a.dtype or a.ptr is None:
                return False
            size = wp.types.type_size_in_bytes(a.dtype)
            before = (a.ptr - parent.ptr) // size
            after = parent.shape[0] - before - a.shape[0]
            if before < self.pad or after < self.pad:
                return False
        return True

    @staticmethod
    def check_contiguous(*arrays, who="the lattice kernels"):
        """``who`` (by default the lattice kernels) read state arrays from their data pointer: refuse strided views."""
        for a in arrays:
            if not a.is_contiguous:
                raise ValueError(f"{who} need contiguous state arrays (got strides {a.strides})")

    @property
    def stencil_tables(self) -> list:
        """The per-jelly stencil tables in the order the lattice kernels take them.

        jelly_start, jelly_shape, jelly_types, jelly_rest, jelly_ks, jelly_kd.
        """
        return [self.jelly_start, self.jelly_shape, self.jelly_types, self.jelly_rest, self.jelly_ks, self.jelly_kd]

    def nbytes(self) -> int:
        """Bytes of the device arrays held here."""
        arrays = [
            self.jelly_start,
            self.jelly_shape,
            self.jelly_types,
            self.jelly_rest,
            self.jelly_ks,
            self.jelly_kd,
            self.jelly_world,
        ]
        arrays += [a for a in (self.particle_coord_k,) if a is not None]
        return sum(a.capacity for a in arrays)


def eval_lattice_forces(model, q: wp.array, qd: wp.array, f_out: wp.array, scratch: wp.array | None):
    """Spring forces of a lattice model into ``f_out`` (every element written), with its chosen kernel
    (``scratch``: the row kernel's workspace, ``forces.ForceWork.lattice_scratch``)."""
    lat = model.lattice
    if lat.kernel == "rows":
        if scratch is None:
            raise ValueError("the lattice row kernel needs its scratch: choose the kernel (set_kernel) before making "
                             "the integrator")
        wp.launch(
            lattice_kernels.eval_lattice_rows,
            dim=lat.jelly_count,
            inputs=[
                *lat.stencil_tables,
                lat.particle_coord_k,
                q,
                qd,
                scratch,
            ],
            outputs=[f_out],
            device=model.device,
        )
    else:
        lat.check_contiguous(q, qd)
        wp.launch(
            lattice_kernels.eval_lattice_springs,
            dim=model.particle_count,
            inputs=[
                model.particle_jelly,
                *lat.stencil_tables,
                q,
                qd,
            ],
            outputs=[f_out],
            device=model.device,
        )
