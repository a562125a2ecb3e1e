"""Fast paths agree with the general ones: lattice vs spring list, fused vs plain, graph vs plain, batch vs single.

References: a float64 NumPy evaluation of the spring forces, float64 runs of the spring-list path,
and the plain paths themselves where the arithmetic is the same (bitwise).
"""

import json
import os
import time
import types

import numpy as np
import pytest
import warp as wp
from softsim_warp.kernels.lattice import make_single_stage

from softsim_warp.core.integrators import ExplicitIntegrator
from softsim_warp.core.methods import EXPLICIT_NAMES as EXPLICIT
from softsim_warp.core.forces import eval_forces
from softsim_warp.core.lattice import spring_counts
from softsim_warp.core.model import ModelBuilder
from softsim_warp.io.metrics import MetricsProbe
from softsim_warp.io.simulate import Simulator

EPS32 = float(np.finfo(np.float32).eps)
EPS64 = float(np.finfo(np.float64).eps)
SPRINGS = {
    "structural": {"ks": 1000.0, "kd": 1.0},
    "shear": {"ks": 700.0, "kd": 0.5},
    "bending": {"ks": 300.0, "kd": 0.2},
}


def _builder(shape=(4, 5, 6), springs=SPRINGS, degrees=30.0, second=True, world=0, builder=None):
    b = builder or ModelBuilder((0.0, -9.8, 0.0))
    b.add_jelly(
        shape,
        (0.3, 0.4, 0.5),
        0.01,
        springs,
        center=(0.0, 0.3, 0.0),
        axis=(1.0, 0.0, 1.0),
        degrees=degrees,
        world=world,
    )
    if second:
        # A second jelly with another shape and without shear springs: per-jelly tables and type masks.
        b.add_jelly(
            (3, 2, 4),
            0.2,
            0.02,
            {"structural": {"ks": 100.0, "kd": 1.0}, "bending": {"ks": 30.0, "kd": 0.2}},
            center=(1.0, 0.5, 0.0),
            world=world,
        )
    return b


def _reference_forces(model, q, qd):
    """Float64 spring forces and, per particle, the scale of their rounding error.

    f_a = -sum_s (ks (l - r) + kd (v_a - v_b).d^) d^ over the springs s = (a, b), f_b = -f_a.
    A float32 evaluation rounds l (and r) to ~eps l, which ks turns into ~eps ks (l + r); the
    damper and the final products add ~eps kd |v_a - v_b|; a sum of up to 32 terms adds at most
    32 eps sum |term|. ``scale`` is sum over springs of ks (l + r) + kd |dv| + 32 |term|.
    """
    pairs = model.spring_indices_host
    x = q.astype(np.float64)
    v = qd.astype(np.float64)
    d = x[pairs[:, 0]] - x[pairs[:, 1]]
    length = np.linalg.norm(d, axis=1)
    dhat = d / length[:, None]
    dv = v[pairs[:, 0]] - v[pairs[:, 1]]
    ks, kd, rest = model.spring_stiffness_host, model.spring_damping_host, model.spring_rest_host
    term = -(ks * (length - rest) + kd * np.einsum("ij,ij->i", dv, dhat))[:, None] * dhat
    f = np.zeros_like(x)
    np.add.at(f, pairs[:, 0], term)
    np.add.at(f, pairs[:, 1], -term)
    per_spring = ks * (length + rest) + kd * np.linalg.norm(dv, axis=1) + 32.0 * np.linalg.norm(term, axis=1)
    scale = np.zeros(len(x))
    np.add.at(scale, pairs[:, 0], per_spring)
    np.add.at(scale, pairs[:, 1], per_spring)
    return f, scale


def _perturbed_state(model, device, seed=0, precision=np.float32):
    rng = np.random.default_rng(seed)
    spacing = min(s for info in model.jellies for s in info.spacing if s > 0)
    q = (model.particle_q_host + rng.normal(scale=0.1 * spacing, size=(model.particle_count, 3))).astype(precision)
    qd = rng.normal(scale=1.0, size=(model.particle_count, 3)).astype(precision)
    return q, qd


@pytest.mark.parametrize("shape", [(4, 5, 6), (6, 7, 8), (1, 6, 5), (2, 2, 2), (5, 1, 1)])
@pytest.mark.parametrize("kernel", ["gather", "rows"])
def test_lattice_forces_match_float64_reference(device, shape, kernel):
    lattice = _builder(shape).finalize(device, force_path="lattice")
    springs = _builder(shape).finalize(device, force_path="springs")
    lattice.lattice.set_kernel(kernel)
    q, qd = _perturbed_state(springs, device)
    f_ref, scale = _reference_forces(springs, q, qd)
    qa = wp.array(q, dtype=wp.vec3, device=device)
    qda = wp.array(qd, dtype=wp.vec3, device=device)
    for model in (lattice, springs):
        f = wp.full(model.particle_count, wp.vec3(np.inf, np.inf, np.inf), dtype=wp.vec3, device=device)  # poisoned
        eval_forces(model, qa, qda, f)
        err = np.linalg.norm(f.numpy() - f_ref, axis=1)
        # |f32 - f64| <= eps32 * scale (see _reference_forces), per particle.
        assert np.all(err <= EPS32 * scale + 1e-30), (model.lattice_reason, float((err / (scale + 1e-30)).max()))
    assert not lattice.has_derived("spring_indices")  # the lattice path never made the spring arrays


def test_lattice_forces_float64(device):
    """In float64 both paths agree with the reference to float64 rounding (same bound, eps64)."""
    lattice = _builder().finalize(device, "float64", force_path="lattice")
    springs = _builder().finalize(device, "float64", force_path="springs")
    q, qd = _perturbed_state(springs, device, seed=3, precision=np.float64)
    f_ref, scale = _reference_forces(springs, q, qd)
    qa = wp.array(q, dtype=wp.vec3d, device=device)
    qda = wp.array(qd, dtype=wp.vec3d, device=device)
    for kernel in ("gather", "rows"):
        lattice.lattice.set_kernel(kernel)
        f = wp.zeros(lattice.particle_count, dtype=wp.vec3d, device=device)
        eval_forces(lattice, qa, qda, f)
        assert np.all(np.linalg.norm(f.numpy() - f_ref, axis=1) <= EPS64 * scale)


def test_model_states_are_padded_for_the_gather():
    """States and stage buffers sit inside allocations reaching ``lattice.pad`` past both ends; a
    clone, a plain array or a view with too little room is not padded (and gets the checked gather)."""
    model = _builder().finalize("cpu", force_path="lattice")
    lat = model.lattice
    # The largest jelly is 4 x 5 x 6: 2 ny nz + nz + 2 bounds every stencil offset |di ny nz + dj nz + dk|.
    assert lat.pad == 2 * 5 * 6 + 6 + 2
    state = model.state()
    assert lat.padded(state.particle_q, state.particle_qd)
    assert np.array_equal(state.particle_q.numpy(), model.particle_q.numpy())
    integrator = ExplicitIntegrator(model, "rk4", fused=True)
    assert lat.padded(integrator.q_s, integrator.qd_s)
    assert not lat.padded(wp.clone(state.particle_q))
    assert not lat.padded(model.particle_q)
    big = wp.zeros(model.particle_count + 2 * lat.pad, dtype=model.vec3, device="cpu")
    assert lat.padded(big[lat.pad : lat.pad + model.particle_count])
    assert not lat.padded(big[lat.pad - 1 : lat.pad - 1 + model.particle_count])


def test_bench_memory_counts_padded_allocations():
    """The benchmark's memory column counts a padded state array's whole allocation, once."""
    from softsim_warp.studies.bench import device_arrays_bytes

    model = _builder().finalize("cpu", force_path="lattice")
    state = model.state()
    whole = (model.particle_count + 2 * model.lattice.pad) * 12
    assert device_arrays_bytes(state) == 2 * whole
    state.particle_qd = state.particle_q  # the same allocation twice counts once
    assert device_arrays_bytes(state) == whole


def test_step_bytes_lists_each_array_once():
    """``bench.step_bytes`` per particle, array by array (float32: a vec3 array is 12 bytes a particle),
    for the one-jelly benchmark model on a plane: each array a launch reads or writes counted once."""
    from softsim_warp.studies.bench import JellySpec, build_jelly_model, step_bytes

    model = build_jelly_model(4, JellySpec(), "cpu")
    n, v = model.particle_count, 12
    ids = 4 + 4 + 4  # jelly, world, inverse mass
    model.lattice.set_kernel("gather")
    expected = {
        # (method, the one-jelly stage): bytes a particle
        # symplectic: the state read (it is y_n) and y_{n+1} written
        ("symplectic", True): 2 * v + 2 * v,
        ("symplectic", False): 2 * v + ids + 2 * v,
        # rk4, stage by stage: the stage state read; y_n read after the first; the velocity
        # accumulator written (stage 0), read and both written (1), both read and written (2),
        # both read (3); the next state or the result written
        ("rk4", True): (2 * v + v + 2 * v)
        + (4 * v + v + 2 * v + 2 * v)
        + (4 * v + 4 * v + 2 * v)
        + (4 * v + 2 * v + 2 * v),
    }
    expected[("rk4", False)] = expected[("rk4", True)] + 4 * ids
    for (method, uniform), per_particle in expected.items():
        integrator = ExplicitIntegrator(model, method, fused=True, single=uniform)
        assert integrator.single == uniform and integrator.fuse_contact
        assert step_bytes(model, integrator) == n * per_particle, (method, uniform)
    assert expected[("symplectic", True)] == 48 and expected[("rk4", True)] == 384
    # The CPU row kernel (one stage): state read, k-coordinate, force buffer written and read,
    # inverse mass, y_{n+1} written; then plane contact as its own kernel (inverse mass and world,
    # y_n read, y_{n+1} read and written).
    model.lattice.set_kernel("rows")
    rows = ExplicitIntegrator(model, "symplectic", fused=True)
    assert step_bytes(model, rows) == n * ((2 * v + 4 + 2 * v + 4 + 2 * v) + (8 + 6 * v))


def test_clock_monitor_reads_nvidia_smi(tmp_path, monkeypatch):
    """The bench's clock monitor parses nvidia-smi's samples: idle and unreadable ones are left
    out, and the power-cap (0x4) and slowdown (thermal, 0x20) samples are counted."""
    import types

    from softsim_warp.studies.bench import ClockMonitor

    fake = tmp_path / "nvidia-smi"
    lines = [
        "345, 1980, 80.5, 700.00, 0x0000000000000001",  # idle
        "1980, 1980, 450.2, 700.00, 0x0000000000000000",
        "1800, 1980, 699.9, 700.00, 0x0000000000000004",
        "1590, 1980, 700.7, 700.00, 0x0000000000000004",
        "1700, 1980, 650.0, 700.00, 0x0000000000000020",
        "[N/A], 1980, [N/A], 700.00, 0x0000000000000000",
    ]
    ready = tmp_path / "printed"
    body = "".join(f"echo '{line}'\n" for line in lines)
    fake.write_text(f"#!/bin/sh\n{body}touch '{ready}'\nexec sleep 30\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    gpu = types.SimpleNamespace(is_cuda=True, ordinal=0)
    with ClockMonitor(gpu, period_ms=50) as monitor:
        deadline = time.monotonic() + 30.0
        while not ready.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
    assert monitor.command[-4:] == ["-i", "0", "-lms", "50"]
    c = monitor.summary()
    assert c["samples"] == 4
    assert c["sm_clock_mhz"] == {"min": 1590.0, "median": 1750.0, "max": 1980.0}
    assert c["power_w"]["max"] == 700.7 and c["power_limit_w"] == 700.0
    assert c["power_capped_fraction"] == 0.5 and c["slowed_down_fraction"] == 0.25
    # No nvidia-smi (or not a GPU): no monitor, no summary.
    with ClockMonitor(types.SimpleNamespace(is_cuda=False, ordinal=0)) as idle:
        pass
    assert idle.command is None and idle.summary() is None


@pytest.mark.parametrize("method", ["symplectic", "rk4"])
def test_unpadded_states_fall_back_to_the_checked_stage(device, method):
    """The one-jelly stage loads neighbours without bounds checks, so it needs padded states
    (``Model.particle_array``); over states a user made otherwise (``wp.clone``) the step takes the
    generic, bounds-checked stage: on the CPU the same bits (the same sums in the same order); on
    CUDA, where the compiler contracts multiply-adds differently in the two kernels, within 4 ulps
    of the largest coordinate per step."""
    steps = 100
    finals = {}
    for padded in (True, False):
        model, integrator = _gather_integrator(device, method, _dropping(_builder(degrees=0.0, second=False)), single=True)
        states = [model.state(), model.state()]
        if not padded:
            for s in states:
                s.particle_q, s.particle_qd = wp.clone(s.particle_q), wp.clone(s.particle_qd)
        assert model.lattice.padded(states[0].particle_q) == padded
        finals[padded] = _step_states(integrator, states, steps)
    _assert_same_run(device, finals[True], finals[False], steps, EPS32)


def _step_states(integrator, states, steps, dt=1.0e-4):
    """``steps`` steps ping-ponging between the two states; the final positions and velocities."""
    for k in range(steps):
        integrator.step(states[k % 2], states[1 - k % 2], dt)
    return states[0].particle_q.numpy(), states[0].particle_qd.numpy()


def _assert_same_run(device, run, reference, steps, eps):
    """Two (q, qd) results of the same arithmetic: the same bits on the CPU; on CUDA, where the
    compiler contracts multiply-adds differently per kernel, within 4 ulps of the largest
    coordinate per step (the bound of test_lattice_trajectories_match). The run must have moved."""
    assert np.abs(run[1]).max() > 0.0
    if device.is_cpu:
        assert np.array_equal(run[0], reference[0])
        assert np.array_equal(run[1], reference[1])
    else:
        bound = steps * 4.0 * eps * np.abs(reference[0]).max()
        assert np.abs(run[0] - reference[0]).max() <= bound


@pytest.mark.parametrize("kernel", ["gather", "rows"])
def test_blown_up_world_does_not_reach_its_neighbour(device, kernel):
    """A world whose state is NaN leaves the next world in memory untouched, bit for bit.

    The gather must not read a neighbour outside the jelly (here the NaN jelly next door), nor
    drop it by multiplying by zero. The run is the side-by-side comparison's situation: one method
    blows up, the others must not notice.
    """
    finals = []
    for poison in (False, True):
        b = _builder(second=False, world=0)
        b.add_jelly((4, 3, 5), (0.3, 0.2, 0.4), 0.01, SPRINGS, center=(1.0, 0.3, 0.0), world=1)
        model = _dropping(b).finalize(device, force_path="lattice")
        model.lattice.set_kernel(kernel)
        integrator = ExplicitIntegrator(model, "rk4", fused=True)
        states = [model.state(), model.state()]
        n0 = 4 * 5 * 6
        if poison:
            q = states[0].particle_q.numpy()
            q[:n0] = np.nan
            states[0].particle_q.assign(q)
        for k in range(20):
            integrator.step(states[k % 2], states[1 - k % 2], 1.0e-4)
        q = states[0].particle_q.numpy()
        if poison:
            assert np.isnan(q[:n0]).all()
        finals.append(q[n0:])
    assert np.isfinite(finals[1]).all()
    assert np.array_equal(finals[0], finals[1])


def _run(model, method, steps, dt, fused=None, use_graph=False):
    integrator = ExplicitIntegrator(model, method, fused=fused)
    sim = Simulator(model, integrator, dt, 1.0 / (steps * dt), 1, use_graph=use_graph)
    sim.advance(steps)
    return sim.state.particle_q.numpy().astype(np.float64), sim.state.particle_qd.numpy().astype(np.float64)


def _dropping(builder):
    """The jelly starts 1 mm above a plane falling at 1 m/s, so it hits and bounces within the run."""
    b = builder
    lowest = min(np.concatenate(b._q)[:, 1])
    b._qd[0][:, 1] = -1.0
    b.add_plane((0.0, lowest - 1.0e-3, 0.0), (0.0, 1.0, 0.0), restitution=0.5, friction=0.3)
    return b


@pytest.mark.parametrize("method", EXPLICIT)
def test_lattice_trajectories_match(device, method):
    """Short runs with an impact: float32 lattice (fused) and spring-list runs stay within rounding of float64.

    Each step rounds every position to ~eps32 |x| and the velocity update adds the force
    rounding times h/m; over a stable run of N steps these add up to at most ~N eps32 |x|max per
    coordinate (a few ulps per step). The bound below allows 4 ulps of |x|max per step.
    """
    steps, dt = 200, 1.0e-4
    b = _dropping(_builder(second=False))
    plane_y = b.planes[0]["point"][1]
    ref_q, _ = _run(b.finalize(device, "float64", force_path="springs"), method, steps, dt)
    # Contact acted: falling freely the lowest particle would end 1 m/s * 0.02 s + g t^2 / 2 below its start.
    assert ref_q[:, 1].min() > plane_y - 1.0e-3
    bound = steps * 4.0 * EPS32 * np.abs(ref_q).max()
    results = {}
    for path in ("lattice", "springs"):
        model = _dropping(_builder(second=False)).finalize(device, force_path=path)
        results[path], _ = _run(model, method, steps, dt)
        assert np.abs(results[path] - ref_q).max() <= bound, path
    assert np.abs(results["lattice"] - results["springs"]).max() <= 2 * bound
    # In float64 the fused lattice path follows the float64 spring list to float64 rounding.
    lattice64, _ = _run(
        _dropping(_builder(second=False)).finalize(device, "float64", force_path="lattice"), method, steps, dt
    )
    assert np.abs(lattice64 - ref_q).max() <= steps * 4.0 * EPS64 * np.abs(ref_q).max()


@pytest.mark.parametrize("method", ["symplectic", "rk4"])
@pytest.mark.parametrize("kernel", ["gather", "rows"])
def test_fused_matches_unfused(device, method, kernel):
    """The fused stage kernels do the same arithmetic as eval_forces + integrate_stage + collide_planes."""
    steps, dt = 100, 1.0e-4
    runs = {}
    for fused in (False, True):
        model = _dropping(_builder()).finalize(device, force_path="lattice")
        model.lattice.set_kernel(kernel)
        runs[fused], _ = _run(model, method, steps, dt, fused=fused)
    # Contraction of a*b+c into FMA may differ between the kernels: a few ulps per step.
    assert np.abs(runs[True] - runs[False]).max() <= steps * 4.0 * EPS32 * np.abs(runs[False]).max()


def _gather_integrator(device, method, builder=None, **options):
    """The dropping two-jelly model (or ``builder``'s) on the fused gather stages with ``options``
    (which the integrator must have taken as given)."""
    model = (builder or _dropping(_builder())).finalize(device, force_path="lattice")
    model.lattice.set_kernel("gather")
    integrator = ExplicitIntegrator(model, method, fused=True, **options)
    for key, value in options.items():
        assert getattr(integrator, key) == value
    return model, integrator


@pytest.mark.parametrize("method", ["symplectic", "midpoint", "rk4"])
def test_fused_contact_matches_separate_contact(device, method):
    """Plane contact inside the fused gather stage (the last stage's response and the resting-contact
    filter of intermediate stages) calls the same contact_planes on the same values as the separate
    collide_planes launches: on the CPU the same bits. The jelly lands during the run, so contact acts.
    """
    steps, dt = 150, 1.0e-4
    runs = {}
    for fuse_contact in (False, True):
        model, integrator = _gather_integrator(device, method, fuse_contact=fuse_contact)
        sim = Simulator(model, integrator, dt, 1.0 / (steps * dt), 1, use_graph=False)
        sim.advance(steps)
        runs[fuse_contact] = sim.state.particle_q.numpy().astype(np.float64)
    bound = 0.0 if device.is_cpu else steps * 4.0 * EPS32 * np.abs(runs[False]).max()
    assert np.abs(runs[True] - runs[False]).max() <= bound


@pytest.mark.parametrize("path", ["lattice", "springs"])
def test_graph_capture_matches_plain_stepping(path):
    """On the CPU a captured frame replays the same kernels in the same order: bitwise equal."""
    out = {}
    for use_graph in (False, True):
        model = _dropping(_builder()).finalize("cpu", force_path=path)
        out[use_graph] = _run(model, "rk4", 60, 1.0e-4, use_graph=use_graph)
    assert np.array_equal(out[False][0], out[True][0]) and np.array_equal(out[False][1], out[True][1])


def test_batch_matches_single_runs(device):
    """Copies in worlds, each with its own method, advance in shared launches exactly as alone."""
    methods = ["euler", "rk4", "symplectic"]
    b = ModelBuilder((0.0, -9.8, 0.0))
    for w in range(len(methods)):
        _builder(second=False, world=w, builder=b)
    batch = b.finalize(device)
    assert batch.lattice is not None
    integrator = ExplicitIntegrator(batch, methods)
    sim = Simulator(batch, integrator, 1.0e-4, 100.0, 1, use_graph=False)
    sim.advance(50)
    q_batch = sim.state.particle_q.numpy()
    n = q_batch.shape[0] // len(methods)
    for w, method in enumerate(methods):
        q_single, _ = _run(_builder(second=False).finalize(device), method, 50, 1.0e-4)
        assert np.array_equal(q_batch[w * n : (w + 1) * n], q_single.astype(np.float32)), method


def test_lattice_detection():
    assert _builder().finalize("cpu").lattice is not None
    # Rest lengths scaled per offset (a jelly started crushed) still fit the tables.
    b = _builder(second=False)
    b._q[0] = 0.5 * b._q[0]
    crushed = b.finalize("cpu")
    assert crushed.lattice is not None
    # Individual rest lengths, an extra spring, or a loose particle: the general spring list.
    b = _builder(second=False)
    b._rest[0] = b._rest[0] * np.linspace(0.9, 1.1, len(b._rest[0]))
    assert b.finalize("cpu").lattice is None
    b = _builder()
    b.add_spring([0], [70], 10.0, 0.0)
    m = b.finalize("cpu")
    assert m.lattice is None and "belong to no jelly" in m.lattice_reason
    b = _builder()
    b.add_particles([[0.0, 2.0, 0.0]], [0.0, 0.0, 0.0], 0.1)
    assert b.finalize("cpu").lattice is None
    with pytest.raises(ValueError, match="lattice path does not apply"):
        b.finalize("cpu", force_path="lattice")


def test_crushed_jelly_forces_match(device):
    """A jelly started at half size pushes back with the forces of its true rest lengths."""
    models = {}
    for path in ("lattice", "springs"):
        b = _builder(second=False)
        b._q[0] = 0.5 * b._q[0] + np.array([0.0, 0.3, 0.0])
        models[path] = b.finalize(device, force_path=path)
    q, qd = _perturbed_state(models["springs"], device, seed=5)
    f_ref, scale = _reference_forces(models["springs"], q, qd)
    f = wp.zeros(len(q), dtype=wp.vec3, device=device)
    eval_forces(
        models["lattice"], wp.array(q, dtype=wp.vec3, device=device), wp.array(qd, dtype=wp.vec3, device=device), f
    )
    assert np.all(np.linalg.norm(f.numpy() - f_ref, axis=1) <= EPS32 * scale)


def test_lazy_spring_arrays_and_spring_energy(device):
    """Metrics on the lattice path: spring energy sum 1/2 ks (l - r)^2, without making spring arrays."""
    model = _builder().finalize(device)
    q, qd = _perturbed_state(model, device, seed=7)
    state = model.state()
    state.particle_q.assign(q)
    state.particle_qd.assign(qd)
    metrics = MetricsProbe(model).measure(state, 0, 0.0)
    assert not model.has_derived("spring_indices")
    pairs = model.spring_indices_host
    stretch = np.linalg.norm(q[pairs[:, 0]].astype(np.float64) - q[pairs[:, 1]], axis=1) - model.spring_rest_host
    energy = 0.5 * model.spring_stiffness_host * stretch**2
    scale = model.spring_stiffness_host * (np.abs(stretch) * 2.0 * model.spring_rest_host + stretch**2)
    # float32 l carries ~eps l error, so each term is good to ~eps ks |l - r| l, plus the sum's rounding.
    assert metrics.spring_energy == pytest.approx(
        energy.sum(), abs=4 * EPS32 * (scale.sum() + energy.sum() * len(energy))
    )
    # The spring arrays appear on first use, with the builder's values.
    assert np.array_equal(model.spring_indices.numpy(), pairs)
    assert np.allclose(model.spring_rest_length.numpy(), model.spring_rest_host, rtol=EPS32)


def test_bench_cli_writes_json(tmp_path, capsys):
    from softsim_warp.commands.cli import main

    out = tmp_path / "bench.json"
    assert (
        main(
            [
                "bench",
                "--sizes",
                "3",
                "--steps",
                "5",
                "--integrators",
                "euler,rk4",
                "--out",
                str(out),
                "--repeats",
                "2",
                "--paths",
                "lattice,springs",
            ]
        )
        == 0
    )
    data = json.loads(out.read_text())
    assert {"device", "versions", "bandwidth_gbs", "results"} <= set(data)
    rows = data["results"]
    assert {(r["integrator"], r["path"]) for r in rows} == {
        (i, p) for i in ("euler", "rk4") for p in ("lattice", "springs")
    }
    for r in rows:
        assert r["particles"] == 27 and r["springs"] == sum(spring_counts((3, 3, 3)).values())
        for key in (
            "ms_per_step",
            "particle_steps_per_s",
            "spring_evals_per_s",
            "compile_s",
            "memory_bytes",
            "bytes_per_step",
            "bandwidth_fraction",
        ):
            assert r[key] > 0, key
    assert "particle-steps/s" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--sizes", "1"], "error: command line: --sizes: each size must be at least 2 (got '1')"),
        (["--sizes", "ten"], "error: command line: --sizes: not a comma-separated list of integers (got 'ten')"),
        (["--integrators", "verlet"], "error: command line: --integrators: unknown value 'verlet'"),
        (["--steps", "0"], "error: command line: --steps: must be at least 1 (got 0)"),
    ],
)
def test_bench_cli_rejects_bad_input(argv, message, capsys):
    from softsim_warp.commands.cli import main

    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1, err


def test_lattice_kernels_refuse_strided_state(device):
    """The gather addresses state arrays from their data pointer, so a strided view is refused, not misread."""
    model = _builder().finalize(device, force_path="lattice")
    model.lattice.set_kernel("gather")
    n = model.particle_count
    wide = wp.zeros(2 * n, dtype=wp.vec3, device=device)
    f = wp.zeros(n, dtype=wp.vec3, device=device)
    with pytest.raises(ValueError, match="contiguous"):
        eval_forces(model, wide[::2], wide[::2], f)
    # The fused stage writes its output state through the data pointer too.
    integrator = ExplicitIntegrator(model, "symplectic", fused=True)
    state_in, state_out = model.state(), model.state()
    state_out.particle_q = wide[::2]
    with pytest.raises(ValueError, match="contiguous"):
        integrator.step(state_in, state_out, 1.0e-4)


def _shared_coefficient_jellies(copies=False):
    """Three unrotated jellies of spacing 0.1 with the same coefficients in two worlds, the third
    without shear springs (an absent type does not break the sharing), dropped onto a plane.

    Rest lengths are the initial distances, so jellies of other shapes or places share them to
    float32 rounding only; with ``copies`` the three have one shape and place (in three worlds),
    so they share them in float64 too.
    """
    b = _builder(degrees=0.0, second=False)
    no_shear = {k: v for k, v in SPRINGS.items() if k != "shear"}
    if copies:
        for world, springs in ((1, SPRINGS), (2, no_shear)):
            b.add_jelly((4, 5, 6), (0.3, 0.4, 0.5), 0.01, springs, center=(0.0, 0.3, 0.0), world=world)
        return _dropping(b)
    b.add_jelly((3, 7, 3), (0.2, 0.6, 0.2), 0.02, SPRINGS, center=(1.0, 0.0, 0.0), world=1)
    b.add_jelly((3, 3, 4), (0.2, 0.2, 0.3), 0.01, no_shear, center=(0.0, 1.0, 0.0))
    return _dropping(b)


@pytest.mark.parametrize("method", ["symplectic", "midpoint", "rk4"])
@pytest.mark.parametrize("shear", [True, False])
def test_one_jelly_stage_equals_generic_stage(device, method, shear):
    """One jelly of one particle mass steps with the stage compiled for its shape and spring types
    (``single_stage``: coefficients as a kernel argument, no per-particle jelly, world or mass read,
    the springs of absent types not compiled) as with the generic stage that reads them at run time:
    on the CPU the same bits over 100 steps with an impact; on CUDA within 4 ulps of the largest
    coordinate per step. A second jelly, or one particle of another mass, and the model is not single;
    asking for the one-jelly stage then is an error. One compiled kernel per (shape, types)."""
    springs = SPRINGS if shear else {k: v for k, v in SPRINGS.items() if k != "shear"}
    steps = 100
    finals = {}
    for single in (True, False):
        builder = _dropping(_builder(shape=(5, 4, 7), springs=springs, degrees=0.0, second=False))
        model, integrator = _gather_integrator(device, method, builder, single=single)
        assert model.lattice.single
        finals[single] = _step_states(integrator, [model.state(), model.state()], steps)
    _assert_same_run(device, finals[True], finals[False], steps, EPS32)
    two = _dropping(_builder(degrees=0.0)).finalize(device, force_path="lattice")
    assert not two.lattice.single
    with pytest.raises(ValueError, match="one-jelly stage"):
        ExplicitIntegrator(two, method, fused=True, single=True)
    for mass in (0.02, 0.0):  # heavier, or fixed
        b = _dropping(_builder(degrees=0.0, second=False))
        b._mass[0][5] = mass
        assert not b.finalize(device, force_path="lattice").lattice.single
    stage = make_single_stage(wp.float32, (5, 4, 7), 7)
    assert stage is make_single_stage(wp.float32, np.array([5, 4, 7]), np.int32(7))
    assert stage is not make_single_stage(wp.float32, (5, 4, 8), 7)
    assert stage is not make_single_stage(wp.float32, (5, 4, 7), 5)


def test_common_coefficients():
    """Shared coefficients are ks r per half-stencil slot, then -ks and kd per type, rounded as the
    table gather rounds them; jellies that differ in a type both have share nothing."""
    from softsim_warp.kernels.lattice import UNIFORM_SLOTS, common_coefficients, rest_slot

    model = _shared_coefficient_jellies().finalize("cpu", force_path="lattice")
    lat = model.lattice
    layout = lat.layout
    coef = np.array(lat.stencil_coef, dtype=np.float32)
    rest = layout.rest[0].astype(np.float32)
    ks = layout.ks[0].astype(np.float32)
    # Slot of the structural offset (1, 0, 0): rest 0.1 times ks 1000 in float32.
    n = UNIFORM_SLOTS.index(rest_slot(1, 0, 0))
    assert coef[n] == rest[rest_slot(1, 0, 0)] * ks[0]
    assert abs(coef[n] - 100.0) < 1e-4
    n = UNIFORM_SLOTS.index(rest_slot(0, 0, 2))
    assert coef[n] == rest[rest_slot(0, 0, 2)] * ks[2]
    assert list(coef[16:]) == [-1000.0, -700.0, -300.0, 1.0, 0.5, np.float32(0.2)]
    # A rest length or a stiffness that differs in a type two jellies have: no sharing.
    for key, spacing in (("ks", 0.1), ("rest", 0.11)):
        springs = dict(SPRINGS, bending={"ks": 301.0 if key == "ks" else 300.0, "kd": 0.2})
        b = _builder(degrees=0.0, second=False)
        size = tuple(spacing * (n - 1) for n in (3, 3, 4))
        b.add_jelly((3, 3, 4), size, 0.01, springs, center=(0.0, 1.0, 0.0))
        other = b.finalize("cpu", force_path="lattice")
        assert not other.lattice.uniform
        assert not np.any(np.array(other.lattice.stencil_coef))
        lay = other.lattice.layout
        assert common_coefficients(lay.rest, lay.ks, lay.kd, lay.types, np.float32) is None
