"""Output files: checked before a run starts, written atomically (temporary sibling, then rename).

A run's outputs are written to a temporary sibling named ``.<stem>.partial-<pid><suffix>`` and
renamed over the final path when complete (or stopped with its frames kept), so an existing file
is never replaced by an incomplete one, and two processes never share a temporary name.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..core.errors import CommandLineError

USD_SUFFIXES = (".usdc", ".usda", ".usd")


def partial_path(path) -> Path:
    """The temporary sibling of ``path``: hidden, unique per process, same extension (USD picks the format from it)."""
    p = Path(path)
    return p.with_name(f".{p.stem}.partial-{os.getpid()}{p.suffix}")


def check_writable(path, flag: str, suffixes=None) -> Path:
    """Refuse an output path that cannot be written, before any simulation work is done.

    The parent directory is probed by creating (and removing) the temporary file the run will
    use, so permissions, read-only file systems and full inode tables are all found now; this
    holds for root too, for whom ``os.access`` says yes to everything.
    """
    p = Path(path)
    if p.is_dir():
        raise CommandLineError(flag, "is a directory; give a file name", str(p))
    if suffixes and p.suffix not in suffixes:
        raise CommandLineError(flag, f"unsupported file extension; use one of {', '.join(suffixes)}", str(p))
    parent = p.parent
    for up in [parent, *parent.parents]:
        if up.exists():
            if not up.is_dir():
                raise CommandLineError(flag, f"'{up}' is not a directory", str(p))
            break
    if not parent.is_dir():
        raise CommandLineError(flag, f"directory '{parent}' does not exist", str(p))
    probe = partial_path(p)
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        return p  # our own leftover from an earlier run of this pid: writable, the writer replaces it
    except OSError as e:
        raise CommandLineError(flag, f"cannot write in '{parent}': {e.strerror}", str(p)) from None
    os.close(fd)
    os.unlink(probe)
    return p


def check_outputs(out, metrics=None, scene_path=None):
    """Check the USD path and the optional metrics path of a run; returns them as ``Path`` (or None)."""
    out = check_writable(out, "--out", suffixes=USD_SUFFIXES)
    if metrics is None:
        return out, None
    metrics = check_writable(metrics, "--metrics")
    if metrics.resolve() == out.resolve():
        raise CommandLineError("--metrics", "is the same file as --out", str(metrics))
    if scene_path is not None and Path(scene_path).exists() and metrics.resolve() == Path(scene_path).resolve():
        raise CommandLineError("--metrics", "would overwrite the scene file", str(metrics))
    return out, metrics


def write_json_atomic(path, data):
    """Write JSON to a temporary sibling and rename it over ``path``."""
    p = Path(path)
    tmp = partial_path(p)
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, allow_nan=True)
        f.write("\n")
    os.replace(tmp, p)


def save_report(data, out=None, plot_path=None, plot=None):
    """A command's report: JSON to ``out`` (atomically) and ``plot(data, plot_path)``, each when asked."""
    if out:
        write_json_atomic(out, data)
    if plot_path:
        plot(data, plot_path)
