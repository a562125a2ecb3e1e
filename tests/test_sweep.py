"""``softsim sweep`` as a command: --find-stable-dt and bad input.

The sweep's parts have their own files: tests/test_sweep_plan.py (planning variants and batches),
tests/test_sweep_batch.py (a batch on a device: rows equal single runs, metrics on the device),
tests/test_sweep_store.py (the results store: Ctrl-C and --resume) and tests/test_sweep_cluster.py
(a killed worker, a lost scheduler). They share tests/sweep_helpers.py.
"""

from __future__ import annotations

import json

import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.commands import cli  # noqa: E402
from softsim_warp.io.sweep import read_results  # noqa: E402
from tests.sweep_helpers import KS, SMALL, env, sweep, sweep_command, wait_for  # noqa: E402, F401


def test_find_stable_dt_agrees_with_stability(tmp_path):
    rc, out = sweep(tmp_path, "--duration", "0.1", "--integrators", "symplectic,rk4", "--find-stable-dt",
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
