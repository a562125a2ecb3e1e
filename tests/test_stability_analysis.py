"""Tests of softsim_warp.core.stability_analysis against closed forms and against direct time stepping."""

from __future__ import annotations

import importlib
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "softsim_warp"


def _load_modules():
    """Import lattice and stability_analysis, without the package __init__ if that cannot import.

    Both modules are pure NumPy; the package __init__ pulls in Warp and the rest of the simulator,
    which these tests do not need. If that import fails, a bare stand-in package (no __init__ code)
    is used just long enough to import the two modules, then removed so later imports are unaffected.
    """
    try:
        from softsim_warp.core import lattice
        from softsim_warp.core import stability_analysis

        return lattice, stability_analysis
    except ImportError:
        pass
    saved = {k: v for k, v in sys.modules.items() if k == "softsim_warp" or k.startswith("softsim_warp.")}
    for k in saved:
        del sys.modules[k]
    stub = types.ModuleType("softsim_warp")
    stub.__path__ = [str(PACKAGE_DIR)]
    sys.modules["softsim_warp"] = stub
    try:
        lattice = importlib.import_module("softsim_warp.core.lattice")
        stability_analysis = importlib.import_module("softsim_warp.core.stability_analysis")
    finally:
        for k in [k for k in sys.modules if k == "softsim_warp" or k.startswith("softsim_warp.")]:
            del sys.modules[k]
        sys.modules.update(saved)
    return lattice, stability_analysis


lattice, sa = _load_modules()

RK4_REAL_AXIS = 2.785293563405282  # |z| where 1 + z + z^2/2 + z^3/6 + z^4/24 = -1 on the negative real axis


# ---------------------------------------------------------------------------------------------
# Helpers: the force law of the brief, written independently of the module, and a tiny integrator.


def spring_forces(x, v, pairs, rest, ks, kd):
    """f_a = -ks (|d| - r) d^ - kd ((v_a - v_b) . d^) d^, f_b = -f_a."""
    a, b = pairs[:, 0], pairs[:, 1]
    d = x[a] - x[b]
    length = np.linalg.norm(d, axis=1)
    dhat = d / length[:, None]
    mag = -ks * (length - rest) - kd * np.einsum("ij,ij->i", v[a] - v[b], dhat)
    f = np.zeros_like(x)
    np.add.at(f, a, mag[:, None] * dhat)
    np.add.at(f, b, -mag[:, None] * dhat)
    return f


_TABLEAUS = {
    "euler": ([[]], [1.0]),
    "midpoint": ([[], [0.5]], [0.0, 1.0]),
    "rk4": ([[], [0.5], [0.0, 0.5], [0.0, 0.0, 1.0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6]),
}


def simulate_growth(method, h, steps, x0, v0, masses, pairs, rest, ks, kd):
    """Step the nonlinear two-body system and return max amplitude over the run / initial amplitude."""
    x, v = x0.copy(), v0.copy()
    inv_m = 1.0 / masses[:, None]

    def accel(x, v):
        return spring_forces(x, v, pairs, rest, ks, kd) * inv_m

    def amplitude(x, v):
        # Deviation from rest length plus relative speed: zero exactly at rest (rigid motion excluded).
        d = x[0] - x[1]
        return abs(np.linalg.norm(d) - rest[0]) + np.linalg.norm(v[0] - v[1]) * h

    a0 = amplitude(x, v)
    worst = 0.0
    for _ in range(steps):
        if method == "symplectic":
            v = v + h * accel(x, v)
            x = x + h * v
        else:
            a_tab, b_tab = _TABLEAUS[method]
            kx, kv = [], []
            for row in a_tab:
                xs = x + h * sum(c * k for c, k in zip(row, kx)) if row else x
                vs = v + h * sum(c * k for c, k in zip(row, kv)) if row else v
                kx.append(vs)
                kv.append(accel(xs, vs))
            x = x + h * sum(b * k for b, k in zip(b_tab, kx))
            v = v + h * sum(b * k for b, k in zip(b_tab, kv))
        worst = max(worst, amplitude(x, v))
        if worst > 1e6 * a0:
            break
    return worst / a0


def two_body(m=0.5, ks=200.0, kd=0.0, r=1.0):
    """Two particles of mass m on one spring along x: relative motion has w^2 = 2ks/m, 2 zeta w = 2kd/m."""
    points = np.array([[0.0, 0.0, 0.0], [r, 0.0, 0.0]])
    pairs = np.array([[0, 1]])
    K, C, M = sa.linearize(points, pairs, [r], [ks], [kd], [m, m])
    w = math.sqrt(2.0 * ks / m)
    zeta = kd / (m * w)
    return K, C, M, w, zeta


# ---------------------------------------------------------------------------------------------
# Linearisation


def test_jacobians_symmetric_negative_semidefinite_and_momentum_conserving():
    K, C, M = sa.lattice_jacobians((3, 3, 3), (0.2, 0.25, 0.3), 0.01, (500.0, 200.0, 100.0), (0.5, 0.2, 0.1))
    n = 27
    assert K.shape == C.shape == (3 * n, 3 * n) and M.shape == (3 * n,)
    np.testing.assert_allclose(K, K.T, atol=1e-12 * np.abs(K).max())
    np.testing.assert_allclose(C, C.T, atol=1e-12 * np.abs(C).max())
    assert np.linalg.eigvalsh(C).max() <= 1e-12 * np.abs(C).max()
    assert np.linalg.eigvalsh(K).max() <= 1e-12 * np.abs(K).max()  # at rest: K = -sum ks d^d^T
    for J in (K, C):
        blocks = J.reshape(n, 3, n, 3)
        # Internal forces sum to zero (momentum) and do not see a translation of every particle.
        np.testing.assert_allclose(blocks.sum(axis=0), 0.0, atol=1e-12 * np.abs(J).max())
        np.testing.assert_allclose(blocks.sum(axis=2), 0.0, atol=1e-12 * np.abs(J).max())
    # Shear and bending springs make the lattice rigid: only the 6 rigid motions cost no energy.
    eig = np.linalg.eigvalsh(K)
    assert np.sum(np.abs(eig) <= 1e-9 * np.abs(eig).max()) == 6


def test_jacobians_match_finite_differences_away_from_rest():
    rng = np.random.default_rng(7)
    shape = (2, 2, 3)
    points = lattice.lattice_points(shape, (0.1, 0.1, 0.2))
    pairs, types = lattice.lattice_springs(shape)
    rest = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    ks = np.array([300.0, 150.0, 80.0])[types]
    kd = np.array([0.3, 0.2, 0.1])[types]
    # Stretched and sheared: the tension term (1 - r/|d|)(I - d^d^T) is far from zero here.
    x = points * 1.2 + 0.01 * rng.standard_normal(points.shape)
    v0 = np.zeros_like(x)
    K, C, _ = sa.linearize(x, pairs, rest, ks, kd, 0.01)
    eps = 1e-6
    K_fd = np.zeros_like(K)
    C_fd = np.zeros_like(C)
    for j in range(x.size):
        dx = np.zeros(x.size)
        dx[j] = eps
        dx = dx.reshape(x.shape)
        springs = (pairs, rest, ks, kd)
        K_fd[:, j] = (spring_forces(x + dx, v0, *springs) - spring_forces(x - dx, v0, *springs)).ravel() / (2 * eps)
        C_fd[:, j] = (spring_forces(x, v0 + dx, *springs) - spring_forces(x, v0 - dx, *springs)).ravel() / (2 * eps)
    np.testing.assert_allclose(K, K_fd, atol=1e-6 * np.abs(K).max())
    np.testing.assert_allclose(C, C_fd, atol=1e-6 * np.abs(C).max())


def test_zero_length_spring_rejected():
    with pytest.raises(ValueError):
        sa.linearize(np.zeros((2, 3)), np.array([[0, 1]]), [0.0], [1.0], [0.0], 1.0)


# ---------------------------------------------------------------------------------------------
# Two bodies, one spring: closed forms


def test_two_body_eigenvalues_are_reduced_mass_frequency():
    K, C, M, w, _ = two_body()
    lam = sa.system_eigenvalues(K, C, M)
    assert lam.shape == (12,)
    nonzero = lam[np.abs(lam) > 1e-9 * w]
    assert nonzero.size == 2  # 5 free modes (3 translations, 2 rotations) give 10 exact zeros
    np.testing.assert_allclose(np.sort(nonzero.imag), [-w, w], rtol=1e-12)
    np.testing.assert_allclose(nonzero.real, 0.0, atol=1e-12 * w)
    # The plain dense eigensolver sees the same oscillatory pair.
    raw = sa.system_eigenvalues(K, C, M, deflate=False)
    np.testing.assert_allclose(np.sort(raw[np.abs(raw) > 1e-3 * w].imag), [-w, w], rtol=1e-9)


def test_two_body_undamped_max_dt():
    K, C, M, w, _ = two_body()
    dt = {m: sa.max_stable_dt(m, K, C, M) for m in sa.NAMES}
    assert dt["symplectic"] == pytest.approx(2.0 / w, rel=1e-3)
    assert dt["rk4"] == pytest.approx(2.0 * math.sqrt(2.0) / w, rel=1e-6)
    # |1 + i h w| > 1 and |1 + i h w - (h w)^2 / 2| > 1 for every h > 0: no stable step at all.
    assert dt["euler"] == 0.0
    assert dt["midpoint"] == 0.0
    assert dt["implicit"] == math.inf


@pytest.mark.parametrize("zeta_target", [0.05, 0.3, 0.9])
def test_two_body_underdamped_euler_and_symplectic(zeta_target):
    m, ks = 0.5, 200.0
    w = math.sqrt(2.0 * ks / m)
    kd = zeta_target * m * w
    K, C, M, w, zeta = two_body(m=m, ks=ks, kd=kd)
    lam = sa.system_eigenvalues(K, C, M)
    osc = lam[np.abs(lam) > 1e-9 * w]
    np.testing.assert_allclose(osc.real, -zeta * w, rtol=1e-9)
    wd = w * math.sqrt(1 - zeta**2)
    np.testing.assert_allclose(np.sort(osc.imag), [-wd, wd], rtol=1e-9)
    # |1 + h lambda|^2 = 1 with lambda = -zeta w + i w sqrt(1 - zeta^2)  =>  h = 2 zeta / w.
    assert sa.max_stable_dt("euler", K, C, M) == pytest.approx(2.0 * zeta / w, rel=1e-6)
    # Symplectic Euler on x'' = -w^2 x - c x': stable iff h^2 w^2 <= 4 - 2 h c.
    c = 2.0 * zeta * w
    h_symp = (math.sqrt(c * c + 4.0 * w * w) - c) / (w * w)
    assert sa.max_stable_dt("symplectic", K, C, M) == pytest.approx(h_symp, rel=1e-3)


def test_two_body_overdamped():
    m, ks = 0.5, 200.0
    w = math.sqrt(2.0 * ks / m)
    K, C, M, w, zeta = two_body(m=m, ks=ks, kd=3.0 * m * w)
    assert zeta == pytest.approx(3.0)
    lam_max = w * (zeta + math.sqrt(zeta**2 - 1.0))  # the stiffer of the two real decay rates
    assert sa.max_stable_dt("euler", K, C, M) == pytest.approx(2.0 / lam_max, rel=1e-6)
    assert sa.max_stable_dt("midpoint", K, C, M) == pytest.approx(2.0 / lam_max, rel=1e-6)
    assert sa.max_stable_dt("rk4", K, C, M) == pytest.approx(RK4_REAL_AXIS / lam_max, rel=1e-6)
    c = 2.0 * zeta * w
    h_symp = (math.sqrt(c * c + 4 * w * w) - c) / w**2
    assert sa.max_stable_dt("symplectic", K, C, M) == pytest.approx(h_symp, rel=1e-3)


def test_max_dt_from_eigenvalues_closed_forms():
    # Real negative eigenvalues: the real-axis extent of each stability region.
    lam = np.array([-3.0, -10.0, 0.0])
    assert sa.max_stable_dt_from_eigenvalues("euler", lam) == pytest.approx(0.2, rel=1e-12)
    assert sa.max_stable_dt_from_eigenvalues("midpoint", lam) == pytest.approx(0.2, rel=1e-12)
    assert sa.max_stable_dt_from_eigenvalues("rk4", lam) == pytest.approx(RK4_REAL_AXIS / 10.0, rel=1e-9)
    # Imaginary axis: rk4 reaches 2 sqrt(2); rounding noise on the real part does not matter.
    lam = np.array([1e-15 + 5.0j, 1e-15 - 5.0j])
    assert sa.max_stable_dt_from_eigenvalues("rk4", lam) == pytest.approx(2.0 * math.sqrt(2.0) / 5.0, rel=1e-9)
    assert sa.max_stable_dt_from_eigenvalues("euler", lam) == 0.0
    # A growing mode cannot be stepped stably by an explicit method.
    assert sa.max_stable_dt_from_eigenvalues("rk4", np.array([0.5, -2.0])) == 0.0
    with pytest.raises(ValueError):
        sa.max_stable_dt_from_eigenvalues("symplectic", lam)


@pytest.mark.parametrize(
    "method, zeta",
    [("symplectic", 0.0), ("rk4", 0.0), ("euler", 0.3), ("midpoint", 0.3), ("rk4", 0.3), ("symplectic", 0.3)],
)
def test_predicted_dt_separates_bounded_from_growing_runs(method, zeta):
    """Step the nonlinear spring (small amplitude) just below and just above the predicted step."""
    m, ks = 0.5, 200.0
    w = math.sqrt(2.0 * ks / m)
    K, C, M, w, _ = two_body(m=m, ks=ks, kd=zeta * m * w)
    dt = sa.max_stable_dt(method, K, C, M)
    assert 0.0 < dt < math.inf
    x0 = np.array([[0.0, 0.0, 0.0], [1.0 + 1e-6, 0.0, 0.0]])
    v0 = np.zeros((2, 3))
    args = (x0, v0, np.array([m, m]), np.array([[0, 1]]), np.array([1.0]), ks, zeta * m * w)
    assert simulate_growth(method, 0.9 * dt, 2000, *args) < 10.0
    assert simulate_growth(method, 1.1 * dt, 2000, *args) > 1e3


def test_symplectic_step_matrix_radius_at_bound():
    K, C, M, w, _ = two_body()
    # On an undamped mode symplectic Euler keeps |mu| = 1 exactly up to h w = 2, then one eigenvalue
    # leaves the unit circle on the negative real axis.
    assert sa.step_spectral_radius("symplectic", 1.9 / w, K, C, M) == pytest.approx(1.0, abs=1e-9)
    S = sa.symplectic_step_matrix(K, C, M, 2.2 / w)
    mu = 2.0 - 2.2**2
    expected = (abs(mu) + math.sqrt(mu * mu - 4.0)) / 2.0  # larger root of mu^2 - tr mu + 1 = 0
    assert np.abs(np.linalg.eigvals(S)).max() == pytest.approx(expected, rel=1e-9)


# ---------------------------------------------------------------------------------------------
# Lattices


def test_predict_lattice_dt_4x4x4():
    dt = sa.predict_lattice_dt(
        (4, 4, 4), 0.3, 0.01, {"structural": 500.0, "shear": 200.0, "bending": 100.0}, (0.6, 0.2, 0.1),
        methods=("euler", "midpoint", "rk4", "implicit"),
    )
    for method in ("euler", "midpoint", "rk4"):
        assert 0.0 < dt[method] < math.inf
    assert dt["rk4"] > dt["midpoint"]
    assert dt["implicit"] == math.inf


def test_lattice_proportional_damping_closed_forms():
    """kd = alpha ks on every spring makes C = alpha K: every mode has c = alpha w^2."""
    alpha = 2e-3
    ks = np.array([500.0, 200.0, 100.0])
    K, C, M = sa.lattice_jacobians((3, 3, 3), 0.2, 0.01, ks, alpha * ks)
    w2 = np.linalg.eigvalsh(-K / M[:, None])  # M^-1 K is similar to a symmetric matrix
    w2_max = w2.max()
    assert w2_max * alpha**2 < 4.0  # every mode underdamped (zeta = alpha w / 2 < 1)
    # Euler: h = 2 zeta / w = alpha for every mode, independent of the frequency.
    assert sa.max_stable_dt("euler", K, C, M) == pytest.approx(alpha, rel=1e-6)
    # Symplectic: h^2 w^2 <= 4 - 2 h alpha w^2, tightest for the stiffest mode.
    c = alpha * w2_max
    h_symp = (math.sqrt(c * c + 4.0 * w2_max) - c) / w2_max
    dt = sa.predict_lattice_dt((3, 3, 3), 0.2, 0.01, ks, alpha * ks, methods=("euler", "symplectic"))
    assert dt["symplectic"] == pytest.approx(h_symp, rel=1e-3)
    assert dt["euler"] == pytest.approx(alpha, rel=1e-6)


def test_predict_lattice_dt_undamped_and_spring_type_mapping():
    ks = {0: 400.0, 1: 200.0, 2: 100.0}
    dt = sa.predict_lattice_dt((3, 3, 3), 0.2, 0.01, ks, 0.0, methods=("euler", "midpoint", "rk4"))
    assert dt["euler"] == 0.0 and dt["midpoint"] == 0.0
    K, C, M = sa.lattice_jacobians((3, 3, 3), 0.2, 0.01, (400.0, 200.0, 100.0), 0.0)
    w_max = math.sqrt(np.linalg.eigvalsh(-K / M[:, None]).max())
    assert dt["rk4"] == pytest.approx(2.0 * math.sqrt(2.0) / w_max, rel=1e-6)
    with pytest.raises(ValueError):
        sa.predict_lattice_dt((2, 2, 2), 0.2, 0.01, {"structural": 1.0}, 0.0)


# ---------------------------------------------------------------------------------------------
# Stability region boundaries


@pytest.mark.parametrize("method", ["euler", "midpoint", "rk4", "implicit"])
def test_stability_region_boundary_is_on_unit_level_set(method):
    z = sa.stability_region_boundary(method, n=2000)
    assert z.shape == (2000,)
    R = sa.stability_function(method)
    np.testing.assert_allclose(np.abs(R(z)), 1.0, atol=1e-9)
    assert abs(z[0]) < 1e-12  # every boundary passes through z = 0 (R(0) = 1)
    # Consecutive points are close: the curve is traced in order, ready to plot.
    assert np.abs(np.diff(z)).max() < 0.05


def test_stability_region_boundary_extents():
    z = sa.stability_region_boundary("euler", n=1000)
    np.testing.assert_allclose(np.abs(z + 1.0), 1.0, atol=1e-12)
    z = sa.stability_region_boundary("rk4", n=4000)
    assert z.real.min() == pytest.approx(-RK4_REAL_AXIS, abs=1e-3)
    near_axis = z[np.abs(z.real) < 1e-3]
    assert np.abs(near_axis.imag).max() == pytest.approx(2.0 * math.sqrt(2.0), abs=2e-2)
    with pytest.raises(ValueError):
        sa.stability_region_boundary("symplectic")
