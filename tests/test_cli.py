"""The command line end to end on tiny scenes."""

import contextlib
import json
import math
import subprocess
import sys

import pytest
import warp as wp
from pxr import Usd, UsdGeom

TINY = """
name = "tiny"
[simulation]
integrator = "midpoint"
dt = 0.001
frames = 4
fps = 50
[[jelly]]
resolution = 3
size = 0.2
center = [0, 0.3, 0]
particle_mass = 0.01
springs.structural = { ks = 20.0, kd = 0.02 }
springs.shear = { ks = 20.0, kd = 0.02 }
[[plane]]
"""


def softsim(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "softsim_warp", *args], capture_output=True, text=True, cwd=cwd, timeout=600)


def test_run_end_to_end(tmp_path):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    out, metrics = tmp_path / "tiny.usda", tmp_path / "m.json"
    r = softsim("run", str(scene), "--out", str(out), "--metrics", str(metrics), "--quiet")
    assert r.returncode == 0, r.stderr
    data = json.loads(metrics.read_text())
    s = data["summary"]
    for key in ("scene", "integrator", "dt", "device", "particles", "springs", "steps", "frames", "sim_time",
                "wall_seconds", "compile_seconds", "particle_steps_per_second", "exploded"):
        assert key in s
    # 27 particles; no bending springs were asked for: 54 structural + 72 face + 32 body shear.
    assert (s["particles"], s["springs"], s["integrator"], s["exploded"]) == (27, 158, "midpoint", False)
    # 4 frames after frame 0 at 50 fps with dt 1 ms: 20 steps per frame.
    assert (s["frames"], s["steps"]) == (5, 80)
    assert len(data["frames"]) == 5
    f = data["frames"][2]
    assert f["time"] == 0.04
    # Free fall until contact: the centre of mass drops g t^2 / 2 (midpoint is exact for constant g).
    assert abs(f["com"][1] - (0.3 - 0.5 * 9.8 * 0.04**2)) < 1e-6
    assert abs(f["total_energy"] - data["frames"][0]["total_energy"]) < 1e-6
    stage = Usd.Stage.Open(str(out))
    assert len(UsdGeom.Points(stage.GetPrimAtPath("/World/Jelly_0/Particles")).GetPointsAttr().GetTimeSamples()) == 5
    assert "tiny: 5 frames, 80 steps of midpoint" in r.stderr


def test_flags_override_scene_and_builtin_by_name(tmp_path):
    r = softsim("run", "jelly_drop", "--integrator", "rk4", "--frames", "2", "--dt", "0.001",
                "--set", "jelly.0.resolution=3", "--metrics", "m.json", "--out", "o.usdc", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    s = json.loads((tmp_path / "m.json").read_text())["summary"]
    assert (s["integrator"], s["dt"], s["particles"], s["frames"]) == ("rk4", 0.001, 27, 3)


def test_user_errors_are_one_line(tmp_path):
    r = softsim("run", "jelly_drop", "--set", "simulation.dt=-1", "--out", str(tmp_path / "x.usdc"))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "error: jelly_drop.toml: simulation.dt: must be a finite number > 0 (got -1)"
    ]
    r = softsim("run", "jelly_drop", "--set", "jelly.0.springs.shear.kss=3")
    assert r.returncode == 2 and "did you mean 'ks'?" in r.stderr and "Traceback" not in r.stderr
    r = softsim("run", "no_such_scene")
    assert r.returncode == 2 and r.stderr.startswith("error: no_such_scene: scene: no such scene file or built-in scene")


def test_scenes_lists_builtins():
    r = softsim("scenes")
    assert r.returncode == 0 and (r.stdout.startswith("jelly_drop") or "jelly_drop " in r.stdout)


def test_bare_softsim_prints_usage_and_exits_2(capsys):
    from softsim_warp.commands import cli

    assert cli.main([]) == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: softsim") and "softsim -h" in err and "error" not in err


@pytest.mark.parametrize(
    "argv, line",
    [
        (["run", "jelly_drop", "--dt", "-1"], "error: command line: --dt: must be a finite number > 0 (got -1)"),
        (["run", "jelly_drop", "--fps", "0"], "error: command line: --fps: "),
        (["compare", "jelly_drop", "--dt", "0"], "error: command line: --dt: must be a finite number > 0 (got 0"),
        (["run", "jelly_drop", "--set", "simulation.dt=-1"], "error: jelly_drop.toml: simulation.dt: must be a finite"),
    ],
)
def test_a_bad_flag_is_named_not_the_scene_file(argv, line, capsys, tmp_path, monkeypatch):
    """A value a flag set is reported under the flag; one set by --set or the file under its key."""
    from softsim_warp.commands import cli

    monkeypatch.chdir(tmp_path)
    assert cli.main(argv + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(line), err


def test_compile_notice_only_for_a_slow_warm_up(capsys):
    """The one-line notice appears when a warm-up outlasts its threshold (a compile), once per
    process, never with --quiet, and not for a fast one (cached kernels)."""
    import time  # noqa: PLC0415

    from softsim_warp.commands import common  # noqa: PLC0415

    common.compile_notice.shown = False
    with common.compile_notice(after=0.5):
        pass
    with common.compile_notice(quiet=True, after=0.01):
        time.sleep(0.1)
    assert capsys.readouterr().err == ""
    with common.compile_notice(after=0.01):
        time.sleep(0.1)
    with common.compile_notice(after=0.01):
        time.sleep(0.1)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("compiling kernels (first run only; cached in ")
    common.compile_notice.shown = False


@pytest.mark.parametrize("argv", [
    ["run", "jelly_drop", "--frames", "2", "--out", "o.usdc"],
    ["compare", "jelly_drop", "--integrators", "euler,implicit", "--frames", "2", "--out", "o.usdc"],
    ["accuracy", "jelly_drop", "--integrators", "symplectic", "--dts", "0.002", "--duration", "0.02"],
    ["stability", "jelly_drop", "--integrators", "symplectic", "--ks", "none", "--steps", "10", "--lattice", "2",
     "--no-scene"],
], ids=lambda a: a[0])
@pytest.mark.parametrize("quiet", [False, True], ids=["shown", "quiet"])
def test_every_warm_up_of_a_command_gets_the_compile_notice(argv, quiet, tmp_path, monkeypatch):
    """The commands that simulate hand the compile notice to every simulator they make (its
    ``on_warm_up``), with --quiet passed on; no global hook list in the core."""
    from softsim_warp.commands import cli, common  # noqa: PLC0415
    from softsim_warp.core import stepper  # noqa: PLC0415

    entered = []

    @contextlib.contextmanager
    def notice(quiet=False, after=common.COMPILE_NOTICE_AFTER):
        entered.append(quiet)
        yield

    warm_ups = []
    warm_up = stepper.Stepper.warm_up

    def counted(self):
        warm_ups.append(self)
        return warm_up(self)

    monkeypatch.setattr(common, "compile_notice", notice)
    monkeypatch.setattr(stepper.Stepper, "warm_up", counted)
    monkeypatch.chdir(tmp_path)
    argv = argv + ["--set", "jelly.0.resolution=3"] + (["--quiet"] if quiet else [])
    assert cli.main(argv) == 0
    assert warm_ups and entered == [quiet] * len(warm_ups)


def test_a_stepper_enters_on_warm_up_around_its_warm_up_only():
    """``on_warm_up`` wraps the warm-up step (where kernels compile, before the first capture), not
    the steps after it."""
    import softsim_warp as ss  # noqa: PLC0415

    from tests.helpers import jelly_builder  # noqa: PLC0415

    model = jelly_builder().finalize("cpu")
    events = []

    @contextlib.contextmanager
    def around():
        events.append("enter")
        yield
        events.append("exit")

    stepper = ss.Stepper(model, ss.make_integrator("symplectic", model), 1e-3, on_warm_up=around)
    stepper.advance(3)
    stepper.advance(3)
    assert events == ["enter", "exit"] and stepper.warmed_up
    assert ss.Stepper(model, ss.make_integrator("symplectic", model), 1e-3).on_warm_up is None


def test_a_command_hands_its_first_signal_to_mains_handler():
    """A command's own handler (``common.Signals``) gives the first signal it took to the handler it
    puts back (``cli.main``'s): a stop after the block, or one leaving it, reports that signal, with
    no module global between them. Real signals, sent to this process."""
    import os  # noqa: PLC0415
    import signal  # noqa: PLC0415

    from softsim_warp.commands import cli, common, process  # noqa: PLC0415

    stop = cli._Stop()
    stop.armed = False  # record only: this test is its own process's main
    previous = {sig: signal.signal(sig, stop) for sig in process.STOP_SIGNALS}
    try:
        with common.Signals() as signals:
            os.kill(os.getpid(), signal.SIGTERM)  # the first: recorded, no stop yet
            os.kill(os.getpid(), signal.SIGINT)  # the second: stop now
        raise AssertionError("the second signal did not stop the block")
    except KeyboardInterrupt:
        pass
    finally:
        restored = signal.getsignal(signal.SIGTERM)
        for sig, old in previous.items():
            signal.signal(sig, old)
    assert (signals.received, signals.count, signals.stopped) == (signal.SIGTERM, 2, True)
    assert restored is stop and stop.received == signal.SIGTERM


def test_preview_refuses_flags_it_has_no_use_for(tmp_path, capsys):
    """`softsim preview` draws a USD file: it has no scene to `--set` and runs no kernel on a
    `--device`, so both are refused (one line, exit 2) rather than silently ignored."""
    from softsim_warp.commands.cli import main  # noqa: PLC0415

    for flag in (["--set", "jelly.0.size=1"], ["--device", "cuda:0"]):
        assert main(["preview", str(tmp_path / "x.usdc"), "--png", str(tmp_path / "x.png"), *flag]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "unrecognized arguments" in err[0] and flag[0] in err[0], err
        assert "see softsim preview --help" in err[0], err


def test_switch_given_a_value_is_one_line(capsys):
    from softsim_warp.commands.cli import main  # noqa: PLC0415

    assert main(["run", "jelly_drop", "--deterministic=yes"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: command line: --deterministic: is a switch and takes no value (got 'yes')"]


@pytest.mark.skipif(wp.get_cuda_device_count() > 0, reason="a GPU is present: --device cuda resolves")
def test_absent_cuda_is_one_line_without_driver_noise(capfd):
    """Without a GPU, `--device cuda` is refused in one line; Warp's driver errors (printed by its C
    code when it looks up the current context) must not come first."""
    from softsim_warp.commands.cli import main  # noqa: PLC0415

    capfd.readouterr()
    assert main(["run", "jelly_drop", "--device", "cuda"]) == 2
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert err == ["error: command line: --device: device not available here; available: cpu (got 'cuda')"]


def test_energy_change_without_energy_to_compare_with():
    """A jelly that has not moved between the frames compared has no energy available above its
    lowest state: the relative change would divide rounding by rounding, so it is not given."""
    from types import SimpleNamespace  # noqa: PLC0415

    from softsim_warp.io.runinfo import energy_drift  # noqa: PLC0415

    still = [SimpleNamespace(total_energy=-12.5, gravity_energy=-12.5), SimpleNamespace(total_energy=-12.5 + 1e-15,
                                                                                      gravity_energy=-12.5)]
    drift, rel = energy_drift(still)
    assert 0 < drift < 1e-14 and math.isnan(rel)
    falling = [SimpleNamespace(total_energy=0.0, gravity_energy=0.0), SimpleNamespace(total_energy=-0.5,
                                                                                     gravity_energy=-2.0)]
    assert energy_drift(falling) == (-0.5, -0.25)
