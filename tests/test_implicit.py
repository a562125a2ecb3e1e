"""The implicit integrator: linearised backward Euler solved by preconditioned CG on the device.

References that cannot agree by accident: a dense float64 NumPy solve of the same linear system
built independently from the spring list, the energy balance of backward Euler, the measured
convergence order against RK4, the linear stability limit of explicit Euler, and float64 runs.
"""

import json

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels import implicit as implicit_kernels

from softsim_warp.commands.cli import main as cli_main
from softsim_warp.core.implicit import ImplicitIntegrator
from softsim_warp.core.integrators import ExplicitIntegrator
from softsim_warp.core.stepper import make_integrator
from softsim_warp.core.model import ModelBuilder, build_model, populate
from softsim_warp.io.scene import load_scene
from softsim_warp.io.metrics import MetricsProbe
from softsim_warp.io.simulate import Simulator
from softsim_warp.core.stability_analysis import lattice_jacobians, predict_lattice_dt, step_spectral_radius

EPS32 = float(np.finfo(np.float32).eps)
SPRING_TYPES = ("structural", "shear", "bending")


def _state(model, q, qd):
    s = model.state()
    s.particle_q = wp.array(np.asarray(q), dtype=model.vec3, device=model.device)
    s.particle_qd = wp.array(np.asarray(qd), dtype=model.vec3, device=model.device)
    return s


def _spring_forces(q, v, pairs, rest, ks, kd):
    """Spring and damper forces in float64 NumPy: f_a = -(ks (|d| - r) + kd (v_a - v_b).d^) d^, f_b = -f_a."""
    d = q[pairs[:, 0]] - q[pairs[:, 1]]
    length = np.linalg.norm(d, axis=1)
    dhat = d / length[:, None]
    mag = ks * (length - rest) + kd * np.einsum("ij,ij->i", v[pairs[:, 0]] - v[pairs[:, 1]], dhat)
    f = np.zeros_like(q)
    np.add.at(f, pairs[:, 0], -mag[:, None] * dhat)
    np.add.at(f, pairs[:, 1], mag[:, None] * dhat)
    return f


def _dense_system(x, v, pairs, rest, ks, kd, mass, gravity, h, linearization, clamp=True, kv_term=True):
    """A and b of one step, assembled densely from the springs, independently of the kernels.

    Baraff-Witkin: (M - h C - h^2 K) dv = h (f(x, v) + M g + h K v), C and K at x.
    Predictor: (M - h C - h^2 K) dv = h (f(x + h v, v) + M g), C and K at x + h v.
    Per spring, with d = x_a - x_b: -K_aa = ks [d^d^T + max(0, 1 - r/|d|)(I - d^d^T)] (the clamp is the
    definiteness fix), -C_aa = kd d^d^T, and the a-b blocks are the negatives.
    """
    n = len(x)
    X = x if linearization == "baraff_witkin" else x + h * v
    A = np.zeros((3 * n, 3 * n))
    b = np.zeros(3 * n)
    eye = np.eye(3)
    for s, (i, j) in enumerate(pairs):
        d = X[i] - X[j]
        length = np.linalg.norm(d)
        dhat = d / length
        P = np.outer(dhat, dhat)
        t = 1.0 - rest[s] / length
        if clamp:
            t = max(t, 0.0)
        S = ks[s] * (P + t * (eye - P))
        B = h * kd[s] * P + h * h * S
        for r, c, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            A[3 * r : 3 * r + 3, 3 * c : 3 * c + 3] += sign * B
        if linearization == "baraff_witkin" and kv_term:
            t_kv = h * h * (S @ (v[i] - v[j]))
            b[3 * i : 3 * i + 3] -= t_kv
            b[3 * j : 3 * j + 3] += t_kv
    f = _spring_forces(X, v, pairs, rest, ks, kd)
    b += h * (f + mass[:, None] * gravity).ravel()
    A += np.diag(np.repeat(mass, 3))
    return A, b


def _perturbed_lattice(precision="float32", with_anchor=True, seed=0, device="cpu"):
    """A 3x3x3 jelly, perturbed and moving at random, plus a fixed anchor particle on a spring."""
    rng = np.random.default_rng(seed)
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    springs = {
        "structural": {"ks": 300.0, "kd": 0.4},
        "shear": {"ks": 200.0, "kd": 0.3},
        "bending": {"ks": 100.0, "kd": 0.2},
    }
    b.add_jelly((3, 3, 3), 0.3, 0.02, springs, center=(0.0, 0.5, 0.0))
    if with_anchor:
        anchor = b.add_particles([[0.0, 0.9, 0.0]], [0.0, 0.0, 0.0], 0.0)  # mass 0: fixed
        b.add_spring([anchor], [0], 150.0, 0.2, rest=0.2)
    model = b.finalize(device, precision)
    q = model.particle_q_host.copy()
    free = model.particle_mass_host > 0
    # Perturb by up to 12 % of the spacing: some springs compress, so the clamp matters.
    q[free] += rng.uniform(-0.018, 0.018, (free.sum(), 3))
    v = np.zeros_like(q)
    v[free] = rng.normal(0.0, 0.5, (free.sum(), 3))
    return model, q, v


def _dense_step(model, q, v, h, tol, linearization):
    """One backward Euler step of ``model`` from (q, v) solved densely in float64: (dv*, the bound on
    |dv - dv*| of a float32 solve to CG tolerance ``tol``, and the dense system's parts)."""
    pairs = model.spring_indices_host
    rest, ks, kd = model.spring_rest_host, model.spring_stiffness_host, model.spring_damping_host
    mass = model.particle_mass_host
    free = np.repeat(mass > 0, 3)
    A, b = _dense_system(q, v, pairs, rest, ks, kd, mass, model.gravity_host, h, linearization)
    Aff = A[np.ix_(free, free)]
    dv_ref = np.zeros(3 * len(q))
    dv_ref[free] = np.linalg.solve(Aff, b[free])  # fixed particles: dv = 0

    # |dv - dv*| <= |A^-1| (|r| + |db| + |dA| |dv|): CG stops at |r| <= tol |b|; float32 rounds each
    # term of b (spring forces ks |d|, dampers, gravity) and of A dv (blocks times dv, summed over the
    # <= G springs of a particle) to about G eps32 of its magnitude.
    lam_min = np.linalg.eigvalsh(Aff)[0]
    springs_per_particle = np.bincount(pairs.ravel(), minlength=len(q)).max()
    d = q[pairs[:, 0]] - q[pairs[:, 1]]
    term_scale = h * (
        ks * (np.linalg.norm(d, axis=1) + rest) + kd * np.linalg.norm(v[pairs[:, 0]] - v[pairs[:, 1]], axis=1)
    )
    db = np.sqrt(len(pairs)) * term_scale.max() + np.linalg.norm(h * mass * np.linalg.norm(model.gravity_host))
    dA = np.abs(Aff).sum(axis=1).max()
    bound = (
        tol * np.linalg.norm(b[free]) + (springs_per_particle + 2) * EPS32 * (db + dA * np.linalg.norm(dv_ref))
    ) / lam_min
    return dv_ref, bound, (pairs, rest, ks, kd, mass, free)


@pytest.mark.parametrize("linearization", ["baraff_witkin", "predictor"])
def test_one_step_equals_dense_float64_solve(device, linearization):
    model, q, v = _perturbed_lattice(device=device)
    # The float32 state is the common input; the reference reads it exactly in float64.
    q = q.astype(np.float32).astype(np.float64)
    v = v.astype(np.float32).astype(np.float64)
    h = 0.01
    tol = 1.0e-6
    integ = ImplicitIntegrator(model, cg_tolerance=tol, cg_max_iterations=1000, linearization=linearization)
    s0, s1 = _state(model, q, v), _state(model, q, v)
    s1.particle_q.fill_(np.inf)  # poison: every particle must be written
    s1.particle_qd.fill_(np.inf)
    integ.step(s0, s1, h)
    assert integ.stats()["cg_unconverged_solves"] == 0
    dv = s1.particle_qd.numpy().astype(np.float64) - v
    dv_ref, bound, (pairs, rest, ks, kd, mass, free) = _dense_step(model, q, v, h, tol, linearization)
    err = np.linalg.norm(dv.ravel() - dv_ref)
    assert err <= bound, (err, bound)
    # The bound is tight enough to see the parts of the system: without the definiteness clamp or
    # (Baraff-Witkin) without the h^2 K v term, the solution moves by far more than the bound.
    A2, b2 = _dense_system(
        q, v, pairs, rest, ks, kd, mass, model.gravity_host, h, linearization, clamp=False, kv_term=False
    )
    other = np.linalg.solve(A2[np.ix_(free, free)], b2[free])
    assert np.linalg.norm(other - dv_ref[free]) > 10.0 * bound
    # Positions follow x_{n+1} = x_n + h v_{n+1}.
    np.testing.assert_allclose(
        s1.particle_q.numpy(), (q + h * (v + dv_ref.reshape(-1, 3))).astype(np.float32), atol=h * bound + 4 * EPS32
    )


def test_coincident_particles_stay_finite(device):
    # |d| = 0: the spring has no direction; force and Jacobian are defined as 0, not 0/0.
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    b.add_particles([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], [0.0, 0.0, 0.0], 0.1)
    b.add_spring([0], [1], 1.0e4, 1.0, rest=0.1)
    model = b.finalize(device)
    integ = ImplicitIntegrator(model)
    s0, s1 = model.state(), model.state()
    integ.step(s0, s1, 0.01)
    # With no spring force, both particles fall freely: v = h g, x = x_0 + h^2 g (backward Euler).
    np.testing.assert_allclose(s1.particle_qd.numpy(), [[0.0, -0.098, 0.0]] * 2, rtol=1e-6)
    np.testing.assert_allclose(s1.particle_q.numpy(), [[0.0, 1.0 - 0.00098, 0.0]] * 2, rtol=1e-6)


def _stiff_overrides(ks):
    return [f"jelly.0.springs.{t}.ks={ks}" for t in SPRING_TYPES]


@pytest.mark.parametrize("ks", [1.0e5, 1.0e6])
def test_stiff_jelly_drop_is_stable_at_dt_0_01(device, ks):
    # The jelly_drop scene (ground contact, restitution 0.5, friction 0.5) with every spring type
    # at ks, one second at dt = 0.01: the fall, the impact and settling on the ground.
    scene = load_scene("jelly_drop", _stiff_overrides(ks))
    model = build_model(scene, device)
    integ = make_integrator("implicit", model)
    sim = Simulator(model, integ, dt=0.01, fps=50.0, frames=50)
    result = sim.run()
    assert not result.exploded and result.frames_written == 51
    final = sim.state.particle_q.numpy()
    assert np.isfinite(final).all()
    tol = integ.cg_tolerance
    for prev, m in zip(result.metrics, result.metrics[1:], strict=False):
        # Nothing supplies energy, so it never rises between frames: the contact solve's normal
        # constraints do no work, friction is a damper, and the restitution impulse returns at
        # most what the contact solve removed. Allowed: the CG tolerance's share of the energy
        # (CG stops at |r| <= tol |b|). (The post-step response alone let springs squeezed by the
        # impact invert the lattice: 4e4 J from 10 J at ks = 1e5.)
        assert m.total_energy <= prev.total_energy + tol * abs(prev.total_energy), (m.frame, m.total_energy, prev)
        assert m.com[1] > 0.0
    # The jelly keeps its shape: no particle farther from the centre of mass than the half-diagonal
    # of the 0.5 m cube, plus a 5 % strain margin.
    com = final.mean(axis=0)
    assert np.linalg.norm(final - com, axis=1).max() <= 1.05 * 0.25 * np.sqrt(3.0)
    assert final[:, 1].min() >= -model.contact_epsilon


def _free_flight_jelly(ks, precision):
    """The jelly_drop jelly without the ground, spinning and breathing (a non-rigid velocity field)."""
    scene = load_scene("jelly_drop", _stiff_overrides(ks))
    data = scene.data
    data["plane"] = []
    b = ModelBuilder(scene.sim["gravity"])
    populate(b, data)
    model = b.finalize("cpu", precision)
    q = model.particle_q_host
    c = q.mean(axis=0)
    v = np.cross([2.0, 4.0, 1.0], q - c) + 0.5 * (q - c) * np.array([1.0, -0.5, 0.3])
    return model, q, v


@pytest.mark.parametrize("ks", [1.0e5, 1.0e6])
def test_energy_never_increases_in_free_flight(ks):
    # No work is done on a jelly in free flight (gravity is in the total as potential energy), and
    # backward Euler only removes energy: for a quadratic energy, E_{n+1} - E_n =
    # -1/2 |v_{n+1} - v_n|_M^2 - 1/2 h^2 |v_{n+1}|_K^2 - h v^T C v <= 0 (free fall alone loses
    # 1/2 m h^2 g^2 per particle and step). Run in float64 with a CG tolerance of 1e-10, so that the
    # only allowed increase is the rounding of the energy sums: (particles + springs) eps64 times
    # the sum of the energies' magnitudes.
    model, q, v = _free_flight_jelly(ks, "float64")
    integ = ImplicitIntegrator(model, cg_tolerance=1.0e-10, cg_max_iterations=1000)
    probe = MetricsProbe(model)
    s0, s1 = _state(model, q, v), model.state()
    terms = model.particle_count + model.spring_count
    eps64 = float(np.finfo(np.float64).eps)
    prev = probe.measure(s0, 0, 0.0)
    for k in range(30):
        integ.step(s0, s1, 0.01)
        s0, s1 = s1, s0
        m = probe.measure(s0, k + 1, 0.01 * (k + 1))
        rounding = terms * eps64 * (m.kinetic_energy + abs(m.gravity_energy) + m.spring_energy)
        assert m.total_energy <= prev.total_energy + rounding, (k, m.total_energy - prev.total_energy, rounding)
        prev = m
    assert integ.stats()["cg_unconverged_solves"] == 0


def test_baraff_witkin_linearization_gains_energy_when_spinning():
    # Documented behaviour, not a wish: linearised about x_n, a spring rotated by h omega is
    # stretched to second order, ~h^2 omega^2 |d| / 2 per step, which the first-order model does
    # not see; with ks = 1e5 the spinning jelly more than doubles its energy in the first step.
    model, q, v = _free_flight_jelly(1.0e5, "float32")
    probe = MetricsProbe(model)
    energies = {}
    for lin in ("baraff_witkin", "predictor"):
        integ = ImplicitIntegrator(model, linearization=lin)
        s0, s1 = _state(model, q, v), model.state()
        e0 = probe.measure(s0, 0, 0.0).total_energy
        integ.step(s0, s1, 0.01)
        energies[lin] = probe.measure(s1, 1, 0.01).total_energy - e0
    assert energies["baraff_witkin"] > 1.0  # J, against ~13 J in the jelly
    assert energies["predictor"] < 0.0


@pytest.mark.parametrize("ks", [1.0e5, 1.0e6])
def test_implicit_step_is_ten_times_the_euler_limit(ks):
    # Explicit Euler's largest stable step for the jelly_drop jelly, from the linear analysis of a
    # 4x4x4 lattice with its spacing, masses and springs (the stiffest modes are local).
    scene = load_scene("jelly_drop", _stiff_overrides(ks))
    j = scene.jellies[0]
    spacing = j["size"][0] / (j["resolution"][0] - 1)
    kd = {t: j["springs"][t]["kd"] for t in SPRING_TYPES}
    pred = predict_lattice_dt((4, 4, 4), 3 * spacing, j["particle_mass"], ks, kd, methods=("euler",))["euler"]
    assert 0.0 < pred and 0.01 >= 10.0 * pred
    # The prediction holds in a run of that lattice, seeded with random velocities. Above the
    # limit, the growth per step rho = max |1 + h lambda| is only 1 + O(damping ratio^2), which is
    # why "survival" depends on a run's length: at 10x the limit, run the steps that the analysis
    # says multiply the fastest mode by 1e4 and see the speed grow by > 1e2 (the random start puts
    # only part of its energy in that mode); at half the limit every vibration decays and only the
    # rigid motion is left.
    K, C, masses = lattice_jacobians((4, 4, 4), 3 * spacing, j["particle_mass"], ks, kd)
    rho = step_spectral_radius("euler", 10.0 * pred, K, C, masses)
    b = ModelBuilder((0.0, 0.0, 0.0))
    b.add_jelly((4, 4, 4), 3 * spacing, j["particle_mass"], j["springs"])
    model = b.finalize("cpu")
    rng = np.random.default_rng(1)
    # 5 cm/s: well above the vibration that float32 rounding of the rest lattice starts by itself
    # (position rounding ~1e-7 m times omega ~3e4 rad/s at ks = 1e6).
    v0 = rng.normal(0.0, 0.05, (model.particle_count, 3))
    speed0 = np.linalg.norm(v0, axis=1).max()
    steps = int(np.ceil(np.log(1.0e4) / np.log(rho)))
    for factor, unstable in ((10.0, True), (0.5, False)):
        integ = ExplicitIntegrator(model, "euler")
        s0, s1 = _state(model, model.particle_q_host, v0), model.state()
        for _ in range(steps):
            integ.step(s0, s1, factor * pred)
            s0, s1 = s1, s0
        v = s0.particle_qd.numpy()
        speed = np.linalg.norm(v, axis=1).max() if np.isfinite(v).all() else np.inf
        if unstable:
            assert speed > 100.0 * speed0, (factor, steps, speed, speed0)
        else:
            assert speed < speed0, (factor, steps, speed, speed0)
    # Backward Euler from the same start at the scene's 0.01 s, ten times explicit Euler's limit and
    # more: every vibration decays, and only the rigid motion is left.
    integ = ImplicitIntegrator(model, cg_tolerance=1.0e-6, cg_max_iterations=500)
    s0, s1 = _state(model, model.particle_q_host, v0), model.state()
    for _ in range(20):
        integ.step(s0, s1, 0.01)
        s0, s1 = s1, s0
    v = s0.particle_qd.numpy()
    assert np.isfinite(v).all()
    assert np.linalg.norm(v, axis=1).max() < speed0

    def vibration(x, u):
        """u less its best rigid motion a + w x (x - c) (least squares): the part that deforms."""
        r = x - x.mean(0)
        skew = np.zeros((len(r), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = r[:, 2], -r[:, 1], r[:, 0]
        skew -= skew.transpose(0, 2, 1)  # w x r = skew @ w
        basis = np.concatenate([np.tile(np.eye(3), (len(r), 1)), skew.reshape(-1, 3)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, u.reshape(-1), rcond=None)
        return np.linalg.norm(u.reshape(-1) - basis @ coef)

    assert vibration(s0.particle_q.numpy(), v) < 1.0e-2 * vibration(model.particle_q_host, v0)


def oscillator_energy_per_period(h_omega: float, precision="float64") -> tuple[float, float]:
    """(measured, predicted) energy kept after one period by an undamped spring oscillator.

    One particle (mass 1 kg) on a spring (ks = 100 N/m, kd = 0) to a fixed particle, no gravity,
    started 1 cm from rest length along the spring: omega = 10 rad/s, h = h_omega / omega. Backward
    Euler maps z = x + i v / omega to z / (1 - i h omega), so the energy (k |z|^2 / 2) keeps the factor
    1 / (1 + (h omega)^2) every step, (1 + (h omega)^2)^(-2 pi / (h omega)) over one period.
    """
    omega = 10.0
    h = h_omega / omega
    steps = round(2.0 * np.pi / h_omega)
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particles([[0.0, 0.0, 0.0], [1.01, 0.0, 0.0]], [0.0, 0.0, 0.0], [0.0, 1.0])
    b.add_spring([0], [1], omega**2, 0.0, rest=1.0)
    model = b.finalize("cpu", precision)
    integ = ImplicitIntegrator(model, cg_tolerance=1.0e-12, cg_max_iterations=10)
    probe = MetricsProbe(model)
    s0, s1 = model.state(), model.state()
    e0 = probe.measure(s0, 0, 0.0).total_energy
    for _ in range(steps):
        integ.step(s0, s1, h)
        s0, s1 = s1, s0
    return probe.measure(s0, 1, steps * h).total_energy / e0, (1.0 + h_omega**2) ** (-steps)


@pytest.mark.parametrize("h_omega", [0.05, 0.2, 1.0])
def test_undamped_oscillator_loses_energy_as_backward_euler_predicts(h_omega):
    # The artificial damping of docs/IMPLICIT.md: the energy kept after one period (rounded to whole
    # steps) equals the closed form. Motion stays on the spring's axis, where the spring is linear,
    # so the linearised step is backward Euler exactly; float64 and a CG tolerance of 1e-12 leave
    # ~1e-12 relative error per step.
    measured, predicted = oscillator_energy_per_period(h_omega)
    assert measured == pytest.approx(predicted, rel=1e-9)


def _converging_jelly():
    """A 4x4x4 jelly in free flight, spinning and breathing: smooth, no contact."""
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    springs = {
        "structural": {"ks": 60.0, "kd": 0.05},
        "shear": {"ks": 40.0, "kd": 0.05},
        "bending": {"ks": 20.0, "kd": 0.02},
    }
    b.add_jelly(
        (4, 4, 4),
        0.3,
        0.05,
        springs,
        center=(0, 1, 0),
        axis=(1, 1, 0),
        degrees=15,
        angular_velocity=(1.0, 2.0, 0.5),
        velocity=(0.3, 0.5, 0.0),
    )
    model = b.finalize("cpu", "float64")
    q = model.particle_q_host
    v = model.particle_qd.numpy() + 1.5 * (q - q.mean(axis=0)) * np.array([1.0, -0.5, 0.3])
    return model, q, v


def _positions_at(model, integ, q, v, dt, t_end):
    s0, s1 = _state(model, q, v), model.state()
    for _ in range(round(t_end / dt)):
        integ.step(s0, s1, dt)
        s0, s1 = s1, s0
    return s0.particle_q.numpy()


def test_first_order_convergence_to_rk4():
    # Backward Euler is first order: halving dt halves the error against an RK4 reference whose own
    # error (order 4, at dt = 2e-4) is ~1e-12 m, far below the implicit errors (~1e-3 m).
    model, q, v = _converging_jelly()
    t_end = 0.4
    ref = _positions_at(model, ExplicitIntegrator(model, "rk4"), q, v, 2.0e-4, t_end)
    errors = []
    for dt in (4.0e-3, 2.0e-3, 1.0e-3):
        integ = ImplicitIntegrator(model, cg_tolerance=1.0e-10, cg_max_iterations=500)
        errors.append(np.abs(_positions_at(model, integ, q, v, dt, t_end) - ref).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    # error ~ C dt^p: p = log2(e(2 dt) / e(dt)); measured 0.87 and 0.92 (approaching 1 from below).
    assert np.all(np.abs(orders - 1.0) <= 0.25), orders


def test_float64_agrees_with_float32():
    # Ten steps of a stiff 4x4x4 jelly in free flight, both precisions. Each float32 step perturbs
    # the positions by rounding (|x| eps32 per coordinate, times the ~G springs summed per particle)
    # and by the CG tolerance (|dv_err| <= tol |b| / m_min, moving x by h |dv_err|); backward Euler
    # does not amplify perturbations, so after N steps the runs differ by at most N times that.
    steps, h, tol = 10, 0.01, 1.0e-6
    out = {}
    for precision in ("float32", "float64"):
        b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
        springs = {t: {"ks": 1.0e4, "kd": 0.1} for t in SPRING_TYPES}
        b.add_jelly(
            (4, 4, 4), 0.3, 0.01, springs, center=(0, 1, 0), axis=(0, 0, 1), degrees=10, angular_velocity=(0, 0, 3.0)
        )
        model = b.finalize("cpu", precision)
        integ = ImplicitIntegrator(
            model, cg_tolerance=tol if precision == "float32" else 1.0e-12, cg_max_iterations=1000
        )
        s0, s1 = model.state(), model.state()
        bnorm = []
        for _ in range(steps):
            integ.step(s0, s1, h)
            s0, s1 = s1, s0
            bnorm.append(np.sqrt(float(integ.scalars.numpy()[implicit_kernels.BB])))
        out[precision] = (s0.particle_q.numpy().astype(np.float64), max(bnorm), model)
    x32, b32, model = out["float32"]
    x64 = out["float64"][0]
    springs_per_particle = np.bincount(model.spring_indices_host.ravel()).max()
    per_step = springs_per_particle * EPS32 * np.abs(x64).max() + h * tol * b32 / model.particle_mass_host.min()
    assert np.abs(x32 - x64).max() <= steps * per_step, (np.abs(x32 - x64).max(), steps * per_step)


def test_solvers_agree(device):
    # The assembled block-sparse matrix (own loop and warp.optim.linear.cg) solves the same system:
    # each solver's step lies within the float32 CG bound of the dense float64 solve.
    model, q, v = _perturbed_lattice(with_anchor=True, device=device)
    q = q.astype(np.float32).astype(np.float64)
    v = v.astype(np.float32).astype(np.float64)
    h, tol = 0.01, 1.0e-6
    for solver in ("matrix_free", "bsr", "warp_cg"):
        integ = ImplicitIntegrator(model, solver=solver, cg_tolerance=tol, cg_max_iterations=1000)
        s0, s1 = _state(model, q, v), model.state()
        integ.step(s0, s1, h)
        assert integ.stats()["cg_iterations_mean"] > 0 and integ.stats()["cg_unconverged_solves"] == 0
        dv_ref, bound, _ = _dense_step(model, q, v, h, tol, integ.linearization)
        err = np.linalg.norm((s1.particle_qd.numpy().astype(np.float64) - v).ravel() - dv_ref)
        assert err <= bound, (solver, err, bound)


def test_cli_runs_implicit_and_reports_cg_iterations(tmp_path):
    out, metrics = tmp_path / "x.usdc", tmp_path / "x.json"
    overrides = []
    for item in _stiff_overrides(1.0e5) + ["implicit.cg_tolerance=1e-5", "implicit.newton_iterations=1"]:
        overrides += ["--set", item]
    rc = cli_main(
        [
            "run",
            "jelly_drop",
            "--integrator",
            "implicit",
            *overrides,
            "--dt",
            "0.01",
            "--frames",
            "3",
            "--fps",
            "50",
            "--out",
            str(out),
            "--metrics",
            str(metrics),
            "--quiet",
        ]
    )
    assert rc == 0 and out.exists()
    summary = json.loads(metrics.read_text())["summary"]
    assert summary["integrator"] == "implicit" and summary["cg_tolerance"] == 1e-5
    # Three frames at 50 fps and dt = 0.01: two steps per frame, six steps, each at least one solve.
    assert summary["steps"] == 6 and summary["cg_steps"] == 6
    assert summary["cg_solves"] >= 6 and summary["cg_iterations_mean"] > 0 and summary["cg_unconverged_solves"] == 0


@pytest.mark.parametrize(
    "item, message",
    [
        ("implicit.cg_tolerance=0", "implicit.cg_tolerance: must be a finite number > 0 and < 1 (got 0)"),
        ("implicit.newton_iterations=0", "implicit.newton_iterations: must be an integer >= 1 (got 0)"),
        ("implicit.linearization=exact", "implicit.linearization: must be one of predictor, baraff_witkin"),
        ("implicit.cg_maxiter=5", "implicit.cg_maxiter: unknown key; did you mean 'cg_max_iterations'?"),
    ],
)
def test_bad_implicit_settings_are_one_line_errors(tmp_path, capsys, item, message):
    rc = cli_main(
        [
            "run",
            "jelly_drop",
            "--integrator",
            "implicit",
            "--set",
            item,
            "--frames",
            "1",
            "--out",
            str(tmp_path / "x.usdc"),
            "--quiet",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err


def _falling_particle_rebound(restitution, h=0.01):
    """(approach speed, rebound speed, tangential speed after) of one particle bouncing on a plane, implicit."""
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    b.add_particles([[0.0, 0.5, 0.0]], [[0.3, 0.0, 0.0]], 0.01)
    b.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=restitution, friction=0.0)
    model = b.finalize("cpu", "float64")
    integ = ImplicitIntegrator(model)
    s0, s1 = model.state(), model.state()
    for _ in range(100):
        integ.step(s0, s1, h)
        v0, v1 = s0.particle_qd.numpy()[0], s1.particle_qd.numpy()[0]
        if v1[1] > 0.0 > v0[1]:
            # The approach velocity is the free step's, v_n + h g, as the response sees it.
            return -(v0[1] - 9.8 * h), v1[1], v1[0]
        s0, s1 = s1, s0
    raise AssertionError("no bounce")


@pytest.mark.parametrize("restitution", [0.3, 0.5, 0.8, 1.0])
def test_free_particle_rebounds_with_restitution(restitution):
    # One particle, no springs: the contact solve stops it (v_n = 0 at x_c = x_n + h v_c) and the
    # restitution impulse gives it back e v_in, capped by the energy the contact solve removed:
    # 1/2 m v_in^2 minus the gravity energy m g h v_in that stopping it above x_free costs. So
    # v_out = min(e, sqrt(1 - 2 g h / v_in)) v_in; e = 1 hits the cap.
    h = 0.01
    v_in, v_out, v_t = _falling_particle_rebound(restitution, h)
    expected = min(restitution, np.sqrt(1.0 - 2.0 * 9.8 * h / v_in)) * v_in
    assert v_out == pytest.approx(expected, rel=1e-10)
    assert v_t == pytest.approx(0.3, rel=1e-12)  # frictionless: the tangential velocity is kept


def test_stiff_cube_flat_impact_converges_to_rigid_restitution():
    # A 4x4x4 cube falling flat on a frictionless plane: as a rigid body it leaves with e v_in.
    # Its springs yield within the step by a relative amount ~ m / (h^2 ks), so the error of the
    # rebound falls as 1/ks: a tenth per decade of stiffness (measured 2.2e-2, 2.2e-3, 2.2e-4).
    h, e, m = 0.01, 0.5, 0.01
    errors = []
    for ks in (1.0e4, 1.0e5, 1.0e6):
        b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
        b.add_jelly((4, 4, 4), 0.3, m, {t: {"ks": ks, "kd": 0.1} for t in SPRING_TYPES}, center=(0.0, 0.3, 0.0))
        b.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=e, friction=0.0)
        model = b.finalize("cpu", "float64")
        integ = ImplicitIntegrator(model, cg_tolerance=1.0e-10, cg_max_iterations=1000)
        s0, s1 = model.state(), model.state()
        for _ in range(40):
            integ.step(s0, s1, h)
            v0, v1 = s0.particle_qd.numpy()[:, 1].mean(), s1.particle_qd.numpy()[:, 1].mean()
            if v1 > 0.0 > v0:
                break
            s0, s1 = s1, s0
        v_in = -(v0 - 9.8 * h)
        errors.append(abs(v1 / (e * v_in) - 1.0))
        assert errors[-1] <= 5.0 * m / (h * h * ks), (ks, errors)
    orders = np.log10(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(orders - 1.0) <= 0.2), (errors, orders)


def test_stiff_seed_bowl_is_stable_at_dt_0_01():
    # seed_bowl (a 1000 kg, 4 m jelly onto a plane with a hole, then into the bowl below;
    # restitution 0.8, friction 0.2) with every spring at ks = 1e5, 5 s at dt = 0.01 (euler fails
    # above 6.1e-4 s here, docs/IMPLICIT.md). Whole-velocity contact constraints would make the bowl's
    # curved contact patch a velocity source (+1e4 J in a frame): this run would explode.
    scene = load_scene("seed_bowl", _stiff_overrides(1.0e5))
    model = build_model(scene, "cpu")
    integ = make_integrator("implicit", model)
    sim = Simulator(model, integ, dt=0.01, fps=10.0, frames=50)
    result = sim.run()
    assert not result.exploded
    q = sim.state.particle_q.numpy()
    assert np.isfinite(q).all()
    tol = integ.cg_tolerance
    for prev, m in zip(result.metrics, result.metrics[1:], strict=False):
        # No work is done on the jelly (see test_stiff_jelly_drop_is_stable_at_dt_0_01).
        assert m.total_energy <= prev.total_energy + tol * abs(prev.total_energy), (m.frame, m.total_energy, prev)
    bowl = scene.data["bowl"][0]
    hole = scene.data["plane"][0]["hole"]
    # It ends in the bowl: its centre of mass over the hole, no particle through the bowl's shell.
    com = result.metrics[-1].com
    offset = np.array(com) - np.array(hole["center"])
    assert np.hypot(offset[0], offset[2]) < hole["radius"]
    below = q[:, 1] < 0.0
    assert below.any()
    dist = np.linalg.norm(q[below] - np.array(bowl["center"]), axis=1)
    assert dist.max() <= bowl["radius"] + model.contact_epsilon
