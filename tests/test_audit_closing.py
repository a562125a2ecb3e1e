"""What a new user meets first, tested:

* A stop acts within about a second however long a frame is, in ``compare`` and ``sweep`` too (the
  steps of a frame taken in chunks, the stop request read between them: ``Simulator.advance_frame``).
* ``sweep --dts`` too small to finish names ``--dts``, the flag the user typed.
* A mesh jelly needs no lattice settings: without ``resolution`` or ``spacing`` it gets
  ``DEFAULT_RESOLUTION`` cells along its longest side.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softsim_warp.commands import cli
from softsim_warp.core.model import build_model
from softsim_warp.io import mesh_scene
from softsim_warp.io.scene import scene_from_dict
from tests.helpers import sigterm_after_first_frame

ROOT = Path(__file__).resolve().parents[1]

# A 3^3 jelly falling with one output frame of 10^7 steps (fps = 1e-4 at dt = 1 ms): hours of steps.
LONG = """\
name = "long"
[simulation]
integrator = "symplectic"
dt = 0.001
duration = 20000.0
fps = 0.0001
gravity = [0.0, -9.8, 0.0]
[[jelly]]
resolution = 3
size = 0.2
center = [0.0, 10.0, 0.0]
particle_mass = 0.01
[jelly.springs.structural]
ks = 50.0
kd = 0.1
"""


def test_compare_stops_within_a_long_frame(tmp_path, monkeypatch, capsys):
    """A real SIGTERM during a frame of 10^7 steps: compare (an explicit batch and an implicit copy,
    two groups) exits 143 within seconds, frame 0 kept in <stem>.partial and marked interrupted."""
    from pxr import Sdf  # noqa: PLC0415


    monkeypatch.chdir(tmp_path)
    (tmp_path / "long.toml").write_text(LONG)
    (tmp_path / "c.usda").write_text("#usda 1.0\n")  # an existing output stays as it was
    sent = sigterm_after_first_frame(monkeypatch, 1.0)  # well inside the long frame
    code = cli.main(["compare", "long.toml", "--integrators", "symplectic,implicit", "--out", "c.usda",
                     "--metrics", "c.json", "--quiet"])
    stopped = time.perf_counter()
    sent["thread"].join(5)
    err = capsys.readouterr().err
    assert code == 128 + signal.SIGTERM, err
    assert stopped - sent["t"] < 5.0, stopped - sent["t"]  # the frame alone would take hours
    assert (tmp_path / "c.usda").read_text() == "#usda 1.0\n"
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "c.partial.usda"))
    assert layer.customLayerData["softsim:status"] == "interrupted"
    assert layer.customLayerData["softsim:frames"] == 1
    metrics = json.loads((tmp_path / "c.partial.json").read_text())
    assert metrics["frames"] == 1 and metrics["steps"] == 0


def test_simulator_advance_frame_same_steps_with_a_stop(monkeypatch):
    """advance_frame takes the same chunks with a stop that never fires as without one (bitwise the
    same state), and drops the frame, returning False, when the stop fires between chunks."""
    from softsim_warp import load_scene  # noqa: PLC0415
    from softsim_warp.core import stepper as stepper_mod  # noqa: PLC0415
    from softsim_warp.io.simulate import Simulator  # noqa: PLC0415

    monkeypatch.setattr(stepper_mod, "MAX_GRAPH_STEPS", 7)
    scene = load_scene("free_flight")
    states = []
    for stop in (None, lambda: False):
        model = build_model(scene, device="cpu")
        sim = Simulator(model, stepper_mod.make_integrator("symplectic", model), 1e-3, 60, 1)
        assert sim.advance_frame(30, stop=stop)
        states.append(sim.state.particle_q.numpy().copy())
    assert np.array_equal(states[0], states[1])
    asked = []

    def stop_after_two():
        asked.append(1)
        return len(asked) > 2

    model = build_model(scene, device="cpu")
    sim = Simulator(model, stepper_mod.make_integrator("symplectic", model), 1e-3, 60, 1)
    assert not sim.advance_frame(30, stop=stop_after_two)
    assert len(asked) == 3  # asked before each chunk; two chunks of 7 taken, then stopped


def test_stop_check_outside_a_worker_never_stops():
    from softsim_warp.io import sweep as engine  # noqa: PLC0415

    assert engine.stop_check(None) is None
    stop = engine.stop_check("softsim-stop-test")
    assert stop() is False
    time.sleep(engine.STOP_POLL_SECONDS * 1.5)
    assert stop() is False and stop() is False


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="needs the sweep extra")
def test_sweep_stops_within_a_long_frame(tmp_path):
    """SIGTERM to `softsim sweep` while its one worker steps a frame of 10^7 steps: the task reads
    the sweep's stop event between chunks and ends, so the cluster closes and the command exits 143
    within seconds (a worker still in its frame would hold the cluster's close until it timed out)."""
    (tmp_path / "long.toml").write_text(LONG)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "softsim_warp", "sweep", "long.toml", "--vary", "jelly.0.particle_mass=0.01,0.02",
         "--workers", "1", "--out", "s.csv"],
        cwd=tmp_path, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    lines = []
    try:
        for line in proc.stderr:
            lines.append(line)
            if "tasks of up to" in line:
                break
        time.sleep(4.0)  # the worker is inside the first task's long frame
        sent = time.perf_counter()
        proc.send_signal(signal.SIGTERM)
        _, rest = proc.communicate(timeout=60)
        took = time.perf_counter() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, "".join(lines) + rest
    assert took < 4.0, took  # a busy worker's close would time out after 4 s more
    assert "interrupted" in rest and "Traceback" not in rest


def test_sweep_dts_too_small_names_dts(tmp_path, capsys):
    code = cli.main(["sweep", "jelly_drop", "--vary", "jelly.0.total_mass=1,2", "--dts", "1e-12", "--workers", "1",
                     "--out", str(tmp_path / "s.csv")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("error: command line: --dts: too many steps") and "raise --dts" in err[0], err
    assert "simulation.dt" not in err[0] and err[0].endswith("(got 1e-12)")
    assert not (tmp_path / "s.csv").exists()
    # A dt the scene (or --set) gives still names simulation.dt.
    code = cli.main(["sweep", "jelly_drop", "--vary", "jelly.0.total_mass=1,2", "--set", "simulation.dt=1e-12",
                     "--workers", "1", "--out", str(tmp_path / "s.csv")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and ": simulation.dt: too many steps" in err[0], err


@pytest.fixture(scope="module")
def critter(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("make_assets", ROOT / "assets" / "make_assets.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    out = tmp_path_factory.mktemp("assets")
    module.main(["--out", str(out)])
    return out / "critter.usda"


def _critter_model(critter, **lattice):
    jelly = {"mesh": str(critter), "center": [0.0, 0.5, 0.0], "total_mass": 0.5,
             "springs": {"structural": {"ks": 120.0, "kd": 0.15}}, **lattice}
    return build_model(scene_from_dict({"simulation": {"dt": 2.5e-4, "frames": 1}, "jelly": [jelly]}), "cpu")


def test_mesh_jelly_default_resolution(critter):
    """A mesh jelly without resolution or spacing is the jelly of DEFAULT_RESOLUTION (12) cells along
    its longest side: the same particles at the same places (the resolution the surface-contact
    tests hold the critter's legs above the floor with, tests/test_surface_contact.py)."""
    assert mesh_scene.DEFAULT_RESOLUTION == 12
    default = _critter_model(critter)
    given = _critter_model(critter, resolution=12)
    assert np.array_equal(default.particle_q_host, given.particle_q_host)
    # The lattice spacing is the longest side over 12: the particles' x coordinates step by it.
    q = default.particle_q_host.astype(np.float64)
    extent = q.max(axis=0) - q.min(axis=0)
    xs = np.unique(np.round(q[:, 0], 6))
    assert np.allclose(np.diff(xs), extent.max() / 12, rtol=1e-4)
    assert not np.array_equal(default.particle_q_host.shape, _critter_model(critter, resolution=10).particle_q_host.shape)


def test_mesh_jelly_without_lattice_keys_runs(tmp_path, critter, capsys):
    """As a new user drops an asset: mesh, centre and mass only; `softsim run` runs it (exit 0)."""
    scene = tmp_path / "drop.toml"
    scene.write_text(f'[simulation]\ndt = 2.5e-4\nframes = 2\n[[jelly]]\nmesh = "{critter}"\ncenter = [0.0, 0.5, 0.0]\n'
                     'total_mass = 0.5\nsprings.structural = { ks = 120.0, kd = 0.15 }\n[[plane]]\n')
    code = cli.main(["run", str(scene), "--out", str(tmp_path / "d.usdc"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert err.startswith("drop: 3 frames") and len(err.splitlines()) == 1, err  # the summary, no warning


@pytest.mark.parametrize("command", [["run", "jelly_drop", "--frames", "2"], ["compare", "jelly_drop", "--frames", "2"]])
def test_full_disk_when_the_usd_file_is_created(tmp_path, command):
    """A disk with room for the lock but not for the new USD file (a real write limit, RLIMIT_FSIZE
    of 64 bytes: USD's CreateNew writes the file at once): one line naming --out, exit 2, no
    temporary left (it was a traceback and a hidden .partial file)."""
    import resource  # noqa: PLC0415

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    proc = subprocess.run([sys.executable, "-m", "softsim_warp", *command, "--quiet", "--out", "o.usdc"],
                          check=False, cwd=tmp_path, capture_output=True, text=True, preexec_fn=limit, timeout=600)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: command line: --out: cannot write") and "o.usdc" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="needs the sweep extra")
def test_sweep_full_disk_is_a_write_error_not_a_lost_scheduler(tmp_path):
    """The rows' part file cannot be written (RLIMIT_FSIZE of 64 bytes, as a full disk): one line
    naming --out and the cause, exit 2 (it said "the scheduler was lost", exit 1), and no empty parts
    folder left to demand --resume of the next sweep."""
    import resource  # noqa: PLC0415

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    proc = subprocess.run(
        [sys.executable, "-m", "softsim_warp", "sweep", "jelly_drop", "--vary", "jelly.0.total_mass=1,2",
         "--set", "simulation.frames=2", "--set", "jelly.0.resolution=3", "--workers", "1", "--quiet", "--out", "s.csv"],
        check=False, cwd=tmp_path, capture_output=True, text=True, preexec_fn=limit, timeout=600)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: command line: --out: cannot write the rows of"), lines
    assert "scheduler" not in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_size_warning_suggests_units_only_when_not_given(tmp_path, capsys):
    """An OBJ read as metres at 1.2 mm: the warning offers size or units; given units that still
    make it 1.2 mm, it offers size alone (units were already given)."""
    obj = tmp_path / "box.obj"
    corners = [(x, y, z) for x in (0, 1.2) for y in (0, 1.0) for z in (0, 1.0)]
    faces = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "".join(f"f {a} {b} {c} {d}\n" for a, b, c, d in faces))
    base = {"mesh": str(obj), "center": [0.0, 1.0, 0.0], "total_mass": 0.5, "springs": {"structural": {"ks": 120.0, "kd": 0.15}}}
    scene_from_dict({"simulation": {"dt": 2.5e-4, "frames": 1}, "jelly": [{**base, "units": "mm", "resolution": 4}]})
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is 0.0012 m along its longest side" in err[0], err
    assert err[0].endswith("give size (its longest side [m]) (got nothing)"), err
    obj_m = tmp_path / "tiny.obj"
    obj_m.write_text(obj.read_text().replace("1.2", "0.0012").replace(" 1.0", " 0.001"))
    scene_from_dict({"simulation": {"dt": 2.5e-4, "frames": 1}, "jelly": [{**base, "mesh": str(obj_m), "resolution": 4}]})
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "give size (its longest side [m]) or units" in err[0], err
