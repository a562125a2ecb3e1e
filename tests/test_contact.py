"""Plane contact against closed forms: restitution on impact, the incline law, holes."""

import math

import numpy as np
import pytest

from softsim_warp import ModelBuilder, make_integrator

METHODS = ["euler", "symplectic", "midpoint", "rk4"]
G = 9.8


def particle_on_plane(device, q, v=(0, 0, 0), normal=(0, 1, 0), restitution=0.5, friction=0.3, eps=0.01, **plane):
    b = ModelBuilder(gravity=(0.0, -G, 0.0))
    b.contact_epsilon = eps
    b.add_particles([q], [v], 0.1)
    b.add_plane((0, 0, 0), normal, restitution, friction, **plane)
    return b.finalize(device, "float64")


@pytest.mark.parametrize("method", METHODS)
def test_rebound_at_restitution_times_impact_speed(device, method):
    # Dropped from H, the particle meets the plane at sqrt(2 g H) (to within g h, the step's own change);
    # the impact step returns v' = -k_r v*, v* = v_n - g h the velocity the step would have reached.
    # With a zero contact band the impact happens on crossing the surface, not up to epsilon above it.
    kr, H, h = 0.6, 0.5, 1e-3
    model = particle_on_plane(device, (0.0, H, 0.0), restitution=kr, eps=0.0)
    integ = make_integrator(method, model)
    a, b = model.state(), model.state()
    for _ in range(2000):
        integ.step(a, b, h)
        v_before, v_after = a.particle_qd.numpy()[0, 1], b.particle_qd.numpy()[0, 1]
        a, b = b, a
        if v_after > 0:
            break
    else:
        pytest.fail("no rebound")
    v_star = v_before - G * h
    assert v_after == pytest.approx(-kr * v_star, rel=1e-12)
    assert -v_star == pytest.approx(math.sqrt(2 * G * H), abs=G * h)
    assert a.particle_q.numpy()[0, 1] >= 0.0  # put back on the surface, not left below it


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("mu", [0.2, 0.3, 0.8])
def test_block_on_incline(device, method, mu):
    # A particle at rest on a 30 degree slope: it stays if mu > tan(theta), else it slides with
    # a = g (sin(theta) - mu cos(theta)). Friction removes at most mu |N.f| h / m of speed per step, so
    # the discrete law is exact step by step.
    theta = math.radians(30.0)
    normal = (math.sin(theta), math.cos(theta), 0.0)
    model = particle_on_plane(device, (0.0, 0.0, 0.0), normal=normal, friction=mu)
    h, n = 1e-3, 500
    integ = make_integrator(method, model)
    a, b = model.state(), model.state()
    for _ in range(n):
        integ.step(a, b, h)
        a, b = b, a
    v = a.particle_qd.numpy()[0]
    x = a.particle_q.numpy()[0]
    assert abs(np.dot(x, normal)) < 1e-12  # stays on the surface
    if mu > math.tan(theta):
        assert np.abs(v).max() == 0.0
        assert np.abs(x).max() < 1e-12
    else:
        accel = G * (math.sin(theta) - mu * math.cos(theta))
        downhill = np.array([math.cos(theta), -math.sin(theta), 0.0])
        assert np.dot(v, downhill) == pytest.approx(accel * n * h, rel=1e-9)
        assert abs(np.dot(v, normal)) < 1e-12
        if method == "symplectic":
            # Friction acts over the whole step (contact moves x by h times its velocity change), so
            # this is symplectic Euler under the constant acceleration a: s_N = sum_k h (k h a).
            t = n * h
            assert np.dot(x, downhill) == pytest.approx(0.5 * accel * t * t + 0.5 * accel * t * h, rel=1e-9)


def test_jelly_settles_on_ground(device):
    # A dropped jelly comes to rest on the plane: no particle below it, speeds near zero,
    # and the centre of mass at about half the edge (plus a sag far below the spacing).
    from softsim_warp import Simulator, build_model, load_scene  # noqa: PLC0415

    # Flat landing (no initial rotation) of a coarse version of the built-in jelly.
    scene = load_scene("jelly_drop", ["jelly.0.resolution=4", "jelly.0.rotation.degrees=0", "simulation.duration=3.0"])
    model = build_model(scene, device)
    sim = Simulator(model, make_integrator("symplectic", model), scene.sim["dt"], scene.sim["fps"], scene.frame_count())
    result = sim.run()
    assert not result.exploded
    q = sim.state.particle_q.numpy()
    assert q[:, 1].min() >= -1e-6
    last = result.metrics[-1]
    assert last.max_speed < 0.05
    assert last.com[1] == pytest.approx(0.25, abs=0.02)


@pytest.mark.parametrize("method", METHODS)
def test_bounce_height_is_restitution_squared(device, method):
    # Dropped from H, the particle meets the plane at v = sqrt(2 g H), far above the restitution
    # threshold (one step of gravity, g h = 0.01 m/s), leaves at e v and rises to (e v)^2 / (2 g) = e^2 H;
    # each later bounce reaches e^2 times the one before.
    kr, H, h = 0.8, 1.0, 1e-3
    model = particle_on_plane(device, (0.0, H, 0.0), restitution=kr, eps=0.0)
    integ = make_integrator(method, model)
    a, b = model.state(), model.state()
    apexes, top, rising = [], 0.0, False
    for _ in range(4000):
        integ.step(a, b, h)
        a, b = b, a
        y, vy = a.particle_q.numpy()[0, 1], a.particle_qd.numpy()[0, 1]
        if vy > 0:
            rising, top = True, max(top, y)
        elif rising:
            apexes.append(max(top, y))
            rising, top = False, 0.0
        if len(apexes) == 2:
            break
    before = H
    for apex in apexes:
        v = math.sqrt(2 * G * before)
        # Error of one bounce: the step that crosses the plane reflects v* = v + up to g h (relative
        # 2 g h / v on the height), puts the particle on the plane instead of up to e v h above it,
        # and the method's position error over the flight is at most e v h / 2 (Euler and
        # symplectic Euler; midpoint and RK4 are exact under constant gravity).
        tol = kr**2 * before * 2 * G * h / v + 1.5 * kr * v * h + G * h * h
        assert apex == pytest.approx(kr**2 * before, abs=tol)
        before = apex


@pytest.mark.parametrize("method", METHODS)
def test_restitution_threshold(device, method):
    # A particle on the plane approaching at u0: an impact when u0 exceeds one step of its pressing
    # impulse (rest_steps = 1, w = g h), leaving at e (u0 + g h); a contact below it: stopped, v = 0.
    kr, h = 0.5, 1e-3
    w = G * h
    for u0, impact in ((0.5 * w, False), (3.0 * w, True)):
        model = particle_on_plane(device, (0.0, 0.0, 0.0), v=(0.0, -u0, 0.0), restitution=kr, friction=0.3)
        integ = make_integrator(method, model)
        a, b = model.state(), model.state()
        integ.step(a, b, h)
        vy = b.particle_qd.numpy()[0, 1]
        assert vy == pytest.approx(kr * (u0 + w) if impact else 0.0, abs=1e-15)


@pytest.mark.parametrize("method", METHODS)
def test_pressed_particle_comes_to_rest(device, method):
    # A particle pressed onto the plane by a force that adds w = 1 m/s of approach per step, leaving
    # it at e w / (1 + e): the old response reflected it every step at that speed forever (a resting
    # jelly's corners read 0.38 m/s). The approach it meets is built within the step (w > u0), so it
    # is a contact: the particle stops and stays, v = 0 and on the plane.
    kr, h, g_big = 0.8, 1e-3, 1000.0
    b = ModelBuilder(gravity=(0.0, -g_big, 0.0))
    b.add_particles([(0.0, 0.0, 0.0)], [(0.0, kr * g_big * h / (1 + kr), 0.0)], 0.1)
    b.add_plane((0, 0, 0), (0, 1, 0), kr, 0.3)
    model = b.finalize(device, "float64")
    integ = make_integrator(method, model)
    s0, s1 = model.state(), model.state()
    for _ in range(20):
        integ.step(s0, s1, h)
        s0, s1 = s1, s0
    assert np.abs(s0.particle_qd.numpy()[0]).max() == 0.0
    # It rises at most for the first step (explicit Euler moves it by h u first, then stops it inside
    # the contact layer); after that it does not move.
    assert 0.0 <= s0.particle_q.numpy()[0, 1] <= kr * g_big * h / (1 + kr) * h


def test_each_world_meets_only_its_own_planes(device):
    """Primitives are sorted by world and each particle visits only its world's range.

    Planes are added out of world order at different heights; a particle dropped in each world
    must come to rest on its own world's plane (y = -0.1 * w), never on another's.
    """
    b = ModelBuilder((0.0, -9.8, 0.0))
    worlds = 3
    for w in reversed(range(worlds)):
        b.add_plane((0.0, -0.1 * w, 0.0), (0.0, 1.0, 0.0), restitution=0.0, friction=0.5, world=w)
    for w in range(worlds):
        b.add_particles([[0.0, 0.05, 0.0]], [[0.0, 0.0, 0.0]], 1.0, world=w)
    model = b.finalize(device)
    first = model.plane_first.numpy()
    assert first.tolist() == [0, 1, 2, 3]
    assert [p["world"] for p in model.planes] == [0, 1, 2]
    integ = make_integrator("symplectic", model)
    a, c = model.state(), model.state()
    for _ in range(500):  # 0.5 s: a fall of at most 0.25 m from rest takes 0.23 s
        integ.step(a, c, 1.0e-3)
        a, c = c, a
    y = a.particle_q.numpy()[:, 1]
    # Resting on its own plane: within the contact layer above it (contact_epsilon), not below.
    for w in range(worlds):
        assert -0.1 * w - 1e-6 <= y[w] <= -0.1 * w + b.contact_epsilon + 1e-6, (w, y)
