"""Mesh jellies ([[jelly]] mesh = ...): voxelisation, the embedded surface, bad assets.

Voxel volumes are checked against closed forms (sphere, torus), a box mesh against the box jelly it
must be bit for bit, and the embedded surface against the affine maps trilinear weights reproduce.
"""

import math
import sys

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, Vt

from softsim_warp.commands import cli
from softsim_warp.core.mesh_assets import load_mesh
from softsim_warp.core.model import build_model, rotation_matrix
from softsim_warp.core.terrain import sphere_mesh
from softsim_warp.core.voxelize import voxelize
from softsim_warp.io.scene import scene_from_dict
from softsim_warp.io.usd import SurfaceMap

SPRINGS = {"structural": {"ks": 50.0, "kd": 0.1}, "shear": {"ks": 50.0, "kd": 0.1}, "bending": {"ks": 25.0}}


def write_usd(path, points, counts, indices, uv=False, prim="/Asset"):
    stage = Usd.Stage.CreateNew(str(path))
    m = UsdGeom.Mesh.Define(stage, prim)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, dtype=np.float32)))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, dtype=np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, dtype=np.int32)))
    if uv:
        pv = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        k = np.arange(len(indices), dtype=np.float32)
        pv.Set(Vt.Vec2fArray.FromNumpy(np.stack([k / len(indices), (k % 7) / 7.0], axis=1).astype(np.float32)))
    stage.GetRootLayer().Save()
    return str(path)


def box_mesh(size):
    sx, sy, sz = (0.5 * s for s in size)
    pts = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    faces = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    return pts, [4] * 6, [i for f in faces for i in f]


def torus_mesh(R, r, nu=128, nv=64):
    u = np.linspace(0, 2 * math.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * math.pi, nv, endpoint=False)
    U, V = np.meshgrid(u, v, indexing="ij")
    pts = np.stack([(R + r * np.cos(V)) * np.cos(U), r * np.sin(V), (R + r * np.cos(V)) * np.sin(U)], -1).reshape(-1, 3)
    idx = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            idx += [a, d, c, b]
    return pts, [4] * (nu * nv), idx


def _mesh_scene(path, **jelly):
    j = {"mesh": path, "center": [0.0, 2.0, 0.0], "total_mass": 1.0, "springs": SPRINGS, **jelly}
    return scene_from_dict({"simulation": {"dt": 1e-3, "frames": 1}, "jelly": [j]})


def _grid(points, resolution):
    """A lattice of ``resolution`` cells along the mesh's longest side, its points at the centres of
    the cells that tile the bounding box (no lattice plane on a tangent plane), centred on the box:
    (shape, size, spacing, centre)."""
    lo, hi = points.min(0), points.max(0)
    h = (hi - lo).max() / resolution
    shape = [max(int(math.ceil(e / h - 1e-6)), 2) for e in hi - lo]
    return shape, [(n - 1) * h for n in shape], h, 0.5 * (lo + hi)


def _grid_volume(points, tris, resolution):
    shape, size, h, center = _grid(points, resolution)
    return voxelize(points - center, tris, shape, size, "cpu").sum() * h**3


def test_voxelised_points_are_the_analytic_inside(device):
    # Each lattice point's inside/outside against the analytic sphere and torus: they may differ only
    # within the tessellation's sagitta of the surface (the mesh's facets cut inside the shape).
    from softsim_warp.core.terrain import fan_triangles

    R, r = 1.0, 0.5
    shapes = [
        (sphere_mesh([0, 0, 0], 1.0, rings=64, segments=128), lambda g: np.linalg.norm(g, axis=1) - 1.0,
         1.0 - math.cos(math.pi / 64)),
        (torus_mesh(R, r), lambda g: np.hypot(np.hypot(g[:, 0], g[:, 2]) - R, g[:, 1]) - r,
         (R + r) * (1.0 - math.cos(math.pi / 128)) + r * (1.0 - math.cos(math.pi / 64))),
    ]
    for (pts, counts, idx), sdf, sagitta in shapes:
        shape, size, h, center = _grid(pts, 30)
        mask = voxelize(pts - center, fan_triangles(counts, idx), shape, size, device)
        axes = [np.linspace(-0.5 * s, 0.5 * s, n) for n, s in zip(shape, size)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) + center
        d = sdf(g)
        assert np.all(mask[d < -sagitta]) and not np.any(mask[d > 1e-4 * h])


def test_voxelised_sphere_and_torus_volume():
    # Each lattice point inside stands for one cell: the voxel volume N h^3, within 3 % of the
    # analytic volume for the sphere and a ring torus (R = 1, r = 0.5, V = 2 pi^2 R r^2) at
    # resolution 30 (cells along the longest side) and finer, with the points at cell centres
    # (_grid; with points on the bounding faces the torus's top and bottom tangent planes would hold
    # lattice planes at resolution 30: -3.7 %).
    from softsim_warp.core.terrain import fan_triangles

    pts, counts, idx = sphere_mesh([0, 0, 0], 1.0, rings=64, segments=128)
    tris = fan_triangles(counts, idx)
    assert _grid_volume(pts, tris, 30) == pytest.approx(4.0 / 3.0 * math.pi, rel=0.03)
    pts, counts, idx = torus_mesh(1.0, 0.5)
    tris = fan_triangles(counts, idx)
    errors = []
    for res in (30, 40, 50, 60, 80):
        volume = _grid_volume(pts, tris, res)
        assert volume == pytest.approx(2 * math.pi**2 * 0.25, rel=0.03)
        errors.append(abs(volume / (2 * math.pi**2 * 0.25) - 1.0))
    # The cells cut by the surface make the error; it falls at least as the cell size (first order)
    # from resolution 30 to 80 (measured: 1.65 % to 0.019 %).
    assert errors[-1] <= errors[0] * 30 / 80


def test_box_mesh_gives_exactly_the_box_lattice(tmp_path, device):
    size = [1.0, 0.5, 0.75]
    path = write_usd(tmp_path / "box.usda", *box_mesh(size))
    meshed = build_model(_mesh_scene(path, resolution=4, rotation={"axis": [1, 1, 0], "degrees": 25.0}), device)
    box = scene_from_dict(
        {
            "simulation": {"dt": 1e-3, "frames": 1},
            "jelly": [{"resolution": [5, 3, 4], "size": size, "center": [0.0, 2.0, 0.0], "total_mass": 1.0,
                       "springs": SPRINGS, "rotation": {"axis": [1, 1, 0], "degrees": 25.0}}],
        }
    )
    ref = build_model(box, "cpu")
    assert np.array_equal(meshed.particle_q_host, ref.particle_q_host)
    assert np.array_equal(meshed.particle_mass_host, ref.particle_mass_host)
    assert np.array_equal(meshed.spring_indices_host, ref.spring_indices_host)
    assert np.array_equal(meshed.spring_rest_host, ref.spring_rest_host)
    assert meshed.lattice is not None  # the whole box: the lattice force path


def _placed(asset, j, rot, center):
    return ((asset.points - np.asarray(j["_mesh_center"])) * j["_mesh_scale"]) @ rot.T + np.asarray(center)


@pytest.fixture
def ball(tmp_path):
    pts, counts, idx = sphere_mesh([0.3, 0.1, -0.2], 0.7, rings=12, segments=16)
    return write_usd(tmp_path / "ball.usda", pts, counts, idx, uv=True)


def test_undeformed_jelly_reproduces_the_asset(ball):
    rotation = {"axis": [0.2, 1.0, 0.3], "degrees": 40.0}
    scene = _mesh_scene(ball, resolution=9, size=0.6, rotation=rotation)
    model = build_model(scene, "cpu")
    info = model.jellies[0]
    assert 0 < info.particle_count < np.prod(info.shape)
    assert model.particle_mass_host.sum() == pytest.approx(1.0, rel=1e-12)  # total_mass over the points inside
    surface = SurfaceMap.of(info)
    x32 = model.particle_q_host.astype(np.float32)
    got = surface.points(x32).astype(np.float64)
    j = scene.jellies[0]
    want = _placed(load_mesh(ball), j, rotation_matrix(j["rotation"]["axis"], 40.0), j["center"])
    # Float32 particles (a few ulps of |x| ~ 2 m, weights up to ~3 when extrapolating).
    assert np.abs(got - want).max() <= 16 * np.finfo(np.float32).eps * 2.5


def test_uniform_stretch_stretches_the_surface_exactly(ball):
    scene = _mesh_scene(ball, resolution=7, size=0.6)
    model = build_model(scene, "cpu")
    emb = model.jellies[0].embedding
    x = model.particle_q_host
    a = np.array([[1.3, 0.2, 0.0], [0.0, 0.8, 0.1], [0.05, 0.0, 1.1]])
    b = np.array([0.5, -1.0, 2.0])
    rest = emb.points(x)
    # Trilinear weights sum to one and reproduce affine maps: S(A x + b) = A S(x) + b.
    assert np.allclose(emb.weights.sum(1), 1.0, atol=1e-12)
    assert np.abs(emb.points(x @ a.T + b) - (rest @ a.T + b)).max() < 1e-12


def test_surface_in_usd_has_asset_topology_uvs_and_normals(tmp_path, ball):
    scene_file = tmp_path / "s.toml"
    scene_file.write_text(
        'name = "s"\n[simulation]\ndt = 1e-3\nframes = 2\nfps = 30\n'
        '[[jelly]]\nmesh = "ball.usda"\nresolution = 6\nsize = 0.5\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.5\n'
        "springs.structural = { ks = 50.0 }\nsprings.shear = { ks = 50.0 }\n"
    )
    out = tmp_path / "o.usda"
    assert cli.main(["run", str(scene_file), "--quiet", "--out", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    surf = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Jelly_0/Surface"))
    src_stage = Usd.Stage.Open(ball)
    src = UsdGeom.Mesh(src_stage.GetPrimAtPath("/Asset"))
    assert list(surf.GetFaceVertexIndicesAttr().Get()) == list(src.GetFaceVertexIndicesAttr().Get())
    st = UsdGeom.PrimvarsAPI(surf).GetPrimvar("st")
    assert st.GetInterpolation() == "faceVarying"
    assert np.array_equal(np.array(st.Get()), np.array(UsdGeom.PrimvarsAPI(src).GetPrimvar("st").Get()))
    assert surf.GetNormalsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    assert len(surf.GetVelocitiesAttr().Get(2)) == len(src.GetPointsAttr().Get())


def test_obj_through_trimesh(tmp_path):
    pytest.importorskip("trimesh")
    pts, counts, idx = box_mesh([1.0, 2.0, 1.0])
    tris = [f[list(k)] for f in np.reshape(idx, (6, 4)) for k in ((0, 1, 2), (0, 2, 3))]
    obj = tmp_path / "box.obj"
    obj.write_text("".join(f"v {p[0]} {p[1]} {p[2]}\n" for p in pts) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in tris))
    a = load_mesh(str(obj))
    assert a.closed and a.volume() == pytest.approx(2.0)
    model = build_model(_mesh_scene(str(obj), resolution=4), "cpu")
    assert model.jellies[0].shape == (3, 5, 3) and model.particle_count == 45


def test_missing_trimesh_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "trimesh", None)
    (tmp_path / "a.stl").write_text("solid x\nendsolid x\n")
    line = _error(capsys, tmp_path, 'mesh = "a.stl"\nresolution = 4\n')
    assert "jelly.0.mesh" in line and "pip install 'softsim-warp[mesh]'" in line


def _error(capsys, tmp_path, jelly_keys):
    p = tmp_path / "s.toml"
    p.write_text(
        'name = "s"\n[simulation]\ndt = 1e-3\nframes = 1\n'
        '[[jelly]]\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.1\nsprings.structural = { ks = 50.0 }\n' + jelly_keys
    )
    code = cli.main(["run", str(p), "--quiet", "--out", str(tmp_path / "o.usdc")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    return err[0]


def _warning(capsys, tmp_path, jelly_keys):
    p = tmp_path / "s.toml"
    p.write_text(
        'name = "s"\n[simulation]\ndt = 1e-3\nframes = 1\n'
        '[[jelly]]\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.1\nsprings.structural = { ks = 50.0 }\n' + jelly_keys
    )
    code = cli.main(["run", str(p), "--quiet", "--out", str(tmp_path / "o.usdc")])
    err = capsys.readouterr().err.strip().splitlines()
    warnings = [line for line in err if line.startswith("warning: ")]
    assert code == 0 and len(warnings) == 1, err
    return warnings[0]


def test_bad_jelly_meshes_are_one_line_errors(tmp_path, capsys):
    line = _error(capsys, tmp_path, 'mesh = "missing.usda"\nresolution = 4\n')
    assert "jelly.0.mesh" in line and "no such mesh file" in line and "missing.usda" in line
    empty = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(empty, "/X")
    empty.GetRootLayer().Save()
    line = _error(capsys, tmp_path, 'mesh = "empty.usda"\nresolution = 4\n')
    assert "jelly.0.mesh" in line and "no Mesh prim" in line
    # Open: a box without its top face; non-manifold: a closed box with one face twice. Both have a
    # clear inside by the winding number (5/6 at the open box's centre, 1 to 3/2 in the other): jellies,
    # with one warning line each (tests/test_surface_contact.py refuses meshes without one).
    pts, counts, idx = box_mesh([1, 1, 1])
    write_usd(tmp_path / "open.usda", pts, counts[:5], idx[:20])
    line = _warning(capsys, tmp_path, 'mesh = "open.usda"\nresolution = 4\n')
    assert "jelly.0.mesh" in line and "open (4 edges on one face only)" in line and "open.usda" in line
    write_usd(tmp_path / "nm.usda", pts, counts + [4], idx + idx[:4])
    line = _warning(capsys, tmp_path, 'mesh = "nm.usda"\nresolution = 4\n')
    assert "jelly.0.mesh" in line and "non-manifold (5 edges shared by more than two faces)" in line  # a quad: 4 sides and its diagonal
    # A thin plate (1 x 0.01 x 1) with 4 cells along its longest side (0.25 m each).
    write_usd(tmp_path / "thin.usda", *box_mesh([1, 0.01, 1]))
    line = _error(capsys, tmp_path, 'mesh = "thin.usda"\nresolution = 4\n')
    assert "jelly.0.resolution" in line and "smaller than one lattice cell" in line
    write_usd(tmp_path / "ok.usda", *box_mesh([1, 1, 1]))
    line = _error(capsys, tmp_path, 'mesh = "ok.usda"\nresolution = 4\nspacing = 0.1\n')
    assert "jelly.0.spacing" in line and "not both" in line
    line = _error(capsys, tmp_path, 'mesh = "ok.usda"\nresolution = 4\nmesh_prim = "/Nope"\n')
    assert "jelly.0.mesh_prim" in line and "/Nope" in line
    line = _error(capsys, tmp_path, 'resolution = 4\nsize = 1.0\nspacing = 0.1\n')
    assert "jelly.0.spacing" in line and "only a mesh jelly" in line


def test_coarse_lattice_still_holds_the_whole_surface():
    # The built-in mesh_pile's torus at 4 cells along its 0.5 m: the tube (0.15 m) is under 2 cells
    # thick and no lattice point lies inside it, yet the cells its surface passes through make the
    # jelly, and every vertex is a convex combination of one kept cell's corners that gives it back.
    from softsim_warp.io.scene import load_scene

    scene = load_scene("mesh_pile", ["jelly.1.resolution=4"])
    model = build_model(scene, "cpu")
    info = model.jellies[1]
    emb = info.embedding
    assert emb.weights.min() >= 0.0 and np.allclose(emb.weights.sum(axis=1), 1.0, atol=1e-12)
    assert emb.corners.min() >= 0 and emb.corners.max() < info.particle_count
    x = model.particle_q_host[info.particle_start : info.particle_start + info.particle_count]
    j = scene.jellies[1]
    asset = load_mesh(j["mesh"])
    rot = rotation_matrix(j["rotation"]["axis"], j["rotation"]["degrees"])
    assert np.abs(emb.points(x) - _placed(asset, j, rot, j["center"])).max() < 1e-12


def test_preview_shows_mesh_jelly_and_mesh_terrain(tmp_path):
    # mesh_drop at a coarse lattice: the character (orange, deforming Surface) over the stairs (grey).
    from matplotlib.colors import rgb_to_hsv
    from matplotlib.image import imread

    from softsim_warp.io.preview import render_png

    out = tmp_path / "m.usdc"
    assert cli.main(["run", "mesh_drop", "--set", "jelly.0.resolution=6", "--frames", "1", "--quiet",
                     "--out", str(out)]) == 0
    png = tmp_path / "m.png"
    render_png(out, png, size=(320, 240))
    rgb = imread(str(png))[..., :3].astype(np.float64)
    hsv = rgb_to_hsv(rgb / rgb.max())
    orange = (hsv[..., 0] > 0.03) & (hsv[..., 0] < 0.11) & (hsv[..., 1] > 0.5) & (hsv[..., 2] > 0.15)
    grey = (hsv[..., 1] < 0.1) & (hsv[..., 2] > 0.2) & (hsv[..., 2] < 0.8)
    assert orange.mean() > 0.005 and grey.mean() > 0.1


def _builder_model(scene, device, precision="float64", masked=True):
    """The scene's model on the masked path on any device (finalize alone takes it on CUDA only),
    or, ``masked=False``, on the spring list."""
    from softsim_warp.core.model import ModelBuilder, populate

    b = ModelBuilder(scene.sim["gravity"])
    b.device = device
    populate(b, scene.data)
    if not masked:
        return b.finalize(device, precision, force_path="springs")
    return b.finalize(device, precision, masked_kernel="gather")


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_masked_lattice_forces_equal_the_spring_list(tmp_path, device, ball, precision):
    # A mesh jelly and a box jelly in one model: neither is a whole-lattice model, so the masked
    # path gathers both; its forces must be the spring list's, spring for spring (the same
    # spring_force arithmetic), summed in another order: equal to the sum's rounding.
    import warp as wp

    from softsim_warp.core.forces import eval_forces

    data = {
        "simulation": {"dt": 1e-3, "frames": 1},
        "jelly": [
            {"mesh": ball, "resolution": 7, "size": 0.6, "center": [0.0, 2.0, 0.0], "total_mass": 1.0, "springs": SPRINGS},
            {"resolution": [3, 4, 2], "size": [0.3, 0.4, 0.1], "center": [2.0, 2.0, 0.0], "total_mass": 0.5,
             "springs": {"structural": {"ks": 80.0, "kd": 0.3}, "bending": {"ks": 20.0, "kd": 0.1}}},
        ],
    }
    model = _builder_model(scene_from_dict(data), device, precision)
    assert model.masked is not None and model.lattice is None
    rng = np.random.default_rng(7)
    n = model.particle_count
    q = model.particle_q_host + 0.02 * rng.standard_normal((n, 3))
    qd = rng.standard_normal((n, 3))
    qa = wp.array(q, dtype=model.vec3, device=device)
    qda = wp.array(qd, dtype=model.vec3, device=device)
    f = wp.zeros(n, dtype=model.vec3, device=device)
    f.fill_(model.vec3(float("inf"), float("inf"), float("inf")))  # poisoned: every entry must be written
    eval_forces(model, qa, qda, f)
    masked = f.numpy().astype(np.float64)
    springs = _builder_model(scene_from_dict(data), device, precision, masked=False)
    assert springs.masked is None
    eval_forces(springs, qa, qda, f)
    ref = f.numpy().astype(np.float64)
    eps = np.finfo(np.float32 if precision == "float32" else np.float64).eps
    # Each particle sums up to 32 spring forces of magnitude up to ks |dx| + kd |dv|.
    scale = np.abs(ref).max()
    assert np.isfinite(masked).all()
    assert np.abs(masked - ref).max() <= 64 * eps * scale


def test_masked_lattice_trajectory_matches_the_spring_list(device, ball):
    # A mesh jelly falling and ringing for 200 steps, float64: the two paths agree to rounding growth.
    scene = _mesh_scene(ball, resolution=6, size=0.5, velocity=[0.0, -1.0, 0.5], angular_velocity=[3.0, 0.0, 1.0])
    out = []
    for masked in (True, False):
        model = _builder_model(scene, device, masked=masked)
        from softsim_warp.core.stepper import make_integrator

        integ = make_integrator("rk4", model)
        s0, s1 = model.state(), model.state()
        for _ in range(200):
            integ.step(s0, s1, 1e-3)
            s0, s1 = s1, s0
        out.append(s0.particle_q.numpy())
    assert np.abs(out[0] - out[1]).max() < 1e-10


def test_uv_seam_split_vertices_still_make_a_closed_mesh(tmp_path):
    # An exporter splits vertices along UV seams: a cube with 24 vertices (4 per face) is closed.
    pts, counts, idx = box_mesh([1.0, 1.0, 1.0])
    faces = np.reshape(idx, (6, 4))
    split = np.concatenate([pts[f] for f in faces])
    write_usd(tmp_path / "split.usda", split, counts, np.arange(24))
    a = load_mesh(str(tmp_path / "split.usda"))
    assert a.points.shape == (24, 3) and a.closed and a.volume() == pytest.approx(1.0)


def test_demo_assets_are_what_the_script_makes(tmp_path):
    # scenes/assets/*.usda are generated (assets/make_assets.py), never edited or downloaded.
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, str(root / "assets" / "make_assets.py"), "--out", str(tmp_path)], check=True,
                   capture_output=True)
    made = sorted(p.name for p in tmp_path.glob("*.usda"))
    assert made == sorted(p.name for p in (root / "scenes" / "assets").glob("*.usda"))
    for name in made:
        assert (tmp_path / name).read_bytes() == (root / "scenes" / "assets" / name).read_bytes(), name
        asset = load_mesh(str(tmp_path / name))
        if name == "blob_open.usda":  # the blob with its base cut off
            assert asset.edge_uses == (64, 0)
        elif name != "bumpy_floor.usda":  # the floor is an open sheet facing up; the rest are closed
            assert asset.closed and asset.volume() > 0
    assert (tmp_path / "bracket.stl").read_bytes() == (root / "scenes" / "assets" / "bracket.stl").read_bytes()


def _fused_masked_run(scene, method, precision, steps, path):
    """Positions and velocities after ``steps`` steps on ``path``: "fused" (the masked fused stage,
    forced on the CPU), "springs" (the spring list, unfused, contact as its own kernels)."""
    from softsim_warp.core.integrators import ExplicitIntegrator

    model = _builder_model(scene, "cpu", precision, masked=path != "springs")
    integ = ExplicitIntegrator(model, method)
    assert integ.fused == (path == "fused")
    s0, s1 = model.state(), model.state()
    for _ in range(steps):
        integ.step(s0, s1, 1e-3)
        s0, s1 = s1, s0
    return model, s0.particle_q.numpy().astype(np.float64), s0.particle_qd.numpy().astype(np.float64)


def _plane_scene(ball, two):
    """A tumbling mesh jelly that lands on a plane during the run; ``two``: with a box jelly beside it
    of other springs and mass (per-jelly tables, the generic stage)."""
    jelly = {"mesh": ball, "resolution": 6, "size": 0.5, "center": [0.0, 2.0, 0.0], "total_mass": 1.0,
             "springs": SPRINGS, "velocity": [0.0, -1.0, 0.5], "angular_velocity": [3.0, 0.0, 1.0]}
    jellies = [jelly]
    if two:
        jellies.append({"resolution": [3, 4, 2], "size": [0.3, 0.4, 0.1], "center": [2.0, 1.9, 0.0], "total_mass": 0.5,
                        "velocity": [0.0, -1.5, 0.0],
                        "springs": {"structural": {"ks": 80.0, "kd": 0.3}, "bending": {"ks": 20.0, "kd": 0.1}}})
    plane = {"point": [0.0, 1.7, 0.0], "normal": [0.0, 1.0, 0.0], "restitution": 0.5, "friction": 0.3}
    return scene_from_dict({"simulation": {"dt": 1e-3, "frames": 1}, "jelly": jellies, "plane": [plane]})


@pytest.mark.parametrize("method", ["symplectic", "rk4"])
@pytest.mark.parametrize("case", ["two jellies", "one jelly"])
def test_fused_masked_stage_matches_the_spring_list(ball, method, case):
    # The fused masked stage (neighbours through the index grid, the stage update and plane contact in
    # one kernel) against the spring list with separate force, update and contact kernels, float64,
    # 250 steps of a tumbling jelly that lands on a plane: the same trajectory to rounding growth.
    two = case == "two jellies"
    scene = _plane_scene(ball, two)
    model, q, qd = _fused_masked_run(scene, method, "float64", 250, "fused")
    _, q_ref, qd_ref = _fused_masked_run(scene, method, "float64", 250, "springs")
    # The plane acted: nothing below it, and the jelly's mean height is far above free fall's, which
    # would have taken it 0.56 m down (v0 = -1 m/s, g = 9.8 m/s^2, 0.25 s).
    assert q_ref[:, 1].min() > 1.7 - 1e-3
    assert q_ref[:, 1].mean() > model.particle_q_host[:, 1].mean() - 0.4
    assert np.abs(q - q_ref).max() < 1e-11
    assert np.abs(qd - qd_ref).max() < 1e-9


@pytest.mark.parametrize("method", ["symplectic", "rk4"])
def test_fused_masked_stage_float32(ball, method):
    # float32 build of the stage: the float64 spring list's trajectory to float32 rounding growth
    # over 60 steps (the jelly lands at step ~50).
    scene = _plane_scene(ball, False)
    _, q_ref, _ = _fused_masked_run(scene, method, "float64", 60, "springs")
    _, q, _ = _fused_masked_run(scene, method, "float32", 60, "fused")
    assert np.abs(q - q_ref).max() < 2e-5
