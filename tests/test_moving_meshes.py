"""Moving mesh terrain ([[mesh]] with a rigid ``motion``, or ``animated = true``) against closed forms.

A mesh with a rigid motion is queried in its own frame: where the contact put it (the pose on the
device) must be NumPy's interpolation of its keys and its spin, and a flat mesh moving as a plane
moves must act as that plane does: a jelly dragged to the platform's speed by Coulomb friction
(v_x = mu (g t + v_y) while it slides, caught at 1 / (mu g)), restitution on the speed relative to
a moving wall. An animated USD asset (assets/make_assets.py ``write_animated_plate``: points and
an Xform time-sampled at different codes, in centimetres, 24 codes a second) is followed to 1e-6 m
at every step's end, and carries what rests on it at its own speed. Static mesh scenes launch
what they did.
"""

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom, UsdValidation

import softsim_warp as ss
from softsim_warp.core.errors import SceneError
from softsim_warp.core.mesh_assets import MeshAsset
from tests.helpers import rate_about_y

ROOT = Path(__file__).resolve().parent.parent
MU, G = 0.8, 9.8


def _make_assets():
    spec = importlib.util.spec_from_file_location("make_assets", ROOT / "assets" / "make_assets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MA = _make_assets()


@pytest.fixture
def plate(tmp_path):
    path = tmp_path / "animated_plate.usda"
    MA.write_animated_plate(path)
    return str(path)


def write_quad(path, normal=(0.0, 1.0, 0.0), size=8.0):
    """A one-quad USD sheet through the origin facing ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    pts = [0.5 * size * (a * u + b * v) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Quad")
    mesh.CreatePointsAttr([tuple(map(float, p)) for p in pts])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.SetDefaultPrim(mesh.GetPrim())
    stage.GetRootLayer().Save()
    return str(path)


def springs(ks, kd):
    return {name: {"ks": ks, "kd": kd} for name in ("structural", "shear", "bending")}


def jelly_scene(terrain, integrator="symplectic", precision="float32", dt=2e-4, center=(0.0, 0.05, 0.0)):
    """A small stiff jelly (3^3 particles, 0.1 m) resting on the given terrain."""
    return ss.scene_from_dict({
        "simulation": {"integrator": integrator, "dt": dt, "duration": 1.0, "gravity": [0.0, -G, 0.0],
                       "precision": precision},
        "jelly": [{"resolution": 3, "size": 0.1, "center": list(center), "particle_mass": 0.01,
                   "springs": springs(1000.0, 0.5)}],
        **terrain,
    })


def stepper(sc, **kw):
    model = ss.build_model(sc, "cpu")
    return model, ss.Stepper(model, ss.make_integrator(sc.sim["integrator"], model), sc.sim["dt"], **kw)


def rodrigues(axis_angle):
    angle = np.linalg.norm(axis_angle)
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(axis_angle) / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


KEYS = [(0.0, [0.0, 0.0, 0.0]), (0.05, [0.1, 0.02, 0.0]), (0.12, [0.3, -0.01, 0.05]), (0.2, [0.3, 0.03, -0.1])]


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_keyframed_mesh_is_where_its_keys_put_it(tmp_path, precision):
    """At every step's end the pose the mesh contact used (its motion's centre and turn on the
    device) carries the mesh's vertices where NumPy's interpolation of the keys and the spin
    (Rodrigues, 20 deg/s about z through (0.5, 0, 0)) puts them, to 1e-6 m."""
    quad = write_quad(tmp_path / "quad.usda", size=2.0)
    center = np.array([0.5, 0.0, 0.0])
    motion = {"keyframes": [{"time": t, "offset": d} for t, d in KEYS],
              "spin": {"axis": [0.0, 0.0, 1.0], "degrees_per_second": 20.0, "center": center.tolist()}}
    sc = jelly_scene({"mesh": [{"path": quad, "motion": motion}]}, precision=precision, center=(0.0, 0.3, 0.0))
    model, st = stepper(sc)
    rest = model.meshes[0]["asset"].points
    tm = st.integrator.run.terrain  # the poses the contact used, the run's own
    times = np.array([k[0] for k in KEYS])
    offsets = np.array([k[1] for k in KEYS])
    worst = 0.0
    for k in range(round(0.25 / sc.sim["dt"])):
        st.advance(1)
        t = (k + 1) * sc.sim["dt"]
        d = np.array([np.interp(t, times, offsets[:, c]) for c in range(3)])
        expected = center + d + (rest - center) @ rodrigues([0.0, 0.0, math.radians(20.0) * t]).T
        c1 = tm.center_now.numpy()[0].astype(np.float64)
        used = c1 + (rest - center) @ rodrigues(tm.turn_now.numpy()[0].astype(np.float64)).T
        worst = max(worst, float(np.abs(used - expected).max()))
    assert worst < 1e-6, worst
    # The mesh's own vertices never move: it is queried in its frame (no refit, graph-captured).
    points = st.integrator.run.meshes.mesh_points
    np.testing.assert_array_equal(points.numpy(), rest.astype(points.numpy().dtype))
    assert st.use_graph and model.mesh_animation is None


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_animated_usd_mesh_follows_its_samples(plate, precision):
    """The points the contact used (the model's and the BVH's) at every step's end are the asset's
    samples interpolated by NumPy (assets/make_assets.py ``animated_plate_world``: the points'
    samples every 12 codes, the Xform's every 24, at 24 codes a second, in centimetres) to 1e-6 m,
    across the samples, between them and after the last (held)."""
    sc = jelly_scene({"mesh": [{"path": plate, "animated": True}]}, precision=precision, dt=1e-3,
                     center=(0.0, 3.0, 0.0))
    _, st = stepper(sc)
    assert not st.use_graph  # a refit is host work: no graph
    worst = 0.0
    for k in range(2200):
        st.advance(1)
        if k % 7 == 0 or k > 2190:
            expected = MA.animated_plate_world((k + 1) * 1e-3)
            poses = st.integrator.run.meshes  # the vertices and BVH the contact used, the run's own
            worst = max(worst, float(np.abs(poses.mesh_points.numpy() - expected).max()),
                        float(np.abs(poses.mesh_bvh[0].points.numpy() - expected).max()))
    assert worst < 1e-6, worst


def test_animated_mesh_carries_what_rests_on_it(plate):
    """The plate's Xform carries it at 0.2 m/s along x while its points tilt about its line x = 0
    (slope 0.1 at 0.5 s to -0.05 at 1 s: each vertex moves at ds/dt x = -0.3 x m/s along y).
    Friction (mu g = 7.8 m/s^2) brings the jelly resting there to the surface's velocity at its
    contact points within 0.03 s: at t = 0.9 s the bottom layer moves at (0.2, -0.3 (x - 0.18))
    m/s (the plate's vertices' velocity interpolated there); it sits on the plate, not in it."""
    sc = jelly_scene({"mesh": [{"path": plate, "animated": True, "friction": MU, "restitution": 0.0}]},
                     center=(0.0, 0.0501, 0.0))
    _model, st = stepper(sc)
    t = 0.9
    st.advance(round(t / sc.sim["dt"]))
    v = st.state.particle_qd.numpy().astype(np.float64)
    x = st.state.particle_q.numpy().astype(np.float64)
    s, rate, pivot = 0.1 - 0.3 * (t - 0.5), -0.3, MA.PLATE_SPEED * t
    bottom = np.argsort(x[:, 1])[:9]
    np.testing.assert_allclose(v[bottom, 0], MA.PLATE_SPEED, atol=1e-3)
    np.testing.assert_allclose(v[bottom, 1], rate * (x[bottom, 0] - pivot), atol=1e-3)
    assert (x[:, 1] - s * (x[:, 0] - pivot)).min() > -1e-5


def _platform(path, method, precision="float64"):
    return jelly_scene({"mesh": [{"path": path, "friction": MU, "restitution": 0.0,
                                  "motion": {"velocity": [1.0, 0.0, 0.0]}}]}, method, precision)


def test_jelly_on_a_moving_mesh_rides_it(tmp_path):
    """Coulomb's law in the platform's frame: the jelly slides while the relative speed lasts, its
    momentum growing by mu times the normal impulse (v_x = mu (g t + v_y)), catches the platform
    (1 m/s) at t = 1 / (mu g) = 0.128 s and rides it; and it does so as on the analytic plane that
    moves alike (same trajectory to 1e-9 m in float64)."""
    quad = write_quad(tmp_path / "quad.usda")
    sc = _platform(quad, "symplectic")
    _model, st = stepper(sc)
    _plane_model, plane_st = stepper(jelly_scene({"plane": [{"friction": MU, "restitution": 0.0, "motion": {
        "velocity": [1.0, 0.0, 0.0]}}]}, "symplectic", "float64"))
    dt = sc.sim["dt"]
    t_catch = 1.0 / (MU * G)
    rows, gap = [], 0.0
    for k in range(round(0.5 / dt)):
        st.advance(1)
        plane_st.advance(1)
        v = st.state.particle_qd.numpy().mean(axis=0)
        rows.append(((k + 1) * dt, v[0], MU * (G * (k + 1) * dt + v[1])))
        gap = max(gap, float(np.abs(st.state.particle_q.numpy() - plane_st.state.particle_q.numpy()).max()))
    t, vx, coulomb = np.array(rows).T
    sliding = t < 0.9 * t_catch
    np.testing.assert_allclose(vx[sliding], coulomb[sliding], rtol=0, atol=1e-4)
    reached = t[np.argmax(vx >= 0.99)]
    assert 0.95 * t_catch <= reached <= 1.1 * t_catch, (reached, t_catch)
    assert abs(vx[t > 0.4].mean() - 1.0) < 5e-3
    assert st.state.particle_q.numpy()[:, 1].min() > -1e-6
    assert gap < 1e-9, gap


def test_jelly_on_a_turning_mesh_turns_with_it(tmp_path):
    """A mesh turntable (90 deg/s about y through the origin) carries a jelly resting 0.3 m off the
    axis: once friction has spun it up, it moves at omega x r (the spin's surface velocity in the
    mesh's frame) and stays at its radius."""
    quad = write_quad(tmp_path / "quad.usda")
    omega = math.radians(90.0)
    sc = jelly_scene({"mesh": [{"path": quad, "friction": MU, "restitution": 0.0, "motion": {
        "spin": {"axis": [0.0, 1.0, 0.0], "degrees_per_second": 90.0, "center": [0.0, 0.0, 0.0]}}}]},
        center=(0.3, 0.05, 0.0))
    _model, st = stepper(sc)
    st.advance(round(1.0 / sc.sim["dt"]))
    x = st.state.particle_q.numpy().astype(np.float64)
    v = st.state.particle_qd.numpy().astype(np.float64)
    rate, radius = rate_about_y(x, v)
    assert abs(rate - omega) < 0.01 * omega, (rate, omega)
    assert abs(radius - 0.3) < 0.005
    assert x[:, 1].min() > -1e-5


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_restitution_against_a_moving_mesh_wall_in_its_frame(e):
    """Two particles (a spring along y, no gravity) at +1 m/s meet a mesh wall coming at 2 m/s: in
    the wall's frame they come in at 3 m/s and leave at e * 3 m/s, so at 2 + 3 e m/s in the world."""
    b = ss.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_jelly((1, 2, 1), (1.0, 0.1, 1.0), 0.01, {"structural": {"ks": 10.0, "kd": 0.0}}, velocity=(1.0, 0.0, 0.0))
    # A square at x = 0.3 facing -x, wound counter-clockwise about its normal.
    wall = MeshAsset(np.array([[0.3, -2.0, -2.0], [0.3, -2.0, 2.0], [0.3, 2.0, 2.0], [0.3, 2.0, -2.0]]),
                     np.array([4]), np.array([0, 1, 2, 3]))
    b.add_mesh(wall, restitution=e, friction=0.0, motion={"velocity": (-2.0, 0.0, 0.0)})
    model = b.finalize("cpu", "float64")
    st = ss.Stepper(model, ss.make_integrator("symplectic", model), 1e-3)
    st.advance(200)  # they meet at t = 0.1 s
    v = st.state.particle_qd.numpy()
    wall_v = -2.0
    incoming, outgoing = 1.0 - wall_v, -(v[:, 0] - wall_v)
    np.testing.assert_allclose(outgoing / incoming, e, rtol=0, atol=1e-12)
    np.testing.assert_allclose(v[:, 1:], 0.0, atol=1e-12)
    assert np.all(st.state.particle_q.numpy()[:, 0] <= 0.3 + wall_v * 0.2 + 1e-12)


def _launched(monkeypatch):
    names = []
    launch = wp.launch

    def record(kernel, *args, **kw):
        names.append(kernel.key)
        return launch(kernel, *args, **kw)

    monkeypatch.setattr(wp, "launch", record)
    return names


def test_static_mesh_launches_nothing_more(tmp_path, monkeypatch, plate):
    """A static mesh scene has no motion or animation arrays, is captured in graphs, and a step
    launches the static mesh contact only; a moving mesh adds move_terrain, an animated one
    deform_mesh and its clock, each taking the moving contact kernel."""
    quad = write_quad(tmp_path / "quad.usda")
    for terrain, extra in ((quad, {}), (quad, {"motion": {"velocity": [1.0, 0.0, 0.0]}}), (plate, {"animated": True})):
        sc = jelly_scene({"mesh": [{"path": terrain, **extra}]})
        model = ss.build_model(sc, "cpu")
        assert ss.Stepper(model, ss.make_integrator("symplectic", model), 2e-4).use_graph == ("animated" not in extra)
        st = ss.Stepper(model, ss.make_integrator("symplectic", model), 2e-4, use_graph=False)
        st.advance(1)  # compiled and loaded
        names = _launched(monkeypatch)
        st.advance(3)
        monkeypatch.undo()
        assert (model.terrain_motion is not None) == ("motion" in extra)
        assert (model.mesh_animation is not None) == ("animated" in extra)
        assert sum("move_terrain" in n for n in names) == (3 if "motion" in extra else 0)
        assert sum("deform_mesh" in n for n in names) == (3 if "animated" in extra else 0)
        assert sum("collide_moving_meshes" in n for n in names) == (3 if extra else 0)
        assert sum("collide_meshes" in n for n in names) == (0 if extra else 3)
        if not extra:
            assert not any("move" in n or "deform" in n or "pin_clock" in n for n in names), names


def test_moving_mesh_errors_are_one_line(tmp_path, plate):
    quad = write_quad(tmp_path / "quad.usda")
    obj = tmp_path / "quad.obj"
    obj.write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 4 3 2\n")
    cases = [
        ({"path": quad, "animated": True}, "symplectic", "mesh.0.animated: the asset's Meshes have fewer than two"),
        ({"path": str(obj), "animated": True}, "symplectic", "mesh.0.animated: only a USD asset has time samples"),
        ({"path": quad, "motion": {"speed": 1.0}}, "symplectic", "mesh.0.motion.speed: unknown key"),
        ({"path": quad, "motion": {"velocity": [1.0, 0.0, 0.0]}}, "implicit",
         "mesh.0.motion: the implicit integrator does not take moving terrain"),
        ({"path": plate, "animated": True}, "implicit", "mesh.0.animated: the implicit integrator does not take"),
    ]
    for entry, integrator, needle in cases:
        with pytest.raises(SceneError) as err:
            jelly_scene({"mesh": [entry]}, integrator)
        assert needle in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_usd_output_animates_moving_meshes(tmp_path, plate):
    """The output gives a moving mesh a transform time-sampled at every frame (its motion's rigid
    map: the mesh as given, moved 0.1 m along x at 1 m/s by frame 1 at 10 fps) and an animated mesh
    its points at every frame (the asset's samples interpolated at the frame's time); both
    validators are clean."""
    from softsim_warp.commands import cli

    quad = write_quad(tmp_path / "quad.usda")
    scene = tmp_path / "moving.toml"
    scene.write_text(
        '[simulation]\ndt = 1e-3\nduration = 0.3\nfps = 10\n'
        '[[jelly]]\nresolution = 3\nsize = 0.1\ncenter = [0.0, 0.3, 0.0]\nparticle_mass = 0.01\n'
        f'[[mesh]]\npath = "{quad}"\nmotion = {{ velocity = [1.0, 0.0, 0.0] }}\n'
        f'[[mesh]]\npath = "{plate}"\nanimated = true\n')
    out = tmp_path / "moving.usdc"
    assert cli.main(["run", str(scene), "--quiet", "--out", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    quad_prim = UsdGeom.Mesh.Get(stage, "/World/Quad_0")
    ops = quad_prim.GetOrderedXformOps()
    assert len(ops) == 1 and ops[0].GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    corner = np.append(np.array(quad_prim.GetPointsAttr().Get()[0], dtype=np.float64), 1.0)
    for frame in range(4):
        moved = corner @ np.array(quad_prim.ComputeLocalToWorldTransform(frame))
        np.testing.assert_allclose(moved[:3], corner[:3] + [0.1 * frame, 0.0, 0.0], atol=1e-9)
    sheet = UsdGeom.Mesh.Get(stage, "/World/Sheet_1")
    assert sheet.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    for frame in range(4):
        got = np.array(sheet.GetPointsAttr().Get(frame), dtype=np.float64)
        np.testing.assert_allclose(got, MA.animated_plate_world(frame / 10.0), atol=1e-6)
        assert len(sheet.GetNormalsAttr().Get(frame)) == 4 * 9
    uv = pytest.importorskip("usd_validation_nvidia")
    results = uv.ValidationEngine().validate(str(out))
    assert [f"{i.severity.name}: {i.message}" for i in results.issues] == []
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)] == []


def test_preview_draws_moving_terrain_where_it_stands(tmp_path, plate):
    """``softsim preview`` reads moving terrain at every frame drawn: the triangles it draws at a
    frame are the moving quad's (1 m/s along x) and the animated plate's (its samples interpolated)
    at that frame's time, the static floor's stay put, and two frames' pictures differ."""
    from softsim_warp.commands import cli
    from softsim_warp.io import preview

    quad = write_quad(tmp_path / "quad.usda", size=1.0)
    scene = tmp_path / "moving.toml"
    scene.write_text(
        '[simulation]\ndt = 1e-3\nduration = 0.3\nfps = 10\n'
        '[[jelly]]\nresolution = 3\nsize = 0.1\ncenter = [0.0, 0.3, 0.0]\nparticle_mass = 0.01\n'
        '[[plane]]\npoint = [0.0, -0.5, 0.0]\n'
        f'[[mesh]]\npath = "{quad}"\nmotion = {{ velocity = [1.0, 0.0, 0.0] }}\n'
        f'[[mesh]]\npath = "{plate}"\nanimated = true\n')
    out = tmp_path / "moving.usdc"
    assert cli.main(["run", str(scene), "--quiet", "--out", str(out)]) == 0
    sc = preview._Scene(str(out))
    assert len(sc.moving_terrain) == 2
    floor = sc._terrain_parts[0]
    quad0 = np.asarray(load_quad_points(quad))
    for frame in (0, 2, 3):
        t = frame / 10.0
        parts = np.split(sc.terrain_at(frame), np.cumsum([len(p) for p in sc._terrain_parts])[:-1])
        np.testing.assert_array_equal(parts[0], floor)
        corners = np.unique(parts[1].reshape(-1, 3).round(9), axis=0)
        np.testing.assert_allclose(corners, np.unique((quad0 + [t, 0.0, 0.0]).round(9), axis=0), atol=1e-6)
        plate_pts = parts[2].reshape(-1, 3)
        expected = MA.animated_plate_world(t)
        # Every drawn vertex is one of the plate's vertices at t.
        gap = np.linalg.norm(plate_pts[:, None] - expected[None], axis=2).min(axis=1)
        assert gap.max() < 1e-6, gap.max()
    a = tmp_path / "a.png"
    b = tmp_path / "b.png"
    preview.render_png(str(out), str(a), frame=0, size=(160, 120))
    preview.render_png(str(out), str(b), frame=3, size=(160, 120))
    import matplotlib.image as mpimg

    assert np.abs(mpimg.imread(a) - mpimg.imread(b)).max() > 0.1


def load_quad_points(path):
    stage = Usd.Stage.Open(path)  # held while its prim is read
    return np.array(UsdGeom.Mesh.Get(stage, "/Quad").GetPointsAttr().Get(), dtype=np.float64)
