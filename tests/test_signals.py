"""SIGINT and SIGTERM at every phase of ``softsim run``, with real processes and real signals.

Each test starts ``python -m softsim_warp run`` on a tiny jelly with ``SOFTSIM_TEST_PAUSE=<phase>``
and the test-only hooks of ``tests/hooks/sitecustomize.py`` loaded (``tests/subprocess_hooks.py``):
at that phase the process writes ``softsim-test: paused at <phase>`` to stderr and waits for a
signal. The test sends it and checks that the run ends with 128 + signum, prints no traceback,
leaves no hidden temporary (``.<stem>.partial-<pid><suffix>``) or lock file (``.<name>.lock``),
keeps outputs that existed unchanged unless the run had completed, and leaves what the phase
promises: nothing before the first frame, the frames written (as ``<stem>.partial<suffix>`` next to
an existing output) after.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from tests.subprocess_hooks import hooked_env

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

FRAMES = 20
ARGS = ["run", "jelly_drop", "--set", "jelly.0.resolution=[3,3,3]", "--frames", str(FRAMES),
        "--out", "out.usdc", "--metrics", "m.json", "--preview", "p.gif"]
OUTPUTS = ("out.usdc", "m.json", "p.gif")
TIMEOUT = 180  # seconds to reach a phase; generous for a cold kernel cache on a busy machine
SIGNALS = pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])


class Run:
    """A ``softsim run`` subprocess in ``cwd`` whose stderr is read continuously."""

    def __init__(self, cwd, pauses="", args=ARGS):
        env = hooked_env(pauses=pauses)
        self.proc = subprocess.Popen([sys.executable, "-m", "softsim_warp", *args], cwd=cwd, env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self.err = b""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for chunk in iter(lambda: self.proc.stderr.read1(4096), b""):
            self.err += chunk

    @property
    def stderr(self) -> str:
        return self.err.decode(errors="replace")

    def wait_until(self, ready, what):
        deadline = time.monotonic() + TIMEOUT
        while not ready():
            if self.proc.poll() is not None:
                self._reader.join(timeout=5)
                pytest.fail(f"run ended with {self.proc.returncode} before {what}:\n{self.stderr}")
            if time.monotonic() > deadline:
                self.proc.kill()
                pytest.fail(f"no {what} within {TIMEOUT} s:\n{self.stderr}")
            time.sleep(0.002)

    def wait_for(self, phase):
        marker = f"softsim-test: paused at {phase}\n".encode()
        self.wait_until(lambda: marker in self.err, f"pause at {phase}")

    def send(self, sig):
        self.proc.send_signal(sig)

    def finish(self, timeout=60) -> int:
        code = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=5)
        return code


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """The outputs of a complete run, as bytes: what a directory holds before a run replaces it."""
    d = tmp_path_factory.mktemp("good")
    run = Run(d)
    assert run.finish(timeout=TIMEOUT) == 0, run.stderr
    return {name: (d / name).read_bytes() for name in OUTPUTS}


def _place(tmp_path, good):
    for name, data in good.items():
        (tmp_path / name).write_bytes(data)


def _usd(path):
    """(status, frame count) of a USD written by softsim run."""
    from pxr import Usd, UsdGeom  # noqa: PLC0415

    stage = Usd.Stage.Open(str(path))
    assert stage is not None, f"{path} does not open"
    attr = UsdGeom.Points(stage.GetPrimAtPath("/World/Jelly_0/Particles")).GetPointsAttr()
    times = attr.GetTimeSamples()
    assert times == [float(k) for k in range(len(times))]
    data = stage.GetRootLayer().customLayerData
    assert data["softsim:frames"] == len(times)
    return data["softsim:status"], len(times)


def _check_clean(tmp_path, run, code, sig):
    assert code == 128 + sig, run.stderr
    assert "Traceback" not in run.stderr, run.stderr
    hidden = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert hidden == [], f"temporaries or locks left behind: {hidden}"


def _check_frames(tmp_path, existed, good, frames):
    """An interrupted run's ``frames`` frames: at the outputs' paths, or beside them when they existed."""
    usd, metrics = ("out.partial.usdc", "m.partial.json") if existed else ("out.usdc", "m.json")
    assert _usd(tmp_path / usd) == ("interrupted", frames)
    summary = json.loads((tmp_path / metrics).read_text())["summary"]
    assert summary["interrupted"] is True and summary["frames"] == frames
    expected = {usd, metrics} | (set(good) if existed else set())
    assert {p.name for p in tmp_path.iterdir()} == expected


def _check_unchanged(tmp_path, existed, good):
    for name, data in good.items():
        if existed:
            assert (tmp_path / name).read_bytes() == data, f"{name} changed"


# Which phases run next to outputs that exist (from an earlier complete run): both kinds are covered.
PHASES = [("import", True), ("start", False), ("scene", True), ("build", False), ("writer", True), ("compile", False),
          ("compile", True), ("run", True), ("run", False), ("save", True), ("preview", True)]


@SIGNALS
@pytest.mark.parametrize("phase,existed", PHASES, ids=[f"{p}-{'existing' if e else 'new'}" for p, e in PHASES])
def test_signal_at_phase(phase, existed, sig, tmp_path, good):
    if existed:
        _place(tmp_path, good)
    run = Run(tmp_path, phase)
    run.wait_for(phase)
    run.send(sig)
    _check_clean(tmp_path, run, run.finish(), sig)
    if phase in ("import", "start", "scene", "build", "writer"):
        # Before the first frame: no output at all, existing ones untouched.
        _check_unchanged(tmp_path, existed, good)
        assert {p.name for p in tmp_path.iterdir()} == (set(good) if existed else set())
    elif phase == "compile":
        # During kernel compilation: frame 0 is written first (docs/ROBUSTNESS.md).
        _check_unchanged(tmp_path, existed, good)
        _check_frames(tmp_path, existed, good, 1)
    elif phase == "run":
        # Paused after frame 2: frames 0..2, and the run stops there.
        _check_unchanged(tmp_path, existed, good)
        _check_frames(tmp_path, existed, good, 3)
    else:
        # After the last frame: the outputs are complete and in place; the GIF is not rendered (or
        # not finished), an existing one stays as it was.
        assert _usd(tmp_path / "out.usdc") == ("complete", FRAMES + 1)
        assert json.loads((tmp_path / "m.json").read_text())["summary"]["frames"] == FRAMES + 1
        assert (tmp_path / "p.gif").read_bytes() == good["p.gif"]
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(OUTPUTS)
        if phase == "save":
            assert f"{signal.Signals(sig).name} came after the last frame" in run.stderr


@pytest.mark.parametrize("first,second", [(signal.SIGINT, signal.SIGTERM), (signal.SIGTERM, signal.SIGINT)],
                         ids=["INT-then-TERM", "TERM-then-INT"])
def test_second_signal_while_closing(first, second, tmp_path, good):
    """The first signal stops the run after frame 2; a second one while the outputs are being closed
    is only recorded: the frames are kept whole, nothing temporary is left, the first signal's code."""
    _place(tmp_path, good)
    run = Run(tmp_path, "run,save")
    run.wait_for("run")
    run.send(first)
    run.wait_for("save")
    run.send(second)
    _check_clean(tmp_path, run, run.finish(), first)
    _check_unchanged(tmp_path, True, good)
    _check_frames(tmp_path, True, good, 3)


@SIGNALS
def test_signal_during_cleanup_after_stop_now(sig, tmp_path, good):
    """Two SIGINTs stop the run at once (outside the steps, so through the cleanup path, which keeps
    the frames written); a third signal during that cleanup changes nothing."""
    _place(tmp_path, good)
    run = Run(tmp_path, "run:2,cleanup")
    run.wait_for("run")
    run.send(signal.SIGINT)
    time.sleep(0.05)
    run.send(signal.SIGINT)
    run.wait_for("cleanup")
    run.send(sig)
    _check_clean(tmp_path, run, run.finish(), signal.SIGINT)
    _check_unchanged(tmp_path, True, good)
    assert _usd(tmp_path / "out.partial.usdc") == ("interrupted", 3)


def test_two_signals_during_preview(tmp_path, good):
    """A signal stops the rendering at once; a second one right after does not disturb its cleanup."""
    _place(tmp_path, good)
    run = Run(tmp_path, "preview:2")
    run.wait_for("preview")
    run.send(signal.SIGTERM)
    time.sleep(0.05)  # two signals pending together are handled in signal-number order (CPython)
    run.send(signal.SIGINT)
    _check_clean(tmp_path, run, run.finish(), signal.SIGTERM)
    assert (tmp_path / "p.gif").read_bytes() == good["p.gif"]
    assert _usd(tmp_path / "out.usdc") == ("complete", FRAMES + 1)


@SIGNALS
def test_signal_while_the_gif_is_saved(sig, tmp_path, good):
    """No seam: the test watches for the GIF's temporary and signals while it is being written."""
    _place(tmp_path, good)
    args = [a if a != str(FRAMES) else "120" for a in ARGS]  # a longer clip: its GIF takes a while to save
    run = Run(tmp_path, args=args)
    # The run's summary line first: at start-up the output checks create and remove a probe of that name.
    run.wait_until(lambda: b"-> " in run.err and any(tmp_path.glob(".p.partial-*.gif")), "GIF temporary")
    run.send(sig)
    _check_clean(tmp_path, run, run.finish(), sig)
    # Unchanged, unless the save won the race with the signal (then the new GIF is whole and in place).
    assert (tmp_path / "p.gif").read_bytes() == good["p.gif"] or "frames -> " in run.stderr
    assert _usd(tmp_path / "out.usdc") == ("complete", 121)


# SIGHUP (the terminal was closed) is a stop signal like SIGTERM: exit 129, the frames kept and marked.
HUP_PHASES = [("import", False), ("start", True), ("scene", False), ("compile", True), ("run", True), ("run", False),
              ("save", True)]


@pytest.mark.parametrize("phase,existed", HUP_PHASES, ids=[f"{p}-{'existing' if e else 'new'}" for p, e in HUP_PHASES])
def test_sighup_at_phase(phase, existed, tmp_path, good):
    test_signal_at_phase(phase, existed, signal.SIGHUP, tmp_path, good)


def _terminal_run(args, cwd, pauses="", controlling=False):
    sys.path.insert(0, os.path.dirname(__file__))
    from terminal import TerminalRun  # noqa: PLC0415

    env = hooked_env(pauses=pauses)
    return TerminalRun([sys.executable, "-m", "softsim_warp", *args], cwd, env=env, controlling=controlling)


def _wait(run, ready, what):
    deadline = time.monotonic() + TIMEOUT
    while not ready():
        if run.proc.poll() is not None or time.monotonic() > deadline:
            run.proc.kill()
            pytest.fail(f"no {what}:\n{run.text}")
        time.sleep(0.01)


def test_terminal_closed_keeps_frames(tmp_path, good):
    """The run's controlling terminal is closed (a real hang-up, not a signal sent by the test): the
    kernel sends SIGHUP and every later write to the terminal fails with EIO. The run still stops
    after the frame in progress, keeps frames 0..2 marked interrupted beside the existing outputs,
    leaves no temporary or lock, and exits with 129."""
    _place(tmp_path, good)
    run = _terminal_run(ARGS, tmp_path, "run", controlling=True)
    _wait(run, lambda: b"softsim-test: paused at run" in run.out, "pause at run")
    run.hang_up()
    code = run.finish()
    assert code == 128 + signal.SIGHUP
    assert hidden_files(tmp_path) == []
    _check_unchanged(tmp_path, True, good)
    _check_frames(tmp_path, True, good, 3)


def hidden_files(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.startswith("."))


def test_sighup_stops_compare(tmp_path):
    """compare (its own handler, common.Signals): SIGHUP stops after the frame in progress, 129, the
    frames kept and marked interrupted."""
    import re  # noqa: PLC0415

    run = _terminal_run(["compare", "jelly_drop", "--integrators", "euler,symplectic", "--frames", "100000",
                         "--no-graph", "--out", "c.usdc"], tmp_path)

    def frames_done():
        counts = re.findall(rb"(\d+)/100001", run.out)
        return int(counts[-1]) if counts else 0

    _wait(run, lambda: frames_done() >= 3, "3 frames")
    run.proc.send_signal(signal.SIGHUP)
    assert run.finish() == 128 + signal.SIGHUP, run.text
    assert "Traceback" not in run.text
    from pxr import Usd  # noqa: PLC0415

    stage = Usd.Stage.Open(str(tmp_path / "c.usdc"))
    assert stage.GetRootLayer().customLayerData["softsim:status"] == "interrupted"
    assert hidden_files(tmp_path) == []


@pytest.mark.parametrize("args", [["scenes"], ["preview", "x.usdc", "--png", "x.png"],
                                  ["bench", "--sizes", "2"], ["accuracy", "jelly_drop"], ["stability", "jelly_drop"],
                                  ["sweep", "jelly_drop", "--vary", "jelly.0.particle_mass=0.01,0.02"]],
                         ids=lambda a: a[0])
def test_sighup_in_every_command(args, tmp_path):
    """Every command ends with 129 on SIGHUP (cli.main's handler), quietly and leaving nothing."""
    run = Run(tmp_path, "start", args=args)
    run.wait_for("start")
    run.send(signal.SIGHUP)
    _check_clean(tmp_path, run, run.finish(), signal.SIGHUP)
    assert list(tmp_path.iterdir()) == []


def test_nohup_keeps_ignoring_sighup(tmp_path):
    """Started with SIGHUP ignored (``nohup``), a run outlives its terminal: SIGHUP changes nothing,
    and the SIGTERM sent after it is the signal that stops the run (143, frames 0..2 kept)."""
    env = hooked_env(pauses="run")
    proc = subprocess.Popen([sys.executable, "-m", "softsim_warp", *ARGS], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    err = b""
    while b"softsim-test: paused at run" not in err:
        chunk = proc.stderr.read1(4096)
        assert chunk, err.decode(errors="replace")
        err += chunk
    proc.send_signal(signal.SIGHUP)
    time.sleep(0.5)
    assert proc.poll() is None
    proc.send_signal(signal.SIGTERM)
    err += proc.stderr.read()
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM, err.decode(errors="replace")
    assert _usd(tmp_path / "out.usdc") == ("interrupted", 3)


def test_sighup_with_the_terminal_still_there(tmp_path):
    """``kill -HUP`` while the terminal lives: the run stops as for SIGTERM and its closing lines
    still reach the terminal (only a hung-up terminal is swapped for /dev/null)."""
    run = _terminal_run(ARGS, tmp_path, "run")
    _wait(run, lambda: b"softsim-test: paused at run" in run.out, "pause at run")
    run.proc.send_signal(signal.SIGHUP)
    assert run.finish() == 128 + signal.SIGHUP, run.text
    assert "3 frames" in run.text and "-> " in run.text, run.text
    assert _usd(tmp_path / "out.usdc") == ("interrupted", 3)
