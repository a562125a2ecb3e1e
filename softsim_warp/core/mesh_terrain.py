"""Triangle-mesh terrain: the model's arrays and BVHs (``wp.Mesh``), its motion, and its output mesh.

Collision is ``collide_meshes`` in kernels/mesh.py, launched by ``contact._launch_contacts`` like
every other terrain kind. A model without meshes allocates nothing here (``mesh_count`` = 0).

A mesh moves in two ways. A rigid ``motion`` (a pin's, as every terrain entry takes) leaves its
vertices and BVH where they were built: ``collide_moving_meshes`` queries it in its own frame
(the particle carried there by the inverse of the pose ``move_terrain`` wrote), so the step is the
same list of launches at every step and a graph captures it on the CPU and on CUDA. An animated USD
asset (``animated = true``) has its time samples on the device (:class:`MeshAnimation`);
``deform_mesh`` interpolates them at every step and the BVH is refit, a host call that no graph
records (checked: a CPU graph replays without it, benchmarks/check_moving_mesh_cuda.py), so a scene
with an animated mesh steps without graphs. Static meshes launch what they did (``collide_meshes``).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .terrain import face_normals
from ..kernels import mesh as mesh_kernels
from ..kernels import pins as pins_kernels


def attach_meshes(m, meshes: list, arr, first):
    """Put the builder's ``meshes`` (dicts of :meth:`ModelBuilder.add_mesh`) on model ``m``, sorted by
    world (``ModelBuilder.finalize``, before the model is frozen; ``Model`` declares the fields).

    Model attributes:
        meshes: host list of dicts (``asset`` in world space, coefficients, world), sorted by world.
        mesh_count: number of terrain meshes.
        mesh_first: index of each world's first mesh, shape [world_count + 1], int32.
        mesh_bvh: host list of the ``wp.Mesh`` objects (kept alive for their ids).
        mesh_id: ``wp.Mesh`` ids, shape [mesh_count], uint64.
        mesh_closed: 1 for a closed mesh (inside by winding number), 0 for an open sheet, shape [mesh_count], int32.
        mesh_reach: how far behind its surface a mesh still pushes particles out [m], shape [mesh_count], scalar.
        mesh_tri_start: each mesh's first triangle in ``mesh_tris``, shape [mesh_count], int32.
        mesh_tris: vertex indices into ``mesh_points`` of every triangle, shape [sum of triangles], vec3i.
        mesh_points: every mesh's vertices in the model's precision [m], shape [sum of vertices], vec3.
        mesh_restitution, mesh_friction: coefficients [1], shape [mesh_count], scalar.
        mesh_motion: each mesh's index among the moving terrain (its rigid ``motion``; -1: none),
            shape [mesh_count], int32 (``contact.TerrainMotion`` fills it in); None without meshes.
        mesh_animated: 1 for a mesh that follows its asset's time samples, shape [mesh_count], int32;
            None without meshes.
        mesh_animation: the animated meshes' samples on the device (:class:`MeshAnimation`), or None.
    """
    meshes = sorted(meshes, key=lambda it: it["world"])
    m.meshes = meshes
    m.mesh_count = len(meshes)
    m.mesh_first = first(meshes)
    if not meshes:
        # Empty arrays (kernels that take every terrain kind, the implicit touch test, read none).
        m.mesh_bvh = []
        m.mesh_id = wp.zeros(0, dtype=wp.uint64, device=m.device)
        m.mesh_closed = wp.zeros(0, dtype=wp.int32, device=m.device)
        m.mesh_reach = wp.zeros(0, dtype=m.scalar, device=m.device)
        m.mesh_tri_start = wp.zeros(0, dtype=wp.int32, device=m.device)
        m.mesh_tris = wp.zeros(0, dtype=wp.vec3i, device=m.device)
        m.mesh_points = wp.zeros(0, dtype=m.vec3, device=m.device)
        m.mesh_restitution = wp.zeros(0, dtype=m.scalar, device=m.device)
        m.mesh_friction = wp.zeros(0, dtype=m.scalar, device=m.device)
        m.mesh_motion = None
        m.mesh_animated = None
        m.mesh_animation = None
        return
    m.mesh_bvh = []
    tri_start, tris, points, offset = [], [], [], 0
    for it in meshes:
        a = it["asset"]
        tri = np.ascontiguousarray(a.triangles, dtype=np.int32)
        m.mesh_bvh.append(
            wp.Mesh(
                points=wp.array(np.asarray(a.points, dtype=np.float32), dtype=wp.vec3, device=m.device),
                indices=wp.array(tri.ravel(), dtype=wp.int32, device=m.device),
                # A closed mesh tells inside from outside by winding number (else Warp casts rays).
                support_winding_number=a.closed,
            )
        )
        tri_start.append(sum(t.shape[0] for t in tris))
        tris.append(tri + offset)
        points.append(a.points)
        offset += a.points.shape[0]
    m.mesh_id = wp.array(np.array([b.id for b in m.mesh_bvh], dtype=np.uint64), dtype=wp.uint64, device=m.device)
    m.mesh_closed = arr(np.array([int(it["asset"].closed) for it in meshes]), wp.int32, np.int32)
    m.mesh_reach = arr(np.array([it["thickness"] for it in meshes]), m.scalar, _np(m))
    m.mesh_tri_start = arr(np.array(tri_start), wp.int32, np.int32)
    m.mesh_tris = arr(np.concatenate(tris), wp.vec3i, np.int32)
    m.mesh_points = arr(np.concatenate(points), m.vec3, _np(m))
    m.mesh_restitution = arr(np.array([it["restitution"] for it in meshes]), m.scalar, _np(m))
    m.mesh_friction = arr(np.array([it["friction"] for it in meshes]), m.scalar, _np(m))
    m.mesh_motion = arr(np.full(len(meshes), -1), wp.int32, np.int32)
    m.mesh_animated = arr(np.array([int(it.get("samples") is not None) for it in meshes]), wp.int32, np.int32)
    animated = [k for k, it in enumerate(meshes) if it.get("samples") is not None]
    starts = np.cumsum([0] + [p.shape[0] for p in points[:-1]])
    m.mesh_animation = MeshAnimation(m, animated, starts) if animated else None


class MeshAnimation:
    """The time-sampled vertices of a model's animated meshes on the device.

    Per animated mesh its sample times [s] and its samples, an array [samples, vertices]; at every
    step's start ``deform_mesh`` puts its vertices where they are at the step's end (linear between
    samples) and its BVH is refit. ``wp.Mesh.refit`` is a host call (on the CPU Warp's graph does
    not record it; on CUDA it is not part of a capture either), so a model with an animated mesh
    steps without a captured graph (``Stepper``). What moves (the vertices, the BVHs, the clock)
    is each run's own (:class:`MeshPoses`).

    ``meshes``: per animated mesh ``(mesh index, first sample time, sample count, first vertex in
    mesh_points, samples [S, V] vec3)``; ``time``: every animated mesh's sample times [s], scalar.
    """

    def __init__(self, m, animated, starts):
        scalar, np_scalar = m.scalar, _np(m)
        times, self.meshes = [], []
        for k in animated:
            t, samples = m.meshes[k]["samples"]
            self.meshes.append((k, len(times), len(t), int(starts[k]),
                                wp.array(np.asarray(samples, dtype=np_scalar), dtype=m.vec3, device=m.device)))
            times.extend(t)
        self.time = wp.array(np.asarray(times, dtype=np_scalar), dtype=scalar, device=m.device)


class MeshPoses:
    """The terrain meshes where one run has them (part of :class:`~softsim_warp.core.model.RunState`).

    With an animated mesh: the run's own copy of every vertex (``mesh_points``), its own BVH of
    each animated mesh (``mesh_bvh``, ``mesh_id``; a static mesh's are the model's), each vertex's
    velocity over the last step and the animation clock. Otherwise the model's arrays, which
    nothing writes, and ``clock`` None.

    Attributes:
        mesh_bvh: host list of the ``wp.Mesh`` objects, one per mesh.
        mesh_id: their ids, shape [mesh_count], uint64.
        mesh_points: every mesh's vertices [m], shape [sum of vertices], vec3.
        mesh_point_velocity: each vertex's velocity over the last step [m/s] (animated meshes; one
            zero entry without them), vec3; None without meshes.
        clock: steps taken by the animation, shape [1], int32, or None.
    """

    def __init__(self, model):
        an = model.mesh_animation
        self.clock = None
        self.mesh_bvh, self.mesh_id, self.mesh_points = model.mesh_bvh, model.mesh_id, model.mesh_points
        self.mesh_point_velocity = wp.zeros(1, dtype=model.vec3, device=model.device) if model.mesh_count else None
        if an is None:
            return
        device = model.device
        self.clock = wp.zeros(1, dtype=wp.int32, device=device)
        self.mesh_points = wp.clone(model.mesh_points)
        self.mesh_point_velocity = wp.zeros(model.mesh_points.shape[0], dtype=model.vec3, device=device)
        self.mesh_bvh = list(model.mesh_bvh)
        for k, _first, _count, _start, _samples in an.meshes:
            bvh = model.mesh_bvh[k]
            self.mesh_bvh[k] = wp.Mesh(points=wp.clone(bvh.points), indices=bvh.indices,
                                       support_winding_number=bool(model.meshes[k]["asset"].closed))
        self.mesh_id = wp.array(np.array([b.id for b in self.mesh_bvh], dtype=np.uint64), dtype=wp.uint64,
                                device=device)

    def reset(self):
        """Restart the animation clock at t = 0."""
        if self.clock is not None:
            self.clock.zero_()


def animate_meshes(model, run, dt):
    """Put the animated meshes of ``run`` (a ``RunState``) where their samples have them at the end
    of the step about to be taken, refit their BVHs and advance their clock; nothing without
    animated meshes."""
    an = model.mesh_animation
    if an is None:
        return
    poses = run.meshes
    h = model.scalar(dt)
    for k, first, count, start, samples in an.meshes:
        bvh = poses.mesh_bvh[k]
        wp.launch(mesh_kernels.deform_mesh, dim=samples.shape[1],
                  inputs=[poses.clock, h, first, count, an.time, samples, start],
                  outputs=[poses.mesh_points, bvh.points, poses.mesh_point_velocity], device=model.device)
        bvh.refit()
    wp.launch(pins_kernels.advance_pin_clock, dim=1, inputs=[poses.clock], device=model.device)


def steps_on_host(model) -> bool:
    """Whether a step of ``model`` has host work (an animated mesh's refit), so no graph may
    capture it."""
    return model.mesh_animation is not None


def sample_points(times, samples, t: float) -> np.ndarray:
    """An animated mesh's vertices at ``t`` [s] on the host: linear between its samples (``times``
    [S], ``samples`` [S, V, 3]), held outside them, as ``deform_mesh`` interpolates."""
    times = np.asarray(times, dtype=np.float64)
    if t <= times[0]:
        return np.asarray(samples[0], dtype=np.float64)
    if t >= times[-1]:
        return np.asarray(samples[-1], dtype=np.float64)
    s = int(np.searchsorted(times, t, side="left")) - 1
    u = (t - times[s]) / (times[s + 1] - times[s])
    return samples[s] + (samples[s + 1] - samples[s]) * u


def _np(m):
    return np.float32 if m.precision == "float32" else np.float64


def moving_mesh_arrays(model, run) -> tuple:
    """What ``collide_moving_meshes`` takes after :func:`mesh_arrays`: each mesh's motion index and
    animation flag, the vertices' velocities, and the rigid motions' arrays (``contact.TerrainMotion``
    and ``run``'s poses; a zero entry each when no terrain moves rigidly)."""
    tm = model.terrain_motion
    if tm is None:
        z = wp.zeros(1, dtype=model.vec3, device=model.device)
        rigid = (z, z, z, z, z)
    else:
        poses = run.terrain
        rigid = (tm.center, poses.center_now, poses.turn_now, poses.velocity_step, tm.spin)
    return (model.mesh_motion, model.mesh_animated, run.meshes.mesh_point_velocity, *rigid)


def mesh_moves(model) -> bool:
    """Whether a terrain mesh of ``model`` moves (a rigid motion or its asset's animation)."""
    return any(it.get("motion") is not None or it.get("samples") is not None for it in model.meshes)


def mesh_arrays(model, run) -> tuple:
    """The meshes' arrays in the order ``collide_meshes`` takes them (``run``'s current vertices and BVHs)."""
    poses = run.meshes
    return (
        model.mesh_first,
        poses.mesh_id,
        model.mesh_closed,
        model.mesh_reach,
        model.mesh_tri_start,
        model.mesh_tris,
        poses.mesh_points,
        model.mesh_restitution,
        model.mesh_friction,
    )


def mesh_touch_arrays(model, run) -> tuple:
    """The meshes' arrays that the implicit integrator's touch test takes (``constrain_contacts``)."""
    poses = run.meshes
    return (
        model.mesh_first,
        poses.mesh_id,
        model.mesh_closed,
        model.mesh_reach,
        model.mesh_tri_start,
        model.mesh_tris,
        poses.mesh_points,
    )


def mesh_output(meshes, roots) -> list:
    """``(prim path, points, counts, indices, normals, primvars)`` of each terrain mesh for the USD
    stage: the asset's own polygons, flat-shaded (each face corner carries its face's normal,
    faceVarying), with the primvars of each of its Meshes (``MeshAsset.primvars``)."""
    out = []
    for path, it in zip(mesh_paths(meshes, roots), meshes):
        a = it["asset"]
        out.append((path, a.points, a.counts, a.indices, face_varying_normals(a.points, a.counts, a.indices),
                    a.primvars))
    return out


def face_varying_normals(points, counts, indices) -> tuple:
    """A flat-shaded mesh's normals for USD: each face corner carries its face's normal."""
    return ("faceVarying", np.repeat(face_normals(points, counts, indices), counts, axis=0))


def mesh_paths(meshes, roots) -> list:
    """The USD prim path of each terrain mesh: its name, numbered within its world."""
    out, index = [], {}
    for it in meshes:
        i = index[it["world"]] = index.get(it["world"], -1) + 1
        out.append(f"{roots.get(it['world'], '/World')}/{it.get('name') or 'Mesh'}_{i}")
    return out


def mesh_anchors(meshes) -> list:
    """Bounding-box corners of each mesh [m] (for the explosion speed bound)."""
    pts = []
    for it in meshes:
        p = it["asset"].points
        pts += [p.min(axis=0), p.max(axis=0)]
    return pts


def mesh_signed_distance(asset, points: np.ndarray) -> np.ndarray:
    """Host signed distance of ``points`` to a mesh terrain (NumPy, for the scene checks) [m]:
    negative behind the nearest face (inside a closed mesh wound outward, behind an open sheet).
    Points in the bounding box are measured by brute force over the triangles, in chunks."""
    p = np.asarray(points, dtype=np.float64)
    v = asset.points
    t = asset.triangles
    # Outside the bounding box nothing is inside: the distance to the box is a positive lower bound.
    lo, hi = v.min(axis=0), v.max(axis=0)
    gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    out = np.linalg.norm(gap, axis=1)
    near = np.nonzero(out == 0.0)[0]
    if near.size:
        out[near] = _brute_distance(v, t, p[near])
    return out


def _brute_distance(v, t, p):
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    out = np.empty(p.shape[0])
    chunk = max(1, (1 << 22) // max(t.shape[0], 1))
    for s in range(0, p.shape[0], chunk):
        x = p[s : s + chunk, None, :]
        q = _closest_on_triangles(x, a[None], b[None], c[None])
        d = x - q
        dist = np.linalg.norm(d, axis=2)
        k = np.argmin(dist, axis=1)
        rows = np.arange(x.shape[0])
        side = np.sign(np.einsum("ij,ij->i", d[rows, k], n[k]))
        side[side == 0] = 1.0
        out[s : s + chunk] = dist[rows, k] * side
    return out


def _closest_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to p, broadcast (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("...k,...k", ab, ap), np.einsum("...k,...k", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("...k,...k", ab, bp), np.einsum("...k,...k", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("...k,...k", ab, cp), np.einsum("...k,...k", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(all="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        res = a + ab * v[..., None] + ac * w[..., None]
        # Vertex and edge regions, applied so that Ericson's first matching test wins.
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    res = np.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + (c - b) * t_bc[..., None], res)
    res = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * t_ac[..., None], res)
    res = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, res)
    res = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * t_ab[..., None], res)
    res = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, res)
    res = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, res)
    return res
