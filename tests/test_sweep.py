"""``softsim sweep``: variants batched as worlds on Dask workers, one row each.

The sweep's promise is that a row is what a single ``softsim run`` of its variant reports, bit for
bit on the CPU (a world of a batch shares launches with the others but no particles, springs or
terrain, and is judged with its own explosion bound), and that no finished row is ever lost: not to
Ctrl-C, not to a killed worker. These tests run a 2-worker ``LocalCluster`` on a 4^3 seed_bowl.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.commands import cli  # noqa: E402
from softsim_warp.core.errors import CommandLineError  # noqa: E402
from softsim_warp.io import sweep as engine  # noqa: E402
from softsim_warp.io.sweep import latin_hypercube, parse_axis, penetration, read_results  # noqa: E402

# 4^3 particles at 20 frames per second: the jelly reaches the hole's rim at t = 1.34 s.
SMALL = ["--set", "jelly.0.resolution=4", "--set", "simulation.fps=20"]
KS = "jelly.0.springs.*.ks"


def _sweep(tmp_path, *argv, name="r.parquet"):
    out = tmp_path / name
    rc = cli.main(["sweep", "seed_bowl", *SMALL, *argv, "--out", str(out), "--quiet"])
    return rc, out


def _env(test_dir=None, delay=0.0):
    env = dict(os.environ)
    env.pop("SOFTSIM_TEST_PAUSE", None)
    if test_dir is not None:
        env["SOFTSIM_SWEEP_TEST_DIR"] = str(test_dir)
        env["SOFTSIM_SWEEP_TEST_DELAY"] = str(delay)
    return env


def _wait_for(predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("timed out")


# ---------------------------------------------------------------------------------------------
# Rows equal single runs, bit for bit


def test_rows_equal_single_runs_bitwise(tmp_path):
    # ks = 1e6 makes rk4 explode at dt = 1e-3 (omega dt > 2.8) and symplectic explode too; 2000 runs
    # through contact with the rim. Two worlds per task, so every row comes out of a batch.
    plot = tmp_path / "study.png"
    rc, out = _sweep(tmp_path, "--duration", "1.5", "--vary", f"{KS}=2000,1000000", "--integrators",
                     "symplectic,rk4", "--workers", "2", "--batch", "2", "--plot", str(plot), "--allow-unstable")
    assert rc == 0
    assert plot.stat().st_size > 10_000
    rows = read_results(out)
    assert [r["index"] for r in rows] == [0, 1, 2, 3]
    assert {r["batch_size"] for r in rows} == {2}
    assert [r["status"] for r in rows] == ["completed", "completed", "exploded", "exploded"]
    for r in rows:
        ks = r[KS]
        metrics = tmp_path / f"{r['integrator']}_{ks}.json"
        code = cli.main(["run", "seed_bowl", *SMALL, "--duration", "1.5", "--integrator", r["integrator"],
                         "--set", f"jelly.0.springs.structural.ks={ks}", "--set", f"jelly.0.springs.shear.ks={ks}",
                         "--set", f"jelly.0.springs.bending.ks={ks}",
                         "--out", str(tmp_path / f"{r['integrator']}_{ks}.usda"), "--metrics", str(metrics), "--quiet",
                         "--allow-unstable"])
        data = json.loads(metrics.read_text())
        s, frames = data["summary"], data["frames"]
        assert code == (3 if s["exploded"] else 0)
        # Bit for bit: the same steps, frames, energies, centre of mass and peak speed.
        assert r["steps"] == s["steps"] and r["frames"] == s["frames"] == len(frames)
        assert r["energy_change"] == s["energy_drift"]
        assert r["energy_change_relative"] == s["energy_drift_relative"]
        assert r["energy_start"] == frames[0]["total_energy"]
        assert r["energy_end"] == frames[-1]["total_energy"]
        assert [r["com_x"], r["com_y"], r["com_z"]] == frames[-1]["com"]
        assert r["max_speed"] == max(f["max_speed"] for f in frames)
        if s["exploded"]:
            assert r["explosion_frame"] == s["explosion"]["frame"]
            assert r["explosion_time"] == s["explosion"]["time"]
            assert r["explosion_reason"] == s["explosion"]["reason"]
        else:
            assert r["explosion_frame"] is None
            assert min(f["com"][1] for f in frames) < 4.0  # it fell onto the plane: contact was part of it
        assert r["particles"] == 64 and r["device"] == "cpu" and r["error"] is None


def test_reference_error_is_zero_for_the_reference_itself(tmp_path):
    # The float64 RK4 run of a float64 RK4 variant is the variant itself: its error is exactly 0; a
    # float32 symplectic variant differs from it by more than float32 rounding and less than the
    # jelly's size.
    rc, out = _sweep(tmp_path, "--duration", "0.5", "--integrators", "symplectic,rk4", "--vary",
                     "simulation.precision=float32,float64", "--reference", "--workers", "2")
    assert rc == 0
    rows = {(r["integrator"], r["simulation.precision"]): r for r in read_results(out)}
    assert rows[("rk4", "float64")]["ref_position_error"] == 0.0
    assert rows[("rk4", "float64")]["ref_com_error"] == 0.0
    sym = rows[("symplectic", "float32")]
    assert 1e-6 < sym["ref_position_error"] < 0.1 and sym["ref_status"] == "completed"


def test_a_failing_variant_fails_alone(monkeypatch):
    # A batch that raises is rerun variant by variant: the bad variant's row says failed with the
    # error, the others are the rows a batch without it gives.
    from softsim_warp.io import scene as scene_mod

    _, source, base = scene_mod.read_scene_data("seed_bowl")
    scene_mod.apply_overrides(base, [("jelly.0.resolution", 4), ("simulation.duration", 0.1)])
    variants = engine.plan_sweep(base, source, [parse_axis(f"{KS}=1000,2000,3000")])
    bad = variants[1].id
    simulate = engine._simulate

    def failing(batch, device, use_graph=True):
        if any(v["id"] == bad for v in batch):
            raise RuntimeError("boom")
        return simulate(batch, device, use_graph)

    monkeypatch.setattr(engine, "_simulate", failing)
    rows = engine.run_batch(engine.task_spec(variants, "cpu", 0))
    assert [r["status"] for r in rows] == ["completed", "failed", "completed"]
    assert rows[1]["error"] == "RuntimeError: boom" and rows[1]["variant_id"] == bad
    monkeypatch.setattr(engine, "_simulate", simulate)
    alone = engine.run_batch(engine.task_spec([variants[0], variants[2]], "cpu", 1))
    for a, b in zip(alone, [rows[0], rows[2]]):
        for key in ("steps", "energy_change", "com_x", "com_y", "com_z", "max_speed"):
            assert a[key] == b[key]


# ---------------------------------------------------------------------------------------------
# No finished row lost


def _interrupt_after_two_parts(command, marks, parts) -> str:
    """Run a sweep ``command`` (tasks slowed down), send SIGINT once two tasks' rows are written to
    ``parts``; asserts exit 130 and returns stderr."""
    proc = subprocess.Popen(command, env=_env(marks, delay=0.7), stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: len(list(parts.glob("part-*.parquet"))) >= 2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    return err


def _cli(*argv):
    return [sys.executable, "-m", "softsim_warp", "sweep", "seed_bowl", *SMALL, *argv, "--quiet"]


def test_killed_worker_sweep_completes_with_every_row(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "kill.csv"
    proc = subprocess.Popen(_cli("--duration", "0.3", "--vary", f"{KS}=1000,2000,3000,4000", "--workers", "2",
                                 "--batch", "1", "--out", str(out)),
                            env=_env(marks, delay=1.5), stderr=subprocess.PIPE, text=True)
    try:
        # A worker holding a task (started, not finished): kill its process outright.
        running = _wait_for(lambda: sorted(marks.glob("*.running")))
        task, pid = running[0].name.split(".")[:2]
        os.kill(int(pid), signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == [0, 1, 2, 3]
    assert all(r["status"] == "completed" for r in rows)
    # The killed task ran again on a worker process other than the killed one.
    assert not (marks / f"{task}.{pid}.done").exists()
    assert any(p.name.startswith(task + ".") for p in marks.glob("*.done"))
    assert all(not r["worker"].endswith(f":{pid}") for r in rows)
    assert not (tmp_path / ".kill.csv.parts").exists()


def test_interrupt_then_resume_recomputes_nothing_and_misses_nothing(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "res.parquet"
    argv = ("--duration", "0.3", "--vary", f"{KS}=1000,2000,3000,4000,5000,6000", "--workers", "1", "--batch", "1",
            "--out", str(out))
    parts = tmp_path / ".res.parquet.parts"
    err = _interrupt_after_two_parts(_cli(*argv), marks, parts)  # two tasks' rows written
    assert "--resume" in err
    first = {r["variant_id"]: r for r in read_results(out)}
    assert 2 <= len(first) < 6

    # Without --resume the unfinished sweep's parts are not thrown away.
    if parts.exists():
        with pytest.raises(CommandLineError, match="--resume"):
            engine.RowStore(out, pq.read_schema(out), resume=False)

    marks2 = tmp_path / "marks2"
    marks2.mkdir()
    done = subprocess.run(_cli(*argv, "--resume"), env=_env(marks2), stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == list(range(6))
    again = {r["variant_id"]: r for r in rows}
    for ident, row in first.items():
        assert again[ident] == row  # same worker, same wall time: kept, not recomputed
    assert len(list(marks2.glob("*.done"))) == 6 - len(first)
    assert not parts.exists()

    # Resuming a complete sweep runs nothing.
    rc, _ = _sweep(tmp_path, *argv[:-2], "--resume", name="res.parquet")
    assert rc == 0 and read_results(out) == rows


def test_lost_scheduler_keeps_finished_rows_and_resume_finishes(tmp_path):
    # An existing cluster (--scheduler): its scheduler is killed mid-sweep; the rows of the tasks
    # that finished stay, the command says to resume, and --resume on a new cluster runs the rest.
    marks = tmp_path / "marks"
    marks.mkdir()
    dask = Path(sys.executable).with_name("dask")
    info = tmp_path / "scheduler.json"
    env = _env(marks, delay=1.0)
    procs = [subprocess.Popen([str(dask), "scheduler", "--port", "0", "--dashboard-address", ":0",
                               "--scheduler-file", str(info)], env=env, stderr=subprocess.DEVNULL)]
    try:
        _wait_for(lambda: info.exists() and info.read_text().strip().endswith("}"))
        procs.append(subprocess.Popen([str(dask), "worker", "--scheduler-file", str(info), "--nthreads", "1",
                                       "--no-nanny"], env=env, stderr=subprocess.DEVNULL))
        address = json.loads(info.read_text())["address"]
        out = tmp_path / "lost.parquet"
        argv = ("--duration", "0.3", "--vary", f"{KS}=1000:6000:6", "--batch", "1", "--out", str(out))
        sweep = subprocess.Popen(_cli(*argv, "--scheduler", address), env=env, stderr=subprocess.PIPE, text=True)
        parts = tmp_path / ".lost.parquet.parts"
        _wait_for(lambda: len(list(parts.glob("part-*.parquet"))) >= 2, timeout=90)  # two tasks' rows written
        procs[0].kill()
        _, err = sweep.communicate(timeout=90)
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert sweep.returncode == 1 and "the scheduler was lost" in err and "--resume" in err, err
    kept = {r["variant_id"]: r for r in read_results(out)}
    assert 2 <= len(kept) < 6
    done = subprocess.run(_cli(*argv, "--workers", "2", "--resume"), env=_env(), stderr=subprocess.PIPE, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == list(range(6))
    assert all(r == kept[r["variant_id"]] for r in rows if r["variant_id"] in kept)


# ---------------------------------------------------------------------------------------------
# --find-stable-dt


def test_find_stable_dt_agrees_with_stability(tmp_path):
    rc, out = _sweep(tmp_path, "--duration", "0.1", "--integrators", "symplectic,rk4", "--find-stable-dt",
                     "--workers", "2")
    assert rc == 0
    rows = {r["integrator"]: r for r in read_results(out)}
    report = tmp_path / "stability.json"
    assert cli.main(["stability", "seed_bowl", *SMALL, "--duration", "0.1", "--integrators", "symplectic,rk4",
                     "--ks", "none", "--out", str(report), "--quiet"]) == 0
    limits = json.loads(report.read_text())["limits"]
    for method in ("symplectic", "rk4"):
        lim = next(x for x in limits if x["integrator"] == method and x["damping"] == "scene")
        r = rows[method]
        assert r["status"] == "completed"
        assert r["stable_dt"] == lim["scene"]["dt"] and r["unstable_dt"] == lim["scene"]["unstable_dt"]
        assert r["stable_dt_jelly"] == lim["jelly"]["dt"]
        assert r["predicted_dt"] == lim["predicted"]
        # The bisection's bracket is tight and the step found is stable below the unstable one.
        assert r["stable_dt"] < r["unstable_dt"] <= r["stable_dt"] * 1.02 + 1e-15


# ---------------------------------------------------------------------------------------------
# Input


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--vary", "ks"], "--vary: expected KEY=V1,V2,... or KEY=LO:HI:N[:log]"),
        (["--vary", f"{KS}=1:2:x"], "the range's count N in LO:HI:N must be an integer >= 1"),
        (["--vary", f"{KS}=0:10:3:log"], "a log range needs LO > 0 and HI > 0"),
        (["--vary", f"{KS}=1:2:3:cubic"], "the range's scale must be lin or log"),
        (["--vary", f"{KS}=1,,2"], "empty value in the list"),
        (["--vary", f"{KS}=1,1"], "repeats a value"),
        (["--vary", "jelly.0.springs.structural.ks=-1,2"], "must be a finite number >= 0"),
        (["--vary", "jelly.0.springs.structural.kz=1,2"], "unknown key; allowed: ks, kd"),
        (["--vary", "jelly.3.springs.structural.ks=1,2"], "index out of range"),
        (["--vary", "jelly.0.nothing.*.ks=1,2"], "no table of the scene matches"),
        (["--vary", f"{KS}=1,2", "--vary", f"{KS}=3"], "given twice"),
        (["--dts", "0.001,0.5"], "must not exceed the frame interval"),
        (["--dts", "0:1:3:log"], "--dts: simulation.dt: a log range needs LO > 0"),
        (["--integrators", "euler,bogus"], "--integrators: unknown integrator"),
        (["--samples", "0", "--vary", f"{KS}=1:2:2"], "--samples: must be an integer from 1"),
        (["--samples", "4"], "give at least one --vary"),
        (["--find-stable-dt", "--dts", "0.001"], "--find-stable-dt finds the step itself"),
        (["--out", "x.json"], "unsupported file extension"),
        (["--metric", "colour"], "--metric: not a numeric column of this sweep; choose from"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, argv, needle):
    argv = [a.replace("x.json", str(tmp_path / "x.json")) for a in argv]
    out = [] if "--out" in argv else ["--out", str(tmp_path / "x.parquet")]
    rc = cli.main(["sweep", "seed_bowl", *argv, *out, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("error: ") and needle in err[0], err
    assert not (tmp_path / "x.parquet").exists()


def test_resume_refuses_another_sweeps_rows(tmp_path, capsys):
    rc, _ = _sweep(tmp_path, "--duration", "0.1", "--vary", f"{KS}=1000", "--workers", "1")
    assert rc == 0
    rc, _ = _sweep(tmp_path, "--duration", "0.1", "--vary", f"{KS}=2000", "--workers", "1", "--resume")
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and "not variants of this sweep" in err[-1]


# ---------------------------------------------------------------------------------------------
# Pieces


def test_ranges_lists_and_wildcards():
    a = parse_axis("x=1:5:5")
    assert a.values == [1, 2, 3, 4, 5] and all(isinstance(v, int) for v in a.values)
    a = parse_axis("x=0.1:0.2:3")
    assert a.values == [0.1, pytest.approx(0.15), 0.2]
    a = parse_axis("x=1e2:1e6:5:log")
    assert a.values[0] == 100.0 and a.values[-1] == 1e6
    np.testing.assert_allclose(np.diff(np.log10(a.values)), 1.0)
    assert parse_axis("x=1,2.5,[1,0,1]").values == [1, 2.5, [1, 0, 1]]
    assert parse_axis("x=1,2.5").values == [1.0, 2.5]  # one column type
    base = {"jelly": [{"springs": {"structural": {"ks": 1}, "bending": {"ks": 2}}}, {"springs": {"shear": {}}}]}
    # Only the tables whose file sets the key; when none does, every table matched.
    assert engine.expand_key(base, "jelly.*.springs.*.ks") == ["jelly.0.springs.structural.ks",
                                                               "jelly.0.springs.bending.ks"]
    assert engine.expand_key(base, "jelly.*.springs.*.kd") == [
        "jelly.0.springs.structural.kd", "jelly.0.springs.bending.kd", "jelly.1.springs.shear.kd"]


def test_latin_hypercube_uses_each_stratum_once():
    axes = [parse_axis("a=0.0:1.0:2"), parse_axis("b=1:100:2:log"), parse_axis("c=x,y,z,w")]
    n = 8
    pts = latin_hypercube(axes, n, seed=3)
    assert len(pts) == n
    a = np.array([p[0] for p in pts])
    b = np.log10([p[1] for p in pts]) / 2.0  # log range mapped to [0, 1]
    for col in (a, b):
        assert sorted(np.floor(col * n).astype(int)) == list(range(n))
    assert sorted(p[2] for p in pts) == sorted(["x", "y", "z", "w"] * 2)
    assert latin_hypercube(axes, n, seed=3) == pts


def test_penetration_closed_forms():
    plane = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]}
    q = np.array([[0.0, 1.0, 0.0], [0.0, -0.25, 0.0], [2.0, -0.1, 0.0]])
    assert penetration({"plane": [plane]}, q, [(0, 3)]) == 0.25
    holed = dict(plane, hole={"center": [2.0, 0.0, 0.0], "radius": 0.5})
    assert penetration({"plane": [holed]}, q, [(0, 3)]) == 0.25  # the particle over the hole is not inside
    sphere = {"center": [0.0, 0.0, 0.0], "radius": 1.0}
    assert penetration({"sphere": [sphere]}, np.array([[0.0, 0.4, 0.0], [3.0, 0, 0]]), [(0, 2)]) == pytest.approx(0.6)
    # A bowl is a shell: a jelly wholly behind it is not inside; one it cuts is, by its shallower side.
    bowl = {"center": [0.0, 0.0, 0.0], "radius": 1.0, "cut_height": 0.5}
    behind = np.array([[0.0, -1.5, 0.0], [0.0, -1.2, 0.0]])
    assert penetration({"bowl": [bowl]}, behind, [(0, 2)]) == 0.0
    cut = np.array([[0.0, -0.9, 0.0], [0.0, -1.05, 0.0]])
    assert penetration({"bowl": [bowl]}, cut, [(0, 2)]) == pytest.approx(0.05)


def test_batch_penetration_is_each_worlds_penetration():
    # All worlds at once (one distance evaluation when the surfaces agree) = world by world.
    rng = np.random.default_rng(5)
    plane = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0], "hole": {"center": [0.5, 0, 0], "radius": 0.3},
             "friction": 0.2}
    bowl = {"center": [0.0, 0.0, 0.0], "radius": 1.0, "cut_height": 0.5, "friction": 0.1}
    sphere = {"center": [0.0, -0.5, 0.0], "radius": 0.4}
    datas, ranges, jellies, start = [], [], [], 0
    for w in range(5):
        moved = dict(sphere, center=[0.1 * w, -0.5, 0.0])  # differs per world: evaluated world by world
        datas.append({"plane": [dict(plane, friction=0.1 * w)], "bowl": [bowl], "sphere": [moved]})
        n = 20 + 3 * w
        ranges.append((start, start + n))
        jellies.append([(0, 8), (8, n)])
        start += n
    q = rng.uniform(-1.2, 1.2, (start, 3)).astype(np.float32)
    got = engine.batch_penetration(datas, q, ranges, jellies)
    for w, (a, b) in enumerate(ranges):
        assert got[w] == penetration(datas[w], q[a:b].astype(np.float64), jellies[w])
    assert (got > 0).all()


def test_batches_group_what_can_share_a_launch():
    from softsim_warp.io import scene as scene_mod

    _, source, base = scene_mod.read_scene_data("seed_bowl")
    axes = [parse_axis("jelly.0.resolution=3,4"), parse_axis("jelly.0.springs.*.ks=1000,2000,3000")]
    variants = engine.plan_sweep(base, source, axes, ["euler", "implicit"])
    assert len(variants) == 12 and len({v.id for v in variants}) == 12
    batches = engine.make_batches(variants, workers=1, is_cuda=True)
    for b in batches:
        assert len({engine.group_key(v) for v in b}) == 1
    explicit = [b for b in batches if b[0].integrator == "euler"]
    assert sorted(len(b) for b in explicit) == [3, 3]  # one per lattice shape
    assert all(len(b) == 1 for b in batches if b[0].integrator == "implicit")
    # A memory budget bounds the batch.
    per = engine.variant_bytes(variants[0], True)
    small = engine.make_batches(variants, workers=1, is_cuda=True, budget=int(4 * per / engine.MEMORY_SHARE) + 1)
    assert max(len(b) for b in small) <= 4 and sum(map(len, small)) == 12


def test_no_terrain_no_reference_reads_no_positions(monkeypatch):
    """A sweep with nothing to measure penetration into, and no reference, never copies positions to
    the host (issue 46, point 6); its rows are those of the sweep that does, penetration 0 in both."""
    from softsim_warp.io import scene as scene_mod

    _, source, base = scene_mod.read_scene_data("free_flight")
    base["simulation"]["duration"] = 0.1
    specs = [{"id": v.id, "data": v.data, "reference": v.reference}
             for v in engine.plan_sweep(base, source, [parse_axis(f"{KS}=500,900")])]
    asked = []
    read_frame = engine._Batch.read_frame

    def spy(self, k, positions=True):
        asked.append(positions)
        return read_frame(self, k, positions)

    monkeypatch.setattr(engine._Batch, "read_frame", spy)
    lean = engine._simulate(specs, "cpu")
    assert asked and not any(asked)
    # The same worlds with a plane far below: positions read, penetration measured (0 too).
    for s in specs:
        s["data"]["plane"] = [{"point": [0.0, -1e3, 0.0], "normal": [0.0, 1.0, 0.0], "restitution": 0.5,
                               "friction": 0.3, "size": 1.0}]
    asked.clear()
    full = engine._simulate(specs, "cpu")
    assert asked and all(asked)
    for a, b in zip(lean, full):
        assert a["max_penetration"] == b["max_penetration"] == 0.0
        assert {k: v for k, v in a.items() if "second" not in k} == {k: v for k, v in b.items() if "second" not in k}
