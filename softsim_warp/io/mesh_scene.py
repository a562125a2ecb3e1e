"""Scene keys that name mesh files: ``[[mesh]]`` terrain and ``[[jelly]] mesh = ...``.

Run by :func:`softsim_warp.io.scene.validate` right after the schema. Paths are resolved against
the scene file's directory (a built-in scene's: the package's scenes folder) and every file is read
here (``core.mesh_assets.load_mesh``, cached), so a missing file, a file without a Mesh, a jelly mesh
with no clear inside and a mesh smaller than one lattice cell are one-line errors before anything is
built (an open or non-manifold jelly mesh with a clear inside is one warning line).

A mesh jelly's lattice is a box lattice with points missing: validation fills in the box, the
jelly's ``resolution`` (particles per axis) and ``size`` (edge lengths [m]): the asset's bounding
box, so every whole-scene check of a box jelly (precision, memory, terrain overlap) holds for it
too, counting the box's points as an upper bound; the box's size and memory are checked before it
is voxelised. The lattice is voxelised here too (once: the builder reuses it), so a ``total_mass``
is spread evenly over the jelly's particles (the corners of the cells the solid touches).
``_mesh_scale`` (the asset's scale) and ``_mesh_center`` (its bounding-box centre in its own frame
[m]) place the asset in the box.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np

from ..core.errors import warn
from ..core.mesh_assets import USD_SUFFIXES, load_mesh, load_mesh_samples, mesh_options, transform_matrix
from ..core.voxelize import NoInsideError, mesh_lattice
from .resources import MAX_LATTICE_POINTS, check_lattice_build

MESH_ONLY = ("mesh_prim", "spacing", "up_axis", "units")
"""``[[jelly]]`` keys that only a mesh jelly takes."""
DEFAULT_RESOLUTION = 12
"""Lattice cells along a mesh jelly's longest side when the scene gives neither ``resolution`` nor
``spacing``: fine enough for thin legs and ears to get cells of their own (tests/test_surface_contact.py's
critter), coarse enough to step fast; an asset dropped in as it comes needs no lattice settings."""
SANE_SIZE = (0.01, 50.0)
"""The longest side [m] of a jelly asset taken at its own size without a word; outside it a warning."""


def scene_base(source: str) -> Path:
    """The directory relative mesh paths start from: the scene file's, or the built-in scenes' folder."""
    p = Path(source)
    if p.is_file():
        return p.resolve().parent
    return Path(str(resources.files("softsim_warp.scenes")))  # as scene.builtin_dir


def _resolve(path: str, base: Path) -> str:
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else base / p)


def resolve_meshes(data: dict, ctx, base=None):
    """Resolve and read every mesh file the validated ``data`` names; fill in mesh jellies' boxes."""
    terrain = data.get("mesh", [])
    jellies = [(i, j) for i, j in enumerate(data.get("jelly", [])) if "mesh" in j or any(k in j for k in MESH_ONLY)]
    if not terrain and not jellies:
        return
    base = Path(base) if base is not None else scene_base(ctx.source)
    for i, t in enumerate(terrain):
        t["path"] = _resolve(t["path"], base)
        if t.get("animated"):  # its samples read (and cached) now: an asset without them is an error here
            # (load_mesh_samples refuses a file that is not USD before reading it, as it needs no reader)
            load_mesh_samples(t["path"], t.get("prim"), source=ctx.source, key=f"mesh.{i}.path", **mesh_options(t))
        else:
            load_mesh(t["path"], t.get("prim"), source=ctx.source, key=f"mesh.{i}.path", **mesh_options(t))
    for i, j in jellies:
        _mesh_jelly(i, j, ctx, base)


def scene_assets(data: dict) -> list[tuple[str, Path]]:
    """The mesh files a validated scene reads (its paths resolved), as ``(key, path)``:
    ``("mesh.0.path", ...)`` for terrain, ``("jelly.1.mesh", ...)`` for a mesh jelly, in the scene's
    order. A command declares these as inputs (``Outputs.add_input``), so that no output overwrites them.
    """
    return [
        (f"{kind}.{i}.{name}", Path(entry[name]))
        for kind, name in (("mesh", "path"), ("jelly", "mesh"))
        for i, entry in enumerate(data.get(kind, []))
        if entry.get(name)
    ]


def add_asset_inputs(outputs, *scenes) -> None:
    """Declare the mesh files of each scene (a validated ``Scene``, or its ``data``) as inputs of
    ``outputs`` (an ``io.outputs.Outputs``), each ``(key, path)`` once, so that no output of the
    command can be one of them. Call it before adding the outputs."""
    seen = set()
    for scene in scenes:
        for key, path in scene_assets(getattr(scene, "data", scene)):
            if (key, path) not in seen:
                seen.add((key, path))
                outputs.add_input(key, path)


def _mesh_jelly(i, j, ctx, base):
    key = f"jelly.{i}"
    if "mesh" not in j:
        name = next(k for k in MESH_ONLY if k in j)
        ctx.fail(f"{key}.{name}", "only a mesh jelly takes it; give mesh = \"file\" too", j[name])
    j["mesh"] = _resolve(j["mesh"], base)
    asset = load_mesh(j["mesh"], j.get("mesh_prim"), colliders=False, source=ctx.source, key=f"{key}.mesh",
                      **mesh_options(j))
    # An open or non-manifold mesh is a jelly wherever its winding number gives a clear inside
    # (core/voxelize.mesh_lattice refuses one that gives none): one warning line says what was found.
    boundary, non_manifold = asset.edge_uses
    flaws = ([f"open ({boundary} edges on one face only)"] if boundary else []) + (
        [f"non-manifold ({non_manifold} edges shared by more than two faces)"] if non_manifold else [])
    if "resolution" in j and "spacing" in j:
        ctx.fail(f"{key}.spacing", "give resolution or spacing for a mesh jelly, not both", j["spacing"])
    if "resolution" not in j and "spacing" not in j:
        j["resolution"] = [DEFAULT_RESOLUTION] * 3
    lo, hi = asset.points.min(axis=0), asset.points.max(axis=0)
    extent0 = hi - lo
    longest0 = float(extent0.max())
    if "size" not in j and not SANE_SIZE[0] <= longest0 <= SANE_SIZE[1]:
        # A millimetre CAD file read as metres, or a centimetre asset without metersPerUnit: it
        # would simulate, but not as the asset the user has in mind.
        warn(ctx.source, f"{key}.size", f"the mesh {Path(j['mesh']).name} is {longest0:.4g} m along its longest "
             f"side, outside {SANE_SIZE[0] * 100:g} cm to {SANE_SIZE[1]:g} m; give size (its longest side [m])"
             + (" or units" if "units" not in j and not j["mesh"].lower().endswith(USD_SUFFIXES) else ""))
    scale = 1.0
    if "size" in j:
        if len(set(j["size"])) != 1:
            ctx.fail(f"{key}.size", "a mesh jelly's size is one number: the length of its longest side [m]", j["size"])
        scale = j["size"][0] / longest0
    extent = extent0 * scale
    if "resolution" in j:
        if len(set(j["resolution"])) != 1:
            ctx.fail(f"{key}.resolution", "a mesh jelly's resolution is one number: cells along its longest side",
                     j["resolution"])
        h = float(extent.max()) / j["resolution"][0]
    else:
        h = j["spacing"]
    if extent.min() < h and boundary:
        ctx.fail(f"{key}.mesh", f"the mesh is {flaws[0]} and thinner than one lattice cell ({h:.4g} m): it encloses "
                 "no volume; close it, or use it as terrain ([[mesh]])", j["mesh"])
    if extent.min() < h:
        ctx.fail(f"{key}.{'spacing' if 'spacing' in j else 'resolution'}",
                 f"the mesh ({' x '.join(f'{e:.4g}' for e in extent)} m) is smaller than one lattice cell "
                 f"({h:.4g} m) along an axis; use a finer lattice", j.get("spacing", j.get("resolution")))
    # Points per axis: the lattice spans the bounding box exactly, in a whole number of cells of at
    # most h along each axis (a box mesh of k cells gives exactly k + 1 points, the extent's rounding
    # forgiven). The asset's extreme vertices then lie on the lattice's outer planes: an asset
    # resting upright on a floor has its lowest vertex on its lowest particles, with no gap below it.
    given = ["spacing", j["spacing"]] if "spacing" in j else ["resolution", j["resolution"][0]]
    cells = [max(int(math.ceil(e / h - 1e-6)), 1) for e in extent]
    shape = [c + 1 for c in cells]
    # The lattice's size is checked before it is voxelised (which allocates per point).
    points = math.prod(shape)
    if points > MAX_LATTICE_POINTS:
        ctx.fail(f"{key}.{given[0]}", f"the lattice would have {points:,} points, more than {MAX_LATTICE_POINTS:,} "
                 "(a kernel launch counts them in 32 bits); use a coarser lattice", given[1])
    check_lattice_build(shape, tuple(j.get("springs", {})), ctx.source, f"{key}.{given[0]}", given[1])
    j["resolution"] = shape
    j["size"] = [c * h if abs(e - c * h) <= 1e-6 * h else float(e) for c, e in zip(cells, extent)]
    j["_mesh_scale"] = scale
    j["_mesh_center"] = (0.5 * (lo + hi)).tolist()
    # For core/voxelize.py: an error found when the builder voxelises, and the cached read of the file.
    j["_source"], j["_mesh_key"] = ctx.source, f"{key}.mesh"
    # Voxelise now (core/voxelize.mesh_lattice, kept for the builder): the particle count gives a
    # total_mass its per-particle mass, and a mesh with no clear inside is an error here.
    try:
        mask = mesh_lattice(j)[1]
    except NoInsideError as e:
        ctx.fail(f"{key}.mesh", str(e), j["mesh"])
    if flaws:
        warn(ctx.source, f"{key}.mesh", f"the mesh is {' and '.join(flaws)}; its inside is taken from its "
                  "winding number", j["mesh"])
    if "total_mass" in j and "particle_mass" not in j:
        j["particle_mass"] = j.pop("total_mass") / int(mask.sum())


def terrain_asset(t: dict, i: int, source="<scene>"):
    """A validated ``[[mesh]]`` entry's mesh in world space (its transform applied)."""
    return load_mesh(t["path"], t.get("prim"), source=source, key=f"mesh.{i}.path", **mesh_options(t)).transformed(
        *transform_matrix(t.get("transform"))
    )


def mesh_signed_distance_entry(entry: dict, points: np.ndarray) -> np.ndarray:
    """``checks.TERRAIN_SDF`` entry for ``[[mesh]]``."""
    from ..core.mesh_terrain import mesh_signed_distance  # noqa: PLC0415

    return mesh_signed_distance(terrain_asset(entry, 0).outward(), points)
