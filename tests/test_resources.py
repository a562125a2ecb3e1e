"""Memory estimates: counts match the built model, the builder's estimate bounds what it allocates,
and a scene too large is refused before anything is allocated."""

import sys
import time
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softsim_warp import build_model, load_scene
from softsim_warp.commands import cli
from softsim_warp.io import resources
from softsim_warp.core.errors import SceneError

sys.path.insert(0, str(Path(__file__).parent))
import robustness_cases as rc  # noqa: E402


@pytest.mark.parametrize("res", [[2, 1, 1], [5, 1, 3], [3, 3, 3], [4, 6, 5], [10, 10, 10]])
def test_counts_match_built_model(res):
    scene = load_scene("jelly_drop", [f"jelly.0.resolution={res}"])
    counts = resources.scene_counts(scene.data)
    model = build_model(scene, device="cpu")
    assert counts.particles == model.particle_count
    assert counts.springs == model.spring_count
    # Surface points are those the USD surface mesh writes every frame.
    assert counts.surface == np.unique(model.jellies[0].surface_quads).size or min(res) == 1


def test_host_build_estimate_bounds_measured_peak():
    """The builder's estimate is an upper bound of its measured NumPy peak, and not a loose one."""
    scene = load_scene("jelly_drop", ["jelly.0.resolution=[16,16,16]"])
    est = resources.estimate(scene.data)
    tracemalloc.start()
    try:
        build_model(scene, device="cpu")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= est.host_build <= 2 * peak, (peak, est.host_build)


def test_huge_resolution_refused_fast_without_allocating(tmp_path, monkeypatch):
    """--set of a 4000^3 jelly: exit 2 with the estimate and the memory available, nothing allocated."""
    (tmp_path / "scene.toml").write_text(rc.BASE)
    monkeypatch.chdir(tmp_path)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        code = cli.main(["run", "scene.toml", "--quiet", "--set", "jelly.0.resolution=[4000,4000,4000]"])
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert code == 2
    # 6.4e10 particles would need terabytes; the refusal costs less than a megabyte and no time.
    assert peak < 1 << 20, peak
    assert elapsed < 2.0, elapsed


def test_usd_frames_count_towards_memory(tmp_path, monkeypatch, capsys):
    """A small jelly with a billion output frames would hold every frame in memory: refused."""
    (tmp_path / "scene.toml").write_text(rc.BASE)
    monkeypatch.chdir(tmp_path)
    code = cli.main(["run", "scene.toml", "--quiet", "--frames", "1000000000"])
    err = capsys.readouterr().err
    assert code == 2
    assert "scene too large" in err and "1,000,000,001 USD frames" in err and "available" in err
    # The frames, not the jelly, are what is too large: the line names them.
    assert err.startswith("error: scene.toml: simulation.frames: scene too large") and err.rstrip().endswith(
        "(got 1000000000)"
    )


class _FakeGpu:
    is_cuda = True
    free_memory = 64 << 20
    total_memory = 80 << 30

    def __str__(self):
        return "cuda:0"


def test_device_memory_refusal_names_free_and_total():
    scene = load_scene("jelly_drop", ["jelly.0.resolution=[100,100,100]"])
    est = resources.estimate(scene.data, frames=10)
    assert est.on(True)[1] > _FakeGpu.free_memory
    with pytest.raises(SceneError) as e:
        resources.check_fits(scene, _FakeGpu(), frames=10, host_available=1 << 50)
    line = e.value.line()
    assert "jelly.0.resolution: scene too large" in line
    assert "on cuda:0" in line and "64 MiB free of 80 GiB" in line and "(got [100, 100, 100])" in line


def test_estimate_grows_with_stages_and_precision():
    """Device bytes per particle follow the buffers: RK4 has 4 more vec3 per particle than Euler, float64 doubles."""
    scene = load_scene("jelly_drop")
    n = resources.scene_counts(scene.data).particles
    e32 = resources.estimate(scene.data, "euler").device
    r32 = resources.estimate(scene.data, "rk4").device
    assert r32 - e32 == 4 * 3 * 4 * n  # q_s, qd_s, acc_q, acc_qd: 4 vec3 of float32
    e64 = resources.estimate(scene.data, "euler", precision="float64").device
    ints = (8 * n) + 8 * resources.scene_counts(scene.data).springs  # int32 arrays do not double
    assert e64 - ints == 2 * (e32 - ints)


def test_fits_on_real_device(device):
    scene = load_scene("jelly_drop")
    est = resources.check_fits(scene, device, frames=10)
    host, dev = est.on(device.is_cuda)
    assert host > 0 and (dev > 0) == device.is_cuda


def test_available_host_memory_is_plausible():
    avail = resources.available_host_bytes()
    assert avail is None or 0 < avail < 1 << 50


def test_validation_refuses_before_building(monkeypatch):
    """The scene loader itself refuses a scene whose builder would not fit (the Python API too)."""
    monkeypatch.setattr(resources, "available_host_bytes", lambda: 1 << 18)
    with pytest.raises(SceneError, match="scene too large: building 1,000 particles"):
        load_scene("jelly_drop")
    monkeypatch.setattr(resources, "available_host_bytes", lambda: None)  # unknown: no refusal
    load_scene("jelly_drop")


def test_fake_cpu_device_counts_everything_on_host():
    scene = load_scene("jelly_drop")
    cpu = SimpleNamespace(is_cuda=False)
    est = resources.estimate(scene.data, frames=100)
    host, dev = est.on(False)
    assert dev == 0 and host >= est.device + est.usd
    with pytest.raises(SceneError, match="of memory on"):
        resources.check_fits(scene, cpu, frames=100, host_available=host - 1)
    resources.check_fits(scene, cpu, frames=100, host_available=host)


def test_compare_checks_all_copies_together(monkeypatch, tmp_path, capsys):
    """Each copy alone fits, all of them at once do not: compare refuses before building anything."""
    monkeypatch.chdir(tmp_path)
    scene = load_scene("jelly_drop", ["jelly.0.resolution=[20,20,20]"])
    one = resources.estimate(scene.data, frames=scene.frame_count())
    need = one.host_build + one.device + one.host_model + one.usd  # what one copy can need at most on the CPU
    monkeypatch.setattr(resources, "available_host_bytes", lambda: int(1.5 * need))
    code = cli.main(["compare", "jelly_drop", "--set", "jelly.0.resolution=[20,20,20]", "--integrators",
                     "euler,symplectic,rk4", "--quiet", "--out", "c.usdc"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scene too large: 3 copies with 24,000 particles" in err[0], err
    assert list(tmp_path.iterdir()) == []


def test_bench_refuses_sizes_that_cannot_fit(monkeypatch, capsys):
    """A benchmark size whose jelly would not fit is refused with its flag and value, before building."""
    code = cli.main(["bench", "--sizes", "10,2000", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: command line: --sizes: too large: 8,000,000,000 particles"), err
    assert "(got 2000)" in err[0]
