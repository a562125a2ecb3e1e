"""The visible surface of a mesh jelly collides, and imperfect meshes load.

A mesh jelly's particles are the corners of every lattice cell its solid touches, and each surface
vertex is a convex combination of the corners of the cell that holds it (core/voxelize.py). The
drops below measure the written Surface at every frame with a point-in-mesh test of their own
(the generalized winding number and point-triangle distances in NumPy, nothing of the contact
code), and each has a control: the embedding this replaced (only the points inside the mesh, each
vertex tied to the nearest cell with eight corners inside, its weights extrapolating), under which
the same drop pushes the surface through the floor and into the other jelly.
"""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from softsim_warp.commands import cli
from softsim_warp.core import lattice
from softsim_warp.core import voxelize as vx
from softsim_warp.core.mesh_assets import load_mesh
from softsim_warp.core.model import build_model
from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.terrain import fan_triangles, signed_volume, sphere_mesh
from softsim_warp.io.penetration import distances_to_triangles, winding_numbers
from softsim_warp.io.scene import scene_from_dict
from softsim_warp.io.simulate import Simulator

ROOT = Path(__file__).resolve().parents[1]
SPRINGS = {"structural": {"ks": 120.0, "kd": 0.15}, "shear": {"ks": 120.0, "kd": 0.15}, "bending": {"ks": 60.0, "kd": 0.08}}
DT = 2.5e-4


def make_assets():
    spec = importlib.util.spec_from_file_location("make_assets", ROOT / "assets" / "make_assets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def assets(tmp_path_factory):
    out = tmp_path_factory.mktemp("assets")
    make_assets().main(["--out", str(out)])
    return out


# -- An independent point-in-mesh test ------------------------------------------------------------


def distance_to_triangles(points, triangles, queries) -> np.ndarray:
    """Distance from each query point to the nearest point of the triangle mesh."""
    return distances_to_triangles(points, triangles, queries)


def test_independent_point_in_mesh_on_a_sphere():
    pts, counts, idx = sphere_mesh([0.1, 0.2, 0.3], 1.0, rings=24, segments=32)
    tris = fan_triangles(counts, idx)
    q = np.array([[0.1, 0.2, 0.3], [0.1, 0.9, 0.3], [0.1, 1.4, 0.3], [3.0, 0.0, 0.0]])
    assert np.allclose(winding_numbers(pts, tris, q), [1, 1, 0, 0], atol=1e-9)
    sagitta = 1.0 - math.cos(math.pi / 24)
    assert distance_to_triangles(pts, tris, q) == pytest.approx([1.0, 0.3, 0.2, np.linalg.norm([2.9, -0.2, -0.3]) - 1],
                                                                abs=sagitta)


# -- The interior-only embedding, for the controls ----------------------------------------------------------


def interior_embedding(monkeypatch):
    """Make mesh jellies without the surface embedding: the lattice points inside the mesh only, each vertex in
    the nearest cell with all eight corners inside (trilinear weights extrapolating outside it)."""
    kept = {}

    def inside_only(points, triangles, shape, size, inside):
        kept["mask"] = np.asarray(inside, dtype=bool)
        return kept["mask"]

    def nearest_full_cell(points, shape, size):
        shape = [int(n) for n in shape]
        ncell = [n - 1 for n in shape]
        present = kept["mask"].reshape(shape)
        full = np.ones(ncell, dtype=bool)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    full &= present[dx : dx + ncell[0], dy : dy + ncell[1], dz : dz + ncell[2]]
        axes = vx.lattice_axes(shape, size)
        centres = np.stack(np.meshgrid(*[0.5 * (x[1:] + x[:-1]) for x in axes], indexing="ij"), -1)[full]
        cells = np.argwhere(full)
        near = np.argmin(((points[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        cell = cells[near]
        t = np.stack([(points[:, a] - axes[a][cell[:, a]]) / (axes[a][1] - axes[a][0]) for a in range(3)], axis=1)
        corners, weights = [], []
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    corners.append(lattice.lattice_index(cell[:, 0] + dx, cell[:, 1] + dy, cell[:, 2] + dz, shape))
                    w = np.ones(len(points))
                    for a, d in enumerate((dx, dy, dz)):
                        w = w * (t[:, a] if d else 1.0 - t[:, a])
                    weights.append(w)
        return np.stack(corners, axis=1).astype(np.int64), np.stack(weights, axis=1)

    monkeypatch.setattr(vx, "solid_mask", inside_only)
    monkeypatch.setattr(vx, "embed", nearest_full_cell)
    monkeypatch.setattr(vx, "_LATTICES", {})


# -- Drops ------------------------------------------------------------------------------------------


def _jelly(path, center, resolution, **extra):
    return {"mesh": str(path), "resolution": resolution, "center": center, "total_mass": 0.5, "springs": SPRINGS, **extra}


def surfaces_per_frame(jellies, frames, fps=30):
    """Drop ``jellies`` onto the plane y = 0; the Surface vertices of each jelly at every written
    frame, and the (triangles, size) of each asset."""
    scene = scene_from_dict({
        "simulation": {"dt": DT, "frames": frames, "fps": fps, "gravity": [0.0, -9.8, 0.0]},
        "jelly": jellies,
        "plane": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0], "restitution": 0.2, "friction": 0.5}],
    })
    model = build_model(scene, "cpu")
    infos = model.jellies
    frames_out = []

    class Writer:
        def write_frame(self, k, t, positions, metrics):
            frames_out.append([
                j.embedding.points(positions[j.particle_start : j.particle_start + j.particle_count]) for j in infos
            ])

    result = Simulator(model, make_integrator("symplectic", model), DT, fps, frames).run([Writer()])
    assert not result.exploded and len(frames_out) == frames + 1
    shapes = []
    for j in infos:
        tris = fan_triangles(j.embedding.counts, j.embedding.indices)
        rest = frames_out[0][len(shapes)]
        shapes.append((tris, float(np.ptp(rest, axis=0).max())))
    return frames_out, shapes


def deepest_below_plane(frames_out, shapes, k=0):
    """Per frame, the depth of jelly k's deepest Surface vertex below y = 0 over its size."""
    return np.array([-f[k][:, 1].min() / shapes[k][1] for f in frames_out])


def test_thin_legs_stay_above_the_plane(assets, monkeypatch):
    # The critter (legs 0.04 m and ears 0.03 m across, about one 0.056 m cell at 12 cells along its
    # 0.675 m) dropped tilted onto a plane for 1.5 s: every vertex of every frame above the plane
    # within 1 % of its size. It lands: some frame brings the lowest vertex within a cell of the plane.
    critter = assets / "critter.usda"
    jelly = _jelly(critter, [0.0, 0.6, 0.0], 12, rotation={"axis": [1.0, 0.0, 1.0], "degrees": 10.0})
    frames_out, shapes = surfaces_per_frame([jelly], 45)
    depth = deepest_below_plane(frames_out, shapes)
    assert depth.max() <= 0.01, depth.max()
    h = 0.675 / 12
    assert depth.max() > -h / shapes[0][1]
    # The embedding is convex: weights in [0, 1] summing to 1.
    emb = build_model(scene_from_dict({"simulation": {"dt": DT, "frames": 1}, "jelly": [jelly]}), "cpu").jellies[0].embedding
    assert emb.weights.min() >= 0.0 and emb.weights.max() <= 1.0
    assert np.allclose(emb.weights.sum(axis=1), 1.0, atol=1e-12)
    # Control: with the interior embedding the same drop puts the legs through the plane.
    interior_embedding(monkeypatch)
    frames_out, shapes = surfaces_per_frame([jelly], 45)
    assert deepest_below_plane(frames_out, shapes).max() > 0.05


def test_upright_critter_stands_on_its_feet(assets):
    # Dropped upright from 8 cm, after 1.5 s the critter stands on the plane: its lowest vertices are
    # its four foot tips, touching (within 1 % of its size; the lattice's lowest plane runs through
    # them, so no cell reaches below the feet) and none below.
    jelly = _jelly(assets / "critter.usda", [0.0, 0.40, 0.0], 12)
    frames_out, shapes = surfaces_per_frame([jelly], 45)
    rest, last = frames_out[0][0], frames_out[-1][0]
    assert abs(last[:, 1].min()) <= 0.01 * shapes[0][1], last[:, 1].min()
    feet = np.argsort(rest[:, 1])[:4]
    legs = {(np.sign(x), np.sign(z)) for x, z in rest[feet][:, [0, 2]] - rest.mean(axis=0)[[0, 2]]}
    assert len(legs) == 4  # one tip per leg
    assert np.all(last[feet, 1] <= 0.01 * shapes[0][1])


@pytest.mark.parametrize("terrain", ["sphere", "bowl"])
def test_thin_legs_stay_out_of_curved_terrain(assets, terrain):
    # The critter dropped onto a sphere (r = 0.4 m), and into a bowl (r = 0.8 m): the depth of its
    # deepest Surface vertex in the solid, from the analytic distance, within 1 % of its size at
    # every frame; it touches (within a cell). A vertex is a convex combination of particles outside
    # the sphere, which can lie inside it only by the sagitta of a cell's diagonal, (h sqrt 3)^2 / 8 r
    # = 3 mm here; inside the bowl's sphere a convex combination of points inside stays inside.
    h = 0.675 / 12
    if terrain == "sphere":
        extra = {"sphere": [{"center": [0.0, 0.0, 0.0], "radius": 0.4}],
                 "plane": [{"point": [0.0, -1.0, 0.0], "normal": [0.0, 1.0, 0.0]}]}
        center, depth_of = [0.05, 0.9, 0.0], lambda p: 0.4 - np.linalg.norm(p, axis=1)
    else:
        extra = {"bowl": [{"center": [0.0, 0.8, 0.0], "radius": 0.8, "cut_height": 0.8}]}
        center, depth_of = [0.2, 0.5, 0.0], lambda p: np.linalg.norm(p - [0.0, 0.8, 0.0], axis=1) - 0.8
    scene = scene_from_dict({"simulation": {"dt": DT, "frames": 30, "fps": 30},
                             "jelly": [_jelly(assets / "critter.usda", center, 12)], **extra})
    model = build_model(scene, "cpu")
    emb = model.jellies[0].embedding
    depth = []

    class Writer:
        def write_frame(self, k, t, positions, metrics):
            depth.append(depth_of(emb.points(positions)).max() / 0.675)

    assert not Simulator(model, make_integrator("symplectic", model), DT, 30, 30).run([Writer()]).exploded
    assert max(depth) <= 0.01 and max(depth) > -h / 0.675, depth


def test_blob_stays_out_of_the_stairs_mesh():
    # mesh_drop for 1.5 s: the blob tumbles onto the stairs (a closed mesh). No Surface vertex of
    # any frame inside the stairs (winding number above 1/2) deeper than 1 % of the blob's 0.4 m.
    from softsim_warp.io.scene import load_scene

    scene = load_scene("mesh_drop", ["simulation.duration=1.5"])
    model = build_model(scene, "cpu")
    emb = model.jellies[0].embedding
    stairs = load_mesh(scene.data["mesh"][0]["path"]).outward()
    depth = []

    class Writer:
        def write_frame(self, k, t, positions, metrics):
            p = emb.points(positions)
            inside = p[winding_numbers(stairs.points, stairs.triangles, p) > 0.5]
            depth.append(distance_to_triangles(stairs.points, stairs.triangles, inside).max() if len(inside) else 0.0)
            gap.append(distance_to_triangles(stairs.points, stairs.triangles, p[::5]).min())

    gap = []
    sim = Simulator(model, make_integrator("symplectic", model), scene.sim["dt"], 20, 30)
    assert not sim.run([Writer()]).exploded
    assert max(depth) <= 0.01 * 0.4, max(depth)
    assert min(gap) < 2 * 0.4 / 10  # it lands on them: within two cells


def _overlap(frames_out, shapes, a, b, stop_above=np.inf):
    """Per frame, the depth of jelly a's deepest Surface vertex inside jelly b's Surface, over the
    size of jelly b (winding number above 1/2; the distance to b's nearest face); the frames up to
    the first deeper than ``stop_above``."""
    depth = []
    for f in frames_out:
        if depth and depth[-1] > stop_above:
            break
        pa, pb = f[a], f[b]
        lo, hi = pb.min(axis=0), pb.max(axis=0)
        near = np.flatnonzero(np.all((pa >= lo) & (pa <= hi), axis=1))
        d = 0.0
        if near.size:
            inside = near[winding_numbers(pb, shapes[b][0], pa[near]) > 0.5]
            if inside.size:
                d = distance_to_triangles(pb, shapes[b][0], pa[inside]).max()
        depth.append(d / shapes[b][1])
    return np.array(depth)


def test_two_jellies_surfaces_do_not_overlap(assets, monkeypatch):
    # The critter dropped onto the open blob on the plane: at every frame neither Surface holds a
    # vertex of the other deeper than 1 % of its size. They meet: each Surface lies within a cell of
    # its particles, and contact keeps the particles a pair distance (the mean spacing) apart, so at
    # rest on each other the Surfaces are less than 1.5 (h1 + h2) apart.
    jellies = [
        _jelly(assets / "blob_open.usda", [0.0, 0.32, 0.0], 8, size=0.5),
        _jelly(assets / "critter.usda", [0.05, 0.95, 0.0], 10, rotation={"axis": [0.0, 0.0, 1.0], "degrees": 20.0}),
    ]
    frames_out, shapes = surfaces_per_frame(jellies, 24)
    into_blob, into_critter = _overlap(frames_out, shapes, 1, 0), _overlap(frames_out, shapes, 0, 1)
    assert into_blob.max() <= 0.01 and into_critter.max() <= 0.01, (into_blob.max(), into_critter.max())
    gap = min(float(np.min(np.linalg.norm(f[1][::7, None, :] - f[0][None, ::7, :], axis=2))) for f in frames_out)
    h1, h2 = 0.5 / 8, 0.675 / 10
    assert gap < 1.5 * (h1 + h2)
    for k in (0, 1):
        assert deepest_below_plane(frames_out, shapes, k).max() <= 0.01
    # Control: the interior embedding lets the critter's surface sink into the blob's.
    interior_embedding(monkeypatch)
    frames_out, shapes = surfaces_per_frame(jellies, 24)
    assert _overlap(frames_out, shapes, 1, 0, stop_above=0.02).max() > 0.02


# -- Imperfect meshes -------------------------------------------------------------------------------


def _grid(points, resolution):
    lo, hi = points.min(0), points.max(0)
    h = (hi - lo).max() / resolution
    shape = [int(math.ceil(e / h)) + 2 for e in hi - lo]
    return shape, [(n - 1) * h for n in shape], h, 0.5 * (lo + hi)


def test_open_mesh_volume_is_the_closed_originals(assets):
    # The blob with its base cut off (a hole 0.23 m across, 64 open edges) against the closed blob,
    # voxelised on one lattice: the points whose winding number is above 1/2 fill the same volume
    # within 5 %, and both are within 5 % of the closed mesh's exact volume. Reversed, the open mesh
    # is turned outward again (by its volume about its centre) and gives the same inside.
    closed = load_mesh(str(assets / "blob.usda")).outward()
    hole = load_mesh(str(assets / "blob_open.usda"))
    assert not hole.closed and hole.edge_uses == (64, 0)
    exact = signed_volume(closed.points, closed.triangles)
    for resolution in (10, 20):
        shape, size, h, center = _grid(closed.points, resolution)
        v_closed = vx.voxelize(closed.points - center, closed.triangles, shape, size, "cpu").sum() * h**3
        for mesh in (hole.outward(open_too=True), hole.reversed().outward(open_too=True)):
            v_open = vx.voxelize(mesh.points - center, mesh.triangles, shape, size, "cpu").sum() * h**3
            assert v_open == pytest.approx(v_closed, rel=0.05) and v_open == pytest.approx(exact, rel=0.05)
    assert np.array_equal(hole.reversed().outward(open_too=True).indices, hole.indices)


def _cli(capsys, argv):
    code = cli.main(argv)
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines()


def _scene_file(tmp_path, mesh, extra=""):
    path = tmp_path / "s.toml"
    path.write_text(
        '[simulation]\ndt = 2.5e-4\nframes = 1\n\n[[jelly]]\n'
        f'mesh = "{mesh}"\nresolution = 8\ncenter = [0.0, 1.0, 0.0]\ntotal_mass = 0.5\n{extra}'
        'springs.structural = { ks = 100.0, kd = 0.1 }\n'
    )
    return str(path)


def test_open_mesh_is_a_jelly_with_one_warning(tmp_path, assets, capsys):
    code, err = _cli(capsys, ["run", _scene_file(tmp_path, assets / "blob_open.usda"), "--quiet",
                              "--out", str(tmp_path / "o.usdc")])
    warnings = [line for line in err if line.startswith("warning: ")]
    assert code == 0 and len(warnings) == 1 and not any("Traceback" in line for line in err), err
    assert warnings[0] == err[0] and "jelly.0.mesh" in err[0] and "open (64 edges on one face only)" in err[0]


def test_cad_stl_with_rounding_in_shared_corners_is_closed(tmp_path, assets, capsys):
    # bracket.stl: every triangle its own corners, the zero coordinates written as +-3e-16 noise.
    # Welded exactly it would be open; welded at 1e-7 of its size it is closed, of the bracket's volume.
    stl = assets / "bracket.stl"
    assert "e-16" in stl.read_text()
    mesh = load_mesh(str(stl))
    exact_weld = np.unique(mesh.points, axis=0).shape[0]
    assert mesh.closed and np.unique(mesh.welded).size == 12 < exact_weld  # the L profile's 6 corners, twice
    assert mesh.volume() == pytest.approx(0.3 * 0.04 * 0.1 + 0.04 * 0.16 * 0.1, rel=1e-9)
    code, err = _cli(capsys, ["run", _scene_file(tmp_path, stl), "--quiet", "--out", str(tmp_path / "o.usdc")])
    assert code == 0 and not any(line.startswith("warning: ") for line in err), err


def test_sheets_are_refused_with_one_line(tmp_path, capsys):
    from tests.test_mesh_jelly import write_usd

    # A hemisphere shell (a bowl, open at its rim): winding numbers around 1/2 all through it.
    pts, counts, idx = sphere_mesh([0.0, 0.0, 0.0], 0.5, rings=16, segments=24)
    tris = fan_triangles(counts, idx)
    top = tris[(pts[tris][:, :, 1] >= -1e-9).all(axis=1)]
    write_usd(tmp_path / "dome.usda", pts, [3] * len(top), top.ravel())
    code, err = _cli(capsys, ["run", _scene_file(tmp_path, tmp_path / "dome.usda"), "--quiet",
                              "--out", str(tmp_path / "o.usdc")])
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("error: ") and "jelly.0.mesh" in err[0] and "no clear inside" in err[0]
    assert "terrain" in err[0] and "dome.usda" in err[0]
    # A flat square: no thickness at all.
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], dtype=float)
    write_usd(tmp_path / "square.usda", sq, [4], [0, 3, 2, 1])
    code, err = _cli(capsys, ["run", _scene_file(tmp_path, tmp_path / "square.usda"), "--quiet",
                              "--out", str(tmp_path / "o.usdc")])
    assert code == 2 and len(err) == 1, err
    assert "encloses no volume" in err[0] and "terrain" in err[0]


# -- Cost of loading ---------------------------------------------------------------------------------


def test_lattice_size_is_checked_before_voxelising(monkeypatch, capsys, tmp_path):
    from softsim_warp.io import resources

    def no_voxelising(*args, **kwargs):
        raise AssertionError("voxelised before the size check")

    monkeypatch.setattr(vx, "voxelize", no_voxelising)
    monkeypatch.setattr(resources, "available_host_bytes", lambda: 8 * 2**30)
    code, err = _cli(capsys, ["run", "mesh_drop", "--set", "jelly.0.resolution=250", "--frames", "1", "--quiet",
                              "--out", str(tmp_path / "o.usdc")])
    assert code == 2 and len(err) == 1 and "scene too large" in err[0] and "jelly.0.resolution" in err[0], err
    assert err[0].endswith("(got 250)")
    code, err = _cli(capsys, ["run", "mesh_drop", "--set", "jelly.0.resolution=3000", "--frames", "1", "--quiet",
                              "--out", str(tmp_path / "o.usdc")])
    assert code == 2 and len(err) == 1 and "jelly.0.resolution" in err[0] and "more than 2,147,483,647" in err[0], err
    scene = _scene_file(tmp_path, ROOT / "scenes" / "assets" / "blob.usda").replace("resolution = 8", "spacing = 1e-5")
    Path(scene).write_text(Path(scene).read_text().replace("resolution = 8", "spacing = 1e-5"))
    code, err = _cli(capsys, ["run", scene, "--quiet", "--out", str(tmp_path / "o.usdc")])
    assert code == 2 and len(err) == 1 and "jelly.0.spacing" in err[0] and "more than 2,147,483,647" in err[0], err
