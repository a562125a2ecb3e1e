"""Convergence orders, stability limits against the linear analysis, float32 against float64.

All runs use the built-in ``free_flight`` scene (no terrain, so no contact to spoil the orders) on a
4x4x4 lattice to stay fast.
"""

import json
import math

import numpy as np
import pytest

from softsim_warp.studies import accuracy
from softsim_warp.studies import stability
from softsim_warp.commands.cli import main
from softsim_warp.io.scene import load_scene

SMALL = ["jelly.0.resolution=4"]


def _implicit_available():
    try:
        import softsim_warp.core.implicit  # noqa: F401, PLC0415
    except ImportError:
        return False
    return True


# Steps in each method's asymptotic range on the 4x4x4 free_flight jelly. euler's are 8-32 times
# below its linear limit kd/ks = 2e-3 s: closer to it, the weakly damped modes that euler amplifies
# by |1 + h lambda| ~ 1 make the error grow faster than h (measured local orders 1.1-1.8 between
# 5e-4 and 2e-3). The others' errors are well above the float64 round-off floor (~1e-14).
ORDER_DTS = {
    "euler": [2.5e-4, 1.25e-4, 6.25e-5],
    "symplectic": [1e-3, 5e-4, 2.5e-4],
    "midpoint": [2e-3, 1e-3, 5e-4],
    "rk4": [4e-3, 2e-3, 1e-3],
    "implicit": [2.5e-4, 1.25e-4, 6.25e-5],
}
EXPECTED_ORDER = {"euler": 1, "symplectic": 1, "midpoint": 2, "rk4": 4, "implicit": 1}


def test_free_flight_orders():
    overrides = SMALL + ["simulation.duration=0.3"]
    methods = ["euler", "symplectic", "midpoint", "rk4"]
    if _implicit_available():
        # A CG residual of 1e-4 would add a step-independent error; the order needs the exact step.
        overrides.append("implicit.cg_tolerance=1e-10")
        methods.append("implicit")
    scene = load_scene("free_flight", overrides)
    # rk4 at 3e-5 s has an error ~ (3e-5 / 1e-3)^4 = 1e-6 times rk4's at 1e-3 s (6e-8), ~1e-14: far
    # below every error measured here; the report's self_error checks that claim.
    report = accuracy.measure(scene, methods, {m: ORDER_DTS[m] for m in methods}, device="cpu",
                              precision="float64", reference_dt=3e-5)
    ref = report["reference"]
    smallest = min(r["rms_error"] for r in report["runs"])
    # Reference converged: its difference to the half-step run is >= 1000x below every error.
    assert ref["self_error"] * 1000 < smallest, ref
    assert all(r["stable"] for r in report["runs"])
    for m in methods:
        order = report["orders"][m]["order"]
        assert len(report["orders"][m]["dts_fitted"]) == 3, report["orders"][m]
        # error ~ C dt^p: the slope of log(error) against log(dt) is p.
        assert abs(order - EXPECTED_ORDER[m]) <= 0.1, (m, order, report["orders"][m])  # within 0.04 measured


def test_free_flight_centre_of_mass_is_a_parabola():
    """Spring forces cancel in pairs, so the centre of mass flies x0 + v0 t + g t^2 / 2: rk4 and
    midpoint integrate a constant acceleration exactly; euler lags by g h t / 2 (x_n = x0 + v0 t +
    g t (t - h) / 2)."""
    scene = load_scene("free_flight", SMALL + ["simulation.duration=0.2"])
    j = scene.jellies[0]
    g = np.array(scene.sim["gravity"])
    for method in ("rk4", "euler"):
        tr = accuracy.run_trajectory(scene, method, 1e-3, device="cpu", precision="float64")
        t = tr.times[: tr.frames_done, None]
        com = tr.positions.mean(axis=1)  # equal masses
        exact = np.array(j["center"]) + np.array(j["velocity"]) * t + 0.5 * g * t * t
        if method == "euler":
            exact -= 0.5 * g * tr.dt * t
        np.testing.assert_allclose(com, exact, atol=1e-12, rtol=0)


@pytest.mark.parametrize("method", ["euler", "midpoint", "rk4"])
def test_stability_limit_matches_linear_prediction(method):
    scene = load_scene("free_flight", SMALL)
    js = stability.free_jelly(scene.jellies[0])
    assert js["resolution"] == [4, 4, 4]
    predicted = stability.predict(js, [method])[method]
    model = stability.lattice_model(js, "cpu", "float64")
    limit = stability.measure_limit(model, method, guess=predicted, steps=1000, max_dt=0.1, rtol=0.02)
    measured = math.sqrt(limit["dt"] * limit["unstable_dt"])  # middle of the final 2% bracket
    assert limit["bound"] == ""
    # The 2 % bracket around the prediction, and 1 % more (0.5 to 1.6 % is measured).
    assert abs(measured / predicted - 1.0) <= 0.03, (method, measured, predicted)


def test_float32_agrees_with_float64(device):
    """Each step rounds every position once in float32 (relative error <= eps/2); independent
    roundings accumulate like a random walk, so after N steps the two runs differ by about
    eps |x| sqrt(N). Allow 4x that; and the float32 run must differ from float64 at all."""
    scene = load_scene("free_flight", SMALL + ["simulation.duration=0.1"])
    eps = float(np.finfo(np.float32).eps)
    for method in ("euler", "symplectic", "midpoint", "rk4"):
        a = accuracy.run_trajectory(scene, method, 1e-3, device=device, precision="float32")
        b = accuracy.run_trajectory(scene, method, 1e-3, device=device, precision="float64")
        steps = a.steps_per_frame * (a.frames_done - 1)
        diff = float(np.abs(a.positions - b.positions).max())
        bound = 4.0 * eps * float(np.abs(b.positions).max()) * math.sqrt(steps)
        assert 0.0 < diff <= bound, (method, diff, bound)


def test_accuracy_cli(tmp_path, capsys):
    out, plot = tmp_path / "acc.json", tmp_path / "acc.png"
    rc = main(["accuracy", "free_flight", "--set", "jelly.0.resolution=3", "--integrators", "euler,rk4",
               "--dts", "4e-3,2e-3", "--duration", "0.1", "--out", str(out), "--plot", str(plot), "--quiet"])
    assert rc == 0
    report = json.loads(out.read_text())
    assert {r["integrator"] for r in report["runs"]} == {"euler", "rk4"}
    assert plot.stat().st_size > 10_000
    text = capsys.readouterr().out
    assert "RMS error" in text and "fitted order" in text


def test_accuracy_cli_marks_unstable_runs(tmp_path, capsys):
    # euler at 8e-3 s is 4x its linear limit kd/ks = 2e-3 s: it must appear as unstable, not vanish.
    out = tmp_path / "acc.json"
    rc = main(["accuracy", "free_flight", "--set", "jelly.0.resolution=3", "--integrators", "euler",
               "--dts", "8e-3,1e-3", "--duration", "0.5", "--out", str(out), "--quiet"])
    assert rc == 0
    runs = json.loads(out.read_text())["runs"]
    assert [r["stable"] for r in runs] == [False, True]
    # Strict JSON: an infinite error is written as null (no Infinity token).
    assert runs[0]["rms_error"] is None and runs[0]["explosion"]["reason"]
    assert "UNSTABLE" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["accuracy", "free_flight", "--integrators", "eulr"], "--integrators: unknown integrator"),
        (["accuracy", "free_flight", "--dts", "1e-3,x"], "--dts: must be a comma-separated list"),
        (["accuracy", "free_flight", "--dts", "0.5"], "--dts: steps must not exceed the frame interval"),
        (["stability", "free_flight", "--ks", "-1"], "--ks: values must be finite and > 0"),
        (["stability", "free_flight", "--steps", "3"], "--steps: must be an integer >= 10"),
    ],
)
def test_bad_arguments_exit_2(argv, needle, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_stability_cli(tmp_path, capsys):
    out, plot = tmp_path / "st.json", tmp_path / "st.png"
    rc = main(["stability", "free_flight", "--set", "jelly.0.resolution=3", "--integrators", "symplectic",
               "--ks", "1e3", "--steps", "200", "--no-scene", "--rtol", "0.1", "--out", str(out), "--plot", str(plot),
               "--quiet"])
    assert rc == 0
    report = json.loads(out.read_text())
    assert [(r["integrator"], r["damping"]) for r in report["limits"]] == [("symplectic", "scene"), ("symplectic", "none")]
    assert report["ks_map"][0]["ks"] == 1e3
    assert plot.stat().st_size > 10_000
    assert "predicted" in capsys.readouterr().out


def test_stability_without_ks_map_draws_one_panel(tmp_path):
    """`--ks none`: no map, so no empty right-hand panel and no matplotlib warning about a legend
    without entries."""
    import warnings  # noqa: PLC0415

    from PIL import Image  # noqa: PLC0415

    plot = tmp_path / "st.png"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc = main(["stability", "free_flight", "--set", "jelly.0.resolution=3", "--integrators", "symplectic",
                   "--ks", "none", "--steps", "200", "--no-scene", "--rtol", "0.1", "--plot", str(plot), "--quiet"])
    assert rc == 0
    width, height = Image.open(plot).size
    assert width < 1.5 * height  # one 7 x 5.5 in panel, not the 13 x 5.5 in pair


def test_find_limit_brackets_a_known_threshold():
    # A fake criterion with its threshold at 0.0123: the bracket must hold it and be rtol wide.
    lim = stability.find_limit(lambda h: h <= 0.0123, guess=0.001, max_dt=1.0, rtol=0.01)
    assert lim["dt"] <= 0.0123 < lim["unstable_dt"] <= lim["dt"] * 1.01
    assert stability.find_limit(lambda h: True, guess=0.01, max_dt=0.05)["bound"] == ">="
    assert stability.find_limit(lambda h: False, guess=0.01, min_dt=1e-4)["bound"] == "<"


def test_accuracy_refuses_a_reference_run_that_cannot_finish(capsys):
    """A step of 1e-13 s makes the reference run 5e11 steps: refused up front with how long it would take."""
    assert main(["accuracy", "free_flight", "--dts", "1e-13", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: command line: --dts: the reference run of"), err
    assert "days" in err[0] and "(got '1e-13')" in err[0]
