"""USD output: one stage per run, written as the run goes and moved into place when closed.

``pxr`` is imported lazily so that benchmarks run where usd-core is not installed.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..core import lattice
from ..core.mesh_terrain import face_varying_normals, sample_points
from ..core.pins import motion_transform
from ..core.terrain import fan_triangles, vertex_normals
from ..core.errors import CommandLineError
from .outputs import commit, discard, kept_partial_path, partial_path, target_of

SPRING_COLORS = {  # the seed's colours: structural blue, shear yellow, bending green
    "structural": (0.2, 0.4, 1.0),
    "shear": (1.0, 0.85, 0.1),
    "bending": (0.2, 0.8, 0.3),
}
JELLY_COLOR = (0.95, 0.35, 0.25)
TERRAIN_COLOR = (0.6, 0.6, 0.6)


def plane_mesh(point, normal, size, hole_center=None, hole_radius=0.0, segments=64):
    """Vertices and faces of a square of edge ``size`` on a plane, with a circular hole cut out.

    Returns:
        ``(points (V, 3), counts (F,), indices (sum counts,))``.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    point = np.asarray(point, dtype=np.float64)
    if hole_radius <= 0:
        c = point
        half = 0.5 * size
        corners = [c + half * (su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        return np.array(corners), np.array([4]), np.array([0, 1, 2, 3])  # (u, v, n) right-handed: faces n
    # Centre the square on the hole (projected onto the plane) and join the hole's circle to the
    # square's boundary with quads along rays from the centre.
    hc = np.asarray(hole_center, dtype=np.float64)
    c = hc - np.dot(hc - point, n) * n
    half = max(0.5 * size, 1.05 * hole_radius)
    ang = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    ray = half / np.max(np.abs(dirs), axis=1)  # distance from the centre to the square along each ray
    inner = c + hole_radius * (dirs[:, :1] * u + dirs[:, 1:] * v)
    outer = c + ray[:, None] * (dirs[:, :1] * u + dirs[:, 1:] * v)
    pts = np.concatenate([inner, outer])
    idx = []
    for i in range(segments):
        j = (i + 1) % segments
        idx += [i, segments + i, segments + j, j]
    return pts, np.full(segments, 4), np.array(idx)


class SurfaceMap:
    """How a jelly's ``Surface`` mesh follows its particles.

    A box jelly shows its boundary particles themselves (``take``: the particle of each surface
    vertex). A mesh jelly shows its asset's surface embedded in the lattice (``corners``,
    ``weights``: each vertex a trilinear combination of a cell's eight particles), with the
    asset's topology and primvars. Velocities map the same way (the map is linear).
    """

    def __init__(self, counts, indices, take=None, corners=None, weights=None, primvars=()):
        self.counts = np.asarray(counts, dtype=np.int64)
        self.indices = np.asarray(indices, dtype=np.int64)
        self.take, self.corners, self.weights = take, corners, weights
        self.primvars = list(primvars)
        self.double_sided = False
        self.triangles = fan_triangles(self.counts, self.indices)

    @classmethod
    def of(cls, info):
        """The map of a :class:`~softsim_warp.core.model.JellyInfo`, or None when it has no surface."""
        emb = getattr(info, "embedding", None)
        if emb is not None:
            return cls(emb.counts, emb.indices, corners=emb.corners, weights=emb.weights, primvars=emb.primvars)
        quads = info.surface_quads
        if not quads.size:
            return None
        double_sided = min(info.shape) == 1
        if double_sided:
            # A one-particle-thick jelly lists each face once per side, on the same particles: keep
            # one side (doubleSided shows both), so every vertex has one normal.
            _, first = np.unique(np.sort(quads, axis=1), axis=0, return_index=True)
            quads = quads[np.sort(first)]
        used = np.unique(quads)
        remap = np.full(info.particle_count, -1, dtype=np.int64)
        remap[used] = np.arange(used.size)
        surface = cls(np.full(quads.shape[0], 4), remap[quads].ravel(), take=used)
        surface.double_sided = double_sided
        return surface

    def points(self, x) -> np.ndarray:
        """Surface points (float32, contiguous) of the jelly's particle values ``x`` (positions or velocities)."""
        if self.take is not None:
            return np.ascontiguousarray(x[self.take])
        # Sum in float64: an undeformed jelly gives back its asset's vertices to float32 rounding.
        y = np.einsum("vk,vkj->vj", self.weights, x[self.corners].astype(np.float64))
        return np.ascontiguousarray(y, dtype=np.float32)


def _author_primvars(mesh, primvars, Sdf, UsdGeom, Vt):
    """Carry an asset's primvars (UVs, display colours, other plain data) over to a Mesh:
    ``(name, type name, interpolation, values (NumPy), indices or None)`` each, as
    ``core.mesh_assets`` keeps them (those that stay valid when the surface deforms)."""
    api = UsdGeom.PrimvarsAPI(mesh.GetPrim())
    for name, type_name, interpolation, values, indices in primvars:
        value_type = Sdf.ValueTypeNames.Find(type_name)
        pv = api.CreatePrimvar(name, value_type, interpolation)
        flat = np.asarray(values)
        if indices is None and interpolation != UsdGeom.Tokens.constant:
            # Repeated values (a UV shared by the corners around a vertex) are written once, indexed.
            uniq, inverse = np.unique(flat.reshape(len(flat), -1), axis=0, return_inverse=True)
            if len(uniq) < len(flat):
                flat, indices = uniq.reshape((-1,) + flat.shape[1:]), inverse.ravel()
        pv.Set(value_type.type.pythonClass.FromNumpy(np.ascontiguousarray(flat)))
        if indices is not None:
            pv.SetIndices(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))


class UsdWriter:
    """Writes a model's frames to a USD stage (``.usdc`` by default, ``.usda`` by extension).

    The stage is written to a hidden temporary beside ``path``'s target and moved into place by
    :meth:`close` (``outputs.commit``: flushed, renamed, the directory synced). A run that did not
    complete replaces ``path`` only when no file was there before it; otherwise, and always for a
    run that failed, its frames are kept as ``<stem>.partial<suffix>`` (``written_path`` says
    where), so a good output is never replaced by a worse one. The temporary is saved every
    ``save_every_frames`` frames, by simulated frames, so identical runs write identical bytes. A
    frame with a non-finite position is written as it is, and the file is then never marked
    complete (status ``nonfinite``).

    Args:
        path: output file.
        model: the model whose particles are written.
        fps: frames per second (time code = frame index).
        springs: also write spring segments as BasisCurves, one prim per spring type.
        groups: optional ``{world: (prim_name, offset)}`` to put each world under its own Xform
            with a translation (side-by-side comparisons).
    """

    def __init__(self, path, model, fps, springs=False, groups=None, save_every_frames=600, metadata=None):
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt  # noqa: PLC0415 - usd-core is optional on GPU hosts

        self._pxr = (Gf, Sdf, Usd, UsdGeom, Vt)
        self.path = Path(path)
        target = target_of(self.path)
        self.replaces = target.is_file()  # a file is there already: only a complete run may replace it
        self.tmp = partial_path(self.path)
        self.written_path = None
        self.model = model
        self.fps = float(fps)
        self.save_every = max(int(save_every_frames), 1)
        self.last_frame = -1
        self.nonfinite_frames = 0
        discard(self.tmp)
        from pxr import Tf  # noqa: PLC0415

        try:
            layer = Sdf.Layer.CreateNew(str(self.tmp))
        except Tf.ErrorException:
            layer = None
        if layer is None:  # USD writes the new file at once: a full disk fails here, as in save()
            discard(self.tmp)
            free = _free_bytes(self.tmp.parent)
            raise CommandLineError(
                "--out", f"cannot write '{target_of(self.path)}': the write failed (a full disk, a quota or a "
                "file size limit)" + (f" ({free / 1e6:.0f} MB free)" if free is not None else ""), str(self.path))
        stage = Usd.Stage.Open(layer)
        self.stage = stage
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(0)
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        self._metadata = dict(metadata or {})
        self._metadata.setdefault("softsim:status", "running")
        # The physics settings beside the caller's (integrator, dt): what a reader needs to rerun it.
        self._metadata.setdefault("softsim:gravity", Gf.Vec3d(*[float(g) for g in model.gravity_host]))
        self._metadata.setdefault("softsim:fps", self.fps)
        self._metadata.setdefault("softsim:precision", str(model.precision))
        layer.customLayerData = self._metadata

        groups = groups or {}
        self.roots = {}
        for w in range(model.world_count):
            if w in groups:
                name, offset = groups[w]
                xf = UsdGeom.Xform.Define(stage, f"/World/{name}")
                xf.AddTranslateOp().Set(Gf.Vec3d(*[float(c) for c in offset]))
                self.roots[w] = f"/World/{name}"
            else:
                self.roots[w] = "/World"

        self.moving_terrain = []  # (transform op, motion) of each moving plane, bowl and sphere
        self.jelly_prims = []
        for info in model.jellies:
            root = f"{self.roots[info.world]}/{info.name}"
            UsdGeom.Xform.Define(stage, root)
            pts = UsdGeom.Points.Define(stage, f"{root}/Particles")
            width = 0.5 * min([s for s in info.spacing if s > 0] or [0.05])
            widths = Vt.FloatArray([width] * info.particle_count)
            pts.CreateWidthsAttr(widths)
            pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            # A particle's id is its index in the jelly, the same in every frame.
            pts.CreateIdsAttr(Vt.Int64Array.FromNumpy(np.arange(info.particle_count, dtype=np.int64)))
            pts.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([Gf.Vec3f(*JELLY_COLOR)]))
            surface = SurfaceMap.of(info)
            mesh = None
            if surface is not None:
                mesh = UsdGeom.Mesh.Define(stage, f"{root}/Surface")
                mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(surface.counts.astype(np.int32)))
                mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(surface.indices.astype(np.int32)))
                # The surface shows the simulated particles themselves, not a subdivision limit.
                mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
                if surface.double_sided:
                    mesh.CreateDoubleSidedAttr(True)
                if "displayColor" not in {pv[0] for pv in surface.primvars}:  # the asset's own colours win
                    mesh.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([Gf.Vec3f(*JELLY_COLOR)]))
                _author_primvars(mesh, surface.primvars, Sdf, UsdGeom, Vt)
            curves = {}
            if springs:
                for t, tname in enumerate(lattice.SPRING_TYPE_NAMES):
                    lo, hi = info.spring_start, info.spring_start + info.spring_count
                    sel = np.nonzero(model.spring_type_host[lo:hi] == t)[0] + lo
                    if sel.size == 0:
                        continue
                    c = UsdGeom.BasisCurves.Define(stage, f"{root}/Springs_{tname}")
                    c.CreateTypeAttr(UsdGeom.Tokens.linear)
                    c.CreateCurveVertexCountsAttr(Vt.IntArray([2] * sel.size))
                    c.CreateWidthsAttr(Vt.FloatArray([0.1 * width]))
                    c.SetWidthsInterpolation(UsdGeom.Tokens.constant)
                    c.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([Gf.Vec3f(*SPRING_COLORS[tname])]))
                    curves[tname] = (c, model.spring_indices_host[sel].ravel(), Vt.FloatArray([0.1 * width]))
            self.jelly_prims.append((info, pts, widths, mesh, surface, curves))
        # The initial pose as every attribute's default value: a reader that asks for no time
        # (and validators that count normals against the default points) sees a whole mesh.
        self._write_jellies(np.ascontiguousarray(model.particle_q_host, dtype=np.float32), None, Usd.TimeCode.Default())

        plane_index = {}  # numbered within each world, so every copy of a comparison has Plane_0
        for p in model.planes:
            i = plane_index[p["world"]] = plane_index.get(p["world"], -1) + 1
            points, counts, indices = plane_mesh(p["point"], p["normal"], p["size"], p["hole_center"], p["hole_radius"])
            mesh = self.add_static_mesh(f"{self.roots[p['world']]}/Plane_{i}", points, counts, indices)
            if p.get("motion") is not None:
                self._animate(mesh, p["motion"])
        # Bowls and spheres; ``self.roots`` puts each world's terrain under its group.
        # (a mesh terrain adds its normals and its asset's primvars as a fifth and sixth item).
        for prim_path, points, counts, indices, *extra in model.terrain_meshes(self.roots):
            self.add_static_mesh(prim_path, points, counts, indices, normals=extra[0] if extra else None,
                                 primvars=extra[1] if len(extra) > 1 else ())
        for prim_path, motion in model.terrain_motions(self.roots):
            self._animate(UsdGeom.Mesh.Get(stage, prim_path), motion)
        # Animated meshes: their points (and extent and flat normals) sampled at every frame.
        self.animated_meshes = []
        for prim_path, times, samples in model.terrain_animations(self.roots):
            mesh = UsdGeom.Mesh.Get(stage, prim_path)
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
            indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
            self.animated_meshes.append((mesh, times, samples, counts, indices))
        self.save()

    def _animate(self, mesh, motion):
        """Give moving terrain (its mesh as given) a transform, time-sampled at every frame by
        :meth:`write_frame`: the rigid map of its motion (``core/pins.motion_transform``)."""
        Gf = self._pxr[0]
        op = mesh.AddTransformOp()
        op.Set(Gf.Matrix4d(1.0))  # the default: the mesh as given
        self.moving_terrain.append((op, motion))

    def add_static_mesh(self, prim_path, points, counts, indices, color=TERRAIN_COLOR, normals=None, primvars=()):
        """A mesh that does not move (terrain); ``normals`` ``(interpolation, (N, 3))`` or None for
        area-weighted vertex normals of its faces; ``primvars`` as ``MeshAsset.primvars`` (a
        displayColor among them replaces ``color``)."""
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        mesh = UsdGeom.Mesh.Define(self.stage, prim_path)
        pts = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
        mesh.CreatePointsAttr(pts)
        mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(pts))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in indices]))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        if normals is None:
            normals = (UsdGeom.Tokens.vertex, vertex_normals(points, fan_triangles(counts, indices)))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals[1], dtype=np.float32)))
        mesh.SetNormalsInterpolation(normals[0])
        mesh.CreateDoubleSidedAttr(True)
        if "displayColor" not in {pv[0] for pv in primvars}:
            mesh.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([Gf.Vec3f(*color)]))
        _author_primvars(mesh, primvars, Sdf, UsdGeom, Vt)
        return mesh

    wants_velocities = True
    """The Simulator passes ``velocities=`` to :meth:`write_frame` (motion blur)."""

    takes_time_code = True
    """The Simulator passes ``time_code=`` for a shorter last frame (a duration not a whole number of frames)."""

    def write_frame(self, frame, t, positions, metrics=None, velocities=None, time_code=None):
        """Write all jellies' positions (float32, as simulated in float32) at time code ``frame``
        (or ``time_code``, the last frame's ``t * fps`` when it is shorter than the others).

        Extents include the points' widths; the Surface gets its normals; ``velocities`` (the
        particles' [m/s], same shape as ``positions``), when given, go to Particles and Surface.
        """
        pos32 = np.ascontiguousarray(positions, dtype=np.float32)
        vel32 = None if velocities is None else np.ascontiguousarray(velocities, dtype=np.float32)
        if not np.isfinite(pos32).all():
            self.nonfinite_frames += 1
        code = frame if time_code is None else time_code
        self._write_jellies(pos32, vel32, code)
        Gf = self._pxr[0]
        for op, motion in self.moving_terrain:
            rot, shift = motion_transform(motion, t)
            # USD transforms row vectors (p' = p M): R transposed, the translation in the last row.
            m = np.identity(4)
            m[:3, :3] = rot.T
            m[3, :3] = shift
            op.Set(Gf.Matrix4d(m.tolist()), code)
        if self.animated_meshes:
            Vt = self._pxr[4]
            UsdGeom = self._pxr[3]
            for mesh, times, samples, counts, indices in self.animated_meshes:
                pts = sample_points(times, samples, t)
                p32 = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pts, dtype=np.float32))
                mesh.GetPointsAttr().Set(p32, code)
                mesh.GetExtentAttr().Set(UsdGeom.PointBased.ComputeExtent(p32), code)
                normals = face_varying_normals(pts, counts, indices)[1]
                mesh.GetNormalsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32)), code)
        self.last_frame = frame
        self.stage.SetEndTimeCode(max(code, 0))
        if frame > 0 and frame % self.save_every == 0:
            self.save()

    def _write_jellies(self, pos32, vel32, time):
        """Points, extents (widths included), Surface normals and, if given, velocities at ``time``."""
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        for info, pts, widths, mesh, surface, curves in self.jelly_prims:
            lo, hi = info.particle_start, info.particle_start + info.particle_count
            x = pos32[lo:hi]
            arr = Vt.Vec3fArray.FromNumpy(x)
            pts.GetPointsAttr().Set(arr, time)
            pts.GetExtentAttr().Set(UsdGeom.Points.ComputeExtent(arr, widths), time)
            if vel32 is not None:
                pts.GetVelocitiesAttr().Set(Vt.Vec3fArray.FromNumpy(vel32[lo:hi]), time)
            if mesh is not None:
                sx = surface.points(x)
                surf = Vt.Vec3fArray.FromNumpy(sx)
                mesh.GetPointsAttr().Set(surf, time)
                mesh.GetExtentAttr().Set(UsdGeom.PointBased.ComputeExtent(surf), time)
                normals = vertex_normals(sx, surface.triangles).astype(np.float32)
                mesh.GetNormalsAttr().Set(Vt.Vec3fArray.FromNumpy(normals), time)
                if vel32 is not None:
                    mesh.GetVelocitiesAttr().Set(Vt.Vec3fArray.FromNumpy(surface.points(vel32[lo:hi])), time)
            for c, ends, cwidths in curves.values():
                seg = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pos32[ends]))
                c.GetPointsAttr().Set(seg, time)
                c.GetExtentAttr().Set(UsdGeom.Curves.ComputeExtent(seg, cwidths), time)

    def save(self):
        """Write the stage to the temporary; a write error (a full disk) is a one-line error naming the file."""
        from pxr import Tf  # noqa: PLC0415

        try:
            ok = self.stage.GetRootLayer().Save()
        except Tf.ErrorException:
            ok = False
        if not ok:
            reason = "the write failed (a full disk, a quota or a file size limit)"
            # A layer whose save failed is not touched again (USD may crash on it): the run's frames
            # are lost, the previous output stays as it was.
            self.discard()
            free = _free_bytes(self.tmp.parent)
            raise CommandLineError(
                "--out", f"cannot write '{target_of(self.path)}': {reason}"
                + (f" ({free / 1e6:.0f} MB free)" if free is not None else ""), str(self.path)
            )

    def close(self, status="complete", extra=None) -> Path:
        """Record ``status`` in the layer's custom data, save, and move the file into place (see the
        class docstring); returns the path the frames went to (``written_path``)."""
        if self.stage is None:  # discarded after a failed save: nothing to move into place
            return None
        if status == "complete" and self.nonfinite_frames:
            status = "nonfinite"
        self._metadata["softsim:status"] = status
        self._metadata.update(extra or {})
        self.stage.GetRootLayer().customLayerData = self._metadata
        try:
            self.save()
        except BaseException:
            self.discard()
            raise
        self.stage = None
        if status == "complete" or (status != "failed" and not self.replaces):
            commit(self.tmp, self.path, "--out")
            self.written_path = self.path
        else:
            kept = kept_partial_path(self.path)
            commit(self.tmp, kept, "--out")
            self.written_path = kept
        return self.written_path

    def discard(self):
        """Drop the temporary file (used when nothing worth keeping was written)."""
        self.stage = None
        discard(self.tmp)


def _free_bytes(directory) -> int | None:
    try:
        st = os.statvfs(directory)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize
