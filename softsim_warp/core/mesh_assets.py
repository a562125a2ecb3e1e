"""Triangle meshes read from files: USD (usd-core) and OBJ/STL/PLY (trimesh, an optional extra).

A mesh is read once per file, prim, options and modification time (``load_mesh`` is cached), in
softsim's world: metres, y up. A USD file says its own units and axis (every xform above each Mesh,
the stage's authored ``metersPerUnit`` and ``upAxis`` applied; an unauthored metersPerUnit is
metres); an OBJ, STL or PLY file says neither, so the scene gives them (``up_axis``, ``units``;
default y up, metres). A z-up asset is turned by -90 degrees about x, (x, y, z) -> (x, z, -y), so
that its up becomes +y. Polygons are kept as they are for output (the asset's own topology, with
the primvars that stay valid when the surface deforms) and split into fan triangles for the
queries (``MeshAsset.triangles``). Errors are one-line :class:`~softsim_warp.core.errors.SceneError`
lines naming the scene file, the key and the value.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SceneError, warn
from .native_output import held_stderr
from .terrain import fan_triangles, signed_volume

USD_SUFFIXES = (".usd", ".usda", ".usdc")
TRIMESH_SUFFIXES = (".obj", ".stl", ".ply")
# Vertices closer than this fraction of a mesh's bounding-box diagonal are one vertex when edges are
# counted (MeshAsset.welded): far below any feature a lattice resolves, far above float64 rounding.
WELD_TOLERANCE = 1e-7

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "km": 1000.0, "in": 0.0254, "ft": 0.3048, "yd": 0.9144}
"""Names a scene's ``units`` key takes, in metres per unit (a number of metres per unit works too)."""
UP_AXES = ("Y", "Z")
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""(x, y, z) -> (x, z, -y): a rotation (no mirror), so faces keep their winding."""


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
    """``(name, type name, interpolation, values (NumPy), indices or None)`` of each primvar to carry
    over: those that stay valid when the surface deforms (``_kept_primvar``), UVs and display colours."""
    name: str = ""

    @functools.cached_property
    def triangles(self) -> np.ndarray:
        """Fan triangles of the faces, shape [T, 3], int64."""
        return fan_triangles(self.counts, self.indices)

    @functools.cached_property
    def edge_uses(self) -> tuple:
        """``(boundary edges, non-manifold edges)``: edges with one face, edges with more than two.

        Vertices closer than :data:`WELD_TOLERANCE` of the bounding-box diagonal count as one (a UV
        seam splits vertices, not the surface; a CAD export's shared corners may differ in the last bits).
        """
        t = self.welded[self.triangles]
        a, b = t.T.ravel(), t[:, [1, 2, 0]].T.ravel()
        # One int64 per edge, sorted: a run of equal keys is one edge (many times faster than unique rows).
        key = np.minimum(a, b) * (int(t.max(initial=0)) + 1) + np.maximum(a, b)
        key.sort()
        count = np.diff(np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1], [True]])))
        return int((count == 1).sum()), int((count > 2).sum())

    @functools.cached_property
    def welded(self) -> np.ndarray:
        """Each vertex's index among the vertices welded at :data:`WELD_TOLERANCE` of the mesh's size, shape [V].

        Positions are rounded to a grid of that step from the bounding box's low corner: two
        positions that differ by rounding error (1e-16 against a step of 1e-7 of the size) fall in
        one grid point unless they straddle a grid half-step, which rounding noise alone almost never does.
        """
        p = np.asarray(self.points, dtype=np.float64)
        if p.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        lo = p.min(axis=0)
        step = WELD_TOLERANCE * float(np.linalg.norm(p.max(axis=0) - lo))
        key = np.round((p - lo) / step) if step > 0 else p
        # Rows sorted, then numbered by group (as unique rows, without their slow structured sort).
        order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
        ordered = key[order]
        group = np.concatenate([[0], np.cumsum(np.any(ordered[1:] != ordered[:-1], axis=1))])
        weld = np.empty(p.shape[0], dtype=np.int64)
        weld[order] = group
        return weld

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
                    values = np.ascontiguousarray(np.asarray(values)[perm])
            primvars.append((name, type_name, interp, values, idx))
        return MeshAsset(self.points, self.counts, self.indices[perm], primvars, self.name)

    def outward(self, open_too=False) -> MeshAsset:
        """A closed mesh wound so that its faces point out of the volume they enclose.

        ``open_too``: an open mesh too (a jelly's mesh with holes), by its signed volume about its
        bounding box's centre (an open mesh's volume depends on the origin; about a point inside,
        the holes' missing cones are small). An open sheet used as terrain keeps its winding: its
        faces say which side collides.
        """
        if self.closed:
            return self.reversed() if self.volume() < 0 else self
        if open_too and self.triangles.shape[0]:
            p = self.points - 0.5 * (self.points.min(axis=0) + self.points.max(axis=0))
            if signed_volume(p, self.triangles) < 0:
                return self.reversed()
        return self


def _face_reversal(counts) -> np.ndarray:
    """The face-corner permutation that reverses every face's vertex order."""
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    ends = np.repeat(np.cumsum(counts) - 1, counts)
    corner = np.arange(int(counts.sum()))
    return starts + ends - corner


def load_mesh(path, prim=None, colliders=True, source="<scene>", key="mesh.path", up_axis=None, units=None) -> MeshAsset:
    """Read a mesh file, in metres, y up.

    Args:
        path: a ``.usd``/``.usda``/``.usdc`` file (usd-core) or ``.obj``/``.stl``/``.ply`` (trimesh).
        prim: in a USD file, a prim path: that Mesh, or every Mesh under that prim, merged into one
            (each with its own transform); default: every Mesh under the stage's default prim (the
            whole stage when it has none). With ``colliders=True`` (terrain) only those Meshes with
            UsdPhysics' CollisionAPI, when some have it.
        source, key: the scene file and key that named it, for error messages.
        up_axis, units: an OBJ/STL/PLY file's up axis ("Y" or "Z") and metres per unit (a number
            or a name in ``UNITS``); None: y up, metres. A USD file says its own.

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
    base = key.rsplit(".", 1)[0]
    if suffix in USD_SUFFIXES:
        for name, value in (("up_axis", up_axis), ("units", units)):
            if value is not None:
                raise SceneError(source, f"{base}.{name}", f"a USD file gives its own upAxis and metersPerUnit ({path}); "
                                 "the key is for OBJ, STL and PLY files (use size to rescale)", value)
    meters = meters_per_unit(units, source, f"{base}.units")
    axis = "Y" if up_axis is None else str(up_axis)
    if axis not in UP_AXES:
        raise SceneError(source, f"{base}.up_axis", f"must be one of {', '.join(UP_AXES)}", up_axis)
    return _load_cached(resolved, st.st_mtime_ns, st.st_size, prim, bool(colliders), source, key, axis, meters, given,
                        suffix)


def meters_per_unit(units, source="<scene>", key="units") -> float:
    """Metres per unit of a scene's ``units`` value: a name in ``UNITS`` or a finite number > 0 (None: 1)."""
    if units is None:
        return 1.0
    if isinstance(units, str):
        if units in UNITS:
            return UNITS[units]
    elif isinstance(units, (int, float)) and not isinstance(units, bool):
        try:
            if math.isfinite(units) and units > 0:
                return float(units)
        except OverflowError:  # an integer too large for a float
            pass
    raise SceneError(source, key, f"must be one of {', '.join(UNITS)} or a finite number of metres per unit > 0",
                     units)


def mesh_options(entry: dict) -> dict:
    """``up_axis`` and ``units`` of a validated ``[[jelly]]`` or ``[[mesh]]`` entry, as ``load_mesh`` takes them."""
    return {"up_axis": entry.get("up_axis"), "units": entry.get("units")}


def _to_y_up(points, meters, axis):
    """Positions in a file's units and up axis, in metres with y up."""
    points = points * meters if meters != 1.0 else points
    return points @ Z_UP_TO_Y_UP.T if axis == "Z" else points


@functools.lru_cache(maxsize=32)
def _load_cached(path, _mtime, _size, prim, colliders, source, key, axis, meters, given, suffix):
    """``path``: the file (symlinks resolved, the cache's key); ``given``: the name to open it by
    (its extension picks the format, for usd-core and trimesh alike); ``suffix``: that extension."""
    if suffix in USD_SUFFIXES:
        mesh = _load_usd(given, prim, colliders, source, key)
    else:
        if prim is not None:
            raise SceneError(source, key.rsplit(".", 1)[0] + (".prim" if key.endswith(".path") else ".mesh_prim"),
                             "only a USD file has prims", prim)
        mesh = _load_trimesh(given, source, key, suffix.lstrip("."))
        mesh = MeshAsset(_to_y_up(mesh.points, meters, axis), mesh.counts, mesh.indices, mesh.primvars, mesh.name)
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
    # trimesh logs (and sometimes prints tracebacks) about what it could not read beside the
    # geometry: a missing .mtl or texture, an unknown OBJ statement. softsim reads only positions,
    # faces and UVs, so those lines are noise in a successful run: its logger and warnings are
    # silenced around the load; a failure to read the mesh itself is still an error below.
    log = logging.getLogger("trimesh")
    level, propagate = log.level, log.propagate
    log.setLevel(logging.CRITICAL + 1)
    log.propagate = False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tm = trimesh.load(path, file_type=file_type, force="mesh", process=False)
            faces = np.asarray(getattr(tm, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
            points = np.asarray(getattr(tm, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
            uv = getattr(getattr(tm, "visual", None), "uv", None)
    except Exception as e:  # noqa: BLE001 - any parse failure is the file's fault
        raise SceneError(source, key, f"cannot read the mesh: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
                         path) from None
    finally:
        log.setLevel(level)
        log.propagate = propagate
    primvars = []
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
_USD_DIAGNOSTIC = re.compile(
    r"^(?:Warning|Error|Coding Error|Fatal Error|Status): (?:in \S+ at line \d+ of \S+ -- )?(.*)$")


def _load_usd(path, prim_path, colliders, source, key):
    """Read a USD asset; USD's own diagnostics (written by C++ straight to descriptor 2) become the
    project's lines: a sublayer that is missing or part of a cycle is an error (the asset is not
    what its author composed, and USD skips that sublayer silently but for its warning), any
    other diagnostic one ``warning:`` line on stderr."""
    from pxr import Tf  # noqa: PLC0415

    try:
        with held_stderr() as held:
            mesh = _read_usd(path, prim_path, colliders, source, key)
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
            # Once per process: the scene's checks and the model's build each read the asset.
            warn(source, key, f"USD: {note}", path)
            break
    return mesh


def load_mesh_samples(path, prim=None, colliders=True, source="<scene>", key="mesh.path", up_axis=None, units=None):
    """The time samples of an animated USD asset as :func:`load_mesh` reads it (the same Meshes, in
    metres, y up, in world space): ``(times [S] in s, points [S, V, 3])`` at every time code at which
    the Meshes' points or a transform above them has a sample, a time code being
    1 / timeCodesPerSecond seconds (time code 0 at t = 0). A :class:`SceneError` for a file that
    is not USD, has fewer than two samples, or whose point count changes between samples."""
    if not str(path).lower().endswith(USD_SUFFIXES):
        raise SceneError(source, key.rsplit(".", 1)[0] + ".animated",
                         "only a USD asset has time samples to follow; give a USD file or leave animated out", path)
    load_mesh(path, prim, colliders, source, key, up_axis, units)  # the asset's own errors first
    st = os.stat(path)
    return _samples_cached(str(path), st.st_mtime_ns, prim, bool(colliders), source, key)


@functools.lru_cache(maxsize=8)
def _samples_cached(path, _mtime, prim_path, colliders, source, key):
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    meters, axis, prims = _usd_meshes(stage, path, prim_path, colliders, source, key)
    codes = set()
    for prim in prims:
        codes.update(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        p = prim
        while p and not p.IsPseudoRoot():
            if p.IsA(UsdGeom.Xformable):
                codes.update(UsdGeom.Xformable(p).GetTimeSamples())
            p = p.GetParent()
    codes = sorted(codes)
    if len(codes) < 2:
        raise SceneError(source, key.rsplit(".", 1)[0] + ".animated", "the asset's Meshes have fewer than two time "
                         "samples of their points or transforms: nothing to follow", len(codes))
    frames = []
    for code in codes:
        cache = UsdGeom.XformCache(Usd.TimeCode(code))
        pts = []
        for prim in prims:
            x = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(Usd.TimeCode(code)) or [], dtype=np.float64)
            m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)
            pts.append(_to_y_up(x.reshape(-1, 3) @ m[:3, :3] + m[3, :3], meters, axis))
        frame = np.concatenate(pts)
        if frames and frame.shape != frames[0].shape:
            raise SceneError(source, key, f"the animated Meshes' point count changes at time code {code:g} "
                             f"({frames[0].shape[0]} then {frame.shape[0]}); only the positions may change", path)
        if not np.isfinite(frame).all():
            raise SceneError(source, key, f"the mesh has non-finite vertex positions at time code {code:g}", path)
        frames.append(frame)
    return np.asarray(codes, dtype=np.float64) / float(stage.GetTimeCodesPerSecond()), np.stack(frames)


def _usd_meshes(stage, path, prim_path, colliders, source, key):
    """``(metres per unit, up axis, the Mesh prims to read)`` of an open USD stage (see :func:`load_mesh`)."""
    from pxr import Sdf, Usd, UsdGeom, UsdPhysics  # noqa: PLC0415

    if stage is None:
        raise SceneError(source, key, f"cannot be opened as USD; give {USD_EXPECTED}", path)
    # An authored metersPerUnit converts to metres; without one the file is taken to be in metres,
    # softsim's unit (not USD's fallback of centimetres: most hand-made and script-made files mean metres).
    meters = 1.0
    if UsdGeom.StageHasAuthoredMetersPerUnit(stage):
        meters = stage.GetMetadata(UsdGeom.Tokens.metersPerUnit)
        if not isinstance(meters, (int, float)) or not math.isfinite(meters) or meters <= 0:
            raise SceneError(source, key, f"{path}: metersPerUnit must be a finite number of metres per unit > 0",
                             meters)
    axis = str(UsdGeom.GetStageUpAxis(stage))
    prim_key = key.rsplit(".", 1)[0] + (".prim" if key.endswith(".path") else ".mesh_prim")
    if prim_path is not None:
        if not Sdf.Path.IsValidPathString(prim_path) or not Sdf.Path(prim_path).IsAbsolutePath():
            raise SceneError(source, prim_key, "is not an absolute prim path", prim_path)
        root = stage.GetPrimAtPath(prim_path)
        meshes = _meshes_under(root, Usd, UsdGeom) if root else []
        if not meshes:
            found = _meshes_under(stage.GetPseudoRoot(), Usd, UsdGeom)[:5]
            raise SceneError(source, prim_key, f"no Mesh prim there or under it in {path}; Meshes: "
                             f"{', '.join(str(p.GetPath()) for p in found) or 'none'}", prim_path)
    else:
        root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
        meshes = _meshes_under(root, Usd, UsdGeom)
        if not meshes:
            found = _meshes_under(stage.GetPseudoRoot(), Usd, UsdGeom)[:5]
            where = "the file has no Mesh prim" if not found else (
                f"no Mesh prim under the default prim {root.GetPath()}; name one with the prim key; Meshes: "
                + ", ".join(str(p.GetPath()) for p in found))
            raise SceneError(source, key, where, path)
    with_api = [p for p in meshes if p.HasAPI(UsdPhysics.CollisionAPI)] if colliders else []
    return meters, axis, with_api or meshes


def _read_usd(path, prim_path, colliders, source, key):
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    meters, axis, prims = _usd_meshes(stage, path, prim_path, colliders, source, key)
    # An animated Mesh (a cache with time samples and no default) is read at its first sample.
    time = Usd.TimeCode.EarliestTime()
    cache = UsdGeom.XformCache(time)
    parts = []
    for prim in prims:
        mesh = UsdGeom.Mesh(prim)
        pts = np.asarray(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
        if counts.sum() != indices.size or (indices.size and (indices.min() < 0 or indices.max() >= len(pts))):
            raise SceneError(source, key, f"the Mesh {prim.GetPath()} has inconsistent face counts and indices", path)
        if (counts < 3).any():
            raise SceneError(source, key, f"the Mesh {prim.GetPath()} has faces of fewer than 3 vertices", path)
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row vectors: x' = x M
        pts = _to_y_up(pts @ m[:3, :3] + m[3, :3], meters, axis)
        # Faces wind right-handed in what we return: a left-handed mesh, or a mirroring xform, is reversed.
        flips = (mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded) != (np.linalg.det(m[:3, :3]) < 0)
        primvars = [pv for pv in (_kept_primvar(pv, counts, indices, len(pts), time)
                                  for pv in UsdGeom.PrimvarsAPI(prim).GetPrimvarsWithValues()) if pv is not None]
        part = MeshAsset(pts, counts, indices, primvars, prim.GetName())
        parts.append(part.reversed() if flips else part)
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [p.points.shape[0] for p in parts[:-1]])
    return MeshAsset(
        np.concatenate([p.points for p in parts]),
        np.concatenate([p.counts for p in parts]),
        np.concatenate([p.indices + o for p, o in zip(parts, offsets)]),
        _merged_primvars(parts),
        "+".join(p.name for p in parts),
    )


def _meshes_under(root, Usd, UsdGeom) -> list:
    """The Mesh prims at or under ``root`` that are drawn: instance proxies included, guides and
    invisible Meshes left out."""
    out = []
    for p in Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if p.IsA(UsdGeom.Mesh):
            img = UsdGeom.Imageable(p)
            if img.ComputeVisibility() != UsdGeom.Tokens.invisible and img.ComputePurpose() != UsdGeom.Tokens.guide:
                out.append(p)
    return out


# Primvars that describe the undeformed geometry go stale as soon as the surface moves: normals
# and tangent frames (the Surface's normals are recomputed every frame), positions and vectors of
# any name (rest positions, velocities), matrices, and skinning data (skel:*) whose binding the
# output does not have. Kept: UVs, colours, opacities and other plain numbers, attached to faces,
# corners or vertices, which a deformation carries along unchanged.
_STALE_ROLES = {"Normal", "Point", "Vector", "Frame", "Transform"}
_STALE_SCALARS = ("matrix", "quat", "frame", "point", "normal", "vector")
_STALE_NAMES = re.compile(r"^(skel:|normals$|.*tangent|.*binormal)", re.IGNORECASE)
_ORDER = {"constant": 0, "uniform": 1, "vertex": 2, "varying": 2, "faceVarying": 3}


def _kept_primvar(pv, counts, indices, n_points, time):
    """``(name, type name, interpolation, values (NumPy), indices or None)`` of a primvar that stays
    valid under deformation and fits the mesh's topology; None for any other (left out)."""
    name = str(pv.GetPrimvarName())
    type_name = pv.GetTypeName()
    interp = str(pv.GetInterpolation())
    if (_STALE_NAMES.match(name) or type_name.role in _STALE_ROLES or not type_name.isArray
            or str(type_name.scalarType).startswith(_STALE_SCALARS) or pv.GetElementSize() != 1
            or interp not in _ORDER):
        return None
    values = np.asarray(pv.GetAttr().Get(time))
    if values.dtype.kind not in "fiub" or values.ndim == 0:  # strings, tokens, assets: not carried
        return None
    want = {"constant": 1, "uniform": len(counts), "vertex": n_points, "varying": n_points,
            "faceVarying": len(indices)}[interp]
    idx = np.asarray(pv.GetIndices(time), dtype=np.int64) if pv.IsIndexed() else None
    used = len(idx) if idx is not None else len(values)
    if used != want or (idx is not None and idx.size and (idx.min() < 0 or idx.max() >= len(values))):
        return None  # a primvar that does not fit the mesh would make the output invalid
    if interp == "varying":  # the same count as vertex for a mesh without subdivision
        interp = "vertex"
    return (name, str(type_name), interp, values, None if idx is None else idx.astype(np.int32))


def _expanded(values, idx, interp, target, part):
    """A primvar of the Mesh ``part``, one value per element of ``target`` interpolation (no indices)."""
    v = values if idx is None else values[idx]
    if interp == target:
        return v
    if interp == "constant":
        n = {"uniform": len(part.counts), "vertex": part.points.shape[0], "faceVarying": len(part.indices)}[target]
        return np.repeat(v[:1], n, axis=0)
    if interp == "uniform":  # to faceVarying: each face's value on each of its corners
        return np.repeat(v, part.counts, axis=0)
    return v[part.indices]  # vertex to faceVarying


def _merged_primvars(parts) -> list:
    """The primvars of several Meshes merged into one: those every part has, with one type; each at
    the finest interpolation among the parts' (a constant that differs between parts becomes
    uniform; uniform beside vertex becomes faceVarying)."""
    out = []
    names = [{pv[0]: pv for pv in p.primvars} for p in parts]
    for name, type_name, *_ in parts[0].primvars:
        got = [n.get(name) for n in names]
        if any(g is None or g[1] != type_name for g in got):
            continue
        interps = {g[2] for g in got}
        if interps == {"constant"}:
            firsts = [(g[3] if g[4] is None else g[3][g[4]])[:1] for g in got]
            if all(np.array_equal(f, firsts[0]) for f in firsts):
                out.append(got[0])
                continue
            target = "uniform"
        else:
            target = max(interps, key=_ORDER.get)
            if {"uniform", "vertex"} <= interps:
                target = "faceVarying"
        merged = np.concatenate([_expanded(g[3], g[4], g[2], target, p) for p, g in zip(parts, got)])
        out.append((name, type_name, target, merged, None))
    return out


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
