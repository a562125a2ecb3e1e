"""Frames of many steps: captured graphs hold at most ``MAX_GRAPH_STEPS`` steps (so a tiny dt cannot make
one frame's capture try 10^10 steps and abort in ``std::bad_alloc``), chunked replay steps exactly
as launching the steps one by one, and a run whose steps cannot finish is refused up front."""

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import softsim_warp as ss
from softsim_warp.commands import cli
from softsim_warp.core import stepper as stepper_mod
from softsim_warp.core.errors import SceneError
from softsim_warp.io import resources

# The step sizes of one call after another: remainders of every size and from either buffer, a call
# of exactly one chunk, calls of several chunks, more remainder sizes than the cache keeps.
CALLS = [2500, 13, 6, 7, 1, 20, 2, 3, 4, 5, 9, 11, 14, 15]


def _stepper(device, method, use_graph):
    scene = ss.load_scene("jelly_drop", ["jelly.0.resolution=[3,3,3]"])
    model = ss.build_model(scene, device=device)
    return ss.Stepper(model, ss.make_integrator(method, model), scene.sim["dt"], use_graph=use_graph)


@pytest.mark.parametrize("method", ["symplectic", "rk4"])
def test_chunked_capture_equals_plain_stepping(device, method, monkeypatch):
    """Graphs of at most 7 steps (the cap lowered from its default), replayed 357 times for 2500 steps
    and then for calls of other sizes, give the bits of plain stepping: chunks of an odd step count
    alternate the buffers, and each (size, buffer) pair has its own graph."""
    monkeypatch.setattr(stepper_mod, "MAX_GRAPH_STEPS", 7)
    captured = []
    replay = stepper_mod.Stepper._replay

    def spy(self, n, chunk):
        held = len(self._graphs)
        replay(self, n, chunk)
        if len(self._graphs) > held:
            captured.append(n)

    monkeypatch.setattr(stepper_mod.Stepper, "_replay", spy)
    finals = {}
    for use_graph in (False, True):
        st = _stepper(device, method, use_graph)
        for n in CALLS:
            st.advance(n)
        finals[use_graph] = (st.state.particle_q.numpy(), st.state.particle_qd.numpy())
        if use_graph:
            keys = set(st._graphs)
    q, qd = finals[False]
    assert np.isfinite(q).all()
    assert q[:, 1].max() < 1.0 + 0.25  # it fell (0.25 m is half the jelly's size; it starts at y = 1)
    # Every graph holds at most 7 steps; both buffers' graphs of 7 steps exist; the remainders kept
    # are at most MAX_CACHED_GRAPHS (the later sizes ran without a graph).
    assert max(captured) <= 7 and {(7, 0), (7, 1)} <= keys
    assert len([k for k in keys if k[0] != 7]) <= stepper_mod.MAX_CACHED_GRAPHS
    assert len(captured) == len(keys)  # each graph captured once
    assert len(keys) == 2 + stepper_mod.MAX_CACHED_GRAPHS  # CALLS has more remainder sizes than that
    # The same launches in the same order: the same bits (on CUDA too: the explicit lattice path
    # has no atomics).
    assert np.array_equal(finals[True][0], q) and np.array_equal(finals[True][1], qd)


def test_default_cap_bounds_graphs():
    """The default cap is what the comment in core/stepper.py justifies, and a long call captures no
    graph above it."""
    assert 100 <= stepper_mod.MAX_GRAPH_STEPS <= 1000
    st = _stepper("cpu", "symplectic", True)
    st.advance(3 * stepper_mod.MAX_GRAPH_STEPS + 5)
    assert max(n for n, _ in st._graphs) == stepper_mod.MAX_GRAPH_STEPS
    assert set(st._graphs) == {(stepper_mod.MAX_GRAPH_STEPS, 0), (5, 0)}


def test_tiny_dt_refused_up_front(tmp_path, monkeypatch, capsys):
    """dt = 1e-12 over jelly_drop's 5 s is 5e12 steps: one line naming simulation.dt, exit 2, no file."""
    monkeypatch.chdir(tmp_path)
    code = cli.main(["run", "jelly_drop", "--set", "simulation.dt=1e-12", "--quiet", "--out", "x.usdc"])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2
    assert len(lines) == 1, err
    assert "simulation.dt: too many steps" in lines[0] and "(got 1e-12)" in lines[0]
    assert "5,000,000,000,000 steps" in lines[0] and "at least" in lines[0] and "days" in lines[0]
    assert not list(tmp_path.iterdir())


class _Device:
    def __init__(self, name):
        self.name = name
        self.is_cuda = name.startswith("cuda")

    def __str__(self):
        return self.name


def test_step_check_bounds():
    """The refusal follows the lower bound of a step's time: 30 days is the limit, the CPU's bound
    grows with the particles, and a dt so small that the step count overflows is refused too."""
    scene = ss.load_scene("jelly_drop", ["jelly.0.resolution=[3,3,3]"])  # 27 particles
    cpu = _Device("cpu")
    floor = resources.step_seconds_floor(27, False)
    assert floor == resources.STEP_FLOOR_SECONDS["cpu"]
    per_particle = resources.STEP_SECONDS_PER_PARTICLE["cpu"]
    assert resources.step_seconds_floor(10**6, False) == pytest.approx(10**6 * per_particle)
    limit = resources.MAX_RUN_DAYS * 86400.0 / floor  # steps
    frames, fps = 60, 60.0

    def with_sim(**sim):
        return SimpleNamespace(data=scene.data | {"simulation": scene.data["simulation"] | sim}, source="s.toml")

    assert resources.check_steps(with_sim(dt=frames / fps / (0.9 * limit)), cpu, frames) == pytest.approx(0.9 * limit)
    bad = with_sim(dt=frames / fps / (1.1 * limit))
    with pytest.raises(SceneError) as e:
        resources.check_steps(bad, cpu, frames)
    assert e.value.line().startswith("s.toml: simulation.dt: too many steps") and "on cpu" in e.value.line()
    assert resources.check_steps(scene, cpu, 0) == 0.0  # no frames, no steps
    with pytest.raises(SceneError) as e:
        resources.check_steps(with_sim(dt=5e-324, precision="float64"), _Device("cuda:0"), 300)
    assert "more than 1e300 steps" in e.value.line() and "on cuda:0" in e.value.line()
    # check_fits, which `softsim run` calls, makes the check.
    with pytest.raises(SceneError, match="too many steps"):
        resources.check_fits(bad, cpu, frames=frames)


def test_small_dt_frame_runs_with_bounded_graphs(tmp_path, monkeypatch):
    """dt = 1e-6 at 60 fps is 16,667 steps in one frame: the run completes, replaying graphs of at
    most MAX_GRAPH_STEPS steps (one capture of the whole frame held 16,667 steps' launches)."""
    monkeypatch.chdir(tmp_path)
    sizes = []
    replay = stepper_mod.Stepper._replay

    def spy(self, n, chunk):
        sizes.append(n)
        return replay(self, n, chunk)

    monkeypatch.setattr(stepper_mod.Stepper, "_replay", spy)
    code = cli.main([
        "run", "jelly_drop", "--quiet", "--set", "jelly.0.resolution=[3,3,3]", "--set", "simulation.dt=1e-6",
        "--fps", "60", "--frames", "1", "--out", "x.usdc", "--metrics", "m.json",
    ])
    assert code == 0
    summary = json.loads(Path("m.json").read_text())["summary"]
    assert summary["status"] == "complete" and summary["frames"] == 2
    assert summary["steps"] == round(1 / (60 * 1e-6)) == 16667
    assert sum(sizes) == 16667 and max(sizes) <= stepper_mod.MAX_GRAPH_STEPS
    assert math.isfinite(summary["energy_drift"])
    assert Path("x.usdc").stat().st_size > 0
