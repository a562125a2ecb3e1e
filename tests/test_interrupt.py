"""Interrupted and concurrent runs, with real ``softsim run`` processes and real signals.

A run is started on a long scene (100 000 frames) with its stderr on a terminal (a pty: the
progress bar is drawn only there), the test reads the bar until some frames are done, then signals
it. SIGINT and SIGTERM must leave a valid USD at the final path holding at least the frames
reported done, and exit with 128 + signum; SIGKILL must leave an existing file at the final path
untouched, the unfinished output only as a ``.partial`` file.
"""

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))
from terminal import TerminalRun  # noqa: E402

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

LONG = ["run", "jelly_drop", "--frames", "100000", "--no-graph"]
STARTUP_TIMEOUT = 180  # seconds until the first frames; generous for a cold kernel cache on a busy machine


class Run(TerminalRun):
    """A ``softsim run`` subprocess whose stderr, a terminal, is read continuously (tqdm writes ``k/total``)."""

    def __init__(self, args, cwd):
        super().__init__([sys.executable, "-m", "softsim_warp", *args], cwd)

    @property
    def err(self) -> bytes:
        return self.out

    def frames_done(self) -> int:
        counts = re.findall(rb"(\d+)/100001", self.err)
        return int(counts[-1]) if counts else 0

    def wait_for_frames(self, n):
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while self.frames_done() < n:
            if self.proc.poll() is not None:
                pytest.fail(f"run ended early with {self.proc.returncode}: {self.err.decode(errors='replace')}")
            if time.monotonic() > deadline:
                self.proc.kill()
                pytest.fail("no progress within the start-up timeout")
            time.sleep(0.05)
        return self.frames_done()


def _open_usd(path):
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    stage = Usd.Stage.Open(str(path))
    assert stage is not None, f"{path} does not open"
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/Jelly_0/Particles"))
    attr = points.GetPointsAttr()
    times = attr.GetTimeSamples()
    return stage, attr, times


def _validate_usd(path):
    """Opens, holds contiguous frames 0..k-1 of finite points, and passes every USD validator."""
    from pxr import UsdValidation  # noqa: PLC0415

    stage, attr, times = _open_usd(path)
    assert times == [float(k) for k in range(len(times))]
    for t in times:
        p = np.asarray(attr.Get(t))
        assert p.shape == (1000, 3) and np.isfinite(p).all()
    assert stage.GetEndTimeCode() == len(times) - 1
    registry = UsdValidation.ValidationRegistry()
    errors = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators()).Validate(stage)
    assert not errors, [(e.GetName(), e.GetMessage()) for e in errors]
    return stage, len(times)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_keeps_completed_frames(sig, tmp_path):
    out = tmp_path / "long.usdc"
    run = Run([*LONG, "--out", str(out), "--metrics", str(tmp_path / "long.json")], tmp_path)
    seen = run.wait_for_frames(5)
    run.proc.send_signal(sig)
    code = run.finish()
    assert code == 128 + sig, run.err.decode(errors="replace")
    stage, frames = _validate_usd(out)
    # Every frame reported done is in the file; the run stopped after the frame it was in.
    assert frames >= seen
    data = stage.GetRootLayer().customLayerData
    assert data["softsim:status"] == "interrupted" and data["softsim:frames"] == frames
    import json  # noqa: PLC0415

    summary = json.loads((tmp_path / "long.json").read_text())["summary"]
    assert summary["interrupted"] is True and summary["frames"] == frames
    assert not list(tmp_path.glob(".*partial*")), "temporary files left behind"


def test_second_sigint_stops_mid_frame(tmp_path):
    """Frames of 5 000 steps: the first SIGINT asks to stop after the frame, the second stops at once,
    dropping the frame in progress and keeping the frames written."""
    out = tmp_path / "slow.usda"
    # --no-graph: a captured frame is one launch, which a signal cannot split; plain steps can stop mid-frame.
    run = Run(["run", "jelly_drop", "--frames", "100000", "--fps", "2", "--dt", "1e-4", "--no-graph", "--out", str(out)],
              tmp_path)
    run.wait_for_frames(1)
    run.proc.send_signal(signal.SIGINT)
    time.sleep(0.2)
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 130, run.err.decode(errors="replace")
    stage, frames = _validate_usd(out)
    assert frames >= 1
    assert stage.GetRootLayer().customLayerData["softsim:status"] == "interrupted"


def test_sigkill_leaves_existing_output_untouched(tmp_path):
    out = tmp_path / "keep.usdc"
    old = b"the previous, complete output\n"
    out.write_bytes(old)
    before = os.stat(out)
    run = Run([*LONG, "--out", str(out)], tmp_path)
    run.wait_for_frames(3)
    run.proc.kill()
    assert run.finish() == -signal.SIGKILL
    assert out.read_bytes() == old
    after = os.stat(out)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
    partial = tmp_path / f".keep.partial-{run.proc.pid}.usdc"
    assert partial.is_file(), sorted(p.name for p in tmp_path.iterdir())


def test_failed_start_leaves_existing_output_untouched(tmp_path):
    """A run refused before simulating (bad --metrics path) never touches --out."""
    out = tmp_path / "keep.usda"
    out.write_text("#usda 1.0\n")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "softsim_warp",
            "run",
            "jelly_drop",
            "--frames",
            "2",
            "--out",
            str(out),
            "--metrics",
            str(tmp_path / "missing" / "m.json"),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert out.read_text() == "#usda 1.0\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.usda"]


def test_concurrent_runs_in_one_directory(tmp_path):
    """Two runs writing different files in one directory at the same time: both complete and correct."""
    runs = {
        name: subprocess.Popen(
            [
                sys.executable,
                "-m",
                "softsim_warp",
                "run",
                "jelly_drop",
                "--frames",
                "20",
                "--quiet",
                "--integrator",
                integrator,
                "--out",
                f"{name}.usda",
                "--metrics",
                f"{name}.json",
            ],
            cwd=tmp_path,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        for name, integrator in (("a", "symplectic"), ("b", "midpoint"))
    }
    for name, proc in runs.items():
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err.decode(errors="replace")
    for name, integrator in (("a", "symplectic"), ("b", "midpoint")):
        stage, frames = _validate_usd(tmp_path / f"{name}.usda")
        data = stage.GetRootLayer().customLayerData
        assert frames == 21 and data["softsim:integrator"] == integrator and data["softsim:status"] == "complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.usda", "b.json", "b.usda"]
    # Different integrators, so the two files must differ: neither overwrote the other.
    assert (tmp_path / "a.usda").read_bytes() != (tmp_path / "b.usda").read_bytes()
