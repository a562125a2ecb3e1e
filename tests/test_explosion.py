"""Explosions: detected every frame, exit 3 with frame, time, integrator, dt and the predicted stable dt,
and the USD and metrics of the good frames kept, valid, and marked as exploded."""

import json
import math
import re

import numpy as np
import pytest

from softsim_warp import build_model, load_scene, make_integrator
from softsim_warp.commands import cli
from softsim_warp.io.runinfo import predicted_stable_dt
from softsim_warp.io.simulate import Simulator

# Explicit Euler on the seed-like jelly at 4 ms: ten times the symplectic step, twice the largest
# step the linear analysis predicts stable for Euler (about 2 ms), so it must blow up (--allow-unstable:
# run past the check that refuses it before stepping, tests/test_stable_step.py).
EXPLODING = ["run", "jelly_drop", "--integrator", "euler", "--dt", "0.004", "--frames", "60", "--quiet",
             "--allow-unstable"]


def _usd_frames(path):
    from pxr import Usd  # noqa: PLC0415

    stage = Usd.Stage.Open(str(path))
    assert stage is not None
    attr = stage.GetPrimAtPath("/World/Jelly_0/Particles").GetAttribute("points")
    samples = attr.GetTimeSamples()
    return stage, {t: np.asarray(attr.Get(t)) for t in samples}


def test_exploding_run_exits_3_and_keeps_good_frames(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code = cli.main([*EXPLODING, "--out", "boom.usda", "--metrics", "boom.json"])
    err = capsys.readouterr().err
    assert code == 3
    line = err.strip().splitlines()[-1]
    m = re.match(
        r"error: jelly_drop\.toml: simulation exploded at frame (\d+) \(t = ([\d.e+-]+) s\) with integrator euler "
        r"at dt = 0\.004 s: .*; largest dt predicted stable for this jelly: ([\d.e+-]+) s; frames 0-(\d+) were kept$",
        line,
    )
    assert m, line
    frame, t, predicted, last_kept = int(m.group(1)), float(m.group(2)), float(m.group(3)), int(m.group(4))
    assert last_kept == frame - 1 and frame >= 1
    # The message's prediction is the linear analysis, and it says that 4 ms is unstable for Euler.
    scene = load_scene("jelly_drop", ["simulation.integrator=euler", "simulation.dt=0.004"])
    assert predicted == pytest.approx(predicted_stable_dt(scene, "euler"), rel=1e-2)
    assert predicted < 0.004
    # Frame k is the state after round(k / (fps dt)) steps.
    assert t == pytest.approx(round(frame / (60 * 0.004)) * 0.004)

    stage, frames = _usd_frames(tmp_path / "boom.usda")
    data = stage.GetRootLayer().customLayerData
    assert data["softsim:status"] == "exploded"
    assert data["softsim:frames"] == frame
    assert sorted(frames) == list(range(frame))
    assert all(np.isfinite(p).all() for p in frames.values())

    metrics = json.loads((tmp_path / "boom.json").read_text())
    s = metrics["summary"]
    assert s["exploded"] is True and s["status"] == "exploded"
    assert s["explosion"]["frame"] == frame and s["explosion"]["jelly"] == 0
    assert s["explosion"]["message"] in line
    assert [f["frame"] for f in metrics["frames"]] == list(range(frame))
    assert all(math.isfinite(f["total_energy"]) for f in metrics["frames"])
    assert not list(tmp_path.glob(".*partial*")), "temporary files left behind"


def test_stable_run_is_marked_complete(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = cli.main(["run", "jelly_drop", "--frames", "3", "--quiet", "--out", "ok.usda", "--metrics", "ok.json"])
    assert code == 0
    stage, frames = _usd_frames(tmp_path / "ok.usda")
    assert stage.GetRootLayer().customLayerData["softsim:status"] == "complete"
    assert sorted(frames) == [0, 1, 2, 3]
    summary = json.loads((tmp_path / "ok.json").read_text())["summary"]
    assert summary["status"] == "complete" and summary["exploded"] is False


def _run_sim(device, use_graph, integrator="euler", dt=0.004, frames=30):
    scene = load_scene("jelly_drop", [f"simulation.integrator={integrator}", f"simulation.dt={dt}"])
    model = build_model(scene, device=device)
    sim = Simulator(model, make_integrator(integrator, model), dt, 60.0, frames, use_graph=use_graph)
    return sim.run()


def test_explosion_detected_the_same_with_captured_frames(device):
    """Each frame's steps replayed as one captured graph (no host sync possible between steps) explode at
    the same frame as steps launched one by one: the check needs nothing per step."""
    plain = _run_sim(device, use_graph=False)
    graph = _run_sim(device, use_graph=True)
    assert plain.exploded and graph.exploded
    assert plain.explosion["frame"] == graph.explosion["frame"]
    assert plain.frames_written == graph.frames_written == plain.explosion["frame"]


def test_nonfinite_state_is_an_explosion(device):
    scene = load_scene("jelly_drop")
    model = build_model(scene, device=device)
    qd = model.particle_qd.numpy()
    qd[7] = np.nan  # one poisoned particle: the run must not write a single frame of it
    model.particle_qd.assign(qd)  # the model's initial velocities (a frozen model's array, not its field)
    sim = Simulator(model, make_integrator("symplectic", model), 4e-4, 60.0, 5)
    result = sim.run()
    assert result.exploded and result.explosion["frame"] == 0
    assert result.frames_written == 0
    assert "non-finite" in result.explosion["reason"]


def test_speed_bound_is_an_explosion(device):
    """A run whose speed passes max_speed stops at the first frame past it; the frames before stay."""
    scene = load_scene("jelly_drop")
    model = build_model(scene, device=device)
    # Free fall from rest: |v| = g t, so a bound of 1 m/s is passed at t = 1/9.8 s, frame ceil(60/9.8) = 7.
    sim = Simulator(model, make_integrator("symplectic", model), 4e-4, 60.0, 30, max_speed=1.0)
    result = sim.run()
    assert result.exploded
    first_over = next(k for k in range(31) if 9.8 * round(k / (60 * 4e-4)) * 4e-4 > 1.0)
    assert result.explosion["frame"] == first_over
    assert "exceeds the bound 1 m/s" in result.explosion["reason"]


def test_end_of_run_line_says_how_the_run_ended(tmp_path, monkeypatch, capsys):
    """The summary of an exploded run says so, with the steps really done (not 0); a damped run says
    its energy was dissipated, an undamped explicit Euler run that it gained energy."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(["run", "hard_undamped", "--integrator", "euler", "--frames", "6", "--quiet", "--out", "u.usdc",
                     "--allow-unstable"]) == 3
    line = capsys.readouterr().err.splitlines()[0]
    assert line.startswith("EXPLODED: hard_undamped: 6 frames, 100 steps of euler") and "energy GAINED" in line
    assert cli.main(["run", "jelly_drop", "--frames", "30", "--quiet", "--out", "d.usdc",
                     "--set", "jelly.0.resolution=[3,3,3]"]) == 0
    line = capsys.readouterr().err.splitlines()[0]
    assert line.startswith("jelly_drop: 31 frames, 1250 steps") and "dissipated by damping, friction and contact" in line
