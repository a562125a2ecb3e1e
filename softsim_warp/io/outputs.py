"""Output files: checked together before any work, locked while a command runs, written atomically.

Every command declares its inputs and outputs to an :class:`Outputs` before it does any work:

* each output is probed for writability (permissions, read-only file systems, full inode tables);
* no output may be an input or another output of the same command, however it is spelled
  (symlinks, ``..``, hard links: existing files are compared by device and inode);
* while the command runs it holds an advisory lock per output (``fcntl.flock`` on a hidden
  ``.<name>.lock`` beside the file's target), so a second process writing the same file is refused
  at once instead of interleaving its results with the first's;
* leftover temporaries of killed runs for those outputs are removed.

Writing goes to a hidden temporary beside the target (``.<stem>.partial-<pid><suffix>``), which
:func:`commit` flushes to disk (``fsync``), renames over the target and makes durable by syncing
the directory: a reader sees the old file or the new one, also after a power loss. An output that
is a symlink is written through to its target; one that is not a regular file (a FIFO,
``/dev/stdout``, ``/dev/null``) is streamed into directly when the content is complete.
"""

from __future__ import annotations

import fcntl
import glob
import json
import math
import os
import stat
import tempfile
from pathlib import Path

from ..core.errors import CommandLineError

USD_SUFFIXES = (".usdc", ".usda", ".usd")
JSON_SUFFIXES = (".json",)


def target_of(path) -> Path:
    """The file ``path`` names, symlinks followed (absolute): what a write must change.

    A link that resolves to no path although it opens (``/dev/stdout`` on a pipe: ``/proc/self/fd/1``
    reads ``pipe:[N]``) is its own target: opening the name reaches the stream.
    """
    real = os.path.realpath(os.fspath(path))
    if not os.path.lexists(real) and os.path.exists(path):
        return Path(os.path.abspath(path))
    return Path(real)


def is_stream(path) -> bool:
    """Whether ``path`` exists and is not a regular file (a FIFO, a character device): written by streaming."""
    try:
        return not stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def partial_path(path) -> Path:
    """The temporary of ``path``'s target: hidden, unique per process, same extension (USD picks the
    format from it). Beside the target, so the rename stays within one file system; in the system's
    temporary directory for a stream target (``/dev/stdout`` has no writable directory)."""
    p = target_of(path)
    name = f".{p.stem}.partial-{os.getpid()}{p.suffix}"
    return Path(tempfile.gettempdir()) / name if is_stream(p) else p.with_name(name)


def kept_partial_path(path) -> Path:
    """Where a run that did not complete keeps its result when it may not replace ``path``: ``<stem>.partial<suffix>``."""
    p = target_of(path)
    return p.with_name(f"{p.stem}.partial{p.suffix}")


def _fsync_dir(directory: Path):
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def commit(tmp, path, flag="output"):
    """Move the finished temporary ``tmp`` to ``path``'s target, durably; stream it into a non-regular target.

    A full disk or quota (``ENOSPC``, ``EDQUOT``) and other write errors become a one-line
    :class:`CommandLineError` naming the file; the temporary is removed and the target keeps its
    previous content.
    """
    tmp, target = Path(tmp), target_of(path)
    try:
        if is_stream(target):
            with open(tmp, "rb") as src, open(target, "wb") as dst:
                while chunk := src.read(1 << 20):
                    dst.write(chunk)
            tmp.unlink()
            return
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, target)
        _fsync_dir(target.parent)
    except OSError as e:
        discard(tmp)
        raise CommandLineError(flag, f"cannot write '{target}': {e.strerror or e}", str(path)) from None


def discard(tmp):
    """Remove a temporary if it is there."""
    try:
        os.unlink(tmp)
    except OSError:
        pass


def save_atomic(path, save, flag="output"):
    """Write ``path`` through ``save(temporary_path)`` (``fig.savefig``, ``image.save``, ...), then
    :func:`commit` it; nothing is left on failure. The temporary keeps the extension, which picks the format."""
    tmp = partial_path(path)
    try:
        save(os.fspath(tmp))
    except OSError as e:
        discard(tmp)
        raise CommandLineError(flag, f"cannot write '{target_of(path)}': {e.strerror or e}", str(path)) from None
    except BaseException:
        discard(tmp)
        raise
    commit(tmp, path, flag)


def write_atomic(path, write, flag="output"):
    """Like :func:`save_atomic` for ``write(file)`` on a text file."""

    def save(tmp):
        with open(tmp, "w") as f:
            write(f)

    save_atomic(path, save, flag)


def strict_json(value):
    """``value`` with every non-finite float replaced by ``None`` (JSON has no NaN or Infinity)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


def write_json_atomic(path, data, flag="--metrics"):
    """Write ``data`` as strict JSON (non-finite numbers as ``null``) to ``path``, atomically."""

    def write(f):
        json.dump(strict_json(data), f, indent=1, allow_nan=False)
        f.write("\n")

    write_atomic(path, write, flag)


def save_report(data, out=None, plot_path=None, plot=None):
    """A command's report: JSON to ``out`` and ``plot(data, path)`` to ``plot_path``, each atomically, when asked."""
    if out:
        write_json_atomic(out, data, "--out")
    if plot_path:
        save_atomic(plot_path, lambda tmp: plot(data, tmp), "--plot")


NAME_MAX = 255  # bytes in one file name on Linux file systems (ext4, xfs, btrfs, tmpfs)
# What the longest name derived from an output adds to its name: the hidden temporary of the
# <stem>.partial<ext> that a run keeps beside an existing output, .<stem>.partial.partial-<pid><ext>
# (a pid has at most 10 digits).
_TEMPORARY_EXTRA = len(".") + len(".partial") + len(".partial-") + 10


def _stream_kind(path) -> str:
    mode = os.stat(path).st_mode
    for test, kind in ((stat.S_ISFIFO, "a pipe or FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return kind
    return "a special file"


def _check_name_lengths(path, flag: str):
    """Refuse a path with a name longer than the file system allows, the output's own name counting
    the names derived from it beside it (its temporary ``.<stem>.partial-<pid><ext>``, its lock, the
    ``<stem>.partial<ext>`` of a run that did not complete and that file's temporary)."""
    parts = Path(path).parts
    for i, part in enumerate(parts):
        size = len(os.fsencode(part))
        last = i == len(parts) - 1
        limit = NAME_MAX - _TEMPORARY_EXTRA if last else NAME_MAX
        if size > limit:
            shown = part if len(part) <= 40 else part[:20] + "..." + part[-12:]
            what = (f"file name is {size} bytes; at most {limit} (the file system allows {NAME_MAX} per name, "
                    "and the temporaries beside it add up to 28 bytes to the name)" if last else
                    f"a directory name ('{shown}') is {size} bytes; the file system allows at most {NAME_MAX}")
            raise CommandLineError(flag, f"name too long: {what}", os.fspath(path))


def _absolute_or_error(path, flag: str):
    """``path`` made absolute; a one-line error when it is relative and the current directory is gone."""
    try:
        return os.path.abspath(path)
    except FileNotFoundError:
        raise CommandLineError(
            flag, "is a relative path and the current directory no longer exists (it was deleted); "
            "cd to an existing directory or give an absolute path", os.fspath(path)
        ) from None


def check_writable(path, flag: str) -> Path:
    """Refuse an output path that cannot be written, before any simulation work is done.

    The target's directory is probed by creating (and removing) the temporary file the command
    will use, so permissions, read-only file systems and full inode tables are all found now; this
    holds for root too, for whom ``os.access`` says yes to everything. An empty path (an unset
    shell variable), a name too long for the file system and a relative path in a deleted current
    directory are refused here too.
    """
    if os.fspath(path) == "":
        raise CommandLineError(flag, "is empty; give a file path", "")
    _check_name_lengths(path, flag)
    _absolute_or_error(path, flag)
    try:
        return _check_writable(path, flag)
    except OSError as e:  # a path the system refuses to look at (ELOOP, EACCES on a parent, ENAMETOOLONG)
        raise CommandLineError(flag, f"cannot use this path: {e.strerror or e}", os.fspath(path)) from None


def _check_writable(path, flag: str) -> Path:
    p = Path(path)
    if p.is_dir():
        raise CommandLineError(flag, "is a directory; give a file name", str(p))
    target = target_of(p)
    if target.is_dir():
        raise CommandLineError(flag, "links to a directory; give a file name", str(p))
    # The directory the file lands in, spelled as the user gave it unless the path is a symlink.
    parent = target.parent if p.is_symlink() else p.parent
    for up in [parent, *parent.parents]:
        if up.exists():
            if not up.is_dir():
                raise CommandLineError(flag, f"'{up}' is not a directory", str(p))
            break
    if not parent.is_dir():
        raise CommandLineError(flag, f"directory '{parent}' does not exist", str(p))
    # A device or FIFO is streamed into when the content is complete. It is not opened now: opening
    # and closing a FIFO would hand its reader an end of file.
    if is_stream(target) and not os.access(target, os.W_OK):
        raise CommandLineError(flag, "cannot write: permission denied", str(p))
    probe = partial_path(p)
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        return p  # our own leftover from an earlier run of this pid: writable, the writer replaces it
    except OSError as e:
        raise CommandLineError(flag, f"cannot write in '{probe.parent}': {e.strerror}", str(p)) from None
    os.close(fd)
    os.unlink(probe)
    return p


def check_suffix(path, flag: str, suffixes=None) -> None:
    """Refuse an output whose extension is not one of ``suffixes`` (any extension when None)."""
    p = Path(path)
    if suffixes and p.suffix not in suffixes:
        allowed = suffixes[0] if len(suffixes) == 1 else "one of " + ", ".join(suffixes)
        raise CommandLineError(flag, f"unsupported file extension; use {allowed}", str(p))


def _identity(path):
    """What makes two paths the same file: device and inode of an existing file, else the resolved path."""
    try:
        st = os.stat(path)
        return ("inode", st.st_dev, st.st_ino)
    except OSError:
        return ("path", os.fspath(target_of(path)))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Outputs:
    """A command's output files: checked together before any work and locked while the command runs.

    ``add`` each input and output (in the order the command names them), then use the object as a
    context manager around the work: it takes the outputs' locks on entry (refusing at once if
    another process holds one) and releases them on exit.
    """

    def __init__(self):
        self._inputs = []  # (flag, path, identity)
        self._outputs = []  # (flag, path, identity)
        self._locks = []  # (fd, lock path)

    def add_input(self, flag: str, path) -> None:
        """Declare an input file (the scene, a mesh asset) that no output may be; ``flag`` names it in errors."""
        if path is not None and os.path.exists(path):  # False, not an error, for a name the system refuses
            self._inputs.append((flag, Path(path), _identity(path)))

    def add(self, flag: str, path, suffixes=None, streams=False) -> Path | None:
        """Check the output ``path`` of ``flag`` (writable, not an input, not another output, one of
        ``suffixes``); returns it.

        An output that is an input or another output is reported as such, before its extension.
        ``streams``: a device or FIFO (``/dev/stdout``) is taken whatever its name, for an output
        whose format does not follow from its extension (JSON); otherwise it needs one of ``suffixes`` too.
        """
        if path is None:
            return None
        p = check_writable(path, flag)
        if is_stream(p):  # /dev/null twice, or --metrics /dev/stdout with a plot to /dev/stdout: no file to lose
            if not streams and suffixes and p.suffix not in suffixes:
                # The format follows from the extension, which a device or a pipe does not have.
                allowed = "/".join(suffixes)
                what = f"is {_stream_kind(p)}, not a regular file path (unsupported file extension)"
                raise CommandLineError(flag, f"{what}; give a {allowed} file path", str(p))
            return p
        ident = _identity(p)
        for other_flag, other, other_ident in self._inputs:
            if ident == other_ident:
                raise CommandLineError(flag, f"would overwrite the input {other_flag} ('{other}'); choose another file", str(p))
        for other_flag, other, other_ident in self._outputs:
            if ident == other_ident:
                raise CommandLineError(flag, f"is the same file as {other_flag}", str(p))
        check_suffix(p, flag, suffixes)
        self._outputs.append((flag, p, ident))
        return p

    def __enter__(self):
        try:
            for flag, path, _ in self._outputs:
                self._lock(flag, path)
        except BaseException:
            self.release()
            raise
        return self

    def __exit__(self, *exc):
        self.release()
        return False

    def _lock(self, flag, path):
        target = target_of(path)
        lock_path = target.with_name(f".{target.name}.lock")
        while True:
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as e:
                raise CommandLineError(flag, f"cannot create the lock file '{lock_path}': {e.strerror}", str(path)) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise CommandLineError(
                    flag, f"another softsim process (pid {holder}) is writing this file; wait for it or choose another",
                    str(path),
                ) from None
            # The holder before us may have removed the lock file after we opened it: retry on the new one.
            try:
                same = os.stat(lock_path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        try:
            os.ftruncate(fd, 0)
            os.write(fd, str(os.getpid()).encode())
        except OSError as e:  # a full disk or quota: the lock file is ours (locked), so remove it
            discard(lock_path)
            os.close(fd)
            raise CommandLineError(flag, f"cannot write the lock file '{lock_path}': {e.strerror or e}",
                                   str(path)) from None
        self._locks.append((fd, lock_path))
        # We hold the lock: temporaries of this output, and of the <stem>.partial<ext> that a run of it
        # keeps when it may not replace it, from processes that are gone are leftovers.
        for written in (target, kept_partial_path(target)):
            prefix = os.fspath(written.with_name(f".{written.stem}.partial-"))
            for leftover in glob.glob(glob.escape(prefix) + "*"):
                pid = leftover[len(prefix):]
                pid = pid[: len(pid) - len(written.suffix)] if written.suffix else pid
                if pid.isdecimal() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
                    discard(leftover)

    def release(self):
        for fd, lock_path in reversed(self._locks):
            try:
                os.unlink(lock_path)  # while still holding it, so no one locks a file about to vanish
            except OSError:
                pass
            os.close(fd)
        self._locks = []
