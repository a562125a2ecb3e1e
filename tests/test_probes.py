"""The GPU measurement scripts in benchmarks/ compute what they claim: every variant's forces agree.

They time kernels on the GPU machine (docs/PERFORMANCE.md); here each runs once on a small lattice
on the CPU, and the forces of its variants must agree with its reference variant to float32
rounding (the scripts record the largest relative difference in their JSON).
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    "script, args, key",
    [
        ("benchmarks/column_probe.py", ["--columns", "2,4"], "rows"),  # product gather included
        ("benchmarks/layout_probe.py", [], "rows"),
    ],
)
def test_probe_variants_agree(tmp_path, script, args, key):
    out = tmp_path / "probe.json"
    argv = [str(ROOT / script), "--device", "cpu", "--size", "12", "--evals", "1", "--repeats", "1", "--out", str(out)]
    subprocess.run([sys.executable, *argv, *args], check=True, capture_output=True, timeout=600)
    rows = json.loads(out.read_text())[key]
    assert len(rows) >= 3
    for row in rows:
        assert row["max_rel_diff"] < 1.0e-5, row


def test_regs_probe_variants_agree(tmp_path):
    """benchmarks/regs_probe.py times the fused stage's native gather against the Warp-loop one; on
    the CPU their trajectories are the same bits."""
    out = tmp_path / "regs.json"
    argv = [str(ROOT / "benchmarks/regs_probe.py"), "--device", "cpu", "--size", "8", "--caps", "0"]
    argv += ["--kernels", "integrate_lattice_stage_stencil,integrate_lattice_stage", "--steps", "20", "--repeats", "1"]
    subprocess.run([sys.executable, *argv, "--out", str(out)], check=True, capture_output=True, timeout=600)
    rows = json.loads(out.read_text())["rows"]
    assert {r["kernel"] for r in rows} == {"integrate_lattice_stage_stencil", "integrate_lattice_stage"}
    assert len(rows) == 4
    assert all(r["max_rel_diff"] == 0.0 for r in rows), rows
