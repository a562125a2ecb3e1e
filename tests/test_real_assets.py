"""Assets as other tools write them: units and up axes, USD files of
several Meshes, skinned Meshes with static normals, OBJ/PLY files with what trimesh warns about.

The assets are made by ``assets/make_assets.py --real`` (``write_real_assets``), nothing is
downloaded. Each test runs the real command (``cli.main``) or the scene validation on them and checks
the geometry against the file's own numbers, computed here independently of the loader.
"""

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdSkel, UsdValidation

from softsim_warp.commands import cli
from softsim_warp.core.errors import SceneError
from softsim_warp.core.mesh_assets import load_mesh
from softsim_warp.core.terrain import fan_triangles, vertex_normals
from softsim_warp.io.scene import load_scene
from tests.test_outputs import _one_line_error

ROOT = Path(__file__).resolve().parents[1]
SIM = '[simulation]\nintegrator = "symplectic"\ndt = 1e-3\nframes = 2\nfps = 30\n'
SPRINGS = "springs.structural = { ks = 200.0, kd = 0.1 }\n"


def _make_assets_module():
    spec = importlib.util.spec_from_file_location("make_assets", ROOT / "assets" / "make_assets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MA = _make_assets_module()


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    out = tmp_path_factory.mktemp("real_assets")
    MA.write_real_assets(out)
    return out


def _jelly(mesh, extra="", center=(0.0, 1.0, 0.0), resolution=8):
    return (f'[[jelly]]\nmesh = "{mesh}"\nresolution = {resolution}\ncenter = [{center[0]}, {center[1]}, {center[2]}]\n'
            f"total_mass = 0.5\n{extra}" + SPRINGS)


def _scene(tmp_path, assets, body, name="s.toml"):
    """A scene file beside the assets (relative paths), in a folder of its own."""
    path = Path(assets) / f"{tmp_path.name}_{name}"
    path.write_text(SIM + body)
    return path


def _run(scene, out, capsys=None, *extra):
    code = cli.main(["run", str(scene), "--quiet", "--out", str(out), *extra])
    assert code == 0
    return Usd.Stage.Open(str(out))


def _surface(stage, time=0.0, jelly="Jelly_0"):
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{jelly}/Surface"))
    return mesh, np.array(mesh.GetPointsAttr().Get(time), dtype=np.float64)


def _validator_issues(path):
    uv = pytest.importorskip("usd_validation_nvidia")
    results = uv.ValidationEngine().validate(str(path))
    return [f"{i.severity.name} {i.rule.__name__ if i.rule else ''}: {i.message}" for i in results.issues]


def _usd_validation(path):
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    return [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))]


# ---------------------------------------------------------------------------------------------
# Point 3: units and axes


def test_zup_centimetre_usd_stands_upright_at_its_size(tmp_path, assets):
    # The pebble is 0.24 x 0.6 x 0.2 m with y up; the file holds it z up, in centimetres.
    pts = MA.lat_long(MA.tall_pebble_radius, rings=24, segments=32)[0]
    a = load_mesh(str(assets / "zup_cm.usda"), colliders=False)
    assert a.points.shape == pts.shape
    # The file stores float32 centimetres: equal to their rounding (6e-8 relative).
    assert np.abs(a.points - pts).max() < 1e-6
    assert np.ptp(a.points, axis=0) == pytest.approx([0.24, 0.6, 0.2], abs=1e-6)
    # The same points with the stage's upAxis y read as lying on their side (the control).
    lying = tmp_path / "lying.usda"
    layer = Sdf.Layer.FindOrOpen(str(assets / "zup_cm.usda"))
    layer.Export(str(lying))
    stage = Usd.Stage.Open(str(lying))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.Save()
    assert np.ptp(load_mesh(str(lying), colliders=False).points, axis=0) == pytest.approx([0.24, 0.2, 0.6], abs=1e-6)
    # As a jelly: the Surface's height along world y, in the output, is the asset's 0.6 m.
    stage = _run(_scene(tmp_path, assets, _jelly("zup_cm.usda")), tmp_path / "z.usdc")
    _, x = _surface(stage)
    assert np.ptp(x, axis=0) == pytest.approx([0.24, 0.6, 0.2], abs=1e-5)
    assert x[:, 1].mean() == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("value", [0.0, -0.01, math.inf, math.nan])
def test_bad_meters_per_unit_is_one_line_error(tmp_path, assets, capsys, value):
    bad = tmp_path / "bad_mpu.usda"
    Sdf.Layer.FindOrOpen(str(assets / "zup_cm.usda")).Export(str(bad))
    stage = Usd.Stage.Open(str(bad))
    stage.SetMetadata(UsdGeom.Tokens.metersPerUnit, value)
    stage.Save()
    scene = tmp_path / "s.toml"
    scene.write_text(SIM + _jelly("bad_mpu.usda"))
    assert cli.main(["run", str(scene), "--quiet", "--out", str(tmp_path / "o.usdc")]) == 2
    line = _one_line_error(capsys, "jelly.0.mesh", "metersPerUnit", "bad_mpu.usda")
    assert "non-manifold" not in line
    assert not (tmp_path / "o.usdc").exists()


def test_millimetre_stl_with_units_has_its_real_size(tmp_path, assets, capsys):
    # 120 x 60 x 40 mm, z up: 0.12 m along x, 0.04 m tall (world y), 0.06 m deep (world z).
    a = load_mesh(str(assets / "bracket_mm.stl"), colliders=False, units="mm", up_axis="Z")
    assert np.ptp(a.points, axis=0) == pytest.approx([0.12, 0.04, 0.06], abs=1e-9)
    assert a.points[:, 1].min() == pytest.approx(0.0, abs=1e-12)  # it stood on z = 0: now on y = 0
    assert a.closed and a.volume() == pytest.approx(0.12 * 0.06 * 0.04, rel=1e-6)
    # In inches (a number of metres per unit works as well as a name).
    b = load_mesh(str(assets / "bracket_mm.stl"), colliders=False, units=0.0254)
    assert np.ptp(b.points, axis=0) == pytest.approx(0.0254 * np.array(MA.BRACKET_MM), rel=1e-7)
    # As a jelly, validated: no warning, the lattice spans the real size.
    scene = load_scene(str(_scene(tmp_path, assets, _jelly("bracket_mm.stl", 'units = "mm"\nup_axis = "Z"\n'))))
    assert capsys.readouterr().err == ""
    assert max(scene.data["jelly"][0]["size"]) <= 0.12 + 1e-9


def test_jelly_asset_of_implausible_size_warns_once(tmp_path, assets, capsys):
    # Read as metres the millimetre block is 120 m long: one warning line naming the size and the key.
    load_scene(str(_scene(tmp_path, assets, _jelly("bracket_mm.stl"))))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "jelly.0.size" in err[0] and "120 m" in err[0], err
    # A 1.2 mm asset (units given as a number, 10 micrometres per unit) is too small: a warning too.
    load_scene(str(_scene(tmp_path, assets, _jelly("bracket_mm.stl", "units = 1e-5\n", resolution=12), name="um.toml")))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "jelly.0.size" in err[0] and "0.0012 m" in err[0], err
    # With size, nothing is said: the user has chosen.
    load_scene(str(_scene(tmp_path, assets, _jelly("bracket_mm.stl", "size = 0.3\n"), name="sized.toml")))
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "extra, key, needle",
    [
        ('units = "furlong"', "jelly.0.units", "must be one of m, cm, mm"),
        ("units = -1.0", "jelly.0.units", "metres per unit > 0"),
        ("units = true", "jelly.0.units", "metres per unit > 0"),
        ('up_axis = "X"', "jelly.0.up_axis", "must be one of Y, Z"),
    ],
)
def test_bad_units_and_axes_are_one_line_errors(tmp_path, assets, capsys, extra, key, needle):
    scene = _scene(tmp_path, assets, _jelly("bracket_mm.stl", extra + "\n"))
    assert cli.main(["run", str(scene), "--quiet", "--out", str(tmp_path / "o.usdc")]) == 2
    _one_line_error(capsys, key, needle)


def test_usd_file_refuses_units_keys(tmp_path, assets, capsys):
    # A USD file states its own metersPerUnit and upAxis: a scene key beside them would be a second truth.
    scene = _scene(tmp_path, assets, '[[mesh]]\npath = "zup_cm.usda"\nunits = "cm"\n' + _jelly("pawn.usda"))
    assert cli.main(["run", str(scene), "--quiet", "--out", str(tmp_path / "o.usdc")]) == 2
    _one_line_error(capsys, "mesh.0.units", "metersPerUnit")


# ---------------------------------------------------------------------------------------------
# Point 4: USD assets of several Meshes


def _pawn_parts():
    """The pawn's two Meshes in world space, computed from the script's own numbers: x S + T."""
    out = []
    for xf, rings, segs in ((MA.PAWN_BASE, 16, 24), (MA.PAWN_HEAD, 12, 18)):
        pts, counts, idx, uv = MA.lat_long(lambda d: np.full(len(d), 0.2), rings, segs)
        out.append((pts * np.array(xf["scale"]) + np.array(xf["translate"]), counts, idx, uv))
    return out


def test_usd_of_two_meshes_is_one_jelly_with_both(tmp_path, assets):
    (base, cb, ib, uvb), (head, _, ih, uvh) = _pawn_parts()
    a = load_mesh(str(assets / "pawn.usda"), colliders=False)
    assert a.points.shape[0] == len(base) + len(head)
    assert np.abs(a.points - np.concatenate([base, head])).max() < 1e-6
    assert np.array_equal(a.indices, np.concatenate([ib, ih + len(base)]))
    assert a.closed
    stage = _run(_scene(tmp_path, assets, _jelly("pawn.usda", resolution=10) + "[[plane]]\n"), tmp_path / "p.usdc")
    mesh, x = _surface(stage)
    assert len(x) == len(base) + len(head)
    # Undeformed at frame 0: the asset, placed with its bounding-box centre at the jelly's centre.
    want = np.concatenate([base, head])
    want = want - 0.5 * (want.min(0) + want.max(0)) + [0.0, 1.0, 0.0]
    assert np.abs(x - want).max() < 1e-5
    # Each Mesh's colour on its own faces (a constant per Mesh becomes one value per face), its UVs on its corners.
    api = UsdGeom.PrimvarsAPI(mesh)
    color = api.GetPrimvar("displayColor")
    assert color.GetInterpolation() == UsdGeom.Tokens.uniform
    per_face = np.array(color.ComputeFlattened())
    assert np.allclose(per_face[: len(cb)], (0.9, 0.9, 0.85)) and np.allclose(per_face[len(cb):], (0.8, 0.2, 0.2))
    st = api.GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    assert np.allclose(np.array(st.ComputeFlattened()), np.concatenate([uvb, uvh]))


def test_prim_names_one_mesh_or_a_subtree(tmp_path, assets, capsys):
    # A jelly per Mesh when the scene asks: mesh_prim names the Mesh (or an Xform above it).
    head = _pawn_parts()[1][0]
    for prim in ("/Pawn/Head", "/Pawn/Head/Geom"):
        a = load_mesh(str(assets / "pawn.usda"), prim, colliders=False)
        assert np.abs(a.points - head).max() < 1e-6
    scene = _scene(tmp_path, assets, _jelly("pawn.usda", 'mesh_prim = "/Pawn/Nope"\n'))
    assert cli.main(["run", str(scene), "--quiet", "--out", str(tmp_path / "o.usdc")]) == 2
    _one_line_error(capsys, "jelly.0.mesh_prim", "/Pawn/Nope", "/Pawn/Base/Geom")


def test_terrain_of_two_meshes_keeps_each_meshs_primvars(tmp_path, assets):
    (base, cb, _, uvb), (head, _, _, uvh) = _pawn_parts()
    body = '[[mesh]]\npath = "pawn.usda"\ntransform = { translate = [0.0, -1.0, 0.0] }\n'
    stage = _run(_scene(tmp_path, assets, body + _jelly("zup_cm.usda", resolution=4)), tmp_path / "t.usdc")
    terrain = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.GetName().startswith("Mesh")]
    assert len(terrain) == 1
    mesh = UsdGeom.Mesh(terrain[0])
    x = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    assert np.abs(x - (np.concatenate([base, head]) + [0.0, -1.0, 0.0])).max() < 1e-6
    api = UsdGeom.PrimvarsAPI(mesh)
    per_face = np.array(api.GetPrimvar("displayColor").ComputeFlattened())
    assert np.allclose(per_face[: len(cb)], (0.9, 0.9, 0.85)) and np.allclose(per_face[len(cb):], (0.8, 0.2, 0.2))
    assert np.allclose(np.array(api.GetPrimvar("st").ComputeFlattened()), np.concatenate([uvb, uvh]))
    assert _validator_issues(tmp_path / "t.usdc") == [] and _usd_validation(tmp_path / "t.usdc") == []


# ---------------------------------------------------------------------------------------------
# Point 5: valid output


def test_skinned_asset_output_is_valid_and_its_normals_are_recomputed(tmp_path, assets):
    src = Usd.Stage.Open(str(assets / "skinned.usda"))
    body = src.GetPrimAtPath("/Character/Body")
    assert body.HasAPI(UsdSkel.BindingAPI) and UsdGeom.PrimvarsAPI(body).HasPrimvar("skel:jointIndices")
    static = np.array(UsdGeom.PrimvarsAPI(body).GetPrimvar("normals").Get(), dtype=np.float64)
    # Spinning about z, so that by the last frame the asset's static normals are wrong.
    scene = _scene(tmp_path, assets, _jelly("skinned.usda", "angular_velocity = [0.0, 0.0, 6.0]\n")
                   + '[[mesh]]\npath = "skinned.usda"\ntransform = { translate = [0.0, -2.0, 0.0] }\n')
    out = tmp_path / "sk.usdc"
    stage = _run(scene, out, None, "--frames", "6")
    assert _validator_issues(out) == []
    assert _usd_validation(out) == []
    for prim in (stage.GetPrimAtPath("/World/Jelly_0/Surface"),
                 next(p for p in stage.Traverse() if p.GetName().startswith("Body"))):
        names = {str(pv.GetPrimvarName()) for pv in UsdGeom.PrimvarsAPI(prim).GetPrimvarsWithValues()}
        assert names == {"displayColor", "st"}, names  # no skel:*, normals or tangents
        assert not prim.HasAPI(UsdSkel.BindingAPI) and not prim.GetRelationship("skel:skeleton")
    mesh, x = _surface(stage, 6.0)
    tris = fan_triangles(np.array(mesh.GetFaceVertexCountsAttr().Get()), np.array(mesh.GetFaceVertexIndicesAttr().Get()))
    normals = np.array(mesh.GetNormalsAttr().Get(6.0), dtype=np.float64)
    assert np.abs(normals - vertex_normals(x, tris)).max() < 1e-5
    # The control: the static normals are far from the deformed surface's (a stale copy would show).
    assert np.abs(static - normals).max() > 0.3
    # And the validator does catch skinning primvars left on a Mesh without SkelBindingAPI.
    bad = tmp_path / "bad.usdc"
    stage.GetRootLayer().Export(str(bad))
    broken = Usd.Stage.Open(str(bad))
    UsdGeom.PrimvarsAPI(broken.GetPrimAtPath("/World/Jelly_0/Surface")).CreatePrimvar(
        "skel:jointIndices", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex, 1).Set([0] * len(x))
    broken.Save()
    assert any("SkelBindingAPI" in issue for issue in _validator_issues(bad))


@pytest.mark.parametrize("name", sorted(MA.REAL_ASSETS))
def test_every_test_asset_gives_valid_output(tmp_path, assets, name):
    extra = 'units = "mm"\nup_axis = "Z"\n' if name.endswith(".stl") else ""
    out = tmp_path / "v.usdc"
    _run(_scene(tmp_path, assets, _jelly(name, extra, resolution=6) + "[[plane]]\n"), out)
    assert _validator_issues(out) == []
    assert _usd_validation(out) == []


# ---------------------------------------------------------------------------------------------
# Point 8: what trimesh needs, and what it says


@pytest.mark.parametrize("name", ["latin1.obj", "lost_texture.ply"])
def test_obj_and_ply_load_with_stderr_clean(tmp_path, assets, capfd, caplog, name):
    trimesh = pytest.importorskip("trimesh")
    capfd.readouterr()
    scene = _scene(tmp_path, assets, _jelly(name, resolution=6) + "[[plane]]\n")
    stage = _run(scene, tmp_path / "o.usdc")
    # Only the run's own summary line (``<scene>: N frames ...``) is on stderr, and trimesh logged
    # nothing (pytest's log capture would otherwise take its records off stderr: they are counted).
    err = capfd.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"{scene.stem}: ") and " frames, " in err[0], err
    assert [r.getMessage() for r in caplog.records if r.name.startswith("trimesh")] == []
    mesh, x = _surface(stage)
    assert UsdGeom.PrimvarsAPI(mesh).HasPrimvar("st")  # the UVs came through
    a = load_mesh(str(assets / name), colliders=False)
    assert a.closed and a.volume() > 0 and len(x) == a.points.shape[0]
    if name == "lost_texture.ply":
        # The control: trimesh left alone logs a traceback about the missing image.
        trimesh.load(str(assets / name), force="mesh", process=False)
        assert any("unable to load image" in r.getMessage() for r in caplog.records if r.name.startswith("trimesh"))


def test_run_in_a_fresh_process_prints_nothing_from_trimesh(tmp_path, assets):
    # Outside pytest (no log capture): Python prints an unhandled logger's warnings on stderr.
    scene = _scene(tmp_path, assets, _jelly("lost_texture.ply", resolution=6) + "[[plane]]\n")
    run = subprocess.run([sys.executable, "-m", "softsim_warp", "run", str(scene), "--quiet", "--out",
                          str(tmp_path / "o.usdc")], check=False, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert [line for line in run.stderr.splitlines() if not line.startswith(f"{scene.stem}: ")] == []
    load = "import sys, trimesh; trimesh.load(sys.argv[1], force='mesh', process=False)"
    control = subprocess.run([sys.executable, "-c", load, str(assets / "lost_texture.ply")], check=False,
                             capture_output=True, text=True)
    assert "Traceback" in control.stderr and "missing_texture.png" in control.stderr


def test_unreadable_obj_is_still_an_error(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_bytes(b"v 0 0 0\nf 1 2 3\n")  # a face on vertices that are not there
    with pytest.raises(SceneError):
        load_mesh(str(bad))


def test_which_meshes_and_primvars_are_read(tmp_path):
    # Under the default prim: drawn Meshes only (a guide and an invisible Mesh left out, a Mesh
    # outside the default prim too); of the primvars, those valid under deformation that fit the mesh.
    pts, counts, idx, uv = MA.lat_long(lambda d: np.full(len(d), 0.1), rings=6, segments=8)
    path = tmp_path / "mixed.usda"
    stage = Usd.Stage.CreateNew(str(path))
    root = UsdGeom.Xform.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    for name, offset in (("Shown", 0.0), ("Guide", 1.0), ("Hidden", 2.0)):
        MA._define_mesh(stage, f"/Root/{name}", pts + [offset, 0.0, 0.0], counts, idx, uv=uv)
    MA._define_mesh(stage, "/Elsewhere", pts + [5.0, 0.0, 0.0], counts, idx)
    UsdGeom.Imageable(stage.GetPrimAtPath("/Root/Guide")).CreatePurposeAttr(UsdGeom.Tokens.guide)
    UsdGeom.Imageable(stage.GetPrimAtPath("/Root/Hidden")).MakeInvisible()
    api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Root/Shown"))
    n = len(pts)
    api.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set([(0, 0, 0)] * n)
    api.CreatePrimvar("wind", Sdf.ValueTypeNames.Vector3fArray, UsdGeom.Tokens.vertex).Set([(0, 0, 0)] * n)
    api.CreatePrimvar("label", Sdf.ValueTypeNames.StringArray, UsdGeom.Tokens.constant).Set(["a"])
    api.CreatePrimvar("short", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set([1.0] * (n - 1))
    api.CreatePrimvar("heat", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.uniform).Set(list(range(len(counts))))
    api.CreatePrimvar("skel:jointWeights", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set([1.0] * n)
    stage.GetRootLayer().Save()
    a = load_mesh(str(path), colliders=False)
    assert np.abs(a.points - pts).max() < 1e-6  # only /Root/Shown
    kept = {p[0]: p for p in a.primvars}
    assert set(kept) == {"displayColor", "st", "heat"}
    assert np.array_equal(kept["heat"][3], np.arange(len(counts)))
    # Naming a prim outside the default prim reads it.
    assert np.abs(load_mesh(str(path), "/Elsewhere", colliders=False).points - (pts + [5.0, 0.0, 0.0])).max() < 1e-6


def test_animated_mesh_is_read_at_its_first_sample(tmp_path):
    # A cache exported from an animation: points as time samples only, no default value.
    pts, counts, idx, uv = MA.lat_long(lambda d: np.full(len(d), 0.1), rings=6, segments=8)
    path = tmp_path / "cache.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = MA._define_mesh(stage, "/Cache", pts, counts, idx, uv=uv)
    mesh.GetPointsAttr().Clear()
    for t, dy in ((1.0, 0.0), (2.0, 1.0)):
        mesh.GetPointsAttr().Set([tuple(p) for p in (pts + [0.0, dy, 0.0]).astype(float)], t)
    stage.GetRootLayer().Save()
    a = load_mesh(str(path), colliders=False)
    assert np.abs(a.points - pts).max() < 1e-6


def test_millimetre_zup_stl_as_terrain(tmp_path, assets):
    # The keys work for [[mesh]] too: the block lies 0.04 m tall on y = 0, under a jelly dropped on it.
    body = '[[mesh]]\npath = "bracket_mm.stl"\nunits = "mm"\nup_axis = "Z"\n'
    out = tmp_path / "t.usdc"
    stage = _run(_scene(tmp_path, assets, body + _jelly("pawn.usda", center=(0.0, 0.5, 0.0), resolution=6)), out)
    terrain = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.GetName().startswith("bracket_mm")]
    assert len(terrain) == 1
    x = np.array(UsdGeom.Mesh(terrain[0]).GetPointsAttr().Get(), dtype=np.float64)
    assert x.min(0) == pytest.approx([-0.06, 0.0, -0.03], abs=1e-7)
    assert x.max(0) == pytest.approx([0.06, 0.04, 0.03], abs=1e-7)


def test_units_on_a_box_jelly_is_an_error(tmp_path, capsys):
    scene = tmp_path / "box.toml"
    scene.write_text(SIM + '[[jelly]]\nresolution = 3\nsize = 0.2\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.1\n'
                     'units = "mm"\n' + SPRINGS)
    assert cli.main(["run", str(scene), "--quiet", "--out", str(tmp_path / "o.usdc")]) == 2
    _one_line_error(capsys, "jelly.0.units", "only a mesh jelly takes it")
