"""``softsim sweep``: a results file that existed is never replaced by part of a table, and a bad
``--scheduler`` address is one line.

A sweep to an ``--out`` that already holds a file (an earlier sweep's, not the one being resumed)
writes its rows to ``<stem>.partial<ext>`` until it is complete; interrupted, it leaves the old file
byte for byte, and ``--resume`` finishes it from the partial file and the parts, then replaces the
old file with the complete table. Tiny scenes: the 3^3 jelly of tests/robustness_cases.py.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pq = pytest.importorskip("pyarrow.parquet")

from softsim_warp.commands import cli
from softsim_warp.io import sweep as engine
from softsim_warp.io.sweep import check_scheduler_address, read_results

sys.path.insert(0, str(Path(__file__).parent))
from test_sweep_store import _interrupt_after_two_parts
from tests.sweep_helpers import env as _env

KS = "jelly.0.springs.structural.ks"


@pytest.fixture
def scene(base_scene):
    return base_scene


# ---------------------------------------------------------------------------------------------
# --scheduler


@pytest.mark.parametrize(
    "address, why",
    [
        ("notanaddress", "no port"),
        ("foo://x:1", "unknown scheme 'foo'"),
        ("tcp://host", "no port"),
        ("tcp://:8786", "no host"),
        ("tcp://host:http", "the port must be an integer from 1 to 65535"),
        ("tcp://host:70000", "the port must be an integer from 1 to 65535"),
        ("inproc://x", "unknown scheme 'inproc'"),
        ("tcp://host:8786/x", "not HOST:PORT after the scheme"),
        ("   ", "empty"),
    ],
)
def test_bad_scheduler_address_is_one_line(tmp_path, capsys, scene, address, why):
    out = tmp_path / "s.csv"
    rc = cli.main(["sweep", str(scene), "--vary", f"{KS}=1,2", "--scheduler", address, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1, err
    assert err.startswith(f"error: command line: --scheduler: {why}; expected a scheduler address tcp://HOST:PORT"), err
    assert err.rstrip().endswith(f"(got {address!r})"), err
    assert not out.exists()


def test_good_scheduler_addresses_pass():
    assert check_scheduler_address("tcp://10.0.0.1:8786") == "tcp://10.0.0.1:8786"
    assert check_scheduler_address(" host:8786 ") == "tcp://host:8786"
    assert check_scheduler_address("TLS://[::1]:8786") == "tls://[::1]:8786"


# ---------------------------------------------------------------------------------------------
# An interrupted sweep leaves an existing results file alone


def _cli(scene, *argv):
    return [sys.executable, "-m", "softsim_warp", "sweep", str(scene), *argv, "--quiet"]


def test_interrupted_sweep_keeps_the_old_file_and_resume_replaces_it(tmp_path, scene):
    out, plot = tmp_path / "s.csv", tmp_path / "s.png"
    partial, partial_plot = tmp_path / "s.partial.csv", tmp_path / "s.partial.png"
    parts = tmp_path / ".s.csv.parts"
    # A complete earlier sweep.
    first = ["--vary", f"{KS}=10,20", "--duration", "0.05", "--workers", "1", "--out", str(out)]
    assert cli.main(["sweep", str(scene), *first, "--quiet"]) == 0
    plot.write_bytes(b"an earlier figure")
    old = out.read_bytes()
    assert len(read_results(out)) == 2

    # Another sweep to the same --out, interrupted after two of its six tasks.
    marks = tmp_path / "marks"
    marks.mkdir()
    argv = [
        "--vary",
        f"{KS}=1:100:6",
        "--duration",
        "0.1",
        "--workers",
        "1",
        "--batch",
        "1",
        "--out",
        str(out),
        "--plot",
        str(plot),
    ]
    err = _interrupt_after_two_parts(_cli(scene, *argv), marks, parts)
    assert out.read_bytes() == old  # the earlier table, byte for byte
    assert plot.read_bytes() == b"an earlier figure"
    kept = read_results(partial)
    assert 2 <= len(kept) < 6 and all(r["status"] == "completed" for r in kept)
    assert partial_plot.exists()
    line = err.strip().splitlines()[-1]
    assert f"{len(kept)} of 6 rows kept in {partial}" in line and "is unchanged" in line and "--resume" in line, err

    # Without --resume the unfinished sweep is not thrown away.
    again = subprocess.run(_cli(scene, *argv), check=False, env=_env(), stderr=subprocess.PIPE, text=True, timeout=60)
    assert again.returncode == 2 and "add --resume" in again.stderr, again.stderr
    assert out.read_bytes() == old and read_results(partial) == kept

    # --resume runs only the rest and puts the complete table at --out.
    marks2 = tmp_path / "marks2"
    marks2.mkdir()
    done = subprocess.run(
        _cli(scene, *argv, "--resume"), check=False, env=_env(marks2), stderr=subprocess.PIPE, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    rows = read_results(out)
    assert sorted(r["index"] for r in rows) == list(range(6))
    by_id = {r["variant_id"]: r for r in rows}
    assert all(by_id[r["variant_id"]] == r for r in kept)  # kept, not recomputed
    assert len(list(marks2.glob("*.done"))) == 6 - len(kept)
    assert not partial.exists() and not parts.exists()
    assert plot.read_bytes().startswith(b"\x89PNG") and partial_plot.exists()  # the partial figure stays


def test_resume_of_a_new_sweep_over_an_old_file_refuses_other_rows(tmp_path, capsys, scene):
    """The rows of an unfinished sweep over an old file are in its partial file: --resume of another
    sweep names that file, and nothing is written."""
    out = tmp_path / "s.parquet"
    argv = [
        "sweep",
        str(scene),
        "--vary",
        f"{KS}=10",
        "--duration",
        "0.05",
        "--workers",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    assert cli.main(argv) == 0
    old = out.read_bytes()
    # An unfinished sweep of other variants over it, as an interrupted one leaves it.
    schema = pq.read_schema(out)
    store = engine.RowStore(out, schema)
    assert store.keep_out and store.results == tmp_path / "s.partial.parquet"
    store.add([{**dict.fromkeys(schema.names), "variant_id": "another", "index": 0, "status": "completed"}])
    store.consolidate()
    assert out.read_bytes() == old and (tmp_path / ".s.parquet.parts" / engine.KEEP_OUT_MARK).exists()
    capsys.readouterr()
    assert cli.main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"'{store.results}' holds 1 rows that are not variants of this sweep" in err[0], err
    assert out.read_bytes() == old
