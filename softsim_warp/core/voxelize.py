"""Mesh jellies: a mesh voxelised into the lattice cells it touches, its surface embedded in them.

The jelly's lattice is the box lattice of its scene entry (``io/mesh_scene.py`` fills in the box:
the asset's bounding box, its extreme vertices on the outer planes). Its particles are the corners
of every cell the solid touches (:func:`solid_mask`): a cell with a corner inside the mesh (Warp's
generalized winding number above 1/2, ``mark_inside_mesh`` in kernels/mesh.py: an open mesh with
holes still has a clear inside), a cell that holds a vertex, or one a face passes through.
``ModelBuilder.add_jelly(mask=...)`` keeps those particles and the stencil springs between them. A
mask that keeps every point (a box mesh) gives exactly the box jelly, and then the lattice force path.

The asset's own surface rides on the lattice: each vertex is the trilinear combination of the eight
corners of the cell that holds it (:func:`embed`), weights in [0, 1]: a convex combination, so a
vertex is never farther out than the farthest of its cell's particles. Contact keeps particles out
of terrain; a plane (or a flat mesh) then keeps every vertex out too, thin legs and ears included.
Trilinear weights reproduce every affine map exactly, so the undeformed jelly gives the asset back
and a uniform stretch stretches it exactly.
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


def voxelize(points, triangles, shape, size, device=None, thresholds=(0.5,)) -> np.ndarray:
    """Which points of the ``shape`` lattice spanning ``size`` (centred on the origin) lie inside the
    mesh ``(points, triangles)`` (same frame) or on its surface; bool, lattice order.

    Inside: the generalized winding number above 1/2 (an open mesh's holes are bridged smoothly).
    ``thresholds``: several winding-number levels at once (one BVH): then a bool array
    ``(len(thresholds), points)``, row k the points whose winding number is above ``thresholds[k]``.
    """
    shape = [int(n) for n in shape]
    size = np.asarray(size, dtype=np.float64)
    device = wp.get_device(device)
    spacing = np.array([s / (n - 1) if n > 1 else 0.0 for n, s in zip(shape, size)])
    bvh = wp.Mesh(
        points=wp.array(np.asarray(points, dtype=np.float32), dtype=wp.vec3, device=device),
        indices=wp.array(np.asarray(triangles, dtype=np.int32).ravel(), dtype=wp.int32, device=device),
        support_winding_number=True,
    )
    h = float(spacing[spacing > 0].min()) if (spacing > 0).any() else 1.0
    rows = []
    for threshold in thresholds:
        inside = wp.zeros(int(np.prod(shape)), dtype=wp.int32, device=device)
        wp.launch(
            mesh_kernels.mark_inside_mesh,
            dim=inside.shape[0],
            inputs=[bvh.id, wp.vec3(*(-0.5 * size)), wp.vec3(*spacing), wp.vec3i(*shape), 1e-4 * h, float(threshold)],
            outputs=[inside],
            device=device,
        )
        rows.append(inside.numpy().astype(bool))
    return rows[0] if len(rows) == 1 else np.stack(rows)


def holding_cells(points, shape, size) -> np.ndarray:
    """The lattice cell ``(i, j, k)`` that holds each of ``points`` (lattice frame), shape [V, 3], int64.

    A point on a lattice plane goes to the cell above it (the last cell's upper face to the last
    cell); a point outside the box to the nearest cell.
    """
    axes = lattice_axes(shape, size)
    p = np.asarray(points, dtype=np.float64)
    ncell = [max(int(n) - 1, 1) for n in shape]
    return np.stack(
        [np.clip(np.searchsorted(axes[a], p[:, a], side="right") - 1, 0, ncell[a] - 1) for a in range(3)], axis=1
    )


def face_samples(points, triangles, spacing) -> np.ndarray:
    """Points on the faces no farther than half a ``spacing`` from the next along each face (the
    vertices excluded): every cell a face passes through then holds a sample, up to cells it only grazes.

    Each triangle longer than half a spacing is split into n^2 similar triangles (n its longest edge
    over half the spacing, rounded up); the samples are their corners. Triangles are grouped by n,
    so the work is vectorised per group.
    """
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    longest = np.maximum(np.maximum(np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1)),
                         np.linalg.norm(a - c, axis=1))
    n = np.ceil(longest / (0.5 * spacing)).astype(np.int64)
    out = [np.zeros((0, 3))]
    for k in np.unique(n[n > 1]):
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = (i + j <= k) & ~(((i == 0) & (j == 0)) | ((i == k) & (j == 0)) | ((i == 0) & (j == k)))
        u, v = i[keep] / k, j[keep] / k
        sel = n == k
        aa, bb, cc = a[sel], b[sel], c[sel]
        out.append((aa[:, None, :] + u[None, :, None] * (bb - aa)[:, None, :] + v[None, :, None] * (cc - aa)[:, None, :])
                   .reshape(-1, 3))
    return np.concatenate(out)


def solid_mask(points, triangles, shape, size, inside) -> np.ndarray:
    """The lattice points of a mesh jelly: the eight corners of every cell the solid touches.

    A cell is kept when one of its corners is ``inside`` (bool per lattice point, :func:`voxelize`),
    when it holds a vertex of the mesh (``points``, lattice frame) or when a face passes through it
    (:func:`face_samples`, which also keeps a thin part whose vertices lie cells apart in one piece).
    Returns bool per lattice point, lattice order.
    """
    shape = [int(n) for n in shape]
    ncell = [max(n - 1, 1) for n in shape]
    present = np.asarray(inside, dtype=bool).reshape(shape)
    cells = np.zeros(ncell, dtype=bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                cells |= present[dx : dx + ncell[0], dy : dy + ncell[1], dz : dz + ncell[2]]
    spacing = min(s / (n - 1) for n, s in zip(shape, size) if n > 1)
    for pts in (points, face_samples(points, triangles, spacing)):
        c = holding_cells(pts, shape, size)
        cells[c[:, 0], c[:, 1], c[:, 2]] = True
    mask = np.zeros(shape, dtype=bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                mask[dx : dx + ncell[0], dy : dy + ncell[1], dz : dz + ncell[2]] |= cells
    return mask.ravel()


def embed(points, shape, size) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear embedding of ``points`` (the asset's vertices, lattice frame) in the cells that hold
    them (:func:`holding_cells`; :func:`solid_mask` keeps their corners).

    Returns:
        ``(corners (V, 8) lattice indices, weights (V, 8))``; the weights lie in [0, 1] and sum to 1.
    """
    shape = [int(n) for n in shape]
    axes = lattice_axes(shape, size)
    p = np.asarray(points, dtype=np.float64)
    cell = holding_cells(p, shape, size)
    # In [0, 1] inside the box; clipped, a point a rounding error outside keeps convex weights.
    t = np.stack(
        [np.clip((p[:, a] - axes[a][cell[:, a]]) / (axes[a][cell[:, a] + 1] - axes[a][cell[:, a]]), 0.0, 1.0)
         for a in range(3)], axis=1
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


class NoInsideError(ValueError):
    """A mesh whose winding number gives no clear inside (an open sheet, faces that enclose nothing)."""


# An open mesh's inside is clear when more lattice points have a winding number above 3/4 than
# between 1/4 and 3/4 (a closed mesh's is 0 or 1 everywhere; a box without its lid has 5/6 at its
# centre and 1/2 only near the hole; an open sheet has values near 1/2 all around it).
CLEAR_LEVELS = (0.25, 0.5, 0.75)


def mesh_lattice(j: dict, device=None) -> tuple:
    """The masked lattice and surface embedding of a validated mesh jelly entry ``j``.

    Returns ``(asset (outward), mask (bool, lattice order), corners (V, 8) jelly particle indices,
    weights (V, 8))``. Computed once per asset and lattice (validation computes it, on the default
    device, to count the particles; the builder then reuses it); raises :class:`NoInsideError`
    for a mesh without a clear inside.
    """
    # Cached: one object per file version (the same source and key as validation's read).
    raw = load_mesh(j["mesh"], j.get("mesh_prim"), colliders=False, source=j.get("_source", "<scene>"),
                    key=j.get("_mesh_key", "mesh.path"), **mesh_options(j))
    key = (id(raw), tuple(j["resolution"]), tuple(j["size"]), float(j["_mesh_scale"]), tuple(j["_mesh_center"]))
    hit = _LATTICES.get(key)
    if hit is None or hit[0] is not raw:
        asset = raw.outward(open_too=True)
        local = (asset.points - np.asarray(j["_mesh_center"])) * j["_mesh_scale"]
        shape, size = j["resolution"], j["size"]
        if asset.closed:
            inside = voxelize(local, asset.triangles, shape, size, device)
        else:
            above_quarter, inside, above_three_quarters = voxelize(local, asset.triangles, shape, size, device,
                                                                   CLEAR_LEVELS)
            clear = int(above_three_quarters.sum())
            unclear = int((above_quarter & ~above_three_quarters).sum())
            if unclear >= clear:
                raise NoInsideError(
                    f"the mesh encloses no clear inside ({unclear} lattice points have a winding number between "
                    f"1/4 and 3/4, {clear} above 3/4): a jelly needs faces around a volume; close the mesh, "
                    "or use it as terrain ([[mesh]])"
                )
        mask = solid_mask(local, asset.triangles, shape, size, inside)
        corners, weights = embed(local, shape, size)
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
    except NoInsideError as e:
        raise SceneError(j.get("_source", "<scene>"), f"{key}.mesh", str(e), j["mesh"]) from None
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
