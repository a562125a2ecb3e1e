"""Moving analytic terrain (a plane, bowl or sphere with a pin's motion) against closed forms.

A jelly on a plane moving at 1 m/s is dragged by Coulomb friction on the relative tangential speed:
while it slides, its momentum grows by mu times the normal impulse, v_x = mu (g t + v_y) (v_y its
centre's vertical velocity), and it reaches the plane's speed where mu g predicts. A moving wall
reflects the relative normal speed by its restitution. A jelly on a turntable turns at the table's
rate. A keyframed plane is where NumPy's interpolation of its keys puts it at every step's end.
A scene where nothing moves launches no terrain motion and no moving contact variant.
"""

import math

import numpy as np
import pytest
import warp as wp

import softsim_warp as ss
from softsim_warp.core.errors import SceneError
from softsim_warp.core.pins import path_position
from softsim_warp.io.scene import load_scene
from tests.helpers import rate_about_y

MU, G = 0.8, 9.8


def springs(ks, kd):
    return {name: {"ks": ks, "kd": kd} for name in ("structural", "shear", "bending")}


def scene(motion, integrator="symplectic", friction=MU, restitution=0.0, center=(0.0, 0.05, 0.0), **plane):
    """A small stiff jelly (3^3 particles, 0.1 m) resting on a plane that moves by ``motion``."""
    return ss.scene_from_dict({
        "simulation": {"integrator": integrator, "dt": 2e-4, "duration": 1.0, "gravity": [0.0, -G, 0.0]},
        "jelly": [{"resolution": 3, "size": 0.1, "center": list(center), "particle_mass": 0.01,
                   "springs": springs(1000.0, 0.5)}],
        "plane": [{"friction": friction, "restitution": restitution, "motion": motion, **plane}],
    })


def stepper(sc):
    model = ss.build_model(sc, "cpu")
    return model, ss.Stepper(model, ss.make_integrator(sc.sim["integrator"], model), sc.sim["dt"])


@pytest.mark.parametrize("method", ["euler", "symplectic", "midpoint", "rk4"])
def test_jelly_on_a_moving_plane_rides_it(method):
    """Coulomb's law in the plane's frame: the jelly slides while the relative speed lasts, its
    momentum growing by mu times the normal impulse (v_x = mu (g t + v_y), exactly while every
    touching particle slides), and catches the plane (1 m/s) at t = 1 / (mu g) = 0.128 s."""
    sc = scene({"velocity": [1.0, 0.0, 0.0]}, method)
    _, st = stepper(sc)
    dt = sc.sim["dt"]
    t_catch = 1.0 / (MU * G)
    rows = []
    for k in range(round(0.5 / dt)):
        st.advance(1)
        v = st.state.particle_qd.numpy().mean(axis=0)
        rows.append(((k + 1) * dt, v[0], MU * (G * (k + 1) * dt + v[1])))
    t, vx, coulomb = np.array(rows).T
    sliding = t < 0.9 * t_catch
    np.testing.assert_allclose(vx[sliding], coulomb[sliding], rtol=0, atol=1e-4)
    assert np.all(vx <= coulomb + 1e-4)  # friction never gives more than mu times the normal impulse
    reached = t[np.argmax(vx >= 0.99)]
    assert 0.95 * t_catch <= reached <= 1.1 * t_catch, (reached, t_catch)
    assert abs(vx[t > 0.4].mean() - 1.0) < 5e-3  # riding the plane
    x = st.state.particle_q.numpy()
    assert x[:, 1].min() > -1e-6  # on the plane, not in it
    # The plane has moved 0.5 m; the jelly lags by what it slid, that of a block accelerated at
    # mu g: 1 / (2 mu g) = 0.064 m (measured 0.063).
    slip = 0.5 - x[:, 0].mean()
    assert abs(slip - 0.5 * t_catch) < 0.05 * 0.5 * t_catch, slip


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_restitution_against_a_moving_wall_in_its_frame(e):
    """Two particles (a spring along y, no gravity) at +1 m/s meet a wall coming at 2 m/s: in the
    wall's frame they come in at 3 m/s and leave at e * 3 m/s, so at 2 + 3 e m/s in the world."""
    b = ss.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_jelly((1, 2, 1), (1.0, 0.1, 1.0), 0.01, {"structural": {"ks": 10.0, "kd": 0.0}}, velocity=(1.0, 0.0, 0.0))
    b.add_plane((0.3, 0.0, 0.0), (-1.0, 0.0, 0.0), restitution=e, friction=0.0, motion={"velocity": (-2.0, 0.0, 0.0)})
    model = b.finalize("cpu", "float64")
    st = ss.Stepper(model, ss.make_integrator("symplectic", model), 1e-3)
    st.advance(200)  # they meet at t = 0.1 s
    v = st.state.particle_qd.numpy()
    wall = -2.0
    incoming, outgoing = 1.0 - wall, -(v[:, 0] - wall)
    np.testing.assert_allclose(outgoing / incoming, e, rtol=0, atol=1e-12)
    np.testing.assert_allclose(v[:, 1:], 0.0, atol=1e-12)
    wall_x = 0.3 + wall * 0.2
    assert np.all(st.state.particle_q.numpy()[:, 0] <= wall_x + 1e-12)


def test_jelly_on_a_turntable_turns_with_it():
    """A plane spinning about its normal (90 deg/s about y through the origin) carries a jelly
    resting 0.3 m off the axis (omega^2 r = 0.74 m/s^2, well under mu g): after friction has spun
    it up, every particle moves at omega x r and the jelly stays at its radius."""
    omega = math.radians(90.0)
    sc = scene({"spin": {"axis": [0.0, 1.0, 0.0], "degrees_per_second": 90.0, "center": [0.0, 0.0, 0.0]}},
               center=(0.3, 0.05, 0.0))
    _, st = stepper(sc)
    st.advance(round(1.0 / sc.sim["dt"]))
    x = st.state.particle_q.numpy().astype(np.float64)
    v = st.state.particle_qd.numpy().astype(np.float64)
    rate, radius = rate_about_y(x, v)
    assert abs(rate - omega) < 0.01 * omega, (rate, omega)
    assert abs(radius - 0.3) < 0.005
    # Where it is: the table turned 90 degrees; the jelly lags by the arc it slid while friction
    # brought it to the table's speed u = omega r, u^2 / (2 mu g) (0.047 rad; measured 0.046).
    angle = math.atan2(-x[:, 2].mean(), x[:, 0].mean())
    lag = (omega * 0.3) ** 2 / (2 * MU * G) / 0.3
    assert abs(math.pi / 2 - angle - lag) < 0.1 * lag, (math.pi / 2 - angle, lag)


KEYS = [(0.0, [0.0, 0.0, 0.0]), (0.05, [0.1, 0.02, 0.0]), (0.12, [0.3, -0.01, 0.05]), (0.2, [0.3, 0.03, -0.1])]


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_keyframed_plane_is_where_its_keys_put_it(precision):
    """At every step's end the plane the contact used (its point and normal on the device) is the
    keys' linear interpolation (NumPy's interp) carried by its spin (Rodrigues about z), to 1e-6 m."""
    sc = scene({"keyframes": [{"time": t, "offset": d} for t, d in KEYS],
                "spin": {"axis": [0.0, 0.0, 1.0], "degrees_per_second": 20.0}}, center=(0.0, 0.2, 0.0))
    sc.sim["precision"] = precision
    _, st = stepper(sc)
    dt = sc.sim["dt"]
    times = np.array([k[0] for k in KEYS])
    offsets = np.array([k[1] for k in KEYS])
    worst = 0.0
    for k in range(round(0.25 / dt)):
        st.advance(1)
        t = (k + 1) * dt
        expected = np.array([np.interp(t, times, offsets[:, c]) for c in range(3)])
        a = math.radians(20.0) * t
        worst = max(worst, float(np.abs(st.integrator.run.terrain.plane_point.numpy()[0] - expected).max()),
                    float(np.abs(st.integrator.run.terrain.plane_normal.numpy()[0] - [-math.sin(a), math.cos(a), 0.0]).max()))
    assert worst < 1e-6, worst


def test_smooth_keyframed_sphere_follows_the_pin_path():
    """A sphere's centre with smooth keys and a spin about an off-centre point follows the pin's
    path (core/pins.path_position, NumPy float64) to 1e-6 m at every step's end."""
    motion = {"keyframes": [{"time": t, "offset": d} for t, d in KEYS], "interpolation": "smooth",
              "velocity": [0.2, 0.0, 0.0], "spin": {"axis": [0.0, 1.0, 0.0], "degrees_per_second": 45.0,
                                                     "center": [0.1, 0.0, 0.0]}}
    sc = ss.scene_from_dict({
        "simulation": {"integrator": "symplectic", "dt": 1e-3, "duration": 1.0, "precision": "float64"},
        "jelly": [{"resolution": 2, "size": 0.1, "center": [0.0, 2.0, 0.0], "particle_mass": 0.01}],
        "sphere": [{"center": [0.5, 0.0, 0.0], "radius": 0.3, "motion": motion}],
    })
    model, st = stepper(sc)
    pin = model.spheres[0]["motion"]
    for k in range(250):
        st.advance(1)
        expected = path_position(pin, np.array([0.5, 0.0, 0.0]), (k + 1) * 1e-3)
        assert np.abs(st.integrator.run.terrain.sphere_center.numpy()[0] - expected).max() < 1e-6


def test_hole_moves_with_its_plane():
    """A plane with a hole (radius 0.1 m at the origin) slides along x at 1 m/s; two jellies fall
    from 1.225 m, landing at t = 0.5 s: the one at x = 0.5 m falls through the hole, which is there
    by then, the one at x = 0 lands on the plane where the hole was at the start. (At 0.6 s the
    hole has passed x = 0.5 m, and the plane, a half-space, puts what fell through back on top, as a
    static plane does a particle that leaves its hole's circle below it.)"""
    def column(x):
        return {"resolution": [1, 2, 1], "size": [1.0, 0.02, 1.0], "center": [x, 1.235, 0.0], "particle_mass": 0.01,
                "springs": {"structural": {"ks": 100.0, "kd": 0.1}}}

    sc = ss.scene_from_dict({
        "simulation": {"integrator": "symplectic", "dt": 1e-3, "duration": 1.0, "jelly_contact": False},
        "jelly": [column(0.5), column(0.0)],
        "plane": [{"hole": {"center": [0.0, 0.0, 0.0], "radius": 0.1}, "friction": 0.0, "restitution": 0.0,
                   "motion": {"velocity": [1.0, 0.0, 0.0]}}],
    })
    _, st = stepper(sc)
    st.advance(550)
    y = st.state.particle_q.numpy()[:, 1]
    np.testing.assert_allclose(st.integrator.run.terrain.plane_hole_center.numpy()[0], [0.55, 0.0, 0.0], atol=1e-5)
    assert y[:2].max() < -0.1  # through the hole
    assert y[2:].min() > -1e-6  # on the plane


def test_moving_bowl_carries_what_it_holds():
    """A bowl moving sideways at 0.5 m/s carries a jelly resting in it: nothing leaves it, and the
    jelly ends moving with the bowl."""
    sc = ss.scene_from_dict({
        "simulation": {"integrator": "symplectic", "dt": 2e-4, "duration": 1.0},
        "jelly": [{"resolution": 3, "size": 0.1, "center": [0.0, -0.45, 0.0], "particle_mass": 0.01,
                   "springs": springs(1000.0, 0.5)}],
        "bowl": [{"center": [0.0, 0.0, 0.0], "radius": 0.52, "cut_height": 0.0, "friction": 0.8, "restitution": 0.0,
                  "motion": {"velocity": [0.5, 0.0, 0.0]}}],
    })
    _, st = stepper(sc)
    st.advance(round(1.0 / sc.sim["dt"]))
    x = st.state.particle_q.numpy()
    center = st.integrator.run.terrain.bowl_center.numpy()[0]
    np.testing.assert_allclose(center, [0.5, 0.0, 0.0], atol=1e-5)
    assert np.linalg.norm(x - center, axis=1).max() < 0.52 + 1e-5  # inside the bowl
    assert abs(st.state.particle_qd.numpy()[:, 0].mean() - 0.5) < 0.02


def _launched(monkeypatch):
    names = []
    launch = wp.launch

    def record(kernel, *args, **kw):
        names.append(kernel.key)
        return launch(kernel, *args, **kw)

    monkeypatch.setattr(wp, "launch", record)
    return names


def test_static_terrain_launches_nothing_more(monkeypatch):
    """Static terrain has no motion arrays and a step launches no terrain motion and no moving
    variant; a moving plane adds one launch a step (move_terrain) and takes its contact kernel."""
    for motion, moving in ((None, False), ({"velocity": [1.0, 0.0, 0.0]}, True)):
        data = {"velocity": [1.0, 0.0, 0.0]} if moving else {}
        sc = scene(data) if moving else ss.scene_from_dict({
            "simulation": {"integrator": "symplectic", "dt": 2e-4, "duration": 1.0},
            "jelly": [{"resolution": 3, "size": 0.1, "center": [0.0, 0.05, 0.0], "particle_mass": 0.01}],
            "plane": [{}], "sphere": [{"center": [1.0, 0.0, 0.0], "radius": 0.1}]})
        model = ss.build_model(sc, "cpu")
        st = ss.Stepper(model, ss.make_integrator("symplectic", model), 2e-4, use_graph=False)
        st.advance(1)  # compiled and loaded
        names = _launched(monkeypatch)
        st.advance(3)
        monkeypatch.undo()
        assert (model.terrain_motion is not None) == moving
        assert sum("move_terrain" in n for n in names) == (3 if moving else 0)
        assert any("collide_moving" in n for n in names) == moving


@pytest.mark.parametrize(
    "entry,needle",
    [
        ({"motion": {"velocity": [1.0, 0.0]}}, "plane.0.motion.velocity: must be a list of 3 finite numbers"),
        ({"motion": {"speed": 1.0}}, "plane.0.motion.speed: unknown key"),
        ({"motion": {"keyframes": [{"time": 1.0, "offset": [0, 0, 0]}, {"time": 0.5, "offset": [0, 0, 0]}]}},
         "plane.0.motion.keyframes: times must be strictly increasing"),
        ({"motion": {"spin": {"axis": [0, 0, 0]}}}, "plane.0.motion.spin.axis: must not be the zero vector"),
        ({"motion": {"interpolation": "cubic"}}, "plane.0.motion.interpolation"),
        ({"motion": 3}, "plane.0.motion: must be a table"),
    ],
)
def test_bad_motion_is_one_line(entry, needle):
    data = {"simulation": {"duration": 1.0}, "jelly": [{"resolution": 2, "size": 0.1, "particle_mass": 0.01}],
            "plane": [entry]}
    with pytest.raises(SceneError) as e:
        ss.scene_from_dict(data)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_implicit_with_moving_terrain_is_refused():
    data = {"simulation": {"duration": 1.0, "integrator": "implicit"},
            "jelly": [{"resolution": 2, "size": 0.1, "particle_mass": 0.01}],
            "sphere": [{"center": [0, -1, 0], "radius": 0.5, "motion": {"velocity": [0, 1, 0]}}]}
    with pytest.raises(SceneError) as e:
        ss.scene_from_dict(data)
    assert "sphere.0.motion: the implicit integrator does not take moving terrain" in str(e.value)


def test_usd_animates_moving_terrain(tmp_path):
    """The turntable's plane is written once, as given, with a transform sampled at every frame:
    the rigid map of its motion at the frame's time (60 deg/s about y), which puts its mesh where
    the contact had it; static terrain gets no transform."""
    from pxr import Usd, UsdGeom

    from softsim_warp.commands import cli

    out = tmp_path / "turntable.usda"
    argv = ["run", "turntable", "--frames", "3", "--fps", "10", "--quiet", "--out", str(out),
            "--set", "jelly.0.resolution=3"]
    assert cli.main(argv) == 0
    stage = Usd.Stage.Open(str(out))
    plane = UsdGeom.Mesh.Get(stage, "/World/Plane_0")
    ops = plane.GetOrderedXformOps()
    assert len(ops) == 1 and ops[0].GetOpType() == UsdGeom.XformOp.TypeTransform
    assert ops[0].GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    corner = np.array(plane.GetPointsAttr().Get()[0], dtype=np.float64)
    for frame in range(4):
        a = math.radians(60.0) * frame / 10.0
        m = np.array(plane.ComputeLocalToWorldTransform(frame))
        moved = np.append(corner, 1.0) @ m
        # About +y by a: (x, z) -> (x cos a + z sin a, -x sin a + z cos a).
        expected = [corner[0] * math.cos(a) + corner[2] * math.sin(a), corner[1],
                    -corner[0] * math.sin(a) + corner[2] * math.cos(a)]
        np.testing.assert_allclose(moved[:3], expected, atol=1e-9)
    static = tmp_path / "jelly_drop.usda"
    assert cli.main(["run", "jelly_drop", "--frames", "1", "--quiet", "--out", str(static), "--set",
                     "jelly.0.resolution=3"]) == 0
    assert UsdGeom.Mesh.Get(Usd.Stage.Open(str(static)), "/World/Plane_0").GetOrderedXformOps() == []


def test_platform_carries_the_stack():
    """The built-in `platform` (full size, 8000 steps): while the platform accelerates at 2 m/s^2
    (well under mu g) the bottom jelly keeps its speed; once the platform runs at 1 m/s the stack's
    centre moves at it give or take its sway; the jellies stay stacked and stop with the platform."""
    from softsim_warp.core.contact import terrain_at

    sc = load_scene("platform")
    model, st = stepper(sc)
    plane = model.planes[0]
    parts = [slice(j.particle_start, j.particle_start + j.particle_count) for j in model.jellies]
    rows = []
    for k in range(400):  # 10 ms samples
        st.advance(20)
        t = (k + 1) * 0.01
        vp = (terrain_at(plane, t + 1e-5)["point"][0] - terrain_at(plane, t - 1e-5)["point"][0]) / 2e-5
        q, v = st.state.particle_q.numpy(), st.state.particle_qd.numpy()
        rows.append((t, vp, v[:, 0].mean(), *[v[s, 0].mean() for s in parts], *[q[s, 0].mean() for s in parts],
                     *[q[s, 1].mean() for s in parts]))
    o = np.array(rows)
    t = o[:, 0]
    accel, cruise, stopped = (t > 1.0) & (t < 1.5), (t >= 2.0) & (t <= 2.5), t >= 3.5
    assert np.abs(o[accel, 3] - o[accel, 1]).max() < 0.06  # bottom jelly (measured 0.043)
    assert np.abs(o[accel, 2] - o[accel, 1]).max() < 0.12  # the stack's centre (0.091)
    assert 0.8 < o[cruise, 2].min() and o[cruise, 2].max() < 1.2  # sways about 1 m/s (0.87-1.14)
    assert np.abs(o[stopped, 2]).max() < 0.2  # (0.13)
    np.testing.assert_allclose(st.integrator.run.terrain.plane_point.numpy()[0], [1.5, 0.0, 0.0], atol=1e-6)
    heights = o[:, 9:12]
    assert np.all(heights.min(axis=0) > [0.2, 0.8, 1.4])  # stacked: none slid off (0.25, 0.84, 1.43)
    assert np.abs(o[:, 7:9] - o[:, 6:7]).max() < 0.2  # within 0.2 m of the bottom jelly in x (0.12)
