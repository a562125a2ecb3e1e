"""The process and its surroundings misused: empty and over-long paths, a full disk at the
lock, special files as outputs, an unusable Warp kernel cache, a deleted working directory, a
failing standard output, progress bars in log files, Warp's start-up text, USD's own diagnostics,
symlinked mesh assets and a byte-order mark.

Process-level promises (exit codes, what reaches stderr, what is left on disk) are checked on real
``softsim`` processes; the rest in-process through ``cli.main``. SIGHUP is in tests/test_signals.py.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from softsim_warp.commands import cli
from softsim_warp.core.errors import CommandLineError, SceneError
from softsim_warp.core.mesh_assets import load_mesh
from softsim_warp.io import outputs as outputs_mod
from softsim_warp.io.scene import read_scene_data

sys.path.insert(0, os.path.dirname(__file__))
import robustness_cases as rc  # noqa: E402
from terminal import TerminalRun  # noqa: E402

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX processes and files")

SOFTSIM = [sys.executable, "-m", "softsim_warp"]
TINY = ["--set", "jelly.0.resolution=[3,3,3]", "--frames", "2"]
ASSETS = Path(__file__).resolve().parents[1] / "scenes" / "assets"
SIM = '[simulation]\nintegrator = "symplectic"\ndt = 1e-3\nframes = 2\nfps = 30\n'
SPRINGS = "springs.structural = { ks = 50.0, kd = 0.1 }\n"
PLANE = "[[plane]]\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 1.0, 0.0]\n"


def softsim(args, cwd, env=None, timeout=300, **kw):
    """A real ``softsim`` process; returns the CompletedProcess (text)."""
    return subprocess.run([*SOFTSIM, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, **kw)


def one_error_line(stderr: str, *needles) -> str:
    """stderr is exactly one ``error: <file>: <key>: <what> (got <value>)`` line holding every needle."""
    lines = stderr.strip().splitlines()
    assert "Traceback" not in stderr, stderr
    assert len(lines) == 1, f"expected one line on stderr, got:\n{stderr}"
    assert rc.LINE.match(lines[0]), lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def in_process(argv, cwd):
    """``cli.main(argv)`` in ``cwd`` with descriptor 2 captured; returns (exit code, stderr)."""
    old = os.getcwd()
    os.chdir(cwd)
    try:
        with rc._captured_stderr() as err:
            code = cli.main(argv)
    finally:
        os.chdir(old)
    return code, err[0]


def hidden(directory) -> list:
    return sorted(p.name for p in Path(directory).iterdir() if p.name.startswith("."))


def _jelly_scene(tmp_path, mesh, name="mj.toml"):
    scene = tmp_path / name
    scene.write_text(SIM + f'[[jelly]]\nmesh = "{mesh}"\nresolution = 4\ncenter = [0.0, 0.5, 0.0]\n'
                     "total_mass = 0.1\n" + SPRINGS + PLANE)
    return scene


# --- empty paths ------------------------------------------------------------------------------------

EMPTY = [
    ("run", ["run", "jelly_drop", *TINY, "--out", ""], "--out"),
    ("run-metrics", ["run", "jelly_drop", *TINY, "--metrics", ""], "--metrics"),
    ("run-preview", ["run", "jelly_drop", *TINY, "--preview", ""], "--preview"),
    ("run-scene", ["run", ""], "scene"),
    ("compare", ["compare", "jelly_drop", "--out", ""], "--out"),
    ("compare-metrics", ["compare", "jelly_drop", "--metrics", ""], "--metrics"),
    ("compare-plot", ["compare", "jelly_drop", "--plot", ""], "--plot"),
    ("preview-usd", ["preview", "", "--png", "a.png"], "usd"),
    ("preview-png", ["preview", "jelly_drop.usdc", "--png", ""], "--png"),
    ("preview-gif", ["preview", "jelly_drop.usdc", "--gif", ""], "--gif"),
    ("accuracy", ["accuracy", "jelly_drop", "--out", ""], "--out"),
    ("accuracy-plot", ["accuracy", "jelly_drop", "--plot", ""], "--plot"),
    ("stability", ["stability", "jelly_drop", "--out", ""], "--out"),
    ("stability-plot", ["stability", "jelly_drop", "--plot", ""], "--plot"),
    ("bench", ["bench", "--out", ""], "--out"),
    ("bench-plot", ["bench", "--plot", ""], "--plot"),
    ("bench-scene", ["bench", "--scene", ""], "--scene"),
    ("sweep", ["sweep", "jelly_drop", "--out", ""], "--out"),
    ("sweep-plot", ["sweep", "jelly_drop", "--plot", ""], "--plot"),
]


@pytest.mark.parametrize("argv,flag", [e[1:] for e in EMPTY], ids=[e[0] for e in EMPTY])
def test_empty_path_is_an_error(argv, flag, tmp_path):
    """An empty path (an unset shell variable) is one line, exit 2, never the default name: the files
    of the default names that exist stay as they were and nothing is added."""
    defaults = ("jelly_drop.usdc", "jelly_drop_compare.usdc", "jelly_drop_sweep.parquet")
    for name in defaults:
        (tmp_path / name).write_bytes(b"an earlier result\n")
    code, err = in_process(argv, tmp_path)
    assert code == 2
    one_error_line(err, f"command line: {flag}: is empty; give ", "(got '')")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(defaults)
    assert all((tmp_path / name).read_bytes() == b"an earlier result\n" for name in defaults)


def test_empty_path_real_process(tmp_path):
    (tmp_path / "jelly_drop.usdc").write_bytes(b"keep\n")
    proc = softsim(["run", "jelly_drop", *TINY, "--out", ""], tmp_path)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "--out: is empty")
    assert (tmp_path / "jelly_drop.usdc").read_bytes() == b"keep\n"


def test_check_writable_refuses_empty():
    """The output check itself refuses an empty path (for callers other than the command line)."""
    with pytest.raises(CommandLineError, match="is empty"):
        outputs_mod.check_writable("", "--out")


# --- a full disk at the lock ------------------------------------------------------------------------

# os.write fails with ENOSPC on the lock file named by FAIL_LOCK only: the disk fills up just as the
# command writes its pid into that lock (the outputs locked before it are released again).
ENOSPC_AT_LOCK = """
import errno, os, sys
real_write = os.write
def write(fd, data):
    try:
        name = os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        name = ""
    if os.path.basename(name) == os.environ["FAIL_LOCK"]:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return real_write(fd, data)
os.write = write
from softsim_warp.__main__ import entry
sys.argv[0] = "softsim"
sys.exit(entry())
"""


@pytest.fixture(scope="module")
def small_usd(tmp_path_factory):
    d = tmp_path_factory.mktemp("usd")
    proc = softsim(["run", "jelly_drop", *TINY, "--out", "in.usdc", "--quiet"], d)
    assert proc.returncode == 0, proc.stderr
    return d / "in.usdc"


LOCKED = [
    ("run", ["run", "jelly_drop", *TINY, "--out", "o.usdc"], "o.usdc"),
    ("run-metrics", ["run", "jelly_drop", *TINY, "--out", "o.usdc", "--metrics", "m.json"], "m.json"),
    ("run-preview", ["run", "jelly_drop", *TINY, "--out", "o.usdc", "--preview", "p.gif"], "p.gif"),
    ("compare", ["compare", "jelly_drop", "--integrators", "euler", "--frames", "2", "--out", "c.usdc"], "c.usdc"),
    ("preview-png", ["preview", "{usd}", "--png", "f.png"], "f.png"),
    ("preview-gif", ["preview", "{usd}", "--gif", "f.gif"], "f.gif"),
    ("accuracy", ["accuracy", "jelly_drop", "--integrators", "euler", "--dts", "1e-3", "--duration", "0.01",
                  "--out", "a.json"], "a.json"),
    ("sweep", ["sweep", "jelly_drop", "--vary", "jelly.0.springs.structural.ks=100,200", "--duration", "0.01",
               "--workers", "1", "--out", "s.csv"], "s.csv"),
]


@pytest.mark.parametrize("argv,output", [c[1:] for c in LOCKED], ids=[c[0] for c in LOCKED])
def test_full_disk_at_the_lock(argv, output, tmp_path, small_usd):
    """ENOSPC while writing the pid into the lock: one line naming the lock file, exit 2, before any
    work; no lock file and no temporary left, an existing output unchanged."""
    (tmp_path / output).write_bytes(b"the previous output\n")
    argv = [a.replace("{usd}", str(small_usd)) for a in argv]
    proc = subprocess.run([sys.executable, "-c", ENOSPC_AT_LOCK, *argv, "--quiet"], cwd=tmp_path,
                          env={**os.environ, "FAIL_LOCK": f".{output}.lock"}, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 2, proc.stderr
    one_error_line(proc.stderr, "cannot write the lock file", f".{output}.lock", "No space left on device")
    assert hidden(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == [output]
    assert (tmp_path / output).read_bytes() == b"the previous output\n"


def test_lock_write_error_in_process(tmp_path, monkeypatch):
    """Any OSError writing the lock (EIO here) is the same refusal, and the lock is released."""
    real_write = os.write

    def write(fd, data):
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".lock"):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return real_write(fd, data)

    outs = outputs_mod.Outputs()
    outs.add("--out", tmp_path / "x.usda", outputs_mod.USD_SUFFIXES)
    monkeypatch.setattr(os, "write", write)
    with pytest.raises(CommandLineError, match="cannot write the lock file .*Input/output error"):
        with outs:
            pass
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
    with outs:  # nothing held: the same outputs lock at once
        assert hidden(tmp_path) == [".x.usda.lock"]
    assert list(tmp_path.iterdir()) == []


# --- names too long ---------------------------------------------------------------------------------


@pytest.mark.parametrize("argv,needle", [
    (["--out", "a" * 300 + ".usdc"], "--out: name too long: file name is 305 bytes; at most 227"),
    # 240 bytes fit the file system, but not the temporaries beside the file
    (["--out", "b" * 235 + ".usdc"], "--out: name too long: file name is 240 bytes"),
    (["--metrics", "c" * 300 + "/m.json"], "--metrics: name too long: a directory name"),
    (["--preview", "d" * 256 + ".gif"], "--preview: name too long"),
], ids=["file", "file-with-temporary", "directory", "preview"])
def test_name_too_long(argv, needle, tmp_path):
    code, err = in_process(["run", "jelly_drop", *TINY, *argv], tmp_path)
    assert code == 2
    one_error_line(err, needle)
    assert list(tmp_path.iterdir()) == []


def test_longest_name_that_fits_is_written(tmp_path):
    """The bound is exact: a 227-byte name is written, and the longest name derived from it (the
    temporary of its kept <stem>.partial<ext>, with a 10-digit pid) is 255 bytes, which the file system takes."""
    name = "e" * 222 + ".usda"
    longest = tmp_path / f".{name[:-5]}.partial.partial-{'9' * 10}.usda"
    assert len(longest.name) == 255
    longest.write_bytes(b"")
    longest.unlink()
    code, err = in_process(["run", "jelly_drop", *TINY, "--out", name, "--quiet"], tmp_path)
    assert code == 0, err
    assert (tmp_path / name).is_file()


def test_asset_name_too_long(tmp_path):
    """A mesh asset path with a component over 255 bytes: one line naming the key, exit 2."""
    scene = _jelly_scene(tmp_path, "f" * 300 + ".usda")
    code, err = in_process(["run", str(scene), "--out", "o.usda"], tmp_path)
    assert code == 2
    one_error_line(err, "mj.toml: jelly.0.mesh: cannot read the file: File name too long")


def test_name_too_long_real_process(tmp_path):
    proc = softsim(["run", "jelly_drop", *TINY, "--out", "g" * 300 + ".usdc"], tmp_path)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "name too long")


# --- special files as outputs -----------------------------------------------------------------------


def test_usd_to_stdout_pipe_names_the_cause(tmp_path):
    """--out /dev/stdout on a pipe: the USD format follows from the extension, which a pipe lacks."""
    proc = softsim(["run", "jelly_drop", *TINY, "--out", "/dev/stdout"], tmp_path)
    assert proc.returncode == 2
    line = one_error_line(proc.stderr, "--out: is a pipe or FIFO, not a regular file path (unsupported file extension);",
                          "give a .usdc/.usda/.usd file path")
    assert "/proc" not in line
    assert list(tmp_path.iterdir()) == []


def test_usd_to_stdout_terminal_names_the_cause(tmp_path):
    run = TerminalRun([*SOFTSIM, "run", "jelly_drop", *TINY, "--out", "/dev/stdout"], tmp_path, stdout=True)
    assert run.finish(timeout=300) == 2
    assert "--out: is a character device, not a regular file path (unsupported file extension)" in run.text, run.text
    assert "Traceback" not in run.text


def test_metrics_streamed_to_stdout_pipe(tmp_path):
    """JSON's format does not follow from a name: --metrics /dev/stdout on a pipe streams the metrics."""
    proc = softsim(["run", "jelly_drop", *TINY, "--out", "o.usda", "--metrics", "/dev/stdout", "--quiet"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)["summary"]
    assert summary["frames"] == 3 and summary["status"] == "complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.usda"]


def test_target_of_a_magic_link():
    """/proc/self/fd/N of a pipe reads 'pipe:[inode]', which is no path: the link itself is the target."""
    r, w = os.pipe()
    try:
        link = f"/proc/self/fd/{w}"
        assert outputs_mod.target_of(link) == Path(link)
        assert outputs_mod.is_stream(link)
    finally:
        os.close(r)
        os.close(w)


# --- the Warp kernel cache --------------------------------------------------------------------------


def _env(**changes):
    env = dict(os.environ)
    env.pop("WARP_CACHE_PATH", None)
    env.update(changes)
    return env


def _warp_version():
    import warp  # noqa: PLC0415

    return warp.config.version


@pytest.mark.parametrize("command", [
    ["run", "jelly_drop", *TINY, "--out", "o.usdc"],
    ["compare", "jelly_drop", "--integrators", "euler", "--frames", "2", "--out", "c.usdc"],
    ["bench", "--sizes", "2", "--steps", "1", "--repeats", "1", "--integrators", "euler"],
    ["accuracy", "jelly_drop", "--integrators", "euler", "--dts", "1e-3", "--duration", "0.01"],
    ["stability", "jelly_drop", "--integrators", "euler", "--ks", "none"],
    ["sweep", "jelly_drop", "--vary", "jelly.0.springs.structural.ks=100,200", "--duration", "0.01", "--workers", "1"],
], ids=["run", "compare", "bench", "accuracy", "stability", "sweep"])
def test_kernel_cache_home_unusable(command, tmp_path):
    """HOME=/proc: Warp's default cache (~/.cache/warp/<version>) cannot be made; every command that
    simulates says so in one line naming the directory and WARP_CACHE_PATH, exit 2, nothing written."""
    proc = softsim(command, tmp_path, env=_env(HOME="/proc"))
    assert proc.returncode == 2, proc.stderr
    one_error_line(proc.stderr, "environment: WARP_CACHE_PATH: cannot use '/proc/.cache/warp/",
                   "set WARP_CACHE_PATH to a writable directory", "(got nothing)")
    assert proc.stdout == ""
    assert list(tmp_path.iterdir()) == []


def test_kernel_cache_path_is_a_file(tmp_path):
    (tmp_path / "afile").write_text("not a directory\n")
    proc = softsim(["run", "jelly_drop", *TINY, "--out", "o.usdc"], tmp_path, env=_env(WARP_CACHE_PATH="afile"))
    assert proc.returncode == 2
    one_error_line(proc.stderr, "WARP_CACHE_PATH: cannot use", "afile/", "Not a directory", "(got 'afile')")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def _read_only(directory, command):
    """``command`` run with ``directory`` read-only: a read-only bind mount in a user and mount
    namespace of its own (root ignores permission bits), else mode 0555 for a user who is not root."""
    unshare = shutil.which("unshare")
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && shift && exec "$@"'
    wrap = [unshare, "-rm", "sh", "-c", script, "sh", str(directory)]
    if unshare and subprocess.run([*wrap, "true"], capture_output=True).returncode == 0:
        return [*wrap, *command], None
    if os.geteuid() != 0:
        directory.chmod(0o555)
        return command, "Permission denied"
    pytest.skip("no way to make a directory read-only for root here (no unshare)")


def test_kernel_cache_read_only(tmp_path):
    """WARP_CACHE_PATH whose versioned directory exists but cannot be written: one line, before any work."""
    cache = tmp_path / "cache"
    versioned = cache / _warp_version()
    versioned.mkdir(parents=True)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    command, why = _read_only(versioned, [*SOFTSIM, "run", "jelly_drop", *TINY, "--out", str(out_dir / "o.usdc")])
    proc = subprocess.run(command, cwd=out_dir, env=_env(WARP_CACHE_PATH=str(cache)), capture_output=True, text=True,
                          timeout=300)
    versioned.chmod(0o755)
    assert proc.returncode == 2, proc.stderr
    why = why or "Read-only file system"
    line = one_error_line(proc.stderr, f"cannot use '{versioned}' as Warp's kernel cache: {why};", f"(got '{cache}')")
    assert ".softsim-probe" not in line
    assert list(out_dir.iterdir()) == [] and list(versioned.iterdir()) == []


# --- a deleted working directory --------------------------------------------------------------------


def _in_deleted_directory(tmp_path, args):
    """``softsim args`` started in a directory removed just before (the shell's ``cd d; rmdir ../d``)."""
    d = tmp_path / "gone"
    d.mkdir()
    script = 'cd "$1" && rmdir "$1" && shift && exec "$@"'
    return subprocess.run(["sh", "-c", script, "sh", str(d), *SOFTSIM, *args], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("args,flag", [
    (["run", "jelly_drop", *TINY], "--out"),  # the default output, jelly_drop.usdc, is relative
    (["run", "jelly_drop", *TINY, "--out", "{tmp}/o.usdc", "--metrics", "m.json"], "--metrics"),
    (["run", "scene.toml"], "scene"),
    (["compare", "jelly_drop", "--integrators", "euler", "--frames", "2"], "--out"),
], ids=["run-default-out", "run-metrics", "run-scene-file", "compare"])
def test_deleted_cwd_relative_paths(args, flag, tmp_path):
    proc = _in_deleted_directory(tmp_path, [a.replace("{tmp}", str(tmp_path)) for a in args])
    assert proc.returncode == 2
    one_error_line(proc.stderr, f": {flag}: is a relative path and the current directory no longer exists")


def test_deleted_cwd_absolute_paths_work(tmp_path):
    out = tmp_path / "o.usda"
    proc = _in_deleted_directory(tmp_path, ["run", "jelly_drop", *TINY, "--out", str(out), "--quiet"])
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert out.is_file()


# --- standard output failing ------------------------------------------------------------------------

STDOUT_COMMANDS = [
    ["scenes"],
    ["bench", "--sizes", "2", "--steps", "1", "--repeats", "1", "--integrators", "euler", "--quiet"],
]


@pytest.mark.parametrize("args", STDOUT_COMMANDS, ids=["scenes", "bench"])
def test_stdout_broken_pipe_is_quiet(args, tmp_path):
    """The reader is gone (``| head -c 10`` having read its bytes): no traceback, nothing on stderr,
    status 141 (128 + SIGPIPE), as a Unix tool killed by SIGPIPE reports to ``set -o pipefail``."""
    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([*SOFTSIM, *args], cwd=tmp_path, stdout=w, stderr=subprocess.PIPE, text=True,
                              timeout=300)
    finally:
        os.close(w)
    assert proc.returncode == 128 + signal.SIGPIPE, proc.stderr
    assert proc.stderr == ""


def test_stdout_pipe_closed_by_head(tmp_path):
    """The shell's own pipeline: bench prints its table, head keeps 10 bytes; a quiet end either way
    (0 when the table fit the pipe before head left, else 141)."""
    cmd = " ".join([*SOFTSIM, *STDOUT_COMMANDS[1]]) + " | head -c 10; echo \" ${PIPESTATUS[0]}\""
    proc = subprocess.run(["bash", "-c", cmd], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.stderr == ""
    assert proc.stdout.split()[-1] in ("0", "141"), proc.stdout
    assert len(proc.stdout.rsplit(" ", 1)[0]) == 10


@pytest.mark.parametrize("args", STDOUT_COMMANDS, ids=["scenes", "bench"])
def test_stdout_full(args, tmp_path):
    with open("/dev/full", "w") as full:
        proc = subprocess.run([*SOFTSIM, *args], cwd=tmp_path, stdout=full, stderr=subprocess.PIPE, text=True,
                              timeout=300)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "command line: stdout: cannot write to standard output: No space left on device",
                   "(got '/dev/full')")


def test_stdout_closed(tmp_path):
    """``softsim scenes >&-``: an error, not exit 0 with nothing printed."""
    proc = subprocess.run(["sh", "-c", 'exec "$@" >&-', "sh", *SOFTSIM, "scenes"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "stdout: standard output is closed")


def test_stdout_closed_does_not_capture_files(tmp_path):
    """With stdout closed, descriptor 1 stays taken (by /dev/null): the run's files cannot land on it,
    and a run that prints nothing on stdout works."""
    proc = subprocess.run(["sh", "-c", 'exec "$@" >&-', "sh", *SOFTSIM, "run", "jelly_drop", *TINY, "--out", "o.usda",
                           "--metrics", "m.json"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "m.json").read_text())["summary"]["status"] == "complete"
    assert (tmp_path / "o.usda").read_text().startswith("#usda 1.0")


# --- progress bars only on a terminal ---------------------------------------------------------------


@pytest.mark.parametrize("command", [
    ["run", "jelly_drop", "--frames", "30", "--out", "o.usda"],
    ["compare", "jelly_drop", "--integrators", "euler,symplectic", "--frames", "30", "--out", "c.usda"],
], ids=["run", "compare"])
def test_progress_bar_only_on_a_terminal(command, tmp_path):
    """stderr to a log file gets the summary lines, not the bar's redraws; a terminal gets the bar."""
    with open(tmp_path / "log.txt", "w") as log:
        proc = subprocess.run([*SOFTSIM, *command], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=log, timeout=300)
    assert proc.returncode == 0
    text = (tmp_path / "log.txt").read_text()
    assert "\r" not in text and "/31" not in text and "frame/s" not in text, text
    run = TerminalRun([*SOFTSIM, *command], tmp_path)
    assert run.finish(timeout=300) == 0, run.text
    assert "/31" in run.text, run.text


def test_progress_bar_helper_follows_the_terminal(monkeypatch):
    """One helper (common.progress_bar) decides for every command: disabled off a terminal."""
    from softsim_warp.commands import common  # noqa: PLC0415

    with open(os.devnull, "w") as null:
        monkeypatch.setattr(sys, "stderr", null)
        bar = common.progress_bar(10, "x", "frame")
        assert bar.disable
        bar.update(1)
        bar.close()
    assert common.progress_bar(10, "x", quiet=True) is None


# --- Warp's start-up text -----------------------------------------------------------------------------


@pytest.mark.parametrize("args,needle", [
    (["--quiet", "--out", "nodir/x.json"], "--out: directory 'nodir' does not exist"),
    (["--device", "cuda:7"], "--device: device not available here"),
    (["--sizes", "1"], "--sizes: each size must be at least 2"),
], ids=["out", "device", "sizes"])
def test_bench_error_is_one_line(args, needle, tmp_path):
    """No banner on stdout, no CUDA driver notice on stderr: the error line alone."""
    proc = softsim(["bench", *args], tmp_path)
    assert proc.returncode == 2
    one_error_line(proc.stderr, needle)
    assert proc.stdout == ""


def test_bench_quiet_prints_only_results(tmp_path):
    proc = softsim(["bench", "--sizes", "2", "--steps", "1", "--repeats", "1", "--integrators", "euler", "--quiet"],
                   tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert "initialized" not in proc.stdout and "Kernel cache" not in proc.stdout, proc.stdout


def test_debug_shows_warp_start_up(tmp_path):
    proc = softsim(["bench", "--sizes", "1", "--debug"], tmp_path)
    assert proc.returncode == 2
    assert "Warp " in proc.stdout + proc.stderr and "initialized" in proc.stdout + proc.stderr


# --- USD diagnostics of an input asset ----------------------------------------------------------------

TETRA = ('def Mesh "Tetra" {\n point3f[] points = [(0,0,0),(0.2,0,0),(0,0.2,0),(0,0,0.2)]\n'
         " int[] faceVertexCounts = [3,3,3,3]\n int[] faceVertexIndices = [0,2,1, 0,1,3, 0,3,2, 1,2,3]\n}\n")


def _layer(path, sublayers=(), body=""):
    subs = f"(\n    subLayers = [{', '.join(f'@{s}@' for s in sublayers)}]\n)\n" if sublayers else ""
    Path(path).write_text(f"#usda 1.0\n{subs}{body}")


def test_missing_sublayer_is_one_line(tmp_path):
    _layer(tmp_path / "asset.usda", ["parts/missing.usda"], TETRA)
    scene = _jelly_scene(tmp_path, "asset.usda")
    proc = softsim(["run", str(scene), "--out", "o.usda"], tmp_path)
    assert proc.returncode == 2
    line = one_error_line(proc.stderr, "mj.toml: jelly.0.mesh: its sublayer @parts/missing.usda@", "cannot be opened",
                          "asset.usda")
    assert "Warning" not in line and "stage.cpp" not in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["asset.usda", "mj.toml"]


def test_sublayer_cycle_is_one_line(tmp_path):
    _layer(tmp_path / "a.usda", ["b.usda"], TETRA)
    _layer(tmp_path / "b.usda", ["a.usda"])
    scene = _jelly_scene(tmp_path, "a.usda")
    proc = softsim(["run", str(scene), "--out", "o.usda"], tmp_path)
    assert proc.returncode == 2
    one_error_line(proc.stderr, "jelly.0.mesh: its subLayers form a cycle")
    assert "stage.cpp" not in proc.stderr


def test_sublayers_that_resolve_load(tmp_path):
    """The same asset split over two layers that exist reads as the mesh it composes (no message)."""
    _layer(tmp_path / "top.usda", ["geo.usda"])
    _layer(tmp_path / "geo.usda", (), TETRA)
    mesh = load_mesh(tmp_path / "top.usda")
    assert mesh.points.shape == (4, 3) and mesh.triangles.shape == (4, 3)
    with pytest.raises(SceneError, match="sublayer @nothere.usda@"):
        _layer(tmp_path / "broken.usda", ["nothere.usda"], TETRA)
        load_mesh(tmp_path / "broken.usda")


def test_other_usd_diagnostic_is_one_warning_line(tmp_path):
    """A diagnostic that leaves the mesh whole (a reference elsewhere in the file that is missing)
    is one ``warning:`` line of the project's form; the run goes on."""
    _layer(tmp_path / "asset.usda", (), 'def Xform "Extra" (\n    references = @gone.usda@\n)\n{\n}\n' + TETRA)
    scene = _jelly_scene(tmp_path, "asset.usda")
    proc = softsim(["run", str(scene), "--out", "o.usda", "--quiet"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning: ")]
    assert len(warnings) == 1, proc.stderr
    assert "mj.toml: jelly.0.mesh: USD: In </Extra>: Could not open asset @gone.usda@" in warnings[0]
    assert "0x" not in warnings[0] and "stage.cpp" not in proc.stderr
    assert (tmp_path / "o.usda").is_file()


# --- symlinked mesh assets: the name given picks the format -------------------------------------------


def test_symlink_to_hash_named_usd(tmp_path):
    """``c.usda -> store/3f9a1c`` (a content store's name): read as USD, the same mesh as the file."""
    store = tmp_path / "store"
    store.mkdir()
    shutil.copyfile(ASSETS / "blob.usda", store / "3f9a1c")
    (tmp_path / "c.usda").symlink_to(Path("store") / "3f9a1c")
    direct = load_mesh(ASSETS / "blob.usda")
    linked = load_mesh(tmp_path / "c.usda")
    assert (linked.points == direct.points).all() and (linked.indices == direct.indices).all()
    code, err = in_process(["run", str(_jelly_scene(tmp_path, "c.usda")), "--out", "o.usda", "--quiet"], tmp_path)
    assert code == 0, err


def test_symlink_usd_name_to_obj_file(tmp_path):
    """``f.usda -> floor.obj``: the name says USD, so it is read as USD, and OBJ text is not USD."""
    (tmp_path / "floor.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 0 1\nf 1 2 3\n")
    (tmp_path / "f.usda").symlink_to("floor.obj")
    with pytest.raises(SceneError, match=r"cannot be read as USD"):
        load_mesh(tmp_path / "f.usda")


def test_symlink_obj_name_to_hash_named_file(tmp_path):
    pytest.importorskip("trimesh")
    (tmp_path / "9b2e").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (tmp_path / "t.obj").symlink_to("9b2e")
    mesh = load_mesh(tmp_path / "t.obj")
    assert mesh.points.shape == (4, 3) and mesh.closed


# --- a byte-order mark ----------------------------------------------------------------------------------


def test_scene_with_byte_order_mark(tmp_path):
    """A UTF-8 BOM (Windows editors) is not TOML: it is dropped, and the scene reads as without it."""
    (tmp_path / "plain.toml").write_text(rc.BASE)
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf" + rc.BASE.encode())
    assert read_scene_data(str(tmp_path / "bom.toml"))[2] == read_scene_data(str(tmp_path / "plain.toml"))[2]
    code, err = in_process(["run", "bom.toml", "--out", "o.usda", "--quiet"], tmp_path)
    assert code == 0, err


def test_byte_order_mark_inside_is_still_an_error(tmp_path):
    """Only a leading mark is dropped; one inside the text is a TOML syntax error as before."""
    (tmp_path / "s.toml").write_bytes(rc.BASE.replace("[simulation]", "\ufeff[simulation]").encode())
    code, err = in_process(["run", "s.toml", "--quiet"], tmp_path)
    assert code == 2
    one_error_line(err, "s.toml: line 4", "TOML syntax error")
