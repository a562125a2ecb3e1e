"""Triangle meshes read from files: USD (usd-core) and OBJ/STL/PLY (trimesh, an optional extra).

A mesh is read once per file, prim and modification time (``load_mesh`` is cached), in world space
(every xform above the prim and the stage's authored metersPerUnit applied; unauthored is metres). Polygons are kept as they are
for output (the asset's own topology, with its primvars) and split into fan triangles for the
queries (``MeshAsset.triangles``). Errors are one-line :class:`~softsim_warp.core.errors.SceneError`
lines naming the scene file, the key and the value.
"""

from __future__ import annotations

import functools
import math
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SceneError
from .native_output import held_stderr
from .terrain import fan_triangles, signed_volume

USD_SUFFIXES = (".usd", ".usda", ".usdc")
TRIMESH_SUFFIXES = (".obj", ".stl", ".ply")


@dataclass
class MeshAsset:
    """One mesh in world space [m], float64."""

    points: np.ndarray
    """Vertex positions [m], shape [V, 3]."""
    counts: np.ndarray
    """Vertices per face, shape [F]."""
    indices: np.ndarray
    """Face vertex indices, shape [sum(counts)]."""
    primvars: list = field(default_factory=list)
    """``(name, type name, interpolation, values, indices or None)`` of each primvar to carry over (UVs)."""
    name: str = ""

    @functools.cached_property
    def triangles(self) -> np.ndarray:
        """Fan triangles of the faces, shape [T, 3], int64."""
        return fan_triangles(self.counts, self.indices)

    @functools.cached_property
    def edge_uses(self) -> tuple:
        """``(boundary edges, non-manifold edges)``: edges with one face, edges with more than two.

        Vertices at the same position count as one (a UV seam splits vertices, not the surface).
        """
        _, weld = np.unique(self.points, axis=0, return_inverse=True)
        t = weld.ravel()[self.triangles]
        e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
        _, count = np.unique(e, axis=0, return_counts=True)
        return int((count == 1).sum()), int((count > 2).sum())

    @property
    def closed(self) -> bool:
        """Every edge joins exactly two triangles (a watertight surface)."""
        boundary, non_manifold = self.edge_uses
        return boundary == 0 and non_manifold == 0 and self.triangles.shape[0] > 0

    def volume(self) -> float:
        return signed_volume(self.points, self.triangles)

    def transformed(self, matrix, translate) -> MeshAsset:
        """The mesh under x -> matrix x + translate (a negative determinant reverses every face)."""
        pts = self.points @ np.asarray(matrix, dtype=np.float64).T + np.asarray(translate, dtype=np.float64)
        out = MeshAsset(pts, self.counts, self.indices, self.primvars, self.name)
        return out.reversed() if np.linalg.det(matrix) < 0 else out

    def reversed(self) -> MeshAsset:
        """The same surface with every face's winding reversed (face-varying primvars follow)."""
        perm = _face_reversal(self.counts)
        primvars = []
        for name, type_name, interp, values, idx in self.primvars:
            if interp == "faceVarying":
                if idx is not None:
                    idx = np.asarray(idx)[perm]
                else:
                    permuted = np.ascontiguousarray(np.asarray(values)[perm])
                    values = permuted if isinstance(values, np.ndarray) else type(values).FromNumpy(permuted)
            primvars.append((name, type_name, interp, values, idx))
        return MeshAsset(self.points, self.counts, self.indices[perm], primvars, self.name)

    def outward(self) -> MeshAsset:
        """A closed mesh wound so that its faces point out of the volume they enclose."""
        if self.closed and self.volume() < 0:
            return self.reversed()
        return self


def _face_reversal(counts) -> np.ndarray:
    """The face-corner permutation that reverses every face's vertex order."""
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    ends = np.repeat(np.cumsum(counts) - 1, counts)
    corner = np.arange(int(counts.sum()))
    return starts + ends - corner


def load_mesh(path, prim=None, every=True, source="<scene>", key="mesh.path") -> MeshAsset:
    """Read a mesh file.

    Args:
        path: a ``.usd``/``.usda``/``.usdc`` file (usd-core) or ``.obj``/``.stl``/``.ply`` (trimesh).
        prim: the prim path of the Mesh in a USD file; default: every Mesh with UsdPhysics'
            CollisionAPI, else every Mesh (``every=True``, merged into one), or the first Mesh
            (``every=False``).
        source, key: the scene file and key that named it, for error messages.

    The format follows from the name given, not from the name a symlink points to (a content store
    names its files by hash: ``c.usda -> store/3f9a1c`` is USD, ``f.usda -> floor.obj`` is USD too).
    """
    p = Path(path)
    try:
        if not p.is_file():
            raise SceneError(source, key, "no such mesh file" if not p.exists() else "is not a regular file", str(path))
        st = os.stat(p)
        given = os.path.abspath(p)
        resolved = str(p.resolve())
    except OSError as e:  # a name too long, a loop of links, a directory without search permission
        raise SceneError(source, key, f"cannot read the file: {e.strerror or e}", str(path)) from None
    suffix = p.suffix.lower()
    if suffix not in USD_SUFFIXES + TRIMESH_SUFFIXES:
        raise SceneError(source, key, f"unknown mesh format; use {', '.join(USD_SUFFIXES + TRIMESH_SUFFIXES)}", str(path))
    return _load_cached(resolved, st.st_mtime_ns, st.st_size, prim, bool(every), source, key, given, suffix)


@functools.lru_cache(maxsize=32)
def _load_cached(path, _mtime, _size, prim, every, source, key, given, suffix):
    """``path``: the file (symlinks resolved, the cache's key); ``given``: the name to open it by
    (its extension picks the format, for usd-core and trimesh alike); ``suffix``: that extension."""
    if suffix in USD_SUFFIXES:
        mesh = _load_usd(given, prim, every, source, key)
    else:
        if prim is not None:
            raise SceneError(source, key.rsplit(".", 1)[0] + (".prim" if key.endswith(".path") else ".mesh_prim"),
                             "only a USD file has prims", prim)
        mesh = _load_trimesh(given, source, key, suffix.lstrip("."))
    if mesh.points.shape[0] == 0 or mesh.triangles.shape[0] == 0:
        raise SceneError(source, key, "the mesh has no faces", path)
    if not np.isfinite(mesh.points).all():
        raise SceneError(source, key, "the mesh has non-finite vertex positions", path)
    return mesh


def _load_trimesh(path, source, key, file_type):
    try:
        import trimesh  # noqa: PLC0415 - optional extra
    except ImportError:
        raise SceneError(source, key, "reading OBJ/STL/PLY needs trimesh: pip install 'softsim-warp[mesh]'",
                         path) from None
    try:
        tm = trimesh.load(path, file_type=file_type, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - any parse failure is the file's fault
        raise SceneError(source, key, f"cannot read the mesh: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
                         path) from None
    faces = np.asarray(getattr(tm, "faces", np.zeros((0, 3))), dtype=np.int64)
    points = np.asarray(getattr(tm, "vertices", np.zeros((0, 3))), dtype=np.float64)
    primvars = []
    uv = getattr(getattr(tm, "visual", None), "uv", None)
    if uv is not None and len(uv) == len(points):
        primvars.append(("st", "texCoord2f[]", "vertex", np.asarray(uv, dtype=np.float32), None))
    return MeshAsset(points, np.full(faces.shape[0], 3), faces.ravel(), primvars, Path(path).stem)


USD_EXPECTED = "a USD file with a Mesh"
_PXR_NAMESPACE = re.compile(r"pxrInternal_\w*?__pxrReserved__::")


def _usd_error_gist(exc) -> str:
    """The first message of a (multi-line, ``pxr.Tf.ErrorException``) USD error, on one line.

    Each of the exception's errors reads ``Error in '<function>' at line N in file F : '<message>'``;
    the first one is the cause (the later ones only say that the stage could not be opened).
    """
    for text in [str(a) for a in getattr(exc, "args", ())] or [str(exc)]:
        found = re.search(r" in file \S+ : '(.*)'\s*$", text, re.DOTALL)
        message = _PXR_NAMESPACE.sub("", found.group(1) if found else text)
        first = next((line.strip() for line in message.splitlines() if line.strip()), "")
        if first:
            return first
    return type(exc).__name__


# USD's warnings about the layer stack: the asset is not what its author composed.
_SUBLAYER_MISSING = re.compile(r"Could not load sublayer @([^@]*)@ of layer @([^@]*)@")
_SUBLAYER_CYCLE = re.compile(r"Sublayer hierarchy with root layer @([^@]*)@ has cycles\. "
                             r"Detected when layer @([^@]*)@ was seen")
_WARNED = set()  # (file, modification time, message) of the warnings printed
_USD_DIAGNOSTIC = re.compile(
    r"^(?:Warning|Error|Coding Error|Fatal Error|Status): (?:in \S+ at line \d+ of \S+ -- )?(.*)$")


def _load_usd(path, prim_path, every, source, key):
    """Read a USD asset; USD's own diagnostics (written by C++ straight to descriptor 2) become the
    project's lines: a sublayer that is missing or part of a cycle is an error (the asset is not
    what its author composed, and USD skips that sublayer silently but for its warning), any
    other diagnostic one ``warning:`` line on stderr."""
    from pxr import Tf  # noqa: PLC0415

    try:
        with held_stderr() as held:
            mesh = _read_usd(path, prim_path, every, source, key)
    except Tf.ErrorException as e:
        # Not USD (text in a .usdc), a syntax error in a .usda, a damaged crate file whose values
        # fail to read: the file's fault, one line.
        raise SceneError(
            source, key, f"cannot be read as USD ({_usd_error_gist(e)}); give {USD_EXPECTED}", path
        ) from None
    text = held[0] if held else ""
    missing = _SUBLAYER_MISSING.search(text)
    if missing:
        raise SceneError(source, key, f"its sublayer @{missing.group(1)}@ (in @{missing.group(2)}@) cannot be opened; "
                         "give the missing file or remove it from subLayers", path)
    cycle = _SUBLAYER_CYCLE.search(text)
    if cycle:
        raise SceneError(source, key, f"its subLayers form a cycle (@{cycle.group(2)}@ is reached twice, from "
                         f"@{cycle.group(1)}@); remove one of the subLayers entries", path)
    for line in text.splitlines():
        found = _USD_DIAGNOSTIC.match(line.strip())
        if found:
            note = re.sub(r" \(instantiating stage on stage @[^@]*@ <0x[0-9a-f]+>\)$", "",
                          _PXR_NAMESPACE.sub("", found.group(1)))
            # Once per file version: the scene's checks and the model's build each read the asset.
            seen = (os.path.realpath(path), os.stat(path).st_mtime_ns, note)
            if seen not in _WARNED:
                _WARNED.add(seen)
                print(f"warning: {SceneError(source, key, f'USD: {note}', path).line()}", file=sys.stderr)
            break
    return mesh


def _read_usd(path, prim_path, every, source, key):
    from pxr import Sdf, Usd, UsdGeom, UsdPhysics  # noqa: PLC0415

    stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    if stage is None:
        raise SceneError(source, key, f"cannot be opened as USD; give {USD_EXPECTED}", path)
    # An authored metersPerUnit converts to metres; without one the file is taken to be in metres,
    # softsim's unit (not USD's fallback of centimetres: most hand-made and script-made files mean metres).
    meters = UsdGeom.GetStageMetersPerUnit(stage) if UsdGeom.StageHasAuthoredMetersPerUnit(stage) else 1.0
    prim_key = key.rsplit(".", 1)[0] + (".prim" if key.endswith(".path") else ".mesh_prim")
    if prim_path is not None:
        if not Sdf.Path.IsValidPathString(prim_path):
            raise SceneError(source, prim_key, "is not a prim path", prim_path)
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsA(UsdGeom.Mesh):
            found = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)][:5]
            raise SceneError(source, prim_key, f"no Mesh prim there in {path}; Meshes: {', '.join(found) or 'none'}",
                             prim_path)
        prims = [prim]
    else:
        meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
        if not meshes:
            raise SceneError(source, key, "the file has no Mesh prim", path)
        colliders = [p for p in meshes if p.HasAPI(UsdPhysics.CollisionAPI)]
        prims = (colliders or meshes) if every else meshes[:1]
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    parts = []
    for prim in prims:
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        if counts.sum() != indices.size or (indices.size and (indices.min() < 0 or indices.max() >= len(pts))):
            raise SceneError(source, key, f"the Mesh {prim.GetPath()} has inconsistent face counts and indices", path)
        if (counts < 3).any():
            raise SceneError(source, key, f"the Mesh {prim.GetPath()} has faces of fewer than 3 vertices", path)
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row vectors: x' = x M
        pts = (pts @ m[:3, :3] + m[3, :3]) * meters
        # Faces wind right-handed in what we return: a left-handed mesh, or a mirroring xform, is reversed.
        flips = (mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded) != (np.linalg.det(m[:3, :3]) < 0)
        primvars = []
        if len(prims) == 1:
            for pv in UsdGeom.PrimvarsAPI(prim).GetPrimvarsWithValues():
                name = pv.GetPrimvarName()
                if name == "displayColor" or name == "displayOpacity" or pv.GetAttr().Get() is None:
                    continue
                interp = pv.GetInterpolation()
                idx = np.asarray(pv.GetIndices(), dtype=np.int32) if pv.IsIndexed() else None
                primvars.append((str(name), str(pv.GetTypeName()), str(interp), pv.GetAttr().Get(), idx))
        part = MeshAsset(pts, counts, indices, primvars, prim.GetName())
        parts.append(part.reversed() if flips else part)
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [p.points.shape[0] for p in parts[:-1]])
    return MeshAsset(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.counts for p in parts]),
        np.concatenate([p.indices + o for p, o in zip(parts, offsets)]),
        [],
        "+".join(p.name for p in parts),
    )


def transform_matrix(transform: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """``(3x3 matrix, translation)`` of a scene's ``transform = {translate, rotation, scale}``: scale, then rotate, then translate."""
    if not transform:
        return np.eye(3), np.zeros(3)
    scale = np.broadcast_to(np.asarray(transform.get("scale", 1.0), dtype=np.float64), (3,))
    rot = transform.get("rotation") or {}
    r = _rotation(rot.get("axis", (0.0, 1.0, 0.0)), rot.get("degrees", 0.0))
    return r @ np.diag(scale), np.asarray(transform.get("translate", (0.0, 0.0, 0.0)), dtype=np.float64)


def _rotation(axis, degrees):
    """Rotation by ``degrees`` about ``axis`` (Rodrigues' formula, as ``model.rotation_matrix``,
    which this module cannot import: the model imports it)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = math.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)
