"""A batch of a sweep on a device (softsim_warp/io/sweep/batch.py): rows equal single runs, metrics
reduced on the device.

The sweep's promise is that a row is what a single ``softsim run`` of its variant reports, bit for
bit on the CPU (a world of a batch shares launches with the others but no particles, springs or
terrain, and is judged with its own explosion bound). What a run does not report, the penetration
into terrain and the error against the reference run, is checked against float64 NumPy over the same
particles and against closed forms. The host reads a few numbers per world a frame, never the
particles, and launches nothing for what a sweep does not ask.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import warp as wp

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.commands import cli  # noqa: E402
from softsim_warp.io import scene as scene_mod  # noqa: E402
from softsim_warp.io import sweep as engine  # noqa: E402
from softsim_warp.io.checks import SHELLS, TERRAIN_SDF  # noqa: E402
from softsim_warp.io.sweep import batch as batch_mod  # noqa: E402
from softsim_warp.io.sweep import parse_axis, read_results  # noqa: E402
from tests.sweep_helpers import KS, SMALL, sweep  # noqa: E402

# ---------------------------------------------------------------------------------------------
# Rows equal single runs, bit for bit


def test_rows_equal_single_runs_bitwise(tmp_path):
    # ks = 1e6 makes rk4 explode at dt = 1e-3 (omega dt > 2.8) and symplectic explode too; 2000 runs
    # through contact with the rim. Two worlds per task, so every row comes out of a batch.
    plot = tmp_path / "study.png"
    rc, out = sweep(tmp_path, "--duration", "1.5", "--vary", f"{KS}=2000,1000000", "--integrators",
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
    rc, out = sweep(tmp_path, "--duration", "0.5", "--integrators", "symplectic,rk4", "--vary",
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
    simulate = batch_mod._simulate

    def failing(batch, device, use_graph=True, **kw):
        if any(v["id"] == bad for v in batch):
            raise RuntimeError("boom")
        return simulate(batch, device, use_graph, **kw)

    monkeypatch.setattr(batch_mod, "_simulate", failing)
    rows = engine.run_batch(engine.task_spec(variants, "cpu", 0))
    assert [r["status"] for r in rows] == ["completed", "failed", "completed"]
    assert rows[1]["error"] == "RuntimeError: boom" and rows[1]["variant_id"] == bad
    monkeypatch.setattr(batch_mod, "_simulate", simulate)
    alone = engine.run_batch(engine.task_spec([variants[0], variants[2]], "cpu", 1))
    for a, b in zip(alone, [rows[0], rows[2]]):
        for key in ("steps", "energy_change", "com_x", "com_y", "com_z", "max_speed"):
            assert a[key] == b[key]




# ---------------------------------------------------------------------------------------------
# Penetration and the reference error, reduced on the device


def penetration(data: dict, q: np.ndarray, jelly_ranges) -> float:
    """Float64 NumPy reference: the largest depth [m] of a particle of one world inside its terrain
    (``checks.TERRAIN_SDF``'s distances); a shell counts for a jelly it cuts, by the shallower side."""
    worst = 0.0
    for kind, sdf in TERRAIN_SDF.items():
        for entry in data.get(kind, []):
            if kind in SHELLS:
                for a, b in jelly_ranges:
                    phi = sdf(entry, q[a:b])
                    phi = phi[np.isfinite(phi)]
                    if phi.size and phi.min() < 0 < phi.max():
                        worst = max(worst, float(min(-phi.min(), phi.max())))
            else:
                phi = sdf(entry, q)
                phi = phi[np.isfinite(phi)]
                if phi.size and phi.min() < 0:
                    worst = max(worst, float(-phi.min()))
    return worst


def _worlds(terrains, precision="float64", jellies=1):
    """A batch of seed_bowl 4^3 worlds (``jellies`` jellies each), world w with terrain ``terrains[w]``."""
    _, source, base = scene_mod.read_scene_data("seed_bowl")
    base["jelly"][0]["resolution"] = [4, 4, 4]
    base["simulation"]["precision"] = precision
    base["simulation"]["duration"] = 0.05
    for k in range(1, jellies):
        base["jelly"].append(dict(base["jelly"][0], center=[20.0 * k, 30.0, 0.0]))
    datas = []
    for terrain in terrains:
        data = {k: v for k, v in base.items() if k not in ("plane", "bowl", "sphere")}
        data.update(terrain)
        datas.append(scene_mod.validate(data, source))
    return datas


def _depths(batch, q):
    batch.sim.state.particle_q.assign(q)
    batch.penetration.launch(batch.sim.state)
    return batch.penetration.read()


def test_penetration_closed_forms():
    plane = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]}
    holed = dict(plane, hole={"center": [2.0, 0.0, 1.0], "radius": 0.5})
    sphere = {"center": [0.0, 0.0, 0.0], "radius": 1.0}
    bowl = {"center": [0.0, 0.0, 0.0], "radius": 1.0, "cut_height": 0.5}
    datas = _worlds([{"plane": [plane]}, {"plane": [holed]}, {"sphere": [sphere]}, {"bowl": [bowl]},
                     {"bowl": [bowl]}])
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    q = np.tile([0.0, 5.0, 0.0], (5 * 64, 1))  # far from everything but the bowl's inside
    q[5, 1] = -0.25  # world 0: 0.25 below the plane
    q[64 + 3] = [2.0, -0.75, 1.0]  # world 1: over the hole, not inside
    q[64 + 4, 1] = -0.5  # world 1: 0.5 below the plane
    q[128 + 7] = [0.0, 0.4, 0.0]  # world 2: 0.6 inside the sphere
    # World 3: wholly behind the bowl (outside its sphere): not inside. World 4: cut by it, 0.9 from
    # the centre inside and 1.05 outside: in by the shallower side, 0.05.
    q[192:256] = [0.0, -1.5, 0.0]
    q[256:320] = [0.0, -1.05, 0.0]
    q[256:288] = [0.0, -0.9, 0.0]
    got = _depths(batch, q)
    np.testing.assert_allclose(got, [0.25, 0.5, 0.6, 0.0, 0.05], rtol=1e-14, atol=0)


@pytest.mark.parametrize("precision, tol", [("float64", 1e-13), ("float32", 2e-6)])
def test_penetration_of_each_world_is_the_float64_distances(precision, tol):
    # Random particles around a plane with a hole, a bowl, spheres that differ from world to world,
    # and all of them, two jellies a world: every world's depth is what float64 NumPy finds over its particles,
    # to the precision's rounding of coordinates of about 1 m.
    rng = np.random.default_rng(5)
    plane = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0], "hole": {"center": [0.5, 0.0, 0.0], "radius": 0.3}}
    bowl = {"center": [0.0, 0.0, 0.0], "radius": 1.0, "cut_height": 0.5}
    spheres = [{"sphere": [{"center": [0.1 * w, -0.5, 0.0], "radius": 0.6}]} for w in range(2)]
    terrains = [{"plane": [plane]}, {"bowl": [bowl]}, *spheres, {"plane": [plane], "bowl": [bowl], **spheres[0]}]
    datas = _worlds(terrains, precision, jellies=2)
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    n = batch.model.particle_count
    q = rng.uniform(-1.2, 1.2, (n, 3))
    got = _depths(batch, q.astype(np.float32 if precision == "float32" else np.float64))
    if precision == "float32":
        q = q.astype(np.float32).astype(np.float64)
    want = [penetration(datas[w], q[a:b], [(0, 64), (64, 128)]) for w, (a, b) in enumerate(batch.ranges)]
    assert (np.asarray(want) > 0).all()
    np.testing.assert_allclose(got, want, rtol=0, atol=tol)


def test_position_error_is_the_float64_rms():
    from softsim_warp.io.metrics import PositionErrorProbe

    datas = _worlds([{}, {}, {}], "float32")
    refs = _worlds([{}, {}, {}], "float64")
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    ref = batch_mod._Batch(refs, "cpu", use_graph=False)
    probe = PositionErrorProbe(batch.model, batch.ranges)
    rng = np.random.default_rng(1)
    q_ref = rng.normal(size=(192, 3))
    q = (q_ref + rng.normal(scale=1e-3, size=q_ref.shape)).astype(np.float32)
    q[128:] = q_ref[128:]  # world 2: the reference rounded to float32
    batch.sim.state.particle_q.assign(q)
    ref.sim.state.particle_q.assign(q_ref)
    probe.launch(batch.sim.state.particle_q, ref.sim.state.particle_q)
    got = probe.read()
    d = q.astype(np.float64) - q_ref
    want = [np.sqrt(np.mean(np.sum(d[a:b] ** 2, axis=1))) for a, b in batch.ranges]
    np.testing.assert_allclose(got, want, rtol=1e-14)
    assert 0 < got[2] < 1e-6 < got[0]
    ref.sim.state.particle_q.assign(q.astype(np.float64))
    probe.launch(batch.sim.state.particle_q, ref.sim.state.particle_q)
    assert (probe.read() == 0.0).all()  # the same positions: exactly 0


def _spy(monkeypatch):
    """Record each launched kernel's key and each device array copied to the host's length."""
    launched, copied = [], []
    launch, numpy = wp.launch, wp.array.numpy

    def spy_launch(kernel, *args, **kwargs):
        launched.append(kernel.key.rsplit("__", 1)[-1])
        return launch(kernel, *args, **kwargs)

    def spy_numpy(self):
        copied.append(self.shape[0] if self.ndim else 1)
        return numpy(self)

    monkeypatch.setattr(wp, "launch", spy_launch)
    monkeypatch.setattr(wp.array, "numpy", spy_numpy)
    return launched, copied


def _specs(base, source, mode="run"):
    return [{"id": v.id, "data": v.data, "reference": v.reference}
            for v in engine.plan_sweep(base, source, [parse_axis(f"{KS}=500,900")], mode=mode)]


@pytest.mark.parametrize("mode", ["run", "reference"])
def test_the_host_reads_no_particles(monkeypatch, mode):
    """However many frames a batch runs, it copies no more particle arrays to the host (those of its
    set-up only): each frame it reads a few numbers per jelly and per world."""
    _, source, base = scene_mod.read_scene_data("seed_bowl")
    base["jelly"][0]["resolution"] = [4, 4, 4]
    base["simulation"]["fps"] = 20
    copies = []
    for duration in (0.1, 0.6):
        base["simulation"]["duration"] = duration
        specs = _specs(base, source, mode)
        launched, copied = _spy(monkeypatch)
        rows = batch_mod._simulate(specs, "cpu")
        monkeypatch.undo()
        assert rows[0]["frames"] == round(duration * 20) + 1
        assert "measure_penetration" in launched  # seed_bowl has terrain
        assert ("measure_position_error" in launched) == (mode == "reference")
        copies.append(sum(1 for n in copied if n >= 64))  # particle arrays (64 particles a world)
    assert copies[0] == copies[1]


def test_no_terrain_no_reference_launches_nothing_for_them(monkeypatch):
    """A sweep with nothing to measure penetration into, and no reference, launches nothing for them
    (its rows are those of the sweep that does, penetration 0 in both)."""
    _, source, base = scene_mod.read_scene_data("free_flight")
    base["simulation"]["duration"] = 0.1
    specs = _specs(base, source)
    launched, _ = _spy(monkeypatch)
    lean = batch_mod._simulate(specs, "cpu")
    assert launched and not {"measure_penetration", "combine_shell_depths", "measure_position_error"} & set(launched)
    # The same worlds with a plane far below: penetration measured (0 too).
    for s in specs:
        s["data"]["plane"] = [{"point": [0.0, -1e3, 0.0], "normal": [0.0, 1.0, 0.0], "restitution": 0.5,
                               "friction": 0.3, "size": 1.0}]
    launched.clear()
    full = batch_mod._simulate(specs, "cpu")
    assert "measure_penetration" in launched
    for a, b in zip(lean, full):
        assert a["max_penetration"] == b["max_penetration"] == 0.0
        assert {k: v for k, v in a.items() if "second" not in k} == {k: v for k, v in b.items() if "second" not in k}


def test_penetration_into_meshes(tmp_path):
    # A closed unit box (tests/test_mesh_jelly.py's) is solid however deep: a particle inside is in by
    # its distance to the nearest face, as the float64 NumPy distance says. An open square sheet
    # facing up at y = 0 (tests/test_mesh_terrain.py's) is solid only within its thickness behind
    # it: 0.25 under it is inside, 1.5 under it or beside it below its plane is not.
    from tests.test_mesh_jelly import box_mesh, write_usd
    from tests.test_mesh_terrain import quad, write_mesh

    box = write_usd(tmp_path / "box.usda", *box_mesh([1.0, 1.0, 1.0]))
    sheet = write_mesh(tmp_path / "ground.usda", *quad([0, 1, 0]))
    sheet_entry = {"path": sheet, "thickness": 0.5}
    datas = _worlds([{"mesh": [{"path": box}]}, {"mesh": [sheet_entry]}, {"mesh": [sheet_entry]},
                     {"mesh": [sheet_entry]}])
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    q = np.tile([0.0, 5.0, 0.0], (4 * 64, 1))
    q[3] = [0.1, -0.2, 0.15]  # 0.3 inside the box (from the bottom face)
    q[64 + 3] = [1.0, -0.25, 0.5]
    q[128 + 9] = [-2.0, -1.5, 3.0]
    q[192 + 1] = [9.0, -1.0, 0.0]
    got = _depths(batch, q)
    np.testing.assert_allclose(got, [0.3, 0.25, 0.0, 0.0], rtol=1e-12, atol=0)
    assert got[0] == pytest.approx(penetration(datas[0], q[:64], [(0, 64)]), rel=1e-12)


def test_run_compare_and_sweep_judge_an_explosion_alike(tmp_path):
    # ks = 1e6 makes symplectic and rk4 explode at dt = 1e-3 (omega dt > 2.8): the frame and the
    # reason are the same in softsim run, in a copy of softsim compare and in a row of softsim sweep
    # (one explosion test, io/metrics.explosion_reason, on the device's per-jelly values).
    ks = ["--set", "jelly.0.springs.structural.ks=1e6", "--set", "jelly.0.springs.shear.ks=1e6",
          "--set", "jelly.0.springs.bending.ks=1e6"]
    common = ["seed_bowl", *SMALL, *ks, "--duration", "1.0", "--allow-unstable"]
    cmp_json = tmp_path / "cmp.json"
    assert cli.main(["compare", *common, "--integrators", "symplectic,rk4", "--out", str(tmp_path / "c.usda"),
                     "--metrics", str(cmp_json), "--quiet"]) == 3  # copies exploded
    copies = {v["name"]: v["exploded"] for v in json.loads(cmp_json.read_text())["variants"]}
    rc, out = sweep(tmp_path, *ks, "--duration", "1.0", "--integrators", "symplectic,rk4", "--workers", "1",
                    "--allow-unstable")
    assert rc == 0
    rows = {r["integrator"]: r for r in read_results(out)}
    for method in ("symplectic", "rk4"):
        metrics = tmp_path / f"{method}.json"
        code = cli.main(["run", *common, "--integrator", method, "--out", str(tmp_path / f"{method}.usda"),
                         "--metrics", str(metrics), "--quiet"])
        explosion = json.loads(metrics.read_text())["summary"]["explosion"]
        assert code == 3 and explosion is not None
        assert copies[method]["frame"] == rows[method]["explosion_frame"] == explosion["frame"]
        assert copies[method]["reason"] == rows[method]["explosion_reason"] == explosion["reason"]


def test_penetration_into_moving_terrain_is_measured_where_it_is_now():
    # A sphere rising at 1 m/s: after 0.1 s its centre is 0.1 m higher, and a particle 0.3 m above
    # its rest centre is 0.1 m inside it (it would be on its surface at rest).
    sphere = {"center": [0.0, -0.5, 0.0], "radius": 0.4, "motion": {"velocity": [0.0, 1.0, 0.0]}}
    datas = _worlds([{"sphere": [sphere]}, {"sphere": [dict(sphere, motion={"velocity": [0.0, 0.0, 0.0]})]}])
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    batch.sim.advance(round(0.1 / datas[0]["simulation"]["dt"]))
    q = np.tile([0.0, 5.0, 0.0], (2 * 64, 1))
    q[0] = q[64] = [0.0, -0.1, 0.0]
    np.testing.assert_allclose(_depths(batch, q), [0.1, 0.0], rtol=1e-12, atol=1e-12)


def test_each_worlds_speed_bound_is_its_single_runs():
    # Worlds of different terrain (a moving bowl and a moving sphere included), jelly placement and
    # initial velocity: each world's explosion bound is, bit for bit, the bound a model of that
    # variant alone derives (io/metrics.speed_bound).
    from softsim_warp.core.model import build_model
    from softsim_warp.io.metrics import speed_bound
    from softsim_warp.io.worlds import world_speed_bound

    bowl = {"center": [40.0, 9.0, 0.0], "radius": 9.0, "cut_height": 5.0}
    terrains = [{}, {"plane": [{"point": [0.0, -3.0, 0.0], "normal": [0.0, 1.0, 0.0]}]},
                {"bowl": [dict(bowl, motion={"velocity": [0.5, 0.0, 0.0]})]},
                {"sphere": [{"center": [30.0, 0.0, 0.0], "radius": 2.0, "motion": {"velocity": [0.0, 2.0, 0.0]}}]}]
    datas = _worlds(terrains)
    for w, data in enumerate(datas):
        data["jelly"][0]["velocity"] = [0.3 * w, -1.0, 0.7]
        data["jelly"][0]["center"] = [-5.0 + w, 10.0 + 0.5 * w, 0.0]
    batch = batch_mod._Batch(datas, "cpu", use_graph=False)
    for w, data in enumerate(datas):
        alone = speed_bound(build_model(scene_mod.Scene(data), "cpu"))
        assert world_speed_bound(batch.model, *batch.ranges[w], w) == alone == batch.worlds.bound[w]


# ---------------------------------------------------------------------------------------------
# A frame of all worlds judged at once is each world judged alone


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_exploded_mask_is_explosion_reason_of_each_world(precision):
    # Every combination of the edge values of the test: a count of non-finite particles, speeds at,
    # just above and beyond the bound (NaN included), energies at and past the overflow limit (NaN,
    # +-inf, +-safe, just below it). The batch's mask is True exactly where the single run's test
    # gives a reason.
    import itertools  # noqa: PLC0415
    import math  # noqa: PLC0415

    from softsim_warp.io.metrics import exploded_mask, explosion_reason  # noqa: PLC0415

    safe = math.sqrt(float(np.finfo(np.dtype(precision)).max))
    bound = 7.5
    energies = [0.0, -3.0, 1e3, np.nextafter(safe, 0.0), safe, -safe, math.inf, -math.inf, math.nan]
    speeds = [0.0, bound, np.nextafter(bound, math.inf), math.inf, math.nan]
    combos = list(itertools.product([0, 3], speeds, energies, energies, energies, energies))
    cols = [np.array(c) for c in zip(*combos)]
    mask = exploded_mask(*cols, np.full(len(combos), bound), precision)
    expected = [explosion_reason(*c, bound, precision) is not None for c in combos]
    assert mask.tolist() == expected
    assert 0 < sum(expected) < len(expected)


def test_world_columns_are_world_frame_of_each_world():
    # One jelly a world (the sweep's case) is vectorised; several jellies a world are summed by
    # world_frame. Both give each world's values bit for bit as world_frame of that world alone.
    from softsim_warp.io.worlds import world_columns, world_frame  # noqa: PLC0415

    rng = np.random.default_rng(7)
    jellies_count = 9
    arrays = {"ke": rng.random(jellies_count), "ge": rng.normal(size=jellies_count) * 1e3,
              "se": rng.random(jellies_count) * 1e-3, "mom": rng.normal(size=(jellies_count, 3)),
              "vmax": rng.random(jellies_count) * 10, "bad": np.array([0, 0, 2, 0, 0, 0, 1, 0, 0], np.int32),
              "mass": np.array([1.0, 2.0, 0.0, 0.5, 3.0, 1.5, 1.0, 2.5, 0.25])}
    for layout in ([(j, j + 1) for j in range(jellies_count)], [(0, 1), (1, 4), (4, 5), (5, 9)]):
        cols = world_columns(arrays, layout)
        for w, jellies in enumerate(layout):
            alone = world_frame(arrays, jellies)
            assert cols["com"][w].tolist() == alone["com"]
            assert int(cols["nonfinite"][w]) == alone["nonfinite"]
            for key in ("kinetic_energy", "spring_energy", "gravity_energy", "total_energy", "max_speed"):
                assert float(cols[key][w]) == alone[key], key
