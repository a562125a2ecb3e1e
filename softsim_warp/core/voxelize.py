"""Mesh jellies: a closed mesh voxelised into a lattice with points missing, its surface embedded.

The jelly's lattice is the box lattice of its scene entry (``io/mesh_scene.py`` fills in the box
around the asset); the points inside the mesh are found on the device with Warp's winding-number
query (``mark_inside_mesh`` in kernels/mesh.py), and ``ModelBuilder.add_jelly(mask=...)`` keeps
those particles and the stencil springs between them. A mask that keeps every point (a box mesh)
gives exactly the box jelly, and then the lattice force path.

The asset's own surface rides on the lattice: each vertex is a trilinear combination of the eight
particles of one cell whose corners are all present (its own cell, or the nearest such cell, whose
weights then extrapolate). Trilinear weights reproduce every affine map exactly, so the undeformed
jelly gives the asset back and a uniform stretch stretches it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..kernels import mesh as mesh_kernels
from . import lattice
from .errors import SceneError
from .mesh_assets import load_mesh, mesh_options


@dataclass
class SurfaceEmbedding:
    """An asset's surface in a jelly's lattice (``JellyInfo.embedding``)."""

    counts: np.ndarray
    """Vertices per face of the asset, shape [F]."""
    indices: np.ndarray
    """Face vertex indices of the asset, shape [sum(counts)]."""
    corners: np.ndarray
    """Jelly-local particle index of each vertex's eight cell corners, shape [V, 8], int64."""
    weights: np.ndarray
    """Trilinear weight of each corner (they sum to 1), shape [V, 8], float64."""
    primvars: list = field(default_factory=list)
    """The asset's primvars to carry to the Surface (see ``MeshAsset.primvars``)."""

    def points(self, x: np.ndarray) -> np.ndarray:
        """Surface vertices of the jelly's particle positions ``x`` [m], float64 (V, 3)."""
        return np.einsum("vk,vkj->vj", self.weights, np.asarray(x, dtype=np.float64)[self.corners])


def lattice_axes(shape, size) -> list:
    """Coordinates of the lattice planes along each axis, centred on the origin (as ``lattice.lattice_points``)."""
    return [np.linspace(-0.5 * s, 0.5 * s, n) if n > 1 else np.zeros(1) for n, s in zip(shape, size)]


def voxelize(points, triangles, shape, size, device=None) -> np.ndarray:
    """Which points of the ``shape`` lattice spanning ``size`` (centred on the origin) lie inside the
    closed mesh ``(points, triangles)`` (same frame) or on its surface; bool, lattice order."""
    shape = [int(n) for n in shape]
    size = np.asarray(size, dtype=np.float64)
    device = wp.get_device(device)
    spacing = np.array([s / (n - 1) if n > 1 else 0.0 for n, s in zip(shape, size)])
    bvh = wp.Mesh(
        points=wp.array(np.asarray(points, dtype=np.float32), dtype=wp.vec3, device=device),
        indices=wp.array(np.asarray(triangles, dtype=np.int32).ravel(), dtype=wp.int32, device=device),
        support_winding_number=True,
    )
    inside = wp.zeros(int(np.prod(shape)), dtype=wp.int32, device=device)
    h = float(spacing[spacing > 0].min()) if (spacing > 0).any() else 1.0
    wp.launch(
        mesh_kernels.mark_inside_mesh,
        dim=inside.shape[0],
        inputs=[bvh.id, wp.vec3(*(-0.5 * size)), wp.vec3(*spacing), wp.vec3i(*shape), 1e-4 * h],
        outputs=[inside],
        device=device,
    )
    return inside.numpy().astype(bool)


def embed(points, shape, size, mask) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear embedding of ``points`` (the asset's vertices, lattice frame) in the cells of a
    masked lattice whose eight corners are all present.

    Returns:
        ``(corners (V, 8) lattice indices, weights (V, 8))``.
    """
    shape = [int(n) for n in shape]
    axes = lattice_axes(shape, size)
    p = np.asarray(points, dtype=np.float64)
    present = np.asarray(mask, dtype=bool).reshape(shape)
    ncell = [max(n - 1, 1) for n in shape]
    full = np.ones(ncell, dtype=bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                full &= present[dx : dx + ncell[0], dy : dy + ncell[1], dz : dz + ncell[2]]
    if not full.any():
        raise ValueError("no lattice cell has all eight corners inside the mesh")
    cell = np.stack(
        [np.clip(np.searchsorted(axes[a], p[:, a], side="right") - 1, 0, ncell[a] - 1) for a in range(3)], axis=1
    )
    ok = full[cell[:, 0], cell[:, 1], cell[:, 2]]
    todo = np.nonzero(~ok)[0]
    radius = 1
    while todo.size:
        # Nearest full cell (distance from the vertex to the cell's box) among the cells within
        # ``radius`` of the vertex's own; once some are found, one ring more settles the nearest.
        best, found = _nearest_full(p[todo], cell[todo], full, axes, ncell, radius)
        if found.any():
            best2, found2 = _nearest_full(p[todo], cell[todo], full, axes, ncell, radius + 1)
            cell[todo[found2]] = best2[found2]
            todo = todo[~found2]
        radius += 1
    t = np.stack(
        [(p[:, a] - axes[a][cell[:, a]]) / (axes[a][cell[:, a] + 1] - axes[a][cell[:, a]]) for a in range(3)], axis=1
    )
    corners, weights = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corners.append(lattice.lattice_index(cell[:, 0] + dx, cell[:, 1] + dy, cell[:, 2] + dz, shape))
                w = np.ones(p.shape[0])
                for a, d in enumerate((dx, dy, dz)):
                    w = w * (t[:, a] if d else 1.0 - t[:, a])
                weights.append(w)
    return np.stack(corners, axis=1).astype(np.int64), np.stack(weights, axis=1)


def _nearest_full(p, cell, full, axes, ncell, radius):
    r = np.arange(-radius, radius + 1)
    off = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    cand = cell[:, None, :] + off[None, :, :]  # (V, K, 3)
    inside = np.all((cand >= 0) & (cand < np.asarray(ncell)), axis=2)
    c = np.clip(cand, 0, np.asarray(ncell) - 1)
    is_full = inside & full[c[..., 0], c[..., 1], c[..., 2]]
    gap = np.zeros(c.shape[:2])
    for a in range(3):
        lo, hi = axes[a][c[..., a]], axes[a][c[..., a] + 1]
        g = np.maximum(np.maximum(lo - p[:, None, a], p[:, None, a] - hi), 0.0)
        gap += g * g
    gap = np.where(is_full, gap, np.inf)
    k = np.argmin(gap, axis=1)
    rows = np.arange(p.shape[0])
    return c[rows, k], np.isfinite(gap[rows, k])


class MeshLatticeError(ValueError):
    """A mesh that gives no usable lattice at the asked resolution (too few points or no full cell)."""


def mesh_lattice(j: dict, device=None) -> tuple:
    """The masked lattice and surface embedding of a validated mesh jelly entry ``j``.

    Returns ``(asset (outward), mask (bool, lattice order), corners (V, 8) jelly particle indices,
    weights (V, 8))``. Computed once per asset and lattice (validation computes it, on the default
    device, to count the particles; the builder then reuses it); raises :class:`MeshLatticeError`.
    """
    raw = load_mesh(j["mesh"], j.get("mesh_prim"), colliders=False, **mesh_options(j))  # cached: one object per file version
    key = (id(raw), tuple(j["resolution"]), tuple(j["size"]), float(j["_mesh_scale"]), tuple(j["_mesh_center"]))
    hit = _LATTICES.get(key)
    if hit is None or hit[0] is not raw:
        asset = raw.outward()
        local = (asset.points - np.asarray(j["_mesh_center"])) * j["_mesh_scale"]
        shape, size = j["resolution"], j["size"]
        mask = voxelize(local, asset.triangles, shape, size, device)
        if mask.sum() < 2:
            raise MeshLatticeError("the mesh holds fewer than 2 lattice points")
        try:
            corners, weights = embed(local, shape, size, mask)
        except ValueError as e:
            raise MeshLatticeError(str(e)) from None
        compact = np.cumsum(mask) - 1  # lattice index -> jelly particle index
        if len(_LATTICES) >= 16:
            _LATTICES.pop(next(iter(_LATTICES)))
        hit = _LATTICES[key] = (raw, asset, mask, compact[corners], weights)
    return hit[1:]


_LATTICES: dict = {}  # mesh_lattice's results (the file's asset is kept in the value, so its id stays unique)


def add_mesh_jelly(builder, j: dict, world=0, name="", key="jelly") -> object:
    """Add a validated mesh jelly (``[[jelly]] mesh = ...``) to ``builder``; returns its JellyInfo."""
    try:
        asset, mask, corners, weights = mesh_lattice(j, builder.device)
    except MeshLatticeError as e:
        given_key, given = j.get("_mesh_given", ("resolution", j["resolution"]))
        raise SceneError(j.get("_source", "<scene>"), f"{key}.{given_key}", f"{e}; use a finer lattice", given) from None
    mass = j["particle_mass"] if "particle_mass" in j else j["total_mass"] / int(mask.sum())
    info = builder.add_jelly(
        j["resolution"],
        j["size"],
        mass,
        j["springs"],
        center=j["center"],
        axis=j["rotation"]["axis"],
        degrees=j["rotation"]["degrees"],
        velocity=j["velocity"],
        angular_velocity=j["angular_velocity"],
        world=world,
        name=name,
        initial_scale=j.get("initial_scale"),
        mask=mask,
        self_contact=j.get("self_contact", False),
    )
    info.embedding = SurfaceEmbedding(asset.counts, asset.indices, corners, weights, asset.primvars)
    return info
