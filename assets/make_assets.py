"""Make softsim's demo assets: every mesh is computed here, nothing is downloaded.

    python assets/make_assets.py            # writes scenes/assets/*.usda (the built-in scenes use them)
    python assets/make_assets.py --out DIR

* ``blob.usda``: a character, a rounded body with two ears and a snout (a star-shaped surface
  r(direction) around its centre: closed, manifold, wound outward), face-varying UVs (longitude,
  latitude) with a seam;
* ``torus.usda`` and ``pebble.usda`` (a superellipsoid): more closed shapes with UVs, for piles;
* ``stairs.usda``: a closed staircase solid (the step profile extruded), UsdPhysics CollisionAPI;
* ``bumpy_floor.usda``: an open height-field sheet facing up (y = sum of smooth bumps), vertex
  normals and UVs, CollisionAPI;
* ``critter.usda``: a creature with thin legs and ears (about one lattice cell thick at 12 cells
  along it), its parts closed surfaces that overlap;
* ``plate.usda``: a thin closed box (1 x 1 m, 2 cm thick, facing x), a plate to throw jellies at;
* ``blob_open.usda``: the blob with its base cut off (an open mesh, as scans often are);
* ``bracket.stl``: an L-shaped CAD bracket in ASCII STL whose shared corners differ by 1e-16 where
  they should be 0 (a closed solid once welded with a tolerance).

Meshes are in metres (metersPerUnit = 1, up axis y), right-handed, every face wound outward
(blob_open has a hole; the rest are closed).

``--real DIR`` writes assets as other tools make them, for the tests (tests/test_real_assets.py),
not shipped:

* ``zup_cm.usda``: a tall pebble (0.24 x 0.6 x 0.2 m) written as a CAD or DCC tool does: up axis
  z, metersPerUnit 0.01 (the points in centimetres);
* ``pawn.usda``: a chess pawn of two Meshes (a base and a head), each under its own xform;
* ``bracket_mm.stl``: a binary STL of a 120 x 60 x 40 mm block, in millimetres, z up;
* ``skinned.usda``: a Mesh bound to a Skeleton (SkelBindingAPI, skel:joints, jointIndices and
  jointWeights primvars), with static normals and tangents as primvars beside its UVs;
* ``latin1.obj``: an OBJ with a Latin-1 comment, a material library that is not there and UVs;
* ``lost_texture.ply``: a PLY whose header names a texture image that is not there, with UVs.

``write_animated_plate(path)`` writes ``animated_plate.usda``, terrain for the tests of animated
meshes (tests/test_moving_meshes.py): a sheet whose points tilt (time-sampled) under a translating
Xform (time-sampled), in centimetres at 24 time codes a second.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdPhysics, Vt

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE.parent / "scenes" / "assets"


def lat_long(radius_fn, rings=48, segments=64):
    """A closed star-shaped surface x = r(d) d over unit directions d (poles at -y and +y).

    Returns ``(points, counts, indices, uv)``: triangles at the poles, quads elsewhere, wound
    outward; ``uv`` is face-varying (one (u, v) per face corner), u the longitude in [0, 1] (the
    seam's last column carries u = 1), v the latitude from the bottom pole.
    """
    theta = np.linspace(0.0, math.pi, rings + 1)[1:-1]  # polar angle from the bottom pole
    phi = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack([st * np.cos(phi), -ct * np.ones_like(phi), st * np.sin(phi)], axis=-1).reshape(-1, 3)
    dirs = np.concatenate([[[0.0, -1.0, 0.0]], d, [[0.0, 1.0, 0.0]]])
    points = dirs * radius_fn(dirs)[:, None]
    top = len(points) - 1

    def ring(k, j):
        return 1 + k * segments + (j % segments)

    counts, indices, uv = [], [], []

    def uv_of(k, j):  # k: ring (-1 bottom pole, rings - 1 top pole), j: column (may be == segments)
        return (j / segments, (k + 1) / rings)

    # Increasing azimuth turns from x towards z, counter-clockwise seen from below (-y):
    # (pole, j, j + 1) faces -y, out of the bottom; the top pole's fan is reversed.
    for j in range(segments):
        counts.append(3)
        indices += [0, ring(0, j), ring(0, j + 1)]
        uv += [((j + 0.5) / segments, 0.0), uv_of(0, j), uv_of(0, j + 1)]
    for k in range(rings - 2):
        for j in range(segments):
            counts.append(4)
            indices += [ring(k, j), ring(k + 1, j), ring(k + 1, j + 1), ring(k, j + 1)]
            uv += [uv_of(k, j), uv_of(k + 1, j), uv_of(k + 1, j + 1), uv_of(k, j + 1)]
    for j in range(segments):
        counts.append(3)
        indices += [top, ring(rings - 2, j + 1), ring(rings - 2, j)]
        uv += [((j + 0.5) / segments, 1.0), uv_of(rings - 2, j + 1), uv_of(rings - 2, j)]
    return points, np.array(counts), np.array(indices), np.array(uv, dtype=np.float32)


def _bump(dirs, toward, height, width):
    t = np.asarray(toward, dtype=np.float64)
    t = t / np.linalg.norm(t)
    return height * np.exp(-np.sum((dirs - t) ** 2, axis=1) / width**2)


def blob_radius(dirs):
    """A squat rounded body (0.5 m across) with two ears up and apart and a small snout (+x)."""
    r = 0.25 * (1.0 + 0.08 * dirs[:, 1])  # a little wider at the top than the bottom
    r = r + _bump(dirs, (0.0, 1.0, 0.55), 0.13, 0.22) + _bump(dirs, (0.0, 1.0, -0.55), 0.13, 0.22)
    return r + _bump(dirs, (1.0, 0.1, 0.0), 0.05, 0.3)


def ellipsoid_radius(a):
    """r(d) of the ellipsoid of semi-axes ``a`` (x, y, z) around its centre."""
    a = np.asarray(a, dtype=np.float64)
    return lambda dirs: 1.0 / np.sqrt(np.sum((dirs / a) ** 2, axis=1))


def critter():
    """A four-legged creature 0.6 m long with thin legs (0.04 m across, pointed feet) and thin ears
    (0.03 m across): an ellipsoid body, a round head, legs, ears and a tail, each a closed surface,
    overlapping where they join (as modelled parts often are: the winding number counts their
    overlap as inside). At 12 cells along its length a leg is about one cell thick.

    Returns ``(points, counts, indices)``, wound outward, feet at y = 0.
    """
    parts = [  # (centre, semi-axes): body, head, four legs, two ears, a tail
        ((0.0, 0.32, 0.0), (0.22, 0.11, 0.11)),
        ((0.25, 0.42, 0.0), (0.085, 0.08, 0.08)),
        *[((x, 0.17, z), (0.02, 0.17, 0.02)) for x in (-0.14, 0.14) for z in (-0.065, 0.065)],
        *[((0.26, 0.55, z), (0.015, 0.09, 0.03)) for z in (-0.045, 0.045)],
        ((-0.26, 0.38, 0.0), (0.08, 0.015, 0.015)),
    ]
    points, counts, indices = [], [], []
    for centre, semi in parts:
        pts, c, idx, _ = lat_long(ellipsoid_radius(semi), rings=24, segments=24)
        indices.append(np.asarray(idx) + sum(len(p) for p in points))
        points.append(pts + np.asarray(centre))
        counts.append(c)
    return np.concatenate(points), np.concatenate(counts), np.concatenate(indices)


def cut_base(points, counts, indices, height):
    """The mesh without the faces whose every vertex lies below ``height`` (y): an open base, as a
    scanned animal's often is (the vertices no face uses are dropped)."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    keep = [bool((points[indices[s : s + c], 1] >= height).any()) for s, c in zip(starts, counts)]
    indices = np.asarray(indices)[np.repeat(keep, counts)]
    used, indices = np.unique(indices, return_inverse=True)
    return points[used], np.asarray(counts)[keep], indices.ravel()


def bracket_triangles():
    """An L-shaped CAD bracket (0.3 x 0.2 x 0.1 m, its flange 0.04 m thick) as triangles ``(T, 3, 3)``,
    wound outward: the L profile extruded along z."""
    prof = [(0.0, 0.0), (0.3, 0.0), (0.3, 0.04), (0.04, 0.04), (0.04, 0.2), (0.0, 0.2)]  # counter-clockwise
    z0, z1 = 0.0, 0.1
    tris = []
    # Caps: the profile's fan from (0, 0) (it is star-shaped about that corner), front (z1) and back (z0).
    for k in range(1, len(prof) - 1):
        a, b, c = prof[0], prof[k], prof[k + 1]
        tris.append([(*a, z1), (*b, z1), (*c, z1)])
        tris.append([(*a, z0), (*c, z0), (*b, z0)])
    for k in range(len(prof)):
        a, b = prof[k], prof[(k + 1) % len(prof)]
        tris.append([(*a, z0), (*b, z0), (*b, z1)])
        tris.append([(*a, z0), (*b, z1), (*a, z1)])
    return np.array(tris, dtype=np.float64)


def write_stl(path, triangles, jitter=0.0, seed=0):
    """An ASCII STL (each triangle its own three corners, as STL stores them). ``jitter``: every
    corner coordinate that is 0 is written as a random multiple of it instead (a CAD exporter's
    rounding: shared corners that differ in the last bits, 0.0 against -2.7e-16)."""
    rng = np.random.default_rng(seed)
    t = np.array(triangles, dtype=np.float64)
    zero = t == 0.0
    t[zero] = jitter * rng.uniform(-3.0, 3.0, size=int(zero.sum()))
    lines = ["solid bracket"]
    for tri in t:
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        n = n / np.linalg.norm(n)
        lines += [f"  facet normal {n[0]:.9g} {n[1]:.9g} {n[2]:.9g}", "    outer loop"]
        lines += [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in tri.tolist()]
        lines += ["    endloop", "  endfacet"]
    lines.append("endsolid bracket")
    Path(path).write_text("\n".join(lines) + "\n")


def torus(R=0.2, r=0.09, nu=64, nv=24):
    """A ring torus about the y axis, quads wound outward, face-varying UVs."""
    u = np.linspace(0, 2 * math.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * math.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    pts = np.stack([(R + r * np.cos(V)) * np.cos(U), r * np.sin(V), (R + r * np.cos(V)) * np.sin(U)], -1).reshape(-1, 3)
    idx, uv = [], []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            idx += [a, d, c, b]
            uv += [(i / nu, j / nv), (i / nu, (j + 1) / nv), ((i + 1) / nu, (j + 1) / nv), ((i + 1) / nu, j / nv)]
    return pts, np.full(nu * nv, 4), np.array(idx), np.array(uv, dtype=np.float32)


def pebble_radius(dirs, a=(0.22, 0.12, 0.16), p=3.0):
    """A superellipsoid |x/a|^p + |y/b|^p + |z/c|^p = 1 along each direction: a rounded pebble."""
    s = np.sum(np.abs(dirs / np.asarray(a)) ** p, axis=1)
    return s ** (-1.0 / p)


def plate(width=1.0, height=1.0, thickness=0.02):
    """A thin box centred on the origin, ``thickness`` along x: six quads wound outward."""
    hx, hy, hz = 0.5 * thickness, 0.5 * height, 0.5 * width
    pts = np.array([[x, y, z] for x in (-hx, hx) for y in (-hy, hy) for z in (-hz, hz)], dtype=np.float64)
    # Corner c has bits (x, y, z) = (c >> 2, c >> 1, c) & 1; each face counter-clockwise from outside.
    idx = [0, 1, 3, 2, 4, 6, 7, 5, 0, 4, 5, 1, 2, 3, 7, 6, 0, 2, 6, 4, 1, 5, 7, 3]
    return pts, np.full(6, 4), np.array(idx)


def stairs(steps=5, run=0.35, rise=0.15, width=1.2):
    """A staircase solid descending towards +x: step i spans x in [i run, (i + 1) run] with its
    tread at y = (steps - i) rise; closed (the step profile extruded along z), wound outward."""
    xs = [i * run for i in range(steps + 1)]
    hs = [(steps - i) * rise for i in range(steps)]
    # The profile in (x, y), counter-clockwise: along the floor, then up the back and down the steps.
    prof = [(x, 0.0) for x in xs]
    for i in reversed(range(steps)):
        prof += [(xs[i + 1], hs[i]), (xs[i], hs[i])]
    # (x_{i+1}, h_{i+1}) -> (x_{i+1}, h_i) is the riser between two treads.
    n = len(prof)
    z0, z1 = -0.5 * width, 0.5 * width
    pts = [(x, y, z1) for x, y in prof] + [(x, y, z0) for x, y in prof]
    counts, idx = [], []
    for k in range(n):  # the extruded outline: floor, back, treads and risers
        a, b = k, (k + 1) % n
        counts.append(4)
        idx += [a, a + n, b + n, b]
    # The two sides, one convex polygon per step column (with the lower riser's top corner on its
    # right edge, so the sides share every edge with the outline), starting at the column's left
    # floor corner so that a fan from its first vertex has no sliver.
    for i in range(steps):
        col = [(xs[i], 0.0), (xs[i + 1], 0.0)]
        if i + 1 < steps:
            col.append((xs[i + 1], hs[i + 1]))
        col += [(xs[i + 1], hs[i]), (xs[i], hs[i])]
        front = [_side_vertex(pts, p, z1) for p in col]  # counter-clockwise about +z: faces +z
        back = [_side_vertex(pts, p, z0) for p in col]
        counts += [len(col), len(col)]
        idx += front + back[::-1]
    return np.array(pts, dtype=np.float64), np.array(counts), np.array(idx)


def _side_vertex(pts, p, z):
    """The index of vertex (p, z), added if it is new (a floor corner under a riser)."""
    for i, q in enumerate(pts):
        if abs(q[0] - p[0]) < 1e-12 and abs(q[1] - p[1]) < 1e-12 and q[2] == z:
            return i
    pts.append((p[0], p[1], z))
    return len(pts) - 1


def bumpy_floor(size=4.0, n=48, height=0.06):
    """An open height field y(x, z) over a square of edge ``size``, facing up, with vertex normals."""
    g = np.linspace(-0.5 * size, 0.5 * size, n + 1)
    X, Z = np.meshgrid(g, g, indexing="ij")
    k = 2.0 * math.pi / 1.3
    Y = height * (np.sin(k * X) * np.cos(k * Z) + 0.5 * np.cos(0.7 * k * (X + Z)))
    pts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    # Analytic normals of y = f(x, z): (-f_x, 1, -f_z) normalised.
    fx = height * (k * np.cos(k * X) * np.cos(k * Z) - 0.35 * k * np.sin(0.7 * k * (X + Z)))
    fz = height * (-k * np.sin(k * X) * np.sin(k * Z) - 0.35 * k * np.sin(0.7 * k * (X + Z)))
    nrm = np.stack([-fx, np.ones_like(fx), -fz], -1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    idx = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            idx += [a, d, c, b]  # x towards z is clockwise seen from above: (a, d, c, b) faces +y
    uv = np.stack([(X + 0.5 * size) / size, (Z + 0.5 * size) / size], -1).reshape(-1, 2).astype(np.float32)
    return pts, np.full(n * n, 4), np.array(idx), nrm, uv


def write_mesh(path, name, points, counts, indices, uv=None, uv_interp="faceVarying", normals=None, collision=False,
               color=(0.8, 0.8, 0.8)):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Asset")
    stage.SetDefaultPrim(root.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, f"/Asset/{name}")
    pts = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
    mesh.CreatePointsAttr(pts)
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(pts))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    if normals is None:
        normals = _vertex_normals(points, counts, indices)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex if len(normals) == len(points) else UsdGeom.Tokens.faceVarying)
    mesh.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([tuple(color)]))
    if uv is not None:
        pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, uv_interp)
        values, inverse = np.unique(np.asarray(uv, dtype=np.float32), axis=0, return_inverse=True)
        pv.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(values)))  # indexed: each (u, v) once
        pv.SetIndices(Vt.IntArray.FromNumpy(inverse.ravel().astype(np.int32)))
    if collision:
        UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
    stage.GetRootLayer().Save()


def _fan(counts, indices):
    counts = np.asarray(counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return np.array([[indices[s], indices[s + k], indices[s + k + 1]] for s, c in zip(starts, counts) for k in range(1, c - 1)])


def _vertex_normals(points, counts, indices):
    p = np.asarray(points, dtype=np.float64)
    t = _fan(counts, indices)
    a = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, t[:, k], a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _flat_normals(points, counts, indices):
    """Face-varying normals: each corner carries its face's normal (sharp edges: stairs)."""
    p = np.asarray(points, dtype=np.float64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = []
    for s, c in zip(starts, counts):
        f = p[indices[s : s + c]]
        area = sum(np.cross(f[k] - f[0], f[k + 1] - f[0]) for k in range(1, c - 1))
        out += [area / np.linalg.norm(area)] * c
    return np.array(out)


def signed_volume(points, counts, indices):
    p = np.asarray(points, dtype=np.float64)
    t = _fan(counts, indices)
    return float(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])).sum() / 6.0)


# -- assets as other tools write them (``--real``): for the tests, not shipped ------------------

Z_UP_FROM_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""(x, y, z) -> (x, -z, y): a y-up shape written into a z-up file (its up, +y, becomes +z)."""


def tall_pebble_radius(dirs):
    return pebble_radius(dirs, a=(0.12, 0.3, 0.1))


def write_zup_cm(path):
    """A tall pebble (0.24 x 0.6 x 0.2 m, y up in softsim's frame) in a z-up centimetre stage."""
    pts, counts, idx, uv = lat_long(tall_pebble_radius, rings=24, segments=32)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdGeom.Xform.Define(stage, "/Pebble")
    stage.SetDefaultPrim(root.GetPrim())
    _define_mesh(stage, "/Pebble/Geom", 100.0 * pts @ Z_UP_FROM_Y_UP.T, counts, idx, uv=uv, color=(0.5, 0.8, 0.4))
    stage.GetRootLayer().Save()


PAWN_BASE = {"translate": (0.0, 0.1, 0.0), "scale": (1.0, 0.5, 1.0)}
PAWN_HEAD = {"translate": (0.0, 0.28, 0.0), "scale": (0.45, 0.45, 0.45)}


def write_pawn(path):
    """Two closed Meshes under one default prim, each with its own transform: a squashed sphere
    (the base) and a smaller sphere (the head) that sinks into it; each its own colour."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Pawn")
    stage.SetDefaultPrim(root.GetPrim())
    sphere = lat_long(lambda d: np.full(len(d), 0.2), rings=16, segments=24)
    for name, xf, rings, color in (("Base", PAWN_BASE, 16, (0.9, 0.9, 0.85)), ("Head", PAWN_HEAD, 12, (0.8, 0.2, 0.2))):
        pts, counts, idx, uv = sphere if rings == 16 else lat_long(lambda d: np.full(len(d), 0.2), rings, 18)
        x = UsdGeom.Xform.Define(stage, f"/Pawn/{name}")
        x.AddTranslateOp().Set(xf["translate"])
        x.AddScaleOp().Set(xf["scale"])
        _define_mesh(stage, f"/Pawn/{name}/Geom", pts, counts, idx, uv=uv, color=color)
    stage.GetRootLayer().Save()


BRACKET_MM = (120.0, 60.0, 40.0)


def write_stl_mm(path, size=BRACKET_MM):
    """A binary STL of a block ``size`` [mm] (x, y, z), z up, resting on z = 0: a triangle soup, as
    CAD tools write it (each triangle its own three corners)."""
    x, y, z = size
    c = np.array([[i * x, j * y, k * z] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    c[:, :2] -= 0.5 * np.array([x, y])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]  # outward
    tris = np.array([[q[0], q[k], q[k + 1]] for q in quads for k in (1, 2)])
    v = c[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rec = np.zeros(len(tris), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"], rec["v"] = n, v
    with open(path, "wb") as f:
        f.write(b"softsim test block, millimetres, z up".ljust(80, b" "))
        f.write(np.uint32(len(tris)).tobytes())
        f.write(rec.tobytes())


def write_skinned(path):
    """A character Mesh as a rigging tool exports it: bound to a one-joint Skeleton under a
    SkelRoot (SkelBindingAPI, skel:skeleton, jointIndices and jointWeights primvars), with static
    normals and tangents as primvars beside its UVs."""
    from pxr import Gf, UsdSkel  # noqa: PLC0415

    pts, counts, idx, uv = lat_long(blob_radius, rings=16, segments=24)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdSkel.Root.Define(stage, "/Character")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
    skel.CreateJointsAttr(["root"])
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    mesh = _define_mesh(stage, "/Character/Body", pts, counts, idx, uv=uv, color=(0.95, 0.55, 0.2), normals=False)
    api = UsdGeom.PrimvarsAPI(mesh)
    nrm = _vertex_normals(pts, counts, idx)
    api.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(nrm, dtype=np.float32)))
    tangent = np.cross([0.0, 1.0, 0.0], nrm)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    api.CreatePrimvar("tangents", Sdf.ValueTypeNames.Float3Array, UsdGeom.Tokens.vertex).Set(
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(tangent, dtype=np.float32)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set(Vt.IntArray([0] * len(pts)))
    binding.CreateJointWeightsPrimvar(False, 1).Set(Vt.FloatArray([1.0] * len(pts)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    stage.GetRootLayer().Save()


def write_latin1_obj(path):
    """An OBJ as an older tool writes it: a Latin-1 comment (not UTF-8), a material library that
    is not there, UVs; a closed box of 0.3 x 0.2 x 0.25 m wound outward."""
    size = np.array([0.3, 0.2, 0.25])
    c = (np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64) - 0.5) * size
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    lines = ["# Modèle exporté par l'outil de Günther (Latin-1)", "mtllib matériaux_absents.mtl", "o Boîte"]
    lines += [f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for p in c]
    lines += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "usemtl Peau"]
    lines += ["f " + " ".join(f"{v + 1}/{k + 1}" for k, v in enumerate(q)) for q in quads]
    Path(path).write_bytes(("\n".join(lines) + "\n").encode("latin-1"))


def write_lost_texture_ply(path):
    """An ASCII PLY of a tetrahedron (wound outward) with per-corner UVs, its header naming a
    texture image that is not there (trimesh logs a traceback about it)."""
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.2]])
    faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    uv = [[0, 0], [0, 1], [1, 0]]
    lines = ["ply", "format ascii 1.0", "comment TextureFile missing_texture.png", "element vertex 4",
             "property float x", "property float y", "property float z", "element face 4",
             "property list uchar int vertex_indices", "property list uchar float texcoord", "end_header"]
    lines += [" ".join(f"{c:g}" for c in p) for p in pts]
    lines += ["3 " + " ".join(map(str, f)) + " 6 " + " ".join(f"{c:g}" for u in uv for c in u) for f in faces]
    Path(path).write_text("\n".join(lines) + "\n")


def _define_mesh(stage, prim_path, points, counts, indices, uv=None, color=(0.8, 0.8, 0.8), normals=True):
    """A Mesh prim with (vertex) normals, face-varying UVs and a displayColor."""
    mesh = UsdGeom.Mesh.Define(stage, prim_path)
    pts = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
    mesh.CreatePointsAttr(pts)
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(pts))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    if normals:
        nrm = _vertex_normals(points, counts, indices)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(nrm, dtype=np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateDisplayColorPrimvar().Set(Vt.Vec3fArray([tuple(color)]))
    if uv is not None:
        pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        pv.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(uv, dtype=np.float32)))
    return mesh


# The animated plate: a 2 m square sheet (4 x 4 vertices, facing up) in centimetres, its points
# tilting about z (time-sampled every half second) under an Xform translated along x at 0.2 m/s
# (sampled every second), 24 time codes a second.
PLATE_CODES_PER_SECOND = 24.0
PLATE_POINT_CODES = (0.0, 12.0, 24.0, 36.0, 48.0)
PLATE_XFORM_CODES = (0.0, 24.0, 48.0)
PLATE_TILT = (0.0, 0.1, -0.05, 0.15, 0.0)  # slope dy/dx of the sheet at each point sample [1]
PLATE_SPEED = 0.2  # [m/s] along x


def animated_plate_points(code_index):
    """The plate's vertices [cm] in its Mesh's frame at ``PLATE_POINT_CODES[code_index]``."""
    g = np.linspace(-100.0, 100.0, 4)
    x, z = np.meshgrid(g, g, indexing="ij")
    x, z = x.ravel(), z.ravel()
    return np.stack([x, PLATE_TILT[code_index] * x, z], axis=1)


def animated_plate_world(t):
    """The plate's vertices [m] in the world at ``t`` [s], as an animated USD asset is followed:
    linear between its samples (points and translation alike), held outside them."""
    times = np.array(PLATE_POINT_CODES) / PLATE_CODES_PER_SECOND
    samples = np.stack([animated_plate_points(k) for k in range(len(PLATE_POINT_CODES))]) * 0.01
    flat = samples.reshape(len(times), -1)
    pts = np.array([np.interp(t, times, flat[:, c]) for c in range(flat.shape[1])]).reshape(-1, 3)
    end = PLATE_XFORM_CODES[-1] / PLATE_CODES_PER_SECOND
    pts[:, 0] += PLATE_SPEED * min(max(t, 0.0), end)
    return pts


def write_animated_plate(path):
    """``animated_plate.usda`` (see ``animated_plate_points``): time-sampled points under a
    time-sampled translation, metersPerUnit 0.01."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(PLATE_CODES_PER_SECOND)
    stage.SetStartTimeCode(PLATE_POINT_CODES[0])
    stage.SetEndTimeCode(PLATE_POINT_CODES[-1])
    root = UsdGeom.Xform.Define(stage, "/Plate")
    stage.SetDefaultPrim(root.GetPrim())
    op = root.AddTranslateOp()
    for code in PLATE_XFORM_CODES:
        op.Set((PLATE_SPEED * 100.0 * code / PLATE_CODES_PER_SECOND, 0.0, 0.0), code)
    n = 4
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]
    mesh = UsdGeom.Mesh.Define(stage, "/Plate/Sheet")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for q in quads for i in q]))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    points, extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    for k, code in enumerate(PLATE_POINT_CODES):
        pts = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(animated_plate_points(k), dtype=np.float32))
        points.Set(pts, code)
        extent.Set(UsdGeom.PointBased.ComputeExtent(pts), code)
    UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
    stage.GetRootLayer().Save()


REAL_ASSETS = {
    "zup_cm.usda": write_zup_cm,
    "pawn.usda": write_pawn,
    "bracket_mm.stl": write_stl_mm,
    "skinned.usda": write_skinned,
    "latin1.obj": write_latin1_obj,
    "lost_texture.ply": write_lost_texture_ply,
}


def write_real_assets(out) -> list:
    """Write every ``REAL_ASSETS`` file into ``out``; returns their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, write in REAL_ASSETS.items():
        write(out / name)
    return [out / name for name in REAL_ASSETS]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="output folder (default: scenes/assets)")
    ap.add_argument("--real", metavar="DIR", help="write the test assets as other tools make them into DIR instead")
    args = ap.parse_args(argv)
    if args.real:
        for path in write_real_assets(args.real):
            print(path)
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    pts, counts, idx, uv = lat_long(blob_radius)
    write_mesh(out / "blob.usda", "Blob", pts, counts, idx, uv=uv, color=(0.95, 0.55, 0.2))
    pts, counts, idx, uv = torus()
    write_mesh(out / "torus.usda", "Torus", pts, counts, idx, uv=uv, color=(0.3, 0.6, 0.95))
    pts, counts, idx, uv = lat_long(pebble_radius, rings=32, segments=48)
    write_mesh(out / "pebble.usda", "Pebble", pts, counts, idx, uv=uv, color=(0.5, 0.8, 0.4))
    pts, counts, idx = stairs()
    write_mesh(out / "stairs.usda", "Stairs", pts, counts, idx, normals=_flat_normals(pts, counts, idx), collision=True)
    pts, counts, idx, nrm, uv = bumpy_floor()
    write_mesh(out / "bumpy_floor.usda", "Floor", pts, counts, idx, uv=uv, uv_interp="vertex", normals=nrm,
               collision=True)
    pts, counts, idx = critter()
    write_mesh(out / "critter.usda", "Critter", pts, counts, idx, color=(0.55, 0.45, 0.9))
    pts, counts, idx, uv = lat_long(blob_radius)
    pts, counts, idx = cut_base(pts, counts, idx, pts[:, 1].min() + 0.03)
    write_mesh(out / "blob_open.usda", "BlobOpen", pts, counts, idx, color=(0.9, 0.35, 0.45))
    pts, counts, idx = plate()
    write_mesh(out / "plate.usda", "Plate", pts, counts, idx, normals=_flat_normals(pts, counts, idx), collision=True)
    write_stl(out / "bracket.stl", bracket_triangles(), jitter=1e-16)
    for name in ("blob", "torus", "pebble", "stairs", "bumpy_floor", "critter", "blob_open", "plate"):
        print(out / f"{name}.usda")
    print(out / "bracket.stl")


if __name__ == "__main__":
    main()
