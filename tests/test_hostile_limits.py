"""Limits and results: memory limits other than free memory, step counts checked in every
command before any work, durations that are not whole frames and stops within long frames, bounded
iteration counts, overflow reported as an explosion, the initial scale in the precision check, the
energy summary's advice, and jellies that start overlapping."""

from __future__ import annotations

import json
import math
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softsim_warp import load_scene
from softsim_warp.commands import cli
from softsim_warp.core.errors import SceneError
from softsim_warp.io import checks, resources, runinfo
from softsim_warp.io import scene as scene_mod
from tests.helpers import sigterm_after_first_frame

GIB = 1 << 30


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error: "), err
    assert "Traceback" not in err and "Warning" not in err
    return lines[0]


def _main(args, capsys):
    code = cli.main(list(args))
    return code, capsys.readouterr().err


FALL = """\
name = "fall"
[simulation]
integrator = "symplectic"
dt = 0.001
{timing}
gravity = [0.0, -9.8, 0.0]
{extra}
[[jelly]]
resolution = 3
size = 0.2
center = [0.0, 10.0, 0.0]
particle_mass = 0.01
velocity = {velocity}
[jelly.springs.structural]
ks = 50.0
kd = 0.1
"""


def _fall(tmp_path, timing="duration = 0.5\nfps = 1.0", extra="", velocity="[0.0, 0.0, 0.0]", name="fall.toml"):
    path = tmp_path / name
    path.write_text(FALL.format(timing=timing, extra=extra, velocity=velocity))
    return path


# ---------------------------------------------------------------------------------------------
# 1. Memory limits other than free memory


def _limited(limit_bytes):
    def preexec():
        resource.setrlimit(resource.RLIMIT_AS, (limit_bytes, limit_bytes))

    return preexec


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS and /proc/self/status")
@pytest.mark.parametrize(
    "args",
    [
        ["run", "jelly_drop", "--set", "jelly.0.resolution=250", "--out", "x.usdc"],
        ["compare", "jelly_drop", "--set", "jelly.0.resolution=250", "--integrators", "symplectic", "--out", "x.usdc"],
        ["accuracy", "jelly_drop", "--set", "jelly.0.resolution=150"],
        ["stability", "jelly_drop", "--set", "jelly.0.resolution=150"],
        ["bench", "--sizes", "150"],
    ],
    ids=["run", "compare", "accuracy", "stability", "bench"],
)
def test_address_space_limit_refuses_in_every_command(tmp_path, args):
    """Under `ulimit -v` (4 GiB) a 150^3 jelly (250^3 for run and compare, whose box jellies are built as recorded lattices) is refused in one line that
    names the address-space limit, exit 2, instead of dying in NumPy's allocator; nothing written."""
    proc = subprocess.run([sys.executable, "-m", "softsim_warp", *args, "--quiet"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, preexec_fn=_limited(4 * GIB), check=False)
    err = proc.stderr
    if args[0] == "bench":  # Warp's start-up lines are tested elsewhere (test_hostile_io): only the error here
        err = "\n".join(line for line in err.splitlines() if not line.startswith(("Warp ", "   ", "Module ")))
    line = _one_error_line(err)
    assert proc.returncode == 2, proc.stderr
    assert "too large" in line and "under the address-space limit" in line, line
    assert ("jelly.0.resolution" in line) or ("--sizes" in line), line
    assert not list(tmp_path.iterdir())


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS and /proc/self/status")
def test_address_space_available_is_limit_minus_mapped():
    """In a child with RLIMIT_AS set, the bound is the limit less what the process has mapped and
    the room of the libraries not loaded yet (usd-core and Warp's runtime here)."""
    code = ("import resource; from softsim_warp.io import resources as r; "
            "lim = r.host_memory_limits(); "
            "vm = [int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize:')][0]; "
            "soft = resource.getrlimit(resource.RLIMIT_AS)[0] - r.USD_ADDRESS_RESERVE - r.WARP_ADDRESS_RESERVE; "
            "a = lim['address-space limit']; "
            "assert 0 < a <= soft - vm + (64 << 20) and a >= soft - vm - (64 << 20), (a, soft, vm); "
            "assert r.available_host_bytes() == min(lim.values()); print(a)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          preexec_fn=_limited(6 * GIB), check=False)
    assert proc.returncode == 0, proc.stderr
    assert 0 < int(proc.stdout.split()[-1]) < 6 * GIB


def _cgroup(root: Path, files: dict):
    root.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_cgroup_v2_limit(tmp_path, monkeypatch):
    """cgroup v2: memory.max minus memory.current bounds the memory; "max" is no bound; a nested
    cgroup's tighter limit wins over the root's."""
    monkeypatch.setattr(resources, "CGROUP_ROOT", str(tmp_path))
    monkeypatch.setattr(resources, "_own_cgroup_dirs", lambda: [str(tmp_path / "job"), str(tmp_path)])
    _cgroup(tmp_path, {"memory.max": "max\n", "memory.current": "123\n"})
    assert "cgroup memory limit" not in resources.host_memory_limits()
    _cgroup(tmp_path, {"memory.max": str(3 * GIB), "memory.current": str(GIB)})
    assert resources.host_memory_limits()["cgroup memory limit"] == 2 * GIB
    _cgroup(tmp_path / "job", {"memory.max": str(GIB), "memory.current": str(GIB // 4)})
    assert resources.host_memory_limits()["cgroup memory limit"] == GIB - GIB // 4
    assert resources.available_host_bytes() <= GIB - GIB // 4


def test_cgroup_v1_limit(tmp_path, monkeypatch):
    """cgroup v1: memory/memory.limit_in_bytes minus usage; the huge 'unlimited' value is no bound."""
    monkeypatch.setattr(resources, "CGROUP_ROOT", str(tmp_path))
    monkeypatch.setattr(resources, "_own_cgroup_dirs", lambda: [str(tmp_path)])
    _cgroup(tmp_path, {"memory/memory.limit_in_bytes": "9223372036854771712", "memory/memory.usage_in_bytes": "5"})
    assert "cgroup memory limit" not in resources.host_memory_limits()
    _cgroup(tmp_path, {"memory/memory.limit_in_bytes": str(2 * GIB), "memory/memory.usage_in_bytes": str(GIB // 2)})
    assert resources.host_memory_limits()["cgroup memory limit"] == GIB + GIB // 2


def test_cgroup_limit_refuses_run_naming_it(tmp_path, monkeypatch, capsys):
    """A 64 MiB cgroup refuses jelly_drop at 60^3 (about 0.6 GiB) in one line naming the cgroup."""
    cg = tmp_path / "cg"
    monkeypatch.setattr(resources, "CGROUP_ROOT", str(cg))
    monkeypatch.setattr(resources, "_own_cgroup_dirs", lambda: [str(cg)])
    _cgroup(cg, {"memory.max": str(64 << 20), "memory.current": "0"})
    monkeypatch.chdir(tmp_path)
    code, err = _main(["run", "jelly_drop", "--set", "jelly.0.resolution=60", "--quiet", "--out", "x.usdc"], capsys)
    line = _one_error_line(err)
    assert code == 2
    assert "jelly.0.resolution: scene too large" in line and "64 MiB available under the cgroup memory limit" in line
    assert not (tmp_path / "x.usdc").exists()


def test_bench_copies_blames_copies(capsys):
    code, err = _main(["bench", "--copies", "100000000", "--quiet"], capsys)
    line = _one_error_line(err)
    assert code == 2 and "command line: --copies: too large" in line and "(got 100000000)" in line


def test_bench_contact_jellies_checked(capsys):
    """bench --contact builds piles only after their size is checked: 10^8 jellies are refused."""
    code, err = _main(["bench", "--contact", "--jellies", "100000000", "--quiet"], capsys)
    line = _one_error_line(err)
    assert code == 2 and "command line: --jellies: too large" in line


def test_contact_allowance_counts():
    """The contact allowance makes a pile cost more than the same particles without contact."""
    dev = SimpleNamespace(is_cuda=False)
    n, springs = 1000, 12876
    plain = n * resources._device_per_particle(4, "symplectic") + springs * resources._device_per_spring(4, "symplectic", False)
    with pytest.raises(Exception, match="--jellies"):
        resources.check_counts(n, springs, dev, "symplectic", "--jellies", 1, host_available=plain + 96 * n + 192 * springs,
                               contact_particles=n)
    resources.check_counts(n, springs, dev, "symplectic", "--jellies", 1, host_available=plain + 96 * n + 192 * springs)


# ---------------------------------------------------------------------------------------------
# 2. Steps: every command refuses a run that cannot finish, before any work


@pytest.mark.parametrize(
    "args, flag",
    [
        (["compare", "jelly_drop", "--dt", "1e-12", "--integrators", "symplectic,rk4"], "simulation.dt"),
        (["accuracy", "jelly_drop", "--reference-dt", "1e-12"], "--reference-dt"),
        (["stability", "jelly_drop", "--steps", "1000000000000"], "--steps"),
        (["stability", "jelly_drop", "--duration", "1e9"], "--duration"),
    ],
    ids=["compare", "accuracy", "stability_steps", "stability_duration"],
)
def test_too_many_steps_refused_at_once(tmp_path, monkeypatch, capsys, args, flag):
    monkeypatch.chdir(tmp_path)
    t0 = time.perf_counter()
    code, err = _main([*args, "--quiet"], capsys)
    line = _one_error_line(err)
    assert code == 2 and f": {flag}: " in line, line
    assert time.perf_counter() - t0 < 60  # refused up front, not after running
    assert not list(tmp_path.iterdir())


def test_sweep_steps_checked_for_every_variant_and_scheduler():
    """Each variant's own dt is checked (not only each group's first), also for a remote scheduler
    (a device named by kind), before any cluster is started."""
    from softsim_warp.commands import sweep  # noqa: PLC0415

    scene = load_scene("jelly_drop")
    ok = SimpleNamespace(data=scene.data)
    bad_data = json.loads(json.dumps(scene.data))
    bad_data["simulation"]["dt"] = 1e-12
    bad = SimpleNamespace(data=bad_data)
    sweep.check_variant_steps([ok], "jelly_drop.toml", "run", "cuda")
    for device in ("cpu", "cuda", SimpleNamespace(is_cuda=False)):
        with pytest.raises(SceneError, match="too many steps"):
            sweep.check_variant_steps([ok, bad], "jelly_drop.toml", "run", device)
    sweep.check_variant_steps([ok, bad], "jelly_drop.toml", "stable_dt", "cpu")  # probes bound their own steps


def test_stability_limits_are_measured_not_all_below_min_dt():
    """The cause of 'every limit < 1e-07': probes longer than the cap count as unstable. A run within
    the cap finds a real limit (the analysis' prediction within a factor 2)."""
    from softsim_warp.studies import stability as st  # noqa: PLC0415

    assert st.MAX_PROBE_STEPS >= st.DEFAULT_STEPS
    scene = load_scene("free_flight")
    js = st.free_jelly(scene.jellies[0], max_n=4)
    import warp as wp  # noqa: PLC0415

    dev = wp.get_device("cpu")
    p = float(st.predict(js, ["symplectic"], dev)["symplectic"])
    lat = st.lattice_model(js, dev, "float32")
    lim = st.measure_limit(lat, "symplectic", guess=p, steps=st.MAX_PROBE_STEPS // 400, max_dt=1.0, rtol=0.1)
    assert lim["bound"] == "" and 0.5 * p < lim["dt"] < 2.0 * p


# ---------------------------------------------------------------------------------------------
# 3. Durations that are not whole frames; stops within long frames


def test_builtin_scenes_keep_whole_frames():
    """Every built-in scene's duration is whole frames: same frame count as before, no end time
    (so their CPU results stay bitwise the same)."""
    for name in scene_mod.builtin_scenes():
        sc = load_scene(name)
        assert sc.end_time() is None, name
        if "duration" in sc.sim:
            assert sc.frame_count() == max(1, round(sc.sim["duration"] * sc.sim["fps"])), name
        assert sc.run_seconds() == pytest.approx(sc.frame_count() / sc.sim["fps"])


@pytest.mark.parametrize(
    "duration, fps, dt, frames, end",
    [(0.5, 1.0, 1e-3, 1, 0.5), (0.1, 1e-6, 1e-3, 1, 0.1), (2.5, 2.0, 1e-3, 5, None), (1.25, 2.0, 1e-3, 3, 1.25),
     (0.1, 30.0, 1e-3, 3, None), (1.0001, 1.0, 1e-3, 1, None)],
)
def test_frame_count_and_end_time(duration, fps, dt, frames, end):
    """Rounded up, the last frame ends at the duration; whole frames (up to rounding) stay whole; a
    remainder below half a step at this dt ends the run at the frame before."""
    sc = load_scene("jelly_drop", [f"simulation.duration={duration}", f"simulation.fps={fps}", f"simulation.dt={dt}"])
    assert sc.frame_count() == frames
    assert sc.end_time() == end
    assert sc.run_seconds() == pytest.approx(end if end is not None else frames / fps)


def test_tiny_fps_is_few_steps_not_a_billion():
    """fps = 1e-6, duration = 0.1: the run's steps are the duration's, 100, not one frame of 10^6 s
    (10^9 steps at dt = 1 ms)."""
    sc = load_scene("jelly_drop", ["simulation.duration=0.1", "simulation.fps=1e-6", "simulation.dt=1e-3"])
    assert resources.check_steps(sc, SimpleNamespace(is_cuda=False), sc.frame_count()) == pytest.approx(100.0)


def test_half_frame_ends_at_duration_free_fall(tmp_path, monkeypatch, capsys):
    """fps = 1, duration = 0.5: two frames, the last at t = 0.5 s (metrics, USD time code and end
    time), and the jelly has fallen as free fall says: symplectic Euler's closed form
    y_n = y_0 - g dt^2 n (n + 1) / 2, v_n = -g n dt, after n = 500 steps (within the float32
    rounding of the positions), and the continuous 0.5 g t^2 within g dt t / 2 (a run of the whole
    last frame, 1 s, would be 4.9 m lower)."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    monkeypatch.chdir(tmp_path)
    _fall(tmp_path)
    code, err = _main(["run", "fall.toml", "--out", "f.usda", "--metrics", "f.json", "--quiet"], capsys)
    assert code == 0, err
    frames = json.loads((tmp_path / "f.json").read_text())["frames"]
    assert [f["time"] for f in frames] == [0.0, 0.5]
    g, dt, n, y0 = 9.8, 1e-3, 500, 10.0
    y_discrete = y0 - g * dt * dt * n * (n + 1) / 2
    com = frames[-1]["com"]
    # Each float32 step rounds y (and v dt) by at most an ulp: n eps y0 bounds the sum, 6e-4 m, a
    # quarter of the gap to the continuous value (g dt t / 2 = 2.45e-3 m) that the next line checks.
    rounding = n * float(np.finfo(np.float32).eps) * y0
    assert com[1] == pytest.approx(y_discrete, abs=rounding)
    assert abs(com[1] - (y0 - 0.5 * g * 0.5**2)) <= g * dt * 0.5 / 2 + 1e-5
    # The fastest particle: the fall's g n dt plus the springs' response to float32 rounding.
    assert frames[-1]["max_speed"] == pytest.approx(g * n * dt, rel=1e-4)
    stage = Usd.Stage.Open(str(tmp_path / "f.usda"))
    assert stage.GetEndTimeCode() == 0.5
    pts = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Points))
    samples = UsdGeom.Points(pts).GetPointsAttr().GetTimeSamples()
    assert samples == [0.0, 0.5]
    y = np.asarray(UsdGeom.Points(pts).GetPointsAttr().Get(0.5))[:, 1]
    assert y.mean() == pytest.approx(y_discrete, abs=rounding)


def test_stop_within_a_long_frame_keeps_frames(tmp_path, monkeypatch, capsys):
    """A real SIGTERM during a frame of 10^7 steps (fps = 1e-4) stops the run within about a second:
    exit 143, frame 0 kept and marked interrupted (the long frame is dropped)."""

    monkeypatch.chdir(tmp_path)
    _fall(tmp_path, timing="duration = 20000.0\nfps = 0.0001")
    sent = sigterm_after_first_frame(monkeypatch, 0.5)  # well inside the long frame
    code, err = _main(["run", "fall.toml", "--out", "l.usda", "--metrics", "l.json", "--quiet"], capsys)
    stopped = time.perf_counter()
    sent["thread"].join(5)
    assert code == 128 + signal.SIGTERM, err
    assert stopped - sent["t"] < 5.0  # the frame alone would take minutes
    summary = json.loads((tmp_path / "l.json").read_text())
    assert summary["summary"]["status"] == "interrupted" and len(summary["frames"]) == 1
    assert summary["summary"]["steps"] == 0


def test_stepper_stop_between_chunks_same_result(monkeypatch):
    """advance(n, stop) takes the same chunks with or without the callable (bitwise the same state),
    and stops before the next chunk when asked, returning the steps taken."""
    from softsim_warp import build_model  # noqa: PLC0415
    from softsim_warp.core import stepper as stepper_mod  # noqa: PLC0415

    monkeypatch.setattr(stepper_mod, "MAX_GRAPH_STEPS", 7)
    scene = load_scene("free_flight")
    for use_graph in (False, True):
        states = []
        for stop in (None, lambda: False):
            model = build_model(scene, device="cpu")
            st = stepper_mod.Stepper(model, stepper_mod.make_integrator("symplectic", model), 1e-3, use_graph=use_graph)
            assert st.advance(30, stop) == 30
            states.append(st.state.particle_q.numpy().copy())
        assert np.array_equal(states[0], states[1])
        model = build_model(scene, device="cpu")
        st = stepper_mod.Stepper(model, stepper_mod.make_integrator("symplectic", model), 1e-3, use_graph=use_graph)
        asked = iter([False, False, True])
        assert st.advance(30, lambda it=asked: next(it)) == 14  # two chunks of 7, then stop


# ---------------------------------------------------------------------------------------------
# 4 and 5. Bounded counts, huge integers blamed on their key


def _int_fields(table, prefix=""):
    for key, field in table.fields.items():
        name = f"{prefix}{key}"
        if isinstance(field, scene_mod.Int):
            yield name, field
        inner = getattr(field, "item", None) or field
        if hasattr(inner, "fields"):
            yield from _int_fields(inner, name + ".")


def test_every_iteration_count_has_an_upper_bound():
    counts = [(name, f) for name, f in _int_fields(scene_mod.SCHEMA) if "iterations" in name]
    assert {n for n, _ in counts} >= {"simulation.jelly_contact_iterations", "implicit.newton_iterations",
                                      "implicit.cg_max_iterations"}
    for name, field in counts:
        assert field.hi is not None and field.hi <= 10_000, name


@pytest.mark.parametrize(
    "key, hi",
    [("simulation.jelly_contact_iterations", scene_mod.MAX_CONTACT_ITERATIONS),
     ("implicit.newton_iterations", scene_mod.MAX_NEWTON_ITERATIONS),
     ("implicit.cg_max_iterations", scene_mod.MAX_CG_ITERATIONS)],
)
def test_iteration_bounds(key, hi):
    load_scene("jelly_drop", [f"{key}={hi}"])
    for bad in (hi + 1, 10**9, "1e9"):
        with pytest.raises(SceneError) as e:
            load_scene("jelly_drop", [f"{key}={bad}"])
        assert e.value.key == key and f"<= {hi:,}" in e.value.line()


@pytest.mark.parametrize("known_memory", [True, False])
def test_huge_resolution_blames_resolution(monkeypatch, known_memory):
    """2^63 - 1 per axis with total_mass: the derived particle mass underflows, but the answer names
    the resolution, with or without a readable memory size."""
    if not known_memory:
        monkeypatch.setattr(resources, "available_host_bytes", lambda: None)
    for value in ("9223372036854775807", "[2, 2, 9223372036854775807]"):
        with pytest.raises(SceneError) as e:
            load_scene("jelly_drop", [f"jelly.0.resolution={value}"])
        assert e.value.key == "jelly.0.resolution" and "scene too large" in e.value.line()


# ---------------------------------------------------------------------------------------------
# 6. Overflow is an explosion; no library warnings


@pytest.mark.parametrize(
    "overrides",
    [["jelly.0.velocity=[1e38, 0, 0]"], ["simulation.gravity=[0, -1e308, 0]", "simulation.precision=\"float64\""]],
    ids=["velocity_1e38", "gravity_1e308_float64"],
)
def test_overflow_is_an_explosion(tmp_path, monkeypatch, capsys, overrides):
    monkeypatch.chdir(tmp_path)
    _fall(tmp_path, timing="frames = 3\nfps = 30.0")
    args = ["run", "fall.toml", "--out", "v.usda", "--metrics", "v.json", "--quiet"]
    for o in overrides:
        args += ["--set", o]
    code, err = _main(args, capsys)
    assert code == 3, err
    assert "Warning" not in err and "warn" not in err.lower()
    lines = err.strip().splitlines()
    assert lines[-1].startswith("error: fall.toml: simulation exploded at frame 0") and "overflows" in lines[-1]
    assert "dt predicted" not in lines[-1]  # a smaller step would not help
    assert "nan J" not in err and "dissipated" not in err


def test_gravity_near_the_float64_end_is_an_explosion(tmp_path, monkeypatch, capsys):
    """jelly_drop under gravity 1e308 in float64: no energy overflows to inf (m g h ~ 1e308 J), yet
    every energy is past sqrt(max), where the energy change means nothing: an explosion, not a
    report of '1e+308 J dissipated'."""
    monkeypatch.chdir(tmp_path)
    code, err = _main(["run", "jelly_drop", "--frames", "2", "--out", "g.usdc", "--quiet", "--set",
                       "simulation.gravity=[0, -1e308, 0]", "--set", 'simulation.precision="float64"'], capsys)
    assert code == 3, err
    assert "overflows" in err and "dissipated" not in err


def test_energy_overflow_mid_run_keeps_frames(tmp_path, monkeypatch, capsys):
    """Finite at the start, overflowing later: the good frames are kept, marked exploded, strict JSON."""
    monkeypatch.chdir(tmp_path)
    _fall(tmp_path, timing="frames = 20\nfps = 30.0", extra="max_speed = 3e38", velocity="[1e8, 0, 0]")
    code, err = _main(["run", "fall.toml", "--out", "v.usda", "--metrics", "v.json", "--quiet",
                       "--set", "simulation.gravity=[0, -1e15, 0]"], capsys)
    assert code == 3, err
    assert "RuntimeWarning" not in err
    data = json.loads((tmp_path / "v.json").read_text())  # strict JSON: parses
    assert data["summary"]["status"] == "exploded"
    k = data["summary"]["explosion"]["frame"]
    assert k >= 1 and len(data["frames"]) == k
    assert all(math.isfinite(f["total_energy"]) for f in data["frames"])


def test_measure_does_not_warn():
    """The probe's sums of an overflowing state give non-finite numbers without a NumPy warning."""
    import warnings  # noqa: PLC0415

    from softsim_warp import build_model  # noqa: PLC0415
    from softsim_warp.io.metrics import make_probe  # noqa: PLC0415

    scene = load_scene("jelly_drop", ["jelly.0.velocity=[1e38, 0, 0]", "jelly.0.resolution=3"])
    model = build_model(scene, device="cpu")
    probe = make_probe(model)
    state = model.state()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = probe.measure(state, 0, 0.0)
    assert not math.isfinite(m.total_energy)


# ---------------------------------------------------------------------------------------------
# 7. initial_scale in the precision and terrain checks


def test_initial_scale_below_precision_refused():
    with pytest.raises(SceneError) as e:
        load_scene("jelly_drop", ["jelly.0.initial_scale=1e-20"])
    assert e.value.key == "jelly.0.initial_scale" and "starting particle spacing" in e.value.line()
    with pytest.raises(SceneError):
        load_scene("jelly_drop", ["jelly.0.initial_scale=[1, 1e-6, 1]"])  # one axis is enough
    load_scene("jelly_drop", ["jelly.0.initial_scale=1e-6", 'simulation.precision="float64"'])  # float64 resolves it
    load_scene("hard_crushed")  # a tenth: fine


def test_terrain_check_uses_initial_scale():
    """jelly_drop's box (0.5 m) at y = 0.3 reaches below the ground; crushed to a tenth it does not,
    stretched threefold at y = 1 it does."""
    with pytest.raises(SceneError, match="inside terrain"):
        load_scene("jelly_drop", ["jelly.0.center=[0, 0.2, 0]"])
    load_scene("jelly_drop", ["jelly.0.center=[0, 0.2, 0]", "jelly.0.initial_scale=0.1"])
    with pytest.raises(SceneError, match="inside terrain"):
        load_scene("jelly_drop", ["jelly.0.initial_scale=[1, 5, 1]"])


# ---------------------------------------------------------------------------------------------
# 8. The energy summary's advice


def _summary(drift, rel, floor=0.0, pins=False, frames=10):
    return {"status": "complete", "energy_drift": drift, "energy_drift_relative": rel, "energy_rounding": floor,
            "pins_drive": pins, "frames": frames, "scene": "s", "steps": 1, "integrator": "symplectic", "dt": 1e-3,
            "wall_seconds": 1.0, "particle_steps_per_second": 1.0}


def test_summary_line_advice():
    assert "try a smaller dt" in runinfo.summary_line(_summary(0.5, 0.1), "o.usdc")
    line = runinfo.summary_line(_summary(3e-11, 10.34, floor=1e-9), "o.usdc")
    assert "within the rounding" in line and "smaller dt" not in line
    line = runinfo.summary_line(_summary(0.5, 0.1, pins=True), "o.usdc")
    assert "work of the driven pins" in line and "smaller dt" not in line
    assert "dissipated" not in runinfo.summary_line(_summary(-0.5, -0.1, pins=True), "o.usdc")


def test_energy_floor_bounds_rounding_at_rest(tmp_path, monkeypatch, capsys):
    """A float32 10^3 jelly at rest in zero gravity: its energy changes by rounding alone, which is
    below the floor (and so not called a gain); in float64 the same change is 10^8 times smaller."""
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "rest.toml"
    path.write_text(FALL.format(timing="duration = 1.0\nfps = 30.0", extra="", velocity="[0.0, 0.0, 0.0]")
                    .replace("gravity = [0.0, -9.8, 0.0]", "gravity = [0.0, 0.0, 0.0]")
                    .replace("resolution = 3", "resolution = 10").replace("size = 0.2", "size = 0.5")
                    .replace("ks = 50.0", "ks = 1000.0"))
    drifts = {}
    for precision in ("float32", "float64"):
        code, err = _main(["run", "rest.toml", "--out", f"r{precision}.usdc", "--metrics", f"r{precision}.json",
                           "--quiet", "--precision", precision], capsys)
        assert code == 0, err
        s = json.loads((tmp_path / f"r{precision}.json").read_text())["summary"]
        assert abs(s["energy_drift"]) <= s["energy_rounding"], s
        assert "smaller dt" not in err and "within the rounding" in err
        drifts[precision] = s["energy_rounding"]
    assert drifts["float64"] < 1e-8 * drifts["float32"]


def test_real_gain_still_reported(tmp_path, monkeypatch, capsys):
    """Explicit Euler without damping gains energy every step (|1 + i w dt| > 1): still called a gain."""
    monkeypatch.chdir(tmp_path)
    code, err = _main(["run", "hard_undamped", "--integrator", "euler", "--frames", "3", "--out", "u.usdc", "--quiet",
                           "--allow-unstable"],
                      capsys)
    assert code == 0, err
    assert "energy GAINED" in err and "try a smaller dt" in err


def test_hang_scene_not_blamed_on_integrator(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = _main(["run", "hang", "--frames", "60", "--out", "h.usdc", "--quiet"], capsys)
    assert code == 0, err
    assert "adds energy" not in err and "driven pins" in err


# ---------------------------------------------------------------------------------------------
# 9. Jellies that start overlapping


def _box(center, degrees=0.0, size=(1.0, 1.0, 1.0), axis=(0.0, 1.0, 0.0)):
    return {"center": list(center), "size": list(size), "rotation": {"axis": list(axis), "degrees": degrees}}


def test_box_overlap_geometry():
    """Separating-axis depth: apart, touching, overlapping; rotated boxes whose axis-aligned bounds
    overlap but which do not."""
    a = checks.jelly_box(_box((0, 0, 0)))
    assert checks.box_overlap(a, checks.jelly_box(_box((0.5, 0, 0)))) == pytest.approx(0.5)
    assert checks.box_overlap(a, checks.jelly_box(_box((1.0, 0, 0)))) == pytest.approx(0.0, abs=1e-12)
    assert checks.box_overlap(a, checks.jelly_box(_box((2.0, 0, 0)))) < 0
    # Two cubes turned 45 degrees about z, side by side along x at 1.45 m: their bounds (1.414 m
    # wide) overlap, the cubes (corner to corner at 1.414 m) do not.
    r1 = checks.jelly_box(_box((0, 0, 0), 45.0, axis=(0, 0, 1)))
    r2 = checks.jelly_box(_box((1.45, 0, 0), 45.0, axis=(0, 0, 1)))
    assert checks.box_overlap(r1, r2) < 0


def test_identical_jellies_warned(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    text = FALL.format(timing="frames = 2\nfps = 30.0", extra="", velocity="[0.0, 0.0, 0.0]")
    jelly = text[text.index("[[jelly]]"):]
    (tmp_path / "two.toml").write_text(text + "\n" + jelly)
    code, err = _main(["run", "two.toml", "--out", "t.usdc", "--quiet"], capsys)
    assert code == 0
    warnings_ = [line for line in err.splitlines() if line.startswith("warning:")]
    assert warnings_ == [
        ("warning: two.toml: jelly.1.center: jelly.1 starts overlapping jelly.0 by 0.2 m; they may stay fused; "
         "move one of them (got [0.0, 10.0, 0.0])")
    ]


def test_builtin_multi_jelly_scenes_not_warned():
    for name in ("stack", "collide", "pile", "hard_mass_ratio"):
        sc = load_scene(name)
        assert checks.jelly_overlaps(sc.data) == [], name


def test_moving_terrain_not_blamed_on_integrator():
    """A lid, a platform or a roller does work on the jellies, like a driven pin: the summary says so
    and gives no dt advice; a terrain entry without motion drives nothing."""
    from softsim_warp.io.runinfo import pins_drive
    from softsim_warp.io.scene import load_scene

    for name in ("squeeze", "platform", "roller", "turntable", "hang"):
        assert pins_drive(load_scene(name)), name
    for name in ("jelly_drop", "seed_bowl", "mesh_drop"):
        assert not pins_drive(load_scene(name)), name


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_AS and /proc/self/status")
def test_tight_address_space_leaves_room_for_the_libraries(tmp_path):
    """Under `ulimit -v` 1.5 GB a 10^3 jelly's arrays fit, but usd-core and Warp map about 1 GB more
    after the check and then crash in native code (a segfault, exit 139): the check keeps their
    room, so the answer is one line and exit 2."""
    proc = subprocess.run([sys.executable, "-m", "softsim_warp", "run", "jelly_drop", "--frames", "2", "--out",
                           "x.usdc", "--quiet"], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          preexec_fn=_limited(1_500_000 * 1024), check=False)
    assert proc.returncode == 2, proc.stderr
    line = _one_error_line(proc.stderr)
    assert "address-space limit" in line
    assert not (tmp_path / "x.usdc").exists()
