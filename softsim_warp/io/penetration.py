"""An independent penetration check of written frames (``softsim run --check-penetration``).

From the particle positions of a frame only, never the contact code, it counts the particles

* inside a collider: behind a plane (outside its hole), inside a sphere, outside a bowl's sphere
  below its cut having been inside it (the bowl's wall has no thickness, so a particle is on the
  side it was last seen on above the cut), or inside a closed ``[[mesh]]`` (generalized winding
  number above 1/2); analytic terrain in its pose at the frame's time (``core/contact.terrain_at``);
* inside another jelly of its world: inside one of that jelly's deformed lattice cells;
* inside its own jelly's folded body: inside one of its own jelly's deformed cells none of whose
  corners is within ``SELF_EXCLUSION`` rest spacings of it (the neighbourhood that self-contact
  leaves to the springs, docs/CONTACT.md). An unfolded lattice's cells tile its body without
  overlap, so a particle enters a far cell only when the body has folded or passed through itself.

A cell is the closed surface of its six faces (twelve triangles between its eight corners), and a
point is inside when the surface's winding number is above 1/2 in magnitude (an inverted cell winds
-1). The depth of a particle inside a jelly is its distance to that jelly's boundary (the cell faces
no other cell shares), without the faces near it for its own jelly; inside a collider, its distance
to the collider's surface. Mesh jellies are checked on their lattice (every particle collides).

It also counts the inverted cells of each frame: a cell whose corner tetrahedron at its first corner,
``(x_i+1 - x) . ((x_j+1 - x) x (x_k+1 - x))``, has a negative volume.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.contact import terrain_at
from ..core.particle_contact import SELF_EXCLUSION

KINDS = ("collider", "jelly", "self")

# The eight corners of a cell as lattice offsets (bit 2: +i, bit 1: +j, bit 0: +k) and its six faces,
# each wound so that its normal points out of a cell of positive volume.
_OFFSETS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
_CELL_TRIANGLES = np.concatenate([_FACES[:, [0, 1, 2]], _FACES[:, [0, 2, 3]]])


def winding_numbers(points, triangles, queries) -> np.ndarray:
    """Generalized winding number of the triangle mesh at each query point (Van Oosterom and
    Strackee's solid angle of each triangle, summed over 4 pi)."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    out = np.zeros(len(queries))
    for s in range(0, len(queries), 256):
        q = np.asarray(queries[s : s + 256], dtype=np.float64)
        a, b, c = (p[t[:, k]][None, :, :] - q[:, None, :] for k in range(3))
        out[s : s + 256] = _solid_angles(a, b, c).sum(axis=1) / (4.0 * math.pi)
    return out


def _solid_angles(a, b, c):
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    det = np.einsum("...k,...k", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("...k,...k", a, b) * lc + np.einsum("...k,...k", b, c) * la + np.einsum("...k,...k", c, a) * lb
    return 2.0 * np.arctan2(det, den)


def distances_to_triangles(points, triangles, queries, skip=None) -> np.ndarray:
    """Distance from each query point to the nearest point of the triangle mesh (Ericson 5.1.5,
    vectorised: the closest point in the face, else on one of its three edges). ``skip``: a bool
    array (queries, triangles) of triangles left out per query; inf where none is left."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    n = np.cross(b - a, c - a)
    n2 = np.einsum("tk,tk->t", n, n)
    out = np.full(len(queries), np.inf)

    def to_segment(q, u, v):
        d = v - u
        s = np.clip(np.einsum("qtk,tk->qt", q[:, None, :] - u[None], d) / np.maximum(np.einsum("tk,tk->t", d, d), 1e-300), 0, 1)
        return np.linalg.norm(q[:, None, :] - (u[None] + s[..., None] * d[None]), axis=2)

    for s in range(0, len(queries), 64):
        q = np.asarray(queries[s : s + 64], dtype=np.float64)
        w = q[:, None, :] - a[None]
        h = np.einsum("qtk,tk->qt", w, n) / np.maximum(n2, 1e-300)
        foot = q[:, None, :] - h[..., None] * n[None]
        inside = np.ones(h.shape, dtype=bool)
        for u, v in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("qtk,tk->qt", np.cross(v - u, foot - u[None]), n) >= 0
        face = np.where(inside, np.abs(h) * np.sqrt(n2), np.inf)
        edge = np.minimum(np.minimum(to_segment(q, a, b), to_segment(q, b, c)), to_segment(q, c, a))
        d = np.minimum(face, edge)
        if skip is not None:
            d = np.where(skip[s : s + 64], np.inf, d)
        out[s : s + 64] = d.min(axis=1)
    return out


def jelly_cells(info) -> tuple[np.ndarray, np.ndarray]:
    """A jelly's cells as global particle indices of their eight corners (C, 8), and every particle's
    lattice coordinates (N, 3): the box lattice's cells, or a masked (mesh) jelly's cells whose eight
    corners are all particles."""
    shape = np.asarray(info.shape)
    index = np.arange(info.particle_count) if info.lattice_index is None else np.asarray(info.lattice_index)
    ijk = np.stack(np.unravel_index(index, tuple(shape)), axis=1)
    grid = np.full(int(np.prod(shape)), -1, dtype=np.int64)
    grid[index] = np.arange(info.particle_count) + info.particle_start
    grid = grid.reshape(tuple(shape))
    if np.any(shape < 2):
        return np.zeros((0, 8), dtype=np.int64), ijk
    cells = np.stack([grid[o[0] : shape[0] - 1 + o[0], o[1] : shape[1] - 1 + o[1], o[2] : shape[2] - 1 + o[2]].ravel()
                      for o in _OFFSETS], axis=1)
    return cells[(cells >= 0).all(axis=1)], ijk


def boundary_triangles(cells: np.ndarray) -> np.ndarray:
    """The faces of ``cells`` (C, 8) that no other cell shares, as outward triangles (T, 3)."""
    faces = cells[:, _FACES].reshape(-1, 4)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    outer = faces[counts[inverse.ravel()] == 1]
    return np.concatenate([outer[:, [0, 1, 2]], outer[:, [0, 2, 3]]])


def cell_volumes(q: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed volume of each cell's corner tetrahedron at its first corner; < 0: inverted."""
    o = q[cells[:, 0]]
    a, b, c = q[cells[:, 4]] - o, q[cells[:, 2]] - o, q[cells[:, 1]] - o
    return np.einsum("...i,...i", a, np.cross(b, c))


def _candidate_pairs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, h: float):
    """(point, cell) pairs whose point lies in the cell's bounding box, through a hash grid of cell ``h``."""
    if len(points) == 0 or len(lo) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    def key(ix):
        ix = ix + (1 << 20)
        return (ix[..., 0] << 42) | (ix[..., 1] << 21) | ix[..., 2]
    pk = key(np.floor(points / h).astype(np.int64))
    order = np.argsort(pk, kind="stable")
    sorted_keys = pk[order]
    c_lo = np.floor(lo / h).astype(np.int64)
    span = np.floor(hi / h).astype(np.int64) - c_lo + 1
    total = span.prod(axis=1)
    cell = np.repeat(np.arange(len(lo)), total)
    local = np.arange(total.sum()) - np.repeat(np.cumsum(total) - total, total)
    sy, sz = span[cell, 1], span[cell, 2]
    offset = np.stack([local // (sy * sz), (local // sz) % sy, local % sz], axis=1)
    ck = key(c_lo[cell] + offset)
    start = np.searchsorted(sorted_keys, ck, "left")
    count = np.searchsorted(sorted_keys, ck, "right") - start
    pair_cell = np.repeat(cell, count)
    pair_point = order[np.repeat(start, count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)]
    p = points[pair_point]
    ok = np.all((p >= lo[pair_cell]) & (p <= hi[pair_cell]), axis=1)
    return pair_point[ok], pair_cell[ok]


class PenetrationCheck:
    """A frame writer (``Simulator.run``'s writers) that checks every frame it is given; ``frames``:
    one dict per frame, ``summary()``: the worst of them."""

    def __init__(self, model, exclusion: float = SELF_EXCLUSION):
        self.model = model
        self.exclusion = exclusion
        self.worlds = np.concatenate([np.full(j.particle_count, j.world) for j in model.jellies]) \
            if model.jellies else np.zeros(0, np.int64)
        cells, ijk, owner, spacing = [], [], [], []
        self.boundaries = []
        for n, info in enumerate(model.jellies):
            c, lattice = jelly_cells(info)
            cells.append(c)
            owner.append(np.full(len(c), n))
            ijk.append(lattice)
            spacing.append(np.asarray(info.spacing, dtype=np.float64))
            self.boundaries.append(boundary_triangles(c) if len(c) else np.zeros((0, 3), np.int64))
        self.cells = np.concatenate(cells) if cells else np.zeros((0, 8), np.int64)
        self.cell_jelly = np.concatenate(owner) if owner else np.zeros(0, np.int64)
        self.jelly_of = np.concatenate([np.full(j.particle_count, n) for n, j in enumerate(model.jellies)]) \
            if model.jellies else np.zeros(0, np.int64)
        self.count = sum(j.particle_count for j in model.jellies)
        # Rest positions in the lattice's own frame (the self-exclusion is a rest distance).
        self.rest = np.concatenate([l * s for l, s in zip(ijk, spacing)]) if ijk else np.zeros((0, 3))
        self.spacing = np.array([max(s) for s in spacing]) if spacing else np.zeros(0)
        self.bowl_side = None
        self.frames: list[dict] = []

    # -- the writer interface -------------------------------------------------------------------

    def write_frame(self, k, t, positions, metrics=None):
        record = self.measure(np.asarray(positions, dtype=np.float64)[: self.count], float(t))
        record.update(frame=int(k), time=float(t))
        self.frames.append(record)

    def measure(self, q: np.ndarray, t: float) -> dict:
        """Counts and deepest penetration [m] of each kind, and inverted cells, at positions ``q``, time ``t``."""
        out = {kind: {"count": int(np.count_nonzero(d > 0)), "deepest": float(d.max(initial=0.0))}
               for kind, d in zip(KINDS, self.depths(q, t))}
        out["inverted_cells"] = int(np.count_nonzero(cell_volumes(q, self.cells) < 0)) if len(self.cells) else 0
        return out

    def depths(self, q: np.ndarray, t: float) -> tuple:
        """Each particle's depth [m] inside a collider, another jelly and its own folded body (0: outside)."""
        return (self._colliders(q, t), *self._jellies(q))

    def summary(self) -> dict:
        """The worst frame of each kind: the largest count, the deepest penetration [m] and as a
        fraction of the smallest lattice spacing, the first frame time [s] deeper than 1 % of the
        spacing (None: none), and the most inverted cells."""
        h = float(self.spacing.min()) if len(self.spacing) else 1.0
        out = {"frames": len(self.frames), "spacing": h}
        for kind in KINDS:
            deepest = max((f[kind]["deepest"] for f in self.frames), default=0.0)
            over = [f["time"] for f in self.frames if f[kind]["deepest"] > 0.01 * h]
            out[kind] = {"count": max((f[kind]["count"] for f in self.frames), default=0),
                         "deepest": deepest, "deepest_over_spacing": deepest / h,
                         "first_time_over_1_percent": over[0] if over else None}
        out["inverted_cells"] = max((f["inverted_cells"] for f in self.frames), default=0)
        return out

    # -- colliders ------------------------------------------------------------------------------

    def _terrain(self, kind):
        return [(it, int(it.get("world", -1))) for it in getattr(self.model, kind)]

    def _in_world(self, world):
        return np.ones(self.count, dtype=bool) if world < 0 else self.worlds[: self.count] == world

    def _colliders(self, q, t):
        depth = np.zeros(len(q))
        for item, world in self._terrain("planes"):
            p = terrain_at(item, t)
            d = (q - p["point"]) @ p["normal"]
            behind = (d < 0) & self._in_world(world)
            if p.get("hole_radius", 0.0) > 0:
                r = q - p["hole_center"]
                r -= np.outer(r @ p["normal"], p["normal"])
                behind &= np.linalg.norm(r, axis=1) >= p["hole_radius"]
            depth = np.where(behind, np.maximum(depth, -d), depth)
        for item, world in self._terrain("spheres"):
            s = terrain_at(item, t)
            d = np.linalg.norm(q - s["center"], axis=1) - s["radius"]
            depth = np.where((d < 0) & self._in_world(world), np.maximum(depth, -d), depth)
        bowls = self._terrain("bowls")
        if bowls and self.bowl_side is None:
            self.bowl_side = [None] * len(bowls)
        for b, (item, world) in enumerate(bowls):
            s = terrain_at(item, t)
            d = np.linalg.norm(q - s["center"], axis=1) - s["radius"]
            # The cut's height in the bowl's frame: along the bowl's motion of the y axis.
            up = terrain_at(dict(item, point=item["center"] + np.array([0.0, 1.0, 0.0])), t)["point"] - s["center"]
            below = (q - s["center"]) @ up < item["cut_height"] - item["center"][1]
            side = d < 0
            if self.bowl_side[b] is None:
                self.bowl_side[b] = side.copy()
            crossed = below & (side != self.bowl_side[b]) & self._in_world(world)
            depth = np.where(crossed, np.maximum(depth, np.abs(d)), depth)
            self.bowl_side[b] = np.where(below & ~crossed, side, np.where(below, self.bowl_side[b], side))
        for item, world in self._terrain("meshes"):
            asset = item["asset"]
            lo, hi = asset.points.min(axis=0), asset.points.max(axis=0)
            near = np.flatnonzero(np.all((q >= lo) & (q <= hi), axis=1) & self._in_world(world))
            if near.size == 0:
                continue
            inside = near[winding_numbers(asset.points, asset.triangles, q[near]) > 0.5]
            if inside.size:
                depth[inside] = np.maximum(depth[inside], distances_to_triangles(asset.points, asset.triangles, q[inside]))
        return depth

    # -- jellies --------------------------------------------------------------------------------

    def _jellies(self, q):
        """Depth of each particle inside another jelly and inside its own folded body (0: outside)."""
        other, own = np.zeros(len(q)), np.zeros(len(q))
        if len(self.cells) == 0:
            return other, own
        corners = q[self.cells]
        finite = np.isfinite(corners).all(axis=(1, 2))
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        ok_points = np.isfinite(q).all(axis=1)
        # Grid bins of a spacing, or larger where a cell has been stretched far (at most 9 bins a side
        # per cell, so a torn lattice does not enumerate millions of bins).
        extent = float((hi - lo)[finite].max(initial=0.0))
        h = max(float(self.spacing.max()), extent / 8.0)
        live = np.flatnonzero(finite)
        point, cell = _candidate_pairs(np.where(ok_points[:, None], q, 0.0), lo[live], hi[live], h)
        cell = live[cell]
        keep = ok_points[point]
        point, cell = point[keep], cell[keep]
        pj, cj = self.jelly_of[point], self.cell_jelly[cell]
        keep = self.worlds[point] == self.worlds[self.cells[cell, 0]]
        same = pj == cj
        # Own cells: only those with every corner at least ``exclusion`` rest spacings away.
        local = self.rest[self.cells[cell]] - self.rest[point][:, None, :]
        far = np.linalg.norm(local, axis=2).min(axis=1) >= self.exclusion * self.spacing[pj] * (1 - 1e-9)
        keep &= ~same | far
        point, cell, same = point[keep], cell[keep], same[keep]
        if point.size == 0:
            return other, own
        tri = corners[cell][:, _CELL_TRIANGLES] - q[point][:, None, None, :]
        wind = _solid_angles(tri[:, :, 0], tri[:, :, 1], tri[:, :, 2]).sum(axis=1) / (4.0 * math.pi)
        inside = np.abs(wind) > 0.5
        for is_self, depth in ((False, other), (True, own)):
            sel = inside & (same == is_self)
            for j in np.unique(self.cell_jelly[cell[sel]]):
                pts = np.unique(point[sel & (self.cell_jelly[cell] == j)])
                tris = self.boundaries[j]
                skip = None
                if is_self:
                    ends = self.rest[tris]  # (T, 3, 3)
                    gap = np.linalg.norm(ends[None] - self.rest[pts][:, None, None, :], axis=3).min(axis=2)
                    skip = gap < self.exclusion * self.spacing[j] * (1 - 1e-9)
                d = distances_to_triangles(q, tris, q[pts], skip=skip)
                depth[pts] = np.maximum(depth[pts], np.where(np.isfinite(d), d, 0.0))
        return other, own


def summary_line(summary: dict) -> str:
    """One line of the worst penetration of a run, per kind, and the inverted cells."""
    h = summary["spacing"]
    parts = [f"{kind}: {s['count']} particles, deepest {s['deepest']:.3g} m ({100 * s['deepest'] / h:.2f}% of the spacing)"
             for kind, s in ((k, summary[k]) for k in KINDS)]
    return (f"penetration over {summary['frames']} frames: " + "; ".join(parts)
            + f"; inverted cells at most {summary['inverted_cells']}")
