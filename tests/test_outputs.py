"""Outputs never destroy inputs or good files: collisions, failures, links, devices, locks, durability.

Each case runs the real command in-process (``cli.main``) or as a real process, on real files: real
symlinks and hard links, a real FIFO, ``/dev/null``, a real file-size limit for a full disk.
"""

import json
import os
import resource
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from softsim_warp.commands import cli
from softsim_warp.io import outputs as outputs_mod
from softsim_warp.io.outputs import Outputs
from softsim_warp.io.simulate import Simulator
from softsim_warp.io.usd import UsdWriter

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX files")

SMALL = ["--set", "jelly.0.resolution=[3,3,3]", "--quiet"]
RUN = ["run", "jelly_drop", "--frames", "4", *SMALL]


def _scene(tmp_path):
    src = tmp_path / "scene.toml"
    src.write_text(
        'name = "s"\n[simulation]\nintegrator = "symplectic"\ndt = 1e-3\nframes = 3\nfps = 30\n'
        "[[jelly]]\nresolution = [3, 3, 3]\nsize = 0.2\ncenter = [0.0, 0.5, 0.0]\ntotal_mass = 0.1\n"
        "springs.structural = { ks = 50.0, kd = 0.1 }\n[[plane]]\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 1.0, 0.0]\n"
    )
    return src


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


@pytest.mark.parametrize(
    "argv",
    [
        ["accuracy", "{scene}", "--integrators", "euler", "--dts", "1e-3", "--duration", "0.05", "--out", "{scene}"],
        ["stability", "{scene}", "--integrators", "euler", "--out", "{scene}"],
        ["compare", "{scene}", "--integrators", "euler,rk4", "--out", "{scene_usd}", "--metrics", "{scene}"],
        ["run", "{scene}", "--metrics", "{scene}"],
        ["run", "{scene}", "--metrics", "{link}"],  # a symlink to the scene
        ["run", "{scene}", "--metrics", "{hard}"],  # a hard link to the scene
        ["run", "{scene}", "--metrics", "sub/../{scene_name}"],
    ],
)
def test_outputs_never_overwrite_the_input(tmp_path, monkeypatch, capsys, argv):
    monkeypatch.chdir(tmp_path)
    scene = _scene(tmp_path)
    (tmp_path / "sub").mkdir()
    os.symlink(scene, tmp_path / "link.json")
    os.link(scene, tmp_path / "hard.json")
    before = scene.read_bytes()
    fill = {"scene": str(scene), "scene_usd": str(tmp_path / "x.usdc"), "link": "link.json", "hard": "hard.json",
            "scene_name": scene.name}
    code = cli.main([a.format(**fill) for a in argv] + ["--quiet"])
    assert code == 2
    _one_line_error(capsys, "would overwrite the input scene")
    assert scene.read_bytes() == before
    assert not (tmp_path / "x.usdc").exists()


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["accuracy", "free_flight", "--integrators", "euler", "--out", "r.png", "--plot", "r.png"], "--plot"),
        (["stability", "free_flight", "--out", "r.png", "--plot", "r.png"], "--plot"),
        (["compare", "jelly_drop", "--out", "c.usdc", "--metrics", "c.usdc"], "--metrics"),
        (["run", "jelly_drop", "--out", "r.usdc", "--metrics", "./r.usdc"], "--metrics"),
        (["bench", "--out", "b.json", "--plot", "b.png"], "--plot"),  # b.png links to b.json
    ],
)
def test_two_outputs_of_one_command_are_refused(tmp_path, monkeypatch, capsys, argv, flag):
    monkeypatch.chdir(tmp_path)
    os.symlink("b.json", tmp_path / "b.png")
    assert cli.main(argv + ["--quiet"]) == 2
    _one_line_error(capsys, flag, "is the same file as")
    assert [p.name for p in tmp_path.iterdir()] == ["b.png"]


def test_failed_run_keeps_the_good_output(tmp_path, monkeypatch, capsys):
    """An unexpected failure mid-run (here: an exception from the third frame on) must not replace
    the output of an earlier good run: that stays byte for byte, the failed run's frames are kept as
    out.partial.usdc, marked failed."""
    from pxr import Usd

    monkeypatch.chdir(tmp_path)
    assert cli.main(RUN + ["--out", "out.usdc", "--metrics", "out.json"]) == 0
    good, good_metrics = (tmp_path / "out.usdc").read_bytes(), (tmp_path / "out.json").read_bytes()
    calls = {"n": 0}
    advance = Simulator.advance

    def failing(self, n):
        calls["n"] += 1
        if calls["n"] > 2:
            raise RuntimeError("simulated failure")
        advance(self, n)

    monkeypatch.setattr(Simulator, "advance", failing)
    with pytest.raises(RuntimeError, match="simulated failure"):
        cli.main(RUN + ["--out", "out.usdc", "--metrics", "out.json"])
    assert (tmp_path / "out.usdc").read_bytes() == good
    assert (tmp_path / "out.json").read_bytes() == good_metrics
    kept = Usd.Stage.Open(str(tmp_path / "out.partial.usdc"))
    assert kept.GetRootLayer().customLayerData["softsim:status"] == "failed"
    assert not list(tmp_path.glob(".*partial-*")), "temporaries left behind"


def _interrupted(tmp_path, command, *argv) -> bytes:
    """stderr of ``softsim <command> jelly_drop`` (3^3, 100,000 frames, no graphs) sent SIGINT after its
    third frame; asserts the exit code 130. stderr is a terminal (a pty), where the progress bar is drawn."""
    from tests.terminal import TerminalRun  # noqa: PLC0415

    run = TerminalRun([sys.executable, "-m", "softsim_warp", command, "jelly_drop", "--frames", "100000", "--no-graph",
                       "--set", "jelly.0.resolution=[3,3,3]", *argv], tmp_path)
    deadline = time.monotonic() + 180
    while run.out.count(b"/100001") < 3 and run.proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    run.proc.send_signal(signal.SIGINT)
    assert run.finish(timeout=120) == 130, run.text
    return run.out.replace(b"\r\n", b"\n")


def test_interrupted_run_does_not_replace_an_existing_output(tmp_path):
    """SIGINT during a run whose output existed: the old file stays, the frames go to out.partial.usdc."""
    from pxr import Usd

    assert cli.main(["run", "jelly_drop", "--frames", "2", *SMALL, "--out", str(tmp_path / "out.usdc")]) == 0
    good = (tmp_path / "out.usdc").read_bytes()
    err = _interrupted(tmp_path, "run", "--out", "out.usdc")
    assert (tmp_path / "out.usdc").read_bytes() == good
    kept = Usd.Stage.Open(str(tmp_path / "out.partial.usdc"))
    assert kept.GetRootLayer().customLayerData["softsim:status"] == "interrupted"
    assert b"out.usdc existed" in err


def test_symlinked_output_is_written_through(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "real").mkdir()
    os.symlink("real/target.usdc", tmp_path / "out.usdc")
    os.symlink("real/target.json", tmp_path / "out.json")
    assert cli.main(RUN + ["--out", "out.usdc", "--metrics", "out.json"]) == 0
    assert (tmp_path / "out.usdc").is_symlink() and (tmp_path / "out.json").is_symlink()
    assert (tmp_path / "real" / "target.usdc").stat().st_size > 1000
    assert json.loads((tmp_path / "real" / "target.json").read_text())["summary"]["status"] == "complete"
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["target.json", "target.usdc"]


def test_devices_and_fifos_are_streamed_not_replaced(tmp_path, monkeypatch):
    """``--metrics /dev/null`` leaves the device node; a FIFO receives the JSON and stays a FIFO."""
    monkeypatch.chdir(tmp_path)
    fifo = tmp_path / "metrics.fifo"
    os.mkfifo(fifo)
    got = {}

    def read():
        with open(fifo, "rb") as f:
            got["data"] = f.read()

    reader = threading.Thread(target=read)
    reader.start()
    assert cli.main(RUN + ["--out", "a.usdc", "--metrics", str(fifo)]) == 0
    reader.join(timeout=60)
    assert json.loads(got["data"])["summary"]["status"] == "complete"
    assert fifo.is_fifo()
    assert cli.main(RUN + ["--out", "b.usdc", "--metrics", "/dev/null"]) == 0
    assert os.path.exists("/dev/null") and not os.path.isfile("/dev/null")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.usdc", "b.usdc", "metrics.fifo"]


def test_second_writer_of_an_output_is_refused(tmp_path, monkeypatch, capsys):
    """While one command holds its outputs, another command writing the same file is refused at once."""
    monkeypatch.chdir(tmp_path)
    holder = Outputs()
    holder.add("--out", "shared.usdc", (".usdc",))
    with holder:
        assert cli.main(RUN + ["--out", "./shared.usdc"]) == 2
        _one_line_error(capsys, "--out", f"another softsim process (pid {os.getpid()}) is writing this file")
    assert cli.main(RUN + ["--out", "shared.usdc"]) == 0  # released: the next run goes ahead
    assert not list(tmp_path.glob(".*.lock"))


def test_leftover_temporaries_of_dead_runs_are_removed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    leftover = tmp_path / f".out.partial-{int(dead.stdout)}.usdc"
    leftover.write_bytes(b"x" * 100)
    # The temporary of out.partial.usdc, which a run of out.usdc writes when out.usdc existed.
    kept = tmp_path / f".out.partial.partial-{int(dead.stdout)}.usdc"
    kept.write_bytes(b"x" * 100)
    other = tmp_path / ".other.partial-1.usdc"  # another output's temporary: not ours to touch
    other.write_bytes(b"y")
    assert cli.main(RUN + ["--out", "out.usdc"]) == 0
    assert not leftover.exists() and not kept.exists() and other.exists()


def test_json_outputs_are_strict(tmp_path, monkeypatch):
    """An exploding run's metrics hold no NaN or Infinity tokens (non-finite numbers are null)."""
    monkeypatch.chdir(tmp_path)
    code = cli.main(["run", "hard_stiff_1e6", "--integrator", "euler", "--frames", "3", "--quiet",
                     "--out", "boom.usdc", "--metrics", "boom.json", "--allow-unstable"])
    assert code == 3

    def refuse(token):
        raise AssertionError(f"non-standard JSON token {token}")

    json.loads((tmp_path / "boom.json").read_text(), parse_constant=refuse)
    outputs_mod.write_json_atomic(tmp_path / "x.json", {"a": float("nan"), "b": [float("inf"), 1.0]})
    assert json.loads((tmp_path / "x.json").read_text(), parse_constant=refuse) == {"a": None, "b": [None, 1.0]}


def test_usd_with_nonfinite_positions_is_never_complete(tmp_path):
    from pxr import Usd

    import softsim_warp as ss

    model = ss.build_model(ss.load_scene("jelly_drop", ["jelly.0.resolution=[2,2,2]"]), device="cpu")
    writer = UsdWriter(tmp_path / "nan.usda", model, fps=30)
    q = model.particle_q.numpy()
    writer.write_frame(0, 0.0, q)
    q[3] = np.nan
    writer.write_frame(1, 1 / 30, q)
    writer.close(status="complete")
    stage = Usd.Stage.Open(str(tmp_path / "nan.usda"))
    assert stage.GetRootLayer().customLayerData["softsim:status"] == "nonfinite"


def test_identical_runs_write_identical_bytes_across_saves(tmp_path, monkeypatch):
    """The writer saves by simulated frames (every 600), not by wall-clock time, so two identical runs
    long enough to save several times give the same bytes."""
    monkeypatch.chdir(tmp_path)
    for name in ("a", "b"):
        argv = ["run", "jelly_drop", "--frames", "1900", "--fps", "600", "--set", "jelly.0.resolution=[2,2,2]",
                "--quiet", "--out", f"{name}.usdc"]
        assert cli.main(argv) == 0
    assert (tmp_path / "a.usdc").read_bytes() == (tmp_path / "b.usdc").read_bytes()


def test_full_disk_keeps_the_previous_output(tmp_path):
    """A real write limit (RLIMIT_FSIZE: writes past it fail with EFBIG, as on a full disk): a one-line
    error naming the file, exit 2, and the previous output unchanged."""
    assert cli.main(["run", "jelly_drop", "--frames", "2", *SMALL, "--out", str(tmp_path / "out.usdc")]) == 0
    good = (tmp_path / "out.usdc").read_bytes()

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (len(good) + 4096, len(good) + 4096))

    proc = subprocess.run(
        [sys.executable, "-m", "softsim_warp", "run", "jelly_drop", "--frames", "600", "--quiet", "--out", "out.usdc",
         "--set", "jelly.0.resolution=[6,6,6]"],
        cwd=tmp_path, capture_output=True, text=True, preexec_fn=limit, timeout=600,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: ") and "out.usdc" in lines[0], proc.stderr
    assert (tmp_path / "out.usdc").read_bytes() == good
    assert not list(tmp_path.glob(".*partial-*"))


def test_interrupted_compare_says_so(tmp_path):
    """SIGINT during `softsim compare`: exit 130, and its summary lines say interrupted, not complete."""
    text = _interrupted(tmp_path, "compare", "--integrators", "euler,symplectic", "--out", "c.usdc").decode(
        errors="replace"
    )
    assert "jelly_drop [euler]: euler, interrupted" in text and "complete" not in text, text
    assert "INTERRUPTED: jelly_drop: 2 copies" in text, text
