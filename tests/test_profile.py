"""The opt-in step profile (core/profile.py, ``softsim run --profile``).

Profiling must not change the simulation: a profiled run launches the same kernels in the same
order as a captured one, only one by one with synchronises between them, so on the CPU (where
every run is deterministic) its states and CG iteration counts equal the captured run's bit for
bit. Its times are checked against a clock read around the run: the parts are disjoint intervals
inside the steps, so they cannot add up to more than the wall time of the run.
"""

import json
import time

import numpy as np
import pytest
import warp as wp

from softsim_warp.commands.cli import main as cli_main
from softsim_warp.core.implicit import ImplicitIntegrator
from softsim_warp.core.integrators import ExplicitIntegrator
from softsim_warp.core.lattice import SPRING_TYPE_NAMES
from softsim_warp.core.model import ModelBuilder
from softsim_warp.core.profile import NO_PROFILE, OTHER, StepProfile
from softsim_warp.core.stepper import Stepper

DT = 0.01
# Parts every implicit step with a contact solve has; multigrid adds its two.
IMPLICIT_PARTS = {"velocity_update", "forces_jacobians", "system_assembly", "cg_vector_update", "cg_spring_product",
                  "contact_solve", "contact", OTHER}
MULTIGRID_PARTS = {"multigrid_setup", "multigrid_vcycle"}


def dropped_jelly(size):
    """A stiff jelly (ks = 1e5, 0.5 kg) tilted just above a plane: it touches from the first step,
    so the contact solve runs in every step."""
    b = ModelBuilder(gravity=(0.0, -9.8, 0.0))
    springs = {t: {"ks": 1.0e5, "kd": 0.5} for t in SPRING_TYPE_NAMES}
    b.add_jelly((size,) * 3, 0.25, 0.5, springs, center=(0.0, 0.16, 0.0), axis=(1.0, 0.0, 1.0), degrees=20.0)
    b.add_plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), restitution=0.5, friction=0.5)
    return b.finalize("cpu", "float32")


CASES = {
    # 12^3 is where "auto" takes multigrid on the CPU (multigrid.AUTO_MIN_PARTICLES).
    "implicit_multigrid": (12, lambda m: ImplicitIntegrator(m)),
    "implicit_jacobi": (5, lambda m: ImplicitIntegrator(m, preconditioner="jacobi")),
    "rk4": (5, lambda m: ExplicitIntegrator(m, "rk4")),
}


def run(case, profile, chunks=3, steps=4):
    """Steps of ``case`` through a Stepper, captured (profile off) or profiled; the seconds spent in
    ``advance`` (the warm-up, which compiles, is taken before the clock starts)."""
    size, make = CASES[case]
    model = dropped_jelly(size)
    integ = make(model)
    stepper = Stepper(model, integ, DT, profile=profile)
    stepper.warm_up()
    wall = 0.0
    for _ in range(chunks):
        t0 = time.perf_counter()
        stepper.advance(steps)
        wall += time.perf_counter() - t0
    return stepper, wall


@pytest.mark.parametrize("case", list(CASES))
def test_profiled_run_equals_captured_run_and_its_parts_add_up(case):
    plain, _ = run(case, profile=False)
    profiled, wall = run(case, profile=True)
    assert plain.use_graph and not profiled.use_graph
    assert plain.profile is None and plain.integrator.profile is NO_PROFILE
    # The same kernels in the same order: bitwise the same states on the CPU.
    np.testing.assert_array_equal(profiled.state.particle_q.numpy(), plain.state.particle_q.numpy())
    np.testing.assert_array_equal(profiled.state.particle_qd.numpy(), plain.state.particle_qd.numpy())
    implicit = isinstance(plain.integrator, ImplicitIntegrator)
    if implicit:
        a, b = plain.integrator.stats(), profiled.integrator.stats()
        for key in ("cg_steps", "cg_iterations_mean", "cg_iterations_max", "cg_solves", "cg_unconverged_solves"):
            assert a[key] == b[key], key
        assert a["cg_solves"] > a["cg_steps"]  # contact solves ran

    stats = profiled.profile.stats()
    parts = stats["time_parts_s"]
    assert stats["time_steps"] == 12
    assert all(t >= 0.0 for t in parts.values())
    # Each second of a step goes to exactly one part, so the parts add up to the steps' time (up
    # to the rounding of the sum) ...
    assert sum(parts.values()) == pytest.approx(stats["time_total_s"], rel=1e-9)
    # ... which lies inside the clock read around advance(): the parts are disjoint intervals
    # between synchronises within the steps.
    assert stats["time_total_s"] <= wall
    if implicit:
        # Outside the parts are only the stepper's loop and the profile's own entry and exit, a
        # few microseconds a step, against a step of dozens of launches with a CG solve (ms on
        # the CPU): well above half the wall time.
        assert stats["time_total_s"] >= 0.5 * wall
        expected = IMPLICIT_PARTS | (MULTIGRID_PARTS if plain.integrator.multigrid is not None else set())
        assert (plain.integrator.preconditioner == "multigrid") == (case == "implicit_multigrid")
    else:
        expected = {"stages", "contact", OTHER}
    assert set(parts) == expected


def test_nested_parts_are_charged_exclusively():
    """A part's seconds exclude those of the parts inside it; a step stopped by an interrupt adds its
    time to the total but does not count, so the parts always add up to the total."""
    profile = StepProfile("cpu")
    with profile.step():
        with profile.part("outer"):
            time.sleep(0.05)
            with profile.part("inner"):
                time.sleep(0.2)
    parts = profile.stats()["time_parts_s"]
    assert list(parts) == ["outer", "inner", OTHER]
    assert parts["inner"] >= 0.2 and 0.05 <= parts["outer"] < 0.2  # outer holds its own sleep only
    with pytest.raises(KeyboardInterrupt), profile.step(), profile.part("inner"):
        raise KeyboardInterrupt
    assert profile.steps == 1
    assert sum(profile.seconds.values()) == pytest.approx(profile.total, rel=1e-12)


def test_no_profile_no_synchronise(monkeypatch):
    """Without a profile, steps launched one by one never synchronise (the profile's no-op contexts);
    with one, every part does (which shows the count sees them)."""
    calls = []
    real = wp.synchronize_device
    monkeypatch.setattr(wp, "synchronize_device", lambda *a, **k: (calls.append(a), real(*a, **k)))
    model = dropped_jelly(5)
    counts = []
    for profile in (False, True):
        stepper = Stepper(model, ImplicitIntegrator(model), DT, use_graph=False, profile=profile)
        stepper.warm_up()
        calls.clear()
        stepper.advance(3)
        counts.append(len(calls))
    assert counts[0] == 0 and counts[1] > 3 * 2 * len(IMPLICIT_PARTS)
    with pytest.raises(ValueError, match="use_graph must be off"):
        Stepper(model, ImplicitIntegrator(model), DT, use_graph=True, profile=True)


def cli(tmp_path, *flags):
    # 0.01 s is above symplectic's stable step for this jelly (7.6e-3 s predicted), which four steps do
    # not show; --allow-unstable lets the run past the check that would refuse it.
    return cli_main(["run", "jelly_drop", "--set", "jelly.0.resolution=[4,4,4]", "--dt", "0.01", "--frames", "2",
                     "--fps", "50", "--out", str(tmp_path / "x.usdc"), "--quiet", "--allow-unstable", *flags])


@pytest.mark.parametrize("integrator", ["implicit", "symplectic"])
def test_cli_profile_table_and_metrics(tmp_path, capsys, integrator):
    metrics = tmp_path / "m.json"
    assert cli(tmp_path, "--integrator", integrator, "--profile", "--metrics", str(metrics)) == 0
    out = capsys.readouterr().out
    summary = json.loads(metrics.read_text())["summary"]
    parts = summary["time_parts_s"]
    assert summary["time_steps"] == summary["steps"] == 4
    assert sum(parts.values()) == pytest.approx(summary["time_total_s"], rel=1e-9)
    assert summary["time_total_s"] <= summary["step_seconds"]
    assert out.startswith(f"profile: 4 steps of {integrator} on cpu")
    for name in [*parts, "total"]:
        assert f"\n  {name} " in out
    if integrator == "implicit":
        # 64 particles: jacobi, whose application is inside cg_update.
        assert summary["cg_preconditioner"] == "jacobi" and "contact_solve" in parts
        assert "multigrid_setup" not in parts and "cg_vector_update" in summary["time_notes"][0]
    else:
        assert set(parts) == {"stages", "contact", OTHER}

    # Without --profile: no time_* key, nothing on stdout.
    assert cli(tmp_path, "--integrator", integrator, "--metrics", str(metrics)) == 0
    assert capsys.readouterr().out == ""
    assert not any(k.startswith("time_") for k in json.loads(metrics.read_text())["summary"])


def test_cli_help_lists_profile(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["run", "--help"])
    assert exit_info.value.code == 0
    assert "--profile" in capsys.readouterr().out
