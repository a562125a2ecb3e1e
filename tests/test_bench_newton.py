"""The Newton peer benchmark simulates the same physics: free fall and resting on the ground.

Skipped unless Newton (the ``bench`` extra) is installed.
"""

import numpy as np
import pytest

pytest.importorskip("newton")

from softsim_warp.studies.bench_newton import NewtonJelly, newton_steps_per_second, newton_version
from softsim_warp.core.lattice import lattice_points, lattice_springs

G = 9.81


def _jelly(n=4, size=0.3, height=1.0):
    points = lattice_points((n, n, n), (size, size, size)) + np.array([0.0, height, 0.0])
    pairs, _ = lattice_springs((n, n, n))
    rest = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    return points, pairs, rest


def test_newton_version():
    assert newton_version().startswith("1.")


def test_free_fall_of_center_of_mass():
    """Before contact the centre of mass falls by 1/2 g t^2, whatever the springs do.

    The particles start with random zero-mean velocities, so the springs stretch, compress and
    damp; spring forces are equal and opposite, so only gravity moves the centre of mass.
    Symplectic Euler drops it by g h^2 k (k + 1) / 2 after k steps, within 1/k of 1/2 g t^2.
    """
    points, pairs, rest = _jelly(height=1.0)
    n = len(points)
    rng = np.random.default_rng(0)
    vel = rng.normal(scale=0.05, size=(n, 3)).astype(np.float32)
    vel -= vel.mean(axis=0)
    dt, steps = 1.0e-4, 2000  # t = 0.2 s, drop 0.196 m; the bottom (y = 0.85) stays clear of y = 0
    jelly = NewtonJelly(points, pairs, rest, 1000.0, 1.0, np.full(n, 0.01), (0.0, -G, 0.0), 0.0, "cpu", velocities=vel)
    y0 = jelly.positions()[:, 1].mean()
    jelly.step(dt, steps)
    q = jelly.positions()
    assert int(jelly.contacts.soft_contact_count.numpy()[0]) == 0
    assert q[:, 1].min() > 0.5
    drop = y0 - q[:, 1].mean()
    t = dt * steps
    assert drop == pytest.approx(0.5 * G * t * t, rel=1e-3)
    assert drop == pytest.approx(G * dt * dt * steps * (steps + 1) / 2, rel=1e-4)
    # The springs did act: the lattice moved relative to its centre of mass but stayed intact.
    rel = (q - q.mean(axis=0)) - (points - points.mean(axis=0))
    assert 1e-4 < np.abs(rel).max() < 0.05
    # Sideways the centre of mass keeps its (zero) initial momentum.
    assert np.abs(q[:, [0, 2]].mean(axis=0) - points[:, [0, 2]].mean(axis=0)).max() < 1e-5


def test_jelly_comes_to_rest_on_ground():
    points, pairs, rest = _jelly(height=0.4)
    n = len(points)
    ground, mass, ke = -0.1, 0.01, 1.0e3
    jelly = NewtonJelly(
        points, pairs, rest, 200.0, 0.5, np.full(n, mass), (0.0, -G, 0.0), ground, "cpu", contact_ke=ke, contact_kd=5.0
    )
    jelly.step(1.0e-3, 2000)
    q, v = jelly.positions(), jelly.velocities()
    # Penalty contact: the bottom layer sinks by about (total weight) / (ke * bottom particles).
    sink = n * mass * G / (ke * 16)
    assert q[:, 1].min() > ground - 3 * sink
    assert q[:, 1].min() < ground + sink
    assert np.abs(v).max() < 1e-2
    # It rests upright, about its own height above the ground.
    assert q[:, 1].mean() == pytest.approx(ground + 0.15, abs=0.01)


@pytest.mark.parametrize("use_graph", [False, True])
def test_steps_per_second_runs(use_graph):
    points, pairs, rest = _jelly()
    n = len(points)
    r = newton_steps_per_second(
        points, pairs, rest, 1000.0, 1.0, np.full(n, 0.01), 1e-4, (0.0, -G, 0.0), 0.0, "cpu", 10, use_graph, warmup=2
    )
    assert r["steps_per_second"] > 0 and r["ms_per_step"] > 0
    assert r["steps"] >= 10
    assert r["build_seconds"] >= 0 and r["compile_seconds"] >= 0
