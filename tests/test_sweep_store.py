"""The results store (softsim_warp/io/sweep/store.py): no finished row lost to Ctrl-C; --resume runs
only the missing rows and refuses another sweep's."""

from __future__ import annotations

import signal
import subprocess

import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.core.errors import CommandLineError  # noqa: E402
from softsim_warp.io import sweep as engine  # noqa: E402
from softsim_warp.io.sweep import read_results  # noqa: E402
from tests.sweep_helpers import KS, SMALL, env, sweep, sweep_command, wait_for  # noqa: E402, F401


def _interrupt_after_two_parts(command, marks, parts) -> str:
    """Run a sweep ``command`` (tasks slowed down), send SIGINT once two tasks' rows are written to
    ``parts``; asserts exit 130 and returns stderr."""
    proc = subprocess.Popen(command, env=env(marks, delay=0.7), stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: len(list(parts.glob("part-*.parquet"))) >= 2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    return err


def test_interrupt_then_resume_recomputes_nothing_and_misses_nothing(tmp_path):
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "res.parquet"
    argv = ("--duration", "0.3", "--vary", f"{KS}=1000,2000,3000,4000,5000,6000", "--workers", "1", "--batch", "1",
            "--out", str(out))
    parts = tmp_path / ".res.parquet.parts"
    err = _interrupt_after_two_parts(sweep_command(*argv), marks, parts)  # two tasks' rows written
    assert "--resume" in err
    first = {r["variant_id"]: r for r in read_results(out)}
    assert 2 <= len(first) < 6

    # Without --resume the unfinished sweep's parts are not thrown away.
    if parts.exists():
        with pytest.raises(CommandLineError, match="--resume"):
            engine.RowStore(out, pq.read_schema(out), resume=False)

    marks2 = tmp_path / "marks2"
    marks2.mkdir()
    done = subprocess.run(sweep_command(*argv, "--resume"), env=env(marks2), stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == list(range(6))
    again = {r["variant_id"]: r for r in rows}
    for ident, row in first.items():
        assert again[ident] == row  # same worker, same wall time: kept, not recomputed
    assert len(list(marks2.glob("*.done"))) == 6 - len(first)
    assert not parts.exists()

    # Resuming a complete sweep runs nothing.
    rc, _ = sweep(tmp_path, *argv[:-2], "--resume", name="res.parquet")
    assert rc == 0 and read_results(out) == rows


def test_resume_refuses_another_sweeps_rows(tmp_path, capsys):
    rc, _ = sweep(tmp_path, "--duration", "0.1", "--vary", f"{KS}=1000", "--workers", "1")
    assert rc == 0
    rc, _ = sweep(tmp_path, "--duration", "0.1", "--vary", f"{KS}=2000", "--workers", "1", "--resume")
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and "not variants of this sweep" in err[-1]
