"""Triangle-mesh terrain ([[mesh]]) against the analytic terrain it can reproduce, and bad mesh files.

A flat mesh's distance over a face's interior is the face plane's, in the model's precision, so a
jelly on a mesh plane or slope must follow the analytic plane's trajectory to rounding; a
tessellated bowl comes close to the analytic one, by the tessellation's depth.
"""

import math

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdPhysics

from softsim_warp.commands import cli
from softsim_warp.core.model import build_model
from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.terrain import bowl_mesh
from softsim_warp.io.scene import load_scene, scene_from_dict

JELLY = {
    "resolution": [4, 4, 4],
    "size": 0.5,
    "center": [0.0, 0.45, 0.0],
    "rotation": {"axis": [1.0, 0.0, 1.0], "degrees": 20.0},
    "total_mass": 1.0,
    "springs": {"structural": {"ks": 50.0, "kd": 0.1}, "shear": {"ks": 50.0, "kd": 0.1}, "bending": {"ks": 25.0}},
}


def write_mesh(path, points, counts, indices, prim="/Terrain", collision=False, xform=None):
    """A one-Mesh USD file (optionally under an Xform with a translation)."""
    stage = Usd.Stage.CreateNew(str(path))
    parent = "/Root" if xform is not None else ""
    if xform is not None:
        UsdGeom.Xform.Define(stage, parent).AddTranslateOp().Set(tuple(float(c) for c in xform))
    mesh = UsdGeom.Mesh.Define(stage, parent + prim)
    mesh.CreatePointsAttr([tuple(map(float, p)) for p in points])
    mesh.CreateFaceVertexCountsAttr([int(c) for c in counts])
    mesh.CreateFaceVertexIndicesAttr([int(i) for i in indices])
    if collision:
        UsdPhysics.CollisionAPI.Apply(mesh.GetPrim())
    stage.GetRootLayer().Save()
    return str(path)


def quad(normal, size=8.0, point=(0.0, 0.0, 0.0)):
    """A square of edge ``size`` on a plane, wound to face ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    c = np.asarray(point, float)
    h = 0.5 * size
    pts = [c + h * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return pts, [4], [0, 1, 2, 3]  # (u, v, n) right-handed: counter-clockwise about n


def _scene(terrain, precision="float64", **sim):
    data = {
        "simulation": {"integrator": "symplectic", "dt": 4e-4, "frames": 1, "fps": 60, "precision": precision, **sim},
        "jelly": [dict(JELLY)],
        **terrain,
    }
    return scene_from_dict(data)


def _trajectory(scene, device, method, steps, every):
    model = build_model(scene, device)
    integ = make_integrator(method, model)
    a, b = model.state(), model.state()
    out = []
    for k in range(1, steps + 1):
        integ.step(a, b, scene.sim["dt"])
        a, b = b, a
        if k % every == 0:
            out.append(a.particle_q.numpy().astype(np.float64))
    return np.array(out)


@pytest.mark.parametrize("method", ["symplectic", "rk4", "implicit"])
def test_jelly_on_mesh_plane_follows_the_analytic_plane(tmp_path, device, method):
    # 0.4 s: the drop, the impact (restitution) and the first sliding contact with friction.
    path = write_mesh(tmp_path / "ground.usda", *quad([0, 1, 0]))
    terrain = {"restitution": 0.5, "friction": 0.5}
    analytic = _scene({"plane": [{"point": [0, 0, 0], "normal": [0, 1, 0], **terrain}]})
    meshed = _scene({"mesh": [{"path": path, **terrain}]})
    steps = 1000
    ref = _trajectory(analytic, device, method, steps, 100)
    got = _trajectory(meshed, device, method, steps, 100)
    assert ref[:, :, 1].min() < 0.02  # it did reach the ground (the contact layer is 0.01 m)
    # To 1e-5 of the jelly's size (0.5 m): the same contact, distances equal to rounding.
    assert np.abs(got - ref).max() <= 1e-5 * 0.5


def test_mesh_slope_reproduces_slide(tmp_path, device):
    # The built-in slide with a 4^3 jelly, its plane replaced by a mesh square of the same plane.
    theta = math.radians(30.0)
    normal = [math.sin(theta), math.cos(theta), 0.0]
    downhill = np.array([math.cos(theta), -math.sin(theta), 0.0])
    path = write_mesh(tmp_path / "slope.usda", *quad(normal, size=80.0))
    sets = ["jelly.0.resolution=4", "simulation.integrator=symplectic", "simulation.precision=float64"]
    analytic = load_scene("slide", sets)
    data = dict(analytic.data)
    data["mesh"] = [{"path": path, "restitution": 0.3, "friction": 0.2}]
    data.pop("plane")
    meshed = scene_from_dict({k: v for k, v in data.items()})
    h, steps, every = analytic.sim["dt"], 3000, 500
    ref = _trajectory(analytic, device, "symplectic", steps, every)
    got = _trajectory(meshed, device, "symplectic", steps, every)
    assert np.abs(got - ref).max() <= 1e-5 * 4.0
    # And the block law of slide (tests/test_rest.py) between 2 s and 3 s, landed and sliding.
    com = got.mean(axis=1)
    t = every * h
    a = ((com[-1] - com[-2]) - (com[-2] - com[-3])) @ downhill / t**2
    block = 9.8 * (math.sin(theta) - 0.2 * math.cos(theta))
    # By 2 s the 4^3 jelly slides flat (no rocking term): 9e-8 is measured.
    assert a == pytest.approx(block, rel=1e-4)


def test_mesh_bowl_converges_to_the_analytic_bowl(tmp_path, device):
    # A jelly dropped into a bowl of radius 1, against the analytic bowl, with the bowl tessellated
    # ever finer (rings x segments). A facet lies inside the sphere by up to the sagitta
    # R (1 - cos(pi / segments)), second order in the facet angle: the trajectory's error must be of
    # that size and fall with it (measured: 0.89, 0.92, 1.18 sagittas; ratios 3.8 and 3.1).
    terrain = {"restitution": 0.3, "friction": 0.3}
    analytic = _scene({"bowl": [{"center": [0, 1, 0], "radius": 1.0, "cut_height": 1.0, **terrain}]})
    ref = _trajectory(analytic, device, "symplectic", 1500, 500)
    assert ref[:, :, 1].min() < 0.05  # landed at the bottom
    errors, sagittas = [], []
    for rings, segments in ((16, 32), (32, 64), (64, 128)):
        pts, counts, idx = bowl_mesh([0, 1, 0], 1.0, 1.0, rings=rings, segments=segments)
        path = write_mesh(tmp_path / f"bowl{segments}.usda", pts, counts, idx)
        got = _trajectory(_scene({"mesh": [{"path": path, **terrain}]}), device, "symplectic", 1500, 500)
        errors.append(np.linalg.norm(got.mean(axis=1) - ref.mean(axis=1), axis=1).max())
        sagittas.append(1.0 - math.cos(math.pi / segments))
    assert all(e <= 2.0 * s for e, s in zip(errors, sagittas))
    assert errors[0] / errors[1] > 2.5 and errors[1] / errors[2] > 2.5  # second order: 4x per halving


def test_closed_mesh_keeps_particles_out_and_default_prims(tmp_path):
    # A closed box (12 triangles) as a table under the jelly; the file also holds a Mesh without
    # CollisionAPI far away, which the default prim selection must skip.
    from softsim_warp.core.mesh_assets import load_mesh

    stage = Usd.Stage.CreateNew(str(tmp_path / "box.usda"))
    for name, offset, collide in (("Table", (0, -0.25, 0), True), ("Decor", (0, 50, 0), False)):
        m = UsdGeom.Mesh.Define(stage, f"/{name}")
        c = np.array([[x, y, z] for x in (-1, 1) for y in (-0.25, 0.25) for z in (-1, 1)], float) + offset
        m.CreatePointsAttr([tuple(p) for p in c])
        faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
        m.CreateFaceVertexCountsAttr([4] * 6)
        m.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
        if collide:
            UsdPhysics.CollisionAPI.Apply(m.GetPrim())
    stage.GetRootLayer().Save()
    asset = load_mesh(str(tmp_path / "box.usda"))
    assert asset.closed and asset.points[:, 1].max() == pytest.approx(0.0)
    scene = _scene({"mesh": [{"path": str(tmp_path / "box.usda"), "restitution": 0.0, "friction": 0.5}]}, "float32")
    q = _trajectory(scene, "cpu", "symplectic", 2000, 2000)[-1]
    assert q[:, 1].min() > -0.01 - 1e-6  # resting on the top face, within the contact layer


def _error(capsys, argv):
    code = cli.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def _scene_file(tmp_path, body):
    p = tmp_path / "s.toml"
    p.write_text(
        'name = "s"\n[simulation]\ndt = 1e-3\nframes = 1\n'
        "[[jelly]]\nresolution = 3\nsize = 0.2\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.1\n"
        "springs.structural = { ks = 50.0 }\n" + body
    )
    return str(p)


def test_bad_terrain_meshes_are_one_line_errors(tmp_path, capsys):
    run = ["run", "--quiet", "--out", str(tmp_path / "o.usdc")]
    line = _error(capsys, run + [_scene_file(tmp_path, '[[mesh]]\npath = "nope.usda"\n')])
    assert "mesh.0.path" in line and "no such mesh file" in line and "nope.usda" in line
    empty = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(empty, "/X")
    empty.GetRootLayer().Save()
    line = _error(capsys, run + [_scene_file(tmp_path, '[[mesh]]\npath = "empty.usda"\n')])
    assert "mesh.0.path" in line and "no Mesh prim" in line
    write_mesh(tmp_path / "g.usda", *quad([0, 1, 0]))
    line = _error(capsys, run + [_scene_file(tmp_path, '[[mesh]]\npath = "g.usda"\nprim = "/Nothing"\n')])
    assert "mesh.0.prim" in line and "/Nothing" in line and "/Terrain" in line
    (tmp_path / "x.fbx").write_text("")
    line = _error(capsys, run + [_scene_file(tmp_path, '[[mesh]]\npath = "x.fbx"\n')])
    assert "mesh.0.path" in line and "unknown mesh format" in line


def test_mesh_terrain_transform_and_xforms(tmp_path):
    # A square (x, z in [-1, 1]) under an Xform translated by +1 in y, then the scene's transform:
    # scale 2, rotated 90 degrees about z, moved by (0, -3, 0).
    from softsim_warp.core.mesh_assets import load_mesh, transform_matrix

    path = write_mesh(tmp_path / "g.usda", *quad([0, 1, 0], size=2.0), xform=(0, 1, 0))
    a = load_mesh(path)
    assert np.allclose(a.points[:, 1], 1.0)
    t = {"translate": [0.0, -3.0, 0.0], "rotation": {"axis": [0, 0, 1], "degrees": 90.0}, "scale": 2.0}
    b = a.transformed(*transform_matrix(t))
    # (x, 1, z) -> scale (2x, 2, 2z) -> rotate about z by 90: (-2, 2x, 2z) -> move: (-2, 2x - 3, 2z).
    assert np.allclose(b.points[:, 0], -2.0)
    assert np.allclose(sorted(set(np.round(b.points[:, 1], 9))), [-5.0, -1.0])
    from softsim_warp.core.model import rotation_matrix

    m, _ = transform_matrix({"rotation": {"axis": [1, 2, 3], "degrees": 37.0}})
    assert np.allclose(m, rotation_matrix([1, 2, 3], 37.0), atol=1e-15)


def test_open_sheet_collides_from_its_front_only(tmp_path, device):
    # Two loose particles over and under an open square facing up (thickness 0.1 m): the one above
    # lands and rests on it; the one 0.5 m under it never comes within reach and falls freely,
    # exactly as symplectic Euler integrates gravity: y_n = y_0 - g h^2 n (n + 1) / 2.
    from softsim_warp.core.mesh_assets import load_mesh
    from softsim_warp.core.model import ModelBuilder

    path = write_mesh(tmp_path / "sheet.usda", *quad([0, 1, 0], size=4.0))
    b = ModelBuilder()
    b.add_particles([[0.3, 0.2, 0.1], [0.3, -0.5, 0.1]], [0.0, 0.0, 0.0], 1.0)
    b.add_mesh(load_mesh(path), restitution=0.0, friction=0.5, thickness=0.1)
    model = b.finalize(device, "float64")
    assert model.mesh_closed.numpy().tolist() == [0]
    integ = make_integrator("symplectic", model)
    s0, s1 = model.state(), model.state()
    h, n = 1e-3, 400
    for _ in range(n):
        integ.step(s0, s1, h)
        s0, s1 = s1, s0
    q = s0.particle_q.numpy()
    assert 0.0 <= q[0, 1] <= 0.01  # resting on the sheet, within the contact layer
    assert q[1, 1] == pytest.approx(-0.5 - 9.8 * h * h * n * (n + 1) / 2, abs=1e-12)


def test_scene_without_meshes_launches_no_mesh_kernel(monkeypatch):
    # Model only what a scene needs: jelly_drop's steps launch no mesh kernel.
    import warp as wp

    model = build_model(load_scene("jelly_drop", ["jelly.0.resolution=3"]), "cpu")
    assert model.mesh_count == 0
    launched = []
    real = wp.launch
    monkeypatch.setattr(wp, "launch", lambda kernel, *a, **k: (launched.append(kernel.key), real(kernel, *a, **k))[1])
    for method in ("symplectic", "implicit"):
        integ = make_integrator(method, model)
        s0, s1 = model.state(), model.state()
        integ.step(s0, s1, 1e-3)
    assert launched and not any("mesh" in key for key in launched)
