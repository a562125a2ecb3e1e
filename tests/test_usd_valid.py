"""Every built-in scene's USD passes NVIDIA's asset validator (default rules) and OpenUSD's UsdValidation.

Each scene runs a few frames with a small lattice, with and without ``--springs``; a single
failure, warning or error of either validator fails the test. The geometry the validators cannot
judge (winding against the side a surface faces, widths inside extents, normals of the moving
surface at every frame) is checked directly below.
"""

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdValidation

from softsim_warp.commands import cli
from softsim_warp.core.terrain import fan_triangles, signed_volume
from softsim_warp.io.scene import builtin_scenes, read_scene_data

uv = pytest.importorskip("usd_validation_nvidia")

SCENES = sorted(builtin_scenes())
# These explode under explicit methods at their step, by design (docs/HARD_CASES.md): implicit runs them.
EXTRA = {name: ["--integrator", "implicit"] for name in ("hard_mass_ratio", "hard_stiff_1e5", "hard_stiff_1e6")}


def _small(name):
    """--set overrides giving every large box jelly of a scene at most 4 particles per axis (mesh
    jellies a coarse lattice); 6x6x6 jellies keep theirs (hard_mass_ratio is tuned to its lattice)."""
    _, _, data = read_scene_data(name)
    out = []
    for i, j in enumerate(data.get("jelly", [])):
        if "mesh" in j:
            out += ["--set", f"jelly.{i}.resolution=9"]
        elif max(j["resolution"]) > 6:
            out += ["--set", f"jelly.{i}.resolution=[{','.join(str(min(n, 4)) for n in j['resolution'])}]"]
    return out


def _run(tmp_path, name, springs):
    out = tmp_path / f"{name}{'_springs' if springs else ''}.usdc"
    argv = ["run", name, "--frames", "2", "--fps", "30", "--quiet", "--out", str(out), *_small(name), *EXTRA.get(name, [])]
    assert cli.main(argv + (["--springs"] if springs else [])) == 0
    return out


def _issues(path):
    """NVIDIA's validator with its default rules: every issue, whatever its severity."""
    results = uv.ValidationEngine().validate(str(path))
    return [f"{i.severity.name} {i.rule.__name__ if i.rule else ''}: {i.message}" for i in results.issues]


def _usd_validation(stage):
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    return [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)]


@pytest.mark.parametrize("springs", [False, True], ids=["plain", "springs"])
@pytest.mark.parametrize("name", SCENES)
def test_builtin_scene_output_is_valid(tmp_path, name, springs):
    path = _run(tmp_path, name, springs)
    assert _issues(path) == []
    stage = Usd.Stage.Open(str(path))
    assert _usd_validation(stage) == []
    _, _, data = read_scene_data(name)
    # A jelly that starts mirrored (initial_scale with one negative component) is inside out.
    mirrored = {f"Jelly_{i}" for i, j in enumerate(data.get("jelly", [])) if np.prod(j.get("initial_scale", 1.0)) < 0}
    _check_geometry(stage, mirrored, [np.asarray(p["normal"], dtype=np.float64) for p in data.get("plane", [])])


def _check_geometry(stage, mirrored=(), plane_normals=None):
    data = stage.GetRootLayer().customLayerData
    assert len(data["softsim:gravity"]) == 3 and "softsim:dt" in data and "softsim:integrator" in data
    times = [float(t) for t in range(3)]
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Points):
            pts = UsdGeom.Points(prim)
            n = len(pts.GetPointsAttr().Get(0))
            assert list(pts.GetIdsAttr().Get()) == list(range(n))  # stable: authored once
            assert pts.GetVelocitiesAttr().GetTimeSamples() == times
            w = np.array(pts.GetWidthsAttr().Get())
            for t in times:
                x = np.array(pts.GetPointsAttr().Get(t))
                ext = np.array(pts.GetExtentAttr().Get(t))
                # The extent holds every sphere of diameter w: min(x - w/2), max(x + w/2).
                assert np.allclose(ext[0], (x - 0.5 * w[:, None]).min(0), atol=1e-6)
                assert np.allclose(ext[1], (x + 0.5 * w[:, None]).max(0), atol=1e-6)
        elif prim.IsA(UsdGeom.BasisCurves):
            assert UsdGeom.BasisCurves(prim).GetExtentAttr().GetTimeSamples() == times
        elif prim.IsA(UsdGeom.Mesh):
            _check_mesh(UsdGeom.Mesh(prim), times, prim.GetParent().GetName() in mirrored, plane_normals)


def _check_mesh(mesh, times, mirrored=False, plane_normals=None):
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    tris = fan_triangles(counts, indices)
    moving = mesh.GetPointsAttr().ValueMightBeTimeVarying()
    for t in times if moving else [Usd.TimeCode.Default()]:
        x = np.array(mesh.GetPointsAttr().Get(t), dtype=np.float64)
        normals = np.array(mesh.GetNormalsAttr().Get(t), dtype=np.float64)
        assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex or not moving
        assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
        if moving:
            assert len(normals) == len(x)
            assert len(mesh.GetVelocitiesAttr().Get(t)) == len(x)
        # Right-handed winding agrees with the normals, face by face (area-weighted).
        area = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
        if mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex and not _flat(mesh):
            # (face by face at the start; a crumpled face of a later frame may turn against its
            # vertices' normals, the surface as a whole may not)
            along = np.einsum("ij,ij->i", area, normals[tris].mean(axis=1))
            assert np.all(along > 0) if t in (0.0, Usd.TimeCode.Default()) else along.sum() > 0
    name = mesh.GetPrim().GetName()
    if name.startswith("Plane"):
        # A plane's faces wind towards the side that collides: its normal, +y for the ground.
        x = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
        area = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]).sum(0)
        if plane_normals is not None:  # the scene's normal, whichever way it faces (a lid faces down)
            assert area @ plane_normals[int(name.split("_")[1])] > 0.999 * np.linalg.norm(area)
        else:
            assert area[1] > 0 or abs(area[1]) < 1e-9 * np.linalg.norm(area)
    if name.startswith("Sphere") or (name == "Surface" and not _flat(mesh) and not mirrored):
        x = np.array(mesh.GetPointsAttr().Get(times[0] if moving else Usd.TimeCode.Default()), dtype=np.float64)
        assert signed_volume(x, tris) > 0  # closed and wound outward


def _flat(mesh):
    """A sheet (a one-particle-thick jelly, or terrain) shows both sides of one layer of faces."""
    return bool(mesh.GetDoubleSidedAttr().Get())


def test_flat_plane_faces_its_normal():
    from softsim_warp.io.usd import plane_mesh

    for normal in ([0, 1, 0], [0.3, 0.9, -0.2], [1, 0, 0]):
        for hole in (0.0, 0.3):
            pts, counts, idx = plane_mesh([0.1, 0.2, 0.3], normal, 2.0, [0, 0, 0], hole)
            tris = fan_triangles(counts, idx)
            area = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
            n = np.asarray(normal, float) / np.linalg.norm(normal)
            assert np.all(area @ n > 0)
