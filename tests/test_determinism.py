"""Determinism: CPU runs are bitwise identical run after run; the --deterministic (atomic-free) path
agrees with the atomic path to float rounding and is bitwise reproducible on every device."""

import json
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from softsim_warp import build_model, eval_forces, load_scene, make_integrator
from softsim_warp.commands import cli, common
from softsim_warp.core.forces import ForceWork, incident_springs_csr
from softsim_warp.io.simulate import Simulator

TIMING = {"wall_seconds", "step_seconds", "compile_seconds", "particle_steps_per_second"}


def _softsim(args, cwd):
    proc = subprocess.run(
        [sys.executable, "-m", "softsim_warp", *args], cwd=cwd, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    return proc


def test_cpu_runs_are_bitwise_identical(tmp_path, monkeypatch):
    """Two separate processes: identical USD bytes and identical metrics but for wall times."""
    for i in (1, 2):
        _softsim(
            [
                "run",
                "jelly_drop",
                "--frames",
                "6",
                "--quiet",
                "--integrator",
                "rk4",
                "--out",
                f"r{i}.usda",
                "--metrics",
                f"r{i}.json",
            ],
            tmp_path,
        )
    assert (tmp_path / "r1.usda").read_bytes() == (tmp_path / "r2.usda").read_bytes()
    # The binary format too (here two runs in this process).
    monkeypatch.chdir(tmp_path)
    for i in (1, 2):
        assert cli.main(["run", "jelly_drop", "--frames", "6", "--quiet", "--out", f"r{i}.usdc"]) == 0
    assert (tmp_path / "r1.usdc").read_bytes() == (tmp_path / "r2.usdc").read_bytes()
    m1, m2 = (json.loads((tmp_path / f"r{i}.json").read_text()) for i in (1, 2))
    assert set(m1["summary"]) == set(m2["summary"])
    assert {k: v for k, v in m1["summary"].items() if k not in TIMING} == {
        k: v for k, v in m2["summary"].items() if k not in TIMING
    }
    assert m1["frames"] == m2["frames"]


def test_csr_lists_every_incident_spring_in_order():
    rng = np.random.default_rng(3)
    n = 30
    pairs = rng.integers(0, n, size=(200, 2))
    offsets, entries = incident_springs_csr(pairs, n)
    assert offsets[0] == 0 and offsets[-1] == 2 * len(pairs)
    for i in range(n):
        expect = []
        for s, (a, b) in enumerate(pairs):  # the order the atomic kernel adds them in on the CPU
            if a == i:
                expect.append(s)
            if b == i:
                expect.append(-(s + 1))
        assert list(entries[offsets[i] : offsets[i + 1]]) == expect


def _perturbed_state(model, seed=0):
    """Positions off rest and random velocities, so every spring and damper carries force."""
    rng = np.random.default_rng(seed)
    q = model.particle_q.numpy() + rng.normal(scale=0.02, size=(model.particle_count, 3))
    qd = rng.normal(scale=0.5, size=(model.particle_count, 3))
    return (wp.array(q, dtype=model.vec3, device=model.device), wp.array(qd, dtype=model.vec3, device=model.device))


def _forces(model, q, qd, work=None):
    f = wp.empty(model.particle_count, dtype=model.vec3, device=model.device)
    f.fill_(wp.inf)  # poisoned: the gather must write every particle
    eval_forces(model, q, qd, f, work)
    return f.numpy()


@pytest.mark.parametrize("res", [[6, 5, 4], [7, 1, 3]])
def test_gather_agrees_with_atomics(device, res):
    scene = load_scene("jelly_drop", [f"jelly.0.resolution={res}"])
    atomic = build_model(scene, device=device, force_path="springs")  # the atomic spring list, not the lattice rows
    det = build_model(scene, device=device, deterministic=True, force_path="springs")
    q, qd = _perturbed_state(atomic)
    fa = _forces(atomic, q, qd)
    work = ForceWork(det)
    fd = _forces(det, q, qd, work)
    assert np.isfinite(fd).all()
    if not device.is_cuda:
        # On the CPU the atomic kernel adds each particle's forces in ascending spring order, from
        # zero: the gather's order. Same operations, same bits.
        assert np.array_equal(fa, fd)
    # Both sum the same per-spring forces in different orders: per component, the difference is at
    # most the two summation errors, each <= (k - 1) eps sum_s |f_s| for k incident springs (k <= 32).
    sf = work.spring_force.numpy().astype(np.float64)
    offsets, entries = det.spring_csr_offsets.numpy(), det.spring_csr_springs.numpy()
    bound = np.zeros_like(fd, dtype=np.float64)
    for i in range(det.particle_count):
        e = entries[offsets[i] : offsets[i + 1]]
        idx = np.where(e >= 0, e, -e - 1)
        bound[i] = 2 * max(len(e) - 1, 1) * np.finfo(np.float32).eps * np.abs(sf[idx]).sum(axis=0)
    assert (np.abs(fa.astype(np.float64) - fd) <= bound).all()


def test_gather_is_bitwise_reproducible(device):
    scene = load_scene("jelly_drop")
    det = build_model(scene, device=device, deterministic=True, force_path="springs")
    q, qd = _perturbed_state(det, seed=1)
    first = _forces(det, q, qd)
    for _ in range(5):
        assert np.array_equal(first, _forces(det, q, qd))


def _run(device, deterministic, integrator="rk4", frames=6, force_path="auto"):
    scene = load_scene("jelly_drop")
    model = build_model(scene, device=device, deterministic=deterministic, force_path=force_path)
    sim = Simulator(model, make_integrator(integrator, model), 4e-4, 60.0, frames)
    positions = []

    class Keep:
        def write_frame(self, k, t, pos, metrics):
            positions.append(pos.copy())

    result = sim.run([Keep()])
    return np.stack(positions), [m.as_dict() for m in result.metrics]


@pytest.mark.parametrize("force_path", ["auto", "springs"])
def test_deterministic_run_is_bitwise_reproducible(device, force_path):
    """Whole runs with --deterministic: same positions and metrics, bit for bit, on CPU and CUDA.

    ``auto`` takes the lattice path (atomic-free by construction), ``springs`` the spring list
    with the CSR gather in place of the atomic force kernel.
    """
    p1, m1 = _run(device, True, force_path=force_path)
    p2, m2 = _run(device, True, force_path=force_path)
    assert np.array_equal(p1, p2)
    assert m1 == m2


def test_deterministic_metrics_agree_with_atomic(device):
    """The fixed-order metric sums equal the atomic ones up to float32 summation error."""
    _, ma = _run(device, False, frames=3)
    _, md = _run(device, True, frames=3)
    eps = np.finfo(np.float32).eps
    for a, d in zip(ma, md):
        # 1000 terms per jelly: |difference| <= 2 * 1000 eps * (sum of |terms|); the energies here are
        # sums of positive terms, so sum |terms| is the value itself.
        for key in ("kinetic_energy", "gravity_energy", "spring_energy"):
            assert abs(a[key] - d[key]) <= 2 * 1000 * eps * abs(a[key]) + 1e-30, key
        assert a["max_speed"] == d["max_speed"]
        assert np.allclose(a["com"], d["com"], rtol=0, atol=2 * 1000 * eps * 2.0)


def test_deterministic_flag_in_outputs(tmp_path):
    _softsim(
        ["run", "jelly_drop", "--frames", "2", "--quiet", "--deterministic", "--out", "d.usda", "--metrics", "d.json"],
        tmp_path,
    )
    assert json.loads((tmp_path / "d.json").read_text())["summary"]["deterministic"] is True
    assert 'bool "softsim:deterministic" = 1' in (tmp_path / "d.usda").read_text()


class _FakeGpu:
    is_cuda = True


def test_deterministic_refuses_implicit_on_cuda():
    """The implicit solver sums with atomics: --deterministic with it is refused on CUDA, allowed on the CPU."""
    from softsim_warp.core.errors import CommandLineError  # noqa: PLC0415

    with pytest.raises(CommandLineError) as e:
        common.check_deterministic("implicit", _FakeGpu())
    assert e.value.line().startswith("command line: --deterministic: not available with the implicit integrator")
    common.check_deterministic("implicit", wp.get_device("cpu"))
    for name in ("euler", "symplectic", "midpoint", "rk4"):
        common.check_deterministic(name, _FakeGpu())


@pytest.mark.parametrize("scene_name", ["mesh_drop", "pile"])
def test_mesh_and_contact_scenes_are_bitwise_reproducible(device, scene_name):
    """A mesh jelly on mesh stairs (the masked lattice, mesh terrain) and a pile of jellies in contact
    (candidate lists, pair passes; the first two jellies touch at about 0.9 s): with
    --deterministic, two runs give the same positions and metrics, bit for bit, on the CPU and on
    CUDA."""
    scene = load_scene(scene_name, [f"simulation.duration={0.1 if scene_name == 'mesh_drop' else 1.5}"])
    runs = []
    for _ in range(2):
        model = build_model(scene, device=device, deterministic=True)
        integrator = make_integrator("symplectic", model)
        sim = Simulator(model, integrator, scene.sim["dt"], scene.sim["fps"], scene.frame_count())
        positions = []

        class Keep:
            def write_frame(self, k, t, pos, metrics):
                positions.append(pos.copy())

        result = sim.run([Keep()])
        runs.append((np.stack(positions), [m.as_dict() for m in result.metrics]))
        if scene_name == "pile":
            assert integrator.run.particle_contact.contacts.numpy().any()  # jellies in contact at the end
    assert np.array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
