"""Terrain primitives against closed forms: hole, bowl, sphere; and the seed_bowl scene (a tilted
plane: test_contact.test_block_on_incline).

Single particles in float64, so that what is left is the method's own error; each tolerance is
derived from the step size next to its assert.
"""

import math

import numpy as np
import pytest

from softsim_warp.core.integrators import ExplicitIntegrator
from softsim_warp.core.model import ModelBuilder, build_model
from softsim_warp.io.scene import load_scene
from softsim_warp.io.simulate import Simulator

G = 9.8


def _run(builder, method, dt, steps, device, precision="float64", record=None):
    """Advance a model ``steps`` steps; ``record(k, q, qd)`` sees every state (host copies)."""
    model = builder.finalize(device, precision)
    integrator = ExplicitIntegrator(model, method)
    s0, s1 = model.state(), model.state()
    for k in range(steps):
        integrator.step(s0, s1, dt)
        s0, s1 = s1, s0
        if record is not None and record(k + 1, s0.particle_q.numpy(), s0.particle_qd.numpy()):
            break
    return s0.particle_q.numpy(), s0.particle_qd.numpy()


def test_particle_over_hole_falls_through(device):
    # Plane y = 0 with a hole of radius 0.5 around (2, 0, 1): one particle over the hole, one beside it.
    b = ModelBuilder(gravity=(0.0, -G, 0.0))
    b.add_particles([[2.2, 1.0, 1.1], [3.0, 1.0, 1.0]], [0.0, 0.0, 0.0], 1.0)
    b.add_plane([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], restitution=0.0, friction=0.5,
                hole_center=[2.0, 0.0, 1.0], hole_radius=0.5)
    dt, steps = 0.01, 100
    q, qd = _run(b, "rk4", dt, steps, device)
    t = dt * steps
    # Free fall: y(t) = y0 - g t^2 / 2, v(t) = -g t; RK4 is exact for a constant force (float64 rounding).
    assert q[0, 1] == pytest.approx(1.0 - 0.5 * G * t * t, abs=1e-12)
    assert qd[0, 1] == pytest.approx(-G * t, abs=1e-12)
    np.testing.assert_allclose(q[0, [0, 2]], [2.2, 1.1], atol=1e-12)
    # Beside the hole the plane holds: inelastic landing, then at rest on y = 0 (within the contact layer).
    assert 0.0 <= q[1, 1] < b.contact_epsilon
    assert np.linalg.norm(qd[1]) < 1e-12


def test_particle_in_bowl_settles_at_lowest_point(device):
    # Bowl: inside of the unit sphere centred at (0, 1, 0) below y = 1; lowest point (0, 0, 0).
    radius, mu = 1.0, 0.008
    center = np.array([0.0, 1.0, 0.0])
    theta0 = 0.15  # released at rest on the wall, outside the friction cone tan(theta) <= mu
    start = center + radius * np.array([math.sin(theta0), -math.cos(theta0), 0.0])
    b = ModelBuilder(gravity=(0.0, -G, 0.0))
    b.add_particles([start], [0.0, 0.0, 0.0], 1.0)
    b.add_bowl(center, radius, cut_height=1.0, restitution=0.5, friction=mu)
    q, qd = _run(b, "symplectic", 2e-3, 6000, device)
    x, v = q[0], qd[0]
    # Coulomb friction stops the particle where static friction can hold it: inside the cone
    # tan(theta) <= mu around the lowest point, i.e. at most R sin(atan mu) = 0.008 from it
    # horizontally, which is within the contact layer eps = 0.01.
    cone = radius * math.sin(math.atan(mu))
    assert math.hypot(x[0], x[2]) <= cone + 1e-9
    assert cone < b.contact_epsilon
    assert abs(np.linalg.norm(x - center) - radius) < b.contact_epsilon  # on the bowl's surface
    assert np.linalg.norm(x - [0.0, 0.0, 0.0]) < b.contact_epsilon  # so at the lowest point
    assert np.linalg.norm(v) < 1e-9  # at rest (the friction branch sets v = 0 exactly)


def test_particle_outside_bowl_passes(device):
    # A bowl holds what is inside it: a particle falling past the outside of the sphere below the
    # cut is not pulled through the wall; it falls freely.
    b = ModelBuilder(gravity=(0.0, -G, 0.0))
    b.add_particles([[1.2, 0.5, 0.0]], [0.0, 0.0, 0.0], 1.0)
    b.add_bowl([0.0, 1.0, 0.0], 1.0, cut_height=1.0, restitution=0.5, friction=0.3)
    q, _ = _run(b, "rk4", 0.01, 50, device)
    assert q[0, 1] == pytest.approx(0.5 - 0.5 * G * 0.5**2, abs=1e-9)  # y0 - g t^2 / 2


def test_particle_slides_off_sphere_at_closed_form_angle(device):
    # Frictionless particle released at rest on a solid sphere, theta0 from the top. Energy:
    # v^2 = 2 g R (cos theta0 - cos theta); it leaves when gravity's normal part no longer supplies
    # the centripetal force, g cos theta = v^2 / R, i.e. at cos theta = (2/3) cos theta0.
    radius, theta0, dt = 1.0, 0.1, 1e-3
    b = ModelBuilder(gravity=(0.0, -G, 0.0))
    b.add_particles([[radius * math.sin(theta0), radius * math.cos(theta0), 0.0]], [0.0, 0.0, 0.0], 1.0)
    b.add_sphere([0.0, 0.0, 0.0], radius, restitution=0.0, friction=0.0)
    left = {}

    def record(k, q, qd):
        x, v = q[0], qd[0]
        n = x / np.linalg.norm(x)
        # On the surface the contact cancels every approaching normal velocity (leaving float64
        # rounding, ~1e-16 |v|), so the first state moving away from the sphere is the detachment.
        if np.dot(v, n) > 1e-12:
            left["cos"], left["speed"] = n[1], np.linalg.norm(v)
            return True
        return False

    _run(b, "symplectic", dt, 3000, device, record=record)
    expected = 2.0 / 3.0 * math.cos(theta0)
    # The detection lags the true point by at most one step: |d cos| <= sin(theta) |v| h / R.
    tol = math.sqrt(1.0 - expected**2) * left["speed"] * dt / radius
    assert left["cos"] == pytest.approx(expected, abs=tol)
    assert left["cos"] < math.cos(theta0)  # it did slide before leaving


def test_seed_bowl_rk4_stays_in_bowl():
    # The 2023 scene, 5 s of RK4 at dt = 0.001 (float32, CPU): no explosion, and the jelly is in the
    # bowl: its centre of mass within the hole's radius 9/sqrt(2) of the bowl's axis through (2, *, 1).
    scene = load_scene("seed_bowl", ["simulation.integrator=\"rk4\"", "simulation.duration=5.0", "simulation.fps=10"])
    model = build_model(scene, device="cpu")
    sim = Simulator(model, ExplicitIntegrator(model, "rk4"), scene.sim["dt"], scene.sim["fps"], scene.frame_count())
    result = sim.run()
    assert not result.exploded and result.frames_written == scene.frame_count() + 1
    com = np.asarray(result.metrics[-1].com)
    assert result.metrics[-1].time == pytest.approx(5.0)
    assert math.hypot(com[0] - 2.0, com[2] - 1.0) < 9.0 / math.sqrt(2.0)
    # It is not still on the plane where it started (the hole is the only way down to y < 0).
    assert min(m.com[1] for m in result.metrics) < 0.0


def test_terrain_meshes_lie_on_their_surfaces():
    b = ModelBuilder()
    b.add_bowl([2.0, 6.0, 1.0], 9.0, cut_height=0.0)
    b.add_sphere([0.0, -1.0, 0.0], 3.0)
    model = b.finalize("cpu")
    (bowl_path, bp, bc, bi), (sphere_path, sp, sc, si) = model.terrain_meshes()
    assert bowl_path == "/World/Bowl_0" and sphere_path == "/World/Sphere_0"
    np.testing.assert_allclose(np.linalg.norm(bp - [2.0, 6.0, 1.0], axis=1), 9.0, rtol=1e-12)
    assert bp[:, 1].max() == pytest.approx(0.0, abs=1e-12)  # the rim is on the cut
    np.testing.assert_allclose(np.linalg.norm(sp - [0.0, -1.0, 0.0], axis=1), 3.0, rtol=1e-12)
    assert bc.sum() == len(bi) and sc.sum() == len(si)
    # The sphere mesh is closed: its signed volume is close to 4/3 pi r^3 (outward winding, > 0).
    tris = []
    start = 0
    for c in sc:
        f = si[start : start + c]
        tris += [(f[0], f[j], f[j + 1]) for j in range(1, c - 1)]
        start += c
    v = sp[np.array(tris)] - [0.0, -1.0, 0.0]
    volume = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0
    assert volume == pytest.approx(4.0 / 3.0 * math.pi * 27.0, rel=0.03)
