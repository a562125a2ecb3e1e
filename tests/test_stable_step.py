"""The stable step before the run (io/stable_step.py): a dt above a jelly's predicted limit is refused
before any kernel compiles, ``dt = "auto"`` runs at a dt within the factors of the limit measured by
stepping, and the prediction of a 15k-particle mesh jelly stays within a bound on its work."""

import json
import math
import os
import subprocess
import sys

import pytest
import warp as wp

from softsim_warp.commands import cli
from softsim_warp.studies import stability
from softsim_warp.commands import compare as compare_cmd
from softsim_warp.commands import sweep as sweep_cmd
from softsim_warp.core import stability_model as sm
from softsim_warp.core.errors import SceneError, UserError
from softsim_warp.io import stable_step
from softsim_warp.io.scene import load_scene


def _measured(model, method, guess, steps=stability.DEFAULT_STEPS):
    """The limit measured by stepping (softsim stability's bisection): the middle of the 2 % bracket."""
    lim = stability.measure_limit(model, method, guess=guess, steps=steps, max_dt=0.1, rtol=0.02)
    assert lim["bound"] == ""
    return math.sqrt(lim["dt"] * lim["unstable_dt"])


def test_refused_before_any_kernel_compiles(tmp_path):
    """A fresh kernel cache stays empty: the refusal comes before Warp builds a module, with one line
    on stderr naming the jelly, the integrator and the largest stable dt, exit 2, no output file."""
    cache = tmp_path / "warp_cache"
    env = {**os.environ, "WARP_CACHE_PATH": str(cache)}
    # The control: this Warp puts its modules where WARP_CACHE_PATH says.
    probe = subprocess.run([sys.executable, "-c", "import warp as wp; wp.config.quiet = True; wp.init(); "
                            "print(wp.config.kernel_cache_dir)"], env=env, capture_output=True, text=True, check=True)
    kernel_dir = os.path.realpath(probe.stdout.strip().splitlines()[-1])
    assert kernel_dir.startswith(os.path.realpath(cache) + os.sep)

    def cached():
        return {os.path.relpath(os.path.join(d, f), cache) for d, _, fs in os.walk(cache) for f in fs} | {
            os.path.relpath(os.path.join(d, x), cache) for d, xs, _ in os.walk(cache) for x in xs}

    before = cached()
    out = tmp_path / "o.usdc"
    proc = subprocess.run([sys.executable, "-m", "softsim_warp", "run", "hard_stiff_1e5", "--quiet", "--out", str(out)],
                          env=env, capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    pred = sm.predict_jelly_dt(load_scene("hard_stiff_1e5").jellies[0], ("symplectic",)).dt["symplectic"]
    shown = f"{stable_step._floor2(pred):.2g}"
    assert lines == [f"error: hard_stiff_1e5.toml: simulation.dt: jelly.0 (box lattice 10x10x10) is unstable with "
                     f"symplectic above {shown} s; use dt <= {shown} or dt = \"auto\" (got 0.0004)"]
    assert float(shown) <= pred < 1.1 * float(shown)
    after = cached()
    assert after == before, sorted(after - before)  # no module compiled (nor loaded)
    assert not out.exists()


def test_refusal_follows_the_factor():
    """Refused above REFUSE_FACTOR x the prediction, not at or below it; implicit never."""
    scene = load_scene("jelly_drop")
    data = scene.data
    lim = stable_step.jelly_limit(data, 0, "symplectic")
    assert stable_step.limit_problem(data, lim * stable_step.REFUSE_FACTOR * 0.999, "symplectic") is None
    assert "unstable with symplectic" in stable_step.limit_problem(data, lim * stable_step.REFUSE_FACTOR * 1.001,
                                                                    "symplectic")
    stiff = load_scene("hard_stiff_1e6", ["simulation.integrator=implicit"]).data
    stable_step.check_stable_dt(stiff, "hard_stiff_1e6.toml")  # 1e6 N/m at 4e-4 s: implicit Euler is stable
    with pytest.raises(SceneError, match="unstable with symplectic above"):
        stable_step.check_stable_dt(load_scene("hard_stiff_1e6").data, "hard_stiff_1e6.toml")
    stable_step.check_stable_dt(load_scene("hard_stiff_1e6").data, "hard_stiff_1e6.toml", refuse=False)


def test_undamped_euler_is_refused_at_every_dt():
    data = load_scene("hard_undamped", ["simulation.integrator=euler"]).data
    with pytest.raises(SceneError, match=r"jelly.0 \(box lattice 6x6x6\) is unstable with euler at every dt"):
        stable_step.check_stable_dt(data, "hard_undamped.toml")
    with pytest.raises(SceneError, match="no stable dt"):
        load_scene("hard_undamped", ["simulation.integrator=euler", "simulation.dt=auto"])


def test_pins_are_held_in_the_prediction():
    """A pinned particle is out of the system (the dense analysis with its rows removed: the
    matrix-free tests), so pinning never lowers the predicted limit."""
    data = load_scene("hang").data
    pinned = stable_step._pinned(data, 0)
    assert pinned
    free = sm.predict_jelly_dt(data["jelly"][0], ("symplectic",)).dt["symplectic"]
    held = stable_step.jelly_limit(data, 0, "symplectic")
    assert held >= free * (1 - 1e-3)


def test_mesh_jelly_prediction_against_the_measured_limit(capsys):
    """A mesh jelly's own voxelised lattice (not its box): the prediction within the factor of the
    limit measured by stepping, for symplectic and rk4; the refusal names the mesh."""
    scene = load_scene("mesh_drop")
    jelly = scene.jellies[0]
    pred = sm.predict_jelly_dt(jelly, ("symplectic", "rk4"), **stable_step.PREFLIGHT).dt
    model = sm.jelly_builder(jelly).finalize("cpu", "float64")
    assert model.particle_count < math.prod(jelly["resolution"])  # the mesh's lattice points only
    for method in ("symplectic", "rk4"):
        measured = _measured(model, method, pred[method])
        assert 1.0 / stable_step.REFUSE_FACTOR <= measured / pred[method] <= stable_step.REFUSE_FACTOR, method
    dt = 1.2 * pred["symplectic"]
    code = cli.main(["run", "mesh_drop", "--dt", f"{dt:.6g}", "--quiet", "--frames", "1"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dt: jelly.0 (mesh blob.usda) is unstable with symplectic above" in err[0], err


def test_stiff_springs_prediction_against_the_measured_limit():
    """ks = 1e5 (hard_stiff_1e5, 4x4x4): symplectic, midpoint and rk4 within the factor of the
    measured limit; midpoint's slow growth above its limit shows only over many steps."""
    jelly = load_scene("hard_stiff_1e5", ["jelly.0.resolution=4"]).jellies[0]
    pred = sm.predict_jelly_dt(jelly, ("symplectic", "midpoint", "rk4"), **stable_step.PREFLIGHT).dt
    model = sm.jelly_builder(jelly).finalize("cpu", "float64")
    for method, steps in (("symplectic", 1000), ("rk4", 1000), ("midpoint", 20000)):
        measured = _measured(model, method, pred[method], steps)
        assert 1.0 / stable_step.REFUSE_FACTOR <= measured / pred[method] <= stable_step.REFUSE_FACTOR, method


def test_auto_runs_without_exploding_within_the_factor(tmp_path, capsys):
    """--dt auto: the run completes, the summary says the dt and "(auto)", the dt divides the frame,
    and it lies between AUTO_FRACTION^2 and 1 times the limit measured by stepping the free jelly."""
    sets = ["--set", "jelly.0.resolution=6"]
    metrics = tmp_path / "m.json"
    code = cli.main(["run", "jelly_drop", *sets, "--dt", "auto", "--frames", "30", "--quiet",
                     "--out", str(tmp_path / "o.usdc"), "--metrics", str(metrics)])
    assert code == 0
    err = capsys.readouterr().err
    summary = json.loads(metrics.read_text())["summary"]
    dt = summary["dt"]
    assert summary["dt_auto"] is True and not summary["exploded"]
    assert f"at dt={dt:g} s (auto)" in err
    per_frame = 1.0 / (summary["fps"] * dt)
    assert per_frame == pytest.approx(round(per_frame), rel=1e-9)
    jelly = load_scene("jelly_drop", ["jelly.0.resolution=6"]).jellies[0]
    model = sm.jelly_builder(jelly).finalize("cpu", "float64")
    measured = _measured(model, "symplectic", dt / stable_step.AUTO_FRACTION)
    assert stable_step.AUTO_FRACTION**2 * measured <= dt < measured


def test_compare_shares_the_smallest_auto_dt_and_checks_each_copy(tmp_path, capsys):
    parser = cli.build_parser()
    args = parser.parse_args(["compare", "jelly_drop", "--integrators", "euler,rk4", "--dt", "auto"])
    plan = compare_cmd.plan_variants(args)
    euler = load_scene("jelly_drop", ["simulation.integrator=euler", "simulation.dt=auto"]).sim["dt"]
    rk4 = load_scene("jelly_drop", ["simulation.integrator=rk4", "simulation.dt=auto"]).sim["dt"]
    assert euler < rk4 and plan.dt == euler
    out = tmp_path / "c.usdc"
    code = cli.main(["compare", "jelly_drop", "--integrators", "rk4,euler", "--dt", "0.0025", "--quiet",
                     "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and not out.exists()
    assert "--dt: copy euler: jelly.0 (box lattice 10x10x10) is unstable with euler above" in err[0]


def test_sweep_refuses_unless_it_explores_the_step(capsys):
    """Without --dts or --allow-unstable a variant above its limit refuses the whole sweep (naming it);
    with either the variants run and a warning counts them; --find-stable-dt is not checked."""
    parser = cli.build_parser()
    vary = ["--vary", "jelly.0.springs.*.ks=2000,2e5", "--set", "jelly.0.resolution=4"]
    with pytest.raises(UserError, match=r"variant 1 \(jelly.0.springs.\*.ks=200000.0\): jelly.0 .* unstable"):
        sweep_cmd.plan(parser.parse_args(["sweep", "jelly_drop", *vary]))
    capsys.readouterr()
    _, variants, *_ = sweep_cmd.plan(parser.parse_args(["sweep", "jelly_drop", *vary, "--dts", "4e-4,1e-5"]))
    assert len(variants) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ") and "1 of 4 variants" in err[0]
    sweep_cmd.plan(parser.parse_args(["sweep", "jelly_drop", *vary, "--allow-unstable"]))
    assert "1 of 2 variants" in capsys.readouterr().err
    sweep_cmd.plan(parser.parse_args(["sweep", "jelly_drop", *vary, "--find-stable-dt"]))
    assert capsys.readouterr().err == ""


def test_15k_particle_mesh_jelly_prediction_work(monkeypatch):
    """The pre-flight prediction of a ~15k-particle mesh jelly: no Warp kernel launches, at most 60
    passes over the spring list, and the result within 0.5 % of a tightly converged prediction's
    top frequency."""
    jelly = load_scene("mesh_drop", ["jelly.0.resolution=31"]).jellies[0]

    def no_launch(*a, **k):
        raise AssertionError("the prediction launched a Warp kernel")

    monkeypatch.setattr(wp, "launch", no_launch)
    op = sm.jelly_operator(jelly)
    assert 14000 <= op.n <= 17000
    pred = sm.predict_operator_dt(op, ("symplectic",), **stable_step.PREFLIGHT)
    assert pred.converged and op.products <= 60
    tight = sm.predict_operator_dt(sm.jelly_operator(jelly), ("symplectic",), tol=1e-6, dt_tol=1e-6,
                                   max_iterations=120)
    assert pred.max_frequency == pytest.approx(tight.max_frequency, rel=5e-3)
    assert pred.dt["symplectic"] == pytest.approx(tight.dt["symplectic"], rel=5e-3)
