"""Spring forces against a float64 NumPy reference; lattice topology counts."""

import re

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels.precision import Float, both_precisions, vec3

from softsim_warp import ModelBuilder, eval_forces, make_integrator
from softsim_warp.core import lattice
from softsim_warp.core.forces import ForceTerm, ForceTermError
from softsim_warp.core.integrators import ExplicitIntegrator
from tests.helpers import jelly_builder


def reference_forces(q, v, pairs, rest, ks, kd):
    """f_a = -ks(|d| - r) d^ - kd((v_a - v_b).d^) d^, d = x_a - x_b; f_b = -f_a (float64)."""
    d = q[pairs[:, 0]] - q[pairs[:, 1]]
    length = np.linalg.norm(d, axis=1)
    dhat = d / length[:, None]
    mag = ks * (length - rest) + kd * np.sum((v[pairs[:, 0]] - v[pairs[:, 1]]) * dhat, axis=1)
    fa = -mag[:, None] * dhat
    f = np.zeros_like(q)
    np.add.at(f, pairs[:, 0], fa)
    np.add.at(f, pairs[:, 1], -fa)
    return f


def test_spring_counts_of_a_10_cube():
    # 3 * 9 * 100 structural, 6 * 9 * 9 * 10 face + 4 * 9^3 body shear, 3 * 8 * 100 bending.
    pairs, types = lattice.lattice_springs((10, 10, 10))
    assert np.bincount(types).tolist() == [2700, 7776, 2400]
    assert len(pairs) == 12876
    assert lattice.spring_counts((10, 10, 10)) == {"structural": 2700, "shear": 7776, "bending": 2400}
    key = np.sort(pairs, axis=1)
    assert len(np.unique(key, axis=0)) == len(pairs), "each pair once"


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_forces_match_float64_reference(device, precision):
    rng = np.random.default_rng(1)
    b = jelly_builder((4, 3, 5), (0.3, 0.2, 0.4), ks=150.0, kd=0.7)
    b._ks[1][:] = 90.0  # a different ks for the shear springs
    model = b.finalize(device, precision)
    q = model.particle_q_host + rng.normal(scale=0.01, size=model.particle_q_host.shape)
    v = rng.normal(size=q.shape)
    state = model.state()
    state.particle_q.assign(q)
    state.particle_qd.assign(v)
    f = wp.empty_like(state.particle_q)
    f.fill_(wp.inf)  # poisoned: every element must be written
    eval_forces(model, state.particle_q, state.particle_qd, f)
    ref = reference_forces(q, v, model.spring_indices_host, model.spring_rest_host, model.spring_stiffness_host,
                           model.spring_damping_host)
    eps = np.finfo(np.float32 if precision == "float32" else np.float64).eps
    # Each particle sums up to 32 spring forces; inputs were rounded to the working precision too.
    scale = np.abs(ref).max()
    np.testing.assert_allclose(f.numpy(), ref, rtol=0, atol=200 * eps * scale)


def test_zero_length_spring_gives_no_nan(device):
    b = jelly_builder((2, 2, 2), 0.1, ks=100.0, kd=1.0)
    model = b.finalize(device)
    state = model.state()
    q = model.particle_q_host.copy()
    q[1] = q[0]  # two particles on top of each other
    state.particle_q.assign(q)
    f = wp.zeros_like(state.particle_q)
    eval_forces(model, state.particle_q, state.particle_qd, f)
    out = f.numpy()
    assert np.isfinite(out).all()
    # The spring of zero length has no direction and pushes nothing; every other spring acts as usual
    # (float64 reference from the same positions; particles at rest, so the dampers add nothing).
    pairs = model.spring_indices_host
    d = q[pairs[:, 0]].astype(np.float64) - q[pairs[:, 1]].astype(np.float64)
    length = np.linalg.norm(d, axis=1)
    assert (length == 0).sum() == 1
    safe = np.where(length > 0, length, 1.0)
    fs = -(model.spring_stiffness.numpy() * (length - model.spring_rest_length.numpy()) / safe)[:, None] * d
    ref = np.zeros_like(out, dtype=np.float64)
    np.add.at(ref, pairs[:, 0], fs)
    np.add.at(ref, pairs[:, 1], -fs)
    np.testing.assert_allclose(out, ref, rtol=0.0, atol=1e-4 * np.abs(ref).max())
    np.testing.assert_allclose(out.sum(axis=0), 0.0, atol=1e-4)


@pytest.mark.parametrize(
    "springs, needle",
    [
        ({"structral": {"ks": 10.0, "kd": 0.1}}, "unknown spring type 'structral'"),
        ({"shear": {"kd": 0.1}}, "springs['shear'] takes ks"),
        ({"shear": {"ks": 1.0, "kb": 0.1}}, "springs['shear'] takes ks"),
    ],
)
def test_add_jelly_rejects_misspelt_springs(springs, needle):
    """The API refuses what the scene loader refuses: a misspelt type built no springs at all before."""
    from softsim_warp import ModelBuilder

    with pytest.raises(ValueError, match=re.escape(needle)):
        ModelBuilder().add_jelly((3, 3, 3), 0.2, 0.01, springs)


# -- Force terms beyond the springs (core/forces.py): they reach every path or the path refuses -------

@both_precisions
@wp.kernel
def add_linear_drag(c: Float, qd: wp.array(dtype=vec3), f_out: wp.array(dtype=vec3)):
    i = wp.tid()
    f_out[i] = f_out[i] - c * qd[i]


class LinearDrag(ForceTerm):
    """A toy force term: f = -c v on every particle."""

    name = "linear drag"

    def __init__(self, c):
        self.c = c

    def add(self, model, q, qd, f_out):
        wp.launch(add_linear_drag, model.particle_count, inputs=[model.scalar(self.c), qd], outputs=[f_out],
                  device=model.device)


def dragged_pair(device, c, deterministic=False, ks=40.0, mass=0.1, stretch=0.05, velocity=(0.3, -0.2, 0.1)):
    """Two particles of mass m joined by a spring, stretched by ``stretch``, moving together at
    ``velocity``, with linear drag c on both and no gravity."""
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_particles([[-0.5 * (1.0 + stretch), 0, 0], [0.5 * (1.0 + stretch), 0, 0]], [velocity, velocity], mass)
    b.add_spring(0, 1, ks, 0.0, rest=1.0)
    return b.finalize(device, "float64", deterministic=deterministic, force_terms=(LinearDrag(c),))


@pytest.mark.parametrize("deterministic", [False, True])
def test_force_term_reaches_the_spring_list(device, deterministic):
    """With drag c the centre of mass slows as v0 exp(-c t / m), and the stretch s is a damped
    oscillator s'' = -(2 ks / m) s - (c / m) s': s = A exp(-g t)(cos(w t) + g / w sin(w t)),
    g = c / 2m, w = sqrt(2 ks / m - g^2). RK4 at h w = 0.01 follows both to 1e-9."""
    ks, m, A, c = 40.0, 0.1, 0.05, 0.05
    v0 = np.array([0.3, -0.2, 0.1])
    model = dragged_pair(device, c, deterministic, ks, m, A, tuple(v0))
    assert model.lattice is None and model.force_terms[0].name == "linear drag"
    g = c / (2 * m)
    w = np.sqrt(2 * ks / m - g * g)
    h, steps = 0.01 / w, 300
    integ = make_integrator("rk4", model)
    a, b = model.state(), model.state()
    for _ in range(steps):
        integ.step(a, b, h)
        a, b = b, a
    t = h * steps
    q, v = a.particle_q.numpy(), a.particle_qd.numpy()
    np.testing.assert_allclose(v.mean(axis=0), v0 * np.exp(-c * t / m), rtol=0, atol=1e-9)
    x0 = np.zeros(3)
    np.testing.assert_allclose(q.mean(axis=0), x0 + v0 * m / c * (1 - np.exp(-c * t / m)), rtol=0, atol=1e-9)
    stretch = q[1, 0] - q[0, 0] - 1.0
    assert stretch == pytest.approx(A * np.exp(-g * t) * (np.cos(w * t) + g / w * np.sin(w * t)), abs=1e-9)


def test_paths_without_force_terms_refuse_them_in_one_line(device):
    # The lattice path compiles the spring force into its kernels: asked for, it refuses; "auto" takes
    # the spring list instead, which evaluates the term.
    builder = jelly_builder((3, 3, 3), 0.2)
    with pytest.raises(ForceTermError) as refused:
        builder.finalize(device, force_path="lattice", force_terms=(LinearDrag(0.1),))
    assert "\n" not in str(refused.value) and "linear drag" in str(refused.value)
    assert "lattice path" in str(refused.value)
    model = builder.finalize(device, force_terms=(LinearDrag(0.1),))
    assert model.lattice is None and getattr(model, "masked", None) is None
    # The implicit integrator needs each force's Jacobian, which a ForceTerm does not carry.
    with pytest.raises(ForceTermError) as refused:
        make_integrator("implicit", model)
    assert "\n" not in str(refused.value) and "implicit solve path" in str(refused.value)
    # The fused stages exist on the lattice paths only, which the model did not take.
    with pytest.raises(ValueError) as refused:
        ExplicitIntegrator(model, "rk4", fused=True)
    assert "\n" not in str(refused.value) and "force terms" in str(refused.value)
    # A model without force terms is unchanged: the lattice path, and the implicit integrator.
    plain = builder.finalize(device)
    assert plain.lattice is not None and plain.force_terms == ()
    make_integrator("implicit", plain)
