"""Integrators against closed forms: free fall, a spring's period, energy, momentum."""

import math

import numpy as np
import pytest

from softsim_warp import ModelBuilder, make_integrator
from softsim_warp.core.methods import EXPLICIT_NAMES, method
from tests.helpers import energies, jelly_builder, run_steps

METHODS = list(EXPLICIT_NAMES)  # every registered explicit method
G = np.array([0.0, -9.8, 0.0])


@pytest.mark.parametrize("method", METHODS)
def test_free_fall(device, method):
    # x(t) = x0 + v0 t + g t^2 / 2. Explicit Euler lags by exactly g t h / 2 (x_n = x0 + v0 t + g h^2 n(n-1)/2),
    # symplectic Euler leads by g t h / 2; midpoint and RK4 integrate a quadratic exactly.
    # Soft springs at rest: h omega ~ 0.1, so round-off cannot grow into a visible force within the run.
    b = jelly_builder((2, 2, 2), 0.1, ks=1.0, kd=0.01, gravity=G, velocity=(1.0, 2.0, -0.5))
    model = b.finalize(device, "float64")
    h, n = 1.0e-2, 50
    t = h * n
    q0, v0 = model.particle_q_host, model.particle_qd.numpy()
    final = run_steps(model, method, h, n)
    exact = q0 + v0 * t + 0.5 * G * t * t
    offset = {"euler": -0.5 * G * t * h, "symplectic": 0.5 * G * t * h}.get(method, 0.0)
    np.testing.assert_allclose(final.particle_q.numpy(), exact + offset, atol=1e-12)
    if method in ("euler", "symplectic"):
        assert np.abs(final.particle_q.numpy() - exact).max() == pytest.approx(0.5 * 9.8 * t * h, rel=1e-9)
    np.testing.assert_allclose(final.particle_qd.numpy(), v0 + G * t, atol=1e-12)


def two_particle_spring(device, ks=40.0, mass=0.1, rest=1.0, stretch=0.05, kd=0.0):
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particles([[-0.5 * (rest + stretch), 0, 0], [0.5 * (rest + stretch), 0, 0]], [0, 0, 0], mass)
    b.add_spring(0, 1, ks, kd, rest=rest)
    return b.finalize(device, "float64")


def test_spring_period_and_amplitude(device):
    # Two masses m joined by a spring ks: the separation oscillates about r with omega = sqrt(2 ks / m)
    # (reduced mass m/2) and amplitude equal to the initial stretch A.
    ks, m, A = 40.0, 0.1, 0.05
    omega = math.sqrt(2 * ks / m)
    period = 2 * math.pi / omega
    model = two_particle_spring(device, ks, m, 1.0, A)
    h = period / 400  # h omega = 0.016: rk4's phase error per period ~ (h omega)^4 / 120 * 2 pi, far below 1e-6
    integ = make_integrator("rk4", model)
    a, b = model.state(), model.state()
    sep, times = [], []
    for i in range(2 * 400 + 1):
        q = a.particle_q.numpy()
        sep.append(q[1, 0] - q[0, 0] - 1.0)
        times.append(i * h)
        integ.step(a, b, h)
        a, b = b, a
    sep = np.array(sep)
    np.testing.assert_allclose(sep, A * np.cos(omega * np.array(times)), atol=1e-7)
    # Downward zero crossings (at T/4 and 5T/4), interpolated linearly where the curve is nearly straight.
    down = [times[i] - sep[i] * h / (sep[i + 1] - sep[i]) for i in range(len(sep) - 1) if sep[i] > 0 >= sep[i + 1]]
    assert len(down) == 2
    assert down[1] - down[0] == pytest.approx(period, rel=1e-6)
    assert sep.max() == pytest.approx(A, rel=1e-6)


@pytest.mark.parametrize("name", METHODS)
def test_measured_order_matches_the_registry(device, name):
    # Two masses on a spring along x move linearly: the separation is A cos(omega t) exactly. The
    # integrator's error at t = 0.25 s falls as h^order (the registry's order) when h halves. h omega is
    # 0.02 and 0.01: deep in the asymptotic range for every method, and RK4's error (~1e-9) is far above
    # float64 round-off (~1e-14).
    ks, m, A = 40.0, 0.1, 0.05
    omega = math.sqrt(2 * ks / m)
    model = two_particle_spring(device, ks, m, 1.0, A)
    t_end = 0.25
    errors = []
    for steps in (round(t_end * omega / 0.02), 2 * round(t_end * omega / 0.02)):
        h = t_end / steps
        q = run_steps(model, name, h, steps).particle_q.numpy()
        errors.append(abs(q[1, 0] - q[0, 0] - 1.0 - A * math.cos(omega * t_end)))
    assert math.log2(errors[0] / errors[1]) == pytest.approx(method(name).order, abs=0.15), errors


def perturbed_jelly(device, kd=0.0, precision="float64"):
    rng = np.random.default_rng(7)
    model = jelly_builder((3, 3, 3), 0.2, mass=0.01, ks=100.0, kd=kd).finalize(device, precision)
    state = model.state()
    state.particle_q.assign(model.particle_q_host + rng.normal(scale=0.005, size=model.particle_q_host.shape))
    state.particle_qd.assign(rng.normal(scale=0.1, size=model.particle_q_host.shape))
    return model, state


def test_rk4_energy_drift_bound(device):
    # Undamped, no gravity: energy is conserved by the ODE. RK4 multiplies a linear mode of frequency w by
    # R(i h w), |R|^2 = 1 - (h w)^6 / 72 + (h w)^8 / 576: every mode loses energy, at most (h w_max)^6 / 72 of it
    # per step. Over n steps the total energy falls by at most n (h w_max)^6 / 72 of itself: 1.39e-5 for
    # h w_max = 0.1 and n = 1000 (3.3e-6 is measured, the slower modes losing less).
    model, state = perturbed_jelly(device)
    from softsim_warp.core.stability_analysis import predict_lattice_dt  # noqa: PLC0415

    w_max = 2.0 / predict_lattice_dt((3, 3, 3), (0.2,) * 3, 0.01, 100.0, 0.0, methods=("symplectic",))["symplectic"]
    h = 0.1 / w_max
    steps = 1000
    e0 = sum(energies(model, state))
    final = run_steps(model, "rk4", h, steps, state)
    e1 = sum(energies(model, final))
    assert 0.0 < (e0 - e1) / e0 <= steps * (h * w_max) ** 6 / 72.0


def test_symplectic_energy_bounded(device):
    # Symplectic Euler conserves a modified energy: E oscillates with no secular drift. The modified energy of
    # a mode, w^2 x^2 + v^2 - h w^2 x v, lies within a = h w / 2 of its energy either way, so E stays within
    # about 2 a = h w_max of E0 (0.2 here; 0.039 is measured, the slower modes moving less).
    model, state = perturbed_jelly(device)
    from softsim_warp.core.stability_analysis import predict_lattice_dt  # noqa: PLC0415

    w_max = 2.0 / predict_lattice_dt((3, 3, 3), (0.2,) * 3, 0.01, 100.0, 0.0, methods=("symplectic",))["symplectic"]
    h = 0.2 / w_max
    integ = make_integrator("symplectic", model)
    a, b = state, model.state()
    e0 = sum(energies(model, a))
    errs = []
    for _ in range(40):
        for _ in range(50):
            integ.step(a, b, h)
            a, b = b, a
        errs.append(sum(energies(model, a)) - e0)
    errs = np.abs(np.array(errs)) / e0
    assert errs.max() < h * w_max
    assert errs[20:].mean() < 1.5 * errs[:20].mean() + 1e-12  # no growth from the first half to the second


@pytest.mark.parametrize("method", METHODS)
def test_momentum_conserved_without_gravity_and_contact(device, method):
    # Internal spring forces come in equal and opposite pairs: sum m v is constant for every method.
    model, state = perturbed_jelly(device, kd=0.5)
    m = model.particle_mass_host[:, None]
    p0 = (m * state.particle_qd.numpy()).sum(axis=0)
    final = run_steps(model, method, 1e-4, 200, state)
    p1 = (m * final.particle_qd.numpy()).sum(axis=0)
    np.testing.assert_allclose(p1, p0, atol=1e-13)


def test_float32_run_tracks_float64(device):
    # The same steps in float32 stay within float32 round-off growth of the float64 trajectory.
    m64, s64 = perturbed_jelly(device, kd=0.5, precision="float64")
    m32 = jelly_builder((3, 3, 3), 0.2, mass=0.01, ks=100.0, kd=0.5).finalize(device, "float32")
    s32 = m32.state()
    s32.particle_q.assign(s64.particle_q.numpy().astype(np.float32))
    s32.particle_qd.assign(s64.particle_qd.numpy().astype(np.float32))
    f64 = run_steps(m64, "rk4", 1e-3, 100, s64)
    f32 = run_steps(m32, "rk4", 1e-3, 100, s32)
    np.testing.assert_allclose(f32.particle_q.numpy(), f64.particle_q.numpy(), atol=100 * np.finfo(np.float32).eps)
