"""Masked-lattice force path: lattice jellies with points missing (mesh jellies) without a spring list.

A mesh jelly (core/voxelize.py) is a box lattice with the points outside the mesh left out, and its
springs are the standard stencil springs between present neighbours. The regular lattice path
(core/lattice_model.py) needs every point; the spring list handles any topology but pays atomics
(several times the lattice path's cost on CUDA, docs/PERFORMANCE.md). This path keeps the lattice's tables (one
rest length per stencil offset, one ks/kd per type and jelly) and adds, per jelly, a grid of
particle indices over its box (-1 where no point is): one thread per particle gathers its springs
(``eval_masked_springs``, kernels/lattice.py), with no atomics and in a fixed order.

``finalize`` takes it, on CUDA, for a model whose jellies are all (masked or whole) standard
lattices that the regular lattice path does not cover; on the CPU the atomic spring list (one
thread per spring, vectorised by Warp's CPU backend no better) stays, as benchmarks/bench_mesh_jelly.py
measured. The model keeps its spring list too (the implicit integrator's Jacobian and the metrics
read it).

The explicit methods step it with the fused lattice stage (core/fused.py) around the masked gather
(kernels/lattice.py ``make_masked_stage``): each jelly's index grid gets a margin of absent points
(``MaskedLattice.make_stage_tables``), so a neighbour is a grid entry at a constant offset with no
bounds test, and an absent one is replaced by the particle itself (zero force). ``eval_forces``
(implicit, ``fused=False``) keeps ``eval_masked_springs``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import lattice
from ..kernels.lattice import COEF_LENGTH, MASK_MARGIN, REST_SLOTS, rest_slot
from .lattice_model import REST_TOLERANCE
from ..kernels import lattice as lattice_kernels


def detect_masked(builder) -> tuple[dict | None, str]:
    """Host tables of the masked path for ``builder``'s jellies, or ``(None, reason)``."""
    jellies = builder.jellies
    if not jellies or not any(getattr(j, "lattice_index", None) is not None for j in jellies):
        return None, "no masked jelly"
    if sum(j.particle_count for j in jellies) != builder._particle_count:
        return None, "some particles belong to no jelly"
    if sum(j.spring_count for j in jellies) != builder._spring_count:
        return None, "some springs belong to no jelly"
    pairs = np.concatenate(builder._pairs) if builder._pairs else np.zeros((0, 2), dtype=np.int64)
    types = np.concatenate(builder._type) if builder._type else np.zeros(0, dtype=np.int32)
    rest = np.concatenate(builder._rest) if builder._rest else np.zeros(0)
    ks = np.concatenate(builder._ks) if builder._ks else np.zeros(0)
    kd = np.concatenate(builder._kd) if builder._kd else np.zeros(0)
    count = len(jellies)
    tables = {
        "shape": np.zeros((count, 3), dtype=np.int32),
        "grid_start": np.zeros(count, dtype=np.int32),
        "types": np.zeros(count, dtype=np.int32),
        "rest": np.zeros((count, REST_SLOTS)),
        "ks": np.zeros((count, 3)),
        "kd": np.zeros((count, 3)),
        "cell": np.zeros(builder._particle_count, dtype=np.int32),
        "grid": [],
    }
    grid_at = 0
    for j, info in enumerate(jellies):
        name = info.name or f"jelly {j}"
        shape = tuple(int(n) for n in info.shape)
        cells = getattr(info, "lattice_index", None)
        cells = np.arange(int(np.prod(shape))) if cells is None else np.asarray(cells, dtype=np.int64)
        if cells.size != info.particle_count:
            return None, f"{name}: particle count is not its lattice points'"
        grid = np.full(int(np.prod(shape)), -1, dtype=np.int64)
        grid[cells] = np.arange(cells.size) + info.particle_start
        # The springs must be the standard stencil between present points, type by type in stencil order.
        std_pairs, std_types = lattice.lattice_springs(shape)
        present = np.zeros(grid.size, dtype=bool)
        present[cells] = True
        sl = slice(info.spring_start, info.spring_start + info.spring_count)
        j_types = types[sl]
        have = [t for t in range(3) if np.any(j_types == t)]
        keep = present[std_pairs[:, 0]] & present[std_pairs[:, 1]] & np.isin(std_types, have)
        if not (np.array_equal(grid[std_pairs[keep]], pairs[sl]) and np.array_equal(std_types[keep], j_types)):
            return None, f"{name}: springs are not the stencil between its lattice points"
        for t in have:
            sel = j_types == t
            for table, values in (("ks", ks[sl][sel]), ("kd", kd[sl][sel])):
                if values.min() != values.max():
                    return None, f"{name}: {lattice.SPRING_TYPE_NAMES[t]} {table} varies per spring"
                tables[table][j, t] = values[0]
            tables["types"][j] |= 1 << t
        # One rest length per stencil offset (and its opposite).
        coord = np.stack(np.unravel_index(std_pairs[keep], shape), axis=-1)  # (S, 2, 3)
        offsets = coord[:, 1] - coord[:, 0]
        j_rest = rest[sl]
        for off in {tuple(o) for o in offsets}:
            r = j_rest[np.all(offsets == off, axis=1)]
            if r.max() - r.min() > REST_TOLERANCE * max(abs(r.max()), 1e-30):
                return None, f"{name}: rest lengths of offset {off} vary per spring"
            value = float(np.median(r))
            tables["rest"][j, rest_slot(*off)] = value
            tables["rest"][j, rest_slot(*(-o for o in off))] = value
        tables["shape"][j] = shape
        tables["grid_start"][j] = grid_at
        tables["cell"][info.particle_start : info.particle_start + info.particle_count] = cells
        tables["grid"].append(grid)
        grid_at += grid.size
    if grid_at > np.iinfo(np.int32).max:
        return None, "lattice grids too large for int32 indices"
    tables["grid"] = np.concatenate(tables["grid"]).astype(np.int32)
    return tables, "masked lattice"


class MaskedLattice:
    """Device tables of the masked path.

    Attributes:
        particle_cell: each particle's lattice index in its jelly's box, shape [particle_count], int32.
        jelly_shape: lattice points per axis of each jelly's box, shape [J], vec3i.
        jelly_grid_start: each jelly's first entry in ``grid``, shape [J], int32.
        grid: particle index of every box point (-1: none), all jellies, shape [sum of box sizes], int32.
        jelly_types: bit mask of present spring types, shape [J], int32.
        jelly_rest: rest length per stencil offset [m], shape [J, 32], scalar (as the lattice path's).
        jelly_ks, jelly_kd: stiffness [N/m] and damping [N s/m] per spring type, shape [J, 3], scalar.
    """

    def __init__(self, tables: dict, device, scalar, np_scalar):
        def arr(values, dtype, np_dtype):
            return wp.array(np.asarray(values, dtype=np_dtype), dtype=dtype, device=device)

        self.particle_cell = arr(tables["cell"], wp.int32, np.int32)
        self.jelly_shape = arr(tables["shape"], wp.vec3i, np.int32)
        self.jelly_grid_start = arr(tables["grid_start"], wp.int32, np.int32)
        self.grid = arr(tables["grid"], wp.int32, np.int32)
        self.jelly_types = arr(tables["types"], wp.int32, np.int32)
        self.jelly_rest = wp.array2d(np.asarray(tables["rest"], dtype=np_scalar), dtype=scalar, device=device)
        self.jelly_ks = wp.array2d(np.asarray(tables["ks"], dtype=np_scalar), dtype=scalar, device=device)
        self.jelly_kd = wp.array2d(np.asarray(tables["kd"], dtype=np_scalar), dtype=scalar, device=device)
        self._tables, self._device, self._np_scalar, self._scalar = tables, device, np_scalar, scalar
        self.stage_index = None

    def make_stage_tables(self) -> None:
        """Build the fused stage's tables (once; only an explicit integrator's fused stage needs them).

        Attributes made:
            stage_index: int32, each particle's position in this array's grid part, then the jellies'
                index grids: per jelly its box with ``MASK_MARGIN`` absent points on every side, each
                entry a particle index or -1 (see kernels/lattice.py ``_masked_gather_snippet``).
            stage_dims: grid dimensions per jelly (box + 2 margins), shape [J], vec3i.
            stencil_coef: the stage kernel's coefficient argument (zeros: unused by the masked gather).
        """
        if self.stage_index is not None:
            return
        t = self._tables
        n = t["cell"].size
        pad = MASK_MARGIN
        dims = t["shape"] + 2 * pad
        sizes = np.prod(dims, axis=1)
        starts = n + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        index = np.full(n + int(sizes.sum()), -1, dtype=np.int64)
        jelly_of = np.zeros(n, dtype=np.int64)
        for j, (shape, d) in enumerate(zip(t["shape"], dims)):
            grid = t["grid"][t["grid_start"][j] : t["grid_start"][j] + int(np.prod(shape))].reshape(shape)
            full = np.full(tuple(d), -1, dtype=np.int64)
            full[pad:-pad, pad:-pad, pad:-pad] = grid
            index[starts[j] : starts[j] + sizes[j]] = full.reshape(-1)
            present = grid.reshape(-1)[grid.reshape(-1) >= 0]
            jelly_of[present] = j
        # Each particle's position in its jelly's padded grid.
        cell = t["cell"].astype(np.int64)
        shape_p = t["shape"][jelly_of]
        dims_p = dims[jelly_of]
        c = cell % shape_p[:, 2]
        ab = cell // shape_p[:, 2]
        b = ab % shape_p[:, 1]
        a = ab // shape_p[:, 1]
        index[:n] = starts[jelly_of] + ((a + pad) * dims_p[:, 1] + (b + pad)) * dims_p[:, 2] + (c + pad)
        if index.size > np.iinfo(np.int32).max:
            raise ValueError("masked lattice grids too large for int32 indices")
        dev = self._device
        self.stage_index = wp.array(index.astype(np.int32), dtype=wp.int32, device=dev)
        self.stage_dims = wp.array(dims.astype(np.int32), dtype=wp.vec3i, device=dev)
        # The stage kernel's coefficient argument; the masked gather reads the per-jelly tables instead.
        self.stencil_coef = wp.types.vector(COEF_LENGTH, self._scalar)()

    @property
    def stage_tables(self) -> list:
        """The fused stage's tables in the order the lattice stage kernels take them (``stencil_tables``)."""
        return [self.stage_index, self.stage_dims, self.jelly_types, self.jelly_rest, self.jelly_ks, self.jelly_kd]


def masked_lattice(builder, m, force_path="auto", kernel=None) -> tuple[MaskedLattice | None, str]:
    """The masked path of model ``m`` (being finalized from ``builder``) when it applies (see the
    module docstring): ``(MaskedLattice or None, why)``, ``Model.masked`` and ``Model.masked_reason``.

    ``kernel``: "gather" takes it on any device (tests, benchmarks); None: on CUDA only.
    """
    if m.lattice is not None:
        return None, "the lattice path applies"
    if force_path != "auto":
        return None, "force_path=springs"
    tables, reason = detect_masked(builder)
    if tables is None:
        return None, reason
    if kernel != "gather" and not m.device.is_cuda:
        return None, "masked lattice: on CUDA only (the CPU keeps the spring list)"
    return MaskedLattice(tables, m.device, m.scalar, np.float32 if m.precision == "float32" else np.float64), reason


def eval_masked_forces(model, q: wp.array, qd: wp.array, f_out: wp.array):
    """Spring and damper forces of (q, qd) into ``f_out`` on the masked path; every entry is written."""
    masked = model.masked
    wp.launch(
        lattice_kernels.eval_masked_springs,
        dim=model.particle_count,
        inputs=[
            model.particle_jelly,
            masked.particle_cell,
            masked.jelly_shape,
            masked.jelly_grid_start,
            masked.grid,
            masked.jelly_types,
            masked.jelly_rest,
            masked.jelly_ks,
            masked.jelly_kd,
            q,
            qd,
        ],
        outputs=[f_out],
        device=model.device,
    )
