"""The cluster (softsim_warp/io/sweep/cluster.py): a killed worker's task runs again elsewhere; a lost
scheduler keeps the finished rows and --resume on a new cluster runs the rest."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.io.sweep import read_results  # noqa: E402
from tests.sweep_helpers import KS, SMALL, env, sweep, sweep_command, wait_for  # noqa: E402, F401


def test_killed_worker_sweep_completes_with_every_row(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "kill.csv"
    proc = subprocess.Popen(sweep_command("--duration", "0.3", "--vary", f"{KS}=1000,2000,3000,4000", "--workers", "2",
                                 "--batch", "1", "--out", str(out)),
                            env=env(marks, delay=1.5), stderr=subprocess.PIPE, text=True)
    try:
        # A worker holding a task (started, not finished): kill its process outright.
        running = wait_for(lambda: sorted(marks.glob("*.running")))
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


def test_lost_scheduler_keeps_finished_rows_and_resume_finishes(tmp_path):
    # An existing cluster (--scheduler): its scheduler is killed mid-sweep; the rows of the tasks
    # that finished stay, the command says to resume, and --resume on a new cluster runs the rest.
    marks = tmp_path / "marks"
    marks.mkdir()
    dask = Path(sys.executable).with_name("dask")
    info = tmp_path / "scheduler.json"
    environ = env(marks, delay=1.0)
    procs = [subprocess.Popen([str(dask), "scheduler", "--port", "0", "--dashboard-address", ":0",
                               "--scheduler-file", str(info)], env=environ, stderr=subprocess.DEVNULL)]
    try:
        wait_for(lambda: info.exists() and info.read_text().strip().endswith("}"))
        procs.append(subprocess.Popen([str(dask), "worker", "--scheduler-file", str(info), "--nthreads", "1",
                                       "--no-nanny"], env=environ, stderr=subprocess.DEVNULL))
        address = json.loads(info.read_text())["address"]
        out = tmp_path / "lost.parquet"
        argv = ("--duration", "0.3", "--vary", f"{KS}=1000:6000:6", "--batch", "1", "--out", str(out))
        sweep = subprocess.Popen(sweep_command(*argv, "--scheduler", address), env=environ, stderr=subprocess.PIPE, text=True)
        parts = tmp_path / ".lost.parquet.parts"
        wait_for(lambda: len(list(parts.glob("part-*.parquet"))) >= 2, timeout=90)  # two tasks' rows written
        procs[0].kill()
        _, err = sweep.communicate(timeout=90)
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert sweep.returncode == 1 and "the scheduler was lost" in err and "--resume" in err, err
    kept = {r["variant_id"]: r for r in read_results(out)}
    assert 2 <= len(kept) < 6
    done = subprocess.run(sweep_command(*argv, "--workers", "2", "--resume"), env=env(), stderr=subprocess.PIPE, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == list(range(6))
    assert all(r == kept[r["variant_id"]] for r in rows if r["variant_id"] in kept)
